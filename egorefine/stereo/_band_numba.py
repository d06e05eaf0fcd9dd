"""CPU inference path of :func:`egorefine.stereo.band.match_sgm_band` compiled with numba: census + SGM over a
band of ``width`` candidates per pixel.

Pixel ``p`` searches the integers ``lo(p) .. lo(p) + width - 1``; every per-pixel array keeps its candidates relative
to its own ``lo``, in ``(H, W, width)`` layout with the band axis innermost and contiguous (so LLVM turns the
width-16 loops into SIMD code). The steps, per batch item, each split over ``threads`` bands of rows or columns
(:class:`egorefine.core._jit.Workers`, a barrier between them):

1. census words of both images (one int64 per pixel: up to 48 bits, one population count per Hamming distance);
2. per row band, the raw Hamming distances of each pixel against the right image at ``lo(p) - M .. lo(p) + width +
   M - 1`` (a margin of ``M = _MARGIN`` px either side);
3. per row band, the ``block x block`` window sums: window pixel ``q`` of ``p`` contributes its raw row shifted by
   ``lo(p) - lo(q)`` where that is within the margin, and its distances computed directly where it is not (a depth
   edge, where the two bands lie far apart) or where ``q`` is outside the image (the torch path's replicated
   borders); then the two horizontal paths of each row, still in cache;
4. per column band (one band for 8 paths: the diagonals cross columns), the top-down paths, then the bottom-up ones
   with each pixel's selection as soon as its sum is complete.

A path step reads the previous pixel's path costs shifted by ``lo(p) - lo(prev)`` from a buffer padded with +inf
on both sides (``width + 2`` entries each, so any shift reads inside it: a shift beyond ``width + 1`` is clamped,
where every read is +inf anyway); a candidate whose predecessor lies outside the predecessor's band sees +inf
there, exactly as the torch reference's +inf outside each band. The path costs are int32 where that is exact
(integer penalties, every sum below 2**24: the default), otherwise float32 with the torch path's operations in its
order; either way the aggregated costs equal the torch reference's float32 values bit for bit, and the selection
repeats :func:`egorefine.stereo.matching._select` (including its index-in-mantissa encoding over the full range,
so that ties and the sub-pixel fit come out the same).

``AVAILABLE`` is False when numba cannot be imported; callers then take the torch path.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core._jit import AVAILABLE, Workers, thread_count
from ..core._jit import bands as _bands
from ..core._jit import jit as _jit

__all__ = ["AVAILABLE", "match_band"]

# raw distances kept this many px beyond each side of a pixel's band: window neighbours whose band starts within
# this many px of the centre's read them shifted (on a surface neighbouring bands differ by a pixel or two)
_MARGIN = 4
# int32 path costs: this stands for +inf (above every path cost, and + P1 stays far from overflowing)
_INT_INF = 1 << 30
_HALF_INVALID = 5.0e5  # matching._select's INVALID_COST / 2

if AVAILABLE:  # numba is a dependency, but the package stays importable (torch path) without it
    from ._sgm_numba import _ctpop, _edge_padded  # (_ctpop: LLVM's population count)

    @_jit
    def _census_rows(padded, window, y0, y1, out):
        """Rows ``[y0, y1)`` of the census words ``out`` ``(H, W)`` int64 of an image replicate-padded by
        ``window // 2``: bit ``k`` set where neighbour ``k`` (row-major, centre skipped) is darker than the centre,
        as :func:`egorefine.stereo.census_transform`."""
        w = out.shape[1]
        r = window // 2
        for y in range(y0, y1):
            for x in range(w):
                out[y, x] = 0
            k = 0
            for dy in range(window):
                for dx in range(window):
                    if dy == r and dx == r:
                        continue
                    bit = np.int64(k)
                    for x in range(w):  # branch-free, vectorised along the row
                        out[y, x] |= np.int64(padded[y + dy, x + dx] < padded[y + r, x + r]) << bit
                    k += 1

    @_jit
    def _raw_rows(cl, cr, lo, y0, y1, raw):
        """Rows ``[y0, y1)`` of ``raw`` ``(H, W, n)`` int16: ``raw[y, x, t]`` is the Hamming distance of the left
        census at ``(y, x)`` and the right one at column ``x - (lo[y, x] - _MARGIN + t)`` (clamped to the row: the
        torch path's replicated border)."""
        w = cl.shape[1]
        n = raw.shape[2]
        for y in range(y0, y1):
            for x in range(w):
                base = x - lo[y, x] + _MARGIN  # right column of t = 0
                lv = cl[y, x]
                row = raw[y, x]
                if base - (n - 1) >= 0 and base <= w - 1:
                    right = cr[y, base - (n - 1) : base + 1]  # (a slice: indices LLVM knows are >= 0 vectorise)
                    for t in range(n):
                        row[t] = _ctpop(lv ^ right[n - 1 - t])
                else:
                    for t in range(n):
                        row[t] = _ctpop(lv ^ cr[y, min(max(base - t, 0), w - 1)])

    @_jit
    def _window_sums(cl, cr, lo, raw, r, y, sums, cost):
        """Row ``y`` of ``cost`` ``(H, W, width)``: the ``(2r + 1)^2`` window sums of the Hamming distances of each
        pixel's band (as cost.strip_volume: rows and both images' columns clamped separately). ``sums``: int32
        scratch of ``width``."""
        h, w = cl.shape
        width = cost.shape[2]
        for x in range(w):
            lp = lo[y, x]
            for k in range(width):
                sums[k] = 0
            for dy in range(-r, r + 1):
                yy = min(max(y + dy, 0), h - 1)
                for dx in range(-r, r + 1):
                    xx = x + dx
                    if xx >= 0 and xx < w:
                        s = lp - lo[yy, xx]
                        if s >= -_MARGIN and s <= _MARGIN:
                            src = raw[yy, xx, _MARGIN + s :]
                            for k in range(width):
                                sums[k] += src[k]
                            continue
                    # a neighbour's band too far from this one's (a depth edge), or a border column: directly
                    lv = cl[yy, min(max(xx, 0), w - 1)]
                    for k in range(width):
                        sums[k] += _ctpop(lv ^ cr[yy, min(max(xx - lp - k, 0), w - 1)])
            out = cost[y, x]
            for k in range(width):
                out[k] = sums[k]

    @_jit(inline="always")
    def _keep(o, width, acc, mode, lowest):
        """A path row ``o[:width]`` set into (``mode`` 1) or added to (2) ``acc`` (0: neither); returns the minimum
        of ``lowest`` (a pad: +inf) and the row."""
        if mode == 1:
            for k in range(width):
                acc[k] = o[k]
        elif mode == 2:
            for k in range(width):
                acc[k] = acc[k] + o[k]
        for k in range(width):
            lowest = min(lowest, o[k])
        return lowest

    @_jit(inline="always")
    def _step(prev, shift, m, crow, klim, invalid, p1, p2, out, acc, mode):
        """One SGM step (sgm._step) of one pixel: ``out[pad + k] = (C[k] - m) + min(prev[k'], m + P2,
        prev[k' +- 1] + P1)``, ``k' = k + shift`` (the predecessor's band index of this pixel's candidate ``k``),
        ``C[k] = crow[k] + invalid`` for ``k > klim`` (out of view), else ``crow[k]``. ``prev``/``out``: path
        buffers (_buffers), +inf outside ``[pad, pad + width)``; ``m``: the predecessor's minimum. ``mode`` 1 sets,
        2 adds the costs to ``acc`` (0: neither). Returns the new minimum."""
        width = crow.shape[0]
        pad = width + 2
        # slices, so that every index is a loop counter plus a constant (LLVM then knows none is negative, and
        # vectorises; numba's wraparound test of a possibly negative index would keep every access scalar)
        pr = prev[pad + min(max(shift, -pad + 1), pad - 1) - 1 :]  # pr[k + 1]: the predecessor at candidate k
        o = out[pad:]
        mp2 = m + p2
        zero = invalid - invalid
        for k in range(width):
            best = min(min(pr[k + 1], mp2), min(pr[k], pr[k + 2]) + p1)
            o[k] = ((crow[k] + (invalid if k > klim else zero)) - m) + best
        return _keep(o, width, acc, mode, out[0])

    @_jit(inline="always")
    def _start(crow, klim, invalid, out, acc, mode):
        """A path's first pixel (sgm._scan's zero predecessor): ``L = C``; as _step otherwise."""
        o = out[crow.shape[0] + 2 :]
        zero = invalid - invalid
        for k in range(crow.shape[0]):
            o[k] = crow[k] + (invalid if k > klim else zero)
        return _keep(o, crow.shape[0], acc, mode, out[0])

    @_jit
    def _buffers(rows, width, inf, like):
        """``rows`` path buffers of ``3 width + 4`` entries of ``like``'s dtype, all ``inf`` (a band is written at
        ``[width + 2, 2 width + 2)``)."""
        return np.full((rows, 3 * width + 4), inf, dtype=like.dtype)

    @_jit
    def _rows_pass(cl, cr, lo, raw, r, y0, y1, p1, p2, invalid, inf, cost, acc):
        """Rows ``[y0, y1)``: the window sums into ``cost``, then each row's left-to-right plus right-to-left path
        costs into ``acc`` (sgm_aggregate's first two paths, in its order)."""
        w = cl.shape[1]
        width = cost.shape[2]
        sums = np.empty(width, np.int32)
        buf = _buffers(2, width, inf, cost)
        for y in range(y0, y1):
            _window_sums(cl, cr, lo, raw, r, y, sums, cost)
            m = _start(cost[y, 0], -lo[y, 0], invalid, buf[0], acc[y, 0], 1)
            for x in range(1, w):
                k = x & 1
                m = _step(buf[1 - k], lo[y, x] - lo[y, x - 1], m, cost[y, x], x - lo[y, x], invalid, p1, p2, buf[k],
                          acc[y, x], 1)
            m = _start(cost[y, w - 1], w - 1 - lo[y, w - 1], invalid, buf[(w - 1) & 1], acc[y, w - 1], 2)
            for x in range(w - 2, -1, -1):
                k = x & 1
                m = _step(buf[1 - k], lo[y, x] - lo[y, x + 1], m, cost[y, x], x - lo[y, x], invalid, p1, p2, buf[k],
                          acc[y, x], 2)

    @_jit(inline="always")
    def _select_pixel(total, path, paths, lo, width, max_d, min_d, bits, subpixel, parabola, floor, eps, codes):
        """matching._select of one pixel from its path sums so far ``total`` and its last path's costs ``path``
        (at ``[width + 2, 2 width + 2)``): the aggregated cost ``(total + path) / paths`` as float32, encoded with the
        full range's index in the low mantissa bits (matching._encode), the winner and its checks. Returns
        ``(disparity, ok, variance)``; ``ok`` before the texture check."""
        pad = width + 2
        fpaths = np.float32(paths)
        codef = codes.view(np.float32)
        high = np.int32(-(1 << bits))
        top = max_d - 1 - lo  # full-range index of candidate k: top - k
        last = path[pad:]
        for k in range(width):
            codef[k] = np.float32(total[k] + last[k]) / fpaths
        best = np.int32(0x7FFFFFFF)
        for k in range(width):
            code = (max(codes[k], np.int32(0)) & high) | np.int32(top - k)
            codes[k] = code
            best = min(best, code)
        kb = top - (best & ((1 << bits) - 1))
        half = np.float32(_HALF_INVALID)
        c_best = codef[kb]
        plus_ok = kb < width - 1 and codef[min(kb + 1, width - 1)] < half
        minus_ok = kb > 0 and codef[max(kb - 1, 0)] < half
        ok = c_best < half and plus_ok and (kb > 0 or lo == 0)
        interior = plus_ok and minus_ok
        d_int = np.float32(lo + kb)
        if not interior:
            return d_int, ok, np.float32(1.0)
        c_plus, c_minus = codef[kb + 1], codef[kb - 1]
        curvature = (c_minus - np.float32(2.0) * c_best) + c_plus
        if parabola:
            denom = np.float32(2.0) * curvature
        else:
            denom = np.float32(2.0) * (max(c_minus, c_plus) - c_best)
        offset = min(max((c_minus - c_plus) / max(denom, eps), np.float32(-0.5)), np.float32(0.5))
        disparity = d_int + offset if subpixel else d_int
        q = (c_best + floor) / (max(curvature, np.float32(0.0)) + eps)
        variance = np.float32(1.0 / 12.0) + np.float32(0.25) * (q * q)
        return disparity, ok, min(variance, np.float32(1.0e4))

    @_jit
    def _vertical_pass(cost, acc, lo, x0, x1, shifts, top_down, p1, p2, invalid, inf, select, disparity, ok, variance):
        """Columns ``[x0, x1)``: with ``top_down`` the top-down paths of each column shift in ``shifts`` (0, +1, -1:
        the predecessor of column x is x - shift) added to ``acc``; then the bottom-up ones, the last of them
        completing each pixel's sum for its selection (_select_pixel) into ``disparity``, ``ok``, ``variance``. A
        predecessor outside the image starts the path."""
        h, w, width = cost.shape
        n = x1 - x0
        ns = shifts.shape[0]
        (paths, max_d, min_d, bits, subpixel, parabola, floor, eps) = select
        prev = _buffers(ns * n, width, inf, cost)
        cur = prev.copy()
        mins = np.zeros(ns * n, dtype=cost.dtype)
        cmins = np.zeros_like(mins)
        codes = np.empty(width, np.int32)
        for direction in range(0 if top_down else 1, 2):
            for t in range(h):
                y = t if direction == 0 else h - 1 - t
                yp = y - 1 if direction == 0 else y + 1
                for s in range(ns):
                    dx = shifts[s]
                    last = direction == 1 and s == ns - 1
                    mode = 0 if last else 2
                    for i in range(n):
                        x = x0 + i
                        xp = x - dx
                        q = s * n + i
                        if t == 0 or xp < x0 or xp >= x1:
                            cmins[q] = _start(cost[y, x], x - lo[y, x], invalid, cur[q], acc[y, x], mode)
                        else:
                            src = s * n + xp - x0
                            cmins[q] = _step(prev[src], lo[y, x] - lo[yp, xp], mins[src], cost[y, x], x - lo[y, x],
                                             invalid, p1, p2, cur[q], acc[y, x], mode)
                        if last:
                            d, good, var = _select_pixel(acc[y, x], cur[q], paths, lo[y, x], width, max_d, min_d,
                                                         bits, subpixel, parabola, floor, eps, codes)
                            disparity[y, x] = d
                            ok[y, x] = good
                            variance[y, x] = var
                prev, cur = cur, prev
                mins, cmins = cmins, mins


def _path_arithmetic(cost_max: int, p1: np.float32, p2: np.float32, paths: int) -> tuple:
    """``(T, inf, invalid)``: the path costs' type, its +inf and INVALID_COST in it. int32 where the torch path's
    float32 values are exact integers (integer penalties, every sum below 2**24), else float32."""
    integral = p1 >= 0 and p2 >= 0 and p1 == int(p1) and p2 == int(p2)
    if integral and paths * (1.0e6 + cost_max + 2 * float(p2) + float(p1)) < 1 << 24:
        return np.int32, np.int32(_INT_INF), np.int32(1_000_000)
    return np.float32, np.float32(np.inf), np.float32(1.0e6)


def match_band(grey_l: torch.Tensor, grey_r: torch.Tensor, lo: torch.Tensor, width: int, max_disparity: int,
               min_disparity: int, block_size: int, census_window: int, p1: float, p2: float, paths: int,
               opts: dict, threads: int | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Census, window sums, SGM over each pixel's band and the selection of float32 CPU grey pairs.

    Args:
        grey_l, grey_r: ``(B, 1, H, W)`` float32 CPU grey images.
        lo: ``(B, 1, H, W)`` int32, each pixel's lowest candidate (``min_disparity <= lo <= max_disparity - width``).
        width: candidates per pixel (>= 2).
        max_disparity, min_disparity, block_size, census_window: as :func:`egorefine.stereo.match_stereo`.
        p1, p2: SGM penalties in window-*sum* units.
        paths: 4 or 8.
        opts: the selection options of ``matching._select`` (``subpixel``, ``subpixel_fit``, ``cost_floor``,
            ``scale``).
        threads: worker threads (None: ``torch.get_num_threads()``).

    Returns:
        ``(disparity, valid, variance)``, each ``(B, 1, H, W)``, before the texture check and the zeroing of invalid
        pixels (as ``census_sgm_select``).
    """
    b, _, h, w = grey_l.shape
    threads = thread_count(threads)
    left, right = grey_l.detach().numpy(), grey_r.detach().numpy()
    lo_np = np.ascontiguousarray(lo.numpy()[:, 0], dtype=np.int32)
    disparity = np.empty((b, h, w), np.float32)
    valid = np.empty((b, h, w), np.bool_)
    variance = np.empty((b, h, w), np.float32)
    cost_max = block_size * block_size * (census_window * census_window - 1)
    dtype, inf, invalid = _path_arithmetic(cost_max, np.float32(p1), np.float32(p2), paths)
    f1, f2 = dtype(np.float32(p1)), dtype(np.float32(p2))
    num = max_disparity - min_disparity
    select = (paths, max_disparity, min_disparity, max(1, (num - 1).bit_length()), bool(opts["subpixel"]),
              opts["subpixel_fit"] == "parabola", np.float32(opts["cost_floor"] * opts["scale"]),
              np.float32(torch.finfo(torch.float32).eps * 16 * opts["scale"]))
    shifts = np.array((0, 1, -1) if paths == 8 else (0,), np.int64)
    row_bands = _bands(h, threads)
    col_bands = _bands(w, threads) if paths == 4 else [(0, w)]
    r, pad = block_size // 2, census_window // 2
    workers = Workers(threads)
    def item(i: int) -> None:  # (a function, so that each lambda below sees this item's arrays)
        census = np.empty((2, h, w), np.int64)
        padded = [_edge_padded(img[i, 0], pad) for img in (left, right)]
        workers.map(lambda job: _census_rows(padded[job[0]], census_window, *job[1], census[job[0]]),
                    [(k, band) for k in (0, 1) for band in row_bands])
        raw = np.empty((h, w, width + 2 * _MARGIN), np.int16)
        cost = np.empty((h, w, width), dtype)
        acc = np.empty((h, w, width), dtype)
        workers.map(lambda band: _raw_rows(census[0], census[1], lo_np[i], *band, raw), row_bands)
        workers.map(lambda band: _rows_pass(census[0], census[1], lo_np[i], raw, r, *band, f1, f2, invalid, inf,
                                            cost, acc), row_bands)
        workers.map(lambda band: _vertical_pass(cost, acc, lo_np[i], *band, shifts, True, f1, f2, invalid, inf,
                                                select, disparity[i], valid[i], variance[i]), col_bands)

    for i in range(b):
        item(i)
    as_t = lambda a: torch.from_numpy(a).unsqueeze(1)  # noqa: E731
    return as_t(disparity), as_t(valid), as_t(variance)
