"""Predict the next disparity map from the current one and the rig's motion (PAPER.md eq. 1, loop step 3).

Every pixel of frame ``t-1`` is a 3-D point; the rig's motion ``camera_t_T_camera_{t-1}`` moves it
(the discrete form of eq. 1, ``P' = R P + t``), it is projected into frame ``t`` and splatted there.
The new disparity of a moved point is ``f B / Z'`` with ``Z'`` its *new* depth.

We write the point in inverse-depth form, ``P = ray / rho`` with ``ray = K^-1 (x, y, 1)`` and
``rho = d / (f B)``, so that

    q = R ray + t rho,     x' = project(q),     d' = d / q_z,

which stays finite for points at infinity (``d = 0``: pure rotation moves them).

Forward splatting (:func:`predict_disparity`) has two modes:

* ``"hard"`` (with refinement, the default): a z-buffer and a gathered visibility check. Every moved
  source point goes to its nearest target pixel with one ``amax`` scatter of integer keys (the bits
  of ``d'`` as float32 order like the values); a target's candidate is the nearest surface within one
  pixel (the 3x3 maximum: no cracks up to a magnification of 2 per axis), or what landed on the pixel
  itself where that is on the same surface. The target, sent back into frame ``t-1`` at the
  candidate's depth, falls in a source pixel: the candidate is accepted when that pixel's disparity
  is within ``surface_tolerance`` of the one the candidate implies there (the surface really reaches
  the target, so foreground edges are not fattened; compared in frame ``t-1``, where neighbouring
  pixels of a steep surface differ less than after a zoom-in). That source pixel's ``d'`` and
  variance are the start. Where the candidate is rejected, the same start is a fallback (the
  background behind a fattened edge, or a steep surface's own value). The first refinement step
  (below) checks every target once more: it keeps (or, for a fallback, gives) the target when its
  nearest source neighbour is on the start's surface and the step moves it by at most
  ``surface_tolerance``; otherwise the pixel is a hole (where magnification is far beyond 2 the
  inverse warp does not settle and the value would be wrong).
* ``"hard"`` with ``refine_iterations=0``: a coverage test plus a z-buffer. A moved source pixel covers
  a target pixel when the target pixel's centre, sent back into frame ``t-1`` at the source's new
  depth, falls in that source pixel's square (a 0.1 px slack closes hairline cracks and a second,
  single-depth check per target keeps that slack from fattening foreground edges); among the sources
  covering a target, the nearest surface (largest ``d'``) wins and the sources within
  ``surface_tolerance`` of it are averaged with their bilinear weights (values and variances).
* ``"soft"``: differentiable softmax splatting. Each moved point spreads over the target pixels
  it covers among its four neighbours (the same coverage test, a mask without gradient) with
  bilinear weights ``b`` times ``exp((d' - m) / temperature)`` (``m`` the target's z-buffer value,
  a stabiliser without gradient); the value is the normalised weighted mean, differentiable in
  disparity, motion and intrinsics, and the nearest surface dominates smoothly.

Sub-pixel values (both modes): the start value is the moved surface's disparity near, not at, the
target pixel centre. ``refine_iterations`` inverse-warp steps make it exact on smooth surfaces: the
target pixel is sent back into frame ``t-1`` with its current estimate, the source map is sampled
there bilinearly (only among valid neighbours on the same surface: in hard mode the others count
with the estimate's own value, which has the same fixed point as renormalising the weights), and the
sampled point is moved forward again. On planes this converges to the exact value in one or two
steps (tests/refine/test_predict.py measures it); one step is the default. Refinement refines
disparity only; the variance stays the carried one.

Speed: for float32 CPU maps that need no gradient, hard mode with refinement runs compiled
(:mod:`egorefine.refine._predict_numba`, numba, where :func:`egorefine.core.use_compiled` allows it: the same
formulas in three loops, decisions equal to
this path's, values to rounding; about 0.35x this path's time at 640x480 on two threads). The torch
path below is the reference for GPU tensors, float64 and autograd. It is written in pixel-homogeneous
coordinates (one affine map per component over the grid), out-of-image points land in the margin of
a padded flat layout instead of being masked, bilinear neighbours share one index through shifted
views, and masks are applied by arithmetic (``torch.where`` on noisy masks is slow on CPU). When no
input needs a gradient, intermediate maps are updated in place; the two paths give the same numbers
(tests check it). The refinement step is the largest part of hard mode's cost, then the check and the hole fill
(timings in docs/decisions.md).

Known limit: a discrete map knows a depth edge only to within a pixel, so foreground edges alias by
up to half a pixel per prediction and the error random-walks (and grows with magnification) when
predictions are chained without verification; on the test scenes about 1-2 % of valid pixels are
off by more than 0.5 px after 10 frames, all at depth edges.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import torch
from torch import nn
from torch.nn import functional as F

from ..core import (
    _graphs,
    check_choice,
    check_finite,
    check_float,
    check_intrinsics,
    check_positive,
    check_same_device,
    check_setting,
    check_shape,
    check_variance,
    eps_like,
    use_compiled,
)
from ..core.dispatch import needs_grad
from ..core.errors import ValueRangeError
from . import _predict_numba

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
# Margin (pixels) of the padded flat layout of target and source maps (see _Padded).
_PAD = 2


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


def _big(dtype: torch.dtype) -> float:
    """A finite 'minus infinity' for keys and sentinels: far beyond any disparity, its square still finite."""
    return min(1e30, torch.finfo(dtype).max ** 0.5)


def _pixel_motion(motion: torch.Tensor, K: torch.Tensor, baseline: torch.Tensor):
    """The motion in pixel-homogeneous form (eq. 1 with inverse depth ``d / (f B)``).

    A source pixel ``(x, y)`` with disparity ``d`` moves to ``P = A (x, y, 1) + a d`` (``P_z = Z'/Z``); a
    target pixel ``T`` sent back at disparity ``d'`` lands at ``G (T, 1) + e d'`` in frame ``t-1``.
    Returns ``A, a, G, e`` with ``A, G`` ``(B, 3, 3)`` and ``a, e`` ``(B, 3)``.
    """
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
    dtype, device = disparity.dtype, disparity.device
    big = _big(dtype)
    have = ~hole[:, 0]
    d = disparity[:, 0]
    index = torch.int32 if B * H * (W + 2) < 2**31 else torch.int64
    cols = torch.arange(1, W + 1, device=device, dtype=index)
    # running maximum of (column + 1) over non-hole pixels: the nearest non-hole column on the left, plus one (0:
    # none); the same on the mirrored row gives W minus the nearest one on the right (0: none). At a non-hole pixel
    # both are the pixel itself, so the minimum below leaves it unchanged.
    left = (have * cols).cummax(dim=-1).values
    right = (have.flip(-1) * cols).cummax(dim=-1).values.flip(-1)
    # values looked up in each row padded with +big on both sides (a missing side reads +big: the minimum ignores it)
    padded = F.pad(d, (1, 1), value=big).view(-1)
    base = torch.arange(0, B * H * (W + 2), W + 2, device=device, dtype=index).view(B, H, 1)
    at_left = (left + base).view(-1)
    at_right = (base + (W + 1) - right).view(-1)
    fill = torch.minimum(padded.index_select(0, at_left), padded.index_select(0, at_right)).view(B, H, W)
    # rows with no non-hole pixel: the smallest non-hole disparity of the image; images with none: 0
    image_min = d.masked_fill(hole[:, 0], big).flatten(1).amin(dim=1)
    empty = image_min >= big / 2  # (B,): no non-hole pixel at all
    image_fill = torch.where(empty, 0.0, image_min).view(B, 1, 1)
    row_fill = torch.where(left[..., -1:] == 0, image_fill, big)  # (B, H, 1)
    return torch.minimum(fill, row_fill)[:, None], empty


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
    refine_iterations: int = 1,
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
        process_noise: px^2 added to the carried variance per prediction (a number, or a 0-d tensor that
            gradients reach).
        hole_variance: px^2 given to hole pixels.
        fill_holes: fill holes by the background rule (else 0 there).
        temperature: px, softness of the softmax splatting (``"soft"`` only); smaller is harder (a number or a
            0-d tensor).
        refine_iterations: inverse-warp refinement steps (0 keeps the splatted values; one is nearly exact).
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
    check_shape(motion, ["B", "4", "4"], "motion", dims)
    check_shape(K, ["B", "3", "3"], "K", dims)
    check_shape(baseline, ["B"], "baseline", dims)
    check_positive(baseline, "baseline")
    check_finite(motion, "motion")
    check_intrinsics(K, "K", dims)
    check_choice(mode, ["hard", "soft"], "mode")
    if variance is not None:
        check_shape(variance, ["B", "1", "H", "W"], "variance", dims)
        check_variance(variance, "variance")
    if valid is not None:
        check_shape(valid, ["B", "1", "H", "W"], "valid", dims)
        if valid.dtype != torch.bool:
            valid = valid > 0.5
    check_same_device(disparity, "disparity", motion=motion, K=K, baseline=baseline, variance=variance, valid=valid)
    process_noise = check_setting(process_noise, "process_noise")
    temperature = check_setting(temperature, "temperature")
    learnable = [t for t in (process_noise, temperature) if isinstance(t, torch.Tensor)]  # (those needing a gradient)
    if temperature <= 0 or process_noise < 0 or hole_variance <= 0 or surface_tolerance <= 0:
        raise ValueRangeError(
            "temperature, hole_variance and surface_tolerance must be > 0 and process_noise >= 0, got "
            f"{temperature}, {hole_variance}, {surface_tolerance}, {process_noise}"
        )
    if refine_iterations < 0:
        raise ValueRangeError(f"refine_iterations: must be >= 0, got {refine_iterations}")

    # Without gradients (the refiner's loop) intermediate maps are updated in place; with them, out of place.
    fast = not needs_grad(disparity, motion, K, baseline, variance, *learnable)
    # the compiled splat implements hard mode with refinement; it reads every input in the disparity's dtype
    hard_refined = mode == "hard" and refine_iterations > 0
    compiled = hard_refined and use_compiled(
        disparity, valid, *learnable,
        *(t.to(disparity.dtype) for t in (variance, motion, K, baseline) if t is not None))
    if not compiled:
        check_finite(disparity, "disparity")  # (the compiled path tests it inside its kernels)
    settings = (mode, process_noise, hole_variance, fill_holes, temperature, refine_iterations, surface_tolerance)
    if fast and _graphs.usable(disparity, motion, K, baseline):
        # CUDA inference: the splat's ~150 launches replayed from a CUDA graph recorded per shape and settings
        inputs = [t for t in (disparity, motion, K, baseline, variance, valid) if t is not None]
        has = (variance is not None, valid is not None)
        splat = partial(_predict_inputs, has=has, settings=settings)
        return Prediction(*_graphs.replay(splat, ("predict", has, settings), *inputs))
    with torch.set_grad_enabled(not fast):
        return _predict(
            disparity,
            motion,
            K,
            baseline,
            variance,
            valid,
            mode,
            process_noise,
            hole_variance,
            fill_holes,
            temperature,
            refine_iterations,
            surface_tolerance,
            fast,
            compiled,
        )


def _predict_inputs(*inputs: torch.Tensor, has: tuple[bool, bool], settings: tuple) -> tuple[torch.Tensor, ...]:
    """:func:`_predict` without gradients from ``(disparity, motion, K, baseline[, variance][, valid])``, ``has``
    saying which of the optional two are there: the form :func:`egorefine.core._graphs.replay` takes."""
    disparity, motion, K, baseline, *rest = inputs
    variance = rest.pop(0) if has[0] else None
    valid = rest.pop(0) if has[1] else None
    with torch.no_grad():
        return tuple(_predict(disparity, motion, K, baseline, variance, valid, *settings, True))


def _predict(
    disparity: torch.Tensor,
    motion: torch.Tensor,
    K: torch.Tensor,
    baseline: torch.Tensor,
    variance: torch.Tensor | None,
    valid: torch.Tensor | None,
    mode: str,
    process_noise: float,
    hole_variance: float,
    fill_holes: bool,
    temperature: float,
    refine_iterations: int,
    surface_tolerance: float,
    fast: bool,
    compiled: bool = False,
) -> Prediction:
    """The body of :func:`predict_disparity` (inputs checked); ``fast``: no gradient needed, work in place;
    ``compiled``: run the compiled splat (:func:`~egorefine.core.use_compiled` allowed it)."""
    B, _, H, W = disparity.shape
    dtype, device = disparity.dtype, disparity.device
    motion, K, baseline = motion.to(dtype), K.to(dtype), baseline.to(dtype)
    d = disparity[:, 0]
    var = None if variance is None else variance[:, 0].to(dtype)
    # Pixel-homogeneous form (see _pixel_motion); the grid enters as a column and a row vector.
    A, a, G, e = _pixel_motion(motion, K, baseline)
    if compiled:
        # the same steps compiled (egorefine.refine._predict_numba): float32 CPU inference
        out = _predict_numba.hard_splat(
            d.contiguous(), None if var is None else var.contiguous(),
            None if valid is None else valid[:, 0].contiguous(), A, a, G, e, surface_tolerance, refine_iterations,
            fill_holes, process_noise, hole_variance,
        )
        if out is None:  # NaN or Inf in the disparity
            check_finite(disparity, "disparity")
        est, out_var, confidence, landed, hole = out
        return Prediction(est[:, None], out_var[:, None], hole[:, None], landed[:, None], confidence[:, None])
    src_ok = d >= 0
    if valid is not None:
        src_ok = src_ok & valid[:, 0]
    xs = torch.arange(W, device=device, dtype=dtype).view(1, 1, W)
    ys = torch.arange(H, device=device, dtype=dtype).view(1, H, 1)
    layout = _Padded(B, H, W, device)
    back = [_affine_map(G, k, xs, ys) for k in range(3)]  # target pixels turned into frame t-1

    if mode == "hard" and refine_iterations > 0:
        est, est_var, landed, fallback, src_ok, key_src = _hard_start(
            d, var, src_ok, A, a, e, back, layout, xs, ys, surface_tolerance, fast
        )
        est, landed = _hard_refine(
            est, landed, fallback, d, key_src, A, a, e, back, layout, refine_iterations, surface_tolerance, fast
        )
    else:
        est, est_var, landed, src_ok = _coverage_splat(
            d, var, src_ok, A, a, G, e, back, layout, xs, ys, mode, temperature, surface_tolerance, fast
        )
        if refine_iterations > 0:
            est = _refine(est, landed, d, src_ok, A, a, e, back, layout, refine_iterations, surface_tolerance, fast)

    hole4 = ~landed[:, None]
    if fill_holes:  # (reads only the landed values)
        est, _ = fill_holes_background(est[:, None], hole4)
    else:
        est = (est * landed.to(dtype))[:, None]
    carried = (est_var + process_noise) if est_var is not None else est.new_zeros(est[:, 0].shape) + process_noise
    out_var = carried[:, None].masked_fill(hole4, hole_variance)
    confidence = (1.0 + out_var).reciprocal()  # (in place only without autograd: reciprocal keeps its output)
    confidence = confidence.masked_fill_(hole4, 0.0) if fast else confidence.masked_fill(hole4, 0.0)
    return Prediction(est, out_var, hole4, ~hole4, confidence)


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
        refine_iterations: int = 1,
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
