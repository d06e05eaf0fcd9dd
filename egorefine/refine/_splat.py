"""The splat's steps for :func:`egorefine.refine.predict_disparity` (docs/method.md eq. 1 in pixel-homogeneous form).

Private: the pixel-homogeneous motion of a frame step, the padded flat layout that the scatters and gathers share,
the hard splat's start (coverage test, z-buffer, check) and its inverse-warp refinement, and the coverage splat of
both modes. :mod:`egorefine.refine.predict` holds what they mean (its module docstring) and the public API;
:mod:`egorefine.refine._splat_numba` repeats the hard steps compiled.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.nn import functional as F

from ..core import eps_like, use_compiled

# A moved point must keep q_z = Z'/Z above this to count as in front of the new camera: a point
# that came 1000 times closer in one frame step is a degenerate motion, not a scene.
_MIN_DEPTH_RATIO = 1e-3
# Slack (pixels) of the coverage test: sending a target centre back at the *source's* depth, not
# its own, shifts it by (parallax) x (disparity change across one pixel), a few hundredths of a
# pixel on real surfaces; the slack makes neighbouring squares overlap instead of leaving cracks.
_COVER_SLACK = 0.1
# The four bilinear neighbours (x0 + i, y0 + j) of a sub-pixel point.
_CORNERS = ((0, 0), (1, 0), (0, 1), (1, 1))
# Margin (pixels) of the padded flat layout of target and source maps (see _Padded).
_PAD = 2



def _big(dtype: torch.dtype) -> float:
    """A finite 'minus infinity' for keys and sentinels: far beyond any disparity, its square still finite."""
    return min(1e30, torch.finfo(dtype).max ** 0.5)


def _pixel_motion(motion: torch.Tensor, K: torch.Tensor, baseline: torch.Tensor):
    """The motion in pixel-homogeneous form (eq. 1 with inverse depth ``d / (f B)``).

    A source pixel ``(x, y)`` with disparity ``d`` moves to ``P = A (x, y, 1) + a d`` (``P_z = Z'/Z``); a
    target pixel ``T`` sent back at disparity ``d'`` lands at ``G (T, 1) + e d'`` in frame ``t-1``.
    Returns ``A, a, G, e`` with ``A, G`` ``(B, 3, 3)`` and ``a, e`` ``(B, 3)``. On the compiled CPU path
    (:func:`~egorefine.core.use_compiled`) the same products are taken with numpy, far cheaper than twenty torch
    operations on 3 x 3 matrices.
    """
    if use_compiled(motion, K, baseline):
        return tuple(torch.from_numpy(np.ascontiguousarray(m)) for m in _pixel_motion_numpy(
            motion.detach().numpy(), K.detach().numpy(), baseline.detach().numpy()))
    B = K.shape[0]
    fx, fy, cx, cy = K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]
    zero, one = torch.zeros_like(fx), torch.ones_like(fx)
    Kp = torch.stack([fx, zero, cx, zero, fy, cy, zero, zero, one], -1).view(B, 3, 3)
    Kinv = torch.stack([1 / fx, zero, -cx / fx, zero, 1 / fy, -cy / fy, zero, zero, one], -1).view(B, 3, 3)
    R, t = motion[:, :3, :3], motion[:, :3, 3:]
    fb = (fx * baseline).view(B, 1, 1)
    Rt = R.transpose(1, 2)
    A, a = Kp @ R @ Kinv, (Kp @ t / fb)[..., 0]
    G, e = Kp @ Rt @ Kinv, (Kp @ (-(Rt @ t)) / fb)[..., 0]
    return A, a, G, e


def _pixel_motion_numpy(motion: np.ndarray, K: np.ndarray, baseline: np.ndarray) -> tuple[np.ndarray, ...]:
    """:func:`_pixel_motion`'s products on numpy arrays, in their dtype."""
    B = K.shape[0]
    fx, fy, cx, cy = K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]
    Kp = np.zeros((B, 3, 3), K.dtype)
    Kinv = np.zeros((B, 3, 3), K.dtype)
    Kp[:, 0, 0], Kp[:, 0, 2], Kp[:, 1, 1], Kp[:, 1, 2], Kp[:, 2, 2] = fx, cx, fy, cy, 1
    Kinv[:, 0, 0], Kinv[:, 0, 2], Kinv[:, 1, 1], Kinv[:, 1, 2], Kinv[:, 2, 2] = 1 / fx, -cx / fx, 1 / fy, -cy / fy, 1
    R, t = motion[:, :3, :3], motion[:, :3, 3:]
    fb = (fx * baseline).reshape(B, 1, 1)
    Rt = R.transpose(0, 2, 1)
    return Kp @ R @ Kinv, (Kp @ t / fb)[..., 0], Kp @ Rt @ Kinv, (Kp @ (-(Rt @ t)) / fb)[..., 0]


