"""Predict the next disparity map from the current one and the rig's motion (PAPER.md eq. 1, loop step 3).

Every pixel of frame ``t-1`` is a 3-D point; the rig's motion ``camera_t_T_camera_{t-1}`` moves it
(the discrete form of eq. 1, ``P' = R P + t``), it is projected into frame ``t`` and splatted there.
The new disparity of a moved point is ``f B / Z'`` with ``Z'`` its *new* depth.

We write the point in inverse-depth form, ``P = ray / rho`` with ``ray = K^-1 (x, y, 1)`` and
``rho = d / (f B)``, so that

    q = R ray + t rho,     x' = project(q),     d' = d / q_z,

which stays finite for points at infinity (``d = 0``: pure rotation moves them).

Forward splatting (:func:`predict_disparity`) has two modes:

* ``"hard"``: a coverage test plus a z-buffer. A moved source pixel covers a target pixel when
  the target pixel's centre, sent back into frame ``t-1`` at the source's new depth, falls in that
  source pixel's square (so surfaces tile the target without cracks or fattening, up to a
  magnification of 2 per frame; a 0.1 px slack closes hairline cracks and a second, single-depth
  check per target keeps that slack from fattening foreground edges). Among the source pixels
  covering a target, the nearest surface (largest ``d'``) wins; sources within
  ``surface_tolerance`` of the winner are averaged with their bilinear weights.
* ``"soft"``: differentiable softmax splatting. Each moved point spreads over the target pixels
  it covers among its four neighbours (the same coverage test, a mask without gradient) with
  bilinear weights ``b`` times ``exp((d' - m) / temperature)`` (``m`` the target's z-buffer value,
  a stabiliser without gradient); the value is the normalised weighted mean, differentiable in
  disparity, motion and intrinsics, and the nearest surface dominates smoothly.

Sub-pixel values (both modes): the splatted value is the moved surface's disparity near, not at,
the target pixel centre. ``refine_iterations`` inverse-warp steps make it exact on smooth
surfaces: the target pixel is sent back into frame ``t-1`` with its current estimate, the source
map is sampled there bilinearly (only among valid neighbours on the same surface), and the
sampled point is moved forward again. On planes this converges to the exact value in one or two
steps (tests/refine/test_predict.py measures it).

Known limit: a discrete map knows a depth edge only to within a pixel, so foreground edges alias by
up to half a pixel per prediction and the error random-walks (and grows with magnification) when
predictions are chained without verification; on the test scenes about 1-2 % of valid pixels are
off by more than 0.5 px after 10 frames, all at depth edges.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from ..core import (
    check_choice,
    check_finite,
    check_float,
    check_positive,
    check_same_device,
    check_shape,
    eps_like,
)
from ..core.errors import ValueRangeError

__all__ = ["Prediction", "predict_disparity", "fill_holes_background", "PredictDisparity"]

# A moved point must keep q_z = Z'/Z above this to count as in front of the new camera: a point
# that came 1000 times closer in one frame step is a degenerate motion, not a scene.
_MIN_DEPTH_RATIO = 1e-3
# Slack (pixels) of the coverage test: sending a target centre back at the *source's* depth, not
# its own, shifts it by (parallax) x (disparity change across one pixel), a few hundredths of a
# pixel on real surfaces; the slack makes neighbouring squares overlap instead of leaving cracks.
_COVER_SLACK = 0.1
# The four bilinear neighbours (x0 + i, y0 + j) of a sub-pixel point.
_CORNERS = ((0, 0), (1, 0), (0, 1), (1, 1))


class Prediction(NamedTuple):
    """Result of :func:`predict_disparity`, every field ``(B, 1, H, W)``.

    Attributes:
        disparity: predicted disparity of frame ``t`` in pixels; real values where something landed,
            hole pixels filled by the background rule (or 0 with ``fill_holes=False``). Never NaN.
        variance: px^2; carried and inflated where something landed, ``hole_variance`` on holes.
        hole: bool, True where no valid source point landed (before filling).
        valid: bool, ``~hole``: True only where real values landed.
        confidence: in ``[0, 1]``; ``1 / (1 + variance)`` where valid, 0 on holes.
    """

    disparity: torch.Tensor
    variance: torch.Tensor
    hole: torch.Tensor
    valid: torch.Tensor
    confidence: torch.Tensor


def _rotate(R: torch.Tensor, vx: torch.Tensor, vy: torch.Tensor, vz: torch.Tensor | float):
    """``R @ (vx, vy, vz)`` for ``R`` ``(B, 3, 3)`` and components of any shape ``(B, ...)``."""
    shape = (R.shape[0],) + (1,) * (vx.dim() - 1)
    r = [[R[:, i, j].reshape(shape) for j in range(3)] for i in range(3)]
    return tuple(r[i][0] * vx + r[i][1] * vy + r[i][2] * vz for i in range(3))


def _bilinear_gather(
    values: list[torch.Tensor], ok: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor
) -> list[tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]]:
    """The four neighbours of sub-pixel points ``(xs, ys)`` ``(B, H, W)`` in maps ``(B, H, W)``.

    Returns, per neighbour (``_CORNERS`` order), the gathered ``values``, their ``ok`` mask (out-of-image
    neighbours are not ok) and the bilinear weight, each ``(B, H, W)``.
    """
    B, H, W = ok.shape
    x0 = torch.floor(xs.detach().clamp(-2, W + 1))
    y0 = torch.floor(ys.detach().clamp(-2, H + 1))
    fu, fv = xs - x0, ys - y0
    wx, wy = (1 - fu, fu), (1 - fv, fv)
    in_x = ((x0 >= 0) & (x0 <= W - 1), (x0 >= -1) & (x0 <= W - 2))
    in_y = ((y0 >= 0) & (y0 <= H - 1), (y0 >= -1) & (y0 <= H - 2))
    base = (y0 * W + x0).long()
    flat = [v.reshape(B, -1) for v in values]
    ok_flat = ok.reshape(B, -1)
    out = []
    for i, j in _CORNERS:
        inside = in_x[i] & in_y[j]
        idx = torch.where(inside, base + (j * W + i), 0).view(B, -1)
        gathered = [v.gather(1, idx).view(B, H, W) for v in flat]
        out.append((gathered, ok_flat.gather(1, idx).view(B, H, W) & inside, wx[i] * wy[j]))
    return out


def fill_holes_background(disparity: torch.Tensor, hole: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Fill holes with the background: the smaller of the nearest non-hole values left and right in the row.

    The rule (documented here once, used by :func:`predict_disparity`): a hole pixel takes the
    smallest disparity (the farthest surface) among the nearest non-hole pixel to its left and the
    nearest non-hole pixel to its right in the same row; where only one side has one, that side's;
    where the row has none, the smallest non-hole disparity of the whole image; where the image has
    none, 0. Disocclusions open behind foreground edges and regions entering the view are mostly
    background, so the farther neighbour is the better guess.

    Args:
        disparity: ``(B, 1, H, W)``; only non-hole values are read.
        hole: ``(B, 1, H, W)`` bool.

    Returns:
        ``(filled, empty)``: the filled map ``(B, 1, H, W)`` (non-hole pixels unchanged) and a bool
        ``(B,)`` marking images with no non-hole pixel at all (filled with 0).

    >>> d = torch.tensor([[[[5.0, 0.0, 0.0, 2.0, 0.0]]]])
    >>> filled, empty = fill_holes_background(d, d == 0)
    >>> filled
    tensor([[[[5., 2., 2., 2., 2.]]]])
    """
    dims = check_shape(disparity, ["B", "1", "H", "W"], "disparity")
    check_shape(hole, ["B", "1", "H", "W"], "hole", dims)
    B, _, H, W = disparity.shape
    have = ~hole[:, 0]
    d = disparity[:, 0]
    cols = torch.arange(W, device=d.device).expand(B, H, W)
    left = torch.where(have, cols, torch.full_like(cols, -1)).cummax(dim=-1).values
    right = torch.where(have, cols, torch.full_like(cols, W)).flip(-1).cummin(dim=-1).values.flip(-1)
    d_left = d.gather(-1, left.clamp(0, W - 1))
    d_right = d.gather(-1, right.clamp(0, W - 1))
    left_ok, right_ok = left >= 0, right < W
    big = torch.full_like(d, torch.finfo(d.dtype).max)
    row_fill = torch.minimum(torch.where(left_ok, d_left, big), torch.where(right_ok, d_right, big))
    image_min = torch.where(have, d, big).flatten(1).amin(dim=1)  # (B,)
    empty = ~have.flatten(1).any(dim=1)
    image_fill = torch.where(empty, torch.zeros_like(image_min), image_min).view(B, 1, 1).expand(B, H, W)
    fill = torch.where(left_ok | right_ok, row_fill, image_fill)
    return torch.where(have, d, fill)[:, None], empty


