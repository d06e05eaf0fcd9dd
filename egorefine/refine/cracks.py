"""Close the cracks of a forward-splatted prediction by looking each hole pixel up in the source map.

Forward splatting (:func:`~egorefine.refine.predict_disparity`) tiles the target only up to a limited
magnification (its tests: 90 % of the seen pixels land at 3x; 3.6x leaves a third of them as holes). The
refiner predicts from its last verified keyframe with the motion composed since then, so a near surface can
be magnified far more (a road 5 m ahead, four 1.1 m steps later, is 8 times larger), and such surfaces come
out as holes although the keyframe saw them. Disocclusions are holes too, but there the keyframe saw another
surface.

:func:`close_cracks` tells the two apart by an inverse warp. A hole pixel ``T`` starts from its filled value
``d`` (the background rule of :func:`~egorefine.refine.fill_holes_background`). Sent back into the keyframe at
that disparity (docs/method.md eq. 1 inverted, in inverse-depth form: ``h = K R' K^-1 T + K t' d / (f B)`` with
``key_T_t = (R', t')``), it lands at pixel ``(h_x, h_y) / h_z``, where its disparity would be ``d / h_z``. The
keyframe is sampled there bilinearly, but only where the four neighbours are valid and on one surface (spread
below ``surface_tolerance``). The sampled ``d_k`` moved forward gives the new estimate ``d_k h_z``; after
``iterations`` such steps the pixel is accepted when the last step moved it by less than ``tolerance``: the
keyframe saw this pixel's surface at the place and depth the motion predicts. A disocclusion fails the test: sent
back at the background's depth it lands on the foreground that hid it, whose disparity does not match.

Accepted pixels get the sampled value and the sampled variance carried like the splat's (``var_k h_z^2`` plus the
process noise) and become valid; rejected ones stay holes. Float32 CPU maps without gradient take a compiled loop
over the hole pixels (:mod:`egorefine.refine._predict_numba`, where :func:`egorefine.core.use_compiled` allows it)
with the same formulas.

Gradients (the torch path): an accepted pixel's value is the bilinear look-up moved forward, differentiable in the
keyframe's disparity and variance and in the motion, intrinsics and baseline; the other pixels keep the
prediction's values and their graph. Which pixels are holes, which four keyframe pixels a look-up blends and
whether a pixel is accepted are hard decisions: piecewise constant, with no gradient of their own (a value jumps
where an input crosses one of them).
"""

from __future__ import annotations

import torch

from ..core import check_setting, check_shape, use_compiled
from . import _predict_numba
from ._splat import _pixel_motion
from .predict import _SETTINGS, Prediction, _predict_disparity

__all__ = ["close_cracks"]  # (and the refiner's private finish_prediction and predict_finished)

_MIN_DEPTH_RATIO = 1e-3
# close_cracks' defaults (the refiner's settings)
_ITERATIONS, _TOLERANCE, _SURFACE_TOLERANCE = 2, 0.1, 1.0


