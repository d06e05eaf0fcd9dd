"""CPU inference path of :func:`egorefine.stereo.residual.match_residual`, compiled with numba.

The torch path's formulas in float32, one band of rows at a time, for either window:

* ``"warped"`` (:func:`_band`): each row is x-Sobel prefiltered (:func:`egorefine.stereo.cost.prefilter_xsobel`'s
  operations) and its ``2 radius + 1`` planes of ``|L' - R'(warped)|`` are built once, when the row enters the
  window (a ring of the window's rows stays in cache); every output row slides its column sums down and sums its
  window along the row;
* ``"fronto"`` (:func:`_fronto_band`): per output row, the window costs of each disparity some pixel needs, over
  the runs of pixels that need it, then each pixel's own candidates.

Both then read the winner, its neighbours, the runner-up and the texture sum while the row is in cache
(:func:`_decide_row`). The sums are added in another order than ``avg_pool2d``'s, so the costs agree to float32
rounding, not bit for bit. Bands of a fixed number of rows run as nogil kernels on
:class:`egorefine.core._jit.Workers`; the output does not depend on the thread count.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core._jit import AVAILABLE, Workers, thread_count
from ..core._jit import bands as _bands
from ..core._jit import jit as _jit
from .fast import _QUANTISATION_VARIANCE, INVALID_VARIANCE

__all__ = ["AVAILABLE", "match_residual"]

# rows per band: fixed, so that where the column sums restart (and so their float rounding) does not depend on the
# thread count; each band recomputes the window's 2 r rows above it
_BAND_ROWS = 32
_F = np.float32


if AVAILABLE:
    from ._sad_numba import xsobel_row

    @_jit(inline="always")
    def _diff_row(lrow, rrow, prow, okrow, radius, out, base, frac, first, inside, near):
        """The ``2 radius + 1`` planes of ``|L' - R'(warped)|`` of one row into ``out[:n]``, and ``|L'|`` into
        ``out[n]`` (its window sum is the texture measure); ``base .. near`` are scratch rows.

        Per row: the band centre's floor and fraction (a compute-only loop), the ``n + 1`` right-row samples every
        candidate interpolates between (a gather-only loop), then the planes from them (vectorised); pixels whose
        band leaves the row take the torch path's clamped samples in a scalar fix-up loop.
        """
        W = lrow.shape[0]
        n = 2 * radius + 1
        top = _F(W - 1)
        ld = out[n]
        for x in range(W):
            p = prow[x]
            # as the torch path: the prior counts as 0 where it may not be used
            b = _F(x) - (p if okrow[x] and np.isfinite(p) else _F(0.0))
            fl = np.floor(b)
            base[x] = b
            frac[x] = b - fl
            # candidate j samples rrow[fl + radius - j] and the next one (fl clamped first: a huge prior must
            # not overflow the integer conversion; such pixels take the fix-up loop)
            lo = np.int64(min(max(fl, _F(-2 * W)), _F(2 * W))) - radius
            inside[x] = (lo >= 0) & (lo + 2 * radius <= W - 2)
            first[x] = min(max(lo, np.int64(0)), np.int64(W - 2 - 2 * radius))
            ld[x] = abs(lrow[x])
        for k in range(n + 1):
            nk = near[k]
            for x in range(W):
                nk[x] = rrow[first[x] + k]
        for j in range(n):
            dj = out[j]
            v0s, v1s = near[2 * radius - j], near[2 * radius - j + 1]
            for x in range(W):
                v0 = v0s[x]
                dj[x] = abs(lrow[x] - (v0 + frac[x] * (v1s[x] - v0)))
        for x in range(W):
            if inside[x]:
                continue
            for j in range(n):  # the torch path's clamp to [0, W - 1]
                sc = min(max(base[x] - _F(j - radius), _F(0.0)), top)
                x0 = min(np.floor(sc), _F(W - 2))
                f = sc - x0
                v0 = rrow[np.int64(x0)]
                out[j, x] = abs(lrow[x] - (v0 + f * (rrow[np.int64(x0) + 1] - v0)))

    @_jit(inline="always")
    def _window_sums(col, r, out):
        """``out[i] = col[i] + ... + col[i + 2 r]``: the row sums of a window's column sums (slices from 0, SIMD)."""
        m = out.shape[0]
        for i in range(m):
            out[i] = col[i]
        for u in range(1, 2 * r + 1):
            seg = col[u:u + m]
            for i in range(m):
                out[i] += seg[i]

    @_jit(inline="always")
    def _clear_row(drow, vrow, varrow):
        """An output row of no valid pixels (0, False, INVALID_VARIANCE)."""
        for x in range(drow.shape[0]):
            drow[x] = _F(0.0)
            vrow[x] = False
            varrow[x] = _F(INVALID_VARIANCE)

    @_jit(error_model="numpy")  # its divisions have denominators clamped above zero: no checks, SIMD code
    def _decide_row(cost, n, parabola, flt, c0, best, runner, off, var):
        """The matcher's decision on one row of ``n`` candidate costs ``cost[:n, :m]``: the winner ``c0``/``best``,
        the runner-up beyond +-1 (``runner``), the sub-pixel offset of the fit through the winner's neighbours and
        the variance model. Loops over the row without gathers (LLVM vectorises them), then one that gathers the
        neighbours."""
        m = c0.shape[0]
        for x in range(m):
            c0[x] = cost[0, x]
            best[x] = 0
        for j in range(1, n):
            c = cost[j]
            for x in range(m):
                lower = c[x] < c0[x]
                c0[x] = c[x] if lower else c0[x]
                best[x] = np.int32(j) if lower else best[x]
        for x in range(m):
            runner[x] = _F(np.inf)
        for j in range(n):
            c = cost[j]
            for x in range(m):
                step = np.int32(j) - best[x]
                v = c[x] if step * step > 1 else _F(np.inf)
                runner[x] = v if v < runner[x] else runner[x]
        for x in range(m):  # the neighbours into off / var (free until the fit below)
            b = min(max(best[x], np.int32(1)), np.int32(n - 2))  # a winner at an end is rejected by the caller
            off[x] = cost[b - 1, x]
            var[x] = cost[b + 1, x]
        floor_area, eps = flt[0], flt[1]
        for x in range(m):  # the sub-pixel fit and the variance (the matcher's model): arithmetic only
            a0, am, ap = c0[x], off[x], var[x]
            curvature = am - _F(2.0) * a0 + ap
            denom = _F(2.0) * curvature if parabola else _F(2.0) * (max(am, ap) - a0)
            off[x] = min(max((am - ap) / max(denom, eps), _F(-0.5)), _F(0.5))
            q = (a0 + floor_area) / (max(curvature, _F(0.0)) + eps)
            var[x] = min(_F(_QUANTISATION_VARIANCE) + _F(0.25) * (q * q), _F(INVALID_VARIANCE))

    @_jit
    def _band(left, right, cap, prior, ok, y0, y1, radius, r, parabola, uniq, t_need, flt, disparity, valid,
              variance):
        """Output rows ``[y0, y1)`` of one grey image pair, x-Sobel prefiltered here a row at a time (clip level
        ``cap``). ``flt``: ``(area * cost floor, eps, 1 + uniqueness)``.

        The window's rows of difference planes are kept in a ring of ``2 r + 2`` slots, each row computed once when
        it enters the window: the ring (~120 kB at 640 px) stays in cache while the column sums slide down.
        """
        H, W = left.shape
        n = 2 * radius + 1
        slots = 2 * r + 2
        lrow, rrow = np.empty(W, np.float32), np.empty(W, np.float32)
        ring = np.empty((slots, n + 1, W), np.float32)
        top = _F(W - 1)
        base = np.empty(W, np.float32)
        frac = np.empty(W, np.float32)
        first = np.empty(W, np.int64)
        inside = np.empty(W, np.bool_)
        near = np.empty((n + 1, W), np.float32)
        m = W - 2 * r  # window sums are kept for x in [r, W - r), at index x - r
        cols = np.empty((n + 1, W), np.float32)
        cost = np.empty((n + 1, m), np.float32)
        tsum = cost[n]
        c0, runner = np.empty(m, np.float32), np.empty(m, np.float32)
        best = np.empty(m, np.int32)
        off, var = np.empty(m, np.float32), np.empty(m, np.float32)
        for y in range(y0, y1):
            drow, vrow, varrow = disparity[y], valid[y], variance[y]
            _clear_row(drow, vrow, varrow)
            if y < r or y >= H - r:
                continue
            if y == max(y0, r):  # the band's first row: the window's rows, then their full column sums
                for v in range(y - r, y + r + 1):
                    xsobel_row(left, v, cap, lrow)
                    xsobel_row(right, v, cap, rrow)
                    _diff_row(lrow, rrow, prior[v], ok[v], radius, ring[v % slots], base, frac, first, inside, near)
                for j in range(n + 1):
                    col, row0 = cols[j], ring[(y - r) % slots, j]
                    for x in range(W):
                        col[x] = row0[x]
                    for v in range(y - r + 1, y + r + 1):
                        plane = ring[v % slots, j]
                        for x in range(W):
                            col[x] += plane[x]
            else:  # slide down one row: one row enters, one leaves
                v = y + r
                xsobel_row(left, v, cap, lrow)
                xsobel_row(right, v, cap, rrow)
                _diff_row(lrow, rrow, prior[v], ok[v], radius, ring[v % slots], base, frac, first, inside, near)
                for j in range(n + 1):
                    col, enter, leave = cols[j], ring[v % slots, j], ring[(y - r - 1) % slots, j]
                    for x in range(W):
                        col[x] += enter[x] - leave[x]
            for j in range(n + 1):  # window sums of every plane: row sums of the column sums
                _window_sums(cols[j], r, cost[j])
            _decide_row(cost, n, parabola, flt, c0, best, runner, off, var)
            prow, okrow = prior[y, r:r + m], ok[y, r:r + m]
            dout, vout, varout = drow[r:r + m], vrow[r:r + m], varrow[r:r + m]
            ratio = flt[2] if uniq else _F(0.0)  # runner < 0 never holds: the check is off
            for x in range(m):  # the checks and the stores
                p = prow[x]
                xf = _F(x + r)
                b = best[x]
                keep = okrow[x] & np.isfinite(p) & (xf - p - _F(radius) >= _F(0.0)) & (xf - p + _F(radius) <= top)
                keep = keep & (tsum[x] >= t_need) & (b > 0) & (b < n - 1) & (runner[x] >= ratio * c0[x])
                dout[x] = (p + _F(b - radius) + off[x]) if keep else _F(0.0)
                vout[x] = keep
                varout[x] = var[x] if keep else _F(INVALID_VARIANCE)

    @_jit
    def _fronto_band(left, right, cap, prior, ok, y0, y1, radius, r, parabola, uniq, t_need, flt, disparity, valid,
                     variance):
        """Output rows ``[y0, y1)`` of the ``window="fronto"`` search: the matcher's fronto-parallel window costs at
        the integer disparities ``round(prior) + k``, ``|k| <= radius``.

        The band's rows are x-Sobel prefiltered once (with the window's ``r`` rows above and below). Per output row,
        the pixels that need disparity ``D`` form runs along the row (a pixel needs the ``2 radius + 1`` values
        around its rounded prior; runs of one ``D`` less than a window apart are merged). Each run's column sums of
        ``|L' - R'(x - D)|`` over the run and its window margins, and their sums along the row, are loops without
        gathers (SIMD code) into the row's plane of ``D``; each segment of one centre then copies its candidates
        from the planes.
        Every inner loop runs over slices from index 0 (an index that might be negative keeps numba's
        wrap-around check in the loop, and the loop scalar).
        """
        H, W = left.shape
        n = 2 * radius + 1
        lo_row, hi_row = max(y0 - r, 0), min(y1 + r, H)
        lp = np.empty((hi_row - lo_row, W), np.float32)
        rp = np.empty((hi_row - lo_row, W), np.float32)
        for v in range(lo_row, hi_row):
            xsobel_row(left, v, cap, lp[v - lo_row])
            xsobel_row(right, v, cap, rp[v - lo_row])
        m = W - 2 * r  # pixels x in [r, W - r), at index x - r
        centre = np.empty(m, np.int64)
        use = np.empty(m, np.bool_)
        cost = np.empty((n, m), np.float32)
        tcol = np.empty(W, np.float32)
        tsum = np.empty(m, np.float32)
        col = np.empty(W, np.float32)
        planes = np.empty((4 * n, m), np.float32)  # the row's window costs per disparity (grown when needed)
        run_d = np.empty(n * m, np.int64)
        run_a = np.empty(n * m, np.int64)
        run_b = np.empty(n * m, np.int64)
        seg_a, seg_b = np.empty(m, np.int64), np.empty(m, np.int64)  # the row's segments of one centre
        c0, runner = np.empty(m, np.float32), np.empty(m, np.float32)
        best = np.empty(m, np.int32)
        off, var = np.empty(m, np.float32), np.empty(m, np.float32)
        big = _F(2 * W)
        lowest, highest = np.int64(r - W), np.int64(W)  # a centre the checks below can pass lies within these
        for y in range(y0, y1):
            drow, vrow, varrow = disparity[y], valid[y], variance[y]
            _clear_row(drow, vrow, varrow)
            if y < r or y >= H - r:
                continue
            # the band centres, and the pixels searched: every candidate's window inside the right image
            prow, okrow = prior[y, r:r + m], ok[y, r:r + m]
            for i in range(m):
                p = prow[i]
                good = okrow[i] & (abs(p) < big)  # (False for NaN)
                c = np.int64(np.rint(p if good else _F(0.0)))
                good = good & (i - (c + radius) >= 0) & (i + 2 * r - (c - radius) <= W - 1)
                centre[i] = c if good else np.int64(0)
                use[i] = good
            d_lo, d_hi = highest, lowest
            for i in range(m):
                d_lo = min(d_lo, centre[i] if use[i] else highest)
                d_hi = max(d_hi, centre[i] if use[i] else lowest)
            if d_hi < d_lo:
                continue
            d_lo, d_hi = d_lo - radius, d_hi + radius
            span = d_hi - d_lo + 1
            if span > planes.shape[0]:
                planes = np.empty((span, m), np.float32)
            # the runs, one scan along the row over segments of one centre: per disparity its open run (-1: none)
            open_a = np.full(span, -1, np.int64)
            open_b = np.empty(span, np.int64)
            runs = segments = 0
            i = 0
            while i < m:
                if not use[i]:
                    i += 1
                    continue
                c, a = centre[i], i
                while i + 1 < m and use[i + 1] and centre[i + 1] == c:
                    i += 1
                seg_a[segments], seg_b[segments] = a, i
                segments += 1
                for s in range(c - radius - d_lo, c + radius - d_lo + 1):
                    if open_a[s] >= 0 and a - open_b[s] <= 2 * r + 1:
                        open_b[s] = i
                        continue
                    if open_a[s] >= 0:
                        run_d[runs], run_a[runs], run_b[runs] = s, open_a[s], open_b[s]
                        runs += 1
                    open_a[s], open_b[s] = a, i
                i += 1
            for s in range(span):
                if open_a[s] >= 0:
                    run_d[runs], run_a[runs], run_b[runs] = s, open_a[s], open_b[s]
                    runs += 1
            # each run's window costs: pixel index i (x = i + r) needs columns x - r .. x + r, i.e. i .. i + 2 r
            for q in range(runs):
                s, a, b = run_d[q], run_a[q], run_b[q]
                D = s + d_lo
                length, k = b - a + 1, b - a + 1 + 2 * r
                for j in range(k):
                    col[j] = _F(0.0)
                for v in range(y - r, y + r + 1):
                    lrow = lp[v - lo_row, a:a + k]
                    rrow = rp[v - lo_row, a - D:a - D + k]
                    for j in range(k):
                        col[j] += abs(lrow[j] - rrow[j])
                _window_sums(col, r, planes[s, a:a + length])
            # each segment's candidates: slices of the planes (pixels not searched get zeros, masked below)
            for k in range(n):
                ck = cost[k]
                for i in range(m):
                    ck[i] = _F(0.0)
            for g in range(segments):
                a, b = seg_a[g], seg_b[g]
                first = centre[a] - radius - d_lo
                for k in range(n):
                    src, dst = planes[first + k, a:b + 1], cost[k, a:b + 1]
                    for j in range(b - a + 1):
                        dst[j] = src[j]
            # the texture measure: the window sum of |L'|
            for x in range(W):
                tcol[x] = _F(0.0)
            for v in range(y - r, y + r + 1):
                lrow = lp[v - lo_row]
                for x in range(W):
                    tcol[x] += abs(lrow[x])
            _window_sums(tcol, r, tsum)
            _decide_row(cost, n, parabola, flt, c0, best, runner, off, var)
            ratio = flt[2] if uniq else _F(0.0)
            dout, vout, varout = drow[r:r + m], vrow[r:r + m], varrow[r:r + m]
            for i in range(m):
                b = best[i]
                keep = use[i] & (tsum[i] >= t_need) & (b > 0) & (b < n - 1) & (runner[i] >= ratio * c0[i])
                dout[i] = (_F(centre[i] + b - radius) + off[i]) if keep else _F(0.0)
                vout[i] = keep
                varout[i] = var[i] if keep else _F(INVALID_VARIANCE)


