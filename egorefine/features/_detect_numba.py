"""CPU inference path of :func:`egorefine.features.detect` (Shi-Tomasi response), compiled with numba.

The torch path is some forty full-image operator launches: kornia's Sobel gradients, three 7x7
Gaussian blurs of the structure tensor, the smaller eigenvalue, a 7x7 max filter, the thresholds,
a padded copy of the score map cut into grid cells and a top-k within every cell, then the
round-robin top-k and the sub-pixel step on gathered windows. Here one pass over each band of rows
computes the response (:func:`_response_rows`: a ring of seven horizontally blurred rows of
gradient products, the vertical blur and the eigenvalue while the row is in cache), a second pass
keeps the local maxima (:func:`_nms_rows`), the bucketing works on the candidate list only (a few
thousand pixels, not the map) and the sub-pixel step runs over the keypoints in vector loops
(:func:`_refine`). Bands and keypoints are dealt to :class:`egorefine.core._jit.Workers` threads;
the result does not depend on their number. ``detect(image, max_features=1000)`` on the rendered
rigs' first frames, two threads, A/B interleaved with the torch path (whose OpenMP threads then
spin beside these kernels): 10.7 -> 3.2 ms at 640x480, 15.4 -> 4.0 ms at 1242x375; called back to
back, 2.1 and 2.3 ms.

Agreement with the torch path: the same keypoints, weights and slots, bit for bit (tests compare
them). The response repeats kornia's float32 arithmetic in its order: the normalised Sobel taps are
powers of two, so its convolution's sum is the taps' sum in row-major order; the separable blur
(``'reflect'`` border, rows first) is a chain of fused multiply-adds from the first tap's product, as
both the convolution and kornia's sliced CPU blur compute it (``_fma``: LLVM's ``fma``); torch's CPU
``sqrt`` is MKL's vector sqrt, which is not correctly rounded (~0.6 % of values differ from the IEEE
root by one ulp), so the kernels call the same MKL function (:class:`_Setup`). The thresholds, the
normalised strength and the round-robin key (``strength - rank``) are the same float32 operations,
so every decision is the torch path's. Exact ties (equal strengths in a cell, or equal keys: the key
``strength - rank`` keeps ~7 digits, and at 1000 slots one or two pairs of a 640x480 frame tie) are
ordered as ``torch.topk`` orders them, which is its algorithm's business: for the cells that hold one,
``torch.topk`` on the torch path's row of that cell; for the keys, where topk takes libstdc++'s
``std::partial_sort`` (k * 64 <= length: the default 8x8 grid with full cells) the same heap select and
heap sort repeated (:func:`_top_keys`), else ``torch.topk`` on the torch path's key array. The
sub-pixel step (Foerstner's corner point, :func:`egorefine.features.detection._gradient_offsets`)
repeats its float32 formulas per keypoint, its exponentials with MKL's vector exp (torch's ``exp``)
and its 49-term window sums in the order of torch's CPU sum (eight-lane vectors, :func:`_refine`).
:class:`_Setup` checks once per process that torch's library exports MKL's functions and that they,
the sum order and the partial sort reproduce torch's on probes; where one does not, the kernels use
``np.sqrt`` / ``np.exp`` (then positions agree to float rounding) or ``torch.topk`` itself.

``AVAILABLE`` is False when numba cannot be imported; :func:`egorefine.features.detect` then takes
the torch path, which stays the reference for GPU tensors, autograd, float64 and Harris.
"""

from __future__ import annotations

import ctypes
import math
import os
import threading

import numpy as np
import torch

from ..core import ValueRangeError
from ..core._jit import AVAILABLE, Workers
from ..core._jit import bands as _bands
from ..core._jit import jit as _jit

__all__ = ["AVAILABLE", "detect_compiled", "usable_compiled"]

_F = np.float32
# rows per band below which one thread does all (a hand-off to a pool thread costs tens of microseconds)
_MIN_BAND_ROWS = 48
# keypoints per thread below which one thread refines all
_MIN_PER_THREAD = 256


# MKL's vector math mode torch's at::vml uses (VML_HA | VML_FTZDAZ_OFF | VML_ERRMODE_IGNORE)
_VML_MODE = 0x2 | 0x140000 | 0x100


def _vml_probe(fn, op, x: np.ndarray) -> bool:
    """``fn`` (MKL's Fortran ``vms*``) on ``x`` gives what ``op`` (torch's CPU op) gives."""
    y = np.empty_like(x)
    fn(ctypes.byref(ctypes.c_int32(x.size)), x.ctypes.data_as(ctypes.c_void_p), y.ctypes.data_as(ctypes.c_void_p),
       ctypes.byref(ctypes.c_int64(_VML_MODE)))
    return bool(np.array_equal(y, op(torch.from_numpy(x)).numpy()))


def _sum8(x: np.ndarray) -> np.float32:
    """float32 sum of 49 values in the order of torch's CPU sum of a contiguous row (eight-lane vectors)."""
    p = x[0:8] + x[32:40]
    p = p + x[40:48]
    for k in (8, 16, 24):
        p = p + x[k:k + 8]
    f = np.float32(0.0) + x[48]
    for v in p:
        f = np.float32(f + v)
    return f


