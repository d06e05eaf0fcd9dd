"""Stereo matching at half resolution, its disparity brought back to full resolution.

A global matcher (census + SGM) spends its time per pixel and candidate disparity: on images halved in each
direction it has a quarter of the pixels and half of the candidates, an eighth of the work. What it loses is
resolution, which matters least where it is used as a fill (:class:`~egorefine.refine.StereoOptions`'s
``fill_scale``): in the weakly textured holes a local matcher leaves, where a window of twice the size sees more
texture.

The way back to full resolution: a full-resolution pixel lies in one half-resolution pixel (its 2 x 2 block) and
between four of them. It takes the bilinear blend of those four where all are valid and their disparities span at
most ``smooth`` half-resolution px (a slanted surface, a road, keeps its slope instead of steps of 2 x 2 blocks),
else the value of its own block (a depth edge stays sharp, no value between the two sides is made up); doubled, as
a half-resolution pixel is two full ones. Validity is the block's; the variance is the block's times 4.

Two paths, one rule (:func:`~egorefine.core.use_compiled`): a torch reference (any device) and numba kernels for
float32 CPU tensors, equal up to float rounding.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..core import ValueRangeError, check_shape, to_grey, use_compiled
from ..core._jit import AVAILABLE, Workers, split, thread_count
from ..core._jit import jit as _jit
from .matching import INVALID_VARIANCE, StereoOutput, match_stereo

__all__ = ["match_half_resolution"]

# a full-resolution pixel's weight on its own half-resolution block (bilinear, per axis); 1 - this on the next
_NEAR = 0.75

if AVAILABLE:

    @_jit
    def _halve_kernel(img, out):
        """``out`` ``(ceil(H / 2), ceil(W / 2))``: means of the 2 x 2 blocks of ``img`` ``(H, W)``, the last row and
        column repeated where H or W is odd."""
        h, w = img.shape
        for y in range(out.shape[0]):
            y0, y1 = 2 * y, min(2 * y + 1, h - 1)
            for x in range(out.shape[1]):
                x0, x1 = 2 * x, min(2 * x + 1, w - 1)
                out[y, x] = np.float32(0.25) * ((img[y0, x0] + img[y0, x1]) + (img[y1, x0] + img[y1, x1]))

    @_jit(inline="always")
    def _blend(a, b, c, e, va, vb, vc, ve, variance, smooth, low, high):
        """One full-resolution pixel (the module docstring's way back): ``a`` its own block, ``b`` the next one
        along the row, ``c`` the next along the column, ``e`` the diagonal one, ``v*`` their validity. Returns
        ``(disparity, valid, variance)``; selects, no jumps, so that the row loops become SIMD code."""
        near, far = np.float32(_NEAR), np.float32(1.0 - _NEAR)
        spread = max(max(a, b), max(c, e)) - min(min(a, b), min(c, e))
        blend = near * (near * a + far * b) + far * (near * c + far * e)
        value = np.float32(2.0) * (blend if (va & vb & vc & ve) and spread <= smooth else a)
        ok = va and low <= value and value < high
        return (value if ok else np.float32(0.0), ok,
                np.float32(4.0) * variance if ok else np.float32(INVALID_VARIANCE))

    @_jit(inline="always")
    def _border_pixel(x, da, dc, va, vc, vr, smooth, low, high, od, ov, ovar):
        """Output column ``x`` of one row (_blend), its neighbouring block clamped to the row (``da``, ``va``: its
        blocks' disparities and validity; ``dc``, ``vc``: the next row's; ``vr``: its variances)."""
        m = x // 2
        m2 = min(max(m - 1 if x % 2 == 0 else m + 1, 0), da.shape[0] - 1)
        od[x], ov[x], ovar[x] = _blend(da[m], da[m2], dc[m], dc[m2], va[m], va[m2], vc[m], vc[m2], vr[m], smooth,
                                       low, high)

    @_jit
    def _double_rows(d, valid, var, smooth, low, high, out_d, out_valid, out_var, y0, y1):
        """Rows ``[y0, y1)`` of the way back (_blend per pixel). Output columns ``2 m`` and ``2 m + 1`` both lie in
        block ``m`` and blend it with blocks ``m - 1`` and ``m + 1``: the inner loop runs over ``m`` with
        neighbours at fixed offsets; the border blocks (clamped neighbours) and an odd last column go one by
        one."""
        h, w = d.shape
        big_w = out_d.shape[1]
        for y in range(y0, y1):
            k = y // 2
            k2 = min(max(k - 1 if y % 2 == 0 else k + 1, 0), h - 1)
            da, dc, va, vc, vr = d[k], d[k2], valid[k], valid[k2], var[k]
            od, ov, ovar = out_d[y], out_valid[y], out_var[y]
            inner = min(w - 1, (big_w - 1) // 2)  # blocks 1 .. inner - 1 have both neighbours and both columns
            for m in range(1, inner):
                od[2 * m], ov[2 * m], ovar[2 * m] = _blend(da[m], da[m - 1], dc[m], dc[m - 1], va[m], va[m - 1],
                                                           vc[m], vc[m - 1], vr[m], smooth, low, high)
                od[2 * m + 1], ov[2 * m + 1], ovar[2 * m + 1] = _blend(
                    da[m], da[m + 1], dc[m], dc[m + 1], va[m], va[m + 1], vc[m], vc[m + 1], vr[m], smooth, low, high)
            for x in range(min(2, big_w)):  # the border columns
                _border_pixel(x, da, dc, va, vc, vr, smooth, low, high, od, ov, ovar)
            for x in range(max(2, 2 * inner), big_w):
                _border_pixel(x, da, dc, va, vc, vr, smooth, low, high, od, ov, ovar)


def _halve(grey: torch.Tensor) -> torch.Tensor:
    """``(B, 1, H, W)`` -> ``(B, 1, ceil(H / 2), ceil(W / 2))``: 2 x 2 block means, the last row / column repeated
    where H / W is odd."""
    b, _, h, w = grey.shape
    if use_compiled(grey):
        src = grey.detach().contiguous().numpy()
        out = np.empty((b, 1, (h + 1) // 2, (w + 1) // 2), dtype=np.float32)
        for i in range(b):
            _halve_kernel(src[i, 0], out[i, 0])
        return torch.from_numpy(out)
    return F.avg_pool2d(F.pad(grey, (0, w % 2, 0, h % 2), mode="replicate"), 2)


def _double(half: StereoOutput, height: int, width: int, smooth: float, low: float, high: float) -> StereoOutput:
    """The module docstring's way back: ``half`` ``(B, 1, h, w)`` (half-resolution px) -> ``(B, 1, height, width)``
    in full-resolution px, valid where the block is and ``low <= disparity < high``."""
    d, valid, var = half
    b, _, h, w = d.shape
    if use_compiled(d, valid, var):
        out_d = np.empty((b, 1, height, width), dtype=np.float32)
        out_valid = np.empty((b, 1, height, width), dtype=np.bool_)
        out_var = np.empty((b, 1, height, width), dtype=np.float32)
        dn, vn, varn = d.contiguous().numpy(), valid.contiguous().numpy(), var.contiguous().numpy()
        settings = (np.float32(smooth), np.float32(low), np.float32(high))
        threads = thread_count()
        jobs = [(i, rows) for i in range(b) for rows in split(height, threads, height * width)]
        Workers(threads).map(lambda job: _double_rows(dn[job[0], 0], vn[job[0], 0], varn[job[0], 0], *settings,
                                                      out_d[job[0], 0], out_valid[job[0], 0], out_var[job[0], 0],
                                                      *job[1]), jobs)
        return StereoOutput(torch.from_numpy(out_d), torch.from_numpy(out_valid), torch.from_numpy(out_var))

    def rows_and_next(n: int, size: int) -> tuple[torch.Tensor, torch.Tensor]:
        full = torch.arange(n, device=d.device)
        own = full // 2
        return own, torch.where(full % 2 == 0, own - 1, own + 1).clamp(0, size - 1)

    k, k2 = rows_and_next(height, h)
    m, m2 = rows_and_next(width, w)

    def at(t: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
        return t[..., rows, :][..., :, cols]

    a, bb, c, e = at(d, k, m), at(d, k, m2), at(d, k2, m), at(d, k2, m2)
    own_valid = at(valid, k, m)
    all_valid = own_valid & at(valid, k, m2) & at(valid, k2, m) & at(valid, k2, m2)
    spread = torch.maximum(torch.maximum(a, bb), torch.maximum(c, e)) - torch.minimum(torch.minimum(a, bb),
                                                                                      torch.minimum(c, e))
    blend = _NEAR * (_NEAR * a + (1.0 - _NEAR) * bb) + (1.0 - _NEAR) * (_NEAR * c + (1.0 - _NEAR) * e)
    value = 2.0 * torch.where(all_valid & (spread <= smooth), blend, a)
    ok = own_valid & (value >= low) & (value < high)
    return StereoOutput(torch.where(ok, value, torch.zeros_like(value)), ok,
                        torch.where(ok, 4.0 * at(var, k, m), torch.full_like(value, INVALID_VARIANCE)))


def match_half_resolution(left: torch.Tensor, right: torch.Tensor, max_disparity: int, min_disparity: int = 0,
                          smooth: float = 1.0, **options) -> StereoOutput:
    """:func:`~egorefine.stereo.match_stereo` on the pair halved in each direction, brought back to full resolution.

    An eighth of the matcher's work (a quarter of the pixels, half of the candidates), at twice the window size
    and half the precision: a fill for the holes of a full-resolution local matcher (``StereoOptions.fill_scale``),
    not a replacement for it. The way back to full resolution is the module docstring's.

    Args:
        left, right: ``(B, 1|3, H, W)`` rectified float images in [0, 1] (colour is made grey first).
        max_disparity: full-resolution px, exclusive; the half-resolution matcher searches
            ``ceil(max_disparity / 2)`` (exclusive) down to ``min_disparity // 2``, at least 2 candidates.
        min_disparity: full-resolution px, >= 0.
        smooth: half-resolution px: the largest spread of the four blocks around a pixel that is blended
            bilinearly (1.0: a slanted surface, not a depth edge).
        options: the rest of :func:`~egorefine.stereo.match_stereo`'s keyword arguments, used at half resolution
            (``block_size``, ``cost``, ``aggregation``, ...); its tolerances in px are full-resolution px, halved
            for the half-resolution matcher where given (``lr_threshold`` rounded up, ``speckle_range``), so that a
            left-right check of 2 px means 2 px in either call (match_stereo's own defaults apply at half
            resolution as they are).

    Returns:
        :class:`~egorefine.stereo.StereoOutput`: ``(B, 1, H, W)`` each, disparity in full-resolution px within
        ``[min_disparity, max_disparity)`` where valid (0 elsewhere), variance 4 times the half-resolution one
        (INVALID_VARIANCE where not valid).

    Raises:
        ShapeError, ValueRangeError: bad input, naming the argument.

    Example:
        >>> left = torch.rand(1, 1, 48, 64, generator=torch.Generator().manual_seed(0))
        >>> left = F.interpolate(left, scale_factor=2, mode="bilinear")  # texture coarse enough for both scales
        >>> right = torch.roll(left, -6, dims=-1)  # true disparity 6 px
        >>> out = match_half_resolution(left, right, 16, cost="census", aggregation="sgm")
        >>> out.disparity.shape, round(float(out.disparity[0, 0, 48, 64]), 1), bool(out.valid[0, 0, 48, 64])
        (torch.Size([1, 1, 96, 128]), 6.0, True)
    """
    dims = check_shape(left, ["B", "1|3", "H", "W"], "left")
    check_shape(right, ["B", "1|3", "H", "W"], "right", dims)
    if not float(smooth) >= 0.0:
        raise ValueRangeError(f"smooth: expected >= 0 half-resolution px, got {smooth}")
    high, low = -(-int(max_disparity) // 2), int(min_disparity) // 2
    if high - low < 2:
        raise ValueRangeError(f"max_disparity: expected at least 2 half-resolution candidates above min_disparity "
                              f"{min_disparity}, got max_disparity {max_disparity}")
    if options.get("lr_threshold") is not None:
        options["lr_threshold"] = -(-int(options["lr_threshold"]) // 2)
    if options.get("speckle_range") is not None:
        options["speckle_range"] = float(options["speckle_range"]) / 2
    h, w = left.shape[-2:]
    half = match_stereo(_halve(to_grey(left)), _halve(to_grey(right)), high, min_disparity=low, **options)
    return _double(half, h, w, float(smooth), float(min_disparity), float(max_disparity))
