"""Per-frame steps of :class:`~egorefine.refine.EgoMotionRefiner` that are not stages of their own: the confidence
map, taking hole measurements, the recovery rules of a verification, and the constant-velocity guess of where
the features land. Each has a compiled CPU form beside its torch rule (:func:`egorefine.core.use_compiled`)."""

from __future__ import annotations

import torch

from ..core import use_compiled
from ..geometry import disparity_to_depth, project, transform_points, unproject
from ..stereo import StereoOutput
from . import _fuse_numba, _predict_numba
from .predict import Prediction


def _confidence(valid: torch.Tensor, variance: torch.Tensor) -> torch.Tensor:
    """``1 / (1 + variance)`` on valid pixels, 0 elsewhere: the same meaning on every frame (as in predict).
    Float32 CPU maps without gradient take a compiled pass (no full-map torch op to wake torch's OpenMP threads)."""
    if valid.dtype == torch.bool and use_compiled(valid, variance):  # (the kernel reads a bool mask)
        return _fuse_numba.confidence(valid, variance)
    return valid.to(variance.dtype) / (1.0 + variance)


def _take_hole_measurements(
    disparity: torch.Tensor,
    variance: torch.Tensor,
    valid: torch.Tensor,
    outliers: torch.Tensor,
    meas: StereoOutput,
    pred: Prediction,
    max_variance: float,
    background_margin: float | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The loop's map with stereo measurements of its holes (``~valid``) taken: new ``(disparity, variance, valid,
    outliers, confidence)``.

    A valid measurement of a hole pixel is taken where its variance is at most ``max_variance``, or, with a
    ``background_margin``, where the pixel is one of the splat's holes (``pred.hole``, whose ``pred.disparity`` is
    the background fill of :func:`~egorefine.refine.fill_holes_background`) and the measurement lies at most
    ``background_margin`` px above that fill. A hole the motion uncovers shows the background, and the matcher's
    usual error there is the foreground's disparity spilling over the edge: a value on the background's side
    of the fill is plausible even where the cost curve is flat. A taken pixel gets the measurement's value and
    variance and a zero outlier count. Float32 CPU maps without gradient take one compiled pass
    (:func:`egorefine.refine._fuse_numba.take_measurements`), others the same rule in torch.
    """
    if use_compiled(disparity, variance, valid, outliers, meas.disparity, meas.variance, meas.valid, pred.disparity,
                    pred.hole):
        return _fuse_numba.take_measurements(disparity, variance, valid, outliers, meas.disparity, meas.variance,
                                             meas.valid, pred.disparity, pred.hole, max_variance, background_margin)
    take = meas.variance <= max_variance
    if background_margin is not None:
        take = take | (pred.hole & (meas.disparity <= pred.disparity + background_margin))
    take = ~valid & meas.valid & take
    variance = torch.where(take, meas.variance, variance)
    valid = valid | take
    return (torch.where(take, meas.disparity, disparity), variance, valid,
            torch.where(take, torch.zeros_like(outliers), outliers), _confidence(valid, variance))


def _owned(maps: tuple[torch.Tensor, ...], *others: object) -> bool:
    """Whether no tensor among ``others`` (tensors, or tuples of them, e.g. a state or a prediction; anything else
    skipped) shares memory with one of ``maps``, nor two of ``maps`` with each other: then a kernel may write
    ``maps`` in place without changing what ``others`` hold."""
    storages = [m.untyped_storage().data_ptr() for m in maps]
    if len(set(storages)) < len(storages):
        return False
    seen = set()
    for item in others:
        for t in item if isinstance(item, tuple) else (item,):
            if isinstance(t, torch.Tensor):
                seen.add(t.untyped_storage().data_ptr())
    return not set(storages) & seen


def _overrule(
    maps: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor],
    pred: Prediction,
    meas: StereoOutput,
    keep: torch.Tensor,
    restart: torch.Tensor,
    regions: torch.Tensor,
    owned: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The corrected ``(disparity, variance, valid, outliers)`` with the recovery rules of a verification applied:
    items in ``restart`` ``(B,)`` take the measurement whole (their motion failed), items in ``keep`` ``(B,)`` the
    prediction whole (their stereo failed), and elsewhere the pixels of ``regions`` ``(B, 1, H, W)`` take the
    measurement; taken pixels get a zero outlier count. Float32 CPU maps without gradient take one compiled pass
    per map (:func:`egorefine.refine._fuse_numba.overrule`), others the same rule in torch. ``owned``: ``maps``
    are the caller's alone (no other tensor shares their memory), so the compiled pass may write them in place
    (no fresh maps to fault in)."""
    disparity, variance, valid, outliers = maps
    masks = (valid, pred.valid, meas.valid, regions, keep, restart)
    if all(m.dtype == torch.bool for m in masks) and use_compiled(  # (the kernel reads bool masks)
            disparity, variance, outliers, pred.disparity, pred.variance, meas.disparity, meas.variance, *masks):
        inplace = owned and all(m.is_contiguous() for m in maps)
        return _fuse_numba.overrule(maps, (pred.disparity, pred.variance, pred.valid),
                                    (meas.disparity, meas.variance, meas.valid), keep, restart, regions,
                                    inplace=inplace)
    item_keep, item_restart = keep[:, None, None, None], restart[:, None, None, None]
    take = (regions & ~item_keep) | item_restart

    def pick(corrected, predicted, measured):
        return torch.where(item_restart, measured, torch.where(item_keep, predicted, torch.where(take, measured,
                                                                                                 corrected)))

    return (pick(disparity, pred.disparity, meas.disparity), pick(variance, pred.variance, meas.variance),
            pick(valid, pred.valid, meas.valid),
            torch.where(take | item_keep, torch.zeros_like(outliers), outliers))


