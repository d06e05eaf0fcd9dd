"""Block matching: cost volume -> (box | SGM) aggregation -> winner-takes-all or soft-argmin
-> sub-pixel fit -> validity checks (left-right, uniqueness, texture).

The box-aggregated path works on strips of rows so that memory stays at a few
``(B, D, h, W)`` strips whatever the image size; SGM needs the whole volume (its vertical
paths cross every row) and holds about four ``(B, D, H, W)`` volumes. The default matcher
(SAD on the x-Sobel prefiltered images, box aggregation) runs in exact int16 arithmetic
whenever no gradient is needed: compiled for float32 CPU tensors (:mod:`egorefine.stereo._sad_numba`,
numba), in torch otherwise (:mod:`egorefine.stereo.fast`), with the same results. Census + SGM on
float32 CPU tensors without gradient runs compiled too (:mod:`egorefine.stereo._sgm_numba`; about
6 bytes per candidate), with the same results as the torch path.
"""

from __future__ import annotations

import struct
from functools import partial
from typing import NamedTuple

import torch
from torch import nn

from ..core import (
    DTypeError,
    ShapeError,
    ValueRangeError,
    _graphs,
    check_choice,
    check_image,
    check_same_device,
    check_shape,
    to_grey,
    use_compiled,
)
from ..core.dispatch import needs_grad
from . import _fill_numba, _sad_numba, _sgm_numba, _texture_numba
from .cost import COSTS, INVALID_COST, _Features, box_mean_same, prefilter_xsobel, strip_volume
from .fast import _QUANTISATION_VARIANCE, INVALID_VARIANCE, int_scale, match_sad_int
from .sgm import SGM_PATHS, sgm_aggregate
from .speckle import clear_invalid_, remove_speckles, remove_speckles_cleared_

__all__ = ["StereoOutput", "block_matching", "match_stereo", "fill_invalid", "BlockMatching", "INVALID_VARIANCE"]

AGGREGATIONS = ("box", "sgm")
SUBPIXEL_FITS = ("parabola", "equiangular")
# SGM penalties per cost, in that cost's units (window-mean SAD of the prefiltered image, 1 - ZNCC); census's per
# bit of the census string (times census_window**2 - 1 gives mean Hamming distance units): strong smoothing, which
# noisy, weakly textured surfaces need before a winner passes the checks (docs/decisions.md, issue 17)
_SGM_PENALTIES = {"sad": (0.006, 0.05), "zncc": (0.05, 0.4), "census": (2.0 / 3.0, 8.0 / 3.0)}
# the uniqueness ratio per aggregation when none is given: SGM's aggregated costs carry the path penalties, so
# their relative margins are smaller than a box sum's
UNIQUENESS_RATIOS = {"box": 0.15, "sgm": 0.1}
_TEMPERATURES = {"sad": 0.008, "zncc": 0.05, "census": 0.2}
# cost floor of the variance model per cost (keeps a perfect match's variance finite), in that cost's units
COST_FLOORS = {"sad": 1e-3, "zncc": 1e-2, "census": 0.1}
# the exact int16 path of the default SAD matcher (False: always the float path, for comparisons)
_INTEGER_PATH = True
_STRIP_ELEMENTS = 1 << 19  # ~2 MB of float32 per strip volume: stays in cache
# on a GPU launches, not caches, set the time: strips of up to 256 MB (docs/decisions.md)
_GPU_STRIP_ELEMENTS = 1 << 26
# INVALID_COST's float32 bit pattern read as int32 (the encoded value of an out-of-view candidate)
_INVALID_CODE = struct.unpack("<i", struct.pack("<f", INVALID_COST))[0]


class StereoOutput(NamedTuple):
    """Result of :func:`match_stereo`.

    Attributes:
        disparity: ``(B, 1, H, W)`` left-view disparity in px, 0 where invalid.
        valid: ``(B, 1, H, W)`` bool, the pixels that passed every check.
        variance: ``(B, 1, H, W)`` measurement variance in px^2 (>= 1/12; INVALID_VARIANCE where invalid), a
            heuristic of the detached costs: no gradient.

    Example:
        >>> left = torch.rand(1, 1, 24, 32)
        >>> out = match_stereo(left, torch.roll(left, -3, dims=3), 8)  # the right image: shifted 3 px left
        >>> out.disparity.shape, out.valid.dtype, out.variance.shape
        (torch.Size([1, 1, 24, 32]), torch.bool, torch.Size([1, 1, 24, 32]))
        >>> torch.allclose(out.disparity[0, 0, 8:-8, 12:-8], torch.tensor(3.0), atol=0.1)
        True
    """

    disparity: torch.Tensor
    valid: torch.Tensor
    variance: torch.Tensor