def predict_disparity(
    disparity: torch.Tensor,
    motion: torch.Tensor,
    K: torch.Tensor,
    baseline: torch.Tensor,
    variance: torch.Tensor | None = None,
    valid: torch.Tensor | None = None,
    mode: str = "hard",
    process_noise: float = 0.01,
    hole_variance: float = 100.0,
    fill_holes: bool = True,
    temperature: float = 0.1,
    refine_iterations: int = 2,
    surface_tolerance: float = 0.5,
) -> Prediction:
    """Predict frame ``t``'s disparity by moving every 3-D point of frame ``t-1`` (PAPER.md eq. 1).

    Each valid source pixel is lifted to 3-D with its disparity, moved by ``motion`` (the exact
    rigid form of eq. 1), projected into frame ``t`` and splatted (module docstring: the coverage
    test, z-buffer, softmax splatting and inverse-warp refinement). Its new disparity is
    ``f B / Z'``, ``Z'`` its new depth.

    What the caller receives:

    * where a valid point landed: ``disparity`` = the moved surface's disparity at the pixel
      (sub-pixel), ``variance = variance_src * (d'/d)^2 + process_noise`` (first-order propagation
      of disparity through the depth change, plus process noise), ``hole = False``,
      ``valid = True``, ``confidence = 1 / (1 + variance)``;
    * elsewhere (disocclusions, regions entering the view, invalid sources): ``hole = True``,
      ``valid = False``, ``variance = hole_variance``, ``confidence = 0`` and ``disparity`` filled
      by :func:`fill_holes_background` (the background-most of the nearest real values left and
      right in the row) when ``fill_holes``, else 0. Holes are therefore never silent.

    Args:
        disparity: ``(B, 1, H, W)`` disparity of frame ``t-1`` in pixels (negative = invalid).
        motion: ``(B, 4, 4)`` ``camera_t_T_camera_{t-1}``.
        K: ``(B, 3, 3)`` intrinsics in pixels.
        baseline: ``(B,)`` metres, > 0.
        variance: ``(B, 1, H, W)`` px^2 of ``disparity``; None means 0.
        valid: ``(B, 1, H, W)`` bool; invalid source pixels are not splatted. None means all.
        mode: ``"hard"`` (z-buffer) or ``"soft"`` (softmax splatting).
        process_noise: px^2 added to the carried variance per prediction.
        hole_variance: px^2 given to hole pixels.
        fill_holes: fill holes by the background rule (else 0 there).
        temperature: px, softness of the softmax splatting (``"soft"`` only); smaller is harder.
        refine_iterations: inverse-warp refinement steps (0 keeps the splatted values).
        surface_tolerance: px; source disparities within this of the nearest one count as the same
            surface (z-buffer ties, refinement neighbours).

    Returns:
        :class:`Prediction` ``(disparity, variance, hole, valid, confidence)``, each ``(B, 1, H, W)``.

    Shape:
        - disparity, variance, valid: ``(B, 1, H, W)``; motion ``(B, 4, 4)``; K ``(B, 3, 3)``; baseline ``(B,)``.

    >>> from egorefine.geometry import make_intrinsics
    >>> d = torch.full((1, 1, 6, 8), 4.0)
    >>> pred = predict_disparity(d, torch.eye(4)[None], make_intrinsics(10.0, 4.0, 3.0), torch.tensor([1.0]))
    >>> pred.disparity.shape, bool(pred.valid.all()), bool((pred.disparity == 4.0).all())
    (torch.Size([1, 1, 6, 8]), True, True)
    """
    dims = check_shape(disparity, ["B", "1", "H", "W"], "disparity")
    check_float(disparity, "disparity")
    check_finite(disparity, "disparity")
    check_shape(motion, ["B", "4", "4"], "motion", dims)
    check_shape(K, ["B", "3", "3"], "K", dims)
    check_shape(baseline, ["B"], "baseline", dims)
    check_positive(baseline, "baseline")
    check_finite(motion, "motion")
    check_positive(K[:, 0, 0], "K focal")
    check_choice(mode, ["hard", "soft"], "mode")
    if variance is not None:
        check_shape(variance, ["B", "1", "H", "W"], "variance", dims)
        check_float(variance, "variance")
    if valid is not None:
        check_shape(valid, ["B", "1", "H", "W"], "valid", dims)
        if valid.dtype != torch.bool:
            valid = valid > 0.5
    check_same_device(disparity, "disparity", motion=motion, K=K, baseline=baseline, variance=variance, valid=valid)
    if temperature <= 0 or process_noise < 0 or hole_variance <= 0 or surface_tolerance <= 0:
        raise ValueRangeError(
            "temperature, hole_variance and surface_tolerance must be > 0 and process_noise >= 0, got "
            f"{temperature}, {hole_variance}, {surface_tolerance}, {process_noise}"
        )
    if refine_iterations < 0:
        raise ValueRangeError(f"refine_iterations: must be >= 0, got {refine_iterations}")

    B, _, H, W = disparity.shape
    dtype, device = disparity.dtype, disparity.device
    motion, K, baseline = motion.to(dtype), K.to(dtype), baseline.to(dtype)
    d = disparity[:, 0]
    var = torch.zeros_like(d) if variance is None else variance[:, 0].to(dtype)
    src_ok = d >= 0
    if valid is not None:
        src_ok = src_ok & valid[:, 0]

    fx, fy = K[:, 0, 0].view(B, 1, 1), K[:, 1, 1].view(B, 1, 1)
    cx, cy = K[:, 0, 2].view(B, 1, 1), K[:, 1, 2].view(B, 1, 1)
    fb = fx * baseline.view(B, 1, 1)
    R, tr = motion[:, :3, :3], motion[:, :3, 3]
    Rt, tr_back = R.transpose(1, 2), -(R.transpose(1, 2) @ tr[..., None])[..., 0]  # camera_{t-1}_T_camera_t
    ys, xs = torch.meshgrid(
        torch.arange(H, device=device, dtype=dtype), torch.arange(W, device=device, dtype=dtype), indexing="ij"
    )
    xs, ys = xs.expand(B, H, W), ys.expand(B, H, W)
    rx, ry = (xs - cx) / fx, (ys - cy) / fy
    one = 1.0  # third component of every normalised ray

    # ---- move every source point (eq. 1) and project it into frame t
    rho = d / fb
    qx, qy, qz = _rotate(R, rx, ry, one)
    qx = qx + tr[:, 0].view(B, 1, 1) * rho
    qy = qy + tr[:, 1].view(B, 1, 1) * rho
    qz = qz + tr[:, 2].view(B, 1, 1) * rho
    front = qz > _MIN_DEPTH_RATIO
    qz_safe = qz.clamp_min(_MIN_DEPTH_RATIO)  # clamp before dividing: points behind the camera are masked out
    u = fx * qx / qz_safe + cx
    v = fy * qy / qz_safe + cy
    d_new = d / qz_safe  # f B / Z' with Z' = Z q_z
    var_new = var / qz_safe**2  # first-order propagation: d' = d / q_z
    src_ok = src_ok & front & torch.isfinite(u) & torch.isfinite(v)
    u = torch.where(src_ok, u, -10.0)
    v = torch.where(src_ok, v, -10.0)

    # ---- footprint: the four target pixels (x0 + i, y0 + j) around each moved point, bilinear weights.
    # Kept as four (B, H, W) maps, one per corner (_CORNERS), scattered one after the other.
    x0 = torch.floor(u.detach().clamp(-2, W + 1))
    y0 = torch.floor(v.detach().clamp(-2, H + 1))
    fu, fv = u - x0, v - y0
    wx, wy = (1 - fu, fu), (1 - fv, fv)
    in_x = ((x0 >= 0) & (x0 <= W - 1), (x0 >= -1) & (x0 <= W - 2))
    in_y = ((y0 >= 0) & (y0 <= H - 1), (y0 >= -1) & (y0 <= H - 2))
    base = (y0 * W + x0).long() + (torch.arange(B, device=device) * (H * W)).view(B, 1, 1)
    n_flat = B * H * W

    with torch.no_grad():
        # Coverage test: send the target centre back into frame t-1 at the moved point's depth and check
        # that it falls in the source pixel's square (an exact tiling of the source grid). The back-projected
        # direction is affine in the target pixel, so the four corners are the (x0, y0) one plus constants.
        rho_n = d_new / fb
        h0 = _rotate(Rt, (x0 - cx) / fx, (y0 - cy) / fy, one)
        h0 = [h0[k] + tr_back[:, k].view(B, 1, 1) * rho_n for k in range(3)]
        step_x = (Rt[:, :, 0] / fx.view(B, 1)).view(B, 3, 1, 1)
        step_y = (Rt[:, :, 1] / fy.view(B, 1)).view(B, 3, 1, 1)
        z_slack = torch.full((n_flat,), -torch.inf, device=device, dtype=dtype)
        z_strict = z_slack.clone()
        tgts, covers = [], []
        for i, j in _CORNERS:
            pair_ok = src_ok & in_x[i] & in_y[j]
            tgt = torch.where(pair_ok, base + (j * W + i), 0).view(-1)
            hx, hy, hz = (h0[k] + i * step_x[:, k] + j * step_y[:, k] for k in range(3))
            hz_safe = hz.clamp_min(_MIN_DEPTH_RATIO)
            off = torch.maximum((fx * hx / hz_safe + cx - xs).abs(), (fy * hy / hz_safe + cy - ys).abs())
            covered = pair_ok & (hz > _MIN_DEPTH_RATIO) & (off <= 0.5 + _COVER_SLACK)
            strict = covered & (off <= 0.5)
            z_slack.scatter_reduce_(0, tgt, d_new.masked_fill(~covered, -torch.inf).view(-1), "amax")
            z_strict.scatter_reduce_(0, tgt, d_new.masked_fill(~strict, -torch.inf).view(-1), "amax")
            tgts.append(tgt)
            covers.append(covered)
        # Each pair above is tested at its own source's depth, so neighbouring squares of one surface may
        # leave hairline cracks (closed by the slack) and the slack may fatten a foreground edge. Decide
        # per target with ONE depth, the nearest candidate's: send the target back at that depth; the
        # source pixel it falls in (an exact tiling) must belong to that surface. If not, the candidate
        # only reached the target through the slack (fattening): take the nearest strict cover instead.
        zs = torch.where(torch.isfinite(z_slack), z_slack, 0.0).view(B, H, W)
        g0 = _rotate(Rt, rx, ry, one)  # target rays turned into frame t-1 (reused by the refinement)
        rho_c = zs / fb
        gx, gy, gz = (g0[k] + tr_back[:, k].view(B, 1, 1) * rho_c for k in range(3))
        gz_safe = gz.clamp_min(_MIN_DEPTH_RATIO)
        sx = torch.round((fx * gx / gz_safe + cx).clamp(-1, W)).long()
        sy = torch.round((fy * gy / gz_safe + cy).clamp(-1, H)).long()
        s_in = (sx >= 0) & (sx < W) & (sy >= 0) & (sy < H) & (gz > _MIN_DEPTH_RATIO)
        s_idx = (sy.clamp(0, H - 1) * W + sx.clamp(0, W - 1)).view(B, -1)
        s_ok = src_ok.reshape(B, -1).gather(1, s_idx).view(B, H, W) & s_in
        s_d = d_new.reshape(B, -1).gather(1, s_idx).view(B, H, W)
        consistent = (s_ok & ((s_d - zs).abs() < surface_tolerance)).view(-1)
        zbuf = torch.where(consistent | ~torch.isfinite(z_strict), z_slack, z_strict)
        landed = torch.isfinite(zbuf).view(B, H, W)
        zbuf = torch.where(landed.view(-1), zbuf, 0.0)

    d_det = d_new.detach()
    wsum = torch.zeros(n_flat, device=device, dtype=dtype)
    num, num_var = wsum, wsum
    for (i, j), tgt, covered in zip(_CORNERS, tgts, covers, strict=True):
        z_at = zbuf.index_select(0, tgt).view(B, H, W)
        bw = wx[i] * wy[j] + eps_like(d_new)
        if mode == "hard":
            # z-buffer (nearest surface wins); ties within surface_tolerance averaged with bilinear weights
            w = torch.where(covered & ((d_det - z_at).abs() <= surface_tolerance), bw, 0.0)
        else:
            # softmax splatting: weights b * exp((d' - m) / T), m = the per-target z-buffer value (no
            # gradient, for stability); candidates the z-buffer rejected above as fattening are left out.
            sel = covered & (d_det <= z_at + surface_tolerance)
            logit = torch.where(sel, (d_new - z_at) / temperature, -60.0).clamp_min(-60.0)
            w = torch.where(sel, bw * torch.exp(logit), 0.0)
        wsum = wsum.scatter_add(0, tgt, w.view(-1))
        num = num.scatter_add(0, tgt, (w * d_new).view(-1))
        if variance is not None:
            num_var = num_var.scatter_add(0, tgt, (w * var_new).view(-1))
    wsum_safe = wsum.clamp_min(eps_like(wsum)).view(B, H, W)  # clamp: empty targets (holes) get 0, not NaN
    est = num.view(B, H, W) / wsum_safe
    est_var = torch.zeros_like(est) if variance is None else num_var.view(B, H, W) / wsum_safe

    # ---- inverse-warp refinement: exact sub-pixel values on smooth surfaces
    src_maps = [d] if variance is None else [d, var]
    for _ in range(refine_iterations):
        rho = est / fb
        hx, hy, hz = (g0[k] + tr_back[:, k].view(B, 1, 1) * rho for k in range(3))
        hz_ok = hz > _MIN_DEPTH_RATIO
        hz_safe = hz.clamp_min(_MIN_DEPTH_RATIO)
        sxf = fx * hx / hz_safe + cx
        syf = fy * hy / hz_safe + cy
        expect = est / hz_safe  # the source disparity this target value came from
        wk_sum, d_num, v_num = 0.0, 0.0, 0.0
        for gathered, ok_k, wk in _bilinear_gather(src_maps, src_ok, sxf, syf):
            wk = torch.where(ok_k & ((gathered[0] - expect).abs() < surface_tolerance), wk, 0.0)
            wk_sum = wk_sum + wk
            d_num = d_num + wk * gathered[0]
            if variance is not None:
                v_num = v_num + wk * gathered[1]
        ok_ref = landed & hz_ok & (wk_sum > 1e-3)
        wk_sum = wk_sum.clamp_min(1e-3)
        d_src = d_num / wk_sum
        # move the sampled point forward again (eq. 1); only its new depth ratio q_z is needed
        qz2 = R[:, 2, 0].view(B, 1, 1) * (sxf - cx) / fx + R[:, 2, 1].view(B, 1, 1) * (syf - cy) / fy
        qz2 = qz2 + R[:, 2, 2].view(B, 1, 1) + tr[:, 2].view(B, 1, 1) * d_src / fb
        ok_ref = ok_ref & (qz2 > _MIN_DEPTH_RATIO)
        qz2 = qz2.clamp_min(_MIN_DEPTH_RATIO)
        est = torch.where(ok_ref, d_src / qz2, est)
        if variance is not None:
            v_src = v_num / wk_sum
            est_var = torch.where(ok_ref, v_src / qz2**2, est_var)

    hole = ~landed
    est = torch.where(landed, est, 0.0)[:, None]
    hole4 = hole[:, None]
    if fill_holes:
        est, _ = fill_holes_background(est, hole4)
    out_var = torch.where(landed, est_var + process_noise, hole_variance)[:, None]
    confidence = torch.where(hole4, 0.0, 1.0 / (1.0 + out_var))
    return Prediction(est, out_var, hole4, ~hole4, confidence)


