"""Census + SGM in a band of candidates around a prior disparity map.

The dense matcher (census cost, SGM; :meth:`~egorefine.refine.StereoOptions.dense`) searches every candidate
``min_disparity <= d < max_disparity`` at every pixel. Where a prior says where the truth is to within a few px (the
refiner's prediction of a verification frame), only a band of ``width`` candidates around it needs searching.
:func:`match_sgm_band` runs the dense matcher's steps on such bands:

* pixel ``p``'s candidates are the integers ``lo(p) .. lo(p) + width - 1``, ``lo(p) = clamp(round(prior(p)) -
  width // 2 + 1, min_disparity, max_disparity - width)``: the prior's integer is the band's ``width // 2 - 1``-th
  candidate, the band shifted to stay inside the range (the whole range when it is not wider than ``width``);
* the cost (census Hamming distances summed over a ``block_size`` window), the SGM paths and penalties, the sub-pixel
  fit, the texture check and the variance model are the dense matcher's (:func:`~egorefine.stereo.match_stereo`);
  a path step sees a neighbour's costs only at the candidates of that neighbour's band (+inf elsewhere), so a depth
  edge between two bands costs P2, as a jump does in the full search;
* there is no left-right check and no uniqueness test: the prior already fixed which surface is matched (as in
  :func:`~egorefine.stereo.match_residual`); a winner on the band's edge is rejected (the truth may lie beyond it:
  the prior was off by more than about ``width / 2``) unless that edge is the range's limit, where the full matcher's
  rule applies (``d = 0`` may win with ``min_disparity = 0``; ``max_disparity - 1`` never does). This catches a
  prior off by a little more than ``width / 2``, whose band's cheapest candidate is the edge next to the truth;
  further off, a secondary minimum of the costs inside the band (texture that repeats, weak texture that SGM's
  smoothing spreads) can win and pass, as no left-right check or uniqueness test looks beyond the band: the
  prior must be right to within the band for every pixel whose output is used;
* the speckle filter runs as :func:`~egorefine.stereo.match_stereo` runs it.

The work is ``width`` candidates per pixel instead of ``max_disparity - min_disparity``. With ``width`` at least
the range, the result is the full matcher's with ``lr_check=False``.

The torch code below is the reference (GPU, float64, tracing): the full range's cost volume with every candidate
outside a pixel's band set to +inf, then :func:`~egorefine.stereo.sgm_aggregate` and the full matcher's selection.
+inf keeps the path recursion exact: a path cost outside a band stays +inf (``C - m + best`` with ``C = +inf`` and a
finite minimum ``m``), is never any minimum's pick, and no +inf meets a -inf, so no NaN arises. Float32 CPU tensors
without gradient run the compiled kernel (:mod:`egorefine.stereo._band_numba`, where
:func:`egorefine.core.use_compiled` allows it), which gives the same float32 values. Census is piecewise constant
in the images, so the outputs carry no gradient (the full census matcher's do not either).
"""

from __future__ import annotations

import torch

from ..core import (
    ValueRangeError,
    check_finite,
    check_float,
    check_same_device,
    check_shape,
    to_grey,
    use_compiled,
)
from . import _band_numba
from .cost import _Features, box_mean_same, prefilter_xsobel, strip_volume
from .fast import INVALID_VARIANCE
from .matching import (
    COST_FLOORS,
    StereoOutput,
    _check_inputs,
    _despeckle,
    _mask_untextured_compiled,
    _select,
    _sgm_penalties,
)
from .sgm import sgm_aggregate

__all__ = ["match_sgm_band", "band_start"]


