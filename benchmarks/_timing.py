"""The loop's timer, shared by benchmarks/refine.py and benchmarks/speed.py, and a per-stage profiler.

:func:`run_loop` times every frame of one pass of an :class:`~egorefine.refine.EgoMotionRefiner` over a sequence
(the wall time of ``refiner(...)``, nothing else). With a :class:`StageProfiler` it also splits each frame's time
into the stages the refiner calls: the profiler wraps the functions the refiner looks up in its modules (its own
code is not changed) and books each call's *exclusive* time, its wall time less that of the wrapped calls inside
it, to the stage's label. What no wrapper covers is the frame's ``bookkeeping``.
"""

from __future__ import annotations

import dataclasses
import time
from collections import defaultdict
from collections.abc import Callable, Iterable

import torch

from egorefine.data import StereoSequence
from egorefine.refine import EgoMotionRefiner
from egorefine.refine import cracks as _cracks_module
from egorefine.refine import refiner as _refiner_module
from egorefine.stereo import matching as _matching_module

BOOKKEEPING = "bookkeeping"

# (namespace, attribute, stage label) of what a refiner frame calls, in the order of the stage tables. A label in
# ABSORBING keeps the time of wrapped calls made inside it (the fill's own match_stereo is the fill's time).
STAGES: list[tuple[object, str, str]] = [
    (EgoMotionRefiner, "_check_inputs", "checks"),
    (_refiner_module, "to_grey", "checks"),
    (_refiner_module, "build_pyramid", "pyramid"),
    (_refiner_module, "_expected_positions", "tracking"),
    (_refiner_module, "track", "tracking"),
    (_refiner_module, "solve_ego_motion", "motion solve"),
    (_refiner_module, "predict_finished", "prediction splat"),  # (with crack closing where they run fused)
    (_cracks_module, "finish_prediction", "crack closing"),  # (where they do not)
    (_refiner_module, "_confidence", "confidence"),
    (_refiner_module, "replenish", "feature top-up"),
    (_refiner_module, "match_stereo", "box matcher"),
    (_matching_module, "remove_speckles", "speckle filter"),
    (_matching_module, "remove_speckles_cleared_", "speckle filter"),  # (the compiled path: the maps cleared too)
    (_refiner_module, "_fill_matcher", "census+SGM fill"),
    (_refiner_module, "fill_invalid", "census+SGM fill"),
    (EgoMotionRefiner, "_correct", "correction"),
    (_refiner_module, "tracking_collapsed", "health checks"),
    (_refiner_module, "exposure_jumped", "health checks"),
    (_refiner_module, "stereo_failed", "health checks"),
    (_refiner_module, "disagreeing_regions", "health checks"),
    (_refiner_module, "count_per_item", "health checks"),
    (_refiner_module, "_overrule", "health checks"),
    (_refiner_module, "match_residual", "local search"),
    (_refiner_module, "match_stereo_regions", "hole search"),
    (_refiner_module, "_take_hole_measurements", "hole search"),
]
ABSORBING = {"census+SGM fill"}


def stage_labels() -> list[str]:
    """The stage labels in table order, ``bookkeeping`` last."""
    return list(dict.fromkeys(label for _, _, label in STAGES)) + [BOOKKEEPING]


class StageProfiler:
    """Exclusive milliseconds per stage label while active (``with StageProfiler() as prof:``).

    ``prof.take()`` returns and clears what was booked since the last ``take``. Wrappers cost a few microseconds a
    call, against frames of milliseconds.
    """

    def __init__(self, stages: Iterable[tuple[object, str, str]] = STAGES) -> None:
        self.stages = list(stages)
        self.booked: dict[str, float] = defaultdict(float)
        self._stack: list[list] = []  # [label, seconds spent in wrapped calls inside]
        self._saved: list[tuple[object, str, object]] = []

    def _wrap(self, fn: Callable, label: str) -> Callable:
        def timed(*args, **kwargs):
            outer = next((f[0] for f in reversed(self._stack) if f[0] in ABSORBING), None)
            frame = [outer or label, 0.0]
            self._stack.append(frame)
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                elapsed = time.perf_counter() - t0
                self._stack.pop()
                self.booked[frame[0]] += (elapsed - frame[1]) * 1e3
                if self._stack:
                    self._stack[-1][1] += elapsed

        return timed

    def __enter__(self) -> StageProfiler:
        for owner, name, label in self.stages:
            original = owner.__dict__[name] if isinstance(owner, type) else getattr(owner, name)
            self._saved.append((owner, name, original))
            setattr(owner, name, self._wrap(original, label))
        return self

    def __exit__(self, *exc) -> None:
        for owner, name, original in reversed(self._saved):
            setattr(owner, name, original)
        self._saved.clear()

    def take(self) -> dict[str, float]:
        booked, self.booked = dict(self.booked), defaultdict(float)
        return booked


@dataclasses.dataclass
class LoopRun:
    """One timed pass: per-frame disparity and validity ``(T, 1, 1, H, W)``, ms, whether stereo ran, stage ms."""

    disparity: torch.Tensor
    valid: torch.Tensor
    ms: list[float]
    stereo: list[bool]
    stages: list[dict[str, float]]


def run_loop(refiner: EgoMotionRefiner, seq: StereoSequence, frames: range | None = None,
             profiler: StageProfiler | None = None, between: Callable[[int], None] | None = None) -> LoopRun:
    """Run ``refiner`` over ``seq`` from a fresh state, timing each frame's call.

    Args:
        refiner: the loop.
        seq: the sequence (batch of one).
        frames: the frames to time (default: all); earlier frames run untimed to build the state.
        profiler: an active :class:`StageProfiler`, to split each timed frame into stages (``bookkeeping`` is the
            frame's time no stage holds).
        between: called with the frame index before each timed frame (other methods timed interleaved with it).
    """
    frames = range(len(seq)) if frames is None else frames
    K, b = seq.K[None], torch.tensor([seq.baseline])
    state, disp, valid, ms, stereo, stages = None, [], [], [], [], []
    for t in range(frames.stop):
        if t < frames.start:
            _, state = refiner(seq.left[t : t + 1], seq.right[t : t + 1], K, b, state)
            continue
        if between is not None:
            between(t)
        if profiler is not None:
            profiler.take()
        t0 = time.perf_counter()
        out, state = refiner(seq.left[t : t + 1], seq.right[t : t + 1], K, b, state)
        elapsed = (time.perf_counter() - t0) * 1e3
        ms.append(elapsed)
        if profiler is not None:
            booked = profiler.take()
            booked[BOOKKEEPING] = elapsed - sum(booked.values())
            stages.append(booked)
        disp.append(out.disparity)
        valid.append(out.valid)
        stereo.append(bool(out.stereo_ran))
    return LoopRun(torch.cat(disp), torch.cat(valid), ms, stereo, stages)
