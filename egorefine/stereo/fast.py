"""Exact integer fast path of the default matcher: SAD of the x-Sobel prefiltered images,
box aggregation, winner-takes-all with sub-pixel fit and left-right / uniqueness checks.

Used by :func:`egorefine.stereo.match_stereo` when no gradient is needed. The clipped x-Sobel
responses are quantised to integers (``round(255 * scale * g)``, ``scale`` sub-grey-levels; for
8-bit images this is exact as in OpenCV's StereoBM) so that the whole cost volume lives in
int16: absolute differences and their box sums are exact integers, and every full-volume pass
moves half the bytes of float32 (CPU int16 kernels are vectorised twice as wide). Only the
winner's, its neighbours' and the runner-up's costs are converted to float.

The disparity axis is reversed as in :mod:`egorefine.stereo.cost` (index ``j`` is disparity
``max_disparity - 1 - j``): the shifted right image is then a positive-stride view.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import torch
import torch.nn.functional as F

from .cost import _shifted, prefilter_xsobel

__all__ = ["int_scale", "match_sad_int", "INVALID_VARIANCE"]

_MAX_SCALE = 8
# int16 box sum of a candidate that is out of view (or knocked out): above any real sum
_INVALID = 32767
# the matcher's variance constants (px^2; egorefine.stereo.matching imports them from here):
# where the matcher gives no measurement, and the floor of an integer-rounded match
INVALID_VARIANCE = 1.0e4
_QUANTISATION_VARIANCE = 1.0 / 12.0
# box sums of a strip: ~4 MB of int16; raw costs of a chunk of disparities: ~0.5 MB (measured best of
# 2**19..2**23 and 2**16..2**19 at 640x480 and 64 / 128 disparities)
_STRIP_ELEMENTS = 1 << 21
_CHUNK_ELEMENTS = 1 << 18
_MIN_ROWS = 8  # at least this many output rows per strip (the 2r halo rows are computed twice)


def int_scale(block_size: int, cap: float) -> int:
    """Largest sub-grey-level scale (<= 8) whose box sums of ``|L - R|`` fit int16; 0 if none does."""
    for scale in range(_MAX_SCALE, 0, -1):
        if block_size * block_size * 2 * round(255.0 * scale * cap) < _INVALID:
            return scale
    return 0


def _quantise(grey: torch.Tensor, cap: float, scale: int, pad: tuple[int, int, int, int]
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """Clipped x-Sobel ``g`` and, padded (replicate), as non-negative int16 ``round(255 * scale * (g + cap))``."""
    g = prefilter_xsobel(grey, cap)
    c = round(255.0 * scale * cap)
    q = (F.pad(g, pad, mode="replicate") * (255.0 * scale)).round_().clamp_(-c, c).add_(c)
    return g, q.to(torch.int16).contiguous()


def _box_rows(x: torch.Tensor, k: int, out: torch.Tensor) -> torch.Tensor:
    """'valid' box sum of ``k`` rows (dim -2) of ``x`` ``(B, D, n, W)`` into ``out`` ``(B, D, n - k + 1, W)``.

    One reduction over an overlapping strided view (window axis of row stride): torch vectorises it
    along the contiguous W axis, about the price of one addition pass for any ``k``.
    """
    b, d, n, w = x.shape
    sb, sd, sh, sw = x.stride()
    windows = x.as_strided((b, d, n - k + 1, k, w), (sb, sd, sh, sh, sw), x.storage_offset())
    return torch.sum(windows, dim=3, dtype=x.dtype, out=out)


def _box_cols(x: torch.Tensor, k: int, out: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """'valid' box sum of an odd number ``k`` of columns (dim -1) of ``x`` into ``out`` (``pairs``: scratch, x's shape).

    A window reduction whose window axis has stride 1 is not vectorised, so sums of adjacent pairs
    ``p[x] = x[x] + x[x + 1]`` are formed first: ``box_k[x] = x[x] + sum_i p[x + 1 + 2 i]`` (window stride 2).
    """
    w_out = out.shape[-1]
    if k == 1:
        return out.copy_(x[..., :w_out])
    half = (k - 1) // 2
    p = torch.add(x[..., :-1], x[..., 1:], out=pairs[..., :-1])
    b, d, n, _ = p.shape
    sb, sd, sh, sw = p.stride()
    windows = p.as_strided((b, d, n, half, w_out), (sb, sd, sh, 2 * sw, sw), p.storage_offset() + sw)
    torch.sum(windows, dim=3, dtype=x.dtype, out=out)
    return out.add_(x[..., :w_out])


def match_sad_int(left: torch.Tensor, right: torch.Tensor, max_d: int, min_d: int, block: int, cap: float,
                  scale: int, opts: dict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Disparity, validity and variance of the box-aggregated SAD matcher, computed in integers.

    Same decisions and formulas as ``egorefine.stereo.matching._select`` on the float volume
    (up to its float rounding; a right-view tie within ``lr_threshold`` of the left winner passes
    the left-right check here).

    Args:
        left, right: ``(B, 1, H, W)`` grey float images (no gradient needed).
        max_d, min_d, block, cap: search range, odd window size, prefilter clip level.
        scale: quantisation scale from :func:`int_scale` (>= 1).
        opts: the matcher's settings (``subpixel``, ``subpixel_fit``, ``lr_check``, ``lr_threshold``,
            ``uniqueness_ratio``, ``texture_threshold``, ``cost_floor``).

    Returns:
        ``(disparity, valid, variance)`` each ``(B, 1, H, W)`` (0 and ``INVALID_VARIANCE`` where invalid).
    """
    lr_check, lr_threshold, uniqueness_ratio = opts["lr_check"], opts["lr_threshold"], opts["uniqueness_ratio"]
    b, _, h, w = left.shape
    r = block // 2
    num = max_d - min_d
    bits = max(1, (num - 1).bit_length())
    lq = _quantise(left, cap, scale, (r, r, r, r))[1]
    rq = _quantise(right, cap, scale, (r + max_d, r, r, r))[1]
    dev = left.device
    rows = max(_MIN_ROWS, _STRIP_ELEMENTS // max(1, b * num * (w + 2 * r)) - 2 * r)
    rows = min(h, rows)
    wp = w + 2 * r
    # raw costs and their vertical sums are built for a chunk of disparities at a time (cache-sized);
    # only the box sums of the strip hold every disparity
    chunk = max(1, min(num, _CHUNK_ELEMENTS // max(1, b * (rows + 2 * r) * wp)))
    # box sums with max_d extra columns of _INVALID for the right view's diagonal
    # and lr guard planes of _INVALID on both ends of the disparity axis (candidates beyond the range)
    guard = min(lr_threshold, num - 1) if lr_check else 0
    box_shape = (b, num + 2 * guard, rows, w + max_d)
    # index codes min(cost - min, 1) * 2**bits + j: amin gives the lowest index of the minimum
    # (``amin`` over dim 1 is vectorised; ``argmin`` there, and comparisons to bool, are several times slower)
    jvec = torch.arange(num, dtype=torch.int16, device=dev).view(1, num, 1, 1)
    band = min(max_d, w)
    d_col = (max_d - 1 - torch.arange(num, device=dev)).view(1, num, 1, 1)
    # _INVALID where x - d < 0, else 0: applied with maximum (int16, vectorised; masked_fill is not)
    out_of_view = ((torch.arange(band, device=dev).view(1, 1, 1, band) < d_col) * _INVALID).to(torch.int16)
    x_idx = torch.arange(w, device=dev).view(1, 1, 1, w)
    mask = (1 << bits) - 1
    # flat offsets into box_buf (contiguous) of batch item, first real plane, row and column
    sw, sh = 1, w + max_d
    sj = rows * sh
    sb = (num + 2 * guard) * sj
    base = (torch.arange(b, device=dev).view(b, 1, 1, 1) * sb + guard * sj
            + torch.arange(rows, device=dev).view(1, 1, rows, 1) * sh + x_idx * sw)

    def reuse(buffer: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
        """A contiguous ``shape`` tensor in the storage of ``buffer`` (whose content is no longer needed):
        reusing the strip buffers keeps the working set in cache."""
        return buffer.view(-1)[: math.prod(shape)].view(shape)

    def argmin(vol: torch.Tensor, code: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Minimum over dim 1 and its lowest index."""
        low = vol.amin(dim=1, keepdim=True)
        c = torch.sub(vol, low, out=code).clamp_max_(1)
        c = torch.add(jvec, c, alpha=1 << bits, out=c)
        return low, (c.amin(dim=1, keepdim=True) & mask).long()

    dtype = left.dtype
    unit = 1.0 / (255.0 * scale)
    area = float(block * block)
    disparity = torch.empty((b, 1, h, w), dtype=dtype, device=dev)
    variance = torch.empty_like(disparity)
    valid = torch.empty((b, 1, h, w), dtype=torch.bool, device=dev)
    # texture check in integers: window sum of |x-Sobel| (quantised, replicate borders) against the
    # threshold on the window mean; as exact as the costs
    c_level = round(255.0 * scale * cap)
    t_need = opts["texture_threshold"] * area * 255.0 * scale
    def run(starts: list[int]) -> None:
        """Match the strips starting at rows ``starts`` with this call's own buffers."""
        raw = torch.empty((b, chunk, rows + 2 * r, wp), dtype=torch.int16, device=dev)
        vert = torch.empty((b, chunk, rows, wp), dtype=torch.int16, device=dev)
        code_buf = torch.empty((b, num, rows, w), dtype=torch.int16, device=dev)
        box_buf = torch.full(box_shape, _INVALID, dtype=torch.int16, device=dev)
        t_abs = torch.empty((b, 1, rows + 2 * r, wp), dtype=torch.int16, device=dev)
        t_vert = torch.empty((b, 1, rows, wp), dtype=torch.int16, device=dev)
        t_pairs, t_sum = torch.empty_like(t_vert), torch.empty((b, 1, rows, w), dtype=torch.int16, device=dev)

        def texture_ok(y0: int, n: int) -> torch.Tensor:
            a = torch.sub(lq[..., y0 : y0 + n + 2 * r, :], c_level, out=t_abs[:, :, : n + 2 * r]).abs_()
            v = _box_rows(a, block, t_vert[:, :, :n])
            return _box_cols(v, block, t_sum[:, :, :n], t_pairs[:, :, :n]) >= t_need

        for y0 in starts:
            y1 = min(h, y0 + rows)
            n = y1 - y0
            lv = lq[..., y0 : y1 + 2 * r, :]
            rv = _shifted(rq, y0, n + 2 * r, wp, num)
            box_all = box_buf[:, guard : guard + num, :n]
            for c0 in range(0, num, chunk):
                m = min(num, c0 + chunk) - c0
                rw = torch.sub(lv, rv[:, c0 : c0 + m], out=reuse(raw, (b, m, n + 2 * r, wp))).abs_()
                vsum = _box_rows(rw, block, reuse(vert, (b, m, n, wp)))
                _box_cols(vsum, block, box_all[:, c0 : c0 + m, :, :w], reuse(raw, (b, m, n, wp)))
            hsum = box_all[..., :w]
            torch.maximum(hsum[..., :band], out_of_view, out=hsum[..., :band])
            best, j = argmin(hsum, code_buf[:, :, :n])
            jm, jp = (j - 1).clamp_min(0), (j + 1).clamp_max(num - 1)
            c_plus, c_minus = torch.gather(hsum, 1, jm), torch.gather(hsum, 1, jp)  # reversed: j - 1 is d + 1
            ok = (best < _INVALID) & (j > 0) & (c_plus < _INVALID)
            inner = ok & (j < num - 1) & (c_minus < _INVALID)  # interior minimum: the sub-pixel fit is defined
            if min_d > 0:
                ok &= j < num - 1
            if lr_check:
                # left-right check (right view from the same volume: cost_right(xr, d) = cost_left(xr + d, d)):
                # the right view's minimum at xr = x - d must be reached by a disparity within lr_threshold of d
                diag = box_all.as_strided((b, num, n, w), (sb, sj - sw, sh, sw),
                                          box_all.storage_offset() + (max_d - 1) * sw)
                right_min = diag.amin(dim=1, keepdim=True)
                xr = (x_idx - (max_d - 1 - j)).clamp_min(0)  # x - d (>= 0 where ok)
                # cost_right(x - d, d') = cost_left(x - d + d', d') lies at plane j' = j + dj, column x - dj;
                # d' outside the range reads a guard plane. Indices stay in the buffer (dj = -guard needs j >= 0)
                flat = base[:, :, :n] + j * sj
                near = torch.take(box_buf, flat)
                for dj in range(-guard, guard + 1):
                    if dj:
                        near = torch.minimum(near, torch.take(box_buf, flat + dj * (sj - sw)))
                ok &= near <= right_min.gather(3, xr)
            if uniqueness_ratio > 0:
                inv = torch.full_like(best, _INVALID)
                for nb in (jm, j, jp):
                    hsum.scatter_(1, nb, inv)
                second = hsum.amin(dim=1, keepdim=True).float()
                ok &= second > best.float() * (1 + uniqueness_ratio)
            ok &= texture_ok(y0, n)
            valid[..., y0:y1, :] = ok
            _tail(j, best, c_plus, c_minus, ok, inner, max_d, unit, area, opts,
                  (disparity[..., y0:y1, :], variance[..., y0:y1, :]))

    starts = list(range(0, h, rows))
    threads = torch.get_num_threads()
    workers = min(threads, len(starts))
    if dev.type != "cpu" or workers < 2:
        run(starts)
        return disparity, valid, variance
    # CPU with several threads: strips in parallel, each worker single-threaded. Intra-op threading of
    # the many mid-sized strip ops costs more in thread wake-ups than it gains (measured 2x slower with
    # 2 threads); the ops release the GIL, so Python threads run strips concurrently.
    def worker(k: int) -> None:
        torch.set_num_threads(1)
        run(starts[k::workers])

    try:
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(worker, range(workers)))
    finally:
        torch.set_num_threads(threads)
    return disparity, valid, variance


def _tail(j: torch.Tensor, best: torch.Tensor, c_plus: torch.Tensor, c_minus: torch.Tensor, valid: torch.Tensor,
          inner: torch.Tensor, max_d: int, unit: float, area: float, opts: dict, out: tuple[torch.Tensor, ...]) -> None:
    """Sub-pixel fit and variance of one strip (the formulas of ``matching._select``), written into ``out``.

    0/1 float factors replace torch.where (where and masked_fill on bool masks are ~20x slower than
    arithmetic on CPU); strip-sized temporaries stay in cache.
    """
    disparity, variance = out
    dtype = disparity.dtype
    c0, cp, cm = (c.to(dtype).mul_(unit) for c in (best, c_plus, c_minus))
    inner = inner.view(torch.uint8).to(dtype)
    keep = valid.view(torch.uint8).to(dtype)
    curvature = cm - 2 * c0 + cp
    eps = torch.finfo(dtype).eps * 16 * area
    if opts["subpixel_fit"] == "parabola":
        denom = 2 * curvature
    else:  # equiangular (V-shaped) fit
        denom = 2 * (torch.maximum(cm, cp) - c0)
    torch.sub(max_d - 1, j, out=disparity)
    if opts["subpixel"]:
        disparity += ((cm - cp) / denom.clamp_min(eps)).clamp_(-0.5, 0.5).mul_(inner)
    disparity.mul_(keep)
    var = ((c0 + opts["cost_floor"] * area) / (curvature.clamp_min_(0) + eps)).square_().mul_(0.25)
    var = var.add_(_QUANTISATION_VARIANCE).clamp_max_(INVALID_VARIANCE).sub_(1).mul_(inner).add_(1)
    # INVALID_VARIANCE where invalid (0/1 factors: exact)
    torch.mul(var, keep, out=variance).add_(keep.neg_().add_(1).mul_(INVALID_VARIANCE))
