"""What went wrong on a frame: the refiner's per-item status flags and the tests that raise them.

A stereo video is not always the smooth, static scene the method assumes: the cameras can be swapped, covered,
blinded or pointed at something new between two frames. The refiner checks for such frames with the cheap tests
below, reports what it found in :attr:`RefinerOutput.status <egorefine.refine.RefinerOutput>`, and recovers:

* the tracks collapse (most features lost at once): a scene change; the motion counts as failed, stereo runs and
  the item restarts from it;
* stereo fails wholesale (far fewer valid pixels than the prediction has, as on swapped, black or noise images):
  the measurement is rejected and the prediction kept;
* stereo and the prediction disagree over whole regions (an occluder, a wrong motion): those regions take the
  measurement. On ordinary frames no region qualifies, so the paper's gate-and-gain rule is left as it is.

Example:
    >>> live_before, live_after = torch.tensor([300, 300]), torch.tensor([280, 20])
    >>> tracking_collapsed(live_before, live_after).tolist()
    [False, True]
    >>> Status(int(Status.MOTION_FAILED | Status.SCENE_CHANGE))
    <Status.MOTION_FAILED|SCENE_CHANGE: 6>
"""

from __future__ import annotations

import enum

import numpy as np
import torch
import torch.nn.functional as F

from ..core import use_compiled
from . import _health_numba

__all__ = [
    "Status",
    "flag",
    "tracking_collapsed",
    "exposure_jumped",
    "stereo_failed",
    "count_per_item",
    "disagreeing_regions",
]

# A scene change: fewer than this share of the live tracks survive one frame (ordinary frames keep most of them;
# a swapped, covered or blinded camera keeps few), counted only where there were enough tracks to lose.
COLLAPSE_SHARE = 0.25
COLLAPSE_MIN_TRACKS = 20
# An exposure jump: the mean brightness changes by more than this factor between two frames.
EXPOSURE_RATIO = 1.3
# Stereo failed wholesale: it marks fewer than this share of the pixels the prediction has valid.
STEREO_FAILURE_SHARE = 0.5
# Mass disagreement: in a tile of this size, more than this share of the pixels both maps hold differ by more than
# this many px, counting tiles where at least MIN_SUPPORT of the pixels are valid in both.
DISAGREEMENT_TILE = 8
DISAGREEMENT_SHARE = 0.5
DISAGREEMENT_PX = 1.0
DISAGREEMENT_MIN_SUPPORT = 0.25


class Status(enum.IntFlag):
    """Per-item flags of one frame (bits of :attr:`RefinerOutput.status <egorefine.refine.RefinerOutput>`).

    Attributes:
        OK: nothing unusual.
        STEREO_FORCED: stereo ran off its schedule (a motion failure, or the adaptive schedule).
        MOTION_FAILED: the ego-motion could not be estimated; the item restarted from stereo where stereo ran.
        SCENE_CHANGE: most tracks were lost at once; handled as a motion failure.
        MEASUREMENT_REJECTED: stereo failed wholesale; the prediction was kept.
        PREDICTION_RESET: some regions disagreed with stereo as a whole and took the measurement.
        EXPOSURE_JUMP: the mean brightness jumped between two frames.

    The flags of one item combine with ``|``; a ``status`` tensor is tested bit by bit with ``&``.

    Example:
        >>> status = torch.tensor([0, int(Status.STEREO_FORCED | Status.MOTION_FAILED)])  # two items' status
        >>> (status & Status.MOTION_FAILED).bool().tolist()
        [False, True]
        >>> Status.STEREO_FORCED in Status(int(status[1])), Status(2).name
        (True, 'MOTION_FAILED')
    """

    OK = 0
    STEREO_FORCED = 1
    MOTION_FAILED = 2
    SCENE_CHANGE = 4
    MEASUREMENT_REJECTED = 8
    PREDICTION_RESET = 16
    EXPOSURE_JUMP = 32


def flag(mask: torch.Tensor, bit: Status) -> torch.Tensor:
    """``(B,)`` int64: ``bit`` where ``mask`` ``(B,)`` is True, 0 elsewhere (to ``|`` into a status)."""
    return torch.where(mask, int(bit), 0).to(torch.int64)


def tracking_collapsed(live_before: torch.Tensor, live_after: torch.Tensor) -> torch.Tensor:
    """``(B,)`` bool: fewer than :data:`COLLAPSE_SHARE` of ``live_before`` tracks survive into ``live_after``.

    Args:
        live_before, live_after: ``(B,)`` live-track counts before and after tracking one frame.
    """
    enough = live_before >= COLLAPSE_MIN_TRACKS
    return enough & (live_after.to(torch.float64) < COLLAPSE_SHARE * live_before.to(torch.float64))


