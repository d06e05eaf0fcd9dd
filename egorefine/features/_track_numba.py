"""CPU inference path of :func:`egorefine.features.track` (hard ZNCC matching), compiled with numba.

The torch path matches all features at once, but each level of its search is a dozen small
operator launches on ``(B, N, ...)`` tensors (two index gathers, two grouped convolutions, an
arg-min, a gathered parabola) and a frame runs five or so such levels plus the Lucas-Kanade
polish and the forward-backward match: at a few hundred features nearly all of its time is
launch overhead. Every feature's work depends only on its own patches, so here
one compiled loop over the features does each stage of :func:`egorefine.features.tracking._track_live`
(same steps, same settings): the level-0 search around the prediction with the polish of the
features it finds, the coarse-to-fine search and polish of the others, then the way back. The
per-feature tests and the stage sizes are numpy on ``(B, N)`` arrays between the loops. Its timings
against the torch path are in docs/decisions.md.

Agreement with the torch path. Positions (rounding, cut windows, parabola, the polish's bicubic
samples, steps and clamps) repeat its float32 formulas in its order; the window sums (ZNCC terms,
means, the polish's normal equations) are added in float64 instead of the convolutions' float32
order (the correlations with reassociation and fused multiply-adds: :func:`_correlate`). Where the
torch path takes a coarse level's window sums from box maps (decided by how many features it
matches at once, :func:`_box_bits`; the same sums as the window's, combined in float32), so do
these loops. So positions, scores and round-trip errors differ by float32 rounding only (the differences
seen on the refiner's loops are in docs/decisions.md; ``tests/features/test_track_numba.py`` bounds them). A
decision (the arg-min, a threshold) can differ only where two costs, or a value and its
threshold, lie within float32 rounding of each other; in practice that is a template cut outside
the image (flat: every ZNCC is rounding noise), which both paths reject. Features are dealt out to
:class:`egorefine.core._jit.Workers` threads; a feature's result does not depend on the thread count.

``AVAILABLE`` is False when numba cannot be imported; :func:`egorefine.features.track` then takes
its torch path, which stays the reference for GPU tensors, autograd, ``soft=True`` and the SSD/SAD costs.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..core._jit import AVAILABLE, SHARES_PER_THREAD, Workers, thread_count
from ..core._jit import jit as _jit

# the torch path pads feature subsets to multiples of this many slots; the loops repeat its sizes
from ._matching import _SLOT_STEP

__all__ = ["AVAILABLE", "track_compiled", "pyrdown"]

_F = np.float32
# Features per thread below which one thread does all (a hand-off to a pool thread costs tens of
# microseconds, as much as a few dozen level-0 tracks).
_MIN_PER_THREAD = 48


if AVAILABLE:

    @_jit
    def _pyrdown(x, out):
        """_pyramid._pyrdown of images ``x (B, H, W)`` into ``out (B, ceil(H/2), ceil(W/2))``: the [1, 2, 1] / 4 taps
        along columns, then rows, at even positions, borders repeated; its float32 operations in its order."""
        B, H, W = x.shape
        h, w = out.shape[1:]
        rows = np.empty(W, np.float32)
        two, sixteenth = np.float32(2.0), np.float32(0.0625)
        for n in range(B):
            for i in range(h):
                a, b, c = x[n, max(2 * i - 1, 0)], x[n, 2 * i], x[n, min(2 * i + 1, H - 1)]
                for u in range(W):
                    rows[u] = (a[u] + c[u]) + two * b[u]
                o = out[n, i]
                for j in range(w):
                    left, mid, right = rows[max(2 * j - 1, 0)], rows[2 * j], rows[min(2 * j + 1, W - 1)]
                    o[j] = ((left + right) + two * mid) * sixteenth

    # reassociation and fused multiply-adds allowed: only for the float64 window correlations, whose order of
    # additions does not follow the torch path's anyway
    @_jit(fastmath={"reassoc", "contract"})
    def _correlate(tb, wb, p, k, cc):
        """``cc[dy * k + dx] = sum_ij tb[i, j] wb[dy + i, dx + j]`` for ``dy, dx < k``, eight shifts at a time (a
        fixed width: SIMD); ``wb`` has 8 spare columns, ``cc`` 8 spare entries."""
        for dy in range(k):
            for x8 in range(0, k, 8):
                c0 = c1 = c2 = c3 = c4 = c5 = c6 = c7 = 0.0
                for i in range(p):
                    w = wb[dy + i, x8:]
                    t = tb[i]
                    for j in range(p):
                        tv = t[j]
                        c0 += tv * w[j]
                        c1 += tv * w[j + 1]
                        c2 += tv * w[j + 2]
                        c3 += tv * w[j + 3]
                        c4 += tv * w[j + 4]
                        c5 += tv * w[j + 5]
                        c6 += tv * w[j + 6]
                        c7 += tv * w[j + 7]
                o = dy * k + x8
                cc[o] = c0
                cc[o + 1] = c1
                cc[o + 2] = c2
                cc[o + 3] = c3
                cc[o + 4] = c4
                cc[o + 5] = c5
                cc[o + 6] = c6
                cc[o + 7] = c7

    @_jit(inline="always")
    def _clamp(v, lo, hi):
        return min(max(v, lo), hi)

    @_jit(inline="always")
    def _parabola(cm, minus, plus, eps):
        """_matching._parabola in float32: vertex through (-1, minus), (0, cm), (1, plus), clamped to 0.5 px."""
        curv = max(minus - _F(2.0) * cm + plus, eps)
        return min(max(_F(0.5) * (minus - plus) / curv, _F(-0.5)), _F(0.5))

    @_jit(inline="always")
    def _cut(img, x0, y0, rows, cols, out):
        """``out[:rows, :cols]`` = the float64 pixels of ``img`` from ``(x0, y0)`` on, border repeated
        (_matching._extract_patches); returns their sum."""
        H, W = img.shape
        s = 0.0
        inside = x0 >= 0 and y0 >= 0 and x0 + cols <= W and y0 + rows <= H
        for i in range(rows):
            row = img[_clamp(y0 + i, 0, H - 1)]
            o = out[i]
            if inside:
                seg = row[x0:x0 + cols]
                for j in range(cols):
                    v = np.float64(seg[j])
                    o[j] = v
                    s += v
            else:
                for j in range(cols):
                    v = np.float64(row[_clamp(x0 + j, 0, W - 1)])
                    o[j] = v
                    s += v
        return s

    @_jit
    def _match_level(src, dst, px, py, ex, ey, p, radius, box, eps32, eps, tb, wb, cb, cc, acc):
        """_matching._match_level (hard, ZNCC) for one feature: ``(px, py)`` in ``src``, estimate ``(ex, ey)`` in
        ``dst``, both float32 px of this level. Returns ``(x, y, best cost, on edge)``.

        ``box``: the torch path takes this level's window sums from box maps (_matching._box_maps: the window's own
        sums, combined in float32): the costs repeat that combination.
        Scratch: ``tb (>= p, >= p)``, ``wb (>= S, >= S + 8)`` float64 (finite) with ``S = p + 2 radius``,
        ``cb (>= k * k)`` float32, ``cc (>= k * k + 8)`` and ``acc (3, >= S, >= k)`` float64, ``k = 2 radius + 1``.
        """
        h = (p - 1) // 2
        pix = _F(np.rint(px))
        piy = _F(np.rint(py))
        fx = px - pix
        fy = py - piy
        cx = _F(np.rint(ex - fx))
        cy = _F(np.rint(ey - fy))
        # template at the rounded point (border repeated), zero mean
        area = p * p
        tm = _cut(src, np.int64(pix) - h, np.int64(piy) - h, p, p, tb) / area
        tsq = 0.0
        for i in range(p):
            for j in range(p):
                t = tb[i, j] - tm
                tb[i, j] = t
                tsq += t * t
        # window around the rounded estimate (border repeated)
        S = p + 2 * radius
        k = 2 * radius + 1
        icx, icy = np.int64(cx), np.int64(cy)
        _cut(dst, icx - h - radius, icy - h - radius, S, S, wb)
        # ZNCC of every shift (_matching._cost_map): -sum((w - mean w) t0) / sqrt(sum (w - mean w)^2 sum t0^2).
        # Window sums: running sums along each row, then down the columns.
        hs, hq, vs, vq = acc[0], acc[1], acc[2, 0], acc[2, 1]
        for a in range(S):
            row = wb[a]
            s1 = s2 = 0.0
            for j in range(p):
                v = row[j]
                s1 += v
                s2 += v * v
            hs[a, 0] = s1
            hq[a, 0] = s2
            for dx in range(1, k):
                vo, vi = row[dx - 1], row[dx + p - 1]
                s1 += vi - vo
                s2 += vi * vi - vo * vo
                hs[a, dx] = s1
                hq[a, dx] = s2
        for dx in range(k):
            s1 = s2 = 0.0
            for i in range(p):
                s1 += hs[i, dx]
                s2 += hq[i, dx]
            vs[dx] = s1
            vq[dx] = s2
        m32 = _F(tm)
        tsq32 = _F(tsq)
        _correlate(tb, wb, p, k, cc)
        for dy in range(k):
            o = dy * k
            for dx in range(k):
                corr = cc[o + dx]
                if not box:
                    var = max(vq[dx] - vs[dx] * vs[dx] / area, 0.0)
                    cb[o + dx] = _F(-corr / np.sqrt(max(var * tsq, eps)))
                    continue
                # torch's float32 steps from the raw box sums: sum (w - m), sum (w - m)^2, the variance
                rs, rq = _F(vs[dx]), _F(vq[dx])
                w_sum = rs - _F(area) * m32
                w_sq = rq - _F(2.0) * m32 * rs + _F(area) * m32 * m32
                w_var = max(w_sq + _F(-1.0 / area) * w_sum * w_sum, _F(0.0))
                rsq = _F(1.0 / np.sqrt(np.float64(max(w_var * tsq32, eps32))))
                cb[o + dx] = -_F(corr) * rsq
            if dy + 1 < k:
                for dx in range(k):
                    vs[dx] += hs[dy + p, dx] - hs[dy, dx]
                    vq[dx] += hq[dy + p, dx] - hq[dy, dx]
        # first minimum (torch's min), then the parabola on each axis not on the edge
        bi = 0
        bv = cb[0]
        for q in range(1, k * k):
            if cb[q] < bv:
                bv = cb[q]
                bi = q
        ix = bi % k
        iy = bi // k
        edge_x = ix == 0 or ix == k - 1
        edge_y = iy == 0 or iy == k - 1
        subx = _F(0.0) if edge_x else _parabola(bv, cb[bi - 1], cb[bi + 1], eps32)
        suby = _F(0.0) if edge_y else _parabola(bv, cb[bi - k], cb[bi + k], eps32)
        half = _F((k - 1) // 2)
        return ((cx + fx) + ((_F(ix) - half) + subx), (cy + fy) + ((_F(iy) - half) + suby), bv, edge_x or edge_y)

    @_jit
    def _to_level0(src, dst, b, levels, px, py, sx, sy, p, search, refine, box, eps32, eps, tb, wb, cb, cc, acc):
        """_matching._match_to_level0 for item ``b`` of the pyramids (tuples of ``(B, H_l, W_l)``): the coarse levels
        ``levels - 1 .. 1``, then level 0. ``box``: bit ``l`` set where level ``l`` uses box sums.

        Returns level 0's ``(x, y, best cost, on edge)``.
        """
        ex, ey = sx, sy
        for level in range(levels - 1, 0, -1):
            scale = _F(2.0**level)
            radius = search if level == levels - 1 else refine
            ex, ey, _, _ = _match_level(src[level][b], dst[level][b], px / scale, py / scale, ex / scale, ey / scale,
                                        p, radius, (box >> level) & 1 == 1, eps32, eps, tb, wb, cb, cc, acc)
            ex, ey = ex * scale, ey * scale
        radius0 = search if levels == 1 else refine
        return _match_level(src[0][b], dst[0][b], px, py, ex, ey, p, radius0, box & 1 == 1, eps32, eps, tb, wb, cb,
                            cc, acc)

    @_jit(inline="always")
    def _cubic(t):
        """torch's bicubic weights (A = -0.75) for the fraction ``t`` in float32, in grid_sample's order."""
        A = _F(-0.75)
        x = t + _F(1.0)
        c0 = ((A * x - _F(5.0) * A) * x + _F(8.0) * A) * x - _F(4.0) * A
        c1 = ((A + _F(2.0)) * t - (A + _F(3.0))) * t * t + _F(1.0)
        x = _F(1.0) - t
        c2 = ((A + _F(2.0)) * x - (A + _F(3.0))) * x * x + _F(1.0)
        x = _F(2.0) - t
        c3 = ((A * x - _F(5.0) * A) * x + _F(8.0) * A) * x - _F(4.0) * A
        return c0, c1, c2, c3

    @_jit
    def _sample(img, posx, posy, p, out, hv, taps, wxs):
        """_matching._sample_patches (bicubic, border, align_corners) of ``img`` around ``(posx, posy)`` into
        ``out (p, p)`` float64, with grid_sample's float32 steps: the coordinates' normalisation round trip, the
        weights, each sample's four row interpolations and then the column one. A sample's row interpolation
        depends only on its column and the image row, so each is computed once (scratch: ``hv (>= p + 5, p)``
        and ``wxs (p, 4)`` float32, ``taps (p, 4)`` int64)."""
        H, W = img.shape
        scx = _F(2.0 / max(W - 1, 1))
        scy = _F(2.0 / max(H - 1, 1))
        sfx = _F(W - 1) / _F(2.0)
        sfy = _F(H - 1) / _F(2.0)
        maxx, maxy = _F(W - 1), _F(H - 1)
        h = (p - 1) // 2
        # the columns' taps and weights
        for j in range(p):
            x = ((posx + _F(j - h)) * scx - _F(1.0) + _F(1.0)) * sfx
            ix = np.floor(x)
            wxs[j, 0], wxs[j, 1], wxs[j, 2], wxs[j, 3] = _cubic(x - ix)
            for t in range(4):
                taps[j, t] = np.int64(_clamp(ix + _F(t - 1), _F(0.0), maxx))
        # the image rows the samples reach (row positions increase with i), each interpolated along x once
        y_first = ((posy + _F(-h)) * scy - _F(1.0) + _F(1.0)) * sfy
        y_last = ((posy + _F(p - 1 - h)) * scy - _F(1.0) + _F(1.0)) * sfy
        r0 = np.int64(_clamp(np.floor(y_first) - _F(1.0), _F(0.0), maxy))
        r1 = np.int64(_clamp(np.floor(y_last) + _F(2.0), _F(0.0), maxy))
        for r in range(r0, r1 + 1):
            row = img[r]
            hrow = hv[r - r0]
            for j in range(p):
                tp = taps[j]
                wx = wxs[j]
                hrow[j] = wx[0] * row[tp[0]] + wx[1] * row[tp[1]] + wx[2] * row[tp[2]] + wx[3] * row[tp[3]]
        for i in range(p):
            y = ((posy + _F(i - h)) * scy - _F(1.0) + _F(1.0)) * sfy
            iy = np.floor(y)
            wy0, wy1, wy2, wy3 = _cubic(y - iy)
            a0 = np.int64(_clamp(iy - _F(1.0), _F(0.0), maxy)) - r0
            a1 = np.int64(_clamp(iy, _F(0.0), maxy)) - r0
            a2 = np.int64(_clamp(iy + _F(1.0), _F(0.0), maxy)) - r0
            a3 = np.int64(_clamp(iy + _F(2.0), _F(0.0), maxy)) - r0
            h0, h1, h2, h3 = hv[a0], hv[a1], hv[a2], hv[a3]
            o = out[i]
            for j in range(p):
                o[j] = np.float64(wy0 * h0[j] + wy1 * h1[j] + wy2 * h2[j] + wy3 * h3[j])

    @_jit
    def _lk(src, dst, px, py, ex, ey, p, iters, eps32, eps, eb, tb, gxb, gyb, ib, hv, taps, wxs):
        """_matching._lk_refine (ZNCC) for one level-0 feature: the polished ``(x, y)`` and the template's sum of
        squared deviations (the same sum as :func:`_spread`'s).

        Scratch: ``eb (p + 2, p + 2)``, ``tb``, ``gxb``, ``gyb``, ``ib (p, p)``, all float64, and :func:`_sample`'s.
        """
        pix = _F(np.rint(px))
        piy = _F(np.rint(py))
        fx = px - pix
        fy = py - piy
        h = (p + 1) // 2
        _cut(src, np.int64(pix) - h, np.int64(piy) - h, p + 2, p + 2, eb)
        area = p * p
        st = sgx = sgy = 0.0
        for i in range(p):
            for j in range(p):
                tb[i, j] = eb[i + 1, j + 1]
                gxb[i, j] = 0.5 * (eb[i + 1, j + 2] - eb[i + 1, j])
                gyb[i, j] = 0.5 * (eb[i + 2, j + 1] - eb[i, j + 1])
                st += tb[i, j]
                sgx += gxb[i, j]
                sgy += gyb[i, j]
        # zero-mean template and gradients (gain/bias invariance of ZNCC), then the 2x2 normal matrix
        tm, gxm, gym = st / area, sgx / area, sgy / area
        tq = sxx = syy = sxy = 0.0
        for i in range(p):
            for j in range(p):
                t = tb[i, j] - tm
                tb[i, j] = t
                tq += t * t
                gx = gxb[i, j] - gxm
                gy = gyb[i, j] - gym
                gxb[i, j] = gx
                gyb[i, j] = gy
                sxx += gx * gx
                syy += gy * gy
                sxy += gx * gy
        t_std = np.sqrt(max(tq / area, eps))
        reg = 1e-3 * (sxx + syy) + eps
        det = max((sxx + reg) * (syy + reg) - sxy * sxy, eps)
        bx0 = ex - fx
        by0 = ey - fy
        posx, posy = bx0, by0
        for _ in range(iters):
            _sample(dst, posx, posy, p, ib, hv, taps, wxs)
            si = 0.0
            for i in range(p):
                for j in range(p):
                    si += ib[i, j]
            im = si / area
            iq = 0.0
            for i in range(p):
                for j in range(p):
                    v = ib[i, j] - im
                    ib[i, j] = v
                    iq += v * v
            gain = t_std / np.sqrt(max(iq / area, eps))
            bx = by = 0.0
            for i in range(p):
                for j in range(p):
                    r = tb[i, j] - ib[i, j] * gain
                    bx += gxb[i, j] * r
                    by += gyb[i, j] * r
            stx = _clamp(_F(((syy + reg) * bx - sxy * by) / det), _F(-0.5), _F(0.5))
            sty = _clamp(_F(((sxx + reg) * by - sxy * bx) / det), _F(-0.5), _F(0.5))
            posx = bx0 + _clamp(posx + stx - bx0, _F(-1.0), _F(1.0))
            posy = by0 + _clamp(posy + sty - by0, _F(-1.0), _F(1.0))
        return posx + fx, posy + fy, tq

    @_jit
    def _spread(src, px, py, p, tb):
        """Sum of squared deviations of the template at the rounded point (tracking._track_live's texture test)."""
        h = (p - 1) // 2
        m = _cut(src, np.int64(_F(np.rint(px))) - h, np.int64(_F(np.rint(py))) - h, p, p, tb) / (p * p)
        q = 0.0
        for i in range(p):
            for j in range(p):
                d = tb[i, j] - m
                q += d * d
        return q

    @_jit
    def _search(src, dst, levels, points, start, p, search, refine, box, eps32, polish, iters, floor, out_pos,
                out_best, out_edge, spread, order):
        """_matching._match_to_level0 of the features ``order`` (flat ``b * N + n`` indices): ``points (B, N, 2)`` of
        ``src`` (level-0 px) matched into ``dst`` from ``start`` over ``levels`` levels; writes their level-0
        positions, best costs and on-edge flags.

        ``polish``: 0 no more; 2: then _matching._lk_refine (``iters``) and the template's sum of squared deviations
        (the texture test, into ``spread``); 1: those only for a match that the torch path keeps (not on the edge,
        cost ``-best >= floor``), the others being searched again. The polish right after the search finds the
        feature's pixels still in the cache.
        """
        N = points.shape[1]
        radius = max(search, refine)
        tb = np.empty((p + 2, p + 2))
        wb = np.zeros((p + 2 * radius, p + 2 * radius + 8))
        cb = np.empty((2 * radius + 1) ** 2, np.float32)
        cc = np.empty((2 * radius + 1) ** 2 + 8)
        acc = np.empty((3, p + 2 * radius, 2 * radius + 1))
        eb = np.empty((p + 2, p + 2))
        gxb = np.empty((p, p))
        gyb = np.empty((p, p))
        ib = np.empty((p, p))
        hv = np.empty((2 * p + 8, p), np.float32)
        taps = np.empty((p, 4), np.int64)
        wxs = np.empty((p, 4), np.float32)
        eps = np.float64(eps32)
        for f in order:
            b, n = f // N, f % N
            px, py = points[b, n, 0], points[b, n, 1]
            x, y, best, edge = _to_level0(src, dst, b, levels, px, py, start[b, n, 0], start[b, n, 1], p, search,
                                          refine, box, eps32, eps, tb, wb, cb, cc, acc)
            out_best[b, n] = best
            out_edge[b, n] = edge
            if polish == 2 or (polish == 1 and not edge and not -best < floor):
                if iters > 0:
                    x, y, q = _lk(src[0][b], dst[0][b], px, py, x, y, p, iters, eps32, eps, eb, tb, gxb, gyb, ib, hv,
                                  taps, wxs)
                else:
                    q = _spread(src[0][b], px, py, p, tb)
                spread[b, n] = _F(q)
            out_pos[b, n, 0] = x
            out_pos[b, n, 1] = y


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


def _padded(count: int, n: int) -> int:
    """The slot count the torch path matches ``count`` features of ``n`` slots in (_matching._first_true)."""
    return min(n, -(-count // _SLOT_STEP) * _SLOT_STEP)


def _box_bits(n: int, pyramid: tuple[np.ndarray, ...], radii: list[int]) -> int:
    """Bit ``l`` set where the torch path's level-``l`` match of ``n`` features with ``radii[l]`` uses box sums."""
    bits = 0
    for level, radius in enumerate(radii):
        h, w = pyramid[level].shape[-2:]
        if n * (2 * radius + 1) ** 2 > 2 * h * w:
            bits |= 1 << level
    return bits


def _radii(levels: int, search: int, refine: int) -> list[int]:
    """Per-level radii of _matching._match_to_level0 over ``levels`` levels (level 0 first)."""
    return [search if level == levels - 1 else refine for level in range(levels)]


class _Runner:
    """Runs a kernel over a feature list on the worker threads (dealt out in turn: costly features are spread)."""

    def __init__(self, threads: int) -> None:
        self.threads = threads

    def __call__(self, kernel, mask: np.ndarray, *args) -> None:
        """``kernel(*args, order)`` for the features where ``mask (B, N)`` is True, in shares of at least
        ``_MIN_PER_THREAD``, a few per thread: a thread that starts late takes fewer (:meth:`Workers.map`)."""
        idx = np.flatnonzero(mask)
        parts = max(1, min(self.threads, math.ceil(len(idx) / _MIN_PER_THREAD)))
        count = 1 if parts == 1 else max(parts, min(SHARES_PER_THREAD * parts, len(idx) // _MIN_PER_THREAD))
        shares = [np.ascontiguousarray(idx[i::count]) for i in range(count)]
        Workers(parts).map(lambda share: kernel(*args, share), shares)


def track_compiled(
    pyr_prev: list[torch.Tensor],
    pyr_next: list[torch.Tensor],
    keypoints: torch.Tensor,
    weights: torch.Tensor,
    start: torch.Tensor,
    count: int,
    patch_size: int,
    search_radius: int,
    refine_radius: int,
    fb_check: bool,
    fb_threshold: float,
    min_score: float | None,
    min_texture: float,
    lk_iters: int,
    predicted_radius: int | None,
    fb_predicted: bool,
    fb_levels: int,
    threads: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`egorefine.features.tracking._track_live` (hard, ZNCC) on float32 CPU pyramids for every live slot.

    ``keypoints`` / ``start`` ``(B, N, 2)`` and ``weights`` ``(B, N)`` float32, ``count`` the largest number of
    live slots in a row; ``predicted_radius`` None for no search around ``start`` first; ``fb_levels`` the way
    back's levels (<= the pyramids'). Returns the :class:`egorefine.features.TrackOutput` fields as
    :func:`egorefine.features.track` returns them (empty slots unchanged, weight / score / fb_error 0 there).
    """
    levels = len(pyr_prev)
    prev = tuple(_np(p[:, 0]) for p in pyr_prev)
    nxt = tuple(_np(p[:, 0]) for p in pyr_next)
    kp, st = _np(keypoints), _np(start)
    weights = weights.detach()
    b, n = weights.shape
    live = weights.numpy() > 0
    eps32 = np.float32(1e-6)
    run = _Runner(thread_count(threads))
    # The torch path matches the live features in (B, M) subsets whose size decides, per level, whether the
    # window sums come from box maps (_matching._match_level): the sizes are repeated here for that choice.
    slots = n if count > n - _SLOT_STEP else _padded(count, n)
    pos = kp.copy()
    best = np.zeros((b, n), np.float32)
    edge = np.zeros((b, n), np.bool_)
    pred_r = 0 if predicted_radius is None or levels == 1 else int(predicted_radius)
    radii = _radii(levels, search_radius, refine_radius)
    found = np.zeros_like(live)
    spread = np.zeros((b, n), np.float32)
    # (the comparisons take python floats as float32, as torch does)
    floor = np.float32(-np.inf if min_score is None else min_score)
    polish = (lk_iters, floor, pos, best, edge, spread)
    if pred_r:
        # level 0 around the prediction (and the polish of what it finds), then the full search for the live
        # features it missed
        run(_search, live, prev, nxt, 1, kp, st, patch_size, pred_r, pred_r, _box_bits(slots, prev, [pred_r]), eps32,
            1, *polish)
        retry = live & (edge | (-best < floor))
        found = live & ~retry
        retries = int(retry.sum(axis=1).max())
        if retries:
            run(_search, retry, prev, nxt, levels, kp, st, patch_size, search_radius, refine_radius,
                _box_bits(_padded(retries, slots), prev, radii), eps32, 2, *polish)
    else:
        run(_search, live, prev, nxt, levels, kp, st, patch_size, search_radius, refine_radius,
            _box_bits(slots, prev, radii), eps32, 2, *polish)
    score = np.where(live, -best, np.float32(0.0))
    # tracking._track_live's tests, as there
    h, w = prev[0].shape[-2:]
    ok = live & ~edge & (spread >= np.float32(min_texture**2 * (patch_size * patch_size - 1)))
    if min_score is not None:
        ok &= score >= np.float32(min_score)
    x, y = pos[..., 0], pos[..., 1]
    ok &= (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1) & np.isfinite(pos).all(axis=-1)
    fb_error = torch.zeros_like(weights)
    if fb_check:
        back_ok = np.ones_like(ok)
        ways = [(ok & ~found, fb_levels, search_radius)]
        if fb_predicted:
            ways.append((ok & found, 1, refine_radius))
        for check, lv, radius in ways:
            todo = slots if slots <= _SLOT_STEP else int(check.sum(axis=1).max())
            if todo == 0:
                continue
            size = slots if todo > slots - _SLOT_STEP else _padded(todo, slots)
            back = np.zeros_like(kp)
            back_edge = np.zeros_like(edge)
            run(_search, check, nxt, prev, lv, pos, kp, patch_size, radius, refine_radius,
                _box_bits(size, nxt, _radii(lv, radius, refine_radius)), eps32, 0, 0, floor, back, best.copy(),
                back_edge, spread)
            # the round trip's error as the torch path measures it (torch's norm)
            err = torch.from_numpy(back).sub_(torch.from_numpy(kp)).norm(dim=-1)
            fb_error = torch.where(torch.from_numpy(check), err, fb_error)
            back_ok &= ~(back_edge & check)
        ok &= back_ok & (fb_error.numpy() <= np.float32(fb_threshold))
    # empty slots: pos kept the input keypoint, best (so score) is 0
    return torch.from_numpy(pos), weights * torch.from_numpy(ok).to(weights.dtype), torch.from_numpy(score), fb_error


def pyrdown(x: torch.Tensor) -> torch.Tensor:
    """``_pyramid._pyrdown`` of a float32 CPU image batch ``(B, 1, H, W)``, compiled (bit for bit: the same float32
    operations); a torch pass would wake torch's OpenMP threads to spin beside the tracker's kernels."""
    B, _, H, W = x.shape
    xn = x.detach()[:, 0].contiguous().numpy()
    out = np.empty((B, (H + 1) // 2, (W + 1) // 2), np.float32)
    _pyrdown(xn, out)
    return torch.from_numpy(out)[:, None]
