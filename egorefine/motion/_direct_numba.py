"""CPU inference path of the direct photometric refinement (egorefine.motion.direct) compiled with numba.

The torch path spends its time on operator launches: each residual evaluation is a few dozen small operations on
``(B, N)`` tensors (the warp, three ``grid_sample`` calls, the Jacobian's stacks), and the refinement runs some twenty
of them, plus the image-wide steps (blur, gradients, the depth-edge test, the per-cell ``topk``). Here every step of
:func:`egorefine.motion.refine_motion_direct` is a compiled loop, in the torch path's order:

* per image: the Gaussian blur (kornia's separable taps added in their order, borders repeated; where kornia's CPU
  path adds them by fused multiply-adds, at the image sizes its :func:`kornia.filters.gaussian_blur2d` takes that
  path for, so does the kernel), the tracker's pyramid (:func:`egorefine.features._track_numba._pyrdown`, bit for
  bit), and for the new image the central-difference gradients of each level (bit for bit: ``(b - a) / 2``),
  interleaved with the intensities so that a bilinear sample reads two cache lines;
* per previous image: the pixel choice of :func:`~egorefine.motion.direct._select_pixels` as a score map (gradient
  magnitude, the disparity's validity, its 5x5 spread by rows then columns) and one pass per cell that keeps the
  ``per_cell`` largest scores;
* per batch item: the inverse depths and rays of the pixels, the templates of every level, and the coarse-to-fine
  Levenberg-Marquardt loop. Each trial motion is evaluated in three loops (the warp of every pixel, branch-free; the
  bilinear samples of the pixels that land inside, packed; their residuals, weights, robust cost and Jacobian rows,
  branch-free), the 8x8 normal equations are float64 sums over the packed rows, the damped system is solved by
  Gaussian elimination, the increment mapped by the SE(3) exponential, and the step accepted or the damping raised
  as in the torch path. Then the costs before and after (the cost after is the finest level's last one: the same
  evaluation), the brightness model of the input motion and the status codes.

Agreement with the torch path. Blur, pyramid, gradients and the pixel choice's scores repeat the torch path's
float32 operations, so the candidates and their scores are the same; among exactly equal scores in one cell the
kernel takes the first in row order, where ``torch.topk`` leaves the order open. The warp, the bilinear samples
(border clamping as ``grid_sample(..., padding_mode="border", align_corners=True)``), the residuals, weights and
sums run in float64, so costs and motions differ from the float32 torch path by its rounding, and an accept/reject
decision between two nearly equal costs can go the other way and take another short path to the same minimum.
``tests/motion/test_direct_numba.py`` bounds the differences on rendered sequences.

Items with fewer usable pixels than ``min_pixels`` skip the iterations (the torch path runs them and then discards
the result). The two images of an item, and the items, are dealt out to :class:`egorefine.core._jit.Workers`
threads; the result does not depend on the thread count. ``AVAILABLE`` is False when numba cannot be imported;
:func:`refine_motion_direct` then takes its torch path, which stays the reference for GPU tensors, float64 and
autograd.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..core import eps_like
from ..core._jit import AVAILABLE, Workers, scratch, thread_count
from ..core._jit import jit as _jit
from ..geometry.se3 import _SMALL_ANGLE
from .robust import HUBER_K

__all__ = ["AVAILABLE", "refine_compiled"]

_F = np.float32
# kornia's gaussian_blur2d adds its taps by fused multiply-adds (its CPU slice path) from these sizes on
_SLICE_PIXELS = 256 * 256
_SLICE_NUMEL = 128 * 1024
# the half width of the depth-edge window (the torch path's 5x5 maximum and minimum)
_EDGE_RADIUS = 2


if AVAILABLE:
    from ..features._track_numba import _pyrdown
    from ._solve_numba import _se3_exp

    def _make_blur(fused: bool):
        """The separable blur kernel, with fused multiply-adds or without (kornia's two CPU paths round so). Each
        form gets its own name: numba's cache tells functions apart by qualified name and line, and two closures
        of one definition would otherwise load each other's compiled code."""

        def blur(src, k, pad, tmp, out):
            """gaussian_blur2d of ``src (H, W)`` float32 with the 1-D taps ``k`` along rows then columns, borders
            repeated, each tap's product added in tap order; ``pad (W + len(k) - 1,)`` and ``tmp (H, W)`` are work
            arrays."""
            H, W = src.shape
            taps = k.shape[0]
            r = taps // 2
            for y in range(H):
                row = src[y]
                for i in range(r):
                    pad[i] = row[0]
                    pad[r + W + i] = row[W - 1]
                for i in range(W):
                    pad[r + i] = row[i]
                o = tmp[y]
                k0 = k[0]
                for i in range(W):
                    o[i] = pad[i] * k0
                for t in range(1, taps):
                    kt = k[t]
                    for i in range(W):
                        o[i] = o[i] + pad[i + t] * kt
            for y in range(H):
                o = out[y]
                s = tmp[min(max(y - r, 0), H - 1)]
                k0 = k[0]
                for i in range(W):
                    o[i] = s[i] * k0
                for t in range(1, taps):
                    s = tmp[min(max(y - r + t, 0), H - 1)]
                    kt = k[t]
                    for i in range(W):
                        o[i] = o[i] + s[i] * kt

        blur.__name__ = blur.__qualname__ = "_blur_fused" if fused else "_blur_plain"
        return _jit(fastmath={"contract"} if fused else False)(blur)

    _blur_plain = _make_blur(False)
    _blur_fused = _make_blur(True)

    @_jit(error_model="numpy")
    def _magnitude(row, up, down, out):
        """The float32 ``hypot`` of kornia's central differences along one row (borders repeated)."""
        W = row.shape[0]
        half = _F(0.5)
        for x in range(W):
            lo, hi = max(x - 1, 0), min(x + 1, W - 1)
            gx = (row[hi] - row[lo]) * half
            gy = (down[x] - up[x]) * half
            out[x] = _F(math.sqrt(float(gx) * gx + float(gy) * gy))

    @_jit(error_model="numpy")
    def _interior_magnitude(row, up, down, out):
        """:func:`_magnitude` away from the row's ends (no clamped index: SIMD code), then its two ends."""
        W = row.shape[0]
        half = _F(0.5)
        for x in range(1, W - 1):
            gx = (row[x + 1] - row[x - 1]) * half
            gy = (down[x] - up[x]) * half
            out[x] = _F(math.sqrt(float(gx) * gx + float(gy) * gy))
        for x in (0, W - 1):
            lo, hi = max(x - 1, 0), min(x + 1, W - 1)
            gx = (row[hi] - row[lo]) * half
            gy = (down[x] - up[x]) * half
            out[x] = _F(math.sqrt(float(gx) * gx + float(gy) * gy))

    @_jit(error_model="numpy")
    def _scores(grey, disp, valid, has_valid, min_gradient, max_step, known, pad, rh, rl, score):
        """The pixel choice's score map ``(H, W)`` float32 (direct._select_pixels): the gradient magnitude (float32
        ``hypot`` of kornia's central differences) where the disparity is valid, no depth edge is near and the
        magnitude is at least ``min_gradient``, else -1.

        Depth edges as in the torch path: the 5x5 maximum and minimum of the valid disparities (invalid pixels
        stand in as -1e9 and 1e9, which never win beside a valid one), rows then columns, and their difference in
        float32 above ``max_step``. Simple loops over rows (SIMD code); ``known (H, W)`` bool, ``pad (W + 4,)``,
        ``rh``, ``rl`` ``(H, W)`` are work arrays."""
        H, W = grey.shape
        r = _EDGE_RADIUS
        low, high = _F(-1e9), _F(1e9)
        for y in range(H):
            d, ok = disp[y], known[y]
            for x in range(W):
                ok[x] = (d[x] > 0) & (d[x] < np.inf)
            if has_valid:
                v = valid[y]
                for x in range(W):
                    ok[x] = ok[x] & v[x]
            for k in range(2):  # the row's window maximum (rh), then its minimum (rl) as minus the maximum of minus
                sign, fill, o = (_F(1.0), low, rh[y]) if k == 0 else (_F(-1.0), high, rl[y])
                for x in range(r):
                    pad[x] = pad[W + r + x] = -np.inf
                for x in range(W):
                    pad[r + x] = sign * (d[x] if ok[x] else fill)
                for x in range(W):
                    m = pad[x]
                    for t in range(1, 2 * r + 1):
                        m = pad[x + t] if pad[x + t] > m else m
                    o[x] = sign * m
        for y in range(H):
            # the 5x5 window's rows (a row repeated at the borders changes neither extreme)
            rows = (max(y - 2, 0), max(y - 1, 0), y, min(y + 1, H - 1), min(y + 2, H - 1))
            a, b, c, d, e = rh[rows[0]], rh[rows[1]], rh[rows[2]], rh[rows[3]], rh[rows[4]]
            hi = pad[:W]
            for x in range(W):
                m = a[x]
                m = b[x] if b[x] > m else m
                m = c[x] if c[x] > m else m
                m = d[x] if d[x] > m else m
                hi[x] = e[x] if e[x] > m else m
            a, b, c, d, e = rl[rows[0]], rl[rows[1]], rl[rows[2]], rl[rows[3]], rl[rows[4]]
            out = score[y]
            for x in range(W):
                m = a[x]
                m = b[x] if b[x] < m else m
                m = c[x] if c[x] < m else m
                m = d[x] if d[x] < m else m
                m = e[x] if e[x] < m else m
                hi[x] = hi[x] - m  # the spread
            if W >= 3:
                _interior_magnitude(grey[y], grey[max(y - 1, 0)], grey[min(y + 1, H - 1)], out)
            else:
                _magnitude(grey[y], grey[max(y - 1, 0)], grey[min(y + 1, H - 1)], out)
            ok = known[y]
            for x in range(W):
                good = ok[x] & (out[x] >= min_gradient) & (hi[x] <= max_step)
                out[x] = out[x] if good else _F(-1.0)

    @_jit
    def _select(score, cell, per_cell, xy, usable):
        """direct._select_pixels for one item from :func:`_scores`: ``xy (N, 2)`` float32 and ``usable (N,)`` of the
        ``per_cell`` pixels of largest score per cell, cells in row order (``N = (H // cell) (W // cell) per_cell``).

        Chosen in descending score, the first in row order among equal ones (one pass per cell keeps the best so far
        in order). Slots without a usable pixel (score -1) take the cell's first pixels not kept (their positions
        are never used)."""
        H, W = score.shape
        hc, wc = H // cell, W // cell
        k = min(per_cell, cell * cell)
        top_s = np.empty(k, np.float32)
        top_i = np.empty(k, np.int64)
        n = 0
        for ci in range(hc):
            for cj in range(wc):
                m = 0  # pixels kept so far, in descending score
                bar = _F(-0.5)  # what a pixel must exceed to be kept: any score >= 0, then the last one kept
                for yy in range(cell):
                    row = score[ci * cell + yy, cj * cell:(cj + 1) * cell]
                    for xx in range(cell):
                        s = row[xx]
                        if not s > bar:
                            continue
                        j = min(m, k - 1)  # after every kept pixel of an equal or larger score
                        while j > 0 and top_s[j - 1] < s:
                            top_s[j], top_i[j] = top_s[j - 1], top_i[j - 1]
                            j -= 1
                        top_s[j], top_i[j] = s, yy * cell + xx
                        m = min(m + 1, k)
                        if m == k:
                            bar = top_s[k - 1]
                i = 0
                for j in range(k):
                    good = j < m
                    if good:
                        best = top_i[j]
                    else:  # the cell's next pixel not kept
                        while True:
                            kept = False
                            for q in range(m):
                                kept = kept or top_i[q] == i
                            if not kept:
                                break
                            i += 1
                        best = i
                        i += 1
                    xy[n, 0] = cj * cell + best % cell
                    xy[n, 1] = ci * cell + best // cell
                    usable[n] = good
                    n += 1

    @_jit(inline="always")
    def _corners(h, w, x, y):
        """The bilinear cell of ``(x, y)`` clamped to the image (``grid_sample``'s border padding, align_corners):
        ``(i00, i01, i10, i11, tx, ty)``, the four flat indices and the weights."""
        x = min(max(x, 0.0), w - 1.0)
        y = min(max(y, 0.0), h - 1.0)
        x0f, y0f = np.floor(x), np.floor(y)
        x0, y0 = int(x0f), int(y0f)
        x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
        return y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1, x - x0f, y - y0f

    @_jit(inline="always")
    def _blend(img, i00, i01, i10, i11, tx, ty):
        """Bilinear blend of the four samples of ``img`` (float64)."""
        top = img[i00] * (1.0 - tx) + img[i01] * tx
        bottom = img[i10] * (1.0 - tx) + img[i11] * tx
        return top * (1.0 - ty) + bottom * ty

    @_jit(error_model="numpy")
    def _project(M, rays, rho, usable, cam, h, w, front, P, ok):
        """The warp of direct._warp for every pixel: ``P (4, N)`` the moved point ``q`` (inverse-depth form) and
        ``1 / q_z``, ``ok (N,)`` usable, in front of the camera and inside the level's image (branch-free: SIMD
        code). ``rays (3, N)``; ``cam`` the level's ``fx, fy, cx, cy``."""
        r00, r01, r02, t0 = M[0, 0], M[0, 1], M[0, 2], M[0, 3]
        r10, r11, r12, t1 = M[1, 0], M[1, 1], M[1, 2], M[1, 3]
        r20, r21, r22, t2 = M[2, 0], M[2, 1], M[2, 2], M[2, 3]
        fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
        xmax, ymax = w - 1.0, h - 1.0
        X, Y, Z = rays[0], rays[1], rays[2]
        for i in range(X.shape[0]):
            x, y, z, p = X[i], Y[i], Z[i], rho[i]
            qx = r00 * x + r01 * y + r02 * z + t0 * p
            qy = r10 * x + r11 * y + r12 * z + t1 * p
            qz = r20 * x + r21 * y + r22 * z + t2 * p
            iz = 1.0 / qz
            u = fx * qx * iz + cx
            v = fy * qy * iz + cy
            ok[i] = usable[i] & (qz > front) & (u >= 0.0) & (u <= xmax) & (v >= 0.0) & (v <= ymax)  # (NaN: False)
            P[0, i], P[1, i], P[2, i], P[3, i] = qx, qy, qz, iz

    @_jit(error_model="numpy")
    def _gather(P, ok, rho, var_rho, tmpl, tex, h, w, cam, C):
        """The bilinear samples of the level's intensity and gradients (``tex``, interleaved, see :func:`_textures`)
        at the warped pixels that are ``ok``, with what the residuals need, packed into the first columns of ``C``
        (rows ``q_x, q_y, q_z, 1 / q_z, template, rho, var_rho, I, dI/dx, dI/dy``). Border clamping as
        ``grid_sample``'s (align_corners): a sample on the last row or column is that pixel's own. Returns the
        number of pixels packed."""
        fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
        m = 0
        for i in range(ok.shape[0]):
            if not ok[i]:
                continue
            qx, qy, iz = P[0, i], P[1, i], P[3, i]
            u = fx * qx * iz + cx
            v = fy * qy * iz + cy
            x0f, y0f = np.floor(u), np.floor(v)
            x0, y0 = int(x0f), int(y0f)
            tx, ty = u - x0f, v - y0f
            i00 = 3 * (y0 * w + x0)
            i01 = i00 + 3 * (x0 + 1 < w)
            i10 = i00 + 3 * w * (y0 + 1 < h)
            i11 = i10 + (i01 - i00)
            w00, w01 = (1.0 - tx) * (1.0 - ty), tx * (1.0 - ty)
            w10, w11 = (1.0 - tx) * ty, tx * ty
            C[0, m], C[1, m], C[2, m], C[3, m] = qx, qy, P[2, i], iz
            C[4, m], C[5, m], C[6, m] = tmpl[i], rho[i], var_rho[i]
            C[7, m] = w00 * tex[i00] + w01 * tex[i01] + w10 * tex[i10] + w11 * tex[i11]
            C[8, m] = w00 * tex[i00 + 1] + w01 * tex[i01 + 1] + w10 * tex[i10 + 1] + w11 * tex[i11 + 1]
            C[9, m] = w00 * tex[i00 + 2] + w01 * tex[i01 + 2] + w10 * tex[i10 + 2] + w11 * tex[i11 + 2]
            m += 1
        return m

    # No fast-math here: the costs decide whether a step is taken, so two evaluations of one motion (at two call
    # sites, inlined and optimised apart) must give the same bits, as the torch path's do.
    @_jit(error_model="numpy")
    def _terms(C, m, M, gain, offset, cam, sigma2, system):
        """direct._residuals, _weights and _cost of the ``m`` packed pixels of :func:`_gather`: returns the sum of
        their robust costs (each in row 18 of ``C``, added in order after the loop, which stays SIMD code); with
        ``system`` also writes the Jacobian's first six columns (rows 10-15; the seventh is ``-template``, the
        eighth -1), the residuals (row 16) and weights (row 17)."""
        t0, t1, t2 = M[0, 3], M[1, 3], M[2, 3]
        fx, fy = cam[0], cam[1]
        total = 0.0
        for k in range(m):
            qx, qy, qz, iz = C[0, k], C[1, k], C[2, k], C[3, k]
            ix, iy = C[8, k] * fx, C[9, k] * fy
            r = C[7, k] - (gain * C[4, k] + offset)
            # dI/dq through the projection's Jacobian, and the disparity's variance moved through dq/drho = t
            d0, d1 = ix * iz, iy * iz
            d2 = -(ix * qx + iy * qy) * iz * iz
            dr = d0 * t0 + d1 * t1 + d2 * t2
            inv_var = 1.0 / (sigma2 + dr * dr * C[6, k])
            s = abs(r) * math.sqrt(inv_var)
            C[18, k] = 0.5 * s * s if s <= HUBER_K else HUBER_K * (s - 0.5 * HUBER_K)
            if system:
                # J: [dI/dq rho, q x dI/dq, -template, -1] (a left-multiplied increment, translation first)
                p = C[5, k]
                C[10, k], C[11, k], C[12, k] = d0 * p, d1 * p, d2 * p
                C[13, k], C[14, k], C[15, k] = qy * d2 - qz * d1, qz * d0 - qx * d2, qx * d1 - qy * d0
                C[16, k] = r
                C[17, k] = HUBER_K / max(s, HUBER_K) * inv_var
        for k in range(m):
            total += C[18, k]
        return total

    @_jit
    def _evaluate(M, gain, offset, rays, rho, var_rho, usable, tmpl, tex, h, w, cam, sigma2, front, system, P, ok,
                  C):
        """The robust cost at motion ``M`` with brightness ``(gain, offset)`` on one level: ``(sum of the costs,
        number of usable pixels)``; with ``system`` the packed Jacobian, residuals and weights in ``C`` (for
        :func:`_normal` and the brightness fit)."""
        _project(M, rays, rho, usable, cam, h, w, front, P, ok)
        m = _gather(P, ok, rho, var_rho, tmpl, tex, h, w, cam, C)
        return _terms(C, m, M, gain, offset, cam, sigma2, system), m

    @_jit(fastmath={"reassoc", "contract", "nsz"})
    def _normal(C, m, H, g):
        """The normal equations of the ``m`` packed pixels of :func:`_terms`: the upper triangle of
        ``H = J^T W J`` and ``g = J^T W r`` (float64 sums in any order: SIMD code)."""
        w, r, t = C[17, :m], C[16, :m], C[4, :m]
        wr = C[18, :m]
        for k in range(m):
            wr[k] = w[k] * r[k]
        for a in range(7):
            Ja = C[10 + a, :m] if a < 6 else t  # (column 6 is -template: its sign comes below)
            sa = 1.0 if a < 6 else -1.0
            for b in range(a, 7):
                Jb = C[10 + b, :m] if b < 6 else t
                sb = 1.0 if b < 6 else -1.0
                acc = 0.0
                for k in range(m):
                    acc += Ja[k] * w[k] * Jb[k]
                H[a, b] = sa * sb * acc
            acc = acc2 = 0.0
            for k in range(m):
                acc += Ja[k] * w[k]
                acc2 += Ja[k] * wr[k]
            H[a, 7] = -sa * acc
            g[a] = sa * acc2
        acc = acc2 = 0.0
        for k in range(m):
            acc += w[k]
            acc2 += wr[k]
        H[7, 7] = acc
        g[7] = -acc2

    @_jit
    def _solve8(A, b, x):
        """``x = A^-1 b`` for the symmetric ``A`` (upper triangle given) by Gaussian elimination with partial
        pivoting; NaN where it breaks down (the caller then takes no step, as the torch path does)."""
        M = np.empty((8, 9))
        for r in range(8):
            for c in range(8):
                M[r, c] = A[r, c] if c >= r else A[c, r]
            M[r, 8] = b[r]
        for col in range(8):
            piv = col
            for r in range(col + 1, 8):
                if abs(M[r, col]) > abs(M[piv, col]):
                    piv = r
            if piv != col:
                for c in range(9):
                    M[col, c], M[piv, c] = M[piv, c], M[col, c]
            d = M[col, col]
            for r in range(col + 1, 8):
                f = M[r, col] / d
                for c in range(col, 9):
                    M[r, c] -= f * M[col, c]
        for r in range(7, -1, -1):
            v = M[r, 8]
            for c in range(r + 1, 8):
                v -= M[r, c] * x[c]
            x[r] = v / M[r, r]

    @_jit
    def _matmul4(A, B, out):
        for r in range(4):
            for c in range(4):
                out[r, c] = A[r, 0] * B[0, c] + A[r, 1] * B[1, c] + A[r, 2] * B[2, c] + A[r, 3] * B[3, c]

    @_jit(error_model="numpy")
    def _refine_item(prev_pyr, tex, shapes, xy, usable, disp, var, has_var, K, baseline, motion, iterations, sigma,
                     damping, eps, min_pixels, gain_lo, gain_hi, codes, M_out, out):
        """The rest of refine_motion_direct for one item, after the pixel choice: into ``M_out (4, 4)`` the result
        (float64) and into ``out`` ``(gain, offset, cost_before, cost_after, num_pixels, status)``.

        ``prev_pyr``: the levels of the blurred previous image, flat, level ``l`` at ``[shapes[l, 0],
        + shapes[l, 1] * shapes[l, 2])``; ``tex`` those of the new image with its gradients (:func:`_textures`, at
        three times the offsets); ``disp`` and ``var`` the full-resolution disparity and its variance as given;
        ``codes`` the status codes refined, cost rose, too few pixels, not finite, brightness."""
        L = shapes.shape[0]
        N = xy.shape[0]
        sigma2 = sigma * sigma
        front = math.sqrt(eps)
        # the pixels' inverse depths, their variances and rays K^-1 p (the chosen positions are pixel centres)
        fB = float(_F(K[0, 0] * baseline))
        rho = np.zeros(N)
        var_rho = np.zeros(N)
        rays = np.empty((3, N))
        k00, k01, k02, k11, k12, k22 = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2], K[2, 2]
        k10, k20, k21 = K[1, 0], K[2, 0], K[2, 1]
        det = (k00 * (k11 * k22 - k12 * k21) - k01 * (k10 * k22 - k12 * k20) + k02 * (k10 * k21 - k11 * k20))
        inv = np.empty((3, 3))
        inv[0, 0], inv[0, 1], inv[0, 2] = k11 * k22 - k12 * k21, k02 * k21 - k01 * k22, k01 * k12 - k02 * k11
        inv[1, 0], inv[1, 1], inv[1, 2] = k12 * k20 - k10 * k22, k00 * k22 - k02 * k20, k02 * k10 - k00 * k12
        inv[2, 0], inv[2, 1], inv[2, 2] = k10 * k21 - k11 * k20, k01 * k20 - k00 * k21, k00 * k11 - k01 * k10
        tmpl = np.zeros((L, N))
        for i in range(N):
            x, y = float(xy[i, 0]), float(xy[i, 1])
            for r in range(3):
                rays[r, i] = (inv[r, 0] * x + inv[r, 1] * y + inv[r, 2]) / det
            if not usable[i]:
                continue
            yi, xi = int(y), int(x)
            rho[i] = disp[yi, xi] / fB  # (a usable pixel's disparity is valid)
            if has_var:  # nan_to_num(nan=0, posinf=0).clamp(min=0): a non-finite variance counts as none
                v = var[yi, xi]
                var_rho[i] = max(v, 0.0) / (fB * fB) if np.isfinite(v) else 0.0
            for level in range(L):
                off, h, w = shapes[level, 0], shapes[level, 1], shapes[level, 2]
                s = 2.0**-level
                i00, i01, i10, i11, tx, ty = _corners(h, w, x * s, y * s)
                tmpl[level, i] = _blend(prev_pyr[off:off + h * w], i00, i01, i10, i11, tx, ty)
        cams = np.empty((L, 4))
        for level in range(L):
            s = 2.0**-level
            cams[level, 0], cams[level, 1] = K[0, 0] * s, K[1, 1] * s
            cams[level, 2], cams[level, 3] = K[0, 2] * s, K[1, 2] * s

        H, g = np.empty((8, 8)), np.empty(8)
        P, ok, C = np.empty((4, N)), np.empty(N, np.bool_), np.empty((19, N))
        M0 = np.empty((4, 4))
        for r in range(4):
            for c in range(4):
                M0[r, c] = motion[r, c]
        # the input's cost at the finest level, with its best brightness model (direct._best_brightness)
        h, w = shapes[0, 1], shapes[0, 2]
        tex0 = tex[:3 * h * w]
        _, m = _evaluate(M0, 1.0, 0.0, rays, rho, var_rho, usable, tmpl[0], tex0, h, w, cams[0], sigma2, front, True,
                         P, ok, C)
        weights, templates, values = C[17, :m], C[4, :m], C[7, :m]
        sw = st = sv = 0.0
        for k in range(m):
            sw += weights[k]
            st += weights[k] * templates[k]
            sv += weights[k] * values[k]
        sw = max(sw, eps)
        mt, mv = st / sw, sv / sw
        var_t = cov = 0.0
        for k in range(m):
            dt = templates[k] - mt
            var_t += weights[k] * dt * dt
            cov += weights[k] * dt * (values[k] - mv)
        var_t, cov = var_t / sw, cov / sw
        a = cov / max(var_t, eps) if var_t > eps else 1.0
        c = mv - a * mt
        total, n = _evaluate(M0, a, c, rays, rho, var_rho, usable, tmpl[0], tex0, h, w, cams[0], sigma2, front,
                             False, P, ok, C)
        cost_before = total / n if n > 0 else np.inf
        out[2], out[4] = cost_before, n
        M_out[:] = M0
        if n < min_pixels:  # the result would be discarded: no iterations
            out[0], out[1], out[3], out[5] = 1.0, 0.0, cost_before, codes[2]
            return

        # coarse to fine: Levenberg-Marquardt steps, each taken only where it lowers the cost
        cur, trial, E = M0.copy(), np.empty((4, 4)), np.empty((4, 4))
        A, step = np.empty((8, 8)), np.empty(8)
        lam = damping
        cost = cost_before
        for level in range(L - 1, -1, -1):
            off, h, w = shapes[level, 0], shapes[level, 1], shapes[level, 2]
            lv = tex[3 * off:3 * (off + h * w)]
            system = iterations > 0
            total, n = _evaluate(cur, a, c, rays, rho, var_rho, usable, tmpl[level], lv, h, w, cams[level], sigma2,
                                 front, system, P, ok, C)
            if system:
                _normal(C, n, H, g)
            cost = total / n if n > 0 else np.inf
            for it in range(iterations):
                for r in range(8):
                    for col in range(r, 8):
                        A[r, col] = H[r, col]
                    A[r, r] += lam * max(H[r, r], eps) + eps
                _solve8(A, g, step)
                finite = True
                for r in range(8):
                    finite = finite and np.isfinite(step[r])
                for r in range(8):
                    step[r] = -step[r] if finite else 0.0
                _se3_exp(step, 1.0, _SMALL_ANGLE**2, E)
                _matmul4(E, cur, trial)
                a_t, c_t = a + step[6], c + step[7]
                # the last step's system is never used (the next level starts afresh)
                system = it < iterations - 1
                total, n = _evaluate(trial, a_t, c_t, rays, rho, var_rho, usable, tmpl[level], lv, h, w,
                                     cams[level], sigma2, front, system, P, ok, C)
                cost_t = total / n if n > 0 else np.inf
                if cost_t < cost:
                    cur[:] = trial
                    a, c, cost = a_t, c_t, cost_t
                    if system:
                        _normal(C, n, H, g)
                    lam *= 0.5
                else:
                    lam *= 4.0
                lam = min(max(lam, damping * 1e-3), 1e6)

        # acceptance at the finest level: the cost of the current motion there is the last level's
        cost_after = cost
        finite = np.isfinite(cost_after) and np.isfinite(a)
        for r in range(4):
            for col in range(4):
                finite = finite and np.isfinite(cur[r, col])
        status = codes[0] if cost_after < cost_before else codes[1]
        if not (a >= gain_lo and a <= gain_hi):
            status = codes[4]
        if not finite:
            status = codes[3]
        if status == codes[0]:
            M_out[:] = cur
            out[0], out[1], out[3] = a, c, cost_after
        else:
            out[0], out[1], out[3] = 1.0, 0.0, cost_before
        out[5] = status

    @_jit
    def _pyramid(base, shapes, flat):
        """The levels of ``base (H, W)`` into ``flat`` (level 0 a copy, then the tracker's pyrdown)."""
        off, h, w = shapes[0, 0], shapes[0, 1], shapes[0, 2]
        flat[off:off + h * w] = base.reshape(-1)
        for level in range(1, shapes.shape[0]):
            o0, h0, w0 = shapes[level - 1, 0], shapes[level - 1, 1], shapes[level - 1, 2]
            o1, h1, w1 = shapes[level, 0], shapes[level, 1], shapes[level, 2]
            _pyrdown(flat[o0:o0 + h0 * w0].reshape(1, h0, w0), flat[o1:o1 + h1 * w1].reshape(1, h1, w1))

    @_jit
    def _textures(flat, shapes, tex):
        """Every level of a flat pyramid with kornia's ``spatial_gradient(mode="diff")`` (central differences
        halved, borders repeated: the same float32 values, halving is exact), interleaved per pixel into ``tex``
        ``(3 * len(flat),)``: intensity, d/dx, d/dy."""
        half = _F(0.5)
        for level in range(shapes.shape[0]):
            off, h, w = shapes[level, 0], shapes[level, 1], shapes[level, 2]
            img = flat[off:off + h * w].reshape(h, w)
            t = tex[3 * off:3 * (off + h * w)].reshape(h, w, 3)
            for y in range(h):
                row, up, down, o = img[y], img[max(y - 1, 0)], img[min(y + 1, h - 1)], t[y]
                for x in range(w):
                    o[x, 0] = row[x]
                    o[x, 1] = (row[min(x + 1, w - 1)] - row[max(x - 1, 0)]) * half
                    o[x, 2] = (down[x] - up[x]) * half


