"""Matching costs and their box-aggregated cost volumes, built strip by strip.

The volume is never materialised per window element: for a strip of rows the raw
per-pixel cost of every candidate disparity is one broadcast operation against a
strided view of the padded right image, and the block aggregation is a separable box
sum done with log2(k) shifted additions. Only a few ``(B, D, h, W)`` strips live at once.

Internally the disparity axis is stored *reversed* (index ``j`` holds disparity
``max_disparity - 1 - j``) because that makes the shifted right image a view with a
positive stride; :func:`cost_volume` flips it back for callers.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..core import to_grey

__all__ = ["prefilter_xsobel", "census_transform", "cost_volume", "COSTS", "INVALID_COST"]

COSTS = ("sad", "zncc", "census")
# Cost given to candidates that fall outside the right image (x - d < 0): large but
# finite, so that soft-argmin weights underflow to 0 and no NaN/Inf appears.
INVALID_COST = 1.0e6
_CENSUS_WINDOWS = (3, 5, 7)



def prefilter_xsobel(image: torch.Tensor, cap: float = 31.0 / 255.0) -> torch.Tensor:
    """OpenCV StereoBM's ``PREFILTER_XSOBEL``: the raw x-Sobel response clipped to ``[-cap, cap]``.

    For an image in [0, 1] the default cap equals OpenCV's ``preFilterCap=31`` on 8-bit images.

    Args:
        image: ``(B, 1, H, W)`` grey image.
        cap: clip level (> 0).

    Returns:
        ``(B, 1, H, W)`` filtered image in ``[-cap, cap]``.

    >>> prefilter_xsobel(torch.rand(2, 1, 6, 7)).shape
    torch.Size([2, 1, 6, 7])
    """
    # the unnormalised 3x3 x-Sobel with replicated borders, i.e. kornia's
    # spatial_gradient(image, "sobel", normalized=False)[:, :, 0], written separably: on one
    # channel this is much faster than the convolution kornia dispatches to
    padded = F.pad(image, (1, 1, 1, 1), mode="replicate")
    diff = padded[..., 2:] - padded[..., :-2]
    gx = diff[..., :-2, :] + 2 * diff[..., 1:-1, :] + diff[..., 2:, :]
    return gx.clamp(-cap, cap)


def census_transform(image: torch.Tensor, window: int = 5) -> torch.Tensor:
    """Census bit string of each pixel: bit k is set where neighbour k is darker than the centre.

    Args:
        image: ``(B, 1, H, W)`` grey image.
        window: odd window size in {3, 5, 7} (8, 24 or 48 bits).

    Returns:
        ``(B, 1, H, W)`` int32 (window 3, 5) or int64 (window 7) bit strings (replicated borders).

    >>> census_transform(torch.rand(1, 1, 5, 6)).dtype  # int64 for the 7x7 window
    torch.int32
    """
    r = window // 2
    padded = F.pad(image, (r, r, r, r), mode="replicate")
    h, w = image.shape[-2:]
    # int32 holds the 8 or 24 bits of a 3x3 or 5x5 window (half the memory traffic of int64)
    dtype = torch.int32 if window * window - 1 <= 31 else torch.int64
    bits = torch.zeros(image.shape, dtype=dtype, device=image.device)
    k = 0
    for dy in range(window):
        for dx in range(window):
            if dy == r and dx == r:
                continue
            neighbour = padded[..., dy : dy + h, dx : dx + w]
            bits |= (neighbour < image).to(dtype) << k
            k += 1
    return bits


def _popcount(x: torch.Tensor) -> torch.Tensor:
    """Number of set bits of non-negative int32 (< 2**31) or int64 (< 2**63) values, SWAR style."""
    if x.dtype == torch.int32:
        x = x - ((x >> 1) & 0x55555555)
        x = (x & 0x33333333) + ((x >> 2) & 0x33333333)
        x = (x + (x >> 4)) & 0x0F0F0F0F
        x = x + (x >> 8)
        return (x + (x >> 16)) & 0x3F
    x = x - ((x >> 1) & 0x5555555555555555)
    x = (x & 0x3333333333333333) + ((x >> 2) & 0x3333333333333333)
    x = (x + (x >> 4)) & 0x0F0F0F0F0F0F0F0F
    x = x + (x >> 8)
    x = x + (x >> 16)
    x = x + (x >> 32)
    return x & 0x7F


def box_sum_valid(x: torch.Tensor, k: int, dim: int) -> torch.Tensor:
    """Sum of ``k`` consecutive entries along ``dim`` (negative: counted from the end; 'valid' mode: length
    n - k + 1).

    Done with about ``2 log2(k)`` shifted additions (exact; no cumulative-sum drift); the compiled texture check
    (:mod:`egorefine.stereo._texture_numba`) repeats this order of additions.
    """
    if dim >= 0:
        raise ValueError(f"box_sum_valid: dim must be negative, got {dim}")
    tail = (slice(None),) * (-dim - 1)

    def part(a, start: int, length: int):
        return a[(Ellipsis, slice(start, start + length)) + tail]

    n = x.shape[dim]
    out = None
    offset = 0
    power = x  # sums of `size` consecutive entries, length n - size + 1
    size = 1
    while True:
        if k & size:
            piece = part(power, offset, n - k + 1)
            out = piece if out is None else out + piece
            offset += size
        if size * 2 > k:
            break
        m = power.shape[dim]
        power = part(power, 0, m - size) + part(power, size, m - size)
        size *= 2
    return out if out is not None else x


def box_mean_same(x: torch.Tensor, k: int) -> torch.Tensor:
    """Mean over a ``k x k`` window, replicated borders, same size as ``x`` ``(B, C, H, W)``."""
    r = k // 2
    xp = F.pad(x, (r, r, r, r), mode="replicate")
    return box_sum_valid(box_sum_valid(xp, k, -2), k, -1) / (k * k)


class _Features:
    """Per-image quantities a cost needs, padded once for the strip loop."""

    def __init__(self, left: torch.Tensor, right: torch.Tensor, cost: str, block: int, max_d: int,
                 census_window: int, prefilter: bool, prefilter_cap: float) -> None:
        r = block // 2
        self.cost, self.r, self.block, self.max_d = cost, r, block, max_d
        self.height, self.width = left.shape[-2:]
        self.dtype = left.dtype
        if cost == "sad" and prefilter:
            left, right = prefilter_xsobel(left, prefilter_cap), prefilter_xsobel(right, prefilter_cap)
        if cost == "census":
            left, right = census_transform(left, census_window), census_transform(right, census_window)
            # F.pad does not take integer tensors on every backend: pad by index replication.
            self.lp = _replicate_pad_int(left, r, r, r, r)
            self.rp = _replicate_pad_int(right, r + max_d, r, r, r)
        else:
            self.lp = F.pad(left, (r, r, r, r), mode="replicate")
            self.rp = F.pad(right, (r + max_d, r, r, r), mode="replicate").contiguous()
        if cost == "zncc":
            eps = 1e-4  # variance floor (grey levels in [0, 1]): flat windows score ~0, not NaN
            mu_l, mu_r = box_mean_same(left, block), box_mean_same(right, block)
            var_l = (box_mean_same(left * left, block) - mu_l * mu_l).clamp_min(0)
            var_r = (box_mean_same(right * right, block) - mu_r * mu_r).clamp_min(0)
            self.mu_l, self.sd_l = mu_l, torch.sqrt(var_l + eps)
            self.mu_rp = F.pad(mu_r, (max_d, 0, 0, 0), mode="replicate").contiguous()
            self.sd_rp = F.pad(torch.sqrt(var_r + eps), (max_d, 0, 0, 0), mode="replicate").contiguous()


def _replicate_pad_int(x: torch.Tensor, left: int, right: int, top: int, bottom: int) -> torch.Tensor:
    h, w = x.shape[-2:]
    rows = torch.arange(-top, h + bottom, device=x.device).clamp(0, h - 1)
    cols = torch.arange(-left, w + right, device=x.device).clamp(0, w - 1)
    return x[..., rows, :][..., cols].contiguous()


def _shifted(padded: torch.Tensor, y0: int, rows: int, width: int, num: int) -> torch.Tensor:
    """View ``(B, num, rows, width)`` of ``padded`` ``(B, 1, Hp, Wp)`` with entry ``[b, j, y, x]``
    = ``padded[b, 0, y0 + y, x + 1 + j]`` (reversed disparity order: j -> d = max_d - 1 - j)."""
    sb, _, sh, sw = padded.stride()
    return padded.as_strided((padded.shape[0], num, rows, width), (sb, sw, sh, sw),
                             padded.storage_offset() + y0 * sh + sw)


def strip_volume(feat: _Features, y0: int, y1: int, min_d: int) -> torch.Tensor:
    """Box-*sum* cost ``(B, D, y1 - y0, W)`` of rows ``[y0, y1)``, reversed disparity order.

    The window sum (not mean: one pass less; divide by ``block**2`` for the mean) of the raw
    cost, or ``block**2 * (1 - ZNCC)``. Candidates with ``x - d < 0`` get :data:`INVALID_COST` added.
    """
    r, k, w, max_d = feat.r, feat.block, feat.width, feat.max_d
    num = max_d - min_d
    rows = y1 - y0 + 2 * r
    left = feat.lp[..., y0 : y0 + rows, :]
    right = _shifted(feat.rp, y0, rows, w + 2 * r, num)
    # the right view has stride 1 along both D and W: write the result in a plain (B, D, h, W) layout
    shape = (left.shape[0], num, rows, w + 2 * r)
    if feat.cost == "sad":
        if left.requires_grad or right.requires_grad:
            raw = (left.expand(shape) - right).contiguous().abs()
        else:
            raw = torch.sub(left, right, out=left.new_empty(shape)).abs_()
    elif feat.cost == "census":
        raw = _popcount(torch.bitwise_xor(left.expand(shape), right).contiguous()).to(feat.dtype)
    else:  # zncc: the window mean of L * R_d, normalised below
        raw = (left.expand(shape) * right).contiguous()
    vol = box_sum_valid(box_sum_valid(raw, k, -2), k, -1)
    if feat.cost == "zncc":
        mu_r = _shifted(feat.mu_rp, y0, y1 - y0, w, num)
        sd_r = _shifted(feat.sd_rp, y0, y1 - y0, w, num)
        mu_l, sd_l = feat.mu_l[..., y0:y1, :], feat.sd_l[..., y0:y1, :]
        vol = (k * k) * (1.0 - (vol / (k * k) - mu_l * mu_r) / (sd_l * sd_r))
    # candidates looking left of the right image: only the first max_d columns can have any
    band = min(max_d, w)
    penalty = _out_of_view_penalty(num, max_d, band, vol)
    if vol.requires_grad:
        return torch.cat([vol[..., :band] + penalty, vol[..., band:]], dim=-1)
    vol[..., :band] += penalty
    return vol


def _out_of_view_penalty(num: int, max_d: int, width: int, like: torch.Tensor) -> torch.Tensor:
    d = max_d - 1 - torch.arange(num, device=like.device).view(num, 1, 1)
    x = torch.arange(width, device=like.device).view(1, 1, width)
    return torch.where(x < d, INVALID_COST, 0.0).to(like.dtype)


def cost_volume(left: torch.Tensor, right: torch.Tensor, max_disparity: int, min_disparity: int = 0,
                block_size: int = 9, cost: str = "sad", census_window: int = 5, prefilter: bool = True,
                prefilter_cap: float = 31.0 / 255.0) -> torch.Tensor:
    """Box-aggregated matching cost of every candidate disparity (lower is better).

    Inputs are assumed checked (use :func:`egorefine.stereo.block_matching` for the checked
    entry point). Costs are window means: SAD of the x-Sobel prefiltered images, ``1 - ZNCC``
    in [0, 2], or the Hamming distance of census strings. Entries with ``x - d < 0`` have
    ``INVALID_COST / block_size**2`` added (they are never chosen).

    Args:
        left, right: ``(B, 1|3, H, W)`` float images.
        max_disparity, min_disparity: candidates ``min_disparity <= d < max_disparity``.
        block_size: odd window size.
        cost: one of :data:`COSTS`.

    Returns:
        ``(B, D, H, W)`` with ``D = max_disparity - min_disparity``; channel ``i`` is ``d = min_disparity + i``.

    >>> cost_volume(torch.rand(1, 1, 8, 12), torch.rand(1, 1, 8, 12), 4, block_size=3).shape
    torch.Size([1, 4, 8, 12])
    """
    feat = _Features(to_grey(left), to_grey(right), cost, block_size, max_disparity, census_window, prefilter,
                     prefilter_cap)
    vol = strip_volume(feat, 0, feat.height, min_disparity).flip(1)
    return vol / (block_size * block_size)
