"""Close the cracks of a forward-splatted prediction by looking each hole pixel up in the source map.

Forward splatting (:func:`~egorefine.refine.predict_disparity`) tiles the target without cracks up to a
magnification of about two. The refiner predicts from its last verified keyframe with the motion composed
since then, so a near surface can be magnified far more (a road 5 m ahead, four 1.1 m steps later, is 8 times
larger), and such surfaces come out as holes although the keyframe saw them. Disocclusions are holes too, but
there the keyframe saw another surface.

:func:`close_cracks` tells the two apart by an inverse warp. A hole pixel ``T`` starts from its filled value
``d`` (the background rule of :func:`~egorefine.refine.fill_holes_background`). Sent back into the keyframe at
that disparity (PAPER.md eq. 1 inverted, in inverse-depth form: ``h = K R' K^-1 T + K t' d / (f B)`` with
``key_T_t = (R', t')``), it lands at pixel ``(h_x, h_y) / h_z``, where its disparity would be ``d / h_z``. The
keyframe is sampled there bilinearly, but only where the four neighbours are valid and on one surface (spread
below ``surface_tolerance``). The sampled ``d_k`` moved forward gives the new estimate ``d_k h_z``; after
``iterations`` such steps the pixel is accepted when the last step moved it by less than ``tolerance``: the
keyframe saw this pixel's surface at the place and depth the motion predicts. A disocclusion fails the test: sent
back at the background's depth it lands on the foreground that hid it, whose disparity does not match.

Accepted pixels get the sampled value and the sampled variance carried like the splat's (``var_k h_z^2`` plus the
process noise) and become valid; rejected ones stay holes.
"""

from __future__ import annotations

import torch

from ..core import check_shape
from .predict import Prediction

__all__ = ["close_cracks"]

_MIN_DEPTH_RATIO = 1e-3


