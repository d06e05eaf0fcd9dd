"""CPU inference path of census + SGM matching compiled with numba (optional dependency).

The scanline recursion of SGM is sequential along each path, so the eager torch version in
:mod:`egorefine.stereo.sgm` pays about ten operator launches per scanline step. Here the
census cost volume, its box aggregation, the 4 or 8 path costs and the winner selection are
loops compiled by numba, run in nogil kernels over row or column bands from a thread pool
(not numba's ``parallel=True``, whose threading layer can clash with torch's OpenMP).

The kernels repeat the torch path's float32 operations one for one, in the same order, so
their results equal it bit for bit: census costs are integer window sums (exact in float32,
stored as int16), each recursion step is ``(C - m) + min(prev, m + P2, prev[d +- 1] + P1)`` as
in :func:`egorefine.stereo.sgm._step`, the path costs are summed in the order of
:func:`~egorefine.stereo.sgm.sgm_aggregate` (horizontal pair first, then top-down, then
bottom-up), and the selection repeats :func:`egorefine.stereo.matching._select` including its
index-in-mantissa encoding (so ties resolve the same way). Layout is ``(H, W, D)`` with the
disparity axis innermost (contiguous, so LLVM vectorises the loops over it) and reversed as in
:mod:`egorefine.stereo.cost` (index ``j`` is disparity ``max_disparity - 1 - j``).

Phases per batch item (each split over ``threads`` bands, a barrier between them):
census of both images; per row band, the cost rows and their horizontal paths (the row still
in cache) into a float32 volume; per column band, the top-down paths added to it, then the
bottom-up ones with each pixel's winner selection as soon as its sum is complete (the
right view's minimum is gathered per band on the way); per row band, the left-right check.
Diagonal paths (8 paths) cross column bands, so their vertical phase is one band.
Compiled with ``cache=True``: the first call on a machine compiles for a few seconds.

The two volumes (``H W D`` int16 costs and float32 path sums, about 6 bytes per candidate) are kept
per calling thread and reused by the next call of the same size, as OpenCV's SGBM keeps its buffer:
faulting in fresh pages for them on every call costs a sizeable share of the call (docs/decisions.md).
:func:`release_workspace` frees them.

``AVAILABLE`` is False when numba cannot be imported; callers then use the torch path.
"""

from __future__ import annotations

import threading

import numpy as np
import torch

from ..core._jit import AVAILABLE, Workers
from ..core._jit import bands as _bands
from ..core._jit import jit as _jit

__all__ = ["AVAILABLE", "census_sgm_select", "release_workspace"]

if AVAILABLE:  # numba is a dependency, but the package stays importable (torch path) without it
    from llvmlite import ir as _llvm_ir
    from numba.core import types as _types
    from numba.extending import intrinsic

# census bits per int32 word (window 7 has 48 bits: two words)
_WORD_BITS = 24
# the encoded value of an out-of-view candidate in the right-view search: INVALID_COST's float32 bits
_INVALID_CODE = int(np.array(1.0e6, dtype=np.float32).view(np.int32))