def match_residual(left: torch.Tensor, right: torch.Tensor, prior: torch.Tensor, ok: torch.Tensor, radius: int,
                   block: int, parabola: bool, uniqueness: float, texture: float, cost_floor: float,
                   prefilter_cap: float, threads: int | None = None, window: str = "fronto"
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The compiled residual search on grey float32 CPU images ``(B, 1, H, W)`` (prefiltered inside the kernel: a
    torch pass over the images would wake torch's OpenMP threads to spin beside it); ``(disparity, valid,
    variance)`` as the torch path returns them for the prefiltered images, for either ``window``."""
    b, _, h, w = left.shape
    kernel = _fronto_band if window == "fronto" else _band
    threads = thread_count(threads)
    ln, rn = left[:, 0].contiguous().numpy(), right[:, 0].contiguous().numpy()
    cap = np.float32(prefilter_cap)
    prn, okn = prior[:, 0].contiguous().numpy(), ok[:, 0].contiguous().numpy()
    disparity = np.empty((b, h, w), np.float32)
    valid = np.empty((b, h, w), np.bool_)
    variance = np.empty((b, h, w), np.float32)
    area = float(block * block)
    eps = torch.finfo(torch.float32).eps * 16 * area
    flt = np.array([cost_floor * area, eps, 1 + uniqueness], dtype=np.float32)
    # the texture threshold on the window sum, as the torch path compares it (float32)
    t_need = np.float32(np.float32(texture * area))
    tasks = [(i, y0, y1) for i in range(b) for y0, y1 in _bands(h, -(-h // _BAND_ROWS))]

    def task(t: tuple[int, int, int]) -> None:
        i, y0, y1 = t
        kernel(ln[i], rn[i], cap, prn[i], okn[i], y0, y1, radius, block // 2, parabola, uniqueness > 0, t_need, flt,
               disparity[i], valid[i], variance[i])

    Workers(threads).map(task, tasks)
    return (torch.from_numpy(disparity).unsqueeze(1), torch.from_numpy(valid).unsqueeze(1),
            torch.from_numpy(variance).unsqueeze(1))
