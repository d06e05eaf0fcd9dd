"""Run :class:`~egorefine.refine.EgoMotionRefiner` over a whole stereo video: :func:`refine_sequence`."""

from __future__ import annotations

from typing import NamedTuple

import torch

from ..core import DTypeError, ShapeError, check_shape, progress
from .refiner import EgoMotionRefiner

__all__ = ["SequenceResult", "refine_sequence"]


class SequenceResult(NamedTuple):
    """Per-frame outputs of :func:`refine_sequence`, stacked along a leading time axis.

    Attributes:
        disparity: ``(T, B, 1, H, W)``.
        valid: ``(T, B, 1, H, W)`` bool.
        motion: ``(T, B, 4, 4)`` ``camera_t_T_camera_{t-1}`` (identity at t = 0).
        stereo_ran: ``(T,)`` bool.
        variance: ``(T, B, 1, H, W)``.
        confidence: ``(T, B, 1, H, W)``.
        motion_ok: ``(T, B)`` bool.
        num_tracks: ``(T, B)`` features tracked into each frame.
        status: ``(T, B)`` int64 :class:`~egorefine.refine.health.Status` bits of each frame.

    Example:
        >>> from egorefine.data import render_sequence
        >>> from egorefine.refine import TrackingOptions
        >>> seq = render_sequence(num_frames=3, height=40, width=56)
        >>> res = refine_sequence(seq.left, seq.right, seq.K, seq.baseline, max_disparity=8,
        ...                       tracking=TrackingOptions(max_features=64, min_tracks=16))
        >>> res.motion.shape, res.motion_ok.shape, res.status.shape  # frame t of item b: res.motion[t, b]
        (torch.Size([3, 1, 4, 4]), torch.Size([3, 1]), torch.Size([3, 1]))
        >>> torch.equal(res.motion[0, 0], torch.eye(4)), res.stereo_ran.tolist()  # verify_every=5
        (True, [True, False, False])
    """

    disparity: torch.Tensor
    valid: torch.Tensor
    motion: torch.Tensor
    stereo_ran: torch.Tensor
    variance: torch.Tensor
    confidence: torch.Tensor
    motion_ok: torch.Tensor
    num_tracks: torch.Tensor
    status: torch.Tensor


def refine_sequence(
    lefts: torch.Tensor,
    rights: torch.Tensor,
    K: torch.Tensor,
    baseline: torch.Tensor,
    verify_every: int = 5,
    show_progress: bool = False,
    refiner: EgoMotionRefiner | None = None,
    **options,
) -> SequenceResult:
    """Run :class:`EgoMotionRefiner` over a whole stereo video.

    Args:
        lefts: ``(T, B, C, H, W)`` left images (``(T, C, H, W)`` is read as B = 1).
        rights: right images of the same shape (only verification frames are read).
        K: ``(B, 3, 3)`` (or ``(3, 3)``) intrinsics; baseline ``(B,)`` (or a float) metres.
        verify_every: stereo every i-th frame.
        show_progress: show a progress bar on stderr.
        refiner: a configured refiner to use instead of building one from ``options``.
        **options: keyword arguments of :class:`EgoMotionRefiner`.

    Returns:
        :class:`SequenceResult`.

    Example:
        >>> from egorefine.data import render_sequence
        >>> from egorefine.refine import TrackingOptions
        >>> seq = render_sequence(num_frames=3, height=40, width=56)
        >>> res = refine_sequence(seq.left, seq.right, seq.K, seq.baseline, verify_every=2, max_disparity=8,
        ...                       tracking=TrackingOptions(max_features=64, min_tracks=16))
        >>> res.disparity.shape, res.valid.shape, res.stereo_ran.tolist()  # (T, B, 1, H, W); stereo on 0 and 2
        (torch.Size([3, 1, 1, 40, 56]), torch.Size([3, 1, 1, 40, 56]), [True, False, True])
    """
    for name, t in (("lefts", lefts), ("rights", rights)):
        if not isinstance(t, torch.Tensor):
            raise DTypeError(f"{name}: expected a torch.Tensor, got {type(t).__name__} (use torch.as_tensor)")
    if lefts.dim() == 4:
        lefts, rights = lefts[:, None], rights[:, None]
    check_shape(lefts, ["T", "B", "1|3", "H", "W"], "lefts")
    if lefts.shape[0] == 0:
        raise ShapeError(f"lefts: expected at least one frame, got shape {tuple(lefts.shape)}")
    if rights.shape != lefts.shape:
        raise ShapeError(f"rights: expected the shape of lefts {tuple(lefts.shape)}, got {tuple(rights.shape)}")
    T, B = lefts.shape[:2]
    if K.dim() == 2:
        K = K.expand(B, 3, 3)
    if not isinstance(baseline, torch.Tensor) or baseline.dim() == 0:
        baseline = torch.full((B,), float(baseline), device=lefts.device, dtype=lefts.dtype)
    refiner = EgoMotionRefiner(verify_every=verify_every, **options) if refiner is None else refiner
    outs = []
    state = None
    for t in progress(range(T), desc="refine_sequence", enabled=show_progress):
        out, state = refiner(lefts[t], rights[t], K, baseline, state)
        outs.append(out)
    return SequenceResult(
        torch.stack([o.disparity for o in outs]),
        torch.stack([o.valid for o in outs]),
        torch.stack([o.motion for o in outs]),
        torch.tensor([o.stereo_ran for o in outs], device=lefts.device),
        torch.stack([o.variance for o in outs]),
        torch.stack([o.confidence for o in outs]),
        torch.stack([o.motion_ok for o in outs]),
        torch.stack([o.num_tracks for o in outs]),
        torch.stack([o.status for o in outs]),
    )