def close_cracks(
    prediction: Prediction,
    key_disparity: torch.Tensor,
    key_variance: torch.Tensor,
    key_valid: torch.Tensor,
    motion: torch.Tensor,
    K: torch.Tensor,
    baseline: torch.Tensor,
    process_noise: float = 0.0,
    iterations: int = 2,
    tolerance: float = 0.1,
    surface_tolerance: float = 1.0,
) -> Prediction:
    """Hole pixels of ``prediction`` that the keyframe saw become valid, with values looked up in it.

    Args:
        prediction: the :class:`~egorefine.refine.predict.Prediction` of frame ``t`` from the keyframe
            (hole pixels filled by the background rule).
        key_disparity, key_variance, key_valid: ``(B, 1, H, W)`` keyframe maps it was predicted from.
        motion: ``(B, 4, 4)`` ``camera_t_T_key``, the motion the prediction used.
        K: ``(B, 3, 3)`` intrinsics; baseline: ``(B,)`` metres.
        process_noise: variance (px^2) added to looked-up pixels, as the prediction added to splatted ones.
        iterations: inverse-warp steps from the filled start value.
        tolerance: the last step may move the estimate by at most this many px.
        surface_tolerance: the four keyframe neighbours of a look-up must be valid and within this many px.

    Returns:
        A :class:`~egorefine.refine.predict.Prediction` with the closed cracks valid (``hole`` still marks the
        splat's holes). Without gradient: the look-up is a discrete decision on a prediction.

    >>> from egorefine.refine import predict_disparity
    >>> from egorefine.geometry import make_intrinsics
    >>> K, b = make_intrinsics(50.0, 16.0, 12.0), torch.tensor([0.1])
    >>> d = torch.full((1, 1, 24, 32), 4.0)
    >>> step = torch.eye(4)[None]; step[0, 2, 3] = -0.8  # 0.8 m toward a wall 1.25 m away: 2.8x larger
    >>> pred = predict_disparity(d, step, K, b)
    >>> closed = close_cracks(pred, d, torch.ones_like(d), d > 0, step, K, b)
    >>> bool(pred.valid.all()), bool(closed.valid.all())
    (False, True)
    """
    dims = check_shape(key_disparity, ["B", "1", "H", "W"], "key_disparity")
    check_shape(prediction.disparity, ["B", "1", "H", "W"], "prediction.disparity", dims)
    check_shape(motion, ["B", "4", "4"], "motion", dims)
    B, _, H, W = key_disparity.shape
    with torch.no_grad():
        hole = ~prediction.valid[:, 0]
        b_idx, ys, xs = hole.nonzero(as_tuple=True)
        if b_idx.numel() == 0:
            return prediction
        dtype = key_disparity.dtype
        fx, fy, cx, cy = K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]
        # key_T_t in pixel-homogeneous form: h = M (u, v, 1) + m d
        R, t = motion[:, :3, :3].transpose(1, 2), -(motion[:, :3, :3].transpose(1, 2) @ motion[:, :3, 3:])[..., 0]
        zero, one = torch.zeros_like(fx), torch.ones_like(fx)
        Kp = torch.stack([fx, zero, cx, zero, fy, cy, zero, zero, one], -1).view(B, 3, 3)
        Kinv = torch.stack([1 / fx, zero, -cx / fx, zero, 1 / fy, -cy / fy, zero, zero, one], -1).view(B, 3, 3)
        M = (Kp @ R @ Kinv)[b_idx]  # (N, 3, 3)
        m = ((Kp @ t[..., None])[..., 0] / (fx * baseline)[:, None])[b_idx]  # (N, 3)
        pix = torch.stack([xs.to(dtype), ys.to(dtype), torch.ones_like(xs, dtype=dtype)], -1)
        base = (M @ pix[..., None])[..., 0]  # (N, 3)
        flat_d = key_disparity.reshape(-1)
        flat_var = key_variance.reshape(-1)
        flat_ok = key_valid.reshape(-1)
        offset = b_idx * (H * W)

        def look_up(d: torch.Tensor):
            """Keyframe sample at the back-projection of disparity ``d``: (value, variance, ok, h_z)."""
            h = base + m * d[:, None]
            hz = h[:, 2].clamp_min(_MIN_DEPTH_RATIO)
            sx, sy = h[:, 0] / hz, h[:, 1] / hz
            inside = (h[:, 2] > _MIN_DEPTH_RATIO) & (sx >= 0) & (sy >= 0) & (sx <= W - 1) & (sy <= H - 1)
            x0 = sx.clamp(0, W - 1).floor().clamp_max(W - 2).long()
            y0 = sy.clamp(0, H - 1).floor().clamp_max(H - 2).long()
            fx_, fy_ = (sx - x0).clamp(0, 1), (sy - y0).clamp(0, 1)
            corners = [offset + (y0 + j) * W + (x0 + i) for j in (0, 1) for i in (0, 1)]
            weights = [(1 - fx_) * (1 - fy_), fx_ * (1 - fy_), (1 - fx_) * fy_, fx_ * fy_]
            vals = torch.stack([flat_d[c] for c in corners])
            ok = inside & torch.stack([flat_ok[c] for c in corners]).all(0)
            ok &= (vals.amax(0) - vals.amin(0)) <= surface_tolerance
            w = torch.stack(weights)
            value = (w * vals).sum(0)
            var = (w * torch.stack([flat_var[c] for c in corners])).sum(0)
            return value, var, ok, hz

        d = prediction.disparity[b_idx, 0, ys, xs]
        step = torch.full_like(d, float("inf"))
        ok = torch.ones_like(d, dtype=torch.bool)
        for _ in range(max(1, int(iterations))):
            value, var, sample_ok, hz = look_up(d)
            new = value * hz  # d' = d_k / q_z with q_z = 1 / h_z (eq. 1)
            step = (new - d).abs()
            ok &= sample_ok
            d = torch.where(sample_ok, new, d)
        accept = ok & (step <= tolerance)
        var = var * hz * hz + process_noise
        disparity = prediction.disparity.clone()
        variance = prediction.variance.clone()
        valid = prediction.valid.clone()
        keep = ~accept
        disparity[b_idx, 0, ys, xs] = torch.where(accept, d, disparity[b_idx, 0, ys, xs])
        variance[b_idx, 0, ys, xs] = torch.where(accept, var, variance[b_idx, 0, ys, xs])
        valid[b_idx, 0, ys, xs] = accept | (keep & valid[b_idx, 0, ys, xs])
        confidence = torch.where(valid, 1.0 / (1.0 + variance), torch.zeros_like(variance))
    return prediction._replace(disparity=disparity, variance=variance, valid=valid, confidence=confidence)
