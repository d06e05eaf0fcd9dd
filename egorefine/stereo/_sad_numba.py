"""CPU inference path of the default matcher (SAD of the x-Sobel prefiltered images, box aggregation)
compiled with numba.

The exact integer algorithm of :mod:`egorefine.stereo.fast`, one image row at a time: the
window's column sums of ``|L - R_d|`` are kept per disparity and slid down the rows (one row
enters, one leaves), the box sums of a row are built from them, and the winner, its sub-pixel
neighbours, the right view's minimum (left-right check), the runner-up (uniqueness check) and
the texture sum are read while the row is in cache. In eager torch the same work is about six
operator launches per disparity plane and band of rows, and the dispatch, not the arithmetic,
sets the time; here every loop runs over a contiguous row of one disparity plane, so LLVM
vectorises it in int16 lanes.

Integer costs are exact, so every decision (winner, ties, the checks) equals the torch integer
path's; the sub-pixel fit and the variance repeat ``fast._tail``'s float32 operations in its
order, so the outputs are equal (a test compares them). Bands of rows run as nogil kernels on a
thread pool (:class:`egorefine.core._jit.Workers`); the output does not depend on the number of
threads. Memory: a few rows of ``D x W`` int16 per thread, whatever the image size.
The x-Sobel prefilter and the quantised, padded images the kernels read are built compiled too
(:func:`_quantised`, the same float32 operations as ``fast._quantise``): torch passes over the images
would wake torch's OpenMP threads, which then spin beside the kernels.

``AVAILABLE`` is False when numba cannot be imported; callers then use the torch path.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core._jit import AVAILABLE, Workers, thread_count
from ..core._jit import bands as _bands
from ..core._jit import jit as _jit
from .fast import _INVALID, _QUANTISATION_VARIANCE, INVALID_VARIANCE

__all__ = ["AVAILABLE", "match_sad_compiled", "match_sad_windows", "xsobel_row"]

# rows per task: enough that a band's start-up (the window's first 2r + 1 rows) is small beside it,
# few enough that two threads stay busy to the end
_MIN_BAND_ROWS = 16


if AVAILABLE:

    @_jit(inline="always")
    def xsobel_row(img, v, cap, out):
        """Row ``v`` of :func:`egorefine.stereo.cost.prefilter_xsobel` of ``img`` (replicated borders, clipped to
        ``[-cap, cap]``) into ``out``, with that function's float32 operations in its order."""
        H, W = img.shape
        a, b, c = img[max(v - 1, 0)], img[v], img[min(v + 1, H - 1)]
        two = np.float32(2.0)
        # the interior as a loop over slices from 0, without index clamps (SIMD code), then the two borders
        inner = max(W - 2, 0)
        a0, a2, b0, b2, c0, c2, o = a[:inner], a[2:], b[:inner], b[2:], c[:inner], c[2:], out[1:]
        for j in range(inner):
            g = ((a2[j] - a0[j]) + two * (b2[j] - b0[j])) + (c2[j] - c0[j])
            o[j] = min(max(g, -cap), cap)
        for x in (0, W - 1):
            xl, xr = max(x - 1, 0), min(x + 1, W - 1)
            g = ((a[xr] - a[xl]) + two * (b[xr] - b[xl])) + (c[xr] - c[xl])
            out[x] = min(max(g, -cap), cap)

    @_jit
    def _quantise_rows(grey, cap, unit, c, top, left, y0, y1, out):
        """Rows ``y0:y1`` of :func:`egorefine.stereo.fast._quantise`'s padded int16 image (replicated borders:
        ``top`` rows above the image, ``left`` columns left of it) into ``out[0 : y1 - y0]``: ``round(unit * g) + c``
        clipped to ``[0, 2c]``, ``g`` the clipped x-Sobel response and ``unit = 255 * scale`` (float32 operations)."""
        H, W = grey.shape
        row = np.empty(W, np.float32)
        limit = np.float32(c)
        for yp in range(y0, y1):
            xsobel_row(grey, min(max(yp - top, 0), H - 1), cap, row)
            q = out[yp - y0]
            inner = q[left: left + W]
            for x in range(W):
                v = np.rint(row[x] * unit)
                inner[x] = np.int16(min(max(v, -limit), limit) + limit)
            # the replicated border columns (a loop without index clamps vectorises)
            first, last, tail = q[left], q[left + W - 1], q[left + W:]
            for xp in range(left):
                q[xp] = first
            for xp in range(tail.shape[0]):
                tail[xp] = last

    @_jit(inline="always")
    def _absdiff(a, b):
        return max(a, b) - min(a, b)  # |a - b| as max - min: LLVM keeps it in int16 lanes (abs it would widen)

    @_jit(inline="always")
    def _window_sums(col, pairs, r, out):
        """``out[x] = sum(col[x : x + 2r + 1])``: sums of column pairs (``pairs``: scratch), added to the first column
        four pairs per pass (each pass over a row costs a load and a store per element; the adds are cheap)."""
        for u in range(col.shape[0] - 1):
            pairs[u] = col[u] + col[u + 1]
        i = 0
        if r >= 4:  # the first column and the first four pairs in one pass
            p0, p1, p2, p3 = pairs[1:], pairs[3:], pairs[5:], pairs[7:]
            for x in range(out.shape[0]):
                out[x] = col[x] + ((p0[x] + p1[x]) + (p2[x] + p3[x]))
            i = 4
        else:
            for x in range(out.shape[0]):
                out[x] = col[x]
        while i + 4 <= r:
            p0, p1, p2, p3 = pairs[1 + 2 * i:], pairs[3 + 2 * i:], pairs[5 + 2 * i:], pairs[7 + 2 * i:]
            for x in range(out.shape[0]):
                out[x] += (p0[x] + p1[x]) + (p2[x] + p3[x])
            i += 4
        while i < r:
            p0 = pairs[1 + 2 * i:]
            for x in range(out.shape[0]):
                out[x] += p0[x]
            i += 1

    @_jit(error_model="numpy")
    def _band(lp, rp, y0, y1, max_d, num, r, guard, uniq, t_need, c_level, flt, min_d_pos, subpixel, parabola,
              disparity, valid, variance, x0=0):
        """Match output rows ``[y0, y1)`` of one image pair.

        ``lp`` ``(H + 2r, W + 2r)`` and ``rp`` ``(H + 2r, W + 2r + max_d)`` are the quantised prefiltered images,
        replicate-padded (the right one by ``r + max_d`` columns on the left), so that the window of output pixel
        ``(y, x)`` covers padded rows ``y .. y + 2r`` and left columns ``u = x .. x + 2r``, and candidate ``j``
        (disparity ``max_d - 1 - j``) reads right column ``u + 1 + j``. ``flt`` holds the float32 constants
        ``(unit, area * cost_floor, eps, 1 + uniqueness_ratio)``; ``uniq`` enables the uniqueness check,
        ``guard`` is the left-right tolerance (-1: no left-right check). ``x0`` is the image column of output
        column 0 when the arrays are a window of columns (:func:`match_sad_windows`): candidates with
        ``x0 + x < d`` are out of the right view, and the left-right check sees the window's columns only.

        Per row, candidate by candidate: the window's column sums slide down one row, their box sums are stored
        as the candidate's cost row, and one pass over that row updates the running winner and runner-up; after
        the candidates, the winner's neighbours are read back from the stored rows and the checks and the float
        tail run as loops over the row. Every loop is branch-free over a contiguous row (selects, no
        short-circuit conditions, no division checks: ``error_model="numpy"``, the divisors are clamped above
        zero), so LLVM vectorises each one.
        """
        wp = lp.shape[1]
        w = wp - 2 * r
        k = 2 * r + 1
        big = np.int16(_INVALID)
        col = np.zeros((num, wp), np.int16)  # window column sums per candidate
        tcol = np.zeros(wp, np.int16)  # window column sums of |prefiltered| (texture)
        pairs = np.empty(wp, np.int16)
        # the box sums of a row per candidate, with a row of _INVALID above and below (candidates -1 and num) and a
        # column of _INVALID either side (columns -1 and w): the winner's neighbours are then plain reads
        costp = np.full((num + 2, w + 2), big, np.int16)
        cost = costp[1: num + 1]
        costf = costp.reshape(-1)
        stride = w + 2
        U = np.uint64
        last = np.int16(num - 1)
        no_end_check, no_lr, no_uniq = not min_d_pos, guard < 0, not uniq
        best = np.empty(w, np.int16)
        jbest = np.empty(w, np.int16)
        second = np.empty(w, np.int16)
        lowest = np.empty(w, np.int16)  # the lowest cost of the candidates up to j - 2 (best, two steps late)
        cps = np.empty(w, np.int16)
        cms = np.empty(w, np.int16)
        near_l = np.empty(w, np.int16)
        near_r = np.empty(w, np.int16)
        rmin_p = np.empty(w + max_d, np.int16)  # the right view's minimum at xr, stored at xr + max_d
        rmin = rmin_p[max_d:]
        rm_at = np.empty(w, np.int16)
        tsum = np.empty(w, np.int16)
        unit, floor_area, eps, ratio = flt[0], flt[1], flt[2], flt[3]
        zero, half, two, quarter = np.float32(0.0), np.float32(0.5), np.float32(2.0), np.float32(0.25)
        one, qvar, bigvar = np.float32(1.0), np.float32(_QUANTISATION_VARIANCE), np.float32(INVALID_VARIANCE)
        top = np.float32(max_d - 1)
        for y in range(y0, y1):
            first = y == y0
            ln, rn, lo, ro = lp[y + 2 * r], rp[y + 2 * r], lp[max(y - 1, 0)], rp[max(y - 1, 0)]
            for x in range(w):
                best[x] = big
                jbest[x] = 0
                second[x] = big
                lowest[x] = big
            for x in range(w + max_d):
                rmin_p[x] = big
            for j in range(num):
                # slide the window's column sums to row y (all 2r + 1 rows at the band's first row)
                cj = col[j]
                if first:
                    for t in range(k):
                        lrow, rj = lp[y + t], rp[y + t, 1 + j: 1 + j + wp]
                        for u in range(wp):
                            cj[u] += _absdiff(lrow[u], rj[u])
                elif j % 2 == 0:
                    # two candidates per pass, the left rows read once (more streams: LLVM gives up on four);
                    # slices, not offset indices: LLVM vectorises a loop over slices ~10x better here
                    rnj, roj = rn[1 + j: 1 + j + wp], ro[1 + j: 1 + j + wp]
                    if j + 1 < num:
                        cj1, rnk, rok = col[j + 1], rn[2 + j: 2 + j + wp], ro[2 + j: 2 + j + wp]
                        for u in range(wp):
                            a, b = ln[u], lo[u]
                            cj[u] += _absdiff(a, rnj[u]) - _absdiff(b, roj[u])
                            cj1[u] += _absdiff(a, rnk[u]) - _absdiff(b, rok[u])
                    else:
                        for u in range(wp):
                            cj[u] += _absdiff(ln[u], rnj[u]) - _absdiff(lo[u], roj[u])
                # box sums; candidates out of the right view (x < d) cost _INVALID
                out = cost[j, 1: w + 1]
                _window_sums(cj, pairs, r, out)
                for x in range(min(max(max_d - 1 - j - x0, 0), w)):
                    out[x] = big
                # the running winner (the first lowest: a strict <) and the runner-up beyond +-1 candidate of it:
                # when the winner moves to j, the lowest cost up to j - 2; then every candidate from j + 2 on
                jj, jm2 = np.int16(j), np.int16(j - 2)
                for x in range(w):
                    c, b, jb, s = out[x], best[x], jbest[x], second[x]
                    low = lowest[x]
                    moved = c < b
                    s_far = min(s, c) if jb <= jm2 else s
                    lowest[x] = b  # read at candidate j + 1: the lowest up to j - 1
                    second[x] = low if moved else s_far
                    jbest[x] = jj if moved else jb
                    best[x] = min(b, c)
                if guard >= 0:
                    # the right view's minimum at xr = x - d over d: cost_right(xr, d) = cost_left(xr + d, d)
                    d = max_d - 1 - j
                    if d < w:
                        rm, cd = rmin[: w - d], out[d:]
                        for x in range(w - d):
                            rm[x] = min(rm[x], cd[x])
            # the winner's neighbours in candidate (sub-pixel fit) and on the diagonal through its right-view pixel
            # (left-right tolerance 1): reversed order, so j - 1 is d + 1
            # (flat, unsigned indices: no wrap-around code for negative indices)
            for x in range(w):
                at = U(np.int64(jbest[x]) * stride + x)  # costp[jbest, x]
                cps[x] = costf[at + U(1)]
                cms[x] = costf[at + U(2 * stride + 1)]
                near_l[x] = costf[at + U(2 * stride)]
                near_r[x] = costf[at + U(2)]
                rm_at[x] = rmin_p[U(x + 1) + U(jbest[x])]  # the right view's minimum at x - d
            if guard > 1:
                # a wider tolerance: the lowest cost on the winner's right-view pixel within guard candidates
                for x in range(w):
                    jb = np.int64(jbest[x])
                    near = best[x]
                    for dj in range(-guard, guard + 1):
                        jn, xn = jb + dj, x - dj
                        if dj != 0 and 0 <= jn < num and 0 <= xn < w:
                            near = min(near, cost[jn, xn + 1])
                    near_l[x] = near
                    near_r[x] = big
            if first:
                for t in range(k):
                    lrow = lp[y + t]
                    for u in range(wp):
                        tcol[u] += _absdiff(lrow[u], c_level)
            else:
                for u in range(wp):
                    tcol[u] += _absdiff(ln[u], c_level) - _absdiff(lo[u], c_level)
            _window_sums(tcol, pairs, r, tsum)
            vrow = valid[y]
            # the checks, branch-free (SIMD code): a disabled check passes; the right view's minimum at x - d must
            # be reached within guard candidates of d
            nl, nr = (near_l, near_r) if guard > 0 else (best, best)
            for x in range(w):
                b0 = best[x]
                near = min(b0, min(nl[x], nr[x]))
                ok = (max(b0, cps[x]) < big) & (tsum[x] >= t_need)
                ok &= (jbest[x] < last) | no_end_check
                ok &= (near <= rm_at[x]) | no_lr
                ok &= (np.float32(second[x]) > np.float32(b0) * ratio) | no_uniq
                vrow[x] = ok
            # fast._tail: sub-pixel fit and variance in float32, in its order of operations
            drow, varrow = disparity[y], variance[y]
            for x in range(w):
                b0, cp, cm = best[x], cps[x], cms[x]
                inner = max(max(b0, cp), cm) < big
                fp, fm, c0 = np.float32(cp) * unit, np.float32(cm) * unit, np.float32(b0) * unit
                fin = one if inner else zero
                keep = one if vrow[x] else zero
                curvature = (fm - two * c0) + fp
                denom = two * curvature if parabola else two * (max(fm, fp) - c0)
                dsp = top - np.float32(jbest[x])
                if subpixel:
                    dsp += min(max((fm - fp) / max(denom, eps), -half), half) * fin
                drow[x] = dsp * keep
                spread = (c0 + floor_area) / (max(curvature, zero) + eps)
                var = spread * spread * quarter
                var = (min(var + qvar, bigvar) - one) * fin + one
                varrow[x] = var * keep + (one - keep) * bigvar


    @_jit
    def _match_rows(grey_l, grey_r, y0, y1, cap, unit, c, max_d, num, r, guard, uniq, t_need, c_level, flt,
                    min_d_pos, subpixel, parabola, disparity, valid, variance):
        """Output rows ``[y0, y1)`` of one grey float32 pair ``(H, W)``: the quantised prefiltered rows the band needs
        (:func:`_quantise_rows`, its own copy: bands share no buffer), then :func:`_band` into the rows
        ``y0:y1`` of ``disparity``, ``valid``, ``variance``. One call per band: one hand-off to a worker thread."""
        W = grey_l.shape[1]
        rows = y1 - y0 + 2 * r
        lq = np.empty((rows, W + 2 * r), np.int16)
        rq = np.empty((rows, W + 2 * r + max_d), np.int16)
        _quantise_rows(grey_l, cap, unit, c, r, r, y0, y0 + rows, lq)
        _quantise_rows(grey_r, cap, unit, c, r, r + max_d, y0, y0 + rows, rq)
        _band(lq, rq, 0, y1 - y0, max_d, num, r, guard, uniq, t_need, c_level, flt, min_d_pos, subpixel, parabola,
              disparity[y0:y1], valid[y0:y1], variance[y0:y1])


