"""Correct a predicted disparity map with a fresh stereo measurement (docs/method.md, loop step 4).

Two fusion rules, chosen by ``fusion``:

* ``"paper"``: exactly the paper's rule. Where both maps are valid and ``|e - s| > gate``
  (0.5 px), ``e <- e + gain (s - e)`` (gain 0.4); where ``|e - s| <= gate``, ``e`` is kept.
* ``"kalman"``: a per-pixel scalar Kalman update. ``P`` (the predicted variance, carried and
  inflated by process noise in :func:`~egorefine.refine.predict.predict_disparity`) and ``R``
  (the matcher's measurement variance: cost curvature, or 1/12 px^2 for integer quantisation)
  give the gain ``G = P / (P + R)``; ``e <- e + G (s - e)``, ``P <- (1 - G) P``. Innovations
  beyond ``kalman_gate`` standard deviations (``|s - e| > k sqrt(P + R)``) are outliers: not
  fused, counted per pixel, and where a pixel is an outlier ``reset_after`` verifications in a
  row the estimate is reset to the measurement (``e = s``, ``P = R``).

Both rules: where the prediction is invalid (a hole) and the measurement valid, take the
measurement (``e = s``, ``P = R``); where the measurement is invalid, keep the prediction
(disparity, variance and outlier count carried unchanged).

Kalman mode has one more validity rule, ``max_unverified_variance``: a predicted pixel that the
measurement does not cover (stereo rejected it: occlusion, no texture, a left-right conflict) stays
valid only while its own variance says it is accurate, ``P <= max_unverified_variance``: a large ``P``
marks a chain of unverified predictions, a stereo outlier carried on, or a depth edge (see
:func:`edge_variance`), and such pixels are much more often wrong (docs/decisions.md).

:func:`edge_variance` gives the variance a prediction has at its own depth edges: a pixel whose
3x3 neighbourhood spans disparities ``r`` apart may belong to either surface (the splat places an
edge only to within a pixel), a two-point spread of variance ``r^2 / 4``. Added to ``P`` before a
Kalman update, it lets the measurement win at the prediction's edges.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn
from torch.nn import functional as F

from ..core import (
    check_choice,
    check_finite,
    check_float,
    check_same_device,
    check_setting,
    check_shape,
    check_variance,
    use_compiled,
)
from ..core.dispatch import needs_grad
from ..core.errors import ValueRangeError
from . import _fuse_numba, _predict_numba

__all__ = ["Correction", "correct_disparity", "CorrectDisparity", "edge_variance", "QUANTISATION_VARIANCE"]

# Variance of the rounding error of integer disparities (uniform on [-1/2, 1/2]): 1/12 px^2.
QUANTISATION_VARIANCE = 1.0 / 12.0


class Correction(NamedTuple):
    """Result of :func:`correct_disparity`, every field ``(B, 1, H, W)``.

    Attributes:
        disparity: corrected disparity, px.
        variance: its variance, px^2 (see :func:`correct_disparity` for each rule).
        valid: bool, ``predicted_valid | measured_valid`` (Kalman mode with ``max_unverified_variance``: predictions
            without a valid measurement only where their variance is within it).
        outlier_count: consecutive verifications at which the pixel was gated out (dtype of the
            ``outlier_count`` passed in, else of ``predicted``); 0 after a fused or reset pixel.

    Example:
        >>> cor = correct_disparity(torch.full((1, 1, 2, 3), 4.0), torch.full((1, 1, 2, 3), 5.0), None)
        >>> cor.disparity.shape, cor.variance.shape, bool(cor.valid.all())
        (torch.Size([1, 1, 2, 3]), torch.Size([1, 1, 2, 3]), True)
        >>> round(cor.disparity[0, 0, 0, 0].item(), 4), cor.outlier_count[0, 0, 0, 0].item()  # 4 + 0.4 * 1: gated
        (4.4, 1.0)
    """

    disparity: torch.Tensor
    variance: torch.Tensor
    valid: torch.Tensor
    outlier_count: torch.Tensor


def _window_max(x: torch.Tensor, radius: int) -> torch.Tensor:
    """Maximum over the ``(2 radius + 1)^2`` window around each pixel of ``x`` ``(B, 1, H, W)`` (border: the part
    of the window inside the image). Shifted maxima along each axis, ``radius`` times (cheaper on the CPU than
    ``max_pool2d`` of a one-channel map). The torch path of :func:`edge_variance` (GPU, autograd, float64); float32
    CPU maps take a compiled pass instead (this one is memory-bound)."""
    out = x
    for _ in range(radius):
        src = out
        h = src.clone()
        torch.maximum(h[..., 1:], src[..., :-1], out=h[..., 1:])
        torch.maximum(h[..., :-1], src[..., 1:], out=h[..., :-1])
        out = h.clone()
        torch.maximum(out[..., 1:, :], h[..., :-1, :], out=out[..., 1:, :])
        torch.maximum(out[..., :-1, :], h[..., 1:, :], out=out[..., :-1, :])
    return out


def edge_variance(
    disparity: torch.Tensor,
    valid: torch.Tensor | None = None,
    kernel_size: int = 3,
    *,
    base: torch.Tensor | None = None,
) -> torch.Tensor:
    """Variance of a disparity map's depth-edge ambiguity: ``(r / 2)^2`` with ``r`` the local range.

    ``r`` is the spread (max - min) of the valid disparities in the ``kernel_size`` window around each
    pixel. A pixel whose window spans two surfaces ``r`` apart is on either one (a discrete map knows an
    edge only to within a pixel): equally likely, that is a variance of ``r^2 / 4``. On a smooth surface
    ``r`` is the slope times the window, a small term. Invalid pixels and invalid neighbours count 0.

    Args:
        disparity: ``(B, 1, H, W)`` px.
        valid: ``(B, 1, H, W)`` bool (None: all valid).
        kernel_size: odd window size.
        base: ``(B, 1, H, W)`` px^2 the result is added to (a prediction's own variance), in the same pass.

    Returns:
        ``(B, 1, H, W)`` px^2, >= 0, 0 where ``valid`` is False (``base +`` that with ``base``). With gradients
        wanted the torch path carries the graph to the window's largest and smallest valid disparities and to
        ``base``; which pixels those are is a hard decision (piecewise constant).

    >>> d = torch.tensor([[[[1.0, 1.0, 5.0, 5.0]]]])
    >>> edge_variance(d)
    tensor([[[[0., 4., 4., 0.]]]])
    """
    dims = check_shape(disparity, ["B", "1", "H", "W"], "disparity")
    check_float(disparity, "disparity")
    if valid is not None:
        check_shape(valid, ["B", "1", "H", "W"], "valid", dims)
        check_same_device(disparity, "disparity", valid=valid)
    if kernel_size < 1 or kernel_size % 2 == 0:
        raise ValueRangeError(f"kernel_size: must be a positive odd integer, got {kernel_size}")
    if base is not None:
        check_shape(base, ["B", "1", "H", "W"], "base", dims)
        check_same_device(disparity, "disparity", base=base)
    valid = torch.ones_like(disparity, dtype=torch.bool) if valid is None else _as_bool(valid, disparity)
    radius = kernel_size // 2
    if use_compiled(disparity, valid, base):
        # the same maxima and minima compiled (one pass instead of ~12 memory-bound torch ops), the base added in it
        return _predict_numba.edge_variance(disparity[:, 0].contiguous(), valid[:, 0].contiguous(), radius,
                                            None if base is None else base[:, 0].contiguous())[:, None]
    big = torch.finfo(disparity.dtype).max / 4
    if needs_grad(disparity, base):
        # out of place, so that the graph reaches the window's largest and smallest disparity (max_pool2d's padding
        # is -inf: the window's part inside the image, as _window_max)
        hi = F.max_pool2d(disparity.masked_fill(~valid, -big), kernel_size, stride=1, padding=radius)
        lo = F.max_pool2d((-disparity).masked_fill(~valid, -big), kernel_size, stride=1, padding=radius)
        variance = ((hi + lo).clamp_min(0) * valid).square() * 0.25
    else:
        with torch.no_grad():
            hi = _window_max(disparity.masked_fill(~valid, -big), radius)
            lo = _window_max((-disparity).masked_fill(~valid, -big), radius)
            spread = (hi + lo).clamp_min_(0).mul_(valid)  # max - min; a valid pixel sees itself, so both are finite
            variance = spread.square_().mul_(0.25)
    return variance if base is None else base + variance


def _as_bool(x: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    if x is None:
        return torch.ones_like(like, dtype=torch.bool)
    return x if x.dtype == torch.bool else x > 0.5


def correct_disparity(
    predicted: torch.Tensor,
    measured: torch.Tensor,
    measured_valid: torch.Tensor | None,
    fusion: str = "paper",
    gate: float = 0.5,
    gain: float = 0.4,
    predicted_variance: torch.Tensor | None = None,
    measured_variance: torch.Tensor | None = None,
    predicted_valid: torch.Tensor | None = None,
    outlier_count: torch.Tensor | None = None,
    kalman_gate: float = 3.0,
    reset_after: int = 2,
    min_variance: float = 1e-4,
    prior_variance: float = 1.0,
    max_unverified_variance: float | None = None,
    gate_softness: float | None = None,
) -> Correction:
    """Fuse the predicted disparity ``e`` with the measured ``s`` (docs/method.md, loop step 4).

    ``fusion="paper"`` (the paper's rule, reproduced exactly):

    * both valid and ``|e - s| > gate``: ``e <- e + gain (s - e)`` and the variance of that fixed-gain
      blend of two independent estimates, ``(1 - gain)^2 P + gain^2 R``;
    * both valid and ``|e - s| <= gate``: ``e`` and ``P`` unchanged (the paper's blind spot: errors
      below the gate are never corrected);
    * prediction invalid, measurement valid: ``e = s``, ``P = R``;
    * measurement invalid: ``e``, ``P`` unchanged.

    The outlier count only records, per pixel, consecutive verifications where the gate fired; it does
    not change the paper's output.

    ``fusion="kalman"``: both valid: innovation ``y = s - e``, ``S = P + R``. If ``|y| > kalman_gate
    sqrt(S)`` the pixel is an outlier: ``e``, ``P`` kept and its count incremented; once the count
    reaches ``reset_after`` it is reset (``e = s``, ``P = R``, count 0). Otherwise ``G = P / S``,
    ``e <- e + G y``, ``P <- (1 - G) P`` and the count is 0. Prediction invalid, measurement valid:
    ``e = s``, ``P = R``, count 0. Measurement invalid: everything carried. ``P`` is kept
    ``>= min_variance``.

    Both gates are hard decisions: the output is piecewise smooth in ``e`` and ``s``, and the gradient says nothing
    about moving a pixel across a gate. ``gate_softness`` replaces each by a logistic weight, so that gradients see
    the gate (the differentiable configuration of :class:`~egorefine.refine.EgoMotionRefiner`): in paper mode the
    correction is applied with weight ``w = sigmoid((|y| - gate) / gate_softness)`` (``gate_softness`` in px); in
    Kalman mode a pixel is an outlier with weight ``o = sigmoid((|y| - k sqrt(S)) / (gate_softness sqrt(S)))``
    (``gate_softness`` in standard deviations) and gets ``(1 - o)`` of the fused value plus ``o`` of the outlier
    value (the measurement once ``reset_after`` is reached, else the prediction). The outlier count still follows
    the hard gate. As ``gate_softness -> 0`` both rules become the hard ones.

    ``gate``, ``gain`` and ``kalman_gate`` may be 0-d tensors (learnable parameters); gradients then reach them.

    Args:
        predicted: ``(B, 1, H, W)`` predicted disparity ``e``, px.
        measured: ``(B, 1, H, W)`` measured disparity ``s``, px.
        measured_valid: ``(B, 1, H, W)`` bool (None: all valid).
        fusion: ``"paper"`` or ``"kalman"``.
        gate: px, the paper's gate (0.5).
        gain: the paper's gain alpha (0.4), in ``(0, 1]``.
        predicted_variance: ``(B, 1, H, W)`` px^2 (None: ``prior_variance``).
        measured_variance: ``(B, 1, H, W)`` px^2 from the matcher (None: 1/12, integer quantisation).
        predicted_valid: ``(B, 1, H, W)`` bool (None: all valid).
        outlier_count: ``(B, 1, H, W)`` consecutive outlier verifications so far (None: zeros).
        kalman_gate: gate of the Kalman mode in standard deviations of the innovation.
        reset_after: consecutive outliers after which a pixel is reset to the measurement (>= 1).
        min_variance: floor of the variance, px^2.
        prior_variance: px^2 assumed for the prediction when ``predicted_variance`` is None.
        max_unverified_variance: Kalman mode only: px^2, the largest variance with which a prediction the
            measurement does not cover stays valid (None: no limit, every such prediction stays valid).
        gate_softness: > 0: the soft gates above (paper: px; Kalman: standard deviations); None (the default): the
            hard gates of the rules as written.

    Returns:
        :class:`Correction` ``(disparity, variance, valid, outlier_count)``, each ``(B, 1, H, W)``.

    >>> e = torch.tensor([[[[1.0, 2.0]]]])
    >>> s = torch.tensor([[[[1.4, 3.0]]]])
    >>> correct_disparity(e, s, None).disparity  # 0.4 <= gate: kept; 1.0 > gate: 2 + 0.4 * 1
    tensor([[[[1.0000, 2.4000]]]])
    """
    dims = check_shape(predicted, ["B", "1", "H", "W"], "predicted")
    check_float(predicted, "predicted")
    check_shape(measured, ["B", "1", "H", "W"], "measured", dims)
    check_float(measured, "measured")
    for name, t in (
        ("measured_valid", measured_valid),
        ("predicted_variance", predicted_variance),
        ("measured_variance", measured_variance),
        ("predicted_valid", predicted_valid),
        ("outlier_count", outlier_count),
    ):
        if t is not None:
            check_shape(t, ["B", "1", "H", "W"], name, dims)
    # float32 CPU maps: one compiled pass per map says whether the checks below would pass
    variances = (predicted_variance, measured_variance)
    if not (all(t is None or t.dtype == torch.float32 for t in (predicted, measured, *variances))
            and use_compiled(predicted, measured, *variances) and _fuse_numba.plausible((predicted, measured),
                                                                                         variances)):
        check_finite(predicted, "predicted")
        check_finite(measured, "measured")
        for name, t in (("predicted_variance", predicted_variance), ("measured_variance", measured_variance)):
            if t is not None:
                check_variance(t, name)
    check_same_device(
        predicted,
        "predicted",
        measured=measured,
        measured_valid=measured_valid,
        predicted_variance=predicted_variance,
        measured_variance=measured_variance,
        predicted_valid=predicted_valid,
        outlier_count=outlier_count,
    )
    check_choice(fusion, ["paper", "kalman"], "fusion")
    gate, gain, kalman_gate = (check_setting(v, n) for v, n in ((gate, "gate"), (gain, "gain"),
                                                                  (kalman_gate, "kalman_gate")))
    if not gate >= 0:
        raise ValueRangeError(f"gate: must be >= 0, got {gate}")
    if not 0 < gain <= 1:
        raise ValueRangeError(f"gain: must be in (0, 1], got {gain}")
    if max_unverified_variance is not None and not max_unverified_variance > 0:
        raise ValueRangeError(f"max_unverified_variance: must be > 0 or None, got {max_unverified_variance}")
    if gate_softness is not None and not gate_softness > 0:
        raise ValueRangeError(f"gate_softness: must be > 0 or None, got {gate_softness}")
    if not kalman_gate > 0 or reset_after < 1 or not min_variance > 0 or not prior_variance > 0:
        raise ValueRangeError(
            "kalman_gate, min_variance and prior_variance must be > 0 and reset_after >= 1, got "
            f"{kalman_gate}, {min_variance}, {prior_variance}, {reset_after}"
        )

    e, s = predicted, measured.to(predicted.dtype)
    carried = [t.to(e.dtype) for t in (predicted_variance, measured_variance, outlier_count) if t is not None]
    kalman = fusion == "kalman"  # (the kernel implements the Kalman rule; the paper rule is a few torch ops)
    settings = [t for t in (gate, gain, kalman_gate) if isinstance(t, torch.Tensor)]
    if kalman and gate_softness is None and use_compiled(e, s, *carried, measured_valid, predicted_valid, *settings):
        # the same rule compiled: one pass instead of ~20 full-map operations; equal bit for bit (tests)
        P = torch.full_like(e, prior_variance) if predicted_variance is None else predicted_variance.to(e.dtype)
        R = torch.full_like(e, QUANTISATION_VARIANCE) if measured_variance is None else measured_variance.to(e.dtype)
        count = torch.zeros_like(e) if outlier_count is None else outlier_count.to(e.dtype)
        d, var, valid, cnt = _fuse_numba.kalman_fuse(
            e, s, _as_bool(measured_valid, e), _as_bool(predicted_valid, e), P, R, count, float(kalman_gate),
            reset_after,
            min_variance, max_unverified_variance)
        return Correction(d, var, valid, cnt if outlier_count is None else cnt.to(outlier_count.dtype))
    m_ok = _as_bool(measured_valid, e)
    p_ok = _as_bool(predicted_valid, e)
    P = torch.full_like(e, prior_variance) if predicted_variance is None else predicted_variance.to(e.dtype)
    R = torch.full_like(e, QUANTISATION_VARIANCE) if measured_variance is None else measured_variance.to(e.dtype)
    P, R = P.clamp_min(min_variance), R.clamp_min(min_variance)
    count = torch.zeros_like(e) if outlier_count is None else outlier_count
    zero = torch.zeros_like(count)

    both = m_ok & p_ok
    take = m_ok & ~p_ok  # a hole in the prediction: take the measurement
    innovation = s - e

    if fusion == "paper":
        fire = both & (innovation.abs() > gate)
        corrected, corrected_var = e + gain * innovation, (1 - gain) ** 2 * P + gain**2 * R
        if gate_softness is None:
            e_new = torch.where(fire, corrected, e)  # docs/method.md step 4: e <- e + alpha (s - e)
            P_new = torch.where(fire, corrected_var, P)
        else:  # the gate as a logistic weight of the correction
            w = torch.sigmoid((innovation.abs() - gate) / gate_softness)
            e_new = torch.where(both, e + w * gain * innovation, e)
            P_new = torch.where(both, w * corrected_var + (1 - w) * P, P)
        count_new = torch.where(fire, count + 1, torch.where(both, zero, count))
    else:
        S = P + R  # innovation variance (both > 0 after the clamp)
        bound = kalman_gate * S.sqrt()
        outlier = both & (innovation.abs() > bound)
        count_out = count + 1
        reset = outlier & (count_out >= reset_after)
        G = P / S
        fused, fused_var = e + G * innovation, (1 - G) * P
        if gate_softness is None:
            fuse = both & ~outlier
            e_new = torch.where(fuse, fused, e)
            P_new = torch.where(fuse, fused_var, P)
            e_new = torch.where(reset, s, e_new)
            P_new = torch.where(reset, R, P_new)
        else:  # outlier as a logistic weight; its value is the measurement once a reset is due, else the prediction
            o = torch.sigmoid((innovation.abs() - bound) / (gate_softness * S.sqrt()))
            due = (count_out >= reset_after) & both
            out_e, out_P = torch.where(due, s, e), torch.where(due, R, P)
            e_new = torch.where(both, (1 - o) * fused + o * out_e, e)
            P_new = torch.where(both, (1 - o) * fused_var + o * out_P, P)
        count_new = torch.where(outlier & ~reset, count_out, torch.where(both, zero, count))

    e_new = torch.where(take, s, e_new)
    P_new = torch.where(take, R, P_new).clamp_min(min_variance)
    count_new = torch.where(take, zero, count_new)
    valid = m_ok | p_ok
    if fusion == "kalman" and max_unverified_variance is not None:
        # a prediction stereo could not check is vouched for by its own variance only
        valid = m_ok | (p_ok & (P <= max_unverified_variance))
    return Correction(e_new, P_new, valid, count_new)


class CorrectDisparity(nn.Module):
    """Module form of :func:`correct_disparity`: stores the settings, ``forward`` calls the function.

    >>> cor = CorrectDisparity(fusion="kalman")(torch.ones(1, 1, 2, 3), torch.ones(1, 1, 2, 3), None)
    >>> cor.disparity.shape
    torch.Size([1, 1, 2, 3])
    """

    def __init__(
        self,
        fusion: str = "paper",
        gate: float = 0.5,
        gain: float = 0.4,
        kalman_gate: float = 3.0,
        reset_after: int = 2,
        min_variance: float = 1e-4,
        prior_variance: float = 1.0,
        max_unverified_variance: float | None = None,
    ) -> None:
        super().__init__()
        check_choice(fusion, ["paper", "kalman"], "fusion")
        self.fusion = fusion
        self.gate = gate
        self.gain = gain
        self.kalman_gate = kalman_gate
        self.reset_after = reset_after
        self.min_variance = min_variance
        self.prior_variance = prior_variance
        self.max_unverified_variance = max_unverified_variance

    def forward(
        self,
        predicted: torch.Tensor,
        measured: torch.Tensor,
        measured_valid: torch.Tensor | None,
        predicted_variance: torch.Tensor | None = None,
        measured_variance: torch.Tensor | None = None,
        predicted_valid: torch.Tensor | None = None,
        outlier_count: torch.Tensor | None = None,
    ) -> Correction:
        return correct_disparity(
            predicted,
            measured,
            measured_valid,
            fusion=self.fusion,
            gate=self.gate,
            gain=self.gain,
            predicted_variance=predicted_variance,
            measured_variance=measured_variance,
            predicted_valid=predicted_valid,
            outlier_count=outlier_count,
            kalman_gate=self.kalman_gate,
            reset_after=self.reset_after,
            min_variance=self.min_variance,
            prior_variance=self.prior_variance,
            max_unverified_variance=self.max_unverified_variance,
        )