def _check_inputs(left: torch.Tensor, right: torch.Tensor, max_disparity: int, min_disparity: int, block_size: int,
                  cost: str, aggregation: str, subpixel_fit: str, sgm_paths: int, temperature: float | None,
                  differentiable: bool, soft_radius: int | None, census_window: int, speckle_size: int = 0,
                  speckle_range: float = 1.0, uniqueness_ratio: float | None = None, sgm_p1: float | None = None,
                  sgm_p2: float | None = None, census_max_distance: float | None = None) -> None:
    dims = check_shape(left, ["B", "1|3", "H", "W"], "left")
    check_shape(right, ["B", "1|3", "H", "W"], "right", dims)
    check_same_device(left, "left", right=right)
    check_image(left, "left", dims)
    check_image(right, "right", dims)
    width = dims["W"]
    for name, value in (("max_disparity", max_disparity), ("min_disparity", min_disparity),
                        ("block_size", block_size), ("sgm_paths", sgm_paths)):
        if isinstance(value, bool) or not isinstance(value, int):
            raise DTypeError(f"{name}: expected an int, got {type(value).__name__}")
    if not 0 < max_disparity < width:
        raise ValueRangeError(f"max_disparity: expected 0 < max_disparity < width={width}, got {max_disparity}")
    if not 0 <= min_disparity < max_disparity:
        raise ValueRangeError(
            f"min_disparity: expected 0 <= min_disparity < max_disparity={max_disparity}, got {min_disparity}")
    if block_size < 1 or block_size % 2 == 0 or block_size > min(dims["H"], width):
        raise ValueRangeError(f"block_size: expected an odd size in [1, min(H, W)], got {block_size}")
    check_choice(cost, COSTS, "cost")
    check_choice(aggregation, AGGREGATIONS, "aggregation")
    check_choice(subpixel_fit, SUBPIXEL_FITS, "subpixel_fit")
    if census_window not in (3, 5, 7):
        raise ValueRangeError(f"census_window: expected 3, 5 or 7, got {census_window!r}")
    if sgm_paths not in SGM_PATHS:
        raise ValueRangeError(f"sgm_paths: expected one of {SGM_PATHS}, got {sgm_paths}")
    if differentiable and cost == "census":
        raise ValueRangeError("cost: 'census' has no gradient; use 'sad' or 'zncc' with differentiable=True")
    if soft_radius is not None and (isinstance(soft_radius, bool) or not isinstance(soft_radius, int)
                                    or soft_radius < 1):
        raise ValueRangeError(f"soft_radius: expected an int >= 1 or None, got {soft_radius!r}")
    if temperature is not None and not temperature > 0:
        raise ValueRangeError(f"temperature: expected > 0, got {temperature}")
    for name, value in (("uniqueness_ratio", uniqueness_ratio), ("sgm_p1", sgm_p1), ("sgm_p2", sgm_p2)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0):
            raise ValueRangeError(f"{name}: expected a number >= 0 or None, got {value!r}")
    if census_max_distance is not None and (isinstance(census_max_distance, bool) or not isinstance(
            census_max_distance, (int, float)) or not 0 <= census_max_distance <= 1):
        raise ValueRangeError(f"census_max_distance: expected a number in [0, 1] or None, got {census_max_distance!r}")
    if sgm_p1 is not None and sgm_p2 is not None and sgm_p2 < sgm_p1:
        raise ValueRangeError(f"sgm_p2: expected >= sgm_p1={sgm_p1}, got {sgm_p2}")
    if isinstance(speckle_size, bool) or not isinstance(speckle_size, int) or speckle_size < 0:
        raise ValueRangeError(f"speckle_size: expected an int >= 0, got {speckle_size!r}")
    if not speckle_range >= 0:
        raise ValueRangeError(f"speckle_range: expected >= 0, got {speckle_range}")