class PredictDisparity(nn.Module):
    """Module form of :func:`predict_disparity`: stores the settings, ``forward`` calls the function.

    >>> from egorefine.geometry import make_intrinsics
    >>> pred = PredictDisparity()(torch.full((1, 1, 4, 5), 2.0), torch.eye(4)[None],
    ...                           make_intrinsics(10.0, 2.0, 1.5), torch.tensor([0.1]))
    >>> pred.disparity.shape
    torch.Size([1, 1, 4, 5])
    """

    def __init__(
        self,
        mode: str = "hard",
        process_noise: float = 0.01,
        hole_variance: float = 100.0,
        fill_holes: bool = True,
        temperature: float = 0.1,
        refine_iterations: int = 2,
        surface_tolerance: float = 0.5,
    ) -> None:
        super().__init__()
        check_choice(mode, ["hard", "soft"], "mode")
        self.mode = mode
        self.process_noise = process_noise
        self.hole_variance = hole_variance
        self.fill_holes = fill_holes
        self.temperature = temperature
        self.refine_iterations = refine_iterations
        self.surface_tolerance = surface_tolerance

    def forward(
        self,
        disparity: torch.Tensor,
        motion: torch.Tensor,
        K: torch.Tensor,
        baseline: torch.Tensor,
        variance: torch.Tensor | None = None,
        valid: torch.Tensor | None = None,
    ) -> Prediction:
        return predict_disparity(
            disparity,
            motion,
            K,
            baseline,
            variance=variance,
            valid=valid,
            mode=self.mode,
            process_noise=self.process_noise,
            hole_variance=self.hole_variance,
            fill_holes=self.fill_holes,
            temperature=self.temperature,
            refine_iterations=self.refine_iterations,
            surface_tolerance=self.surface_tolerance,
        )