def exposure_jumped(previous: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
    """``(B,)`` bool: the mean brightness of ``current`` differs from ``previous``'s by more than
    :data:`EXPOSURE_RATIO` (either way).

    Args:
        previous, current: ``(B, 1, h, w)`` images (the tracker's coarsest pyramid levels are enough).
    """
    tiny = torch.finfo(current.dtype).tiny
    a = previous.detach().mean((1, 2, 3)).clamp_min(tiny)
    b = current.detach().mean((1, 2, 3)).clamp_min(tiny)
    ratio = torch.maximum(a / b, b / a)
    return ratio > EXPOSURE_RATIO


def stereo_failed(measured_valid: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """``(B,)`` bool: stereo marks fewer than :data:`STEREO_FAILURE_SHARE` of the reference's pixels.

    Args:
        measured_valid: ``(B, 1, H, W)`` bool, the matcher's matches.
        reference: ``(B, 1, H, W)`` bool, the pixels the prediction holds, or ``(B,)`` int64, a count of them
            (the matcher's own count at the last verification, when a fill makes the prediction denser than it).

    Example:
        >>> meas = torch.zeros(2, 1, 2, 2, dtype=torch.bool)
        >>> meas[0] = True
        >>> stereo_failed(meas, torch.ones(2, 1, 2, 2, dtype=torch.bool)).tolist()
        [False, True]
        >>> stereo_failed(meas, torch.tensor([9, 0])).tolist()  # 4 < 0.5 * 9
        [True, False]
    """
    expected = count_per_item(reference) if reference.dtype == torch.bool else reference
    return count_per_item(measured_valid).to(torch.float64) < STEREO_FAILURE_SHARE * expected.to(torch.float64)


def count_per_item(mask: torch.Tensor) -> torch.Tensor:
    """``(B,)`` int64: the True pixels of each item of a ``(B, ...)`` bool mask.

    CPU masks are counted with numpy, item by item: a torch reduction over a full map would wake torch's OpenMP
    threads, which then spin beside the compiled kernels of the next stage (and numpy counts a whole array much
    faster than along an axis).
    """
    if mask.device.type == "cpu":
        flat = mask.detach().reshape(mask.shape[0], -1).numpy()
        return torch.tensor([np.count_nonzero(item) for item in flat], dtype=torch.int64)
    return mask.flatten(1).sum(1)


def disagreeing_regions(
    predicted: torch.Tensor, predicted_valid: torch.Tensor, measured: torch.Tensor, measured_valid: torch.Tensor
) -> torch.Tensor:
    """``(B, 1, H, W)`` bool: the tiles where stereo and the prediction disagree as a whole.

    A tile of :data:`DISAGREEMENT_TILE` px qualifies where over :data:`DISAGREEMENT_SHARE` of the pixels valid in
    both maps differ by more than :data:`DISAGREEMENT_PX`, and at least :data:`DISAGREEMENT_MIN_SUPPORT` of its
    pixels are valid in both. The decision is piecewise constant (no gradient flows through it). Float32 CPU maps
    with bool masks take a compiled pass (:mod:`egorefine.refine._health_numba`), others the rule in torch.

    Args:
        predicted, measured: ``(B, 1, H, W)`` disparity, px.
        predicted_valid, measured_valid: ``(B, 1, H, W)`` bool.

    Example:
        >>> e = torch.full((1, 1, 32, 32), 5.0)
        >>> s = e.clone(); s[..., :8, :8] = 9.0  # one tile off by 4 px
        >>> ok = torch.ones_like(e, dtype=torch.bool)
        >>> disagreeing_regions(e, ok, s, ok)[0, 0, ::8, ::8].tolist()[:2]
        [[True, False, False, False], [False, False, False, False]]
    """
    # (the kernel reads bool masks; no gradient flows through the decision, so one wanted through the maps is none)
    if predicted_valid.dtype == measured_valid.dtype == torch.bool and use_compiled(
            predicted.detach(), predicted_valid, measured.detach(), measured_valid):
        return _health_numba.disagreeing_regions(predicted, predicted_valid, measured, measured_valid,
                                                 DISAGREEMENT_TILE, DISAGREEMENT_PX, DISAGREEMENT_MIN_SUPPORT,
                                                 DISAGREEMENT_SHARE)
    H, W = predicted.shape[-2:]
    with torch.no_grad():
        both = predicted_valid & measured_valid
        off = both & ((predicted - measured).abs() > DISAGREEMENT_PX)
        tile = DISAGREEMENT_TILE
        support = F.avg_pool2d(both.to(predicted.dtype), tile, tile, ceil_mode=True)
        share_off = F.avg_pool2d(off.to(predicted.dtype), tile, tile, ceil_mode=True)
        region = (support >= DISAGREEMENT_MIN_SUPPORT) & (share_off > DISAGREEMENT_SHARE * support)
        return region.repeat_interleave(tile, -2).repeat_interleave(tile, -1)[..., :H, :W]