def _run(threads: int, fn, items: list) -> None:
    """``fn(item)`` for every item, shared by the calling thread and the pool (:meth:`Workers.map`)."""
    Workers(threads).map(fn, items)


def match_sad_compiled(left: torch.Tensor, right: torch.Tensor, max_d: int, min_d: int, block: int, cap: float,
                       scale: int, opts: dict, threads: int | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`egorefine.stereo.fast.match_sad_int` for float32 CPU grey pairs, compiled; the same outputs.

    Args:
        left, right: ``(B, 1, H, W)`` float32 CPU grey images (no gradient needed).
        max_d, min_d, block, cap, scale, opts: as :func:`~egorefine.stereo.fast.match_sad_int`.
        threads: worker threads (None: ``torch.get_num_threads()``).

    Returns:
        ``(disparity, valid, variance)`` each ``(B, 1, H, W)`` (0 and ``INVALID_VARIANCE`` where invalid).
    """
    b, _, h, w = left.shape
    r, num = block // 2, max_d - min_d
    threads = thread_count(threads)
    guard, uniq, t_need, c_level, flt = _settings(max_d, min_d, block, cap, scale, opts)
    grey_l, grey_r = (g.detach()[:, 0].contiguous().numpy() for g in (left, right))
    disparity = np.empty((b, h, w), np.float32)
    valid = np.empty((b, h, w), np.bool_)
    variance = np.empty((b, h, w), np.float32)
    parts = max(1, min(threads * 2, h // _MIN_BAND_ROWS))
    tasks = [(i, y0, y1) for i in range(b) for y0, y1 in _bands(h, parts)]
    quant = (np.float32(cap), np.float32(255.0 * scale), round(255.0 * scale * cap))

    def task(t: tuple[int, int, int]) -> None:
        i, y0, y1 = t
        _match_rows(grey_l[i], grey_r[i], y0, y1, *quant, max_d, num, r, guard, uniq, t_need, c_level, flt,
                    min_d > 0, bool(opts["subpixel"]), opts["subpixel_fit"] == "parabola", disparity[i], valid[i],
                    variance[i])

    _run(threads, task, tasks)
    return (torch.from_numpy(disparity).unsqueeze(1), torch.from_numpy(valid).unsqueeze(1),
            torch.from_numpy(variance).unsqueeze(1))


def _quantised(grey: torch.Tensor, cap: float, scale: int, r: int, left: int, threads: int | None = None
               ) -> np.ndarray:
    """:func:`egorefine.stereo.fast._quantise`'s padded int16 images ``(B, H + 2r, left + W + r)`` of grey float32
    CPU images ``(B, 1, H, W)``, compiled (a torch pass over the images would wake torch's OpenMP threads to spin
    beside the matcher's kernels)."""
    b, _, h, w = grey.shape
    g = grey.detach()[:, 0].contiguous().numpy()
    out = np.empty((b, h + 2 * r, left + w + r), np.int16)
    args = (np.float32(cap), np.float32(255.0 * scale), round(255.0 * scale * cap), r, left)
    threads = thread_count(threads)
    _run(threads, lambda job: _quantise_rows(g[job[0]], *args, *job[1], out[job[0], job[1][0]:job[1][1]]),
         [(i, rows) for i in range(b) for rows in _bands(h + 2 * r, threads)])
    return out


def _setup(left: torch.Tensor, right: torch.Tensor, max_d: int, min_d: int, block: int, cap: float, scale: int,
           opts: dict) -> tuple:
    """Padded quantised images ``lq``, ``rq`` (see :func:`_band`) and the kernel's settings
    ``(guard, uniq, t_need, c_level, flt)``."""
    r = block // 2
    lq = _quantised(left, cap, scale, r, r)
    rq = _quantised(right, cap, scale, r, r + max_d)
    return lq, rq, _settings(max_d, min_d, block, cap, scale, opts)


def _settings(max_d: int, min_d: int, block: int, cap: float, scale: int, opts: dict) -> tuple:
    """The kernel's settings ``(guard, uniq, t_need, c_level, flt)`` (see :func:`_band`)."""
    num = max_d - min_d
    area = float(block * block)
    uniq = opts["uniqueness_ratio"] > 0
    flt = np.array([1.0 / (255.0 * scale), opts["cost_floor"] * area, torch.finfo(torch.float32).eps * 16 * area,
                    1 + opts["uniqueness_ratio"]], dtype=np.float32)
    guard = min(opts["lr_threshold"], num - 1) if opts["lr_check"] else -1
    # the texture threshold on the window sum, rounded to float32 as the float path compares it, then up
    t_need = float(np.float32(opts["texture_threshold"] * area * 255.0 * scale))
    t_need = int(min(max(np.ceil(t_need), -_INVALID), _INVALID))
    c_level = np.int16(round(255.0 * scale * cap))
    return guard, uniq, t_need, c_level, flt


def match_sad_windows(left: torch.Tensor, right: torch.Tensor, boxes: list[list[tuple[int, int, int, int]]],
                      margin: int, max_d: int, min_d: int, block: int, cap: float, scale: int, opts: dict,
                      threads: int | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`match_sad_compiled` on windows of columns only: for each item ``i`` and box ``(y0, y1, x0, x1)`` in
    ``boxes[i]``, the rows ``y0:y1`` of columns ``x0 - margin : x1 + margin`` (clipped) are matched with the whole
    search range, and the box is kept. Costs, winners and every check but the left-right one equal the full
    frame's; the left-right check sees the window's columns. Outside the boxes the output is invalid.

    Returns:
        ``(disparity, valid, variance)`` each ``(B, 1, H, W)``.
    """
    b, _, h, w = left.shape
    r, num = block // 2, max_d - min_d
    threads = thread_count(threads)
    lq, rq, (guard, uniq, t_need, c_level, flt) = _setup(left, right, max_d, min_d, block, cap, scale, opts)
    disparity = np.zeros((b, h, w), np.float32)
    valid = np.zeros((b, h, w), np.bool_)
    variance = np.full((b, h, w), INVALID_VARIANCE, np.float32)
    windows, tasks = [], []
    for i, item_boxes in enumerate(boxes):
        for y0, y1, x0, x1 in item_boxes:
            wx0, wx1 = max(0, x0 - margin), min(w, x1 + margin)
            # contiguous copies of the window (padded rows y0 .. y1 + 2r): the kernel's loops vectorise on them
            lw = np.ascontiguousarray(lq[i, y0:y1 + 2 * r, wx0:wx1 + 2 * r])
            rw = np.ascontiguousarray(rq[i, y0:y1 + 2 * r, wx0:wx1 + 2 * r + max_d])
            out = tuple(np.empty((y1 - y0, wx1 - wx0), dt) for dt in (np.float32, np.bool_, np.float32))
            windows.append((i, y0, y1, x0, x1, wx0, out))
            parts = max(1, min(threads * 2, (y1 - y0) // _MIN_BAND_ROWS))
            tasks += [(lw, rw, a0, a1, wx0, out) for a0, a1 in _bands(y1 - y0, parts)]

    def task(t: tuple) -> None:
        lw, rw, a0, a1, wx0, out = t
        _band(lw, rw, a0, a1, max_d, num, r, guard, uniq, t_need, c_level, flt, min_d > 0, bool(opts["subpixel"]),
              opts["subpixel_fit"] == "parabola", *out, wx0)

    _run(threads, task, tasks)
    for i, y0, y1, x0, x1, wx0, out in windows:  # the boxes, without their margins
        for full, part in zip((disparity, valid, variance), out, strict=True):
            full[i, y0:y1, x0:x1] = part[:, x0 - wx0:x1 - wx0]
    return (torch.from_numpy(disparity).unsqueeze(1), torch.from_numpy(valid).unsqueeze(1),
            torch.from_numpy(variance).unsqueeze(1))