class _Setup:
    """Binds the external math the kernels call (once per process, before their first call) and records which
    of torch's CPU primitives the kernels repeat exactly on this machine.

    torch's CPU ``sqrt`` and ``exp`` of float32 are MKL's vector math (``vmsSqrt`` / ``vmsExp``, high-accuracy
    mode), not correctly rounded: ``sqrt`` differs from the IEEE root in ~0.6 % of values, ``exp`` from libm in
    ~40 %. Where torch's library exports them, the kernels call the same functions (symbols
    ``egorefine_vms_sqrt`` / ``egorefine_vms_exp``); elsewhere those symbols are stand-ins never called and the
    kernels take ``np.sqrt`` / ``np.exp`` (then the response and positions agree to rounding only).
    """

    def __init__(self) -> None:
        self.done = False
        self.vml = False  # MKL's sqrt/exp reproduce torch's
        self.sum8 = False  # torch's float32 sum of 49 values is the eight-lane order (_sum8)
        self.heap = False  # torch.topk's partial sort is libstdc++'s (_partial_sort)
        self.local = None  # MKL's mkl_set_num_threads_local
        self._keep: list = []

    def __call__(self) -> None:
        if self.done:
            return
        import llvmlite.binding as llvm

        sqrt = exp = None
        try:
            lib = ctypes.CDLL(os.path.join(os.path.dirname(torch.__file__), "lib", "libtorch_cpu.so"))
            sqrt, exp, local = lib.VMSSQRT_, lib.VMSEXP_, lib.MKL_Set_Num_Threads_Local
            local.argtypes, local.restype = [ctypes.c_int], ctypes.c_int
        except (OSError, AttributeError):
            sqrt = None
        if sqrt is not None:
            g = torch.Generator().manual_seed(0)
            roots = (torch.rand(1 << 14, generator=g) * 1e-4).numpy()
            args = (-torch.rand(1 << 14, generator=g) * 8.0).numpy()
            before = local(1)  # as in the kernels (_one_thread_mkl): MKL on this thread only
            try:
                self.vml = _vml_probe(sqrt, torch.sqrt, roots) and _vml_probe(exp, torch.exp, args)
            finally:
                local(before)
        if self.vml:
            fns = (sqrt, exp)
            self.local = local
        else:  # stand-ins that resolve the symbols; the kernels do not call them
            proto = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p)
            fns = (proto(lambda *a: None), proto(lambda *a: None))
            self._keep.append(fns)
        for name, fn in zip(("egorefine_vms_sqrt", "egorefine_vms_exp"), fns, strict=True):
            llvm.add_symbol(name, ctypes.cast(fn, ctypes.c_void_p).value)
        g = torch.Generator().manual_seed(1)
        rows = torch.randn(256, 49, generator=g)
        sums = rows.sum(-1).numpy()
        self.sum8 = all(_sum8(r) == t for r, t in zip(rows.numpy(), sums, strict=True))
        if AVAILABLE:
            self.heap = True
            for size, k in ((64000, 1000), (6400, 100), (129, 2)):  # values with many ties
                vals = torch.randint(0, 50, (size,), generator=g).float()
                vals[torch.rand(size, generator=g) < 0.5] = -3.0
                top = vals.topk(k).indices.numpy()
                self.heap &= bool(np.array_equal(_partial_sort(vals.numpy().copy(), k), top))
        self.done = True


_SETUP = _Setup()