if AVAILABLE:

    @intrinsic
    def _ctpop(typingctx, x):
        """LLVM's population count (one instruction on CPUs with POPCNT / AVX-512 VPOPCNT)."""
        sig = x(x)

        def codegen(context, builder, signature, args):
            fn = builder.module.declare_intrinsic("llvm.ctpop", [args[0].type])
            return builder.call(fn, [args[0]])

        return sig, codegen

    @intrinsic
    def _float_from_bits(typingctx, x):
        """The float32 whose bit pattern is the (low 32 bits of the) integer ``x``."""
        if not isinstance(x, _types.Integer):
            return None
        sig = _types.float32(x)

        def codegen(context, builder, signature, args):
            v = args[0]
            if v.type.width != 32:
                v = builder.trunc(v, _llvm_ir.IntType(32))
            return builder.bitcast(v, _llvm_ir.FloatType())

        return sig, codegen

    @intrinsic
    def _bits_of_float(typingctx, x):
        """The int32 bit pattern of the float32 ``x``."""
        if x != _types.float32:
            return None
        sig = _types.int32(x)

        def codegen(context, builder, signature, args):
            return builder.bitcast(args[0], _llvm_ir.IntType(32))

        return sig, codegen

    @_jit
    def _census(padded, window, out):
        """Census words ``out`` ``(words, H, W)`` int32 of an image replicate-padded by ``window // 2``
        (``padded``); bit ``k`` (word ``k // 24``) as census_transform: neighbour ``k`` darker than the centre."""
        words, h, w = out.shape
        r = window // 2
        for y in range(h):
            for word in range(words):
                for x in range(w):
                    out[word, y, x] = 0
            k = 0
            for dy in range(window):
                for dx in range(window):
                    if dy == r and dx == r:
                        continue
                    word, bit = k // 24, np.int32(k % 24)
                    for x in range(w):  # branch-free, vectorised along the row
                        out[word, y, x] |= np.int32(padded[y + dy, x + dx] < padded[y + r, x + r]) << bit
                    k += 1

    @_jit
    def _raw_row(cl, cr, yy, r, max_d, num, rpad, out, colsum, sign):
        """Hamming distances ``out[x', j]`` of (clamped) image row ``yy``, padded columns ``x' in [0, W + 2r)``;
        ``colsum`` gains them and loses ``sign *`` the previous content of ``out`` (the row leaving the window).

        As cost.strip_volume: left column ``x' - r``, right column ``x' + 1 + j`` of the right row padded
        (replicated) by ``r + max_d`` on the left (``rpad``: scratch of ``W + 2r + max_d + 1``).
        """
        words, _, w = cl.shape
        wp = w + 2 * r
        for k in range(words):
            for t in range(rpad.shape[0]):
                rpad[t] = cr[k, yy, min(max(t - r - max_d, 0), w - 1)]
            last = k == words - 1
            for x in range(wp):
                lv = cl[k, yy, min(max(x - r, 0), w - 1)]
                row = out[x]
                col = colsum[x]
                if k == 0 and last:  # one word: distance, window update and store in one pass
                    for j in range(num):
                        new = np.int16(_ctpop(lv ^ rpad[x + 1 + j]))
                        col[j] += new - sign * row[j]
                        row[j] = new
                elif k == 0:
                    for j in range(num):
                        col[j] -= sign * row[j]
                        row[j] = np.int16(_ctpop(lv ^ rpad[x + 1 + j]))
                else:
                    for j in range(num):
                        new = np.int16(_ctpop(lv ^ rpad[x + 1 + j]))
                        row[j] += new
                        if last:
                            col[j] += row[j]

    @_jit(inline="always")
    def _min(a, b):
        return a if a < b else b  # torch.minimum without NaNs; a plain select LLVM vectorises

    @_jit(inline="always")
    def _step(prev, pp, c, cp, jlim, m, p1, p2, out, op):
        """One SGM step (sgm._step) from row ``pp`` of ``prev`` and row ``cp`` of the costs ``c`` into row
        ``op`` of ``out`` (2-D arrays ``(N, D)``):
        ``out[j] = (C[j] - m) + min(prev[j], m + P2, prev[j +- 1] + P1)``. Returns ``min_j out[j]``.

        ``c`` holds the integer window sums; ``C[j] = float32(c[j]) + INVALID_COST`` for ``j < jlim`` (out of
        view), exactly the float32 value cost.strip_volume computes. Path costs are >= 0, where the int32
        order of the float bits is the float order: the min is an integer reduction, which LLVM vectorises
        without fast-math (a float one it would not).
        """
        mp2 = m + p2
        num = c.shape[1]  # >= 2 (an early return for 1 here makes LLVM give up vectorising: much slower)
        big = np.float32(1.0e6)
        zero = np.float32(0.0)
        c0 = np.float32(c[cp, 0]) + (big if 0 < jlim else zero)
        v = (c0 - m) + _min(_min(prev[pp, 0], mp2), prev[pp, 1] + p1)
        out[op, 0] = v
        lo = _bits_of_float(v)
        if jlim <= 1:  # no candidate out of view in the loop below: no penalty to add
            for j in range(1, num - 1):
                best = _min(_min(prev[pp, j], mp2), _min(prev[pp, j - 1] + p1, prev[pp, j + 1] + p1))
                v = (np.float32(c[cp, j]) - m) + best
                out[op, j] = v
                lo = min(lo, _bits_of_float(v))
        else:
            for j in range(1, num - 1):
                best = _min(_min(prev[pp, j], mp2), _min(prev[pp, j - 1] + p1, prev[pp, j + 1] + p1))
                cj = np.float32(c[cp, j]) + (big if j < jlim else zero)
                v = (cj - m) + best
                out[op, j] = v
                lo = min(lo, _bits_of_float(v))
        j = num - 1
        cj = np.float32(c[cp, j]) + (big if j < jlim else zero)
        v = (cj - m) + _min(_min(prev[pp, j], mp2), prev[pp, j - 1] + p1)
        out[op, j] = v
        return _float_from_bits(min(lo, _bits_of_float(v)))

    @_jit(inline="always")
    def _step_add(prev, pp, c, cp, jlim, m, p1, p2, out, op, acc, ap):
        """_step, also adding the new path costs to row ``ap`` of ``acc`` (one pass instead of two)."""
        mp2 = m + p2
        num = c.shape[1]  # >= 2 (an early return for 1 here makes LLVM give up vectorising: much slower)
        big = np.float32(1.0e6)
        zero = np.float32(0.0)
        c0 = np.float32(c[cp, 0]) + (big if 0 < jlim else zero)
        v = (c0 - m) + _min(_min(prev[pp, 0], mp2), prev[pp, 1] + p1)
        out[op, 0] = v
        acc[ap, 0] += v
        lo = _bits_of_float(v)
        if jlim <= 1:  # no candidate out of view in the loop below: no penalty to add
            for j in range(1, num - 1):
                best = _min(_min(prev[pp, j], mp2), _min(prev[pp, j - 1] + p1, prev[pp, j + 1] + p1))
                v = (np.float32(c[cp, j]) - m) + best
                out[op, j] = v
                acc[ap, j] += v
                lo = min(lo, _bits_of_float(v))
        else:
            for j in range(1, num - 1):
                best = _min(_min(prev[pp, j], mp2), _min(prev[pp, j - 1] + p1, prev[pp, j + 1] + p1))
                cj = np.float32(c[cp, j]) + (big if j < jlim else zero)
                v = (cj - m) + best
                out[op, j] = v
                acc[ap, j] += v
                lo = min(lo, _bits_of_float(v))
        j = num - 1
        cj = np.float32(c[cp, j]) + (big if j < jlim else zero)
        v = (cj - m) + _min(_min(prev[pp, j], mp2), prev[pp, j - 1] + p1)
        out[op, j] = v
        acc[ap, j] += v
        return _float_from_bits(min(lo, _bits_of_float(v)))

    @_jit(inline="always")
    def _start(c, cp, jlim, out, op):
        """A path's first pixel: ``out = C`` (see _step); returns its min."""
        for j in range(c.shape[1]):
            out[op, j] = np.float32(c[cp, j]) + (np.float32(1.0e6) if j < jlim else np.float32(0.0))
        lo = _bits_of_float(out[op, 0])
        for j in range(1, c.shape[1]):
            lo = min(lo, _bits_of_float(out[op, j]))
        return _float_from_bits(lo)

    @_jit
    def _horizontal_row(c2, max_d, p1, p2, y, w, h2, buf):
        """``h2[y]`` = LR + RL (left-to-right plus right-to-left path costs, as sgm_aggregate adds them) of
        row ``y`` of the integer costs ``c2`` ``(H * W, D)`` (see _step). A path starts with L = C."""
        base = y * w
        m = _start(c2, base, max_d - 1, h2, base)
        for x in range(1, w):  # left to right, straight into h2
            m = _step(h2, base + x - 1, c2, base + x, max_d - 1 - x, m, p1, p2, h2, base + x)
        # right to left in a pair of row buffers, added to h2 (LR + RL) in the same pass
        m = _start(c2, base + w - 1, max_d - w, buf, 0)
        p = base + w - 1
        for j in range(c2.shape[1]):
            h2[p, j] += buf[0, j]
        k = 0
        for x in range(w - 2, -1, -1):
            p = base + x
            m = _step_add(buf, k, c2, p, max_d - 1 - x, m, p1, p2, buf, 1 - k, h2, p)
            k = 1 - k

    @_jit
    def _rows_pass(cl, cr, r, max_d, num, y0, y1, p1, p2, cost, horiz):
        """Rows ``[y0, y1)``: box sums (block ``2r+1``) of the census Hamming distances into ``cost``
        ``(H, W, D)`` (int16, or int32 for large blocks; the INVALID_COST of out-of-view candidates is added
        where they are read, see _step), as cost.strip_volume; then the horizontal path costs of each row
        (still in cache) into ``horiz``."""
        _, h, w = cl.shape
        k = 2 * r + 1
        wp = w + 2 * r
        ring = np.empty((k, wp, num), dtype=np.int16)
        rpad = np.empty(wp + max_d + 1, dtype=np.int32)
        colsum = np.zeros((wp, num), dtype=cost.dtype)
        acc = np.empty(num, dtype=cost.dtype)
        c2 = cost.reshape(h * w, num)
        h2 = horiz.reshape(h * w, num)
        buf = np.empty((2, num), dtype=np.float32)
        for i in range(k):  # rows y0 - r .. y0 + r (clamped)
            yy = min(max(y0 - r + i, 0), h - 1)
            _raw_row(cl, cr, yy, r, max_d, num, rpad, ring[i], colsum, 0)
        slot = 0  # ring slot of row y - r
        for y in range(y0, y1):
            if y > y0:  # slide the window: drop row y - r - 1, add row y + r
                _raw_row(cl, cr, min(max(y + r, 0), h - 1), r, max_d, num, rpad, ring[slot], colsum, 1)
                slot = (slot + 1) % k
            for j in range(num):
                acc[j] = 0
            for i in range(k - 1):
                for j in range(num):
                    acc[j] += colsum[i, j]
            for x in range(w):
                for j in range(num):
                    acc[j] += colsum[x + k - 1, j]
                p = y * w + x
                for j in range(num):
                    c2[p, j] = acc[j]
                for j in range(num):
                    acc[j] -= colsum[x, j]
            _horizontal_row(c2, max_d, p1, p2, y, w, h2, buf)

    @_jit
    def _select_pixel(lo, codes, codef, num, max_d, bits, subpixel, parabola, uniqueness, floor, eps,
                      min_disparity_positive):
        """matching._select for one pixel from its encoded costs ``codes`` (int32; ``codef``: the same as float32)
        and their minimum ``lo``.

        Returns ``(j, disparity, ok, variance)``; ``ok`` without the left-right check.
        """
        j = lo & ((1 << bits) - 1)
        jm = max(j - 1, 0)
        jp = min(j + 1, num - 1)
        c_best = codef[j]
        c_plus = codef[jm]  # reversed order: j - 1 is d + 1
        c_minus = codef[jp]
        half_invalid = np.float32(5.0e5)
        interior = j > 0 and j < num - 1 and c_plus < half_invalid and c_minus < half_invalid
        curvature = (c_minus - np.float32(2.0) * c_best) + c_plus
        if parabola:
            denom = np.float32(2.0) * curvature
        else:
            denom = np.float32(2.0) * (max(c_minus, c_plus) - c_best)
        offset = np.float32(0.0)
        if interior:
            offset = min(max((c_minus - c_plus) / max(denom, eps), np.float32(-0.5)), np.float32(0.5))
        d_int = np.float32(max_d - 1 - j)
        disparity = d_int + offset if subpixel else d_int
        ok = c_best < half_invalid and j > 0 and c_plus < half_invalid
        if min_disparity_positive:
            ok = ok and j < num - 1
        if uniqueness > 0 and ok:
            # best of the rest once the winner and its neighbours are knocked out (+inf when none is left)
            inf = np.int32(0x7F800000)
            second = inf
            for i in range(num):  # full length, a select per entry: vectorised like the loops that wrote codes
                second = min(second, inf if jm <= i and i <= jp else codes[i])
            # float order = int order of the bits for non-negative floats (a round trip through memory
            # here cost more than the whole check)
            ok = second > _bits_of_float(c_best * np.float32(1.0 + uniqueness))
        kd = max(curvature, np.float32(0.0))
        q = (c_best + floor) / (kd + eps)
        variance = np.float32(1.0 / 12.0) + np.float32(0.25) * (q * q)
        variance = min(variance, np.float32(1.0e4)) if interior else np.float32(1.0)
        return j, disparity, ok, variance

    @_jit
    def _vertical_select(cost, p1, p2, x0, x1, diagonals, paths, horiz, store, max_d, bits, subpixel, parabola,
                         uniqueness, floor, eps, min_disparity_positive, lr_check, max_raw, jbest, disparity, ok,
                         variance, rmin):
        """Vertical (and, with ``diagonals``, diagonal) path costs of columns ``[x0, x1)`` added to the horizontal
        ones ``horiz`` in sgm_aggregate's order (top-down paths into ``horiz``), then the selection of each pixel.

        ``store``: write the aggregated costs into ``horiz`` (else it keeps a partial sum).
        ``max_raw``: a winner whose own (un-aggregated) window cost exceeds it is not ok (negative: no such check).
        Per pixel: ``jbest``, ``disparity``, ``ok`` (checks but the left-right one), ``variance`` ``(H, W)``;
        ``rmin`` ``(H, max_d + W)``: this band's part of the right view's encoded minimum at column
        ``max_d + xr`` (min over bands gives it; the first ``max_d`` columns are spare).
        A diagonal predecessor outside ``[x0, x1)`` starts the path, so diagonals need the full width.
        """
        h, w, num = cost.shape
        c2 = cost.reshape(h * w, num)
        h2 = horiz.reshape(h * w, num)
        n = x1 - x0
        ns = 3 if diagonals else 1  # column shifts 0, +1, -1 per row (sgm_aggregate's order)
        # previous / current row of each path, (ns * (n + 2), D): one zero column (a path start, L = C)
        # on either side of each path's row
        prev = np.zeros((ns * (n + 2), num), dtype=np.float32)
        cur = np.zeros((ns * (n + 2), num), dtype=np.float32)
        mins = np.zeros(ns * (n + 2), dtype=np.float32)
        cmins = np.zeros(ns * (n + 2), dtype=np.float32)
        codes = np.empty(num, dtype=np.int32)
        codef = codes.view(np.float32)
        high = np.int32(-(1 << bits))
        fpaths = np.float32(paths)
        if lr_check:
            for y in range(h):
                for x in range(rmin.shape[1]):
                    rmin[y, x] = np.int32(0x7FFFFFFF)
        for direction in range(2):
            prev[:] = 0.0
            cur[:] = 0.0
            mins[:] = 0.0
            cmins[:] = 0.0
            for t in range(h):
                y = t if direction == 0 else h - 1 - t
                for s in range(ns):
                    dx = 0 if s == 0 else (1 if s == 1 else -1)
                    last = direction == 1 and s == ns - 1
                    row = s * (n + 2)
                    for i in range(n):
                        src = row + i + 1 - dx  # predecessor column
                        q = row + i + 1
                        x = x0 + i
                        p = y * w + x
                        if not last:
                            cmins[q] = _step_add(prev, src, c2, p, max_d - 1 - x, mins[src], p1, p2, cur, q, h2, p)
                        else:
                            cmins[q] = _step(prev, src, c2, p, max_d - 1 - x, mins[src], p1, p2, cur, q)
                            # the aggregated cost, then _encode: clamp_min(0) and the index in the low mantissa
                            # bits; the min of the codes is the winner
                            # (and the right view's running minimum: right pixel xr = x - d sees candidate j;
                            # rmin has max_d spare columns on the left so that no index is negative)
                            lo = np.int32(0x7FFFFFFF)
                            rrow = rmin[y, x + 1 :]
                            for j in range(num):
                                a = (h2[p, j] + cur[q, j]) / fpaths
                                if store:
                                    h2[p, j] = a
                                code = (max(_bits_of_float(a), np.int32(0)) & high) | np.int32(j)
                                codes[j] = code
                                lo = min(lo, code)
                                if lr_check:
                                    rrow[j] = min(rrow[j], code)
                            jb, dsp, good, var = _select_pixel(lo, codes, codef, num, max_d, bits, subpixel, parabola,
                                                               uniqueness, floor, eps, min_disparity_positive)
                            if good and max_raw >= 0:  # (an ok winner is in view: no INVALID_COST in its cost)
                                good = np.float32(c2[p, jb]) <= max_raw
                            jbest[y, x] = jb
                            disparity[y, x] = dsp
                            ok[y, x] = good
                            variance[y, x] = var
                prev, cur = cur, prev
                mins, cmins = cmins, mins

    @_jit
    def _lr_check_rows(rmins, jbest, ok, max_d, bits, lr_threshold, y0, y1):
        """Left-right check of rows ``[y0, y1)``: the right view's winner (min over the bands' ``rmins``, with
        INVALID_COST where ``xr + d`` leaves the image, as matching._right_view_index) against the left one's."""
        bands, h, wp = rmins.shape
        w = wp - max_d  # column max_d + xr holds right pixel xr
        low = (1 << bits) - 1
        jright = np.empty(w, dtype=np.int32)
        for y in range(y0, y1):
            for xr in range(w):
                lo = rmins[0, y, max_d + xr]
                for k in range(1, bands):
                    lo = min(lo, rmins[k, y, max_d + xr])
                if xr + max_d - 1 >= w:
                    lo = min(lo, np.int32(_INVALID_CODE))
                jright[xr] = lo & low
            for x in range(w):
                if ok[y, x]:
                    d_left = max_d - 1 - jbest[y, x]
                    xr = min(max(x - d_left, 0), w - 1)
                    ok[y, x] = abs(max_d - 1 - jright[xr] - d_left) <= lr_threshold


