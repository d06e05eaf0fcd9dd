"""Residual stereo: block matching in a narrow band around a prior disparity map.

Full stereo searches every candidate ``min_disparity <= d < max_disparity`` at every pixel. When a
good prior ``p`` is at hand (the refiner's prediction of the frame from the last verified one), the
truth is within a pixel or two of it, and only ``2 radius + 1`` candidates around it need checking.
:func:`match_residual` does that search with the default matcher's cost (SAD of the x-Sobel
prefiltered images over a ``block_size`` window), in one of two windows:

* ``window="fronto"`` (the default): the candidates are the integer disparities ``c + k``,
  ``c = round(p(y, x))``, and the cost of ``k`` at pixel ``x`` is the matcher's own fronto-parallel window
  sum of ``|L'(y', x') - R'(y', x' - c - k)|``. Wherever the full matcher's integer winner lies within
  ``c +- (radius - 1)`` it is this band's winner too, with the same neighbours: the value and variance are
  the full matcher's (its uniqueness and left-right checks, over the whole range, only remove pixels). The
  prior may be off by up to ``radius - 1`` px;
* ``window="warped"``: the cost of ``k`` is the window sum of ``|L'(y', x') - R'(y', x' - p(y', x') - k)|``,
  the prefiltered right row sampled linearly (the prior of every window pixel warps it, so the search is for
  the residual of a whole warped window); the prior may be off by up to ``radius - 1/2`` px. Linear
  sampling blurs the right window by an amount that depends on the prior's fraction: on the refiner's
  paper-rig sequences this window's measurements were worse than per-frame stereo's on the same pixels,
  the fronto window's as good (see :class:`~egorefine.refine.EgoMotionRefiner`'s ``local_search_window``);

* the winner is the cheapest ``k``; a winner at either end of the band is rejected (the truth may lie
  beyond it: the prior was off by more than ``radius``); the uniqueness and texture checks are the
  matcher's; there is no left-right check (the prior already fixed which surface is matched);
* the sub-pixel fit through the winner's neighbours and the variance model are the matcher's (see
  :func:`~egorefine.stereo.match_stereo`), so a residual measurement can be fused like a full one.

The work is ``2 radius + 1`` cost planes instead of ``max_disparity - min_disparity``: at
``radius=2`` and 128 candidates, 4 % (the fronto window computes, along each row, the window costs of
each disparity over the runs of pixels that need it). Pixels within ``block_size // 2`` of the image border, pixels
whose band leaves the right image, and pixels where ``prior_valid`` is False are not valid.

The torch code below is the reference (GPU, float64, autograd, tracing); float32 CPU tensors without gradient run
the same formulas compiled (:mod:`egorefine.stereo._residual_numba`, where :func:`egorefine.core.use_compiled`
allows it); the two agree to float32 rounding (the window sums are added in a different order, so a near-tie may be
decided differently).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..core import (
    ValueRangeError,
    check_choice,
    check_float,
    check_same_device,
    check_shape,
    to_grey,
    use_compiled,
)
from . import _residual_numba
from .cost import prefilter_xsobel
from .fast import _QUANTISATION_VARIANCE, INVALID_VARIANCE
from .matching import COST_FLOORS, StereoOutput

__all__ = ["match_residual"]

_COST_FLOOR = COST_FLOORS["sad"]  # the matcher's variance model, SAD cost


def match_residual(
    left: torch.Tensor,
    right: torch.Tensor,
    prior: torch.Tensor,
    radius: int = 2,
    block_size: int = 9,
    prior_valid: torch.Tensor | None = None,
    subpixel_fit: str = "equiangular",
    uniqueness_ratio: float = 0.15,
    texture_threshold: float = 0.004,
    prefilter_cap: float = 31.0 / 255.0,
    window: str = "fronto",
) -> StereoOutput:
    """Block matching restricted to a band of ``2 radius + 1`` candidates around a prior.

    Args:
        left, right: ``(B, 1|3, H, W)`` rectified float images in [0, 1].
        prior: ``(B, 1, H, W)`` prior disparity, px (finite).
        radius: half-width of the search band, px (>= 2: a winner needs a neighbour on each side
            and must not be at the band's end).
        block_size: odd window of the SAD cost.
        prior_valid: ``(B, 1, H, W)`` bool, where the prior may be used (None: everywhere).
        subpixel_fit: ``"equiangular"`` (the matcher's default) or ``"parabola"``.
        uniqueness_ratio: reject when a candidate beyond +-1 px of the winner costs less than
            ``(1 + ratio)`` times the winner's (0 disables).
        texture_threshold: reject windows whose mean ``|x-Sobel|`` (clipped) is below it.
        prefilter_cap: clip level of the x-Sobel prefilter.
        window: ``"fronto"`` (the matcher's fronto-parallel window at the integer disparities
            ``round(prior) + k``) or ``"warped"`` (every window pixel shifted by its own prior plus ``k``, the
            right image sampled linearly); see the module docstring.

    Returns:
        :class:`~egorefine.stereo.StereoOutput`: ``disparity`` (0 where not valid), ``valid``, ``variance``
        (INVALID_VARIANCE where not valid), each ``(B, 1, H, W)``.

    Raises:
        ShapeError, DTypeError, DeviceError, ValueRangeError: bad input, naming the argument.

    >>> left = torch.rand(1, 1, 20, 40, generator=torch.Generator().manual_seed(0))
    >>> right = torch.roll(left, -3, dims=-1)  # true disparity 3 px
    >>> out = match_residual(left, right, torch.full((1, 1, 20, 40), 2.4), block_size=5)
    >>> round(float(out.disparity[0, 0, 10, 20])), bool(out.valid[0, 0, 10, 20])
    (3, True)
    """
    dims = check_shape(left, ["B", "1|3", "H", "W"], "left")
    check_shape(right, ["B", "1|3", "H", "W"], "right", dims)
    check_shape(prior, ["B", "1", "H", "W"], "prior", dims)
    for name, t in (("left", left), ("right", right), ("prior", prior)):
        check_float(t, name)
    if prior_valid is not None:
        check_shape(prior_valid, ["B", "1", "H", "W"], "prior_valid", dims)
    check_same_device(left, "left", right=right, prior=prior, prior_valid=prior_valid)
    check_choice(subpixel_fit, ("equiangular", "parabola"), "subpixel_fit")
    check_choice(window, ("fronto", "warped"), "window")
    if int(radius) != radius or radius < 2:
        raise ValueRangeError(f"radius: expected an integer >= 2, got {radius}")
    if int(block_size) != block_size or block_size < 1 or block_size % 2 == 0:
        raise ValueRangeError(f"block_size: expected a positive odd integer, got {block_size}")
    W = left.shape[-1]
    if W < 2 or left.shape[-2] < block_size or W < block_size:
        raise ValueRangeError(f"left: the image ({left.shape[-2]}x{W}) is smaller than the {block_size} px window")
    if not (uniqueness_ratio >= 0 and prefilter_cap > 0):
        raise ValueRangeError(f"uniqueness_ratio >= 0 and prefilter_cap > 0 expected, got {uniqueness_ratio}, "
                              f"{prefilter_cap}")

    grey_l, grey_r = to_grey(left), to_grey(right).to(left.dtype)
    prior = prior.to(left.dtype)
    ok = torch.ones_like(prior, dtype=torch.bool) if prior_valid is None else prior_valid.bool()
    opts = (int(radius), int(block_size), subpixel_fit == "parabola", float(uniqueness_ratio),
            float(texture_threshold))
    if use_compiled(grey_l, grey_r, prior, ok):
        return StereoOutput(*_residual_numba.match_residual(grey_l, grey_r, prior, ok, *opts, cost_floor=_COST_FLOOR,
                                                            prefilter_cap=float(prefilter_cap), window=window))
    lp = prefilter_xsobel(grey_l, prefilter_cap)
    rp = prefilter_xsobel(grey_r, prefilter_cap)
    ok = ok & torch.isfinite(prior)
    return _match_residual_torch(lp, rp, torch.where(ok, prior, torch.zeros_like(prior)), ok, *opts, window)


def _shift_right(image: torch.Tensor, d: int) -> torch.Tensor:
    """``out[..., x] = image[..., x - d]`` (zeros where that leaves the row)."""
    if d >= 0:
        return F.pad(image, (d, 0))[..., : image.shape[-1]]
    return F.pad(image, (0, -d))[..., -d:]


def _match_residual_torch(lp: torch.Tensor, rp: torch.Tensor, prior: torch.Tensor, ok: torch.Tensor, radius: int,
                          block: int, parabola: bool, uniqueness: float, texture: float, window: str) -> StereoOutput:
    """The reference path: ``(B, 2 radius + 1, H, W)`` cost planes, then the matcher's winner, checks and fit."""
    B, _, H, W = lp.shape
    dtype, device = lp.dtype, lp.device
    r, n = block // 2, 2 * radius + 1
    area = float(block * block)
    ks = torch.arange(-radius, radius + 1, device=device, dtype=dtype).view(1, n, 1, 1)
    xs = torch.arange(W, device=device, dtype=dtype).view(1, 1, 1, W)
    border = torch.zeros(1, 1, H, W, dtype=torch.bool, device=device)
    border[..., r:H - r, r:W - r] = True
    if window == "warped":
        centre = prior
        src = (xs - prior - ks).clamp(0, W - 1)  # (B, n, H, W) sample positions in the right row
        x0 = src.floor().clamp(max=W - 2)
        frac = src - x0
        i0 = x0.long()
        row = rp.expand(B, n, H, W)
        r0 = row.gather(3, i0)
        sample = r0 + frac * (row.gather(3, i0 + 1) - r0)
        diff = (lp - sample).abs()
        cost = F.avg_pool2d(diff, block, 1, r, count_include_pad=True) * area  # window sums (borders invalid below)
        ok = ok & (xs - prior - radius >= 0) & (xs - prior + radius <= W - 1)
    else:
        # every candidate's whole window inside the right image; the planes of the disparities some pixel needs
        centre = prior.round().clamp(-2 * W, 2 * W)
        ok = ok & border & (xs - r - centre - radius >= 0) & (xs + r - centre + radius <= W - 1)
        centre = torch.where(ok, centre, torch.zeros_like(centre))
        cost = torch.zeros(B, n, H, W, device=device, dtype=dtype)
        if bool(ok.any()):
            used = centre[ok]
            for d in range(int(used.min()) - radius, int(used.max()) + radius + 1):
                plane = F.avg_pool2d((lp - _shift_right(rp, d)).abs(), block, 1, r, count_include_pad=True) * area
                cost = torch.where(centre + ks == d, plane, cost)
    c0, j = cost.min(1, keepdim=True)
    jj = torch.arange(n, device=device).view(1, n, 1, 1)
    far = (jj - j).abs() > 1
    runner = torch.where(far, cost, torch.full_like(cost, float("inf"))).amin(1, keepdim=True)
    cm = cost.gather(1, (j - 1).clamp(min=0))
    cp = cost.gather(1, (j + 1).clamp(max=n - 1))
    textured = F.avg_pool2d(lp.abs(), block, 1, r, count_include_pad=True) * area >= texture * area
    valid = ok & border & textured & (j > 0) & (j < n - 1)
    if uniqueness > 0:
        valid = valid & ~(runner < (1 + uniqueness) * c0)
    curvature = cm - 2 * c0 + cp
    eps = torch.finfo(dtype).eps * 16 * area
    denom = 2 * curvature if parabola else 2 * (torch.maximum(cm, cp) - c0)
    offset = ((cm - cp) / denom.clamp_min(eps)).clamp(-0.5, 0.5)
    disparity = centre + (j - radius).to(dtype) + offset
    variance = _QUANTISATION_VARIANCE + 0.25 * ((c0 + _COST_FLOOR * area) / (curvature.clamp_min(0) + eps)) ** 2
    disparity = torch.where(valid, disparity, torch.zeros_like(disparity))
    variance = torch.where(valid, variance.clamp_max(INVALID_VARIANCE), torch.full_like(variance, INVALID_VARIANCE))
    return StereoOutput(disparity, valid, variance)