def _affine_map(M: torch.Tensor, k: int, xs: torch.Tensor, ys: torch.Tensor) -> torch.Tensor:
    """Row ``k`` of ``M (x, y, 1)`` over the pixel grid, ``(B, H, W)`` (xs ``(1, 1, W)``, ys ``(1, H, 1)``)."""
    B = M.shape[0]
    return (M[:, k, 0].view(B, 1, 1) * xs + M[:, k, 2].view(B, 1, 1)) + M[:, k, 1].view(B, 1, 1) * ys


def _back_project(back: list[torch.Tensor], e: torch.Tensor, disp: torch.Tensor, inplace: bool = False):
    """Target pixels sent back into frame ``t-1`` at disparity ``disp`` ``(B, H, W)``.

    Returns ``(sx, sy, 1 / h_z, h_z > min)``: the source-frame pixel position, the depth ratio's inverse
    (clamped first, so never a division by ~0) and where the point is in front of the old camera.
    """
    B = disp.shape[0]
    hx, hy, hz = (torch.addcmul(back[k], disp, e[:, k].view(B, 1, 1)) for k in range(3))
    front = hz > _MIN_DEPTH_RATIO
    if inplace:  # no gradient: reuse the buffers
        inv = hz.clamp_min_(_MIN_DEPTH_RATIO).reciprocal_()
        return hx.mul_(inv), hy.mul_(inv), inv, front
    inv = hz.clamp_min(_MIN_DEPTH_RATIO).reciprocal()
    return hx * inv, hy * inv, inv, front


class _Padded:
    """Flat ``(B * Hp * Wp,)`` layout of ``(B, H, W)`` maps with ``_PAD`` cells of margin before and
    ``_PAD + 1`` after, so that every bilinear corner of a point clamped to ``[-_PAD, W + 1]`` has a cell."""

    def __init__(self, B: int, H: int, W: int, device: torch.device) -> None:
        self.B, self.H, self.W = B, H, W
        self.Hp, self.Wp = H + 2 * _PAD + 1, W + 2 * _PAD + 1
        self.size = B * self.Hp * self.Wp
        self.offset = (torch.arange(B, device=device) * (self.Hp * self.Wp) + _PAD * (self.Wp + 1)).view(B, 1, 1)

    def index(self, x: torch.Tensor, y: torch.Tensor, dtype: torch.dtype = torch.int64) -> torch.Tensor:
        """Flat indices of integer-valued float pixel coordinates ``x, y`` ``(B, H, W)`` in ``[-_PAD, W + _PAD]``."""
        flat = torch.add(x, y, alpha=self.Wp)
        if self.size < 2 / torch.finfo(flat.dtype).eps:  # integers exact in this float type: one conversion
            return flat.add_(self.offset.to(flat.dtype)).to(dtype).view(-1)
        return (flat.to(dtype) + self.offset.to(dtype)).view(-1)

    def full(self, value: float, like: torch.Tensor) -> torch.Tensor:
        return torch.full((self.size,), value, device=like.device, dtype=like.dtype)

    def crop(self, flat: torch.Tensor) -> torch.Tensor:
        return flat.view(self.B, self.Hp, self.Wp)[:, _PAD : _PAD + self.H, _PAD : _PAD + self.W]

    def pad(self, x: torch.Tensor, fill: float | None) -> torch.Tensor:
        """``x`` ``(B, H, W)`` in the layout, margins set to ``fill`` (None: the nearest border pixel's value)."""
        if fill is None:
            return F.pad(x, (_PAD, _PAD + 1, _PAD, _PAD + 1), mode="replicate").view(-1)
        return F.pad(x, (_PAD, _PAD + 1, _PAD, _PAD + 1), value=fill).view(-1)




def _per_batch(x: torch.Tensor) -> torch.Tensor:
    return x.reshape(x.shape[0], 1, 1)


