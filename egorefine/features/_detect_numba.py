"""CPU inference path of :func:`egorefine.features.detect` (Shi-Tomasi response), compiled with numba.

The torch path is some forty full-image operator launches: kornia's Sobel gradients, three 7x7
Gaussian blurs of the structure tensor, the smaller eigenvalue, a 7x7 max filter, the thresholds,
a padded copy of the score map cut into grid cells and a top-k within every cell, then the
round-robin top-k and the sub-pixel step on gathered windows. Here one pass over each band of rows
computes the response (:func:`_response_rows`: a ring of seven horizontally blurred rows of
gradient products, the vertical blur and the eigenvalue while the row is in cache), a second pass
keeps the local maxima (:func:`_nms_rows`), the bucketing works on the candidate list only (a few
thousand pixels, not the map: :func:`_select`) and the sub-pixel step runs over the keypoints in
vector loops (:func:`_refine`). Bands and keypoints are dealt to :class:`egorefine.core._jit.Workers`
threads; the result does not depend on their number.

Agreement with the torch path: the same float32 formulas, summed in their natural order, with
``np.sqrt`` / ``np.exp`` (the sub-pixel step's Gaussian weight as the product of its x and y
factors); torch sums in other orders and takes MKL's sqrt/exp, so values agree to float rounding,
not bit for bit: the response differs from kornia's ``gftt_response`` by float32 rounding of its
peak, refined positions of the same corner by more (the corner point is solved from sums of
absolute pixel coordinates, whose float32 spacing grows with the image's width). The selection rule is the
torch path's: candidates ranked in their cell by response, then taken round-robin (the torch path's
key ``strength - rank``, descending). Exact ties, which the torch path leaves in ``torch.topk``'s
order, go here by pixel index (row-major, ascending): deterministic, and a batch item gives what
it gives alone. Rounding can swap two nearly equal candidates or move one across a threshold;
``tests/features/test_detect_numba.py`` bounds how often and by how much, and the agreement and
timings measured on the rendered rigs are in docs/decisions.md.

``AVAILABLE`` is False when numba cannot be imported; :func:`egorefine.features.detect` then takes
the torch path, which stays the reference for GPU tensors, autograd, float64 and Harris.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..core._jit import AVAILABLE, Workers, scratch, thread_count
from ..core._jit import bands as _bands
from ..core._jit import jit as _jit
from ._peaks import _subpixel_offsets

__all__ = ["AVAILABLE", "detect_compiled", "usable_compiled"]

_F = np.float32
# rows per band below which one thread does all (a hand-off to a pool thread costs tens of microseconds)
_MIN_BAND_ROWS = 48
# keypoints per thread below which one thread refines all
_MIN_PER_THREAD = 256


if AVAILABLE:

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
        """kornia's normalised Sobel ``(dx, dy)`` of one pixel from its 3x3 neighbours (row ``a`` above, ``c``
        below; ``0, 1, 2`` left to right)."""
        e = _F(0.125)
        gx = ((a2 - a0) + _F(2.0) * (b2 - b0) + (c2 - c0)) * e
        gy = ((c0 - a0) + _F(2.0) * (c1 - a1) + (c2 - a2)) * e
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

    @_jit(inline="always")
    def _taps7(r0, r1, r2, r3, r4, r5, r6, k0, k1, k2, k3, k4, k5, k6, x):
        """``sum_t r_t[x] k_t`` over the 7 taps."""
        return r0[x] * k0 + r1[x] * k1 + r2[x] * k2 + r3[x] * k3 + r4[x] * k4 + r5[x] * k5 + r6[x] * k6

    @_jit
    def _hblur(p, k, out):
        """``out[x] = sum_t p[x + t] k[t]``: the horizontal 7-tap blur of a padded row."""
        W = out.shape[0]
        k0, k1, k2, k3, k4, k5, k6 = k[0], k[1], k[2], k[3], k[4], k[5], k[6]
        p0, p1, p2, p3 = p[0:W], p[1:W + 1], p[2:W + 2], p[3:W + 3]
        p4, p5, p6 = p[4:W + 4], p[5:W + 5], p[6:W + 6]
        for x in range(W):
            out[x] = _taps7(p0, p1, p2, p3, p4, p5, p6, k0, k1, k2, k3, k4, k5, k6, x)

    @_jit
    def _vblur_response(ring, base, k, out):
        """The vertical blur of the ring's seven rows (``base`` the slot of the top one) of each product, then
        kornia's smaller eigenvalue ``(tr - sqrt((a - c)^2 + 4 b^2)) / 2`` of the blurred tensor."""
        k0, k1, k2, k3, k4, k5, k6 = k[0], k[1], k[2], k[3], k[4], k[5], k[6]
        s0, s1, s2, s3 = base % 7, (base + 1) % 7, (base + 2) % 7, (base + 3) % 7
        s4, s5, s6 = (base + 4) % 7, (base + 5) % 7, (base + 6) % 7
        xx, yy, xy = ring[0], ring[1], ring[2]
        a0, a1, a2, a3, a4, a5, a6 = xx[s0], xx[s1], xx[s2], xx[s3], xx[s4], xx[s5], xx[s6]
        c0, c1, c2, c3, c4, c5, c6 = yy[s0], yy[s1], yy[s2], yy[s3], yy[s4], yy[s5], yy[s6]
        b0, b1, b2, b3, b4, b5, b6 = xy[s0], xy[s1], xy[s2], xy[s3], xy[s4], xy[s5], xy[s6]
        for x in range(out.shape[0]):
            a = _taps7(a0, a1, a2, a3, a4, a5, a6, k0, k1, k2, k3, k4, k5, k6, x)
            c = _taps7(c0, c1, c2, c3, c4, c5, c6, k0, k1, k2, k3, k4, k5, k6, x)
            b = _taps7(b0, b1, b2, b3, b4, b5, b6, k0, k1, k2, k3, k4, k5, k6, x)
            d = a - c
            out[x] = _F(0.5) * ((a + c) - np.sqrt(d * d + _F(4.0) * b * b))

    @_jit
    def _response_rows(img, y0, y1, k, resp):
        """``resp[y] = gftt_response(img)[y]`` (to rounding) for rows ``[y0, y1)`` of one ``(H, W)`` float32
        image (H, W >= 4).

        Rows ``y0 - 3 .. y1 + 2`` (mirrored at the image's edges) are blurred along x into a ring of seven rows
        per product; each output row then takes its seven rows of the ring."""
        H, W = img.shape
        ring = np.empty((3, 7, W), np.float32)
        pxx = np.empty(W + 6, np.float32)
        pyy = np.empty(W + 6, np.float32)
        pxy = np.empty(W + 6, np.float32)
        for j in range(y0 - 3, y1 + 3):
            r = _reflect(j, H)
            _products(img[max(r - 1, 0)], img[r], img[min(r + 1, H - 1)], pxx, pyy, pxy)
            s = (j - y0 + 3) % 7
            _hblur(pxx, k, ring[0, s])
            _hblur(pyy, k, ring[1, s])
            _hblur(pxy, k, ring[2, s])
            y = j - 3
            if y >= y0:
                _vblur_response(ring, (y - y0) % 7, k, resp[y])

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
    def _group(label, count):
        """Stable counting sort: the indices of ``label`` (values ``0 .. count - 1``) grouped by label, ascending
        within a group, and ``per`` with group ``g`` at ``order[per[g]:per[g + 1]]``."""
        per = np.zeros(count + 1, np.int64)
        for g in label:
            per[g + 1] += 1
        for g in range(count):
            per[g + 1] += per[g]
        start = per[:count].copy()
        order = np.empty(label.shape[0], np.int64)
        for i in range(label.shape[0]):
            order[start[label[i]]] = i
            start[label[i]] += 1
        return order, per

    @_jit
    def _sort_desc(o, s):
        """Sorts the indices ``o`` in place by ``s[o]``, descending and stable (insertion sort for short runs)."""
        if o.shape[0] > 64:
            o[:] = o[np.argsort(-s[o], kind="mergesort")]
            return
        for i in range(1, o.shape[0]):
            v = o[i]
            j = i
            while j > 0 and s[o[j - 1]] < s[v]:
                o[j] = o[j - 1]
                j -= 1
            o[j] = v

    @_jit
    def _select(idx, val, thr, peak, W, ch, cw, gx, ncell, kc, ix, iy):
        """detection._detect's bucketing for one image on its candidates ``idx``/``val`` (raster order): those at
        or above ``thr``, ranked in their grid cell by strength ``0.5 val / peak``, then taken round-robin: every
        cell's best, then every cell's second best, ... (the torch path's key ``strength - rank``, descending),
        each round by strength; at most ``kc`` per cell. Equal strengths go by pixel index, ascending (the groups
        are built in raster order and sorted stably). Writes the chosen pixels to ``ix``/``iy`` (as many as fit)
        and returns how many."""
        keep = np.flatnonzero(val >= thr)
        flat = idx[keep]
        strength = _F(0.5) * val[keep] / peak
        order, per = _group((flat // W) // ch * gx + (flat % W) // cw, ncell)
        rank = np.empty(flat.shape[0], np.int64)
        for c in range(ncell):
            o = order[per[c]:per[c + 1]]
            _sort_desc(o, strength)
            for r in range(o.shape[0]):
                rank[o[r]] = min(r, kc)  # kc: not taken
        order, per = _group(rank, kc + 1)
        filled = 0
        for r in range(kc):
            o = order[per[r]:per[r + 1]]
            _sort_desc(o, strength)
            for j in o:
                if filled == ix.shape[0]:
                    return filled
                iy[filled] = flat[j] // W
                ix[filled] = flat[j] % W
                filled += 1
        return filled

    @_jit
    def _refine(img, ix, iy, lo, hi, kx, ky):
        """detection._gradient_offsets (radius 3, two passes) for the keypoints ``[lo, hi)`` of one image:
        Foerstner's corner point over the 7x7 window, re-centred once; writes ``base + offset`` to ``kx``/``ky``.
        Arrays run over the keypoints (the window pixel outermost) so that every step but the window gather is a
        vector loop. The Gaussian weight ``exp(-(qx^2 + qy^2) / 2 sigma^2)`` is taken as the product of its x and
        y factors: 14 exponentials per keypoint instead of 49 (equal to rounding)."""
        H, W = img.shape
        radius = 3
        size = 7
        S = size + 2
        n = hi - lo
        patch = np.empty((S * S, n), np.float32)
        pxs = np.empty((size, n), np.float32)
        pys = np.empty((size, n), np.float32)
        wx = np.empty((size, n), np.float32)
        wy = np.empty((size, n), np.float32)
        ex = np.empty(n, np.float32)
        ey = np.empty(n, np.float32)
        sums = np.empty((5, n), np.float32)
        xs = np.empty(S, np.int64)
        ys = np.empty(S, np.int64)
        sigma = 0.6 * radius
        div = _F(2 * (sigma * sigma))
        lim = _F(1.5)
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
            for s in range(size):
                for i in range(n):
                    qx = pxs[s, i] - ex[i]
                    qy = pys[s, i] - ey[i]
                    wx[s, i] = np.exp(-(qx * qx) / div)
                    wy[s, i] = np.exp(-(qy * qy) / div)
            sums[:] = 0
            s0, s1, s2, s3, s4 = sums[0], sums[1], sums[2], sums[3], sums[4]
            for a in range(size):
                py, fy = pys[a], wy[a]
                for c in range(size):
                    u0, u1, u2 = patch[a * S + c], patch[a * S + c + 1], patch[a * S + c + 2]
                    m0, m2 = patch[(a + 1) * S + c], patch[(a + 1) * S + c + 2]
                    d0, d1, d2 = patch[(a + 2) * S + c], patch[(a + 2) * S + c + 1], patch[(a + 2) * S + c + 2]
                    px, fx = pxs[c], wx[c]
                    for i in range(n):
                        g1, g2 = _sobel(u0[i], u1[i], u2[i], m0[i], m2[i], d0[i], d1[i], d2[i])
                        w = fy[i] * fx[i]
                        s0[i] += w * g1 * g1
                        s1[i] += w * g1 * g2
                        s2[i] += w * g2 * g2
                        s3[i] += w * (g1 * g1 * px[i] + g1 * g2 * py[i])
                        s4[i] += w * (g1 * g2 * px[i] + g2 * g2 * py[i])
            for i in range(n):
                fxx, fxy, fyy, fx_, fy_ = s0[i], s1[i], s2[i], s3[i], s4[i]
                det = fxx * fyy - fxy * fxy
                tr = fxx + fyy
                if det > _F(1e-3) * (tr * tr) + _F(1e-6):  # eps_like(float32), as the torch path
                    bx = _F(ix[lo + i])
                    by = _F(iy[lo + i])
                    qx = (fyy * fx_ - fxy * fy_) / det
                    qy = (fxx * fy_ - fxy * fx_) / det
                    ex[i] = bx + min(max(qx - bx, -lim), lim)
                    ey[i] = by + min(max(qy - by, -lim), lim)
        for i in range(n):
            kx[lo + i] = ex[i]
            ky[lo + i] = ey[i]

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


_KERNEL: list[np.ndarray] = []


def _gauss7() -> np.ndarray:
    """kornia's 7-tap Gaussian (sigma 1) in float32, as gaussian_blur2d builds it for the structure tensor."""
    if not _KERNEL:
        from kornia.filters import get_gaussian_kernel1d

        _KERNEL.append(get_gaussian_kernel1d(7, 1.0, dtype=torch.float32)[0].numpy().astype(np.float32))
    return _KERNEL[0]


def _run(fn, tasks: list, threads: int) -> list:
    """``[fn(*task) for task in tasks]``, shared by the calling thread and the pool (:meth:`Workers.map`)."""
    return Workers(threads).map(lambda task: fn(*task), tasks)


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

    Returns keypoints ``(B, n, 2)`` and weights ``(B, n)`` as :func:`egorefine.features.detect` does (the caller
    has checked the image's values).
    """
    b, _, h, w = grey.shape
    threads = thread_count(threads)
    img = grey.detach()[:, 0].contiguous().numpy()
    pixels = b * h * w  # (per-thread buffers, kept across calls)
    resp, idx, val = (scratch("detect.response", (b, h, w), np.float32),
                      scratch("detect.index", (pixels,), np.int64), scratch("detect.value", (pixels,), np.float32))
    k = _gauss7()
    rows = _bands(h, max(1, min(threads, h // _MIN_BAND_ROWS)))
    _run(_response_rows, [(img[i], y0, y1, k, resp[i]) for i in range(b) for y0, y1 in rows], threads)
    tasks = [(resp[i], y0, y1, nms_radius, border, _F(min_response), idx[i * h * w + y0 * w:],
              val[i * h * w + y0 * w:]) for i in range(b) for y0, y1 in rows]
    found = _run(_nms_rows, tasks, threads)
    gy, gx = grid
    ch, cw = math.ceil(h / gy), math.ceil(w / gx)
    ix = np.zeros((b, n), np.int64)
    iy = np.zeros((b, n), np.int64)
    filled = []
    for i in range(b):
        parts = found[i * len(rows):(i + 1) * len(rows)]
        peak = _F(max(p for _, p in parts))
        thr = max(peak * _F(quality), _F(min_response))  # the torch path's thresholds, in float32
        starts = [i * h * w + y0 * w for y0, _ in rows]
        cidx = np.concatenate([idx[s:s + c] for s, (c, _) in zip(starts, parts, strict=True)])
        cval = np.concatenate([val[s:s + c] for s, (c, _) in zip(starts, parts, strict=True)])
        filled.append(_select(cidx, cval, thr, max(peak, _F(1e-6)), w, ch, cw, gx, gy * gx, min(ch * cw, n),
                              ix[i], iy[i]))
    kx = ix.astype(np.float32)
    ky = iy.astype(np.float32)
    if subpixel == "gradient":
        tasks = [(img[i], ix[i], iy[i], lo, hi, kx[i], ky[i])
                 for i in range(b) if filled[i]
                 for lo, hi in _bands(filled[i], max(1, min(threads, filled[i] // _MIN_PER_THREAD)))]
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
