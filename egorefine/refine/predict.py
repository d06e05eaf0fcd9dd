"""Predict the next disparity map from the current one and the rig's motion (docs/method.md eq. 1, loop step 3).

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
(:mod:`egorefine.refine._splat_numba`, numba, where :func:`egorefine.core.use_compiled` allows it: the same
formulas in three loops, decisions equal to
this path's, values to rounding; faster than this path, docs/decisions.md has the timings). The torch
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

import inspect
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
    use_compiled,
)
from ..core.dispatch import needs_grad
from ..core.errors import ValueRangeError
from . import _splat_numba
from ._splat import (
    _affine_map,
    _big,
    _coverage_splat,
    _hard_refine,
    _hard_start,
    _Padded,
    _pixel_motion,
    _refine,
)

__all__ = ["Prediction", "predict_disparity", "fill_holes_background", "PredictDisparity"]

class Prediction(NamedTuple):
    """Result of :func:`predict_disparity`, every field ``(B, 1, H, W)``.

    Attributes:
        disparity: predicted disparity of frame ``t`` in pixels; real values where something landed,
            hole pixels filled by the background rule (or 0 with ``fill_holes=False``). Never NaN.
        variance: px^2; carried and inflated where something landed, ``hole_variance`` on holes.
        hole: bool, True where no valid source point landed (before filling).
        valid: bool, ``~hole``: True only where real values landed.
        confidence: in ``[0, 1]``; ``1 / (1 + variance)`` where valid, 0 on holes.

    Example:
        >>> from egorefine.geometry import make_intrinsics
        >>> pred = predict_disparity(torch.full((1, 1, 6, 8), 4.0), torch.eye(4)[None], make_intrinsics(10.0, 4.0, 3.0),
        ...                          torch.tensor([1.0]))  # no motion: every pixel lands where it was
        >>> pred.disparity.shape, bool(pred.hole.any()), bool(pred.valid.all())
        (torch.Size([1, 1, 6, 8]), False, True)
        >>> round(pred.confidence[0, 0, 0, 0].item(), 4)  # 1 / (1 + process_noise)
        0.9901
    """

    disparity: torch.Tensor
    variance: torch.Tensor
    hole: torch.Tensor
    valid: torch.Tensor
    confidence: torch.Tensor


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
    """Predict frame ``t``'s disparity by moving every 3-D point of frame ``t-1`` (docs/method.md eq. 1).

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
    return _predict_disparity(disparity, motion, K, baseline, variance, valid, mode, process_noise, hole_variance,
                              fill_holes, temperature, refine_iterations, surface_tolerance)[0]


# predict_disparity's settings with their defaults, for the callers of _predict_disparity that keep them
_SETTINGS = {name: p.default for name, p in inspect.signature(predict_disparity).parameters.items()
             if name in ("hole_variance", "fill_holes", "temperature", "refine_iterations", "surface_tolerance")}


def _predict_disparity(
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
    finish: tuple[int, float, float, float, float] | None = None,
) -> tuple[Prediction, bool]:
    """:func:`predict_disparity` (its checks and its paths), and whether ``finish`` (the refiner's step after the
    splat, see :func:`egorefine.refine._splat_numba.hard_splat`) was done in the same pass: only the compiled splat
    does it, given a variance and a validity; else the caller runs that step itself."""
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
        check_float(variance, "variance")
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
    if not compiled:  # (the compiled path tests these inside its kernels)
        check_finite(disparity, "disparity")
        if variance is not None:
            check_variance(variance, "variance")
    settings = (mode, process_noise, hole_variance, fill_holes, temperature, refine_iterations, surface_tolerance)
    if fast and _graphs.usable(disparity, motion, K, baseline):
        # CUDA inference: the splat's ~150 launches replayed from a CUDA graph recorded per shape and settings
        inputs = [t for t in (disparity, motion, K, baseline, variance, valid) if t is not None]
        has = (variance is not None, valid is not None)
        splat = partial(_predict_inputs, has=has, settings=settings)
        return Prediction(*_graphs.replay(splat, ("predict", has, settings), *inputs)), False
    finish = finish if compiled and variance is not None and valid is not None else None
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
            finish,
        ), finish is not None


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
    finish: tuple[int, float, float, float, float] | None = None,
) -> Prediction:
    """The body of :func:`predict_disparity` (inputs checked); ``fast``: no gradient needed, work in place;
    ``compiled``: run the compiled splat (:func:`~egorefine.core.use_compiled` allowed it), with ``finish`` if
    given (:func:`egorefine.refine._splat_numba.hard_splat`)."""
    B, _, H, W = disparity.shape
    dtype, device = disparity.dtype, disparity.device
    motion, K, baseline = motion.to(dtype), K.to(dtype), baseline.to(dtype)
    d = disparity[:, 0]
    var = None if variance is None else variance[:, 0].to(dtype)
    # Pixel-homogeneous form (see _pixel_motion); the grid enters as a column and a row vector.
    A, a, G, e = _pixel_motion(motion, K, baseline)
    if compiled:
        # the same steps compiled (egorefine.refine._splat_numba): float32 CPU inference
        out = _splat_numba.hard_splat(
            d.contiguous(), None if var is None else var.contiguous(),
            None if valid is None else valid[:, 0].contiguous(), A, a, G, e, surface_tolerance, refine_iterations,
            fill_holes, process_noise, hole_variance, finish=finish,
        )
        if out is None:  # NaN or Inf in the disparity, or a variance not finite and >= 0
            check_finite(disparity, "disparity")
            if variance is not None:
                check_variance(variance, "variance")
            raise ValueRangeError(f"variance: expected finite values >= 0 in {dtype}")  # (beyond its range)
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