def _hard_start(
    d: torch.Tensor,
    var: torch.Tensor | None,
    src_ok: torch.Tensor,
    A: torch.Tensor,
    a: torch.Tensor,
    e: torch.Tensor,
    back: list[torch.Tensor],
    layout: _Padded,
    xs: torch.Tensor,
    ys: torch.Tensor,
    surface_tolerance: float,
    fast: bool,
):
    """Hard mode with refinement, part 1: the surface each target pixel sees and a start value on it.

    Every moved source point goes to its nearest target pixel (one ``amax`` scatter of integer keys: the
    bits of ``d'`` as float32, which order like the values for ``d' >= 0``). A target's candidate is the
    nearest surface within one pixel (the 3x3 maximum, which closes the cracks of a magnification up to
    2), or what landed on the pixel itself where that is on the same surface (closer to the target's own
    value on a slanted surface). The target, sent back into frame ``t-1`` at the candidate's depth, falls
    in a source pixel; the candidate is accepted when that pixel's disparity is within
    ``surface_tolerance`` of the one the candidate implies there (the surface really reaches the target:
    no foreground fattening). That pixel's ``d'`` and variance are the start. Where the candidate is
    rejected the same start is a fallback (the background seen behind a fattened foreground edge, or a
    steep surface's own value), accepted by the first refinement step (:func:`_hard_refine`).

    Returns ``(est, est_var, landed, fallback, src_ok, key_src)``: maps ``(B, H, W)`` (``est_var`` None without
    variance) and the padded source disparity (-big where invalid).
    """
    B, H, W = d.shape
    dtype = d.dtype
    big = _big(dtype)
    with torch.no_grad():
        dd = d.detach()
        Pz = _affine_map(A, 2, xs, ys).addcmul_(dd, _per_batch(a[:, 2]))
        src_ok = src_ok & (Pz > _MIN_DEPTH_RATIO)
        inv = Pz.clamp_min_(_MIN_DEPTH_RATIO).reciprocal_()  # 1 / q_z, clamped first
        d_new = dd * inv  # f B / Z' with Z' = Z q_z
        not_ok = ~src_ok
        # z-buffer keys; -1 for invalid sources (the maximum ignores them, an empty target keeps -1)
        key = d_new.to(torch.float32).view(torch.int32).masked_fill(not_ok, -1)
        tx = _affine_map(A, 0, xs, ys).addcmul_(dd, _per_batch(a[:, 0])).mul_(inv).round_().clamp_(-_PAD, W + 1)
        ty = _affine_map(A, 1, xs, ys).addcmul_(dd, _per_batch(a[:, 1])).mul_(inv).round_().clamp_(-_PAD, H + 1)
        zbuf = torch.full((layout.size,), -1, dtype=torch.int32, device=d.device)
        zbuf.scatter_reduce_(0, layout.index(tx, ty), key.view(-1), "amax")
        del tx, ty, key
        Z = zbuf.view(B, layout.Hp, layout.Wp)[:, _PAD - 1 : _PAD + H + 1, _PAD - 1 : _PAD + W + 1]
        rows = torch.maximum(torch.maximum(Z[..., :-2], Z[..., 1:-1]), Z[..., 2:])
        near = torch.maximum(torch.maximum(rows[:, :-2], rows[:, 1:-1]), rows[:, 2:])  # nearest within 1 px
        del rows
        near_v = near.clamp_min(0).view(torch.float32).to(dtype)
        own_v = Z[:, 1:-1, 1:-1].clamp_min(0).view(torch.float32).to(dtype)  # what landed on the pixel itself
        del zbuf, Z
        cand = torch.lerp(near_v, own_v, (near_v - own_v).lt_(surface_tolerance))  # (near_v >= own_v)
        key_new = layout.pad(d_new.masked_fill_(not_ok, -big), -big)  # d' of valid sources, -big elsewhere
        key_src = layout.pad(dd.masked_fill(not_ok, -big), -big)  # the same in frame t-1 (d)
        # the check: send the targets back at the candidate; compare in frame t-1, like the refinement
        sx, sy, inv_h, front = _back_project(back, e, cand, True)
        picked = layout.index(sx.clamp_(-1, W).round_(), sy.clamp_(-1, H).round_(), torch.int32)
        found = key_src.index_select(0, picked).view(B, H, W)
        has_near = near >= 0
        landed = (found.sub_(inv_h.mul_(cand)).abs_() < surface_tolerance) & front & has_near
        del sx, sy, inv_h, front, found, cand
        est = key_new.index_select(0, picked).view(B, H, W)
        fallback = (est >= 0) & has_near & ~landed
    if fast:
        est = est.clamp_min_(0.0)
    else:
        inv = (_affine_map(A, 2, xs, ys) + d * _per_batch(a[:, 2])).clamp_min(_MIN_DEPTH_RATIO).reciprocal()
        est = layout.pad(d * inv, 0.0).index_select(0, picked).view(B, H, W)
    est_var = None
    if var is not None:
        # first-order propagation d' = d / q_z; replicated margins (a target just outside takes the border's)
        est_var = layout.pad(var * inv * inv, None).index_select(0, picked).view(B, H, W)
    return est, est_var, landed, fallback, src_ok, key_src