def close_cracks(
    prediction: Prediction,
    key_disparity: torch.Tensor,
    key_variance: torch.Tensor,
    key_valid: torch.Tensor,
    motion: torch.Tensor,
    K: torch.Tensor,
    baseline: torch.Tensor,
    process_noise: float = 0.0,
    iterations: int = _ITERATIONS,
    tolerance: float = _TOLERANCE,
    surface_tolerance: float = _SURFACE_TOLERANCE,
) -> Prediction:
    """Hole pixels of ``prediction`` that the keyframe saw become valid, with values looked up in it.

    Args:
        prediction: the :class:`~egorefine.refine.predict.Prediction` of frame ``t`` from the keyframe
            (hole pixels filled by the background rule).
        key_disparity, key_variance, key_valid: ``(B, 1, H, W)`` keyframe maps it was predicted from.
        motion: ``(B, 4, 4)`` ``camera_t_T_key``, the motion the prediction used.
        K: ``(B, 3, 3)`` intrinsics; baseline: ``(B,)`` metres.
        process_noise: variance (px^2) added to looked-up pixels, as the prediction added to splatted ones (a
            number, or a 0-d tensor that gradients reach).
        iterations: inverse-warp steps from the filled start value.
        tolerance: the last step may move the estimate by at most this many px.
        surface_tolerance: the four keyframe neighbours of a look-up must be valid and within this many px.

    Returns:
        A :class:`~egorefine.refine.predict.Prediction` with the closed cracks valid (``hole`` still marks the
        splat's holes). Gradients reach the inputs through the looked-up values; the choice of pixels and their
        acceptance are piecewise constant (module docstring).

    >>> from egorefine.refine import predict_disparity
    >>> from egorefine.geometry import make_intrinsics
    >>> K, b = make_intrinsics(50.0, 16.0, 12.0), torch.tensor([0.1])
    >>> d = torch.full((1, 1, 24, 32), 4.0)
    >>> step = torch.eye(4)[None]; step[0, 2, 3] = -0.9  # 0.9 m toward a wall 1.25 m away: 3.6x larger
    >>> pred = predict_disparity(d, step, K, b)
    >>> closed = close_cracks(pred, d, torch.ones_like(d), d > 0, step, K, b)
    >>> bool(pred.valid.all()), bool(closed.valid.all())
    (False, True)
    """
    dims = check_shape(key_disparity, ["B", "1", "H", "W"], "key_disparity")
    check_shape(prediction.disparity, ["B", "1", "H", "W"], "prediction.disparity", dims)
    check_shape(motion, ["B", "4", "4"], "motion", dims)
    process_noise = check_setting(process_noise, "process_noise")
    learnable = [process_noise] if isinstance(process_noise, torch.Tensor) else []
    B, _, H, W = key_disparity.shape
    maps = (prediction.disparity, prediction.variance, prediction.valid, prediction.confidence)
    key_ok = key_valid if key_valid.dtype == torch.bool else key_valid > 0.5
    # key_T_t in pixel-homogeneous form (the splat's own back-projection): h = G (u, v, 1) + e d
    _, _, G, e = _pixel_motion(motion, K, baseline)
    bool_mask = maps[2].dtype == torch.bool  # (the kernel reads the prediction's mask as bool)
    if bool_mask and use_compiled(*maps, key_disparity, key_variance, key_ok, G.to(torch.float32),
                                  e.to(torch.float32), *learnable):
        # the same look-ups compiled (egorefine.refine._predict_numba); None: no hole
        out = _predict_numba.close_cracks(
            *(t[:, 0].contiguous() for t in maps), key_disparity[:, 0], key_variance[:, 0], key_ok[:, 0],
            G.to(torch.float32), e.to(torch.float32), iterations, tolerance, surface_tolerance, process_noise,
        )
        if out is None:
            return prediction
        disparity, variance, valid, confidence = (t[:, None] for t in out)
        return prediction._replace(disparity=disparity, variance=variance, valid=valid, confidence=confidence)
    if bool(prediction.valid.all()):
        return prediction
    idx = (~prediction.valid).view(-1).nonzero().squeeze(1)  # flat indices of the hole pixels
    dtype = key_disparity.dtype
    b_idx, pix = idx.div(H * W, rounding_mode="floor"), idx.remainder(H * W)
    ys, xs = pix.div(W, rounding_mode="floor").to(dtype), pix.remainder(W).to(dtype)
    M, m = G[b_idx], e[b_idx]  # (N, 3, 3), (N, 3): per point, a gather of 12 numbers
    base = M[:, :, 0] * xs[:, None] + M[:, :, 1] * ys[:, None] + M[:, :, 2]  # (N, 3)
    flat_d, flat_var = key_disparity.reshape(-1), key_variance.reshape(-1)
    flat_ok = key_ok.reshape(-1)
    offset = b_idx * (H * W)

    def look_up(d: torch.Tensor, with_variance: bool):
        """Keyframe sample at the back-projection of disparity ``d``: (value, variance, ok, h_z)."""
        h = torch.addcmul(base, m, d[:, None])
        hz = h[:, 2].clamp_min(_MIN_DEPTH_RATIO)
        sx, sy = h[:, 0] / hz, h[:, 1] / hz
        inside = (h[:, 2] > _MIN_DEPTH_RATIO) & (sx >= 0) & (sy >= 0) & (sx <= W - 1) & (sy <= H - 1)
        # the four pixels blended: a hard choice (no gradient); the bilinear weights within them are smooth
        x0 = sx.detach().clamp(0, W - 1).floor().clamp_max(W - 2)
        y0 = sy.detach().clamp(0, H - 1).floor().clamp_max(H - 2)
        ax, ay = (sx - x0).clamp(0, 1), (sy - y0).clamp(0, 1)
        first = offset + y0.long() * W + x0.long()
        corners = torch.stack([first, first + 1, first + W, first + W + 1])  # (4, N)
        vals = flat_d.take(corners)
        ok = inside & flat_ok.take(corners).all(0) & ((vals.amax(0) - vals.amin(0)) <= surface_tolerance)
        w = torch.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay])  # (4, N)
        var = (w * flat_var.take(corners)).sum(0) if with_variance else None
        return (w * vals).sum(0), var, ok, hz

    d = prediction.disparity.reshape(-1)[idx]
    iterations = max(1, int(iterations))
    ok = torch.ones_like(d, dtype=torch.bool)
    for i in range(iterations):
        value, var, sample_ok, hz = look_up(d, with_variance=i == iterations - 1)
        new = value * hz  # d' = d_k / q_z with q_z = 1 / h_z (eq. 1)
        step = (new - d).abs()
        ok = ok & sample_ok
        d = torch.where(sample_ok, new, d)
    accept = ok & (step <= tolerance)
    keep = accept.nonzero().squeeze(1)
    at = (idx[keep],)
    # out of place: the accepted values replace the holes' and the graph reaches both
    disparity = prediction.disparity.reshape(-1).index_put(at, d[keep]).view_as(prediction.disparity)
    variance = prediction.variance.reshape(-1).index_put(at, var[keep] * hz[keep].square() + process_noise)
    variance = variance.view_as(prediction.variance)
    valid = prediction.valid.reshape(-1).index_put(at, torch.ones_like(keep, dtype=torch.bool))
    valid = valid.view_as(prediction.valid)
    confidence = torch.where(valid, 1.0 / (1.0 + variance), torch.zeros_like(variance))
    return prediction._replace(disparity=disparity, variance=variance, valid=valid, confidence=confidence)


