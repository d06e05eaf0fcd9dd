"""CPU inference path of census + SGM matching compiled with numba (optional dependency).

The scanline recursion of SGM is sequential along each path, so the eager torch version in
:mod:`egorefine.stereo.sgm` pays about ten operator launches per scanline step. Here the
census cost volume, its box aggregation, the 3, 4 or 8 path costs and the winner selection are
loops compiled by numba, run in nogil kernels over row or column bands from a thread pool
(not numba's ``parallel=True``, whose threading layer can clash with torch's OpenMP).

The kernels give the torch path's results bit for bit: census costs are integer window sums
(exact in float32), each recursion step is ``(C - m) + min(prev, m + P2, prev[d +- 1] + P1)`` as
in :func:`egorefine.stereo.sgm._step`, the path costs are summed in the order of
:func:`~egorefine.stereo.sgm.sgm_aggregate` (horizontal pair first, then top-down, then
bottom-up), and the selection repeats :func:`egorefine.stereo.matching._select` including its
index-in-mantissa encoding (so ties resolve the same way). With integer penalties (match_stereo's
census defaults) every float32 value there is an integer below 2**24, so integer arithmetic gives
the same values: the path costs are then int16 (16 SIMD lanes, half the memory of float32), with the
out-of-view INVALID_COST kept apart (see _path_arithmetic); otherwise they are float32 with the torch
path's operations one for one. Layout is ``(H, W, D)`` with the disparity axis innermost
(contiguous, so LLVM vectorises the loops over it) and reversed as in :mod:`egorefine.stereo.cost`
(index ``j`` is disparity ``max_disparity - 1 - j``).

Phases per batch item (each split over ``threads`` bands, a barrier between them):
census of both images (one byte per 8 neighbours); per row band, the cost rows and, a few rows at
a time (their costs still in cache), their horizontal paths, and with one band (one thread) also
the top-down paths; per column band, the top-down paths (if not done yet), then the bottom-up
ones with each row's winner selection as soon as its sums are complete (the right view's minimum
is gathered per band on the way); per row band, the left-right check. Diagonal paths (8 paths)
cross column bands, so their vertical phase is one band. With 3 paths, per stripe of rows
(sgm.sgm_stripes), one pass down it: the census of its rows, then costs, paths and winners row by
row; then, in the same job, the stripe's left-right check (and the texture check, when asked).
Compiled with ``cache=True``: the first call on a machine compiles for several seconds.

The two volumes of 4 and 8 paths (``H W D`` int16 costs and the path sums, int16 or float32) are kept per calling
thread and reused by the next call that fits in them, as OpenCV's SGBM keeps its buffer: faulting in
fresh pages for them on every call costs a sizeable share of the call (docs/decisions.md).
:func:`release_workspace` frees them.

``AVAILABLE`` is False when numba cannot be imported; callers then use the torch path.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core._jit import AVAILABLE, Workers, release_scratch, scratch, thread_count
from ..core._jit import bands as _bands
from ..core._jit import jit as _jit
from . import _texture_numba
from .sgm import sgm_stripes

__all__ = ["AVAILABLE", "census_sgm_select", "release_workspace"]

if AVAILABLE:  # numba is a dependency, but the package stays importable (torch path) without it
    from llvmlite import ir as _llvm_ir
    from numba import literally
    from numba.core import types as _types
    from numba.extending import intrinsic

# the encoded value of an out-of-view candidate in the right-view search: INVALID_COST's float32 bits
_INVALID_CODE = int(np.array(1.0e6, dtype=np.float32).view(np.int32))


# Rows whose horizontal paths step together (_horizontal_band): with more, the band's rows of costs and sums (each a
# multiple of 4 KiB apart for many image widths) outnumber the ways of an L1 cache set; with fewer, each column step
# has less independent work (docs/decisions.md, "Two SGM passes" and "Vector width of the kernels").
BAND_ROWS = 4


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

    @_jit(noalias=True)
    def _census(padded, window, out):
        """Census bytes ``out`` ``(planes, H, W)`` uint8 of an image replicate-padded by ``window // 2``
        (``padded``): bit ``b`` of plane ``i`` is 1 where neighbour ``8 i + b`` (census_transform's order: row by
        row, the centre left out) is darker than the centre; bits past the last neighbour are 0. (Which bit holds
        which neighbour does not change a Hamming distance.) ``window`` is a literal: the loop over a byte's bits
        unrolls, and the one over the row becomes SIMD code."""
        literally(window)
        planes, h, w = out.shape
        r = window // 2
        centre = r * window + r
        for y in range(h):
            for plane in range(planes):
                for x in range(w):
                    c = padded[y + r, x + r]
                    acc = 0
                    for b in range(8):
                        k = plane * 8 + b
                        k = centre if k >= window * window - 1 else (k + 1 if k >= centre else k)  # centre: bit 0
                        acc |= np.int32(padded[y + k // window, x + k % window] < c) << b
                    out[plane, y, x] = np.uint8(acc)

    @_jit(noalias=True)
    def _raw_row(cl, cr, yy, r, max_d, planes, rpad, ring, slot, colsum, leaving):
        """Hamming distances of (clamped) image row ``yy`` into ``ring[slot]`` ``(W + 2r, D)`` uint8, padded columns
        ``x' in [0, W + 2r)``; ``colsum`` gains them and, where ``leaving`` (0xFF, else 0), loses the previous
        content of ``ring[slot]`` (the row leaving the window).

        As cost.strip_volume: left column ``x' - r``, right column ``x' + 1 + j`` of the right row padded
        (replicated) by ``r + max_d`` on the left (``rpad``: ``(planes, W + 2r + max_d + 1)`` scratch). ``planes``
        (census bytes per pixel) is a literal: the loop over them unrolls inside the SIMD loop over ``j``.
        """
        literally(planes)
        _, _, w = cl.shape
        num = colsum.shape[1]
        for i in range(planes):
            for t in range(rpad.shape[1]):
                rpad[i, t] = cr[i, yy, min(max(t - r - max_d, 0), w - 1)]
        for x in range(w + 2 * r):
            xl = min(max(x - r, 0), w - 1)
            for j in range(num):
                d = np.uint8(0)
                for i in range(planes):
                    d = _add(d, _ctpop(_xor(cl[i, yy, xl], rpad[i, x + 1 + j])))
                colsum[x, j] = _add(_sub(colsum[x, j], _like(_and(ring[slot, x, j], leaving), colsum[x, j])),
                                    _like(d, colsum[x, j]))
                ring[slot, x, j] = d

    def _same_type_op(name, int_op, float_op=None):
        """An intrinsic ``name(a, b)`` in the type of both operands: LLVM's ``int_op`` (integers wrap, with no
        promotion to int64, so LLVM keeps 16-bit lanes) or ``float_op``."""

        def typer(typingctx, a, b):
            if a != b or (float_op is None and not isinstance(a, _types.Integer)):
                return None

            def codegen(context, builder, signature, args):
                return getattr(builder, float_op if isinstance(a, _types.Float) else int_op)(*args)

            return a(a, b), codegen

        typer.__name__ = typer.__qualname__ = name
        return intrinsic(typer)

    _add = _same_type_op("_add", "add", "fadd")
    _sub = _same_type_op("_sub", "sub", "fsub")
    _and = _same_type_op("_and", "and_")
    _xor = _same_type_op("_xor", "xor")
    _or = _same_type_op("_or", "or_")

    @intrinsic
    def _like(typingctx, x, like):
        """``x`` converted to the type of ``like`` (an integer to a float exactly as numpy does; unsigned ones
        extended with zeros)."""
        if not isinstance(x, _types.Integer) or not isinstance(like, (_types.Integer, _types.Float)):
            return None

        def codegen(context, builder, signature, args):
            v = args[0]
            target = context.get_value_type(like)
            if isinstance(like, _types.Float):
                return (builder.sitofp if x.signed else builder.uitofp)(v, target)
            if like.bitwidth > x.bitwidth:
                return (builder.sext if x.signed else builder.zext)(v, target)
            if like.bitwidth < x.bitwidth:
                return builder.trunc(v, target)
            return v

        return like(x, like), codegen

    @intrinsic
    def _key(typingctx, x):
        """An integer whose order is that of ``x``: the bits of a non-negative float32, an integer itself."""
        if x == _types.float32:
            def codegen(context, builder, signature, args):
                return builder.bitcast(args[0], _llvm_ir.IntType(32))

            return _types.int32(x), codegen
        if isinstance(x, _types.Integer):
            return x(x), lambda context, builder, signature, args: args[0]
        return None

    @intrinsic
    def _unkey(typingctx, k, like):
        """The inverse of _key for the type of ``like``."""
        def codegen(context, builder, signature, args):
            if isinstance(like, _types.Float):
                return builder.bitcast(args[0], _llvm_ir.FloatType())
            return args[0]

        return like(k, like), codegen

    @_jit(inline="always")
    def _min(a, b):
        return a if a < b else b  # torch.minimum without NaNs; a plain select LLVM vectorises

    @_jit(inline="always")
    def _max(a, b):
        return a if a > b else b

    @_jit(noalias=True)
    def _run(src, dst, smins, dmins, n, back, c2, p0, pstride, x0, xstride, a2, tbig, tsub, p1, p2, max_d, mode):
        """``n`` independent SGM steps (sgm._step): item ``i`` goes from row ``i + 1 - back`` of ``src`` to row
        ``i + 1`` of ``dst``, ``L[j] = (C[j] - m) + min(prev[j], m + P2, prev[j +- 1] + P1)`` in the type ``T`` of
        the path rows, and ``min_j L[j]`` from ``smins`` to ``dmins`` (the predecessor's ``m``).

        Item ``i`` is pixel ``p0 + i * pstride`` (a row of ``c2``, ``a2``) at column ``x0 + i * xstride``. Path
        rows (_path_rows) hold ``L[j]`` at column ``j + 1`` between two pad columns that no minimum picks; a zero
        row (and zero ``m``) starts a path (L = C). ``C[j] = T(c2[p, j]) + tbig[v, j]`` and ``mode`` 1 sets, 2 adds
        ``L[j] - tsub[v, j]`` to ``a2[p, j]`` (0: neither), where ``v = clip(max_d - 1 - x, 0, D)`` counts the
        candidates out of view (see _path_arithmetic; tables rather than a select or a loop that starts at ``v``,
        which LLVM does not vectorise). The min is a reduction over _key, an integer order LLVM vectorises
        without fast-math (a float one it would not). ``mode`` is a literal: a branch per ``j`` on a run-time
        value keeps LLVM from vectorising.
        """
        literally(mode)
        num = c2.shape[1]
        for i in range(n):
            q = i + 1
            pp = q - back
            p = p0 + i * pstride
            v = min(max(max_d - 1 - (x0 + i * xstride), 0), num)
            m = smins[pp]
            mp2 = _add(m, p2)
            lo = _key(dst[q, 0])  # the pad: above every path cost
            for j in range(num):
                best = _min(_min(src[pp, j + 1], mp2), _min(_add(src[pp, j], p1), _add(src[pp, j + 2], p1)))
                cost = _add(_sub(_add(_like(c2[p, j], m), tbig[v, j]), m), best)
                dst[q, j + 1] = cost
                if mode == 1:
                    a2[p, j] = _sub(cost, tsub[v, j])
                elif mode == 2:
                    a2[p, j] = _add(a2[p, j], _sub(cost, tsub[v, j]))
                lo = _min(lo, _key(cost))
            dmins[q] = _unkey(lo, m)

    @_jit
    def _path_rows(rows, num, pad, like):
        """``rows`` zero path rows (a path start: L = C) of ``num`` candidates between two ``pad`` columns, of
        ``like``'s dtype."""
        out = np.zeros((rows, num + 2), dtype=like.dtype)
        out[:, 0] = pad
        out[:, num + 1] = pad
        return out

    @_jit
    def _horizontal_band(c2, a2, y0, n, w, cols, mins, tbig, tsub, p1, p2, max_d):
        """Rows ``[y0, y0 + n)`` of ``a2`` ``(H * W, D)`` = LR + RL (left-to-right plus right-to-left path costs, as
        sgm_aggregate adds them; see _run) of the integer costs ``c2``. The rows step together, column by column
        (independent steps: the next column's loads need not wait for this one's stores). ``cols``: two path rows
        (_path_rows) per row of the band, ``(2, n + 2, D + 2)``; ``mins``: ``(2, n + 2)``."""
        for direction in range(2):
            cols[0, :, 1:-1] = 0
            mins[0] = 0
            k = 0
            for t in range(w):
                x = t if direction == 0 else w - 1 - t
                if direction == 0:
                    _run(cols[k], cols[1 - k], mins[k], mins[1 - k], n, 0, c2, y0 * w + x, w, x, 0, a2, tbig, tsub,
                         p1, p2, max_d, 1)
                else:
                    _run(cols[k], cols[1 - k], mins[k], mins[1 - k], n, 0, c2, y0 * w + x, w, x, 0, a2, tbig, tsub,
                         p1, p2, max_d, 2)
                k = 1 - k

    @_jit
    def _vertical_row(c2, a2, y, w, x0, x1, rows, mins, k, tbig, tsub, p1, p2, max_d, final):
        """Row ``y``, columns ``[x0, x1)``, of the vertical (and, with 3 shifts, diagonal) paths of one direction:
        from ``rows[s, k]`` (the previous row of shift ``s``) to ``rows[s, 1 - k]``, ``(shifts, 2, n + 2, D + 2)``
        path rows with a zero column (a path start) on either side; ``mins`` ``(shifts, 2, n + 2)`` their minima.
        The paths are added to ``a2`` (see _run) in sgm_aggregate's order (column shifts 0, +1, -1); with
        ``final`` the last one is not (_finish_row completes the sum). A diagonal predecessor outside
        ``[x0, x1)`` starts the path, so diagonals need the full width."""
        ns = rows.shape[0]
        for s in range(ns):
            dx = 0 if s == 0 else (1 if s == 1 else -1)
            if final and s == ns - 1:
                _run(rows[s, k], rows[s, 1 - k], mins[s, k], mins[s, 1 - k], x1 - x0, dx, c2, y * w + x0, 1, x0, 1,
                     a2, tbig, tsub, p1, p2, max_d, 0)
            else:
                _run(rows[s, k], rows[s, 1 - k], mins[s, k], mins[s, 1 - k], x1 - x0, dx, c2, y * w + x0, 1, x0, 1,
                     a2, tbig, tsub, p1, p2, max_d, 2)

    @_jit
    def _select_pixel(lo, codes, num, max_d, bits, subpixel, parabola, uniqueness, floor, eps, min_disparity_positive):
        """matching._select for one pixel from its encoded costs ``codes`` (int32) and their minimum ``lo``.

        Returns ``(j, disparity, ok, variance)``; ``ok`` without the left-right check.
        """
        j = lo & ((1 << bits) - 1)
        jm = max(j - 1, 0)
        jp = min(j + 1, num - 1)
        c_best = _float_from_bits(codes[j])
        c_plus = _float_from_bits(codes[jm])  # reversed order: j - 1 is d + 1
        c_minus = _float_from_bits(codes[jp])
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

    @_jit(noalias=True)
    def _finish_row(c2, a2, cur, y, pr, w, x0, x1, tsub, tadd, select, vol, jbest, disparity, ok, variance, rmin,
                    codes, sums):
        """Pixels ``(y, x)``, ``x`` in ``[x0, x1)``: their aggregated costs ``((a2[p] + (L[j] - tsub)) + tadd) * s``
        (``s``: the float32 ``1 / paths``; ``L``: row ``x - x0 + 1`` of ``cur``, the last path, see _run; ``p``:
        pixel ``x`` of row ``pr`` of ``c2`` and ``a2``, which hold image row ``y`` there), then their selection
        (_select_pixel) into ``jbest``, ``disparity``, ``ok``, ``variance``.

        The sum is sgm_aggregate's in float32 (``a2`` then holds float32 path costs, the tables zeros) or, for
        integer path costs, an integer total converted exactly (``tadd``: ``paths * INVALID_COST`` out of view,
        which every path of such a candidate has; see _path_arithmetic). With ``store`` the costs go to
        ``vol[p]``. ``rmin`` ``(H, max_d + W)``: the right view's encoded minimum at column ``max_d + xr`` gains
        each pixel's candidates (``xr = x - d``; the first ``max_d`` columns are spare, so that no index is
        negative). ``codes`` (int32), ``sums`` (float32): ``(D,)`` scratch.
        """
        paths, store, max_d, bits, subpixel, parabola, uniqueness, floor, eps, positive, lr_check, max_raw = select
        num = codes.shape[0]
        high = np.int32(-(1 << bits))
        scale = np.float32(1.0 / paths)  # sgm_aggregate's multiply (for 4 and 8 paths the division's bits)
        for i in range(x1 - x0):
            x = x0 + i
            p = pr * w + x
            v = min(max(max_d - 1 - x, 0), num)
            # the aggregated cost, then _encode: clamp_min(0) and the index in the low mantissa bits; the min of
            # the codes is the winner
            lo = np.int32(0x7FFFFFFF)
            for j in range(num):
                a = ((np.float32(a2[p, j]) + np.float32(_sub(cur[i + 1, j + 1], tsub[v, j]))) + tadd[v, j]) * scale
                sums[j] = a
                code = _or(_and(_max(_bits_of_float(a), np.int32(0)), high), _like(j, high))
                codes[j] = code
                lo = _min(lo, code)
            if store:
                for j in range(num):
                    vol[y * w + x, j] = sums[j]
            if lr_check:  # the right view's running minimum: right pixel xr = x - d sees candidate j
                first = np.uint64(x + 1)  # an unsigned index: no wraparound check, which keeps LLVM from vectorising
                for j in range(num):
                    col = first + np.uint64(j)
                    rmin[y, col] = _min(rmin[y, col], codes[j])
            jb, dsp, good, var = _select_pixel(lo, codes, num, max_d, bits, subpixel, parabola, uniqueness, floor,
                                               eps, positive)
            if good and max_raw >= 0:  # (an ok winner is in view: no INVALID_COST in its cost)
                good = np.float32(c2[p, jb]) <= max_raw
            jbest[y, x] = jb
            disparity[y, x] = dsp
            ok[y, x] = good
            variance[y, x] = var

    @_jit
    def _raw_row_of(cl, cr, yy, r, max_d, planes, rpad, ring, slot, colsum, leaving):
        """_raw_row with ``planes`` (1, 3 or 6: census windows 3, 5, 7) as the literal it takes."""
        if planes == 1:
            _raw_row(cl, cr, yy, r, max_d, 1, rpad, ring, slot, colsum, leaving)
        elif planes == 3:
            _raw_row(cl, cr, yy, r, max_d, 3, rpad, ring, slot, colsum, leaving)
        else:
            _raw_row(cl, cr, yy, r, max_d, 6, rpad, ring, slot, colsum, leaving)

    @_jit
    def _edge_padded(img, r):
        """``numpy.pad(img, r, mode="edge")`` of a 2-D image (numpy's pad costs more than the census it feeds)."""
        h, w = img.shape
        out = np.empty((h + 2 * r, w + 2 * r), img.dtype)
        for y in range(h + 2 * r):
            src, row = img[min(max(y - r, 0), h - 1)], out[y]
            for x in range(r):
                row[x] = src[0]
                row[w + r + x] = src[w - 1]
            for x in range(w):
                row[r + x] = src[x]
        return out

    @_jit
    def _census_of_padded(padded, window, out):
        """_census of an image padded by ``window // 2``, with ``window`` (3, 5 or 7) as the literal it takes: the
        census rows of ``padded``'s rows ``window // 2 ..`` (as many as ``out`` has)."""
        if window == 3:
            _census(padded, 3, out)
        elif window == 5:
            _census(padded, 5, out)
        else:
            _census(padded, 7, out)

    @_jit
    def _census_of(image, window, out):
        """_census of ``image`` ``(H, W)`` (padded here) with ``window`` (3, 5 or 7) as the literal it takes."""
        _census_of_padded(_edge_padded(image, window // 2), window, out)

    @_jit(noalias=True)
    def _cost_row(cl, cr, y, y0, r, max_d, planes, ring, rpad, colsum, box, c2, out_row, row0, h):
        """Row ``y`` of the box sums (block ``2r+1``) of the census Hamming distances into row ``out_row`` of ``c2``
        ``(rows * W, D)`` (int16, or int32 for large blocks; the INVALID_COST of out-of-view candidates is added
        where they are read, see _run), as cost.strip_volume, sliding the window of ``ring`` (raw rows
        ``y - r .. y + r``) and ``colsum`` (their sum: uint8 where it fits, else int16) from row ``y - 1`` (filled
        anew at ``y == y0``). ``cl``, ``cr`` hold the census rows from image row ``row0`` on; ``h``: the image's
        height (rows beyond it are clamped)."""
        w = cl.shape[2]
        k = 2 * r + 1
        num = c2.shape[1]
        if y == y0:
            colsum[:] = 0
            for i in range(k):  # rows y0 - r .. y0 + r (clamped)
                yy = min(max(y0 - r + i, 0), h - 1)
                _raw_row_of(cl, cr, yy - row0, r, max_d, planes, rpad, ring, i, colsum, np.uint8(0))
        else:  # slide the window: drop row y - r - 1 (ring slot (y - y0 - 1) % k), add row y + r
            _raw_row_of(cl, cr, min(max(y + r, 0), h - 1) - row0, r, max_d, planes, rpad, ring, (y - y0 - 1) % k,
                        colsum, np.uint8(0xFF))
        box[:] = 0
        for i in range(k - 1):
            for j in range(num):
                box[j] = _add(box[j], _like(colsum[i, j], box[j]))
        for x in range(w):
            p = out_row * w + x
            for j in range(num):
                b = _add(box[j], _like(colsum[x + k - 1, j], box[j]))
                c2[p, j] = b
                box[j] = _sub(b, _like(colsum[x, j], box[j]))

    @_jit
    def _row_scratch(w, r, num, planes, max_d, band, pad, colsum_like, cost_like, acc_like):
        """The scratch of a pass that computes cost rows (_cost_row: its ring of raw rows, padded right row, column
        sums and box) and horizontal paths of ``band`` rows (_horizontal_band: their path columns and minima)."""
        wp = w + 2 * r
        ring = np.empty((2 * r + 1, wp, num), dtype=np.uint8)
        rpad = np.empty((planes, wp + max_d + 1), dtype=np.uint8)
        colsum = np.empty((wp, num), dtype=colsum_like.dtype)
        box = np.empty(num, dtype=cost_like.dtype)
        cols = _path_rows(2 * (band + 2), num, pad, acc_like).reshape(2, band + 2, num + 2)
        cmins = np.zeros((2, band + 2), dtype=acc_like.dtype)
        return ring, rpad, colsum, box, cols, cmins

    @_jit
    def _rows_pass(cl, cr, planes, r, y0, y1, band, p1, p2, pad, tbig, tsub, cost, acc, colsum_like, shifts,
                   max_d):
        """Rows ``[y0, y1)``: the census costs (_cost_row; ``colsum_like``: the dtype of its column sums) into ``cost``
        and, ``band`` rows at a time (their costs
        still in cache), their horizontal path costs (_horizontal_band) into ``acc``; with ``shifts > 0`` (the
        rows are the whole image) also the top-down ones of that many column shifts (_vertical_row)."""
        _, h, w = cl.shape
        num = cost.shape[2]
        ring, rpad, colsum, box, cols, cmins = _row_scratch(w, r, num, planes, max_d, band, pad, colsum_like, cost,
                                                            acc)
        c2 = cost.reshape(h * w, num)
        a2 = acc.reshape(h * w, num)
        rows = _path_rows(max(shifts, 1) * 2 * (w + 2), num, pad, acc).reshape(max(shifts, 1), 2, w + 2, num + 2)
        mins = np.zeros((max(shifts, 1), 2, w + 2), dtype=acc.dtype)
        for yb in range(y0, y1, band):
            n = min(band, y1 - yb)
            for y in range(yb, yb + n):
                _cost_row(cl, cr, y, y0, r, max_d, planes, ring, rpad, colsum, box, c2, y, 0, h)
            _horizontal_band(c2, a2, yb, n, w, cols, cmins, tbig, tsub, p1, p2, max_d)
            if shifts > 0:
                for y in range(yb, yb + n):
                    _vertical_row(c2, a2, y, w, 0, w, rows, mins, (y - y0) & 1, tbig, tsub, p1, p2, max_d, False)

    @_jit
    def _vertical_select(cost, acc, x0, x1, shifts, top_down, p1, p2, pad, tbig, tsub, tadd, select, vol, jbest,
                         disparity, ok, variance, rmin):
        """Columns ``[x0, x1)``: with ``top_down`` the top-down paths (``shifts`` column shifts, see _vertical_row)
        added to ``acc``, then the bottom-up ones with each row's selection as soon as its sums are complete
        (_finish_row; the right view's minimum is gathered in this band's ``rmin``)."""
        h, w, num = cost.shape
        c2 = cost.reshape(h * w, num)
        a2 = acc.reshape(h * w, num)
        n = x1 - x0
        rows = _path_rows(shifts * 2 * (n + 2), num, pad, acc).reshape(shifts, 2, n + 2, num + 2)
        mins = np.zeros((shifts, 2, n + 2), dtype=acc.dtype)
        codes = np.empty(num, dtype=np.int32)
        sums = np.empty(num, dtype=np.float32)
        max_d = select[2]
        if select[10]:  # lr_check
            rmin[:] = np.int32(0x7FFFFFFF)
        for direction in range(0 if top_down else 1, 2):
            rows[:, 0, :, 1 : num + 1] = 0
            mins[:] = 0
            for t in range(h):
                y = t if direction == 0 else h - 1 - t
                _vertical_row(c2, a2, y, w, x0, x1, rows, mins, t & 1, tbig, tsub, p1, p2, max_d, direction == 1)
                if direction == 1:
                    _finish_row(c2, a2, rows[shifts - 1, 1 - (t & 1)], y, y, w, x0, x1, tsub, tadd, select, vol, jbest,
                                disparity, ok, variance, rmin, codes, sums)

    @_jit
    def _stripe_pass(pl, pr_, window, planes, r, y0, y1, ys, band, num, p1, p2, pad, tbig, tsub, tadd, cost_like,
                     acc_like, colsum_like, select, vol, jbest, disparity, ok, variance, rmin):
        """3 paths: rows ``[y0, y1)`` of one stripe (sgm.sgm_stripes) in one pass down it, each row's costs, paths
        and winner while the row is in cache, from the census of the rows it reads (of ``pl``, ``pr_``: the images
        padded by ``window // 2``): ``band`` rows at a time the census costs (_cost_row) and their
        horizontal paths (_horizontal_band), then row by row the top-down path and the selection (_finish_row, which
        adds the path to the sums), in buffers of ``band`` rows (dtypes of ``cost_like``, ``acc_like``): no volume.
        The top-down path starts at row ``ys <= y0``: the rows ``[ys, y0)`` (the stripe above's) get only their
        costs and that path. ``rmin`` ``(H, max_d + W)``: the right view's minimum, this stripe's rows."""
        rc = window // 2
        h, w = pl.shape[0] - 2 * rc, pl.shape[1] - 2 * rc
        max_d = select[2]
        # the census of the rows the stripe's cost rows read (its own, its path's start, the block's reach)
        lo, hi = max(ys - r, 0), min(y1 + r, h)
        cl = np.empty((planes, hi - lo, w), np.uint8)
        cr = np.empty((planes, hi - lo, w), np.uint8)
        _census_of_padded(pl[lo : hi + 2 * rc], window, cl)
        _census_of_padded(pr_[lo : hi + 2 * rc], window, cr)
        ring, rpad, colsum, box, cols, cmins = _row_scratch(w, r, num, planes, max_d, band, pad, colsum_like,
                                                            cost_like, acc_like)
        c2 = np.empty((band * w, num), dtype=cost_like.dtype)
        a2 = np.empty((band * w, num), dtype=acc_like.dtype)
        rows = _path_rows(2 * (w + 2), num, pad, acc_like).reshape(1, 2, w + 2, num + 2)
        mins = np.zeros((1, 2, w + 2), dtype=acc_like.dtype)
        codes = np.empty(num, dtype=np.int32)
        sums = np.empty(num, dtype=np.float32)
        if select[10]:  # lr_check
            rmin[y0:y1] = np.int32(0x7FFFFFFF)
        t = 0
        for y in range(ys, y0):
            _cost_row(cl, cr, y, ys, r, max_d, planes, ring, rpad, colsum, box, c2, 0, lo, h)
            _vertical_row(c2, a2, 0, w, 0, w, rows, mins, t & 1, tbig, tsub, p1, p2, max_d, True)
            t += 1
        for yb in range(y0, y1, band):
            n = min(band, y1 - yb)
            for y in range(yb, yb + n):
                _cost_row(cl, cr, y, ys, r, max_d, planes, ring, rpad, colsum, box, c2, y - yb, lo, h)
            _horizontal_band(c2, a2, 0, n, w, cols, cmins, tbig, tsub, p1, p2, max_d)
            for y in range(yb, yb + n):
                _vertical_row(c2, a2, y - yb, w, 0, w, rows, mins, t & 1, tbig, tsub, p1, p2, max_d, True)
                _finish_row(c2, a2, rows[0, 1 - (t & 1)], y, y - yb, w, 0, w, tsub, tadd, select, vol, jbest,
                            disparity, ok, variance, rmin, codes, sums)
                t += 1

    @_jit(noalias=True)
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


def _path_arithmetic(cost_max: int, p1: np.float32, p2: np.float32, paths: int) -> tuple:
    """``(T, big, sub, add)``: the type ``T`` of the path costs and their out-of-view terms (see _step, _finish_pixel).

    int16 where that is exact: integer penalties, and every value in range. A path cost is ``L = L' + INVALID_COST``
    out of view, ``L' <= cost + P2``; int16 holds ``L' + big`` with ``big = cost_max + 2 P2 + 1``, which never wins a
    minimum against a candidate in view, as INVALID_COST does not, and cancels where every candidate is out of
    view (in ``C - m``), as INVALID_COST does. The sums keep ``L'`` (``sub = big``) and get ``paths * INVALID_COST``
    back in float32 (``add``), exactly: every value is an integer below 2**24. Otherwise float32 with
    ``big = INVALID_COST`` (the torch path's operations)."""
    big = cost_max + 2 * int(p2) + 1
    integral = p1 >= 0 and p2 >= 0 and p1 == int(p1) and p2 == int(p2)
    if integral and big + cost_max + int(p2) + int(max(p1, p2)) < 1 << 15 and \
            (paths - 1) * (cost_max + int(p2)) < 1 << 15 and paths * (1.0e6 + cost_max + p2) < 1 << 24:
        return np.int16, np.int16(big), np.int16(big), np.float32(paths * 1.0e6)
    return np.float32, np.float32(1.0e6), np.float32(0.0), np.float32(0.0)


def release_workspace() -> None:
    """Free the work volumes that the compiled census + SGM path keeps for the calling thread.

    Public as :func:`egorefine.stereo.release_sgm_workspace`. :func:`~egorefine.stereo.match_stereo` with
    ``cost="census", aggregation="sgm"`` on float32 CPU images keeps its two volumes (4 to 6 bytes per pixel and
    candidate disparity) for the next call that fits in them; call this when a thread is done matching, to hand
    the memory back. The next call allocates them anew.

    Example:
        >>> from egorefine.stereo import match_stereo, release_sgm_workspace
        >>> left = torch.rand(1, 1, 24, 32)
        >>> out = match_stereo(left, torch.roll(left, -2, dims=3), 8, cost="census", aggregation="sgm")
        >>> release_sgm_workspace()  # the volumes of that call are freed; its result is not touched
        >>> out.disparity.shape
        torch.Size([1, 1, 24, 32])
    """
    release_scratch("sgm.")


def census_sgm_select(grey_l: torch.Tensor, grey_r: torch.Tensor, max_disparity: int, min_disparity: int,
                      block_size: int, census_window: int, p1: float, p2: float, paths: int, opts: dict,
                      threads: int | None = None, return_volume: bool = False,
                      texture: tuple[torch.Tensor, int, float, float, float] | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Census cost, box sum, SGM aggregation and winner selection of float32 CPU grey pairs.

    Equal to ``_select(sgm_aggregate(strip_volume(...)))`` of :mod:`egorefine.stereo.matching` (the torch
    path), bit for bit. Memory: one int16 cost volume and one int16 or float32 volume of path sums (4 or 6 bytes
    per candidate; int16 with integer penalties, see _path_arithmetic); with 3 paths, buffers of a few rows per
    stripe instead.

    Args:
        grey_l, grey_r: ``(B, 1, H, W)`` float32 CPU grey images.
        max_disparity, min_disparity, block_size, census_window: as :func:`egorefine.stereo.match_stereo`
            (``max_disparity - min_disparity >= 2``).
        p1, p2: SGM penalties in window-*sum* units (``block_size**2`` times the mean-cost penalties).
        paths: 3, 4 or 8.
        opts: the selection options of ``matching._select`` (its hard winner; no soft-argmin).
        threads: worker threads (None: ``torch.get_num_threads()``).
        return_volume: also return the aggregated volume ``(B, D, H, W)`` (reversed disparity order,
            as ``sgm_aggregate`` returns it), for tests.
        texture: ``(grey_l, block_size, prefilter_cap, texture_threshold, invalid_variance)``: also the texture
            check and the clearing of :func:`egorefine.stereo._texture_numba.mask_untextured` (the same maps), with
            3 paths in each stripe's job while its rows are in cache; None: not done.

    Returns:
        ``(disparity, valid, variance, volume or None)``, the first three ``(B, 1, H, W)`` as ``_select``
        returns them (before the texture check and the zeroing of invalid pixels, unless ``texture``).
    """
    b, _, h, w = grey_l.shape
    num = max_disparity - min_disparity
    threads = thread_count(threads)
    left, right = grey_l.detach().numpy(), grey_r.detach().numpy()
    disparity = np.empty((b, h, w), dtype=np.float32)
    valid = np.empty((b, h, w), dtype=np.bool_)
    variance = np.empty((b, h, w), dtype=np.float32)
    planes = -(-(census_window * census_window - 1) // 8)  # census bytes per pixel
    cost_max = block_size * block_size * (census_window * census_window - 1)
    # window sums of census distances: int16 while they fit (half the memory traffic of float32)
    cost_dtype = np.int16 if cost_max < 1 << 15 else np.int32
    # the cost pass's column sums of census distances: uint8 where they fit
    colsum_like = np.empty(0, np.uint8 if block_size * (census_window * census_window - 1) < 1 << 8 else cost_dtype)
    path_dtype, big, sub, add = _path_arithmetic(cost_max, np.float32(p1), np.float32(p2), paths)
    f1, f2 = path_dtype(p1), path_dtype(p2)
    # pad columns of the path rows: no minimum picks them, and adding P1 stays in range
    path_pad = path_dtype(np.inf) if path_dtype == np.float32 else path_dtype((1 << 15) - 1 - f1)
    # the out-of-view terms by the number v of candidates out of view (row v: v entries, then zeros; see _run)
    out_of_view = np.tri(num + 1, num, -1, dtype=np.bool_)
    tables = (np.where(out_of_view, big, 0).astype(path_dtype), np.where(out_of_view, sub, 0).astype(path_dtype),
              np.where(out_of_view, add, 0).astype(np.float32))
    select = (paths, return_volume, max_disparity, max(1, (num - 1).bit_length()), opts["subpixel"],
              opts["subpixel_fit"] == "parabola", float(opts["uniqueness_ratio"]),
              np.float32(opts["cost_floor"] * opts["scale"]),
              np.float32(torch.finfo(torch.float32).eps * 16 * opts["scale"]), opts["min_disparity"] > 0,
              bool(opts["lr_check"]), _max_raw(opts))
    shifts = 3 if paths == 8 else 1  # column shifts of the vertical paths
    row_bands = _bands(h, threads)
    # one row band: its pass also runs the top-down paths (row by row, the costs still in cache)
    fused = len(row_bands) == 1
    # vertical paths are independent per column; diagonal ones cross columns: one band (3 paths: no vertical phase)
    col_bands = _bands(w, threads) if paths == 4 else [(0, w)]
    stripes = sgm_stripes(h)
    volumes = []
    grey_t = None if texture is None else texture[0].detach().contiguous().numpy()

    def item(i: int, run) -> None:  # run(fn, items): the phases are separated by these barriers
        # a volume returned to the caller stays its own (each batch item's is kept until the end)
        vol = np.empty((h * w, num) if return_volume else (1, num), np.float32)
        jbest = np.empty((h, w), dtype=np.int32)
        rmins = np.empty((len(col_bands), h, max_disparity + w), dtype=np.int32)
        band = BAND_ROWS
        if paths == 3:  # one pass down each stripe: its census, costs, paths and winners in row buffers, no volume
            padded = [_edge_padded(img[i, 0], census_window // 2) for img in (left, right)]

            def stripe(st: tuple[int, int, int]) -> None:
                _stripe_pass(*padded, census_window, planes, block_size // 2, st[0], st[1], st[2], band, num, f1, f2,
                             path_pad, *tables, np.empty(0, cost_dtype), np.empty(0, path_dtype), colsum_like,
                             select, vol, jbest, disparity[i], valid[i], variance[i], rmins[0])
                # the stripe's rows checked while in cache: the right view's winners are its own rows'
                if opts["lr_check"]:
                    _lr_check_rows(rmins, jbest, valid[i], max_disparity, select[3], opts["lr_threshold"], st[0],
                                   st[1])
                if texture is not None:
                    _texture_numba.mask_rows(grey_t[i, 0], *texture[1:4], st[0], st[1], disparity[i], valid[i],
                                             variance[i], texture[4])

            run(stripe, stripes)
        else:
            census = np.empty((2, planes, h, w), dtype=np.uint8)
            run(lambda k: _census_of((left, right)[k][i, 0], census_window, census[k]), (0, 1))
            cost = scratch("sgm.cost", (h, w, num), cost_dtype)  # (a call with fewer candidates reuses them)
            acc = scratch("sgm.sums", (h, w, num), path_dtype)
            run(lambda rows: _rows_pass(census[0], census[1], planes, block_size // 2, rows[0], rows[1], band, f1,
                                        f2, path_pad, *tables[:2], cost, acc, colsum_like, shifts if fused else 0,
                                        max_disparity), row_bands)
            run(lambda k: _vertical_select(cost, acc, col_bands[k][0], col_bands[k][1], shifts, not fused, f1, f2,
                                           path_pad, *tables, select, vol, jbest, disparity[i], valid[i],
                                           variance[i], rmins[k]), range(len(col_bands)))
        if return_volume:
            volumes.append(torch.from_numpy(vol.reshape(h, w, num)).permute(2, 0, 1))
        if opts["lr_check"] and paths != 3:
            run(lambda rows: _lr_check_rows(rmins, jbest, valid[i], max_disparity, select[3], opts["lr_threshold"],
                                            rows[0], rows[1]), row_bands)

    workers = Workers(threads)
    for i in range(b):
        item(i, workers.map)
    as_t = lambda a: torch.from_numpy(a).unsqueeze(1)  # noqa: E731
    out = as_t(disparity), as_t(valid), as_t(variance)
    if texture is not None and paths != 3:  # (3 paths: done in the stripes' jobs)
        _texture_numba.mask_untextured(out, *texture, threads=threads)
    return *out, torch.stack(volumes) if return_volume else None