def _max_raw(opts: dict) -> np.float32:
    """The raw-cost check's bound in window-sum units as matching._select computes it (-1: off)."""
    limit = opts.get("max_raw_cost")
    return np.float32(-1.0) if limit is None else np.float32(limit)


_workspace = threading.local()


def _volume(name: str, shape: tuple[int, ...], dtype: type) -> np.ndarray:
    """The calling thread's reusable work volume ``name`` (allocated anew when the size or type changes)."""
    arrays = getattr(_workspace, "arrays", None)
    if arrays is None:
        arrays = _workspace.arrays = {}
    array = arrays.get(name)
    if array is None or array.shape != shape or array.dtype != dtype:
        arrays.pop(name, None)  # free the old one before allocating the new
        array = arrays[name] = np.empty(shape, dtype=dtype)
    return array


def release_workspace() -> None:
    """Free the work volumes that the compiled census + SGM path keeps for the calling thread.

    Public as :func:`egorefine.stereo.release_sgm_workspace`. :func:`~egorefine.stereo.match_stereo` with
    ``cost="census", aggregation="sgm"`` on float32 CPU images keeps its two volumes (about 6 bytes per pixel and
    candidate disparity) for the next call of the same size; call this when a thread is done matching, to hand
    the memory back. The next call allocates them anew.

    Example:
        >>> from egorefine.stereo import match_stereo, release_sgm_workspace
        >>> left = torch.rand(1, 1, 24, 32)
        >>> out = match_stereo(left, torch.roll(left, -2, dims=3), 8, cost="census", aggregation="sgm")
        >>> release_sgm_workspace()  # the volumes of that call are freed; its result is not touched
        >>> out.disparity.shape
        torch.Size([1, 1, 24, 32])
    """
    _workspace.arrays = {}


