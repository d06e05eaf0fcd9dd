"""The refiner's settings, grouped by the stage they act on.

:class:`~egorefine.refine.EgoMotionRefiner` keeps its common settings as plain arguments (``max_disparity``,
``verify_every``, ``fusion``, ``motion_method``) and takes the rest as one small frozen dataclass per stage:

* :class:`StereoOptions`: the matcher run on verification frames;
* :class:`TrackingOptions`: the feature budget and the tracker;
* :class:`PredictionOptions`: the splat, crack closing and the process noise;
* :class:`CorrectionOptions`: the paper rule's gate and gain and the Kalman rule's gate, reset and variances;
* :class:`SearchOptions`: the measurements between verifications (residual search, hole measurement);
* :class:`ScheduleOptions`: extra stereo runs where the prediction looks weak.

Each validates its fields when built, so a bad value fails where it is written. The flat keywords of earlier
releases (``EgoMotionRefiner(max_features=64, local_search=2)``) still work for one release and warn
(:data:`LEGACY_KEYWORDS` maps each to its group and field).

Example:
    >>> from egorefine.refine import EgoMotionRefiner
    >>> r = EgoMotionRefiner(max_disparity=32, fusion="kalman", tracking=TrackingOptions(max_features=64,
    ...                      min_tracks=16), search=SearchOptions(local_search=2))
    >>> r.tracking.max_features, r.search.local_search
    (64, 2)
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

from ..core import ValueRangeError, check_choice

__all__ = [
    "StereoOptions",
    "TrackingOptions",
    "PredictionOptions",
    "CorrectionOptions",
    "SearchOptions",
    "ScheduleOptions",
    "LEGACY_KEYWORDS",
]


def _odd(value: int, name: str) -> None:
    if int(value) != value or value < 1 or value % 2 == 0:
        raise ValueRangeError(f"{name}: expected a positive odd integer, got {value}")


def _at_least(value: float, low: float, name: str) -> None:
    if not float(value) >= low:
        raise ValueRangeError(f"{name}: expected a number >= {low:g}, got {value}")


@dataclass(frozen=True)
class StereoOptions:
    """The matcher of verification frames (:func:`egorefine.stereo.match_stereo`); None: the matcher's default.

    Attributes:
        min_disparity: smallest candidate, px (>= 0); the refiner's range is ``[min_disparity, max_disparity)``.
        block_size: odd window size of the cost aggregation.
        cost: ``"sad"``, ``"zncc"`` or ``"census"``.
        aggregation: ``"box"`` or ``"sgm"``.
        subpixel: the sub-pixel fit through the winner's neighbours (False: the paper's integer disparities).
        temperature: the soft-argmin's temperature in cost units (``differentiable=True``; None: the matcher's
            default for its cost).
        uniqueness_ratio: reject a winner whose cost is not this share below the runner-up's (0: no test).
        speckle_size: connected regions of fewer pixels are removed (0: no speckle filter).
        speckle_range: px, neighbours closer than this belong to one region of the speckle filter.
        lr_threshold: px, the left-right check's tolerance.
        fill: where the matcher finds no match, take the match of :meth:`dense`'s census + SGM matcher
            (:func:`~egorefine.stereo.fill_invalid`). None: on in Kalman mode with a box matcher (the filter keeps
            the box matcher's accurate, noise-dominated values where it has them and gains SGM's density; the
            stereo frames cost the SGM run more), off in paper mode (the paper's block matching) and with
            ``differentiable=True`` (census is piecewise constant in the images).
        fill_band: None (the default): the fill searches the full range. An int >= 3: at a verification frame
            after the first, the fill searches only ``fill_band`` disparities around the predicted one
            (``egorefine.stereo.band.match_sgm_band``, the fill's matcher without its left-right check), which finds
            the truth where the prediction is off by up to about ``fill_band / 2 - 1`` px; the first frame, and an
            item whose ego-motion failed (its prediction is meaningless), get the full-range fill. The first matcher
            still searches the full range at every verification, so every pixel keeps a full-range measurement: a
            missing or invalid prediction never yields a stale value. Off by default: without the left-right check
            the banded fill keeps wrong matches the full one rejects, and the loop's error grows
            (docs/decisions.md, "A banded fill").
        fill_margin: at a verification frame after the first, the full-range fill searches disparities only up to
            the prediction's largest value plus ``fill_margin`` px (the count rounded up to a multiple of 32, which
            the compiled kernel runs fastest), not up to ``max_disparity``: nothing in view is nearer than the
            prediction says but what entered since the last verification, and the first matcher still searches
            the full range for it. The first frame, a frame where some item's ego-motion failed and a band fill
            (``fill_band``) search the full range. None: always the full range.
        fill_scale: 2 (the default): the full-range fill matches the pair at half resolution
            (:func:`~egorefine.stereo.match_half_resolution`: an eighth of the work; in the weakly textured
            holes it fills, a window twice the size matches more of them; docs/decisions.md, "A half-resolution
            fill"). 1: at full resolution.

    Example:
        >>> StereoOptions(cost="census", aggregation="sgm").matcher_options()  # the rest: the matcher's defaults
        {'cost': 'census', 'aggregation': 'sgm'}
        >>> StereoOptions(block_size=4)
        Traceback (most recent call last):
        ...
        egorefine.core.errors.ValueRangeError: block_size: expected a positive odd integer, got 4
        >>> StereoOptions().fill_band, StereoOptions(fill_band=16).fill_band  # None: the fill's full range
        (None, 16)
        >>> StereoOptions().fill_margin, StereoOptions(fill_margin=None).fill_margin
        (8, None)
        >>> StereoOptions().fill_scale, StereoOptions(fill_scale=1).fill_scale
        (2, 1)
    """

    min_disparity: int = 0
    block_size: int | None = None
    cost: str | None = None
    aggregation: str | None = None
    subpixel: bool | None = None
    temperature: float | None = None
    uniqueness_ratio: float | None = None
    speckle_size: int | None = None
    speckle_range: float | None = None
    lr_threshold: int | None = None
    fill: bool | None = None
    fill_band: int | None = None
    fill_margin: int | None = 8
    fill_scale: int = 2

    def __post_init__(self) -> None:
        if int(self.min_disparity) != self.min_disparity or self.min_disparity < 0:
            raise ValueRangeError(f"min_disparity: expected an integer >= 0, got {self.min_disparity}")
        if self.block_size is not None:
            _odd(self.block_size, "block_size")
        if self.cost is not None:
            check_choice(self.cost, ("sad", "zncc", "census"), "cost")
        if self.aggregation is not None:
            check_choice(self.aggregation, ("box", "sgm"), "aggregation")
        if self.temperature is not None and not float(self.temperature) > 0:
            raise ValueRangeError(f"temperature: expected > 0 or None, got {self.temperature}")
        if self.uniqueness_ratio is not None and not 0.0 <= float(self.uniqueness_ratio) < 1.0:
            raise ValueRangeError(f"uniqueness_ratio: expected in [0, 1) or None, got {self.uniqueness_ratio}")
        if self.speckle_size is not None and (int(self.speckle_size) != self.speckle_size or self.speckle_size < 0):
            raise ValueRangeError(f"speckle_size: expected an integer >= 0 or None, got {self.speckle_size}")
        if self.speckle_range is not None and not float(self.speckle_range) > 0:
            raise ValueRangeError(f"speckle_range: expected > 0 or None, got {self.speckle_range}")
        if self.lr_threshold is not None and (int(self.lr_threshold) != self.lr_threshold or self.lr_threshold < 0):
            raise ValueRangeError(f"lr_threshold: expected an integer >= 0 or None, got {self.lr_threshold}")
        if self.fill is not None and not isinstance(self.fill, bool):
            raise ValueRangeError(f"fill: expected True, False or None, got {self.fill!r}")
        if self.fill_band is not None and (isinstance(self.fill_band, bool) or int(self.fill_band) != self.fill_band
                                           or self.fill_band < 3):
            raise ValueRangeError(f"fill_band: expected an integer >= 3 or None, got {self.fill_band!r}")
        if self.fill_scale not in (1, 2) or isinstance(self.fill_scale, bool):
            raise ValueRangeError(f"fill_scale: expected 1 (full resolution) or 2 (half), got {self.fill_scale!r}")
        if self.fill_margin is not None and (isinstance(self.fill_margin, bool)
                                             or int(self.fill_margin) != self.fill_margin or self.fill_margin < 0):
            raise ValueRangeError(f"fill_margin: expected an integer >= 0 or None, got {self.fill_margin!r}")

    @classmethod
    def dense(cls) -> StereoOptions:
        """The census + SGM matcher set for density: uniqueness test off, SGBM's speckle range of 2 px and a left-right
        tolerance of 2 px, block 5.

        Stereo runs on one frame in ``verify_every``, so a slower, denser matcher there costs a fraction of its
        time per frame. Kalman mode fills the box matcher's holes with it by default (``fill``); as the only
        matcher (with ``CorrectionOptions(max_unverified_variance=None)``) it gives the loop about per-frame
        SGBM's density at a lower error than SGBM's, but its errors are mostly bias that temporal fusion does not
        average away (docs/decisions.md, "A dense configuration of the loop").

        Example:
            >>> StereoOptions.dense().matcher_options()["aggregation"]
            'sgm'
        """
        return cls(cost="census", aggregation="sgm", block_size=5, uniqueness_ratio=0.0, speckle_range=2.0,
                   lr_threshold=2)

    def matcher_options(self) -> dict:
        """The keyword arguments of :func:`~egorefine.stereo.match_stereo` that were set (None: its default)."""
        named = {"block_size": self.block_size, "cost": self.cost, "aggregation": self.aggregation,
                 "subpixel": self.subpixel, "uniqueness_ratio": self.uniqueness_ratio,
                 "speckle_size": self.speckle_size, "speckle_range": self.speckle_range,
                 "lr_threshold": self.lr_threshold}
        return {k: v for k, v in named.items() if v is not None}


@dataclass(frozen=True)
class TrackingOptions:
    """The features and their tracker (:func:`egorefine.features.track`).

    Attributes:
        max_features: feature slots per image (500: enough for a well-conditioned motion solve on a 640x480
            frame at a few ms of tracking).
        min_tracks: detection re-runs when fewer live tracks remain (200).
        soft: the tracker's soft-argmax last step (None: with ``differentiable=True``).

    Example:
        >>> opts = TrackingOptions(max_features=64, min_tracks=16)  # a small image needs fewer features
        >>> opts.max_features, opts.min_tracks, opts.soft
        (64, 16, None)
        >>> dataclasses.replace(opts, min_tracks=-1)
        Traceback (most recent call last):
        ...
        egorefine.core.errors.ValueRangeError: min_tracks: expected an integer >= 0, got -1
    """

    max_features: int = 500
    min_tracks: int = 200
    soft: bool | None = None

    def __post_init__(self) -> None:
        if int(self.max_features) != self.max_features or self.max_features < 1:
            raise ValueRangeError(f"max_features: expected an integer >= 1, got {self.max_features}")
        if int(self.min_tracks) != self.min_tracks or self.min_tracks < 0:
            raise ValueRangeError(f"min_tracks: expected an integer >= 0, got {self.min_tracks}")


@dataclass(frozen=True)
class PredictionOptions:
    """The prediction (docs/method.md eq. 1, :func:`egorefine.refine.predict_disparity`).

    Attributes:
        splat: ``"hard"`` (z-buffer) or ``"soft"`` (softmax) splatting (None: hard, or soft with
            ``differentiable=True``).
        fill_cracks: look the prediction's holes up in the keyframe: surfaces magnified beyond the splat's tiling
            become valid, disocclusions stay holes.
        process_noise: Kalman mode, px^2 added to the carried variance per predicted frame (0.01: a tenth of a
            pixel of drift per frame, the size of a sub-pixel motion error).

    Example:
        >>> PredictionOptions(splat="soft", process_noise=0.04).process_noise  # a fifth of a pixel per frame
        0.04
        >>> PredictionOptions(splat="bilinear")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        egorefine.core.errors.ValueRangeError: splat: ...
    """

    splat: str | None = None
    fill_cracks: bool = True
    process_noise: float = 0.01

    def __post_init__(self) -> None:
        if self.splat is not None:
            check_choice(self.splat, ("hard", "soft"), "splat")
        _at_least(self.process_noise, 0.0, "process_noise")


@dataclass(frozen=True)
class CorrectionOptions:
    """The correction at verification (docs/method.md step 4, :func:`egorefine.refine.correct_disparity`).

    Attributes:
        gate, gain: the paper rule's 0.5 px gate and 0.4 gain.
        kalman_gate, reset_after: Kalman mode: a measurement beyond ``kalman_gate`` standard deviations is an
            outlier; the pixel takes it after ``reset_after`` such verifications in a row (1 and 1: with keyframe
            prediction a disagreement is mostly the prediction's error, which its variance does not model).
        edge_aware, edge_kernel: Kalman mode adds the prediction's depth-edge variance over an ``edge_kernel``
            window, so that the measurement wins at the edges the splat places only to within a pixel.
        max_unverified_variance: Kalman mode, px^2: a prediction stereo did not measure stays valid only while its
            variance is at most this (``0.25^2``: a standard deviation of half the paper's gate; None: always).
        gate_softness: logistic gates (px in paper mode, standard deviations in Kalman mode; None: hard, or 0.1
            with ``differentiable=True``).

    Example:
        >>> opts = CorrectionOptions(kalman_gate=2.0, reset_after=2)  # tolerate one outlier before a reset
        >>> opts.gate, opts.gain, opts.kalman_gate, opts.reset_after
        (0.5, 0.4, 2.0, 2)
        >>> CorrectionOptions(gain=1.5)
        Traceback (most recent call last):
        ...
        egorefine.core.errors.ValueRangeError: gain: expected 0 < gain <= 1, got 1.5
    """

    gate: float = 0.5
    gain: float = 0.4
    kalman_gate: float = 1.0
    reset_after: int = 1
    edge_aware: bool = True
    edge_kernel: int = 3
    max_unverified_variance: float | None = 0.0625
    gate_softness: float | None = None

    def __post_init__(self) -> None:
        _at_least(self.gate, 0.0, "gate")
        if not 0.0 < float(self.gain) <= 1.0:
            raise ValueRangeError(f"gain: expected 0 < gain <= 1, got {self.gain}")
        if not float(self.kalman_gate) > 0:
            raise ValueRangeError(f"kalman_gate: expected > 0, got {self.kalman_gate}")
        if int(self.reset_after) != self.reset_after or self.reset_after < 1:
            raise ValueRangeError(f"reset_after: expected an integer >= 1, got {self.reset_after}")
        _odd(self.edge_kernel, "edge_kernel")
        if self.max_unverified_variance is not None and not float(self.max_unverified_variance) > 0:
            raise ValueRangeError(f"max_unverified_variance: expected > 0 or None, got {self.max_unverified_variance}")
        if self.gate_softness is not None and not float(self.gate_softness) > 0:
            raise ValueRangeError(f"gate_softness: expected > 0 or None, got {self.gate_softness}")


@dataclass(frozen=True)
class SearchOptions:
    """Measurements on frames without stereo.

    Attributes:
        local_search: a residual match (:func:`~egorefine.stereo.match_residual`) ``prediction +- local_search``
            px around the valid predicted pixels, fused by the fusion rule; 0 (off, the paper's loop) or >= 2. It
            costs ``2 local_search + 1`` cost planes and catches keyframe errors that grow as a surface approaches.
        block: its window (odd, px; 7: it only pins down a residual of a pixel or two, and blurs less of an edge
            than the full matcher's window).
        window: ``"fronto"`` (the matcher's window at ``round(prediction) + k``) or ``"warped"`` (each window pixel
            shifted by its own prediction).
        measure_holes: measure the pixels still without a value with the matcher on the tiles where they are
            dense (:func:`~egorefine.stereo.match_stereo_regions`); off: it costs most of a stereo run.
        max_hole_variance, hole_background_margin: a hole measurement is taken where its variance is at most
            ``max_hole_variance`` px^2 or it lies at most ``hole_background_margin`` px above the hole's
            background fill (an uncovered region shows the background; None: variance only).

    Example:
        >>> opts = SearchOptions(local_search=2, window="warped")  # 5 cost planes around each prediction
        >>> opts.local_search, opts.block, opts.measure_holes
        (2, 7, False)
        >>> SearchOptions(local_search=1)
        Traceback (most recent call last):
        ...
        egorefine.core.errors.ValueRangeError: local_search: expected 0 (off) or an integer >= 2, got 1
    """

    local_search: int = 0
    block: int = 7
    window: str = "fronto"
    measure_holes: bool = False
    max_hole_variance: float = 0.2
    hole_background_margin: float | None = 0.5

    def __post_init__(self) -> None:
        r = self.local_search
        if int(r) != r or r < 0 or r == 1:
            raise ValueRangeError(f"local_search: expected 0 (off) or an integer >= 2, got {r}")
        _odd(self.block, "block (local_search_block)")
        check_choice(self.window, ("fronto", "warped"), "window (local_search_window)")
        if not float(self.max_hole_variance) > 0:
            raise ValueRangeError(f"max_hole_variance: expected > 0, got {self.max_hole_variance}")
        if self.hole_background_margin is not None:
            _at_least(self.hole_background_margin, 0.0, "hole_background_margin")


@dataclass(frozen=True)
class ScheduleOptions:
    """Extra stereo runs between verifications.

    Attributes:
        adaptive: run stereo also where the prediction's valid share falls below ``min_coverage`` or its mean
            confidence below ``min_confidence`` (off: the paper's fixed schedule).
        min_coverage, min_confidence: the thresholds, in [0, 1].

    Example:
        >>> from egorefine.refine import EgoMotionRefiner
        >>> refiner = EgoMotionRefiner(max_disparity=32, schedule=ScheduleOptions(adaptive=True, min_coverage=0.9))
        >>> refiner.schedule.adaptive, refiner.schedule.min_coverage, refiner.schedule.min_confidence
        (True, 0.9, 0.5)
    """

    adaptive: bool = False
    min_coverage: float = 0.85
    min_confidence: float = 0.5

    def __post_init__(self) -> None:
        _at_least(self.min_coverage, 0.0, "min_coverage")
        _at_least(self.min_confidence, 0.0, "min_confidence")


# flat keyword of earlier releases -> (the refiner's group argument, the field)
LEGACY_KEYWORDS: dict[str, tuple[str, str]] = {
    "min_disparity": ("stereo", "min_disparity"), "block_size": ("stereo", "block_size"),
    "stereo_cost": ("stereo", "cost"), "aggregation": ("stereo", "aggregation"), "subpixel": ("stereo", "subpixel"),
    "temperature": ("stereo", "temperature"),
    "max_features": ("tracking", "max_features"), "min_tracks": ("tracking", "min_tracks"),
    "soft_tracking": ("tracking", "soft"),
    "splat": ("prediction", "splat"), "fill_cracks": ("prediction", "fill_cracks"),
    "process_noise": ("prediction", "process_noise"),
    "gate": ("correction", "gate"), "gain": ("correction", "gain"), "kalman_gate": ("correction", "kalman_gate"),
    "reset_after": ("correction", "reset_after"), "edge_aware": ("correction", "edge_aware"),
    "edge_kernel": ("correction", "edge_kernel"),
    "max_unverified_variance": ("correction", "max_unverified_variance"),
    "gate_softness": ("correction", "gate_softness"),
    "local_search": ("search", "local_search"), "local_search_block": ("search", "block"),
    "local_search_window": ("search", "window"), "measure_holes": ("search", "measure_holes"),
    "max_hole_variance": ("search", "max_hole_variance"),
    "hole_background_margin": ("search", "hole_background_margin"),
    "adaptive": ("schedule", "adaptive"), "min_coverage": ("schedule", "min_coverage"),
    "min_confidence": ("schedule", "min_confidence"),
}

GROUPS = {"stereo": StereoOptions, "tracking": TrackingOptions, "prediction": PredictionOptions,
          "correction": CorrectionOptions, "search": SearchOptions, "schedule": ScheduleOptions}


def resolve_groups(groups: dict[str, object | None], legacy: dict[str, object], owner: str) -> dict[str, object]:
    """The option groups of ``owner`` with its flat ``legacy`` keywords applied on top (a ``DeprecationWarning``
    naming the group to use instead); an unknown keyword is a ``TypeError``, as Python gives."""
    out = {}
    for name, cls in GROUPS.items():
        given = groups.get(name)
        if given is not None and not isinstance(given, cls):
            raise ValueRangeError(f"{name}: expected a {cls.__name__} or None, got {type(given).__name__}")
        out[name] = cls() if given is None else given
    unknown = sorted(set(legacy) - set(LEGACY_KEYWORDS))
    if unknown:
        raise TypeError(f"{owner}() got an unexpected keyword argument {unknown[0]!r}")
    per_group: dict[str, dict[str, object]] = {}
    for key, value in legacy.items():
        group, field = LEGACY_KEYWORDS[key]
        per_group.setdefault(group, {})[field] = value
    for group, fields in per_group.items():
        cls = GROUPS[group]
        keys = ", ".join(k for k in legacy if LEGACY_KEYWORDS[k][0] == group)
        warnings.warn(f"{owner}({keys}=...): pass {group}={cls.__name__}({', '.join(f'{f}=...' for f in fields)}) "
                      "instead; the flat keywords go in the next release", DeprecationWarning, stacklevel=3)
        out[group] = dataclasses.replace(out[group], **fields)
    return out