def band_start(prior: torch.Tensor, max_disparity: int, min_disparity: int = 0, width: int = 16) -> torch.Tensor:
    """Each pixel's lowest candidate ``lo = clamp(round(prior) - width // 2 + 1, min_disparity, max_disparity -
    width)`` (``min_disparity`` where the range is not wider than ``width``), as int32.

    Args:
        prior: ``(B, 1, H, W)`` finite prior disparity, px.
        max_disparity, min_disparity: the range ``[min_disparity, max_disparity)``.
        width: candidates per pixel.

    Returns:
        ``(B, 1, H, W)`` int32.

    Example:
        >>> band_start(torch.tensor([[[[0.2, 9.6, 40.0]]]]), 32, width=16).flatten().tolist()
        [0, 3, 16]
    """
    width = min(width, max_disparity - min_disparity)
    # clamped as floats first: a huge (finite) prior must not overflow the integer conversion
    lo = torch.round(prior.detach()).sub_(width // 2 - 1).clamp_(min_disparity, max_disparity - width)
    return lo.to(torch.int32)


def match_sgm_band(
    left: torch.Tensor,
    right: torch.Tensor,
    prior: torch.Tensor,
    max_disparity: int,
    min_disparity: int = 0,
    width: int = 16,
    block_size: int = 5,
    census_window: int = 7,
    sgm_p1: float | None = None,
    sgm_p2: float | None = None,
    sgm_paths: int = 4,
    subpixel: bool = True,
    subpixel_fit: str = "equiangular",
    texture_threshold: float = 0.004,
    prefilter_cap: float = 31.0 / 255.0,
    speckle_size: int = 200,
    speckle_range: float = 2.0,
) -> StereoOutput:
    """Census + SGM restricted to a band of ``width`` candidates around a prior (module docstring).

    The defaults are :meth:`~egorefine.refine.StereoOptions.dense`'s matcher (block 5, census window 7, 4 paths,
    speckle range 2 px), less its left-right check.

    Args:
        left, right: ``(B, 1|3, H, W)`` rectified float images in [0, 1] (colour is converted to grey).
        prior: ``(B, 1, H, W)`` prior disparity, px, finite everywhere (a hole in it: fill it from a neighbour).
        max_disparity, min_disparity: the range ``[min_disparity, max_disparity)`` the bands stay in, as
            :func:`~egorefine.stereo.match_stereo`'s.
        width: candidates per pixel (>= 3: a winner needs a neighbour on each side); the truth is found where the
            prior is off by at most about ``width / 2 - 1`` px.
        block_size, census_window, sgm_p1, sgm_p2, sgm_paths, subpixel, subpixel_fit, texture_threshold,
            prefilter_cap, speckle_size, speckle_range: as :func:`~egorefine.stereo.match_stereo`'s.

    Returns:
        :class:`~egorefine.stereo.StereoOutput`: ``disparity`` (0 where not valid), ``valid``, ``variance``
        (INVALID_VARIANCE where not valid), each ``(B, 1, H, W)``, without gradient.

    Raises:
        ShapeError, DTypeError, DeviceError, ValueRangeError: bad input (a prior holding NaN or Inf too), naming the
            argument.

    Example:
        >>> left = torch.rand(1, 1, 24, 48, generator=torch.Generator().manual_seed(0))
        >>> right = torch.roll(left, -5, dims=-1)  # true disparity 5 px
        >>> out = match_sgm_band(left, right, torch.full((1, 1, 24, 48), 6.3), 32, width=8)
        >>> round(float(out.disparity[0, 0, 12, 24]), 1), bool(out.valid[0, 0, 12, 24])
        (5.0, True)
        >>> far = match_sgm_band(left, right, torch.full((1, 1, 24, 48), 14.0), 32, width=8)  # band 11 .. 18
        >>> bool(far.valid.any())
        False
    """
    _check_inputs(left, right, max_disparity, min_disparity, block_size, "census", "sgm", subpixel_fit, sgm_paths,
                  None, False, None, census_window, speckle_size, speckle_range, None, sgm_p1, sgm_p2)
    if sgm_paths not in (4, 8):
        raise ValueRangeError(f"sgm_paths: the band matcher takes 4 or 8, got {sgm_paths}")
    check_shape(prior, ["B", "1", "H", "W"], "prior", check_shape(left, ["B", "1|3", "H", "W"], "left"))
    check_float(prior, "prior")
    check_same_device(left, "left", prior=prior)
    check_finite(prior, "prior")
    if isinstance(width, bool) or not isinstance(width, int) or width < 3:
        raise ValueRangeError(f"width: expected an int >= 3, got {width!r}")
    grey_l, grey_r = to_grey(left).detach(), to_grey(right).detach()
    num = max_disparity - min_disparity
    wb = min(width, num)
    lo = band_start(prior, max_disparity, min_disparity, wb)
    scale = float(block_size * block_size)
    p1, p2 = _sgm_penalties("census", census_window, sgm_p1, sgm_p2, scale)
    opts = {"subpixel": subpixel, "subpixel_fit": subpixel_fit, "lr_check": False, "uniqueness_ratio": 0.0,
            "differentiable": False, "soft_radius": None, "temperature": 1.0, "cost_floor": COST_FLOORS["census"],
            "scale": scale, "min_disparity": min_disparity}
    if use_compiled(grey_l, grey_r) and wb >= 2:
        out = _mask_untextured_compiled(
            _band_numba.match_band(grey_l, grey_r, lo, wb, max_disparity, min_disparity, block_size, census_window,
                                   p1, p2, sgm_paths, opts),
            grey_l, block_size, prefilter_cap, texture_threshold)
    else:
        disparity, valid, variance = _band_torch(grey_l, grey_r, lo, wb, max_disparity, min_disparity, block_size,
                                                 census_window, p1, p2, sgm_paths, opts)
        texture = box_mean_same(prefilter_xsobel(grey_l, prefilter_cap).abs(), block_size)
        valid = valid & (texture >= texture_threshold)
        out = StereoOutput(torch.where(valid, disparity, torch.zeros_like(disparity)), valid,
                           torch.where(valid, variance, torch.full_like(variance, INVALID_VARIANCE)))
    return _despeckle(out, speckle_size, speckle_range)  # as match_stereo


def _band_torch(grey_l: torch.Tensor, grey_r: torch.Tensor, lo: torch.Tensor, width: int, max_disparity: int,
                min_disparity: int, block_size: int, census_window: int, p1: float, p2: float, paths: int,
                opts: dict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The reference: the full range's census volume, +inf outside each pixel's band, SGM, the full matcher's
    selection, then the band's lower edge rejected where it is not the range's ``d = 0``."""
    h = grey_l.shape[-2]
    num = max_disparity - min_disparity
    feat = _Features(grey_l, grey_r, "census", block_size, max_disparity, census_window, False, 1.0)
    vol = strip_volume(feat, 0, h, min_disparity)  # (B, D, H, W), index j is d = max_disparity - 1 - j
    d = max_disparity - 1 - torch.arange(num, device=vol.device).view(1, num, 1, 1)
    vol = vol.masked_fill((d < lo) | (d >= lo + width), float("inf"))
    disparity, valid, variance = _select(sgm_aggregate(vol, p1, p2, paths), max_disparity, opts)
    # a winner at the band's lower edge d = lo has d - 1 out of its band (no interior fit: disparity == lo exactly)
    valid = valid & ((disparity > lo) | (lo == 0))
    return disparity, valid, variance