def _hard_refine(
    est: torch.Tensor,
    landed: torch.Tensor,
    fallback: torch.Tensor,
    d: torch.Tensor,
    key_src: torch.Tensor,
    A: torch.Tensor,
    a: torch.Tensor,
    e: torch.Tensor,
    back: list[torch.Tensor],
    layout: _Padded,
    refine_iterations: int,
    surface_tolerance: float,
    fast: bool,
):
    """Hard mode with refinement, part 2: inverse-warp steps (module docstring) from the start of :func:`_hard_start`.

    Each step sends the target back at its estimate, samples the source bilinearly where the four neighbours
    are on the estimate's surface (within ``surface_tolerance``, in frame t-1; the others count with the
    estimate's own value, so the fixed point is the same as for renormalised weights) and moves the sample
    forward again. The first step also checks every target once more: it stays landed (``fallback`` targets
    become landed) where its nearest neighbour is on its start's surface and the step moves it by at most
    ``surface_tolerance`` (else the inverse warp does not settle there: magnification well beyond 2).

    Returns ``(est, landed)``.
    """
    B, H, W = d.shape
    dtype = d.dtype
    shifts = [j * layout.Wp + i for i, j in _CORNERS]
    idx_dtype = torch.int32 if layout.size < 2**31 else torch.int64
    d_src_pad = key_src if fast else layout.pad(d, 0.0)
    a_z = _per_batch(a[:, 2])
    A20, A21, A22 = (_per_batch(A[:, 2, k]) for k in range(3))
    for step in range(refine_iterations):
        sx, sy, inv_h, hz_ok = _back_project(back, e, est, fast)
        expect = est * inv_h  # the source disparity this target value came from
        qz = torch.addcmul(torch.addcmul(A22, sx, A20), sy, A21)  # q_z of the sampled point, without its disparity
        with torch.no_grad():
            x0 = sx.detach().clamp(-_PAD, W + 1).floor_()
            y0 = sy.detach().clamp(-_PAD, H + 1).floor_()
            idx00 = layout.index(x0, y0, idx_dtype)
        fx, fy = (sx.sub_(x0), sy.sub_(y0)) if fast else (sx - x0, sy - y0)
        vals, flags = [], []
        for c in shifts:
            g = d_src_pad[c:].index_select(0, idx00).view(B, H, W)
            with torch.no_grad():
                key = g if fast else key_src[c:].index_select(0, idx00).view(B, H, W)
                same = torch.sub(key, expect).abs_().lt_(surface_tolerance)  # (1 or 0)
            vals.append(torch.lerp(expect, g, same))
            flags.append(same)
        d_src = torch.lerp(torch.lerp(vals[0], vals[1], fx), torch.lerp(vals[2], vals[3], fx), fy)
        del vals
        # move the sampled point forward again (eq. 1); only its new depth ratio q_z is needed
        qz = qz.addcmul_(d_src, a_z) if fast else torch.addcmul(qz, d_src, a_z)
        with torch.no_grad():
            ok = hz_ok & (qz > _MIN_DEPTH_RATIO)
        new = d_src.div_(qz.clamp_min_(_MIN_DEPTH_RATIO)) if fast else d_src / qz.clamp_min(_MIN_DEPTH_RATIO)
        if step == 0:
            with torch.no_grad():
                rx, ry = fx.detach().round(), fy.detach().round()  # 0 / 1: which neighbour is the nearest
                top = torch.lerp(flags[0], flags[1], rx)
                nearest_same = torch.lerp(top, torch.lerp(flags[2], flags[3], rx), ry) > 0.5
                settled = torch.sub(new, est).abs_() <= surface_tolerance
                landed = (landed | fallback) & nearest_same & settled & hz_ok
        del flags
        est = torch.lerp(est, new, (ok & landed).to(dtype))
    return est, landed


