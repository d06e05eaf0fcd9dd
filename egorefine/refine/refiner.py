"""The predict-and-correct loop: :class:`EgoMotionRefiner` (one frame per call; :func:`refine_sequence` in
:mod:`egorefine.refine.sequence` runs it over a video).

One frame (docs/method.md, "The loop"; docs/architecture.md, "One frame"):

1. track the features of frame t-1 into frame t (search centred where the previous
   motion would carry them);
2. estimate the ego-motion from the tracks with Z from the previous disparity (eq. 2, 3);
3. predict frame t's disparity by moving every 3-D point and splatting it (eq. 1);
4. on verification frames, run stereo and correct the prediction with it (paper's gate and
   gain, or per-pixel Kalman fusion);
5. top the feature set up when tracks thin out.

The state is explicit (:mod:`egorefine.refine.state`): ``out, state = refiner(left, right, K, baseline,
state)``; nothing is kept on the module between calls, so one refiner serves many sequences, and a state can be
saved, inspected or detached. The smaller per-frame steps (confidence, hole measurements, recovery rules, the
constant-velocity guess) are in :mod:`egorefine.refine._steps`.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from torch import nn

from ..core import (
    DeviceError,
    ShapeError,
    StateError,
    ValueRangeError,
    check_choice,
    check_float,
    check_image,
    check_intrinsics,
    check_positive,
    check_setting,
    check_shape,
    to_grey,
)
from ..core.memory import keep_freed_memory
from ..features import build_pyramid, replenish, track
from ..motion import refine_motion_direct, solve_ego_motion
from ..stereo import StereoOutput, fill_invalid, match_residual, match_stereo, match_stereo_regions
from ..stereo.band import match_sgm_band
from ..stereo.matching import _TEMPERATURES
from ..stereo.scale import match_half_resolution
from ._steps import _confidence, _expected_positions, _overrule, _owned, _take_hole_measurements
from .correct import correct_disparity, edge_variance
from .cracks import predict_finished
from .health import (
    Status,
    count_per_item,
    disagreeing_regions,
    exposure_jumped,
    flag,
    stereo_failed,
    tracking_collapsed,
)
from .learning import measurement_features
from .options import (
    CorrectionOptions,
    PredictionOptions,
    ScheduleOptions,
    SearchOptions,
    StereoOptions,
    TrackingOptions,
    resolve_groups,
)
from .state import RefinerOutput, RefinerState

__all__ = ["RefinerState", "RefinerOutput", "EgoMotionRefiner"]

# pyramid levels of the feature tracker (its default)
_TRACK_LEVELS = 3


# The fill's candidate count under StereoOptions.fill_margin is a multiple of this: the compiled census + SGM kernel
# steps 32 candidates at a time, and a count between multiples runs slower than the next multiple
# (docs/decisions.md, "The fill's range from the prediction").
_FILL_CANDIDATE_STEP = 32

# measure_holes: a 6 px tile is matched where at least half of it is holes. Compact disocclusions and regions
# entering the view fill such tiles; so do the strips a few pixels wide that a depth edge uncovers, which larger
# tiles miss; smaller tiles or a lower share cost more than they add (docs/decisions.md, "Hole tiles").
_HOLE_TILE = 6
_HOLE_SHARE = 0.5

# the differentiable preset's gate softness (paper mode: px; Kalman mode: standard deviations): a fifth of the
# paper's 0.5 px gate, so that the soft rule stays close to the hard one away from the gate
_GATE_SOFTNESS = 0.1
# a confidence network's variance scale is clamped to this range (a documented clamp: never 0, never Inf)
_SCALE_RANGE = (1e-3, 1e3)
# a correction network's offset is clamped to this many px either way (a documented clamp)
_OFFSET_BOUND = 2.0


def _grey_right(right: torch.Tensor | None) -> torch.Tensor | None:
    """The right image checked for values (its shape was checked with the left one's) and in grey, or None: once
    a frame, on the frames that match it (stereo, local search and hole search all match grey)."""
    if right is None:
        return None
    check_image(right, "right")
    return to_grey(right)


def _net_output(net: nn.Module, x: torch.Tensor, meas: StereoOutput, name: str) -> torch.Tensor:
    """``net(x)``, checked: a tensor of the measurement's shape (``ShapeError``), finite (``ValueRangeError``)."""
    out = net(x)
    if not isinstance(out, torch.Tensor) or out.shape != meas.disparity.shape:
        got = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
        raise ShapeError(f"{name}: expected an output of shape {tuple(meas.disparity.shape)} (B, 1, H, W), got {got}")
    if not bool(torch.isfinite(out.detach()).all()):
        raise ValueRangeError(f"{name}: its output holds NaN or Inf")
    return out.to(meas.disparity.dtype)


@torch.compiler.disable  # not traced: dynamo would unroll SGM's scanline recursion, which has no gradient anyway
def _fill_matcher(left: torch.Tensor, right: torch.Tensor, max_disparity: int, min_disparity: int,
                  prior: torch.Tensor | None = None, band: int | None = None, scale: int = 1) -> StereoOutput:
    """:meth:`StereoOptions.dense`'s matcher on detached float32 copies: census is piecewise constant in the
    images (a zero gradient), so nothing is lost and the compiled CPU kernels may run; outputs in ``left``'s
    dtype. With a ``prior`` and a ``band``, only ``band`` candidates around the prior (``match_sgm_band``, the
    same matcher less its left-right check); else the full range, at half resolution with ``scale`` 2
    (``match_half_resolution``)."""
    dense = StereoOptions.dense().matcher_options()
    left, right = left.detach().float(), right.detach().float()
    if prior is not None and band is not None:
        same = {k: dense[k] for k in ("block_size", "subpixel", "speckle_size", "speckle_range") if k in dense}
        out = match_sgm_band(left, right, prior.detach().float(), max_disparity, min_disparity, width=band, **same)
    elif scale == 2:
        out = match_half_resolution(left, right, max_disparity, min_disparity=min_disparity, **dense)
    else:
        out = match_stereo(left, right, max_disparity, min_disparity=min_disparity, **dense)
    return StereoOutput(out.disparity.to(left.dtype), out.valid, out.variance.to(left.dtype))


class EgoMotionRefiner(nn.Module):
    """Sub-pixel disparity for a stereo video with stereo matching run on a fraction of the frames.

    ``out, state = refiner(left, right, K, baseline, state)``, once per frame, ``state=None`` on the first
    (docs/method.md, "The loop"): track the features, solve the ego-motion (eq. 2, 3, or the exact SE(3) model), predict
    the disparity by moving every 3-D point (eq. 1) and, every ``verify_every``-th frame, correct the prediction
    with fresh stereo (step 4). Stereo also runs where the ego-motion of some batch item failed and, with
    ``adaptive=True``, where the prediction's coverage or confidence is low; it acts on the whole batch at once.
    Frames the method does not expect (swapped, covered, black or noise images) are caught by the tests of
    ``egorefine.refine.health``; ``out.status`` says what happened to each item. The reasons for the defaults, with
    their measurements, are in docs/decisions.md.

    Gradients: every stage has a torch path that autograd follows (the compiled CPU kernels run only where no
    gradient is wanted, :func:`egorefine.core.use_compiled`). With default options the outputs are piecewise smooth
    in the images, ``K``, the baseline and the learnable parameters: the stereo winner, the track search, the
    z-buffer, the gates and every validity test are hard decisions, constant between their switching points.
    ``differentiable=True`` softens the ones that can be softened (docs/gradients.md).

    Memory: on the first frame of a sequence on the CPU the refiner has the C allocator keep freed memory for
    reuse (:func:`egorefine.core.memory.keep_freed_memory`, process-wide; ``EGOREFINE_KEEP_FREED_MEMORY=0`` leaves
    it alone): each frame's maps then reuse the last frame's memory instead of faulting in fresh pages.

    Args:
        max_disparity: stereo search range ``[min_disparity, max_disparity)``, px; predicted values outside it are
            not valid (no stereo run could verify them).
        verify_every: run stereo every i-th frame (``i`` in the paper); 1 = every frame.
        fusion: ``"paper"`` (the gate/gain rule of docs/method.md, step 4) or ``"kalman"`` (per-pixel variance).
        motion_method: ``"linear"`` (the paper's eq. 3), ``"robust"`` (RANSAC around it), ``"exact"`` (SE(3)
            reprojection; the default: first order is not enough at a metre per frame) or ``"direct"`` (the exact
            solve, then :func:`~egorefine.motion.refine_motion_direct`: the new left image aligned to the previous
            one through the previous frame's disparity; it keeps the exact solve's motion wherever it cannot lower
            the photometric cost). Not the default: it costs an alignment per frame, it helps on large sharp images
            more than on small noisy ones, and on the renders the prediction frames' error comes from elsewhere
            (docs/decisions.md, "What the motion costs the loop").
        stereo: :class:`~egorefine.refine.options.StereoOptions`, the verification matcher (``min_disparity``,
            block, cost, aggregation, sub-pixel fit, soft-argmin temperature, ``fill``: in Kalman mode by
            default the box matcher's holes are filled from census + SGM, for SGBM's density).
        tracking: :class:`~egorefine.refine.options.TrackingOptions`, the feature budget and the tracker.
        prediction: :class:`~egorefine.refine.options.PredictionOptions`, the splat, crack closing, process noise.
        correction: :class:`~egorefine.refine.options.CorrectionOptions`, the paper rule's gate and gain, the Kalman
            rule's gate, reset, edge and unverified variances, soft gates.
        search: :class:`~egorefine.refine.options.SearchOptions`, measurements between verifications (residual
            search, hole measurement; off by default: the paper's loop).
        schedule: :class:`~egorefine.refine.options.ScheduleOptions`, extra stereo runs where the prediction's
            coverage or confidence is low (off by default).
        differentiable: the differentiable configuration: soft-argmin stereo (``stereo.temperature``), the
            tracker's soft last step, soft splatting and a soft gate (``correction.gate_softness``), each unless
            set explicitly. For training; inference is faster with the default hard decisions.
        learnable: the fusion's settings become :class:`torch.nn.Parameter` s: ``gain_logit`` (``gain =
            sigmoid``), ``log_gate``, ``log_process_noise``, ``log_noise_scale`` (a factor of the measurement
            variance, 1 to start) and ``log_temperature`` (the soft matcher's). Stored unconstrained, so that no
            optimiser step can leave a range; a non-finite parameter raises ``ValueRangeError``.
        confidence_net: an ``nn.Module`` mapping the ``(B, NET_INPUTS, H, W)`` features of a measurement
            (:func:`~egorefine.refine.measurement_features`: grey left image, disparity, validity, fill, sub-pixel
            phase) to a positive ``(B, 1, H, W)`` scale of its variance (:class:`~egorefine.refine.ConfidenceNet`;
            clamped to ``[1e-3, 1e3]``). It acts on every fused measurement; in paper mode, whose gain is fixed,
            only on the carried variance.
        correction_net: an ``nn.Module`` mapping the same features to a ``(B, 1, H, W)`` offset in px added to each
            stereo measurement (frame 0 and every verification) where it is valid, before fusion
            (:class:`~egorefine.refine.CorrectionNet`; clamped to ``[-2, 2]`` px). For either network a wrong
            output shape raises ``ShapeError``, NaN or Inf ``ValueRangeError``.
        **legacy: the flat keywords of earlier releases (``max_features=``, ``local_search=``, ...; see
            :data:`~egorefine.refine.options.LEGACY_KEYWORDS`): still accepted for one release, with a
            ``DeprecationWarning`` naming the group to use.

    The paper's method as published is ``fusion="paper", motion_method="linear",
    stereo=StereoOptions(subpixel=False)`` (pixel-accurate block matching, equation (3), gate 0.5 px, gain 0.4).

    Example:
        >>> from egorefine.data import render_sequence
        >>> seq = render_sequence(num_frames=3, height=60, width=80)
        >>> from egorefine.refine import TrackingOptions
        >>> refiner = EgoMotionRefiner(max_disparity=16, verify_every=2,
        ...                            tracking=TrackingOptions(max_features=64, min_tracks=16))
        >>> K, b = seq.K[None], torch.tensor([seq.baseline])
        >>> state = None
        >>> for t in range(3):
        ...     out, state = refiner(seq.left[t:t + 1], seq.right[t:t + 1], K, b, state)
        >>> out.disparity.shape, out.motion.shape, out.stereo_ran
        (torch.Size([1, 1, 60, 80]), torch.Size([1, 4, 4]), True)
    """

    def __init__(
        self,
        max_disparity: int = 64,
        verify_every: int = 5,
        fusion: str = "paper",
        motion_method: str = "exact",
        *,
        stereo: StereoOptions | None = None,
        tracking: TrackingOptions | None = None,
        prediction: PredictionOptions | None = None,
        correction: CorrectionOptions | None = None,
        search: SearchOptions | None = None,
        schedule: ScheduleOptions | None = None,
        differentiable: bool = False,
        learnable: bool = False,
        confidence_net: nn.Module | None = None,
        correction_net: nn.Module | None = None,
        **legacy,
    ) -> None:
        super().__init__()
        check_choice(fusion, ("paper", "kalman"), "fusion")
        check_choice(motion_method, ("linear", "robust", "exact", "direct"), "motion_method")
        if int(verify_every) < 1:
            raise ValueRangeError(f"verify_every: expected an integer >= 1, got {verify_every}")
        groups = resolve_groups({"stereo": stereo, "tracking": tracking, "prediction": prediction,
                                 "correction": correction, "search": search, "schedule": schedule},
                                legacy, type(self).__name__)
        stereo, tracking, prediction = groups["stereo"], groups["tracking"], groups["prediction"]
        correction, search, schedule = groups["correction"], groups["search"], groups["schedule"]
        if int(max_disparity) <= stereo.min_disparity:
            raise ValueRangeError(
                f"max_disparity: must exceed min_disparity={stereo.min_disparity}, got {max_disparity}")
        for name, net in (("confidence_net", confidence_net), ("correction_net", correction_net)):
            if net is not None and not isinstance(net, nn.Module):
                raise ValueRangeError(f"{name}: expected an nn.Module or None, got {type(net).__name__}")
        self.differentiable = bool(differentiable)
        # the differentiable preset: each of its parts unless the caller chose otherwise
        if self.differentiable:
            prediction = dataclasses.replace(prediction, splat=prediction.splat or "soft")
            tracking = dataclasses.replace(tracking, soft=True if tracking.soft is None else tracking.soft)
            if correction.gate_softness is None:
                correction = dataclasses.replace(correction, gate_softness=_GATE_SOFTNESS)
        prediction = dataclasses.replace(prediction, splat=prediction.splat or "hard")
        tracking = dataclasses.replace(tracking, soft=bool(tracking.soft))
        if stereo.fill is None:  # Kalman mode's verification: the box matcher, its holes filled by SGM
            local = (stereo.aggregation or "box") == "box"
            stereo = dataclasses.replace(stereo, fill=fusion == "kalman" and local and not self.differentiable)
        self.stereo, self.tracking, self.prediction = stereo, tracking, prediction
        self.correction, self.search, self.schedule = correction, search, schedule

        self.max_disparity = int(max_disparity)
        self.verify_every = int(verify_every)
        self.fusion = fusion
        self.motion_method = motion_method
        # The settings learning may change: plain numbers, or (learnable) unconstrained parameters mapped into
        # their ranges (gain: a logistic of gain_logit; the positive ones: exp of a log), so that no optimiser step
        # can leave a range.
        self.learnable = bool(learnable)
        temperature = float(_TEMPERATURES[stereo.cost or "sad"] if stereo.temperature is None
                            else stereo.temperature)
        fixed = {"gain": float(correction.gain), "gate": float(correction.gate),
                 "process_noise": float(prediction.process_noise), "noise_scale": 1.0, "temperature": temperature}
        self._fixed = {} if self.learnable else fixed
        if self.learnable:
            if not (fixed["gate"] > 0 and fixed["process_noise"] > 0 and fixed["gain"] < 1):
                raise ValueRangeError(
                    "learnable=True: gate and process_noise must be > 0 and gain < 1 (their parameters are logs and a "
                    f"logit), got gate={fixed['gate']}, process_noise={fixed['process_noise']}, gain={fixed['gain']}")
            self.gain_logit = nn.Parameter(torch.logit(torch.tensor(fixed["gain"])))
            for name in ("gate", "process_noise", "noise_scale", "temperature"):
                setattr(self, f"log_{name}", nn.Parameter(torch.tensor(fixed[name]).log()))
        self.confidence_net = confidence_net
        self.correction_net = correction_net

    # -- the settings learning may change ----------------------------------------------------------------------
    def _value(self, name: str) -> float | torch.Tensor:
        if not self.learnable:
            return self._fixed[name]
        if name == "gain":
            value = torch.sigmoid(self.gain_logit)
        else:
            value = getattr(self, f"log_{name}").exp()
        return check_setting(value, name)  # (a diverged optimiser step: a typed error, not NaN maps)

    @property
    def gain(self) -> float | torch.Tensor:
        """The paper rule's gain, in (0, 1]; with ``learnable=True`` the 0-d tensor ``sigmoid(gain_logit)``."""
        return self._value("gain")

    @property
    def gate(self) -> float | torch.Tensor:
        """The paper rule's gate in px; with ``learnable=True`` the 0-d tensor ``exp(log_gate)``."""
        return self._value("gate")

    @property
    def process_noise(self) -> float | torch.Tensor:
        """Kalman mode's process noise in px^2 per predicted frame; with ``learnable=True``
        ``exp(log_process_noise)``."""
        return self._value("process_noise")

    @property
    def noise_scale(self) -> float | torch.Tensor:
        """Kalman mode's scale of the matcher's measurement variance; 1, or with ``learnable=True``
        ``exp(log_noise_scale)``."""
        return self._value("noise_scale")

    @property
    def temperature(self) -> float | torch.Tensor:
        """The soft-argmin matcher's temperature in cost units (``differentiable=True``); with ``learnable=True``
        ``exp(log_temperature)``."""
        return self._value("temperature")

    def _features(self, grey: torch.Tensor, meas: StereoOutput, matched: torch.Tensor | None) -> torch.Tensor:
        """The networks' input for one measurement (:func:`~egorefine.refine.measurement_features`); ``matched``:
        the first matcher's validity (the rest of ``meas.valid`` is the fill's), or None (no such split)."""
        filled = None if matched is None else meas.valid & ~matched
        return measurement_features(grey, meas.disparity, meas.valid, filled, self.max_disparity)

    def _variance_scale(self, grey: torch.Tensor, meas: StereoOutput,
                        matched: torch.Tensor | None) -> torch.Tensor | float:
        """The factor of a measurement's variance before fusion: ``noise_scale`` times the confidence network's
        per-pixel scale (clamped to ``_SCALE_RANGE``)."""
        scale = self.noise_scale
        if isinstance(scale, torch.Tensor):
            scale = scale.to(grey.dtype)
        if self.confidence_net is None:
            return scale
        net = _net_output(self.confidence_net, self._features(grey, meas, matched), meas, "confidence_net")
        return net.clamp(*_SCALE_RANGE) * scale

    def _corrected(self, grey: torch.Tensor, meas: StereoOutput, matched: torch.Tensor) -> StereoOutput:
        """The measurement with the correction network's offset (clamped to ``_OFFSET_BOUND`` px) where valid."""
        net = _net_output(self.correction_net, self._features(grey, meas, matched), meas, "correction_net")
        offset = net.clamp(-_OFFSET_BOUND, _OFFSET_BOUND) * meas.valid.to(net.dtype)
        return meas._replace(disparity=meas.disparity + offset)

    # -- checks ------------------------------------------------------------------------------------------------
    def _check_inputs(
        self,
        left: torch.Tensor,
        right: torch.Tensor | None,
        K: torch.Tensor,
        baseline: torch.Tensor,
        state: RefinerState | None,
    ) -> None:
        dims = check_image(left, "left")
        if right is not None:  # (its values on the frames that read it: _grey_right)
            check_image(right, "right", dims, values=False)
            if right.device != left.device:
                raise DeviceError(f"right: on {right.device}, but left is on {left.device}")
        check_intrinsics(K, "K", dims)
        check_shape(baseline, ["B"], "baseline", dims)
        check_float(baseline, "baseline")
        check_positive(baseline, "baseline")
        for name, t in (("K", K), ("baseline", baseline)):
            if t.device != left.device:
                raise DeviceError(f"{name}: on {t.device}, but left is on {left.device}")
        if state is None:
            return
        if not isinstance(state, RefinerState):
            raise StateError(f"state: expected a RefinerState or None, got {type(state).__name__}")
        prev = state.image
        if prev.shape[-2:] != left.shape[-2:]:
            raise StateError(
                f"state: carried from a {tuple(prev.shape[-2:])} sequence, but left is {tuple(left.shape[-2:])};"
                " frames may not change size mid-sequence (start a new one with state=None)"
            )
        if prev.shape[0] != left.shape[0]:
            raise StateError(f"state: carried for batch size {prev.shape[0]}, but left has {left.shape[0]}")
        if prev.device != left.device:
            raise StateError(f"state: on {prev.device}, but left is on {left.device}; frames may not change device")
        if prev.dtype != left.dtype:
            raise StateError(f"state: carried in {prev.dtype}, but left is {left.dtype}; frames may not change dtype")

    def _needs_stereo(self, frame: int, motion_ok: torch.Tensor, coverage: torch.Tensor | None,
                      conf: torch.Tensor | None) -> bool:
        if frame % self.verify_every == 0:
            return True
        # One host sync per frame: the schedule decides whether a whole matcher call happens.
        trouble = ~motion_ok
        if self.schedule.adaptive:
            trouble = trouble | (coverage < self.schedule.min_coverage) | (conf < self.schedule.min_confidence)
        return bool(trouble.any())

    def _stereo(self, left: torch.Tensor, right: torch.Tensor | None, frame: int,
                why: str = "verification", corrected: bool = True, prior: torch.Tensor | None = None,
                prior_ok: torch.Tensor | None = None) -> tuple[StereoOutput, torch.Tensor]:
        """The verification measurement, and the validity of its first matcher alone: the health signal (a
        swapped or blank pair still gives SGM matches in the fill, but no longer the box matcher's).

        ``prior``: the prediction ``(B, 1, H, W)``, finite (None on the first frame); where ``prior_ok`` ``(B,)``
        holds for every item (their motion is good) the fill searches up to its largest value plus
        ``stereo.fill_margin`` (:meth:`_fill_range`), or ``stereo.fill_band`` candidates around it item by item;
        else the full range."""
        if right is None:
            raise ValueRangeError(f"right: frame {frame} needs stereo matching ({why}), but right is None")
        out = match_stereo(left, right, self.max_disparity, min_disparity=self.stereo.min_disparity,
                           **self._matcher())
        matched = out.valid
        if self.stereo.fill:  # the holes of a local matcher filled where census + SGM matches
            out = fill_invalid(out, self._fill(left, right, prior, prior_ok))
        if corrected and self.correction_net is not None:
            out = self._corrected(left, out, matched)
        return out, matched

    def _fill(self, left: torch.Tensor, right: torch.Tensor, prior: torch.Tensor | None,
              prior_ok: torch.Tensor | None) -> StereoOutput:
        """The fill: banded around ``prior`` for the items where ``prior_ok`` holds, full range for the others."""
        args = (left, right, self._fill_range(prior, prior_ok), self.stereo.min_disparity)
        band, scale = self.stereo.fill_band, self.stereo.fill_scale
        use = prior is not None and band is not None
        if not use or bool(prior_ok.all()):
            return _fill_matcher(*args, prior, band if use else None, scale)
        if not bool(prior_ok.any()):
            return _fill_matcher(*args, scale=scale)
        # (a rare frame: some items' motion failed) each item its own kind of fill
        banded, full = _fill_matcher(*args, prior, band), _fill_matcher(*args, scale=scale)
        pick = prior_ok.view(-1, 1, 1, 1)
        return StereoOutput(*(torch.where(pick, a, b) for a, b in zip(banded, full, strict=True)))

    def _fill_range(self, prior: torch.Tensor | None, prior_ok: torch.Tensor | None) -> int:
        """The full-range fill's ``max_disparity``: the prediction's largest value plus ``stereo.fill_margin``, the
        candidate count rounded up to a multiple of :data:`_FILL_CANDIDATE_STEP` (``StereoOptions.fill_margin``);
        ``max_disparity`` without a prediction for every item, with a band fill or with the margin off."""
        low, margin = self.stereo.min_disparity, self.stereo.fill_margin
        if prior is None or margin is None or self.stereo.fill_band is not None or not bool(prior_ok.all()):
            return self.max_disparity
        prior = prior.detach()
        # (numpy's max on the CPU: a torch op over the map would wake torch's OpenMP threads beside the kernels)
        largest = float(prior.numpy().max() if prior.device.type == "cpu" else prior.amax())
        need = math.ceil(largest) + margin + 1 - low
        step = _FILL_CANDIDATE_STEP
        return min(self.max_disparity, low + step * max(1, -(-need // step)))

    def measure(self, left: torch.Tensor, right: torch.Tensor) -> tuple[StereoOutput, torch.Tensor]:
        """The verification measurement of one stereo pair before the correction network, and its network input.

        What a verification frame matches (the matcher of ``stereo``, the fill where it is on) and the
        :func:`~egorefine.refine.measurement_features` the networks see for it. The matcher has no learnable
        parts in the default configuration, so a correction network can be fitted to truth on measurements
        computed once: ``net(features)`` should approach ``truth - measurement.disparity`` where
        ``measurement.valid`` (``benchmarks/learning.py`` does this before training through the loop).

        Args:
            left: ``(B, 1|3, H, W)`` left image in [0, 1].
            right: ``(B, 1|3, H, W)`` right image.

        Returns:
            ``(StereoOutput, features)``: disparity, validity and variance ``(B, 1, H, W)``; features ``(B,
            NET_INPUTS, H, W)``.

        Example:
            >>> from egorefine.data import render_sequence
            >>> seq = render_sequence(num_frames=1, height=48, width=64)
            >>> refiner = EgoMotionRefiner(max_disparity=16, fusion="kalman")
            >>> meas, x = refiner.measure(seq.left, seq.right)
            >>> meas.disparity.shape, x.shape
            (torch.Size([1, 1, 48, 64]), torch.Size([1, 6, 48, 64]))
        """
        dims = check_image(left, "left")
        check_image(right, "right", dims)
        grey, right = to_grey(left), to_grey(right)
        meas, matched = self._stereo(grey, right, 0, corrected=False)
        return meas, self._features(grey, meas, matched)

    def _matcher(self) -> dict:
        """The matcher's keyword arguments (the soft-argmin's temperature read at call time: it may learn)."""
        options = self.stereo.matcher_options()
        if self.differentiable:
            options.update(differentiable=True, temperature=self.temperature)
        return options

    def _correct(self, grey, pred, meas, outlier_count: torch.Tensor, verification: bool,
                 matched: torch.Tensor | None = None):
        """Step 4: fuse a measurement (full stereo, or the residual search) into the prediction by ``fusion``.

        Kalman mode adds the prediction's depth-edge variance (``edge_aware``); ``max_unverified_variance`` applies
        at verifications only (between them a prediction the residual search did not cover stays as it was)."""
        kalman = self.fusion == "kalman"
        pred_var = pred.variance
        if kalman and self.correction.edge_aware:
            pred_var = edge_variance(pred.disparity, pred.valid, self.correction.edge_kernel, base=pred_var)
        meas_var = meas.variance
        if self.learnable or self.confidence_net is not None:
            meas_var = meas_var * self._variance_scale(grey, meas, matched)
        return correct_disparity(
            pred.disparity, meas.disparity, meas.valid, fusion=self.fusion, gate=self.gate, gain=self.gain,
            predicted_variance=pred_var, measured_variance=meas_var, predicted_valid=pred.valid,
            outlier_count=outlier_count, kalman_gate=self.correction.kalman_gate,
            reset_after=self.correction.reset_after,
            max_unverified_variance=self.correction.max_unverified_variance if kalman and verification else None,
            gate_softness=self.correction.gate_softness,
        )

    # -- one frame ---------------------------------------------------------------------------------------------
    def forward(
        self,
        left: torch.Tensor,
        right: torch.Tensor | None,
        K: torch.Tensor,
        baseline: torch.Tensor,
        state: RefinerState | None = None,
    ) -> tuple[RefinerOutput, RefinerState]:
        """Refine one frame.

        Args:
            left: ``(B, 1|3, H, W)`` left image in [0, 1].
            right: ``(B, 1|3, H, W)`` right image, or None on frames that do not need stereo. Its shape is
                checked on every frame, its values (range, NaN / Inf) on the frames that read it.
            K: ``(B, 3, 3)`` rectified left intrinsics.
            baseline: ``(B,)`` metres.
            state: the previous call's state, or None to start a sequence.

        Returns:
            ``(RefinerOutput, RefinerState)``.
        """
        self._check_inputs(left, right, K, baseline, state)
        grey = to_grey(left)
        B = grey.shape[0]
        eye = torch.eye(4, device=grey.device, dtype=grey.dtype).expand(B, 4, 4)
        if state is None:
            if grey.device.type == "cpu":  # a frame's maps reuse the last one's memory, not fresh pages
                keep_freed_memory()
            return self._first_frame(grey, _grey_right(right), eye)

        frame = state.frame + 1
        # 1. track features of t-1 into t, search centred by constant velocity.
        # The search starts at the constant-velocity prediction (from frame 2 on: the first step has no motion yet,
        # and a zero-flow prediction would only cost a wasted first search). Matches found next to their prediction
        # skip the forward-backward round trip (the others go back over one level, search_radius wide: a wrong match
        # then lands away from its start; the full coarse-to-fine way back costs more time and gains no accuracy,
        # docs/decisions.md), and each frame's pyramid is built once and reused as `prev`.
        expected = None
        if state.frame > 0:
            expected = _expected_positions(state.keypoints, state.disparity, state.valid, state.motion, K, baseline)
        pyramid = tuple(build_pyramid(grey, _TRACK_LEVELS))
        tracked = track(state.image, grey, state.keypoints, state.weights, predicted=expected, levels=_TRACK_LEVELS,
                        prev_pyramid=None if state.pyramid is None else list(state.pyramid),
                        next_pyramid=list(pyramid), fb_predicted=False, fb_levels=1, soft=self.tracking.soft)
        # 2. ego-motion from the tracks (eq. 2, 3), Z from the previous disparity.
        ego = solve_ego_motion(
            state.keypoints,
            tracked.keypoints,
            state.disparity,
            K,
            baseline,
            weights=tracked.weights,
            valid_prev=state.valid,
            method="exact" if self.motion_method == "direct" else self.motion_method,
        )
        if self.motion_method == "direct":  # the solve refined photometrically where it lowers the cost
            direct = refine_motion_direct(state.image, grey, state.disparity, K, baseline, ego.motion,
                                          prev_valid=state.valid, prev_variance=state.variance)
            ego = ego._replace(motion=torch.where(ego.ok[:, None, None], direct.motion, ego.motion))
        # A scene change (most tracks lost at once: a swapped, covered or blinded camera) counts as a failed motion.
        collapsed = tracking_collapsed((state.weights > 0).sum(1), (tracked.weights > 0).sum(1))
        ok = ego.ok & ~collapsed
        motion = torch.where(collapsed[:, None, None], eye, ego.motion)  # identity where the solve failed
        status = flag(~ok, Status.MOTION_FAILED) | flag(collapsed, Status.SCENE_CHANGE)
        if state.pyramid is not None:
            status = status | flag(exposure_jumped(state.pyramid[-1], pyramid[-1]), Status.EXPOSURE_JUMP)
        # 3. predict disparity (eq. 1 + splat). The map is moved from the keyframe with the composed motion
        # rather than from the previous prediction: each splat re-discretises depth edges, and chained splats
        # let those sub-pixel edge errors random-walk from frame to frame.
        key_motion = motion @ state.key_motion
        steps = state.since_stereo + 1
        process_noise = self.process_noise
        if isinstance(process_noise, torch.Tensor):
            process_noise = process_noise.to(grey.dtype)
        # Then holes the keyframe saw (magnified surfaces outgrow the splat's tiling) are looked up in it
        # (fill_cracks). A predicted value outside the stereo search range cannot be verified by the next stereo
        # run. On the test scenes such values are mostly a stereo outlier magnified by the approach (a mismatched
        # patch at 54 px in a corridor whose truth there is 11 px grows past 100 px within four frames forward, and
        # its large footprint wins the z-buffer): they are not valid, and carry no confidence.
        pred = predict_finished(state.key_disparity, key_motion, K, baseline, state.key_variance, state.key_valid,
                                self.prediction.splat, process_noise * steps, self.prediction.fill_cracks,
                                (self.stereo.min_disparity, self.max_disparity))
        coverage = conf = None
        if self.schedule.adaptive:
            coverage = pred.valid.flatten(1).float().mean(1)
            conf = pred.confidence.flatten(1).mean(1)
        stereo_ran = self._needs_stereo(frame, ok, coverage, conf)
        # (a frame without stereo, local search or hole search does not read the right image)
        uses_right = stereo_ran or self.search.local_search or self.search.measure_holes
        right = _grey_right(right) if uses_right else None

        disparity, variance, valid, outliers = pred.disparity, pred.variance, pred.valid, state.outlier_count
        confidence = pred.confidence
        measure_holes = self.search.measure_holes and not stereo_ran and right is not None
        if stereo_ran:
            # 4. verify against fresh stereo and correct.
            why = "verification" if frame % self.verify_every == 0 else (
                "the ego-motion failed" if not bool(ok.all()) else "adaptive: low coverage or confidence")
            # (where the motion is good the fill's range comes from the prediction: fill_margin, fill_band; the box
            # matcher searches the full range everywhere, so a wrong prediction never yields a stale value)
            meas, matched = self._stereo(grey, right, frame, why, prior=pred.disparity, prior_ok=ok)
            if frame % self.verify_every != 0:
                status = status | int(Status.STEREO_FORCED)
            cor = self._correct(grey, pred, meas, state.outlier_count, verification=True, matched=matched)
            disparity, variance, valid, outliers = cor.disparity, cor.variance, cor.valid, cor.outlier_count
            # Stereo that failed wholesale (swapped, black or noise images) is rejected: the prediction stays. Regions
            # where the two disagree as a whole (an occluder, a wrong motion) take the measurement.
            # (with a fill, SGM matches even a swapped pair: the first matcher's count, against its own last one)
            reference = pred.valid if state.matched is None else state.matched
            rejected = stereo_failed(matched, reference) & ok
            matched_count = None if state.matched is None else torch.where(rejected, state.matched,
                                                                            count_per_item(matched))
            reset = disagreeing_regions(pred.disparity, pred.valid, meas.disparity, meas.valid)
            status = status | flag(rejected, Status.MEASUREMENT_REJECTED)
            reset_items = (count_per_item(reset) > 0) & ~rejected  # (a rejected item keeps its whole prediction)
            status = status | flag(reset_items, Status.PREDICTION_RESET)
            # Where the motion failed the prediction is meaningless: that item restarts from stereo.
            if bool(rejected.any()) or bool(reset_items.any()) or not bool(ok.all()):
                maps = (disparity, variance, valid, outliers)
                # (the correction's maps are fresh unless it passed an input through: then out of place)
                owned = _owned(maps, *pred, *meas, *state, matched)
                disparity, variance, valid, outliers = _overrule(maps, pred, meas, keep=rejected, restart=~ok,
                                                                 regions=reset, owned=owned)
            confidence = _confidence(valid, variance)
        elif self.search.local_search and right is not None:
            # 4'. no stereo on this frame: a narrow residual search around the prediction corrects it.
            meas = match_residual(grey, right, pred.disparity, radius=self.search.local_search,
                                  block_size=self.search.block, prior_valid=pred.valid,
                                  window=self.search.window)
            cor = self._correct(grey, pred, meas, state.outlier_count, verification=False)
            disparity, variance, valid, outliers = cor.disparity, cor.variance, cor.valid, cor.outlier_count
            if not measure_holes:  # (the hole step computes it)
                confidence = _confidence(valid, variance)
        if measure_holes:
            # 4''. the holes the keyframe could not fill (disocclusions, regions entering the view): the matcher on
            # windows around them; a value enters where it is precise or on the background side of the hole's fill.
            # (numpy's not on the CPU: a full-map torch op would wake torch's OpenMP threads beside the matcher)
            hole = torch.from_numpy(np.logical_not(valid.numpy())) if valid.device.type == "cpu" else ~valid
            meas = match_stereo_regions(grey, right, hole, self.max_disparity, tile=_HOLE_TILE,
                                        min_fraction=_HOLE_SHARE,
                                        min_disparity=self.stereo.min_disparity, **self._matcher())
            disparity, variance, valid, outliers, confidence = _take_hole_measurements(
                disparity, variance, valid, outliers, meas, pred, self.search.max_hole_variance,
                self.search.hole_background_margin)
        # 5. keep the tracks, top up when they thin out.
        keypoints, weights = tracked.keypoints, tracked.weights
        live = (weights > 0).sum(1)
        need = live < self.tracking.min_tracks
        if bool(need.any()):
            # Only items that ran short get new features: an item's tracks never depend on its batch neighbours.
            new_kp, new_w = replenish(grey, keypoints, weights, max_features=self.tracking.max_features)
            keypoints = torch.where(need[:, None, None], new_kp, keypoints)
            weights = torch.where(need[:, None], new_w, weights)

        out = RefinerOutput(disparity, valid, motion, stereo_ran, variance, confidence, ok, live, status)
        if stereo_ran:
            key = (disparity, variance, valid, eye.clone(), 0)
        else:
            key = (state.key_disparity, state.key_variance, state.key_valid, key_motion, steps)
            matched_count = state.matched
        new_state = RefinerState(
            grey, keypoints, weights, disparity, variance, valid, outliers, motion, *key[:4], frame, key[4], pyramid,
            matched_count,
        )
        return out, new_state

    def _first_frame(
        self, grey: torch.Tensor, right: torch.Tensor | None, eye: torch.Tensor
    ) -> tuple[RefinerOutput, RefinerState]:
        B = grey.shape[0]
        meas, matched = self._stereo(grey, right, 0)
        empty_kp = torch.zeros(B, self.tracking.max_features, 2, device=grey.device, dtype=grey.dtype)
        empty_w = torch.zeros(B, self.tracking.max_features, device=grey.device, dtype=grey.dtype)
        keypoints, weights = replenish(grey, empty_kp, empty_w, max_features=self.tracking.max_features)
        ok = torch.ones(B, dtype=torch.bool, device=grey.device)
        confidence = _confidence(meas.valid, meas.variance)
        status = torch.zeros(B, dtype=torch.int64, device=grey.device)
        out = RefinerOutput(
            meas.disparity, meas.valid, eye.clone(), True, meas.variance, confidence, ok, (weights > 0).sum(1), status
        )
        state = RefinerState(
            grey, keypoints, weights, meas.disparity, meas.variance, meas.valid,
            torch.zeros_like(meas.variance), eye.clone(),
            meas.disparity, meas.variance, meas.valid, eye.clone(), 0, 0, tuple(build_pyramid(grey, _TRACK_LEVELS)),
            count_per_item(matched) if self.stereo.fill else None,
        )
        return out, state