_KERNELS: dict[tuple[int, float], np.ndarray] = {}


def _blur_taps(size: int, sigma: float) -> np.ndarray:
    """kornia's 1-D Gaussian taps in float32, as gaussian_blur2d builds them for a float32 image."""
    key = (size, sigma)
    if key not in _KERNELS:
        from kornia.filters import get_gaussian_kernel1d

        _KERNELS[key] = get_gaussian_kernel1d(size, torch.tensor([[sigma]]))[0].numpy().astype(np.float32)
    return _KERNELS[key]


def refine_compiled(prev_grey: torch.Tensor, grey: torch.Tensor, disparity: torch.Tensor, valid: torch.Tensor | None,
                    variance: torch.Tensor | None, K: torch.Tensor, baseline: torch.Tensor, motion: torch.Tensor,
                    levels: int, iterations: int, cell: int, per_cell: int, sigma: float, min_gradient: float,
                    min_pixels: int, damping: float, blur: float, max_step: float, threads: int | None = None
                    ) -> tuple[torch.Tensor, ...]:
    """refine_motion_direct on float32 CPU tensors (the caller has checked shapes and arguments).

    Args:
        prev_grey, grey: ``(B, 1, H, W)`` grey images, not yet blurred.
        disparity: ``(B, 1, H, W)`` ``prev_disparity`` as given; ``valid``: ``(B, 1, H, W)`` ``prev_valid`` or None;
        variance: ``(B, 1, H, W)`` ``prev_variance`` or None.
        K, baseline, motion: ``(B, 3, 3)``, ``(B,)``, ``(B, 4, 4)``.
        levels ... max_step: refine_motion_direct's settings.
        threads: worker threads for the per-image steps and the items (default ``torch.get_num_threads()``).

    Returns:
        ``(motion, status, gain, offset, cost_before, cost_after, num_pixels)`` as :class:`DirectMotion` holds them.
    """
    from .direct import _GAIN_RANGE, DIRECT_STATUS

    b, _, h, w = prev_grey.shape
    threads = thread_count(threads)
    images = (prev_grey.detach()[:, 0].contiguous().numpy(), grey.detach()[:, 0].contiguous().numpy())
    disp = disparity.detach()[:, 0].contiguous().numpy()
    has_valid = valid is not None
    valid_n = valid.detach()[:, 0].bool().contiguous().numpy() if has_valid else np.ones((b, 1, 1), np.bool_)
    has_var = variance is not None
    var_n = variance.detach()[:, 0].contiguous().numpy() if has_var else np.zeros((b, 1, 1), np.float32)
    Kn = K.detach().numpy().astype(np.float64)
    bn = baseline.detach().numpy()
    Mn = motion.detach().numpy().astype(np.float64)

    sizes = [(h, w)]
    for _ in range(levels - 1):
        sizes.append(((sizes[-1][0] + 1) // 2, (sizes[-1][1] + 1) // 2))
    offsets = np.cumsum([0] + [y * x for y, x in sizes])
    shapes = np.array([(offsets[i], y, x) for i, (y, x) in enumerate(sizes)], np.int64)
    total = int(offsets[-1])
    n = (h // cell) * (w // cell) * min(per_cell, cell * cell)
    def get(name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
        return scratch("direct." + name, shape, dtype)

    pyrs, tex = get("pyrs", (b, 2, total), np.float32), get("tex", (b, 3 * total), np.float32)
    xy, usable = get("xy", (b, n, 2), np.float32), get("usable", (b, n), np.bool_)
    blurred, tmp = get("blurred", (b, 2, h, w), np.float32), get("tmp", (b, 2, h, w), np.float32)
    maps, known = get("maps", (b, 3, h, w), np.float32), get("known", (b, h, w), np.bool_)
    blur_fn, taps = None, None
    if blur > 0:
        taps = _blur_taps(2 * int(math.ceil(2 * blur)) + 1, float(blur))
        fused = h * w >= _SLICE_PIXELS and b * h * w >= _SLICE_NUMEL
        blur_fn = _blur_fused if fused else _blur_plain

    def prepare(task: tuple[int, int]) -> None:
        i, k = task  # k 0: the previous image (blur, pixel choice, pyramid), 1: the new one (blur, pyramid, texture)
        src = images[k][i]
        if blur_fn is not None:
            blur_fn(src, taps, np.empty(w + taps.shape[0] - 1, np.float32), tmp[i, k], blurred[i, k])
            src = blurred[i, k]
        _pyramid(src, shapes, pyrs[i, k])
        if k == 0:
            _scores(src, disp[i], valid_n[i], has_valid, _F(min_gradient), _F(max_step), known[i],
                    np.empty(w + 2 * _EDGE_RADIUS, np.float32), maps[i, 0], maps[i, 1], maps[i, 2])
            _select(maps[i, 2], cell, per_cell, xy[i], usable[i])
        else:
            _textures(pyrs[i, 1], shapes, tex[i])

    work = Workers(threads)
    work.map(prepare, [(i, k) for i in range(b) for k in (0, 1)])
    M_out = np.empty((b, 4, 4))
    out = np.empty((b, 6))
    codes = np.array([DIRECT_STATUS[k] for k in ("refined", "cost rose", "too few pixels", "not finite",
                                                 "brightness")], np.int64)
    eps = eps_like(prev_grey)

    def item(i: int) -> None:
        _refine_item(pyrs[i, 0], tex[i], shapes, xy[i], usable[i], disp[i], var_n[i], has_var, Kn[i], float(bn[i]),
                     Mn[i], iterations, float(sigma), float(damping), eps, min_pixels, _GAIN_RANGE[0],
                     _GAIN_RANGE[1], codes, M_out[i], out[i])

    work.map(item, range(b))
    status = torch.from_numpy(out[:, 5].astype(np.int64))
    keep = status == DIRECT_STATUS["refined"]
    result = torch.where(keep[:, None, None], torch.from_numpy(M_out).to(motion.dtype), motion)
    f32 = torch.from_numpy(out[:, :4].T.astype(np.float32))
    return result, status, f32[0], f32[1], f32[2], f32[3], torch.from_numpy(out[:, 4].astype(np.int64))