def _refine(
    est: torch.Tensor,
    landed: torch.Tensor,
    d: torch.Tensor,
    src_ok: torch.Tensor,
    A: torch.Tensor,
    a: torch.Tensor,
    e: torch.Tensor,
    back: list[torch.Tensor],
    layout: _Padded,
    refine_iterations: int,
    surface_tolerance: float,
    fast: bool,
) -> torch.Tensor:
    """Inverse-warp refinement of the splatted values (soft mode; module docstring): exact on smooth surfaces."""
    B, H, W = d.shape
    dtype = d.dtype
    big = _big(dtype)
    shifts = [j * layout.Wp + i for i, j in _CORNERS]
    with torch.no_grad():
        # source disparity where valid, far below any disparity where not: one gather gives value and test
        key_src = layout.pad(torch.add(d, src_ok.to(dtype) - 1.0, alpha=big), -big)
        idx_dtype = torch.int32 if layout.size < 2**31 else torch.int64
    d_src_pad = key_src if fast else layout.pad(d, 0.0)
    a_z = _per_batch(a[:, 2])
    for _ in range(refine_iterations):
        sxf, syf, inv_h, hz_ok = _back_project(back, e, est, fast)
        expect = est * inv_h  # the source disparity this target value came from
        with torch.no_grad():
            rx0 = sxf.clamp(-_PAD, W + 1).floor_()
            ry0 = syf.clamp(-_PAD, H + 1).floor_()
            idx00 = layout.index(rx0, ry0, idx_dtype)
        rfu, rfv = sxf - rx0, syf - ry0
        rwx, rwy = (1 - rfu, rfu), (1 - rfv, rfv)
        wk_sum, d_num = None, None
        for (i, j), c in zip(_CORNERS, shifts, strict=True):
            g = key_src[c:].index_select(0, idx00).view(B, H, W)
            with torch.no_grad():
                same = torch.sub(g, expect).abs_().lt_(surface_tolerance)  # (1 or 0)
            if fast:
                wk = same.mul_(rwx[i]).mul_(rwy[j])
                if wk_sum is None:
                    wk_sum, d_num = wk.clone(), wk * g
                else:
                    wk_sum.add_(wk)
                    d_num.addcmul_(wk, g)
            else:
                wk = rwx[i] * rwy[j] * same
                gv = d_src_pad[c:].index_select(0, idx00).view(B, H, W)
                wk_sum = wk if wk_sum is None else wk_sum + wk
                d_num = wk * gv if d_num is None else d_num + wk * gv
        with torch.no_grad():
            ok_ref = landed & hz_ok & (wk_sum > 1e-3)
        wk_safe = wk_sum.clamp_min_(1e-3) if fast else wk_sum.clamp_min(1e-3)
        d_src = d_num.div_(wk_safe) if fast else d_num / wk_safe
        # move the sampled point forward again (eq. 1); only its new depth ratio q_z is needed
        qz2 = torch.addcmul(_per_batch(A[:, 2, 0]) * sxf + _per_batch(A[:, 2, 2]), syf, _per_batch(A[:, 2, 1]))
        qz2 = qz2.addcmul_(d_src, a_z)
        with torch.no_grad():
            ok_ref = (ok_ref & (qz2 > _MIN_DEPTH_RATIO)).to(dtype)
        if fast:
            qz2.clamp_min_(_MIN_DEPTH_RATIO)
            new_est = d_src.div_(qz2)
        else:
            qz2 = qz2.clamp_min(_MIN_DEPTH_RATIO)
            new_est = d_src / qz2
        est = torch.lerp(est, new_est, ok_ref)
    return est