def census_sgm_select(grey_l: torch.Tensor, grey_r: torch.Tensor, max_disparity: int, min_disparity: int,
                      block_size: int, census_window: int, p1: float, p2: float, paths: int, opts: dict,
                      threads: int | None = None, return_volume: bool = False
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Census cost, box sum, SGM aggregation and winner selection of float32 CPU grey pairs.

    Equal to ``_select(sgm_aggregate(strip_volume(...)))`` of :mod:`egorefine.stereo.matching` (the torch
    path), bit for bit. Memory: one int16 cost volume and one float32 volume (about 6 bytes per candidate).

    Args:
        grey_l, grey_r: ``(B, 1, H, W)`` float32 CPU grey images.
        max_disparity, min_disparity, block_size, census_window: as :func:`egorefine.stereo.match_stereo`
            (``max_disparity - min_disparity >= 2``).
        p1, p2: SGM penalties in window-*sum* units (``block_size**2`` times the mean-cost penalties).
        paths: 4 or 8.
        opts: the selection options of ``matching._select`` (its hard winner; no soft-argmin).
        threads: worker threads (None: ``torch.get_num_threads()``).
        return_volume: also return the aggregated volume ``(B, D, H, W)`` (reversed disparity order,
            as ``sgm_aggregate`` returns it), for tests.

    Returns:
        ``(disparity, valid, variance, volume or None)``, the first three ``(B, 1, H, W)`` as ``_select``
        returns them (before the texture check and the zeroing of invalid pixels).
    """
    b, _, h, w = grey_l.shape
    num = max_disparity - min_disparity
    threads = max(1, threads or torch.get_num_threads())
    left, right = grey_l.detach().numpy(), grey_r.detach().numpy()
    disparity = np.empty((b, h, w), dtype=np.float32)
    valid = np.empty((b, h, w), dtype=np.bool_)
    variance = np.empty((b, h, w), dtype=np.float32)
    words = -(-(census_window * census_window - 1) // _WORD_BITS)
    # window sums of census distances: int16 while they fit (half the memory traffic of float32)
    cost_dtype = np.int16 if block_size * block_size * (census_window * census_window - 1) < 1 << 15 else np.int32
    f1, f2 = np.float32(p1), np.float32(p2)
    select = (max_disparity, max(1, (num - 1).bit_length()), opts["subpixel"], opts["subpixel_fit"] == "parabola",
              float(opts["uniqueness_ratio"]), np.float32(opts["cost_floor"] * opts["scale"]),
              np.float32(torch.finfo(torch.float32).eps * 16 * opts["scale"]), opts["min_disparity"] > 0,
              bool(opts["lr_check"]), _max_raw(opts))
    row_bands = _bands(h, threads)
    # vertical paths are independent per column; diagonal ones cross columns: one band
    col_bands = _bands(w, threads) if paths == 4 else [(0, w)]
    volumes = []

    def item(i: int, run) -> None:  # run(fn, items): the phases are separated by these barriers
        census = np.empty((2, words, h, w), dtype=np.int32)
        pad = census_window // 2
        run(lambda k: _census(np.pad((left, right)[k][i, 0], pad, mode="edge"), census_window, census[k]), (0, 1))
        cost = _volume("cost", (h, w, num), cost_dtype)
        # a volume returned to the caller stays its own (each batch item's is kept until the end)
        horiz = np.empty((h, w, num), np.float32) if return_volume else _volume("sums", (h, w, num), np.float32)
        run(lambda band: _rows_pass(census[0], census[1], block_size // 2, max_disparity, num, band[0], band[1],
                                    f1, f2, cost, horiz), row_bands)
        jbest = np.empty((h, w), dtype=np.int32)
        rmins = np.empty((len(col_bands), h, max_disparity + w), dtype=np.int32)
        run(lambda k: _vertical_select(cost, f1, f2, col_bands[k][0], col_bands[k][1], paths == 8, paths, horiz,
                                       return_volume, *select, jbest, disparity[i], valid[i], variance[i], rmins[k]),
            range(len(col_bands)))
        if return_volume:
            volumes.append(torch.from_numpy(horiz).permute(2, 0, 1))
        if opts["lr_check"]:
            run(lambda band: _lr_check_rows(rmins, jbest, valid[i], max_disparity, select[1], opts["lr_threshold"],
                                            band[0], band[1]), row_bands)

    workers = Workers(threads)
    for i in range(b):
        item(i, workers.map)
    as_t = lambda a: torch.from_numpy(a).unsqueeze(1)  # noqa: E731
    return as_t(disparity), as_t(valid), as_t(variance), torch.stack(volumes) if return_volume else None
