"""Direct (photometric) refinement of the ego-motion: the new image aligned to the previous one through its depth.

The feature solve (:func:`~egorefine.motion.solve_ego_motion`) uses a few hundred tracked points; the loop carries a
dense disparity map of the previous frame. Direct methods (the dense visual odometry of Steinbruecker, Sturm and
Cremers, LSD-SLAM, DSO) use it: a pixel ``p`` of the previous left image with inverse depth ``rho = d / (f B)`` is
moved by the motion ``T = camera_t_T_camera_{t-1}`` and projected into the new image, and the motion is the one that
makes the intensities agree,

    r(p) = I_t(pi(R K^-1 p + t rho)) - (a I_{t-1}(p) + b),

with an affine brightness change ``(a, b)`` (exposure, gain) estimated jointly. The point is written in
inverse-depth form (``R K^-1 p + t rho`` is the moved point scaled by ``rho``, whose projection is the same), so a
far point (``rho`` near 0) stays finite and only its rotation moves it. On a stereo frame the new right image
adds a second residual per pixel, the same point seen by the right camera (its pixel the left one moved by the
new disparity ``f B rho / q_z``) against the same previous intensity, with the right camera's own ``(a, b)``.

Steps of :func:`refine_motion_direct` (one batch of items, fixed shapes):

1. **Pixels**: in each cell of a grid over the previous image, the ``per_cell`` pixels of largest gradient magnitude
   with a valid disparity away from depth edges (a well-spread subset: texture carries the photometric signal, flat
   regions none), both images slightly blurred first.
2. **Coarse to fine** over the tracker's image pyramid (:func:`~egorefine.features.build_pyramid`): at each level a
   fixed number of Gauss-Newton steps on the 8 unknowns (the twist of a left-multiplied SE(3) increment, ``a``,
   ``b``), each step Levenberg-damped and taken per item only where it lowers that item's robust cost (Huber on
   intensity residuals; otherwise the item's damping grows). Weights: the Huber weight times
   ``1 / (sigma^2 + (g . du/drho)^2 var_rho)``, the residual's variance from image noise ``sigma`` and from the
   disparity's own variance moved through the warp.
3. **Acceptance**: the refinement is kept for an item only if its cost at the finest level is below the cost of the
   feature solve's motion there (with its best brightness model); otherwise the input motion comes back unchanged,
   flagged. Too few usable pixels (a black, overexposed or textureless frame, a disparity map with no valid pixel)
   or a non-finite result also return the input motion, flagged; never NaN.

Every step is a torch operation (``grid_sample``, batched ``linalg.solve``), so gradients reach the images, the
disparity and ``K`` through the final iterations (the pixel choice and the accept tests are piecewise constant).
For float32 CPU tensors that need no gradient (:func:`~egorefine.core.use_compiled`), the same steps run compiled
(:mod:`egorefine.motion._direct_numba`), with float64 sums; this torch code stays the reference.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d, spatial_gradient

from ..core import ValueRangeError, check_float, check_positive, check_shape, eps_like, to_grey, use_compiled
from ..features import build_pyramid
from ..geometry import se3_exp
from . import _direct_numba
from .robust import robust_loss, robust_weight

__all__ = ["DirectMotion", "refine_motion_direct", "DIRECT_STATUS"]

#: Status codes of :class:`DirectMotion` (``status``), by name.
DIRECT_STATUS = {"refined": 0, "cost rose": 1, "too few pixels": 2, "not finite": 3, "brightness": 4}

# The brightness gains a refinement may end at: outside, the affine model is not what changed between the frames
# (a light switched, the exposure jumped), and the result is not trusted.
_GAIN_RANGE = (0.5, 2.0)

# The kernel on residuals in units of their standard deviation: quadratic within 1.345 of it, linear beyond.
_HUBER = "huber"


class DirectMotion(NamedTuple):
    """Result of :func:`refine_motion_direct`.

    Attributes:
        motion: ``(B, 4, 4)`` ``camera_t_T_camera_{t-1}``: the refined motion where ``status == 0``, else the input.
        status: ``(B,)`` long, :data:`DIRECT_STATUS` codes (0 refined; 1 the refinement raised the cost; 2 too few
            usable pixels; 3 a non-finite result; 4 a brightness gain outside ``[0.5, 2]``).
        gain, offset: ``(B,)`` the brightness model ``I_t ~ gain I_{t-1} + offset`` at the end (1 and 0 where not
            refined).
        cost_before, cost_after: ``(B,)`` the mean robust cost at the finest level with the input motion and with
            the result (equal where not refined).
        num_pixels: ``(B,)`` long, pixels used at the finest level.
    """

    motion: torch.Tensor
    status: torch.Tensor
    gain: torch.Tensor
    offset: torch.Tensor
    cost_before: torch.Tensor
    cost_after: torch.Tensor
    num_pixels: torch.Tensor


def _sample(image: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Bilinear samples ``(B, C, N)`` of ``image`` ``(B, C, H, W)`` at pixel positions ``xy`` ``(B, N, 2)``."""
    h, w = image.shape[-2:]
    norm = torch.stack([2 * xy[..., 0] / max(w - 1, 1) - 1, 2 * xy[..., 1] / max(h - 1, 1) - 1], dim=-1)
    return F.grid_sample(image, norm[:, None], mode="bilinear", padding_mode="border", align_corners=True)[:, :, 0]