if AVAILABLE:
    from llvmlite import ir
    from numba import types
    from numba.core import cgutils
    from numba.extending import intrinsic

    def _vms(name):
        """An intrinsic ``f(n, src, dst)``: MKL's ``vms*`` (Fortran interface, torch's mode) over ``src[:n]``."""

        @intrinsic
        def call(typingctx, n, src, dst):
            sig = types.void(n, src, dst)

            def codegen(context, builder, signature, args):
                cnt, a, b = args
                i32, i64, f32p = ir.IntType(32), ir.IntType(64), ir.FloatType().as_pointer()
                fnty = ir.FunctionType(ir.VoidType(), [i32.as_pointer(), f32p, f32p, i64.as_pointer()])
                fn = cgutils.get_or_insert_function(builder.module, fnty, name)
                np_ = cgutils.alloca_once(builder, i32)
                builder.store(builder.trunc(cnt, i32), np_)
                mp = cgutils.alloca_once(builder, i64)
                builder.store(ir.Constant(i64, _VML_MODE), mp)
                src_data = context.make_array(signature.args[1])(context, builder, a).data
                dst_data = context.make_array(signature.args[2])(context, builder, b).data
                builder.call(fn, [np_, src_data, dst_data, mp])
                return context.get_dummy_value()

            return sig, codegen

        return call

    _vms_sqrt = _vms("egorefine_vms_sqrt")
    _vms_exp = _vms("egorefine_vms_exp")

    @intrinsic
    def _fma(typingctx, a, b, c):
        """``a * b + c`` rounded once (LLVM's ``llvm.fma``), float32: the blurs' multiply-add."""
        sig = types.float32(types.float32, types.float32, types.float32)

        def codegen(context, builder, signature, args):
            return builder.fma(*args)

        return sig, codegen

    @_jit(inline="always")
    def _reflect(i, n):
        """torch's ``'reflect'`` padding: the index of the pixel that virtual row/column ``i`` mirrors."""
        if i < 0:
            return -i
        if i >= n:
            return 2 * (n - 1) - i
        return i

    @_jit(inline="always")
    def _sobel(a0, a1, a2, b0, b2, c0, c1, c2):
        """kornia's normalised Sobel ``(dx, dy)`` of one pixel from its 3x3 neighbours (row ``a`` above, ``c`` below;
        ``0, 1, 2`` left to right), summed in the convolution's row-major tap order."""
        e = _F(0.125)
        q = _F(0.25)
        gx = -e * a0 + e * a2
        gx = gx + -q * b0
        gx = gx + q * b2
        gx = gx + -e * c0
        gx = gx + e * c2
        gy = -e * a0 + -q * a1
        gy = gy + -e * a2
        gy = gy + e * c0
        gy = gy + q * c1
        gy = gy + e * c2
        return gx, gy

    @_jit
    def _products(ra, rb, rc, pxx, pyy, pxy):
        """Gradient products ``dx^2, dy^2, dx dy`` of the row with neighbours ``ra``, ``rb``, ``rc`` (border
        repeated: kornia's Sobel) into ``p[3 : W + 3]``, then the 3 columns either side mirrored (the blur's
        ``'reflect'`` border)."""
        W = rb.shape[0]
        n = W - 2
        a0, a1, a2 = ra[0:n], ra[1:n + 1], ra[2:n + 2]
        b0, b2 = rb[0:n], rb[2:n + 2]
        c0, c1, c2 = rc[0:n], rc[1:n + 1], rc[2:n + 2]
        oxx, oyy, oxy = pxx[4:n + 4], pyy[4:n + 4], pxy[4:n + 4]
        for u in range(n):
            gx, gy = _sobel(a0[u], a1[u], a2[u], b0[u], b2[u], c0[u], c1[u], c2[u])
            oxx[u] = gx * gx
            oyy[u] = gy * gy
            oxy[u] = gx * gy
        for x in (0, W - 1):
            xl, xr = max(x - 1, 0), min(x + 1, W - 1)
            gx, gy = _sobel(ra[xl], ra[x], ra[xr], rb[xl], rb[xr], rc[xl], rc[x], rc[xr])
            pxx[x + 3] = gx * gx
            pyy[x + 3] = gy * gy
            pxy[x + 3] = gx * gy
        for p in (pxx, pyy, pxy):
            for i in range(1, 4):
                p[3 - i] = p[3 + i]
                p[W + 2 + i] = p[W + 2 - i]

    @_jit
    def _hblur(p, k, out):
        """``out[x] = sum_t p[x + t] k[t]`` over the 7 taps (:func:`_taps7`)."""
        W = out.shape[0]
        k0, k1, k2, k3, k4, k5, k6 = k[0], k[1], k[2], k[3], k[4], k[5], k[6]
        p0, p1, p2, p3 = p[0:W], p[1:W + 1], p[2:W + 2], p[3:W + 3]
        p4, p5, p6 = p[4:W + 4], p[5:W + 5], p[6:W + 6]
        for x in range(W):
            out[x] = _taps7(p0, p1, p2, p3, p4, p5, p6, k0, k1, k2, k3, k4, k5, k6, x)

    @_jit(inline="always")
    def _taps7(r0, r1, r2, r3, r4, r5, r6, k0, k1, k2, k3, k4, k5, k6, x):
        """``sum_t r_t[x] k_t`` rounded as kornia's blur: the first product, then one fused multiply-add per tap."""
        acc = r0[x] * k0
        acc = _fma(r1[x], k1, acc)
        acc = _fma(r2[x], k2, acc)
        acc = _fma(r3[x], k3, acc)
        acc = _fma(r4[x], k4, acc)
        acc = _fma(r5[x], k5, acc)
        return _fma(r6[x], k6, acc)

    @_jit
    def _vblur_response(ring, base, k, vml, trace, disc, safe, root, out):
        """The vertical blur of the ring's seven rows (``base`` the slot of the top one) of each product, then
        kornia's smaller eigenvalue ``(tr - sqrt((a - c)^2 + 4 b b)) / 2`` in its float32 steps (the root by MKL's
        vector sqrt where ``vml``: torch's; ``trace``, ``disc``, ``safe``, ``root``: row scratch)."""
        W = out.shape[0]
        k0, k1, k2, k3, k4, k5, k6 = k[0], k[1], k[2], k[3], k[4], k[5], k[6]
        s0, s1, s2, s3 = base % 7, (base + 1) % 7, (base + 2) % 7, (base + 3) % 7
        s4, s5, s6 = (base + 4) % 7, (base + 5) % 7, (base + 6) % 7
        xx, yy, xy = ring[0], ring[1], ring[2]
        a0, a1, a2, a3, a4, a5, a6 = xx[s0], xx[s1], xx[s2], xx[s3], xx[s4], xx[s5], xx[s6]
        c0, c1, c2, c3, c4, c5, c6 = yy[s0], yy[s1], yy[s2], yy[s3], yy[s4], yy[s5], yy[s6]
        b0, b1, b2, b3, b4, b5, b6 = xy[s0], xy[s1], xy[s2], xy[s3], xy[s4], xy[s5], xy[s6]
        four = _F(4.0)
        half = _F(0.5)
        zero = _F(0.0)
        one = _F(1.0)
        for x in range(W):
            a = _taps7(a0, a1, a2, a3, a4, a5, a6, k0, k1, k2, k3, k4, k5, k6, x)
            c = _taps7(c0, c1, c2, c3, c4, c5, c6, k0, k1, k2, k3, k4, k5, k6, x)
            b = _taps7(b0, b1, b2, b3, b4, b5, b6, k0, k1, k2, k3, k4, k5, k6, x)
            trace[x] = a + c
            d = a - c
            q = d * d + (four * b) * b
            disc[x] = q
            safe[x] = q if q > zero else one  # the torch path takes the root of 1 where the disc is not positive
        if vml:
            _vms_sqrt(W, safe, root)
        else:
            for x in range(W):
                root[x] = np.sqrt(safe[x])
        for x in range(W):
            r = root[x] if disc[x] > zero else zero
            out[x] = half * (trace[x] - r)

    @_jit
    def _response_rows(img, y0, y1, k, vml, resp):
        """``resp[y] = gftt_response(img)[y]`` for rows ``[y0, y1)`` of one ``(H, W)`` float32 image (H, W >= 4).

        Rows ``y0 - 3 .. y1 + 2`` (mirrored at the image's edges) are blurred along x into a ring of seven rows
        per product; each output row then takes its seven rows of the ring. Returns whether the image rows
        ``[y0, y1)`` are all finite (the public entry point's check, without a full-image torch reduction)."""
        H, W = img.shape
        finite = True
        for y in range(y0, y1):
            row = img[y]
            bad = False
            for x in range(W):
                bad |= (row[x] - row[x]) != 0  # NaN for NaN and Inf
            finite &= not bad
        ring = np.empty((3, 7, W), np.float32)
        pxx = np.empty(W + 6, np.float32)
        pyy = np.empty(W + 6, np.float32)
        pxy = np.empty(W + 6, np.float32)
        rows = np.empty((4, W), np.float32)
        for j in range(y0 - 3, y1 + 3):
            r = _reflect(j, H)
            _products(img[max(r - 1, 0)], img[r], img[min(r + 1, H - 1)], pxx, pyy, pxy)
            s = (j - y0 + 3) % 7
            _hblur(pxx, k, ring[0, s])
            _hblur(pyy, k, ring[1, s])
            _hblur(pxy, k, ring[2, s])
            y = j - 3
            if y >= y0:
                _vblur_response(ring, (y - y0) % 7, k, vml, rows[0], rows[1], rows[2], rows[3], resp[y])
        return finite

    @_jit(inline="always")
    def _larger(a, b):
        """``max(a, b)`` for finite values, as a compare and select (LLVM vectorises it)."""
        return b if b > a else a

    @_jit
    def _row_max(row):
        """Largest value of a row, eight running maxima at a time."""
        W = row.shape[0]
        m = np.full(8, -np.inf, np.float32)
        for x8 in range(0, W - 7, 8):
            seg = row[x8:x8 + 8]
            for i in range(8):
                m[i] = _larger(m[i], seg[i])
        best = m.max()
        for x in range(W - W % 8, W):
            best = _larger(best, row[x])
        return best

    @_jit
    def _nms_rows(resp, y0, y1, radius, border, floor, idx, val):
        """Local maxima of ``resp`` (one image) in rows ``[y0, y1)``: pixels equal to the maximum of their
        ``(2 radius + 1)^2`` window (cut at the image's edges: detection._max_filter's -inf padding), ``border``
        px or more inside the image, and at least ``floor`` (the smallest threshold there can be). Writes their
        flat indices and values to ``idx`` / ``val`` in raster order; returns ``(count, max of the rows)``."""
        H, W = resp.shape
        peak = -np.inf
        for y in range(y0, y1):
            peak = _larger(peak, _row_max(resp[y]))
        vm = np.empty(W, np.float32)
        hm = np.empty(W, np.float32)
        flag = np.zeros(W + 8, np.uint8)
        n = max(W - 2 * border, 0)
        count = 0
        for y in range(max(y0, border), min(y1, H - border)):
            # the column maxima of the window's rows, then their maxima along the row
            vm[:] = resp[max(y - radius, 0)]
            for t in range(max(y - radius, 0) + 1, min(y + radius, H - 1) + 1):
                row = resp[t]
                for x in range(W):
                    vm[x] = _larger(vm[x], row[x])
            hm[:] = vm
            for d in range(1, radius + 1):
                left, out = vm[0:W - d], hm[d:W]
                for x in range(W - d):
                    out[x] = _larger(out[x], left[x])
                right, out = vm[d:W], hm[0:W - d]
                for x in range(W - d):
                    out[x] = _larger(out[x], right[x])
            # the candidates' flags in a vector loop, then a scan that skips eight clear flags at a time
            seg, top = resp[y, border:W - border], hm[border:W - border]
            for x in range(n):
                v = seg[x]
                flag[x] = (v >= top[x]) & (v >= floor)
            words = flag[:(n + 7) // 8 * 8].view(np.uint64)
            base = y * W + border
            for q in range(words.shape[0]):
                if words[q] != 0:
                    for x in range(q * 8, min(q * 8 + 8, n)):
                        if flag[x]:
                            idx[count] = base + x
                            val[count] = seg[x]
                            count += 1
        return count, peak

    @_jit
    def _bucket(idx, val, thr, peak, W, ch, cw, gx, ncell, kc):
        """The first half of detection._detect's bucketing for one image: the candidates ``idx``/``val`` (raster
        order) at or above ``thr``, their strength ``0.5 val / peak`` (float32), grouped by grid cell and sorted in
        each by strength (ties: raster order). Returns ``(flat, strength, per, tied)``: the flat pixel indices and
        strengths in that order, ``per[c]:per[c + 1]`` the range of cell ``c``, and which cells hold two equal
        strengths among their first ``kc + 1`` (whose order ``torch.topk`` leaves to its algorithm)."""
        m = 0
        for i in range(idx.shape[0]):
            if val[i] >= thr:
                m += 1
        flat = np.empty(m, np.int64)
        strength = np.empty(m, np.float32)
        half = _F(0.5)
        j = 0
        for i in range(idx.shape[0]):
            if val[i] >= thr:
                flat[j] = idx[i]
                strength[j] = half * val[i] / peak
                j += 1
        per = np.zeros(ncell + 1, np.int64)
        cell = np.empty(m, np.int64)
        for i in range(m):
            f = flat[i]
            c = (f // W) // ch * gx + (f % W) // cw
            cell[i] = c
            per[c + 1] += 1
        for c in range(ncell):
            per[c + 1] += per[c]
        start = per[:ncell].copy()
        out_flat = np.empty(m, np.int64)
        out_s = np.empty(m, np.float32)
        for i in range(m):  # by cell, raster order kept
            c = cell[i]
            out_flat[start[c]] = flat[i]
            out_s[start[c]] = strength[i]
            start[c] += 1
        for c in range(ncell):  # then by strength in each cell, stable sorts: raster order for ties
            if per[c + 1] - per[c] > 64:
                o = np.argsort(-out_s[per[c]:per[c + 1]], kind="mergesort") + per[c]
                out_s[per[c]:per[c + 1]] = out_s[o]
                out_flat[per[c]:per[c + 1]] = out_flat[o]
                continue
            for i in range(per[c] + 1, per[c + 1]):
                v, f = out_s[i], out_flat[i]
                j = i
                while j > per[c] and out_s[j - 1] < v:
                    out_s[j] = out_s[j - 1]
                    out_flat[j] = out_flat[j - 1]
                    j -= 1
                out_s[j] = v
                out_flat[j] = f
        tied = np.zeros(ncell, np.bool_)
        for c in range(ncell):
            for j in range(per[c], min(per[c + 1], per[c] + kc + 1) - 1):
                if out_s[j] == out_s[j + 1]:
                    tied[c] = True
        return out_flat, out_s, per, tied

    @_jit(inline="always")
    def _adjust_heap(val, idx, hole, length, v, j):
        """libstdc++'s ``__adjust_heap`` with ``comp(a, b) = a > b`` on ``val`` (``idx`` moves along): sift the
        hole at ``hole`` down, then push ``(v, j)`` up from where it ends."""
        top = hole
        child = hole
        while child < (length - 1) // 2:
            child = 2 * (child + 1)
            if val[child] > val[child - 1]:
                child -= 1
            val[hole] = val[child]
            idx[hole] = idx[child]
            hole = child
        if (length & 1) == 0 and child == (length - 2) // 2:
            child = 2 * (child + 1)
            val[hole] = val[child - 1]
            idx[hole] = idx[child - 1]
            hole = child - 1
        parent = (hole - 1) // 2
        while hole > top and val[parent] > v:
            val[hole] = val[parent]
            idx[hole] = idx[parent]
            hole = parent
            parent = (hole - 1) // 2
        val[hole] = v
        idx[hole] = j

    @_jit
    def _heap_sort_top(val, idx, k):
        """libstdc++'s ``make_heap`` of ``val[:k]`` (``idx`` moves along), under ``a > b``."""
        if k >= 2:
            parent = (k - 2) // 2
            while True:
                _adjust_heap(val, idx, parent, k, val[parent], idx[parent])
                if parent == 0:
                    break
                parent -= 1

    @_jit
    def _partial_sort(val, k):
        """The indices ``torch.topk(val, k)`` returns where it takes ``std::partial_sort`` (``64 k <= len(val)``):
        libstdc++'s heap select and heap sort of (value, index) pairs under ``a > b``, which fixes the order of
        equal values. ``val`` is overwritten."""
        idx = np.arange(val.shape[0])
        _heap_sort_top(val, idx, k)
        for i in range(k, val.shape[0]):  # heap select
            if val[i] > val[0]:
                _adjust_heap(val, idx, 0, k, val[i], idx[i])
        _sort_heap(val, idx, k)
        return idx[:k].copy()

    @_jit
    def _sort_heap(val, idx, k):
        """libstdc++'s ``sort_heap`` of the heap ``val[:k]``: best first."""
        last = k
        while last > 1:
            last -= 1
            v, j = val[last], idx[last]
            val[last], idx[last] = val[0], idx[0]
            _adjust_heap(val, idx, 0, last, v, j)

    @_jit
    def _top_keys(keys, slot, n, invalid):
        """:func:`_partial_sort` of the torch path's key array (``invalid`` but ``keys`` at ``slot``, ascending)
        without building it: past the first ``n`` entries an invalid key never enters the heap. Returns the
        positions in ``keys`` of the real keys among the first ``n``, in torch.topk's order."""
        val = np.full(n, invalid, np.float32)
        idx = np.arange(n)
        m = keys.shape[0]
        j = 0
        while j < m and slot[j] < n:
            val[slot[j]] = keys[j]
            j += 1
        _heap_sort_top(val, idx, n)
        for i in range(j, m):
            if keys[i] > val[0]:
                _adjust_heap(val, idx, 0, n, keys[i], slot[i])
        _sort_heap(val, idx, n)
        count = 0
        for i in range(n):
            if val[i] > invalid:
                count += 1
        out = np.searchsorted(slot, idx[:count])  # slot ascending: the entry holding each chosen index
        return out

    @_jit
    def _keys(strength, per, kc):
        """The round-robin key ``strength - rank`` (float32) of every cell's first ``kc`` candidates, in the index
        order of the torch path's ``(cell, rank)`` key array: ``(keys, slot, src, rank)``, ``slot`` the index
        there, ``src`` the candidate."""
        ncell = per.shape[0] - 1
        total = 0
        for c in range(ncell):
            total += min(per[c + 1] - per[c], kc)
        keys = np.empty(total, np.float32)
        slot = np.empty(total, np.int64)
        src = np.empty(total, np.int64)
        rank = np.empty(total, np.int64)
        j = 0
        for c in range(ncell):
            for r in range(min(per[c + 1] - per[c], kc)):
                keys[j] = strength[per[c] + r] - _F(r)
                slot[j] = c * kc + r
                src[j] = per[c] + r
                rank[j] = r
                j += 1
        return keys, slot, src, rank

    @_jit
    def _sorted_keys(keys, rank, n):
        """The order that sorts ``keys`` descending (ties in index order), round by round: a key ``strength -
        rank`` of rank ``r`` lies in ``[-r, 0.5 - r]``, so only the at most one-per-cell keys of a rank need
        sorting. Returns ``(order, exact)``; ``exact`` is False where two of the first ``n + 1`` tie (torch.topk
        orders those by its algorithm) or the ranks overlap (a negative strength)."""
        m = keys.shape[0]
        rounds = 0
        for j in range(m):
            rounds = max(rounds, rank[j] + 1)
        per = np.zeros(rounds + 1, np.int64)
        for j in range(m):
            per[rank[j] + 1] += 1
        for r in range(rounds):
            per[r + 1] += per[r]
        start = per[:rounds].copy()
        order = np.empty(m, np.int64)
        for j in range(m):  # by rank; cell order within a rank
            r = rank[j]
            order[start[r]] = j
            start[r] += 1
        done = 0
        for r in range(rounds):  # stable insertion sort of each rank by key, as far as the first n + 1 reach
            if done > n:
                break
            for i in range(per[r] + 1, per[r + 1]):
                o = order[i]
                v = keys[o]
                j = i
                while j > per[r] and keys[order[j - 1]] < v:
                    order[j] = order[j - 1]
                    j -= 1
                order[j] = o
            done = per[r + 1]
        exact = True
        for j in range(done - 1):
            a, b = keys[order[j]], keys[order[j + 1]]
            if a < b or (a == b and j < n):
                exact = False
        if done > 0:
            least = keys[order[done - 1]]
            for j in range(done, m):  # the ranks left unsorted lie below: their order does not matter
                if keys[order[j]] > least:
                    exact = False
        return order, exact

    @_jit(inline="always")
    def _terms(gx, gy, w, px, py, out, n):
        """The five normal-equation terms of one window pixel for ``n`` keypoints, in the torch path's float32
        steps: ``w gx gx``, ``w gx gy``, ``w gy gy``, ``w (gx gx px + gx gy py)``, ``w (gx gy px + gy gy py)``."""
        t0, t1, t2, t3, t4 = out[0], out[1], out[2], out[3], out[4]
        for i in range(n):
            g1, g2, we, x, y = gx[i], gy[i], w[i], px[i], py[i]
            t0[i] = we * g1 * g1
            t1[i] = we * g1 * g2
            t2[i] = we * g2 * g2
            t3[i] = we * (g1 * g1 * x + g1 * g2 * y)
            t4[i] = we * (g1 * g2 * x + g2 * g2 * y)

    @_jit
    def _refine(img, ix, iy, lo, hi, vml, kx, ky):
        """detection._gradient_offsets (radius 3, two passes) for the keypoints ``[lo, hi)`` of one image:
        Foerstner's corner point over the 7x7 window, re-centred once; writes ``base + offset`` to ``kx``/``ky``
        (float32, as the torch path adds them). Arrays run over the keypoints (the window pixel outermost) so
        that every step but the window gather is a vector loop. Each pass gathers the 9x9 windows, takes their
        Sobel gradients and the exponents of the Gaussian weights, exponentiates them at once (MKL's vector exp
        where ``vml``: torch's), and sums the terms of the normal equations in the order of torch's CPU sum of
        49 values: eight lanes, lane ``j`` adding pixels ``j, 32 + j, 40 + j, 8 + j, 16 + j, 24 + j``, then pixel
        48 plus the lanes in turn."""
        H, W = img.shape
        radius = 3
        size = 7
        S = size + 2
        L = size * size
        n = hi - lo
        patch = np.empty((S * S, n), np.float32)
        gxs = np.empty((L, n), np.float32)
        gys = np.empty((L, n), np.float32)
        arg = np.empty((L, n), np.float32)
        wgt = np.empty((L, n), np.float32)
        pxs = np.empty((size, n), np.float32)
        pys = np.empty((size, n), np.float32)
        ex = np.empty(n, np.float32)
        ey = np.empty(n, np.float32)
        sums = np.empty((5, n), np.float32)
        lane = np.empty((5, n), np.float32)
        term = np.empty((5, n), np.float32)
        xs = np.empty(S, np.int64)
        ys = np.empty(S, np.int64)
        two = _F(2.0)
        eighth = _F(8.0)
        sigma = 0.6 * radius
        div = _F(2 * (sigma * sigma))  # detection._gradient_offsets: 2 * sigma2
        lim = _F(1.5)
        rel = _F(1e-3)
        eps = _F(1e-6)
        for i in range(n):
            ex[i] = _F(ix[lo + i])
            ey[i] = _F(iy[lo + i])
        for _ in range(2):
            for i in range(n):  # the windows around the rounded estimates, border repeated
                cx = np.int64(np.rint(ex[i]))
                cy = np.int64(np.rint(ey[i]))
                for s in range(S):
                    xs[s] = min(max(cx + s - radius - 1, 0), W - 1)
                    ys[s] = min(max(cy + s - radius - 1, 0), H - 1)
                for r in range(S):
                    row = img[ys[r]]
                    for s in range(S):
                        patch[r * S + s, i] = row[xs[s]]
                for s in range(size):
                    pxs[s, i] = _F(xs[s + 1])
                    pys[s, i] = _F(ys[s + 1])
            for a in range(size):
                dy = pys[a]
                for c in range(size):
                    e = a * size + c
                    u0, u2 = patch[a * S + c], patch[a * S + c + 2]
                    m0, m2 = patch[(a + 1) * S + c], patch[(a + 1) * S + c + 2]
                    d0, d1, d2 = patch[(a + 2) * S + c], patch[(a + 2) * S + c + 1], patch[(a + 2) * S + c + 2]
                    u1 = patch[a * S + c + 1]
                    g1, g2, ar, dx = gxs[e], gys[e], arg[e], pxs[c]
                    for i in range(n):
                        g1[i] = ((u2[i] - u0[i]) + two * (m2[i] - m0[i]) + (d2[i] - d0[i])) / eighth
                        g2[i] = ((d0[i] - u0[i]) + two * (d1[i] - u1[i]) + (d2[i] - u2[i])) / eighth
                        qx = dx[i] - ex[i]
                        qy = dy[i] - ey[i]
                        ar[i] = -(qx * qx + qy * qy) / div
            if vml:
                _vms_exp(L * n, arg.reshape(-1), wgt.reshape(-1))
            else:
                for e in range(L):
                    for i in range(n):
                        wgt[e, i] = np.exp(arg[e, i])
            _terms(gxs[48], gys[48], wgt[48], pxs[6], pys[6], term, n)
            for q in range(5):
                sums[q, :n] = _F(0.0) + term[q]
            for j in range(8):
                _terms(gxs[j], gys[j], wgt[j], pxs[j % size], pys[j // size], lane, n)
                for e in (32 + j, 40 + j, 8 + j, 16 + j, 24 + j):
                    _terms(gxs[e], gys[e], wgt[e], pxs[e % size], pys[e // size], term, n)
                    for q in range(5):
                        lq, tq = lane[q], term[q]
                        for i in range(n):
                            lq[i] += tq[i]
                for q in range(5):
                    sq, lq = sums[q], lane[q]
                    for i in range(n):
                        sq[i] += lq[i]
            for i in range(n):
                fxx, fxy, fyy, fx, fy = sums[0, i], sums[1, i], sums[2, i], sums[3, i], sums[4, i]
                det = fxx * fyy - fxy * fxy
                tr = fxx + fyy
                if det > rel * (tr * tr) + eps:
                    bx = _F(ix[lo + i])
                    by = _F(iy[lo + i])
                    qx = (fyy * fx - fxy * fy) / det
                    qy = (fxx * fy - fxy * fx) / det
                    ex[i] = bx + min(max(qx - bx, -lim), lim)
                    ey[i] = by + min(max(qy - by, -lim), lim)
        for i in range(n):
            bx = _F(ix[lo + i])
            by = _F(iy[lo + i])
            kx[lo + i] = bx + (ex[i] - bx)
            ky[lo + i] = by + (ey[i] - by)

    @_jit
    def _usable(cand, cand_w, kp, live, md2, out):
        """replenish's test for one image: a real candidate at least ``sqrt(md2)`` from every live keypoint
        (squared distances in float32, as the torch path's)."""
        nl = 0
        for j in range(live.shape[0]):
            if live[j]:
                nl += 1
        lx = np.empty(nl, np.float32)
        ly = np.empty(nl, np.float32)
        nl = 0
        for j in range(live.shape[0]):
            if live[j]:
                lx[nl] = kp[j, 0]
                ly[nl] = kp[j, 1]
                nl += 1
        d2 = np.empty(nl, np.float32)
        for i in range(cand.shape[0]):
            if not cand_w[i] > 0:
                out[i] = False
                continue
            cx, cy = cand[i, 0], cand[i, 1]
            for j in range(nl):
                dx = cx - lx[j]
                dy = cy - ly[j]
                d2[j] = dx * dx + dy * dy
            near = np.inf
            for j in range(nl):
                near = min(near, d2[j])
            out[i] = near >= md2


class _Scratch(threading.local):
    """Per-thread buffers reused across calls of one shape (fresh pages cost ~0.3 ms per call at 640x480)."""

    def __init__(self) -> None:
        self.key = None
        self.resp = self.idx = self.val = None

    def get(self, b: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self.key != (b, h, w):
            self.key = (b, h, w)
            self.resp = np.empty((b, h, w), np.float32)
            self.idx = np.empty(b * h * w, np.int64)
            self.val = np.empty(b * h * w, np.float32)
        return self.resp, self.idx, self.val


_SCRATCH = _Scratch()
_KERNEL: list[np.ndarray] = []


def _gauss7() -> np.ndarray:
    """kornia's 7-tap Gaussian (sigma 1) in float32, as gaussian_blur2d builds it for the structure tensor."""
    if not _KERNEL:
        from kornia.filters import get_gaussian_kernel1d

        _KERNEL.append(get_gaussian_kernel1d(7, 1.0, dtype=torch.float32)[0].numpy().astype(np.float32))
    return _KERNEL[0]


def _one_thread_mkl(fn):
    """``fn`` with MKL kept to the calling thread: MKL's vector math would otherwise start an OpenMP team for
    every row (torch.set_num_threads sets MKL's count too), about 0.1 ms a call."""
    local = _SETUP.local
    if local is None:
        return fn

    def call(*args):
        before = local(1)
        try:
            return fn(*args)
        finally:
            local(before)

    return call


def _run(fn, tasks: list, threads: int) -> list:
    """``[fn(*task) for task in tasks]`` on ``threads`` threads; the calling thread takes the first task."""
    fn = _one_thread_mkl(fn)
    if threads <= 1 or len(tasks) <= 1:
        return [fn(*task) for task in tasks]
    pool = Workers(threads).pool
    pending = [pool.submit(fn, *task) for task in tasks[1:]]
    first = fn(*tasks[0])
    return [first, *(job.result() for job in pending)]


def _invalid(n: int) -> float:
    """detection._detect's score of a pixel that is no candidate."""
    return -float(n + 2)


def _cell_order(flat, strength, per, c: int, w: int, ch: int, cw: int, gx: int, kc: int, n: int) -> None:
    """Puts the candidates of cell ``c`` (which holds equal strengths) in the order ``torch.topk`` gives the
    torch path's row of that cell (its ``(ch * cw)`` scores in cell raster order), in place."""
    lo, hi = per[c], per[c + 1]
    f = flat[lo:hi]
    pos = (f // w - (c // gx) * ch) * cw + (f % w - (c % gx) * cw)
    row = np.full(ch * cw, _invalid(n), np.float32)
    row[pos] = strength[lo:hi]
    vals, top = torch.from_numpy(row).topk(kc)
    top = top[vals > _invalid(n)].numpy()
    where = np.empty(ch * cw, np.int64)
    where[pos] = np.arange(hi - lo)
    take = where[top]  # the cell's first min(count, kc) candidates in torch's order
    rest = np.setdiff1d(np.arange(hi - lo), take, assume_unique=True)
    keep = np.concatenate([take, rest])
    flat[lo:hi] = f[keep]
    strength[lo:hi] = strength[lo:hi][keep]


def _fill(flat, strength, per, kc: int, n: int, ncell: int, w: int, ix: np.ndarray, iy: np.ndarray) -> int:
    """The second half of the bucketing: the round-robin order over the cells as ``torch.topk`` orders the torch
    path's key array: sorted, and where keys tie, its partial sort repeated (where it takes one) or called; fills
    ``ix``/``iy`` and returns how many slots are filled."""
    keys, slot, src, rank = _keys(strength, per, kc)
    order, exact = _sorted_keys(keys, rank, n)
    size = max(ncell * kc, n)
    if not exact and _SETUP.heap and 64 * n <= size:
        order = _top_keys(keys, slot, n, np.float32(_invalid(n)))
    elif not exact:
        full = np.full(size, _invalid(n), np.float32)
        full[slot] = keys
        vals, top = torch.from_numpy(full).topk(n)
        order = np.searchsorted(slot, top[vals > _invalid(n)].numpy())
    filled = min(n, order.shape[0])
    f = flat[src[order[:filled]]]
    iy[:filled] = f // w
    ix[:filled] = f % w
    return filled


def detect_compiled(
    grey: torch.Tensor,
    n: int,
    grid: tuple[int, int],
    nms_radius: int,
    quality: float,
    min_response: float,
    border: int,
    subpixel: str,
    threads: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """detection._detect with the Shi-Tomasi response on a float32 CPU ``(B, 1, H, W)`` grey image, H, W >= 4.

    Returns keypoints ``(B, n, 2)`` and weights ``(B, n)`` as :func:`egorefine.features.detect` does; raises
    :class:`egorefine.core.ValueRangeError` (as ``check_finite`` words it) where the image holds NaN or Inf.
    """
    from .detection import _subpixel_offsets

    _SETUP()
    vml = _SETUP.vml
    b, _, h, w = grey.shape
    threads = max(1, threads or torch.get_num_threads())
    img = grey.detach()[:, 0].contiguous().numpy()
    resp, idx, val = _SCRATCH.get(b, h, w)
    k = _gauss7()
    parts = max(1, min(threads, h // _MIN_BAND_ROWS))
    rows = _bands(h, parts)
    finite = _run(_response_rows, [(img[i], y0, y1, k, vml, resp[i]) for i in range(b) for y0, y1 in rows], threads)
    if not all(finite):
        raise ValueRangeError("image: contains NaN or Inf")
    floor = _F(min_response)
    tasks = [(resp[i], y0, y1, nms_radius, border, floor, idx[i * h * w + y0 * w:], val[i * h * w + y0 * w:])
             for i in range(b) for y0, y1 in rows]
    found = _run(_nms_rows, tasks, threads)
    # the thresholds as the torch path computes them, on (B,) tensors
    peak = torch.tensor([max(p for _, p in found[i * len(rows):(i + 1) * len(rows)]) for i in range(b)],
                        dtype=torch.float32)
    thr = torch.clamp(peak * quality, min=min_response).numpy()
    pmc = peak.clamp_min(1e-6).numpy()  # eps_like(float32)
    gy, gx = grid
    ch, cw = math.ceil(h / gy), math.ceil(w / gx)
    kc = min(ch * cw, n)
    ix = np.zeros((b, n), np.int64)
    iy = np.zeros((b, n), np.int64)
    filled = []
    for i in range(b):
        pieces = [(i * h * w + y0 * w, cnt) for (y0, _), (cnt, _) in zip(rows, found[i * len(rows):], strict=False)]
        cidx = np.concatenate([idx[s:s + c] for s, c in pieces])
        cval = np.concatenate([val[s:s + c] for s, c in pieces])
        flat, strength, per, tied = _bucket(cidx, cval, thr[i], pmc[i], w, ch, cw, gx, gy * gx, kc)
        for c in np.flatnonzero(tied):
            _cell_order(flat, strength, per, c, w, ch, cw, gx, kc, n)
        filled.append(_fill(flat, strength, per, kc, n, gy * gx, w, ix[i], iy[i]))
    kx = ix.astype(np.float32)
    ky = iy.astype(np.float32)
    if subpixel == "gradient":
        tasks = []
        for i in range(b):
            cnt = filled[i]
            p = max(1, min(threads, cnt // _MIN_PER_THREAD))
            tasks += [(img[i], ix[i], iy[i], lo, hi, vml, kx[i], ky[i]) for lo, hi in _bands(cnt, p)] if cnt else []
        _run(_refine, tasks, threads)
    kp = torch.from_numpy(np.stack([kx, ky], axis=-1))
    weights = torch.from_numpy((np.arange(n)[None, :] < np.asarray(filled)[:, None]).astype(np.float32))
    if subpixel == "quadratic":
        kp = kp + _subpixel_offsets(torch.from_numpy(resp), torch.from_numpy(ix), torch.from_numpy(iy))
    return kp * weights.unsqueeze(-1), weights


def usable_compiled(
    cand: torch.Tensor, cand_w: torch.Tensor, keypoints: torch.Tensor, live: torch.Tensor, min_distance: float
) -> torch.Tensor:
    """replenish's ``usable`` (B, 2M): real candidates at least ``min_distance`` from every live keypoint."""
    c, cw_, kp, lv = (t.detach().contiguous().numpy() for t in (cand, cand_w, keypoints, live))
    out = np.empty(cw_.shape, np.bool_)
    md2 = _F(min_distance**2)
    for i in range(c.shape[0]):
        _usable(c[i], cw_[i], kp[i], lv[i], md2, out[i])
    return torch.from_numpy(out)