def _gather(vol: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    return torch.gather(vol, 1, index)


def _index_bits(num: int) -> int:
    return max(1, (num - 1).bit_length())


def _encode(vol: torch.Tensor) -> torch.Tensor:
    """Non-negative float32 costs with their disparity index written into the low mantissa bits.

    For non-negative IEEE floats the integer order is the float order, so one fast ``amin``
    over the disparity axis returns the winner's (slightly rounded) cost *and* its index
    (ties go to the lower index); ``argmin`` along a non-inner axis is several times slower.
    Costs lose ``log2(D)`` of their 24 mantissa bits (relative error < 2**-16 for D <= 128),
    which only matters for near-ties. Returns an int32 tensor; a float32 ``vol`` that needs
    no gradient is encoded in place (its values then carry that tiny rounding too).
    """
    num = vol.shape[1]
    bits = _index_bits(num)
    index = torch.arange(num, device=vol.device, dtype=torch.int32).view(1, num, 1, 1)
    if vol.requires_grad or vol.dtype != torch.float32:
        work = vol.detach().to(torch.float32, copy=True)
    else:
        work = vol
    # clamp: a rounding-negative cost (1 - ZNCC) would read as a huge negative integer
    code = work.clamp_min_(0).view(torch.int32)
    return code.bitwise_and_(-(1 << bits)).bitwise_or_(index)


def _decode_index(code: torch.Tensor, num: int) -> torch.Tensor:
    return torch.bitwise_and(code, (1 << _index_bits(num)) - 1).long()


def _right_view_index(code: torch.Tensor, max_d: int) -> torch.Tensor:
    """Winner of the right view from the encoded left volume (reversed order) by diagonal
    re-indexing: cost_right(xr, d) = cost_left(xr + d, d). Returns the reversed index ``(B, 1, h, W)``."""
    b, num, h, w = code.shape
    padded = torch.nn.functional.pad(code, (0, max_d), value=_INVALID_CODE).contiguous()
    sb, sj, sh, sw = padded.stride()
    # entry [b, j, y, xr] = padded[b, j, y, xr + max_d - 1 - j]
    diag = padded.as_strided((b, num, h, w), (sb, sj - sw, sh, sw), padded.storage_offset() + (max_d - 1) * sw)
    return _decode_index(diag.amin(dim=1, keepdim=True), num)


def _select(vol: torch.Tensor, max_d: int, opts: dict, raw: torch.Tensor | None = None
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Disparity, validity and variance of a strip from its (reversed-order) aggregated cost ``(B, D, h, W)``.

    ``vol`` holds window sums; ``opts["scale"]`` (= block**2) converts them to window means. With ``raw`` (the
    strip's costs before aggregation) and ``opts["max_raw_cost"]`` (window-sum units), a winner whose own raw cost
    exceeds that bound is not valid.
    """
    num = vol.shape[1]
    scale = opts["scale"]
    code = _encode(vol)
    best = code.amin(dim=1, keepdim=True)
    j = _decode_index(best, num)
    d_int = (max_d - 1 - j).to(vol.dtype)
    jm, jp = (j - 1).clamp_min(0), (j + 1).clamp_max(num - 1)
    c_best = _gather(vol, j)
    c0 = c_best.detach()
    c_plus, c_minus = _gather(vol, jm), _gather(vol, jp)  # reversed order: j-1 is d+1
    interior = (j > 0) & (j < num - 1) & (c_plus.detach() < INVALID_COST / 2) & (c_minus.detach() < INVALID_COST / 2)
    curvature = c_minus - 2 * c_best + c_plus
    eps = torch.finfo(vol.dtype).eps * 16 * scale
    if opts["subpixel_fit"] == "parabola":
        denom = 2 * curvature
    else:  # equiangular (V-shaped) fit, the natural model for SAD-like costs
        denom = 2 * (torch.maximum(c_minus, c_plus) - c_best)
    # clamp before dividing: a flat or non-interior minimum has no defined offset
    offset = ((c_minus - c_plus) / denom.clamp_min(eps)).clamp(-0.5, 0.5)
    offset = torch.where(interior, offset, torch.zeros_like(offset))
    if opts["differentiable"]:
        logits = -vol / (opts["temperature"] * scale)
        if opts["soft_radius"] is not None:
            # local soft-argmin: only candidates within soft_radius of the hard winner take part,
            # so a second mode elsewhere in the range cannot drag the mean (real images are multimodal)
            idx = torch.arange(num, device=vol.device).view(1, num, 1, 1)
            logits = logits.masked_fill((idx - j).abs() > opts["soft_radius"], float("-inf"))
        weights = torch.softmax(logits, dim=1)
        values = (max_d - 1 - torch.arange(num, device=vol.device, dtype=vol.dtype)).view(1, num, 1, 1)
        disparity = (weights * values).sum(dim=1, keepdim=True)
    elif opts["subpixel"]:
        disparity = d_int + offset
    else:
        disparity = d_int + 0 * c_best  # keeps the graph (zero gradient) for a uniform return
    # validity checks on the detached costs. A winner at the end of the feasible range (the
    # search limit, or the last candidate still inside the right image) may be a truncated
    # minimum whose truth lies beyond: rejected (d = 0 with min_disparity = 0 is a true end).
    valid = (c0 < INVALID_COST / 2) & (j > 0) & (c_plus.detach() < INVALID_COST / 2)
    if opts["min_disparity"] > 0:
        valid &= j < num - 1
    if opts["lr_check"]:
        jr = _right_view_index(code, max_d)
        x = torch.arange(vol.shape[-1], device=vol.device).view(1, 1, 1, -1)
        d_left = max_d - 1 - j  # integer disparity of the left winner
        xr = (x - d_left).clamp(0, vol.shape[-1] - 1)
        d_right = max_d - 1 - torch.gather(jr, 3, xr)
        valid &= (d_right - d_left).abs() <= opts["lr_threshold"]
    if opts["uniqueness_ratio"] > 0:
        # knock out the winner and its two neighbours, then the best of the rest
        inf = torch.tensor(float("inf"), dtype=torch.float32, device=vol.device).view(torch.int32)
        for nb in (jm, j, jp):
            code.scatter_(1, nb, inf.expand_as(best))
        second = code.amin(dim=1, keepdim=True).view(torch.float32)
        valid &= second > c0 * (1 + opts["uniqueness_ratio"])
    if raw is not None and opts.get("max_raw_cost") is not None:
        # float32 bound as the compiled path rounds it (raw census costs are exact integers in float32)
        limit = torch.tensor(opts["max_raw_cost"], dtype=torch.float32).to(raw.dtype)
        valid &= _gather(raw.detach(), j) <= limit.to(raw.device)
    # variance: quantisation floor plus the spread of a noisy minimum, larger when the
    # minimum is shallow (small curvature) relative to its own cost level (heuristic; smooth in the costs, so a
    # loss through a Kalman gain reaches the images by it too)
    kd = curvature.clamp_min(0)
    variance = _QUANTISATION_VARIANCE + 0.25 * ((c_best + opts["cost_floor"] * scale) / (kd + eps)) ** 2
    variance = torch.where(interior, variance.clamp_max(INVALID_VARIANCE), torch.ones_like(variance))
    return disparity, valid, variance


def _sgm_outputs(volume: torch.Tensor, *, p1: float, p2: float, paths: int) -> tuple[torch.Tensor]:
    """``(sgm_aggregate(volume, p1, p2, paths),)``: the form :func:`egorefine.core._graphs.replay` takes."""
    return (sgm_aggregate(volume, p1, p2, paths),)


def _integer_scale(cost: str, aggregation: str, prefilter: bool, block_size: int, prefilter_cap: float,
                   needs_grad: bool, num: int) -> int:
    """The quantisation scale of the exact int16 SAD path (:mod:`egorefine.stereo.fast`) where it applies, else 0."""
    if not (_INTEGER_PATH and cost == "sad" and prefilter and aggregation == "box" and not needs_grad
            and num <= 1 << 14):
        return 0
    return int_scale(block_size, prefilter_cap)


def _compiled_sad(grey_l: torch.Tensor, grey_r: torch.Tensor) -> bool:
    """The int16 SAD path (taken only without gradient) runs compiled (:mod:`egorefine.stereo._sad_numba`) for
    these images: :func:`~egorefine.core.use_compiled`."""
    return use_compiled(grey_l, grey_r)


def _use_numba_sgm(grey_l: torch.Tensor, grey_r: torch.Tensor, cost: str, num: int, differentiable: bool) -> bool:
    """The compiled census + SGM path applies: :func:`~egorefine.core.use_compiled` and the kernel's limits (the
    census cost, the hard winner, at least 2 candidates)."""
    census_hard = cost == "census" and not differentiable and num >= 2
    return census_hard and use_compiled(grey_l, grey_r)


def match_stereo(
    left: torch.Tensor,
    right: torch.Tensor,
    max_disparity: int,
    min_disparity: int = 0,
    block_size: int = 9,
    cost: str = "sad",
    aggregation: str = "box",
    subpixel: bool = True,
    subpixel_fit: str = "equiangular",
    lr_check: bool = True,
    lr_threshold: int = 1,
    uniqueness_ratio: float | None = None,
    texture_threshold: float = 0.004,
    prefilter: bool = True,
    prefilter_cap: float = 31.0 / 255.0,
    census_window: int = 7,
    sgm_p1: float | None = None,
    sgm_p2: float | None = None,
    sgm_paths: int = 4,
    differentiable: bool = False,
    temperature: float | None = None,
    soft_radius: int | None = 2,
    speckle_size: int = 200,
    speckle_range: float = 1.0,
    census_max_distance: float | None = None,
) -> StereoOutput:
    """Dense stereo matching of a rectified pair; disparity, validity and per-pixel variance.

    Args:
        left, right: ``(B, 1|3, H, W)`` float images in [0, 1] (colour is converted to grey).
        max_disparity: candidates are ``min_disparity <= d < max_disparity`` (``0 < max_disparity < W``).
        min_disparity: smallest candidate (>= 0).
        block_size: odd window size of the cost aggregation.
        cost: ``"sad"`` (on the x-Sobel prefiltered image, as OpenCV's BM), ``"zncc"`` or ``"census"``.
        aggregation: ``"box"`` (block matching) or ``"sgm"`` (semi-global, after the box mean).
        subpixel: refine the winner with a fit through its two neighbours.
        subpixel_fit: ``"parabola"`` or ``"equiangular"``.
        lr_check: left-right consistency (right winners from the same volume), tolerance ``lr_threshold`` px.
        uniqueness_ratio: reject when a candidate beyond +-1 px of the winner costs less than
            ``(1 + ratio)`` times the winner's (0 disables). None: 0.15 for box aggregation, 0.1 for SGM, whose
            aggregated costs carry the path penalties and so differ by smaller ratios.
        texture_threshold: reject windows whose mean ``|x-Sobel|`` (clipped, [0,1] grey units) is below it.
        prefilter, prefilter_cap: x-Sobel prefilter of the SAD cost and its clip level.
        census_window: census window (3, 5 or 7; 8, 24 or 48 bits). Default 7: the 48 comparisons tell noisy,
            weakly textured windows apart better than 24 do.
        sgm_p1, sgm_p2: SGM penalties for a disparity change of one px and of more between neighbours, in cost
            units (window means; census: mean Hamming distance), ``0 <= sgm_p1 <= sgm_p2``. None: per-cost
            defaults; census's are 2/3 and 8/3 times the number of census bits (``census_window**2 - 1``), strong
            smoothing, which noisy and weakly textured surfaces need for their winners to pass the checks.
        sgm_paths: 4 (default) or 8 scanline directions, or 3 (OpenCV SGBM 3-way's: horizontal and top-down;
            faster, less accurate).
        census_max_distance: census + SGM only: reject a winner whose own window-mean Hamming distance (before
            aggregation) exceeds this share of the census bits, in [0, 1]; unrelated windows score about 0.5. Strong
            smoothing can carry a winner across windows that match nothing (noise, or a surface seen by one camera
            only); this keeps such a pixel out. Default None (no such check): on noisy, weakly textured surfaces
            right matches score like unrelated windows too, so the check costs much of SGM's density there
            (docs/decisions.md).
        differentiable: disparity by soft-argmin over ``-cost / temperature`` (gradients reach
            both images); the checks still use the hard winner.
        temperature: soft-argmin temperature in cost units (None: per-cost default).
        soft_radius: the soft-argmin averages the candidates within this many px of the hard winner
            (None: the whole range, which multimodal real-image costs bias badly).
        speckle_size, speckle_range: after the checks, invalidate every region of at most ``speckle_size``
            pixels whose 4-neighbours differ by at most ``speckle_range`` px (:func:`remove_speckles`; OpenCV's
            ``speckleWindowSize`` / ``speckleRange``; 0: off). Default 200 px within 1 px: a wrong match on weak
            texture or sensor noise rarely agrees with its neighbours over a large area, while a surface does; twice
            the window OpenCV users run SGBM with, which removes more wrong matches for few right ones
            (measurements in docs/decisions.md).

    Returns:
        :class:`StereoOutput` ``(disparity, valid, variance)``, each ``(B, 1, H, W)``.

    Raises:
        ShapeError, DTypeError, DeviceError, ValueRangeError: bad input, naming the argument.

    >>> out = match_stereo(torch.rand(2, 1, 16, 24), torch.rand(2, 1, 16, 24), 8, block_size=5)
    >>> out.disparity.shape, out.valid.dtype, out.variance.shape
    (torch.Size([2, 1, 16, 24]), torch.bool, torch.Size([2, 1, 16, 24]))
    """
    _check_inputs(left, right, max_disparity, min_disparity, block_size, cost, aggregation, subpixel_fit, sgm_paths,
                  temperature, differentiable, soft_radius, census_window, speckle_size, speckle_range,
                  uniqueness_ratio, sgm_p1, sgm_p2, census_max_distance)
    if uniqueness_ratio is None:
        uniqueness_ratio = UNIQUENESS_RATIOS[aggregation]
    out = _match(left, right, max_disparity, min_disparity, block_size, cost, aggregation, subpixel, subpixel_fit,
                 lr_check, lr_threshold, uniqueness_ratio, texture_threshold, prefilter, prefilter_cap, census_window,
                 sgm_p1, sgm_p2, sgm_paths, differentiable, temperature, soft_radius, census_max_distance)
    return _despeckle(out, speckle_size, speckle_range)


def _despeckle(out: StereoOutput, speckle_size: int, speckle_range: float) -> StereoOutput:
    """A matcher's fresh output with its speckles (:func:`remove_speckles`) made not valid; unchanged for
    ``speckle_size == 0``. Compiled, it clears the removed pixels of ``out``'s maps in place."""
    if speckle_size <= 0:
        return out
    # compiled: the removed pixels cleared in the pass that writes the mask (fresh outputs of the matcher)
    valid = remove_speckles_cleared_(out.disparity, out.valid, out.variance, speckle_size, speckle_range,
                                     INVALID_VARIANCE)
    if valid is not None:
        return StereoOutput(out.disparity, valid, out.variance)
    valid = remove_speckles(out.disparity, out.valid, speckle_size, speckle_range)
    if use_compiled(out.disparity, out.variance, valid):  # compiled: no torch pass over the full maps
        clear_invalid_(valid, out.disparity, out.variance, INVALID_VARIANCE)  # (fresh outputs of the matcher)
        return StereoOutput(out.disparity, valid, out.variance)
    return StereoOutput(torch.where(valid, out.disparity, torch.zeros_like(out.disparity)), valid,
                        torch.where(valid, out.variance, torch.full_like(out.variance, INVALID_VARIANCE)))


def _sgm_penalties(cost: str, census_window: int, sgm_p1: float | None, sgm_p2: float | None,
                   scale: float) -> tuple[float, float]:
    """SGM's ``(P1, P2)`` in the cost volume's units: the per-cost defaults (census: per census bit) or the given
    values, times the window sum's ``scale``."""
    p1, p2 = _SGM_PENALTIES[cost]
    if cost == "census":  # per census bit
        p1, p2 = p1 * (census_window * census_window - 1), p2 * (census_window * census_window - 1)
    return (p1 if sgm_p1 is None else sgm_p1) * scale, (p2 if sgm_p2 is None else sgm_p2) * scale


def _mask_untextured_compiled(out: tuple[torch.Tensor, torch.Tensor, torch.Tensor], grey_l: torch.Tensor,
                              block_size: int, prefilter_cap: float, texture_threshold: float) -> StereoOutput:
    """A compiled matcher's fresh CPU ``(disparity, valid, variance)`` with the texture check applied and the
    maps cleared where not valid, in place in one compiled pass (:mod:`egorefine.stereo._texture_numba`: the
    float path's decisions, no torch pass over the full maps)."""
    return StereoOutput(*_texture_numba.mask_untextured(out, grey_l, block_size, prefilter_cap, texture_threshold,
                                                        INVALID_VARIANCE))


def _match(left: torch.Tensor, right: torch.Tensor, max_disparity: int, min_disparity: int, block_size: int, cost: str,
           aggregation: str, subpixel: bool, subpixel_fit: str, lr_check: bool, lr_threshold: int,
           uniqueness_ratio: float, texture_threshold: float, prefilter: bool, prefilter_cap: float,
           census_window: int, sgm_p1: float | None, sgm_p2: float | None, sgm_paths: int, differentiable: bool,
           temperature: float | None, soft_radius: int | None, census_max_distance: float | None = None
           ) -> StereoOutput:
    """:func:`match_stereo` on checked inputs, before the speckle filter."""
    grey_l, grey_r = to_grey(left), to_grey(right)
    b, _, h, w = grey_l.shape
    num = max_disparity - min_disparity
    opts = {
        "subpixel": subpixel, "subpixel_fit": subpixel_fit, "lr_check": lr_check, "lr_threshold": lr_threshold,
        "uniqueness_ratio": uniqueness_ratio, "differentiable": differentiable, "soft_radius": soft_radius,
        "temperature": temperature if temperature is not None else _TEMPERATURES[cost],
        "cost_floor": COST_FLOORS[cost],
        "scale": float(block_size * block_size),
        "min_disparity": min_disparity,
        # the raw-cost bound of census + SGM, in window-sum units
        "max_raw_cost": (None if census_max_distance is None or cost != "census" or aggregation != "sgm" else
                         census_max_distance * (census_window * census_window - 1) * block_size * block_size),
    }
    grad = needs_grad(left, right)
    scale = _integer_scale(cost, aggregation, prefilter, block_size, prefilter_cap, differentiable or grad, num)
    if scale:
        # exact int16 fast path (the decisions of the float path below, without its float rounding;
        # a right-view tie within lr_threshold of the left winner passes the left-right check)
        if _compiled_sad(grey_l, grey_r):
            return StereoOutput(*_sad_numba.match_sad_compiled(grey_l, grey_r, max_disparity, min_disparity,
                                                               block_size, prefilter_cap, scale,
                                                               {**opts, "texture_threshold": texture_threshold}))
        return StereoOutput(*match_sad_int(grey_l.detach(), grey_r.detach(), max_disparity, min_disparity,
                                           block_size, prefilter_cap, scale,
                                           {**opts, "texture_threshold": texture_threshold}))
    parts: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
    strip = _STRIP_ELEMENTS if grey_l.device.type == "cpu" else _GPU_STRIP_ELEMENTS
    if aggregation == "sgm":
        p1, p2 = _sgm_penalties(cost, census_window, sgm_p1, sgm_p2, opts["scale"])
    if aggregation == "sgm" and _use_numba_sgm(grey_l, grey_r, cost, num, differentiable):
        # CPU inference: census, SGM, selection, the texture check and the masking compiled (the same float32
        # results as below; with 3 paths the checks run in each stripe's job), no torch pass over the full maps
        return StereoOutput(*_sgm_numba.census_sgm_select(
            grey_l, grey_r, max_disparity, min_disparity, block_size, census_window, p1, p2, sgm_paths, opts,
            texture=(grey_l, block_size, prefilter_cap, texture_threshold, INVALID_VARIANCE))[:3])
    # texture check: mean clipped |x-Sobel| over the block (a constant image scores 0)
    texture = box_mean_same(prefilter_xsobel(grey_l.detach(), prefilter_cap).abs(), block_size)
    textured = texture >= texture_threshold
    if aggregation == "sgm":
        feat = _Features(grey_l, grey_r, cost, block_size, max_disparity, census_window, prefilter, prefilter_cap)
        vol = strip_volume(feat, 0, h, min_disparity)
        raw = vol if opts["max_raw_cost"] is not None else None  # (sgm_aggregate does not write into its input)
        if _graphs.usable(vol):
            # CUDA inference: the scanline recursion's ~8 launches per step (2 (H + W) steps) replayed as one graph
            sgm = partial(_sgm_outputs, p1=p1, p2=p2, paths=sgm_paths)
            vol = _graphs.replay(sgm, ("sgm", p1, p2, sgm_paths), vol)[0]
        else:
            vol = sgm_aggregate(vol, p1, p2, sgm_paths)
        rows = max(1, strip // max(1, b * num * w))
        for y0 in range(0, h, rows):
            parts.append(_select(vol[:, :, y0 : y0 + rows], max_disparity, opts,
                                 None if raw is None else raw[:, :, y0 : y0 + rows]))
    else:
        feat = _Features(grey_l, grey_r, cost, block_size, max_disparity, census_window, prefilter, prefilter_cap)
        rows = max(1, strip // max(1, b * num * (w + block_size)))
        for y0 in range(0, h, rows):
            y1 = min(h, y0 + rows)
            parts.append(_select(strip_volume(feat, y0, y1, min_disparity), max_disparity, opts))
    disparity = torch.cat([p[0] for p in parts], dim=2)
    valid = torch.cat([p[1] for p in parts], dim=2) & textured
    variance = torch.cat([p[2] for p in parts], dim=2)
    disparity = torch.where(valid, disparity, torch.zeros_like(disparity))
    variance = torch.where(valid, variance, torch.full_like(variance, INVALID_VARIANCE))
    return StereoOutput(disparity, valid, variance)


def fill_invalid(primary: StereoOutput, secondary: StereoOutput) -> StereoOutput:
    """One map from two matchers: ``primary`` where it found a match, ``secondary`` where only it did.

    A local matcher's valid pixels are its accurate ones, and its per-pixel errors are noise that temporal fusion
    averages away; a global matcher (SGM) also matches the weakly textured pixels a local window cannot, with
    errors that are mostly its smoothing's bias. Filling the first's holes from the second keeps the first's
    accuracy where it has it and the second's density (how :class:`~egorefine.refine.EgoMotionRefiner`'s Kalman
    mode verifies by default, ``StereoOptions.fill``).

    Args:
        primary, secondary: :class:`StereoOutput` s of one pair, each field ``(B, 1, H, W)``.

    Returns:
        :class:`StereoOutput`: disparity and variance from ``primary`` where ``primary.valid``, else from
        ``secondary``; valid where either is. Gradients reach both through the pixels each supplies.

    Example:
        >>> ones = torch.ones(1, 1, 1, 3)
        >>> a = StereoOutput(ones, torch.tensor([[[[True, False, False]]]]), ones)
        >>> b = StereoOutput(2 * ones, torch.tensor([[[[True, True, False]]]]), 3 * ones)
        >>> out = fill_invalid(a, b)
        >>> out.disparity.flatten().tolist(), out.valid.flatten().tolist(), out.variance.flatten().tolist()
        ([1.0, 2.0, 2.0], [True, True, False], [1.0, 3.0, 3.0])
    """
    if primary.disparity.shape != secondary.disparity.shape:
        raise ShapeError(f"fill_invalid: primary is {tuple(primary.disparity.shape)}, secondary "
                         f"{tuple(secondary.disparity.shape)}; expected the same (B, 1, H, W)")
    keep = primary.valid
    if keep.dtype == torch.bool and secondary.valid.dtype == torch.bool and use_compiled(
            primary.disparity, primary.variance, secondary.disparity, secondary.variance, keep, secondary.valid):
        # one compiled pass, no torch pass over the full maps (the loop's CPU inference path)
        return StereoOutput(*_fill_numba.fill_invalid(primary, secondary))
    return StereoOutput(torch.where(keep, primary.disparity, secondary.disparity), keep | secondary.valid,
                        torch.where(keep, primary.variance, secondary.variance))


def block_matching(left: torch.Tensor, right: torch.Tensor, max_disparity: int, **kwargs) -> tuple[
        torch.Tensor, torch.Tensor]:
    """Disparity and validity of a rectified pair; see :func:`match_stereo` for every keyword.

    Returns:
        ``(disparity, valid)``: ``(B, 1, H, W)`` float disparity in px (0 where invalid) and bool mask.

    >>> d, v = block_matching(torch.rand(1, 3, 16, 24), torch.rand(1, 3, 16, 24), 8, block_size=5)
    >>> d.shape, v.shape
    (torch.Size([1, 1, 16, 24]), torch.Size([1, 1, 16, 24]))
    """
    out = match_stereo(left, right, max_disparity, **kwargs)
    return out.disparity, out.valid


class BlockMatching(nn.Module):
    """Module form of :func:`block_matching`: stores the settings, ``forward(left, right) -> (disparity, valid)``.

    >>> BlockMatching(8, block_size=5)(torch.rand(1, 1, 16, 24), torch.rand(1, 1, 16, 24))[0].shape
    torch.Size([1, 1, 16, 24])
    """

    def __init__(self, max_disparity: int, **kwargs) -> None:
        super().__init__()
        self.max_disparity = max_disparity
        self.kwargs = kwargs

    def forward(self, left: torch.Tensor, right: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return block_matching(left, right, self.max_disparity, **self.kwargs)

    def extra_repr(self) -> str:
        return ", ".join([f"max_disparity={self.max_disparity}"] + [f"{k}={v!r}" for k, v in self.kwargs.items()])