def finish_prediction(
    prediction: Prediction,
    key_disparity: torch.Tensor,
    key_variance: torch.Tensor,
    key_valid: torch.Tensor,
    motion: torch.Tensor,
    K: torch.Tensor,
    baseline: torch.Tensor,
    process_noise: float,
    fill_cracks: bool,
    valid_range: tuple[float, float],
) -> Prediction:
    """The refiner's step after the splat: :func:`close_cracks` (when ``fill_cracks``), then predicted values outside
    ``valid_range = [low, high)`` made not valid, with confidence 0 (the next stereo run could not verify them).

    ``prediction`` must be the caller's own, fresh from :func:`~egorefine.refine.predict_disparity`: where
    :func:`egorefine.core.use_compiled` allows it (float32 CPU maps, no gradient wanted) they are changed in place,
    in one compiled pass (no copies of the maps, no full-map torch op); otherwise they go through
    :func:`close_cracks` and torch, out of place, and the outputs carry the graph (the range test is a hard
    decision: piecewise constant).
    """
    low, high = valid_range
    process_noise = check_setting(process_noise, "process_noise")
    learnable = [process_noise] if isinstance(process_noise, torch.Tensor) else []
    maps = (prediction.disparity, prediction.variance, prediction.valid, prediction.confidence)
    key_ok = key_valid if key_valid.dtype == torch.bool else key_valid > 0.5
    _, _, G, e = _pixel_motion(motion, K, baseline)
    # the kernel writes the maps in place: they must be contiguous, the mask bool
    writable = maps[2].dtype == torch.bool and all(t.is_contiguous() for t in maps)
    if writable and use_compiled(*maps, key_disparity, key_variance, key_ok, G.to(torch.float32),
                                 e.to(torch.float32), *learnable):
        _predict_numba.finish_prediction(
            *(t[:, 0] for t in maps), key_disparity[:, 0], key_variance[:, 0], key_ok[:, 0], G.to(torch.float32),
            e.to(torch.float32), _ITERATIONS if fill_cracks else 0, _TOLERANCE, _SURFACE_TOLERANCE, process_noise,
            low, high,
        )
        return prediction
    if fill_cracks:
        prediction = close_cracks(prediction, key_disparity, key_variance, key_valid, motion, K, baseline,
                                  process_noise=process_noise)
    in_range = (prediction.disparity >= low) & (prediction.disparity < high)
    return prediction._replace(valid=prediction.valid & in_range, confidence=prediction.confidence * in_range)


def predict_finished(
    key_disparity: torch.Tensor,
    key_motion: torch.Tensor,
    K: torch.Tensor,
    baseline: torch.Tensor,
    key_variance: torch.Tensor,
    key_valid: torch.Tensor,
    mode: str,
    process_noise: float,
    fill_cracks: bool,
    valid_range: tuple[float, float],
) -> Prediction:
    """The refiner's prediction: :func:`~egorefine.refine.predict_disparity` of the keyframe's map moved by
    ``key_motion`` (its defaults otherwise), then :func:`finish_prediction` with the same keyframe and motion.

    Where the compiled splat runs (float32 CPU, no gradient) it does both in one pass, finishing each row while it
    is in cache (the same formulas, so the same maps); otherwise the two run one after the other.

    Shape:
        - key_disparity, key_variance, key_valid: ``(B, 1, H, W)``; key_motion ``(B, 4, 4)``; K ``(B, 3, 3)``;
          baseline ``(B,)``. Returns a :class:`~egorefine.refine.Prediction` of ``(B, 1, H, W)`` maps.

    Example:
        >>> from egorefine.geometry import make_intrinsics
        >>> d = torch.full((1, 1, 6, 8), 4.0)
        >>> pred = predict_finished(d, torch.eye(4)[None], make_intrinsics(10.0, 4.0, 3.0), torch.tensor([1.0]),
        ...                         torch.zeros_like(d), torch.ones_like(d, dtype=torch.bool), "hard", 0.01, True,
        ...                         (0.0, 64.0))
        >>> bool(pred.valid.all()), bool((pred.disparity == 4.0).all())
        (True, True)
    """
    finish = (_ITERATIONS if fill_cracks else 0, _TOLERANCE, _SURFACE_TOLERANCE, *valid_range)
    pred, finished = _predict_disparity(key_disparity, key_motion, K, baseline, key_variance, key_valid, mode=mode,
                                        process_noise=process_noise, **_SETTINGS, finish=finish)
    if finished:
        return pred
    return finish_prediction(pred, key_disparity, key_variance, key_valid, key_motion, K, baseline, process_noise,
                             fill_cracks, valid_range)