def _window_max(x: torch.Tensor, radius: int) -> torch.Tensor:
    """``F.max_pool2d(x, 2 radius + 1, 1, radius)`` of ``(B, C, H, W)`` as maxima of shifted slices, rows then columns:
    equal values, and several times faster than max_pool2d on the CPU (docs/decisions.md)."""
    h, w = x.shape[-2:]
    padded = F.pad(x, (radius, radius, radius, radius), value=float("-inf"))
    rows = padded[..., :, :w]
    for k in range(1, 2 * radius + 1):
        rows = torch.maximum(rows, padded[..., :, k : k + w])
    out = rows[..., :h, :]
    for k in range(1, 2 * radius + 1):
        out = torch.maximum(out, rows[..., k : k + h, :])
    return out


def _select_pixels(grey: torch.Tensor, disparity: torch.Tensor, valid: torch.Tensor, cell: int, per_cell: int,
                   min_gradient: float, max_step: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Step 1: ``(xy (B, N, 2) float, usable (B, N) bool)``, ``per_cell`` pixels of largest gradient per cell."""
    b, _, h, w = grey.shape
    grad = spatial_gradient(grey, mode="diff")
    g = torch.hypot(grad[:, :, 0], grad[:, :, 1])  # (torch's norm over that size-2 axis is far slower on the CPU)
    # not beside a depth edge: there the intensity mixes two surfaces that move apart (and one may be hidden)
    known = torch.where(valid, disparity, torch.full_like(disparity, float("nan")))
    hi = _window_max(torch.nan_to_num(known, nan=-1e9), 2)
    lo = -_window_max(-torch.nan_to_num(known, nan=1e9), 2)
    smooth = (hi - lo) <= max_step
    score = torch.where(valid & smooth & (disparity > 0) & (g >= min_gradient), g, torch.full_like(g, -1.0))
    hc, wc = h // cell, w // cell
    cells = score[..., : hc * cell, : wc * cell].reshape(b, hc, cell, wc, cell).permute(0, 1, 3, 2, 4)
    best, index = cells.reshape(b, hc * wc, cell * cell).topk(min(per_cell, cell * cell), dim=-1)
    cy, cx = torch.div(index, cell, rounding_mode="floor"), index % cell
    oy = (torch.arange(hc, device=grey.device) * cell).repeat_interleave(wc)[None, :, None]
    ox = (torch.arange(wc, device=grey.device) * cell).repeat(hc)[None, :, None]
    xy = torch.stack([(cx + ox).reshape(b, -1), (cy + oy).reshape(b, -1)], dim=-1).to(grey.dtype)
    return xy, (best >= 0).reshape(b, -1)


def _scaled_intrinsics(K: torch.Tensor, level: int) -> torch.Tensor:
    """``K`` of pyramid level ``level``: :func:`~egorefine.features.build_pyramid` puts pixel ``x`` at ``x / 2^l``."""
    Kl = K.clone()
    Kl[:, :2] = K[:, :2] * 2.0**-level
    return Kl


def _warp(motion: torch.Tensor, rays: torch.Tensor, rho: torch.Tensor, K: torch.Tensor,
          shift: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Moved points in inverse-depth form ``q = R rays + t rho`` ``(B, N, 3)``, their pixels ``(B, N, 2)`` and
    whether they lie in front of the camera. ``shift`` ``(B,)``: ``fx B`` of the right camera of a rectified pair,
    whose pixel is the left one moved by the new disparity ``fx B rho / q_z``; None: the left camera."""
    q = rays @ motion[:, :3, :3].transpose(1, 2) + motion[:, None, :3, 3] * rho[..., None]
    z = q[..., 2]
    front = z > eps_like(z) ** 0.5
    zs = torch.where(front, z, torch.ones_like(z))
    u = K[:, None, 0, 0] * q[..., 0] / zs + K[:, None, 0, 2]
    if shift is not None:
        u = u - shift[:, None] * rho / zs
    v = K[:, None, 1, 1] * q[..., 1] / zs + K[:, None, 1, 2]
    return q, torch.stack([u, v], dim=-1), front


def _residuals(state: tuple, level: dict, motion: torch.Tensor, gain: torch.Tensor, offset: torch.Tensor,
               jacobian: bool):
    """Residuals ``(B, N)``, their weights' geometric part and validity, and (with ``jacobian``) ``J`` ``(B, N, 8)``
    of one camera (``level["shift"]``: None for the left one, see :func:`_warp`)."""
    rays, rho, var_rho, usable = state
    K, image, grads, template = level["K"], level["image"], level["grads"], level["template"]
    shift = level.get("shift")
    h, w = image.shape[-2:]
    q, uv, front = _warp(motion, rays, rho, K, shift)
    inside = front & (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
    value = _sample(image, uv)[:, 0]
    r = value - (gain[:, None] * template + offset[:, None])
    ok = usable & inside
    g = _sample(grads, uv)  # (B, 2, N)
    zs = torch.where(front, q[..., 2], torch.ones_like(q[..., 2]))
    fx, fy = K[:, None, 0, 0], K[:, None, 1, 1]
    # d(u, v) / dq: the projection's Jacobian (q is scale-free: its projection is the moved point's)
    du_dz = -fx * q[..., 0] / zs**2
    if shift is not None:  # the right camera's u also holds -fx B rho / q_z
        du_dz = du_dz + shift[:, None] * rho / zs**2
    du = torch.stack([fx / zs, torch.zeros_like(zs), du_dz], dim=-1)
    dv = torch.stack([torch.zeros_like(zs), fy / zs, -fy * q[..., 1] / zs**2], dim=-1)
    dI_dq = g[:, 0, :, None] * du + g[:, 1, :, None] * dv  # (B, N, 3)
    # the disparity's variance moved through the warp: dq/drho = t (and the right camera's shift, d u / d rho)
    dI_drho = (dI_dq * motion[:, None, :3, 3]).sum(-1)
    if shift is not None:
        dI_drho = dI_drho - g[:, 0] * shift[:, None] / zs
    geometric = dI_drho**2 * var_rho
    if not jacobian:
        return r, geometric, ok, None
    # a left-multiplied increment exp(delta) moves q by rho drho_t + dphi x q: dq/d(rho_t, phi) = [rho I, -hat(q)]
    cross = torch.linalg.cross(q, dI_dq, dim=-1)  # (dI/dq) . (phi x q) = phi . (q x dI/dq)
    J = torch.cat([dI_dq * rho[..., None], cross, -template[..., None], -torch.ones_like(template)[..., None]], -1)
    return r, geometric, ok, J


def _stacked(state: tuple, cameras: list[dict], motion: torch.Tensor, gain: torch.Tensor, offset: torch.Tensor,
             jacobian: bool):
    """:func:`_residuals` of every camera of a level, concatenated along the pixels: ``(B, C N)`` residuals,
    geometric parts and validity, and ``J`` ``(B, C N, 6 + 2 C)`` (the motion's six columns shared, each camera its
    own brightness pair). ``gain``, ``offset``: ``(B, C)``. One camera: its tensors as they are."""
    if len(cameras) == 1:
        return _residuals(state, cameras[0], motion, gain[:, 0], offset[:, 0], jacobian)
    parts = [_residuals(state, lv, motion, gain[:, i], offset[:, i], jacobian) for i, lv in enumerate(cameras)]
    r, geo, ok = (torch.cat([p[k] for p in parts], 1) for k in range(3))
    if not jacobian:
        return r, geo, ok, None
    rows = []
    for i, (_, _, _, J) in enumerate(parts):
        pairs = [J[..., 6:] if k == i else torch.zeros_like(J[..., 6:]) for k in range(len(cameras))]
        rows.append(torch.cat([J[..., :6], *pairs], -1))
    return r, geo, ok, torch.cat(rows, 1)


def _weights(r: torch.Tensor, geometric: torch.Tensor, ok: torch.Tensor, sigma: float) -> torch.Tensor:
    """Per-pixel weights: Huber on the residual in units of its standard deviation, over its variance."""
    variance = sigma * sigma + geometric
    std = variance.sqrt()
    w = robust_weight((r / std).abs(), _HUBER, 1.0) / variance
    return torch.where(ok, w, torch.zeros_like(w))


def _cost(r: torch.Tensor, geometric: torch.Tensor, ok: torch.Tensor, sigma: float) -> torch.Tensor:
    """``(B,)`` mean Huber cost of the normalised residuals over the usable pixels (inf with none)."""
    std = (sigma * sigma + geometric).sqrt()
    loss = torch.where(ok, robust_loss((r / std).abs(), _HUBER, 1.0), torch.zeros_like(r))
    n = ok.sum(-1)
    return torch.where(n > 0, loss.sum(-1) / n.clamp(min=1), torch.full_like(loss[:, 0], float("inf")))


def _best_brightness(r0: torch.Tensor, template: torch.Tensor, w: torch.Tensor, gain: torch.Tensor,
                     offset: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The weighted least-squares ``(gain, offset)`` given residuals ``r0`` computed with ``(gain, offset)``."""
    value = r0 + gain[:, None] * template + offset[:, None]  # the sampled new intensities
    sw = w.sum(-1).clamp(min=eps_like(w))
    mt, mv = (w * template).sum(-1) / sw, (w * value).sum(-1) / sw
    var_t = (w * (template - mt[:, None]) ** 2).sum(-1) / sw
    cov = (w * (template - mt[:, None]) * (value - mv[:, None])).sum(-1) / sw
    a = torch.where(var_t > eps_like(w), cov / var_t.clamp(min=eps_like(w)), torch.ones_like(var_t))
    return a, mv - a * mt


def refine_motion_direct(
    prev_image: torch.Tensor,
    image: torch.Tensor,
    prev_disparity: torch.Tensor,
    K: torch.Tensor,
    baseline: torch.Tensor,
    motion: torch.Tensor,
    prev_valid: torch.Tensor | None = None,
    prev_variance: torch.Tensor | None = None,
    levels: int = 3,
    iterations: int = 4,
    cell: int = 16,
    per_cell: int = 4,
    sigma: float = 0.01,
    min_gradient: float = 0.01,
    min_pixels: int = 64,
    damping: float = 1e-3,
    blur: float = 1.0,
    max_step: float = 0.5,
    right_image: torch.Tensor | None = None,
) -> DirectMotion:
    """Refine the ego-motion ``motion`` by aligning ``image`` to ``prev_image`` warped through ``prev_disparity``.

    See the module description for the model and the steps. Run it after the feature solve: it converges from a
    motion within a few pixels of the truth at the coarsest level, and it keeps the input wherever it cannot do
    better (``status``).

    Args:
        prev_image, image: ``(B, 1, H, W)`` grey (or ``(B, 3, H, W)`` colour, made grey by ``to_grey``) left images
            of frames ``t-1`` and ``t`` in ``[0, 1]``.
        prev_disparity: ``(B, 1, H, W)`` disparity of frame ``t-1`` in pixels (<= 0: none).
        K: ``(B, 3, 3)`` rectified intrinsics; ``baseline``: ``(B,)`` metres.
        motion: ``(B, 4, 4)`` ``camera_t_T_camera_{t-1}``, the starting motion (the feature solve's).
        prev_valid: ``(B, 1, H, W)`` bool, where ``prev_disparity`` holds a value (default: where it is > 0).
        prev_variance: ``(B, 1, H, W)`` the disparity's variance in px^2 (default: none, only image noise weighs).
        levels: pyramid levels (default 3: a start 4 px off at full resolution is 1 px off at the coarsest).
        iterations: Gauss-Newton steps per level (default 4).
        cell, per_cell: pixels are the ``per_cell`` of largest gradient in each ``cell x cell`` block (default 16
            and 4: about 1 200 pixels at 640x480, spread over the image).
        sigma: image noise, in intensity units (default 0.01, about 2.5 grey levels of 8 bits); the Huber kernel
            bends at 1.345 of it.
        min_gradient: pixels with a smaller gradient magnitude (per pixel, central differences) are not used.
        min_pixels: fewer usable pixels at the finest level: the input motion comes back (status 2).
        damping: Levenberg-Marquardt damping, relative to the diagonal of the normal equations.
        blur: Gaussian sigma in pixels applied to both images first (default 1; 0: none): bilinear samples of a
            band-limited image between pixels are close to its true intensities, and the cost is smoother.
        max_step: pixels whose 5x5 neighbourhood spans more than this many px of disparity (a depth edge, where the
            intensity mixes two surfaces that move apart) are not used (default 0.5).
        right_image: ``(B, 1|3, H, W)`` the right image of frame ``t`` (a stereo frame), or None. Given, every pixel
            also compares the previous left intensity with the new right image at the point's new disparity (the
            right camera ``baseline`` to the right of the left one, rectified), with its own brightness model: twice
            the residuals, and a second view of the same motion. This runs on the torch path.

    Returns:
        :class:`DirectMotion`.

    Example:
        >>> from egorefine.data import render_sequence
        >>> seq = render_sequence(num_frames=2, height=96, width=128, seed=0)
        >>> out = refine_motion_direct(seq.left[:1], seq.left[1:], seq.disparity[:1], seq.K[None],
        ...                            torch.tensor([seq.baseline]), torch.eye(4)[None])
        >>> out.motion.shape, out.status.tolist()
        (torch.Size([1, 4, 4]), [0])
    """
    dims = check_shape(prev_image, ["B", "1|3", "H", "W"], "prev_image")
    check_shape(image, ["B", "1|3", "H", "W"], "image", dims)
    check_shape(prev_disparity, ["B", "1", "H", "W"], "prev_disparity", dims)
    check_shape(K, ["B", "3", "3"], "K", dims)
    check_shape(baseline, ["B"], "baseline", dims)
    check_shape(motion, ["B", "4", "4"], "motion", dims)
    if right_image is not None:
        check_shape(right_image, ["B", "1|3", "H", "W"], "right_image", dims)
        check_float(right_image, "right_image")
    for name, x in (("prev_image", prev_image), ("image", image), ("prev_disparity", prev_disparity), ("K", K),
                    ("motion", motion)):
        check_float(x, name)
    check_positive(baseline, "baseline")
    if levels < 1 or iterations < 0 or cell < 2 or per_cell < 1:
        raise ValueRangeError(f"refine_motion_direct: expected levels >= 1, iterations >= 0, cell >= 2, per_cell >= 1;"
                              f" got {levels}, {iterations}, {cell}, {per_cell}")
    if dims["H"] < cell or dims["W"] < cell:
        raise ValueRangeError(f"refine_motion_direct: the image ({dims['H']}x{dims['W']}) is smaller than one cell"
                              f" ({cell} px)")
    dtype = prev_disparity.dtype
    prev_grey = to_grey(prev_image).to(dtype)
    grey = to_grey(image).to(dtype)
    if right_image is None and use_compiled(prev_image, image, prev_disparity, K, baseline, motion, prev_valid,
                                            prev_variance):
        return DirectMotion(*_direct_numba.refine_compiled(
            prev_grey, grey, prev_disparity, prev_valid, prev_variance, K, baseline, motion, levels, iterations, cell,
            per_cell, sigma, min_gradient, min_pixels, damping, blur, max_step))
    greys = [grey] if right_image is None else [grey, to_grey(right_image).to(dtype)]  # the new images, per camera
    if blur > 0:  # band-limited images: bilinear samples between pixels are then close to the true intensities
        k = 2 * int(math.ceil(2 * blur)) + 1
        prev_grey = gaussian_blur2d(prev_grey, (k, k), (blur, blur), border_type="replicate")
        greys = [gaussian_blur2d(g, (k, k), (blur, blur), border_type="replicate") for g in greys]
    valid = prev_disparity > 0 if prev_valid is None else prev_valid.bool() & (prev_disparity > 0)
    finite = torch.isfinite(prev_disparity)
    valid = valid & finite
    disparity = torch.where(valid, prev_disparity, torch.zeros_like(prev_disparity))
    K, motion, baseline = K.to(dtype), motion.to(dtype), baseline.to(dtype)
    b = prev_grey.shape[0]

    # 1. the pixels, their rays K^-1 p and inverse depths rho = d / (f B) (and rho's variance)
    xy, usable = _select_pixels(prev_grey, disparity, valid, cell, per_cell, min_gradient, max_step)
    d = _sample(disparity, xy)[:, 0]
    fB = K[:, 0, 0] * baseline
    rho = d / fB[:, None]
    if prev_variance is None:
        var_rho = torch.zeros_like(rho)
    else:
        var_d = torch.nan_to_num(prev_variance.to(dtype), nan=0.0, posinf=0.0).clamp(min=0)
        var_rho = _sample(var_d, xy)[:, 0] / fB[:, None] ** 2
    ones = torch.ones_like(xy[..., :1])
    rays = torch.linalg.solve(K[:, None], torch.cat([xy, ones], -1)[..., None])[..., 0]  # (B, N, 3)

    # 2. coarse to fine: at each level the template intensities at the pixels (scaled), the new image and gradients
    # (per level, one entry per camera: the left one, then the right one with its shift fx B)
    pyr_prev, pyrs = build_pyramid(prev_grey, levels), [build_pyramid(g, levels) for g in greys]
    state_levels = []
    for level in range(levels):
        template = _sample(pyr_prev[level], xy * 2.0**-level)[:, 0]
        Kl = _scaled_intrinsics(K, level)
        cameras = []
        for i, pyr in enumerate(pyrs):
            grads = spatial_gradient(pyr[level], mode="diff")[:, 0]  # (B, 2, H, W): d/dx, d/dy
            cameras.append({"K": Kl, "image": pyr[level], "grads": grads, "template": template,
                            "shift": Kl[:, 0, 0] * baseline if i == 1 else None})
        state_levels.append(cameras)
    state = (rays, rho, var_rho, usable)
    n_cam = len(greys)
    gain = torch.ones(b, n_cam, dtype=dtype, device=d.device)
    offset = torch.zeros(b, n_cam, dtype=dtype, device=d.device)

    # the input's cost at the finest level, with its best brightness model per camera (the bar the result must pass)
    finest = state_levels[0]
    r, geo, ok, _ = _stacked(state, finest, motion, gain, offset, jacobian=False)
    w0, n = _weights(r, geo, ok, sigma), rho.shape[1]
    fits = [_best_brightness(r[:, i * n:(i + 1) * n], template_i, w0[:, i * n:(i + 1) * n], gain[:, i], offset[:, i])
            for i, template_i in enumerate(lv["template"] for lv in finest)]
    gain0, offset0 = torch.stack([f[0] for f in fits], 1), torch.stack([f[1] for f in fits], 1)
    r, geo, ok, _ = _stacked(state, finest, motion, gain0, offset0, jacobian=False)
    cost_before = _cost(r, geo, ok, sigma)
    num_pixels = ok[:, :n].sum(-1)  # (the left camera's: each pixel counts once)

    current, a, c = motion, gain0, offset0
    lam = torch.full((b,), damping, dtype=dtype, device=d.device)
    eye = torch.eye(6 + 2 * n_cam, dtype=dtype, device=d.device)
    for level in reversed(range(levels)):
        lv = state_levels[level]
        r, geo, ok, J = _stacked(state, lv, current, a, c, jacobian=True)
        cost = _cost(r, geo, ok, sigma)
        for _ in range(iterations):
            w = _weights(r, geo, ok, sigma)
            H = (J * w[..., None]).transpose(1, 2) @ J
            g = (J * (w * r)[..., None]).sum(1)
            diag = torch.diagonal(H, dim1=1, dim2=2).clamp(min=eps_like(H))
            A = H + lam[:, None, None] * torch.diag_embed(diag) + eps_like(H) * eye
            step = -torch.linalg.solve(A, g[..., None])[..., 0]
            step = torch.where(torch.isfinite(step).all(-1, keepdim=True), step, torch.zeros_like(step))
            trial = se3_exp(step[:, :6]) @ current
            a_t, c_t = a + step[:, 6::2], c + step[:, 7::2]
            r_t, geo_t, ok_t, J_t = _stacked(state, lv, trial, a_t, c_t, jacobian=True)
            cost_t = _cost(r_t, geo_t, ok_t, sigma)
            better = cost_t < cost
            pick = better[:, None]
            current = torch.where(better[:, None, None], trial, current)
            a, c = torch.where(pick, a_t, a), torch.where(pick, c_t, c)
            r, geo, J = torch.where(pick, r_t, r), torch.where(pick, geo_t, geo), torch.where(pick[..., None], J_t, J)
            ok = torch.where(pick, ok_t, ok)
            cost = torch.where(better, cost_t, cost)
            lam = torch.where(better, lam * 0.5, lam * 4.0).clamp(min=damping * 1e-3, max=1e6)

    # 3. acceptance at the finest level
    r, geo, ok, _ = _stacked(state, finest, current, a, c, jacobian=False)
    cost_after = _cost(r, geo, ok, sigma)
    finite_result = torch.isfinite(current).all(-1).all(-1) & torch.isfinite(cost_after) & torch.isfinite(a).all(-1)
    status = torch.full((b,), DIRECT_STATUS["refined"], dtype=torch.long, device=d.device)
    status = torch.where(cost_after < cost_before, status, torch.full_like(status, DIRECT_STATUS["cost rose"]))
    in_range = ((a >= _GAIN_RANGE[0]) & (a <= _GAIN_RANGE[1])).all(-1)
    a, c = a[:, 0], c[:, 0]  # (the left camera's brightness model is the one reported)
    status = torch.where(in_range, status, torch.full_like(status, DIRECT_STATUS["brightness"]))
    status = torch.where(finite_result, status, torch.full_like(status, DIRECT_STATUS["not finite"]))
    status = torch.where(num_pixels >= min_pixels, status, torch.full_like(status, DIRECT_STATUS["too few pixels"]))
    keep = status == DIRECT_STATUS["refined"]
    out = torch.where(keep[:, None, None], torch.nan_to_num(current), motion)
    return DirectMotion(out, status, torch.where(keep, a, torch.ones_like(a)),
                        torch.where(keep, c, torch.zeros_like(c)), cost_before,
                        torch.where(keep, cost_after, cost_before), num_pixels)