def _sample(disparity: torch.Tensor, valid: torch.Tensor, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear samples ``(B, N)`` of ``disparity`` ``(B, 1, H, W)`` at pixel positions ``(B, N, 2)`` (clamped to the
    image), and whether all four pixels they blend are ``valid``: a gather of the four corners, not a pass over the
    maps (a full-map torch op wakes torch's OpenMP threads, which then spin beside the compiled tracker)."""
    B, _, H, W = disparity.shape
    x, y = points.unbind(-1)
    x0 = x.floor().clamp(0, max(W - 2, 0))
    y0 = y.floor().clamp(0, max(H - 2, 0))
    fx, fy = (x - x0).clamp(0, 1), (y - y0).clamp(0, 1)
    first = (y0 * W + x0).long()
    dx, dy = min(1, W - 1), min(1, H - 1) * W
    idx = torch.stack([first, first + dx, first + dy, first + dy + dx], dim=-1).view(B, -1)
    d = disparity.reshape(B, H * W).gather(1, idx).view(B, -1, 4)
    ok = valid.reshape(B, H * W).gather(1, idx).view(B, -1, 4).all(-1)
    top = d[..., 0] + fx * (d[..., 1] - d[..., 0])
    bottom = d[..., 2] + fx * (d[..., 3] - d[..., 2])
    return top + fy * (bottom - top), ok


def _expected_positions(
    keypoints: torch.Tensor,
    disparity: torch.Tensor,
    valid: torch.Tensor,
    motion: torch.Tensor,
    K: torch.Tensor,
    baseline: torch.Tensor,
) -> torch.Tensor:
    """Where ``keypoints`` land if the rig repeats ``motion`` (constant velocity): centres the track search.
    Points whose four neighbouring pixels are not all valid keep their position."""
    H, W = disparity.shape[-2:]
    if valid.dtype == torch.bool and use_compiled(keypoints, disparity, valid, motion, K, baseline):  # (a bool mask)
        # compiled: some forty torch ops on a few hundred points cost more in launches than in arithmetic
        return _predict_numba.expected_positions(keypoints.contiguous(), disparity[:, 0].contiguous(),
                                                 valid[:, 0].contiguous(), motion.contiguous(), K.contiguous(),
                                                 baseline.contiguous())
    d, ok = _sample(disparity, valid, keypoints)
    ok = ok & (d > 0)
    depth = disparity_to_depth(d, K[:, 0, 0], baseline)
    points = transform_points(motion, unproject(keypoints, depth, K))
    moved = project(points, K)
    inside = (moved[..., 0] >= 0) & (moved[..., 0] <= W - 1) & (moved[..., 1] >= 0) & (moved[..., 1] <= H - 1)
    ok = ok & inside & (points[..., 2] > 0) & torch.isfinite(moved).all(-1)
    return torch.where(ok[..., None], moved, keypoints)