def _coverage_splat(
    d: torch.Tensor,
    var: torch.Tensor | None,
    src_ok: torch.Tensor,
    A: torch.Tensor,
    a: torch.Tensor,
    G: torch.Tensor,
    e: torch.Tensor,
    back: list[torch.Tensor],
    layout: _Padded,
    xs: torch.Tensor,
    ys: torch.Tensor,
    mode: str,
    temperature: float,
    surface_tolerance: float,
    fast: bool,
):
    """Soft mode, or hard mode without refinement: the coverage test, z-buffer and splatting (module docstring).

    Returns ``(est, est_var, landed, src_ok)``, maps ``(B, H, W)`` (``est_var`` None without variance).
    """
    B, H, W = d.shape
    dtype = d.dtype
    big = _big(dtype)
    slack = 0.5 + _COVER_SLACK
    per_batch = _per_batch
    # ---- move every source point (eq. 1) and project it into frame t
    Px, Py, Pz = (_affine_map(A, k, xs, ys).addcmul_(d, per_batch(a[:, k])) for k in range(3))
    src_ok = src_ok & (Pz > _MIN_DEPTH_RATIO)
    inv = Pz.clamp_min(_MIN_DEPTH_RATIO).reciprocal()  # 1 / q_z, clamped first: points behind are masked out
    u, v = (Px.mul_(inv), Py.mul_(inv)) if fast else (Px * inv, Py * inv)
    d_new = d * inv  # f B / Z' with Z' = Z q_z
    var_new = None if var is None else var * inv * inv  # first-order propagation: d' = d / q_z
    okf = src_ok.to(dtype)
    not_ok = okf - 1.0  # -1 for invalid sources, 0 for valid ones

    # ---- footprint: the four target pixels (x0 + i, y0 + j) around each moved point (_CORNERS), in a padded
    # flat layout: out-of-image corners land in margin cells that are never read back.
    x0 = u.detach().clamp(-_PAD, W + 1).floor_()
    y0 = v.detach().clamp(-_PAD, H + 1).floor_()
    fu, fv = u - x0, v - y0
    tgt = layout.index(x0, y0)  # of corner (0, 0); corner (i, j) is read and written through a view shifted by
    shifts = [j * layout.Wp + i for i, j in _CORNERS]  # j * Wp + i cells, with the same index


    with torch.no_grad():
        # Coverage test: the target centre T sent back into frame t-1 at the moved point's depth must fall in
        # the source pixel's square. With D = T - (u, v) = (i - fu, j - fv) the back-projection is
        # N = (x, y, 1) / q_z + G[:, :2] D exactly ((u, v) goes back to (x, y)), so its offset from the source
        # pixel is E / N_z with E_x = (G00 - x G20, G01 - x G21) . D, E_y likewise with y: no division needed.
        fud, fvd = fu.detach(), fv.detach()
        g20, g21 = per_batch(G[:, 2, 0]), per_batch(G[:, 2, 1])
        col_a, col_b = per_batch(G[:, 0, 0]) - xs * g20, per_batch(G[:, 0, 1]) - xs * g21
        row_a, row_b = per_batch(G[:, 1, 0]) - ys * g20, per_batch(G[:, 1, 1]) - ys * g21
        ex0 = torch.addcmul(col_a * fud, col_b, fvd)  # -E_x at corner (0, 0)
        ey0 = torch.addcmul(row_a * fud, row_b, fvd)
        nz0 = torch.addcmul(inv - g20 * fud, g21.expand_as(fvd), fvd, value=-1.0)  # N_z at corner (0, 0)
        thr0 = torch.addcmul(not_ok, nz0, okf, value=slack)  # slack * N_z; -1 for invalid sources
        del nz0
        z_slack, z_strict = layout.full(-big, d), layout.full(-big, d)
        d_det = d_new.detach()
        keys = []  # the slack keys, kept for the splatting pass
        off, excess = torch.empty_like(d_det), torch.empty_like(d_det)
        k_strict = 1.0 - 0.5 / slack  # strict excess = slack excess + k_strict * threshold
        for (i, j), c in zip(_CORNERS, shifts, strict=True):
            if i == j == 0:
                torch.maximum(torch.abs(ex0, out=off), torch.abs(ey0, out=excess), out=off)  # |offset| N_z
                torch.sub(off, thr0, out=excess)  # > 0: not covered
                torch.add(excess, thr0, alpha=k_strict, out=off)  # > 0: not strictly covered
            else:
                s = slack * (i * g20 + j * g21)  # the threshold's change from corner (0, 0)
                torch.sub(col_a * i + col_b * j, ex0, out=off).abs_()
                torch.maximum(off, torch.sub(row_a * i + row_b * j, ey0, out=excess).abs_(), out=off)
                torch.sub(off, thr0, out=excess).sub_(s)
                torch.add(excess, thr0, alpha=k_strict, out=off).add_(s * k_strict)
            # key = d' where covered, far below any disparity where not (no branches, no masks)
            key = torch.add(d_det, excess.clamp_min_(0.0), alpha=-big, out=excess)
            z_slack[c:].scatter_reduce_(0, tgt, key.view(-1), "amax")
            z_strict[c:].scatter_reduce_(
                0, tgt, torch.add(d_det, off.clamp_min_(0.0), alpha=-big, out=off).view(-1), "amax"
            )
            keys.append(key)
            excess = torch.empty_like(d_det)
        del ex0, ey0, thr0, off, excess
        # Each pair above is tested at its own source's depth, so neighbouring squares of one surface may
        # leave hairline cracks (closed by the slack) and the slack may fatten a foreground edge. Decide
        # per target with ONE depth, the nearest candidate's: send the target back at that depth; the
        # source pixel it falls in (an exact tiling) must belong to that surface. If not, the candidate
        # only reached the target through the slack (fattening): take the nearest strict cover instead.
        zs = layout.crop(z_slack).clamp_min(-1.0)  # -1: nothing landed
        zt = layout.crop(z_strict).clamp_min(-1.0)
        del z_slack, z_strict
        sxf, syf, _, hz_ok = _back_project(back, e, zs.clamp_min(0.0), True)
        key_new = layout.pad(torch.add(d_det, not_ok, alpha=big), -big)  # d' of valid sources, -big elsewhere
        s_idx = layout.index(sxf.clamp_(-1, W).round_(), syf.clamp_(-1, H).round_())
        s_d = key_new.index_select(0, s_idx).view(B, H, W)  # d' of the source pixel it falls in
        consistent = ((s_d - zs).abs_() < surface_tolerance) & hz_ok
        swap = (~consistent & (zt >= 0)).to(dtype)
        zbuf = zs.addcmul_(swap, zt.sub_(zs))  # nearest slack cover, or the nearest strict one where inconsistent
        landed = zbuf >= 0
        del key_new, swap, zt, sxf, syf

    # ---- splatting: among the sources covering a target, the z-buffer's surface (within surface_tolerance)
    # averaged with bilinear weights ("hard"), or softmax weights b * exp((d' - m) / T) ("soft").
    z_pad = layout.pad(zbuf, -1.0)
    wx, wy = (1 - fu, fu), (1 - fv, fv)
    eps = eps_like(d_new)
    wsum, num = layout.full(0.0, d), layout.full(0.0, d)
    num_var = None if var_new is None else layout.full(0.0, d)
    for (i, j), c, key in zip(_CORNERS, shifts, keys, strict=True):
        z_at = z_pad[c:].index_select(0, tgt).view(B, H, W)
        with torch.no_grad():
            if mode == "hard":
                # z-buffer (nearest surface wins); ties within surface_tolerance averaged with bilinear weights
                sel = key.sub_(z_at).abs_().le_(surface_tolerance)  # (1 or 0), in place (keys are done)
            else:
                # candidates the z-buffer rejected above as fattening are left out
                sel = ((key >= 0) & (key <= z_at + surface_tolerance)).to(dtype)
        if mode == "hard":
            w = sel.mul_((wx[i] * wy[j]).add_(eps)) if fast else (wx[i] * wy[j] + eps) * sel
        else:
            # softmax splatting: m = the per-target z-buffer value (no gradient, for stability); selected
            # candidates have d' <= m + surface_tolerance, so the upper clamp never binds on them.
            logit = ((d_new - z_at) / temperature).clamp(-60.0, surface_tolerance / temperature + 1.0)
            w = (wx[i] * wy[j] + eps) * logit.exp() * sel
        wsum[c:].scatter_add_(0, tgt, w.view(-1))
        num[c:].scatter_add_(0, tgt, (w * d_new).view(-1))
        if num_var is not None:
            num_var[c:].scatter_add_(0, tgt, (w * var_new).view(-1))
    wsum_safe = layout.crop(wsum).clamp_min(eps)  # clamp: empty targets (holes) get 0, not NaN
    est = layout.crop(num) / wsum_safe
    est_var = None if num_var is None else layout.crop(num_var) / wsum_safe
    del wsum, num, num_var
    del s_idx, s_d, consistent, keys, tgt

    return est, est_var, landed, src_ok
