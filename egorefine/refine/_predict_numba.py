"""CPU inference path of the hard splat and of crack closing, compiled with numba.

:func:`egorefine.refine.predict_disparity` in hard mode with refinement is about 30 small torch
passes over the image (moving the points, an ``amax`` scatter, the 3x3 z-buffer maximum, the
gathered check, the refinement's four gathered corners, hole filling), each one reading and
writing full-size maps, the largest part of the refiner's loop on the CPU. Every target pixel's work
depends only on its own values and a few gathered
ones, so here it is three loops:

1. (row bands on threads) move every source point (PAPER.md eq. 1 in inverse-depth form), write the
   padded source maps and each point's z-buffer cell and key; then (one thread) the scatter;
2. (row bands on threads) per target pixel: the 3x3 z-buffer maximum, the candidate, the check in
   frame ``t-1``, the start value and the inverse-warp refinement steps;
3. (row bands on threads) the background hole fill and the outputs.

Step 2 works a row at a time and splits each stage into loops that only compute (LLVM turns them
into SIMD code) and loops that only gather (which would keep a loop scalar), several times faster than
one loop per pixel (timings in docs/decisions.md).

They repeat the torch path's float32 formulas in the same order (see :mod:`egorefine.refine.predict`
for what each step means), so the decisions agree with it; values may differ in the last bits
where torch's vectorised kernels fuse a multiply and an add (``lerp``, ``addcmul``): tests compare
the two paths on rendered sequences. :func:`close_cracks` does the inverse-warp look-ups
of :func:`egorefine.refine.close_cracks` for the hole pixels in one loop (:func:`finish_prediction` the same in
place, with the refiner's search-range check after it), and :func:`edge_variance`
the window spreads of :func:`egorefine.refine.correct.edge_variance` in one pass (bit for bit), and
:func:`expected_positions` the refiner's constant-velocity guess of where its features land (one loop
instead of some forty torch ops on a few hundred points, whose launches cost more than their arithmetic).

Used for float32 CPU tensors that need no gradient when numba is installed (``AVAILABLE``); the
torch path stays the reference for GPU tensors, float64 and autograd.
"""

from __future__ import annotations

import threading

import numpy as np
import torch

from ..core._jit import AVAILABLE, Workers
from ..core._jit import bands as _bands
from ..core._jit import jit as _jit

__all__ = ["AVAILABLE", "hard_splat", "close_cracks", "finish_prediction", "edge_variance", "expected_positions"]

_F = np.float32
# the constants of egorefine.refine.predict, as float32
_MIN = _F(1e-3)  # _MIN_DEPTH_RATIO
_BIG = _F(min(1e30, float(np.finfo(np.float32).max) ** 0.5))  # _big(float32)
_PAD = 2  # margin of the padded source layout (_splat._PAD)


if AVAILABLE:

    @_jit(inline="always")
    def _lerp(start, end, weight):
        """torch.lerp's formula (exact at weights 0 and 1); both branches computed, one selected (no jump)."""
        low = start + weight * (end - start)
        high = end - (end - start) * (_F(1.0) - weight)
        return low if abs(weight) < _F(0.5) else high

    @_jit
    def _move_sources(d, valid, has_valid, var, has_var, A, a, y0, y1, key_src, key_new, var_p, at, keys):
        """Step 1 for source rows ``y0:y1`` of one batch item: move the points (eq. 1), write the padded source
        maps (``-big`` where invalid), each point's z-buffer cell ``at`` and key (-1: none). Returns the number of
        non-finite disparities (the caller raises: checked here rather than by a torch pass over the map)."""
        H, W = d.shape
        wp = key_src.shape[1]
        bits = np.empty(W, np.float32)  # d' written here is read back as int32: its z-buffer key
        as_int = bits.view(np.int32)
        bad = 0
        for y in range(y0, y1):
            yf = _F(y)
            for x in range(W):
                xf = _F(x)
                dv = d[y, x]
                bad += not np.isfinite(dv)
                pz = ((A[2, 0] * xf + A[2, 2]) + A[2, 1] * yf) + dv * a[2]
                ok = (dv >= 0) & (pz > _MIN)
                if has_valid:
                    ok = ok & valid[y, x]
                inv = _F(1.0) / max(pz, _MIN)
                d_new = dv * inv
                if has_var:
                    var_p[y + _PAD, x + _PAD] = var[y, x] * inv * inv
                key_src[y + _PAD, x + _PAD] = dv if ok else -_BIG
                key_new[y + _PAD, x + _PAD] = d_new if ok else -_BIG
                tx = np.rint((((A[0, 0] * xf + A[0, 2]) + A[0, 1] * yf) + dv * a[0]) * inv)
                ty = np.rint((((A[1, 0] * xf + A[1, 2]) + A[1, 1] * yf) + dv * a[1]) * inv)
                tx = min(max(tx, _F(-_PAD)), _F(W + 1))
                ty = min(max(ty, _F(-_PAD)), _F(H + 1))
                at[y, x] = (np.int32(ty) + _PAD) * wp + np.int32(tx) + _PAD
                bits[x] = d_new
            for x in range(W):
                # the bits of d' >= 0 as int32 order like the values: the maximum key is the nearest surface
                keys[y, x] = as_int[x] if key_new[y + _PAD, x + _PAD] >= 0 else -1
        if has_var:  # replicated margins: a target just outside takes the border's variance
            for y in range(y0 + _PAD, y1 + _PAD):
                for x in range(_PAD):
                    var_p[y, x] = var_p[y, _PAD]
                for x in range(_PAD + W, wp):
                    var_p[y, x] = var_p[y, _PAD + W - 1]
        return bad

    @_jit
    def _scatter(at, keys, zbuf, var_p, has_var):
        """Step 1, sequential part: the z-buffer keeps each cell's largest key; the variance's margin rows."""
        H, W = at.shape
        flat = zbuf.reshape(-1)
        for y in range(H):
            for x in range(W):
                key, cell = keys[y, x], at[y, x]
                if key > flat[cell]:
                    flat[cell] = key
        if has_var:
            for y in range(_PAD):
                var_p[y, :] = var_p[_PAD, :]
            for y in range(_PAD + H, var_p.shape[0]):
                var_p[y, :] = var_p[_PAD + H - 1, :]

    @_jit
    def _targets(zbuf, zval, key_src, key_new, var_p, has_var, A, a, G, e, tol, iterations, y0, y1,
                 est_out, var_out, landed_out, fill_holes, process_noise, hole_variance, later,
                 disparity, variance, confidence):
        """Steps 2 and 3 for target rows ``y0:y1`` of one batch item; returns the smallest landed value (+big:
        none). A row without a landed pixel is filled later, from the whole image (marked in ``later``).

        A row at a time, each stage split into loops without gathers (compiled to SIMD code) and loops that only
        gather: with the gathers inside, the loop stays scalar and several times slower.
        """
        H, W = est_out.shape
        wp = key_src.shape[1]
        src_flat, new_flat, var_flat = key_src.reshape(-1), key_new.reshape(-1), var_p.reshape(-1)
        lowest = _BIG
        xs = np.arange(W).astype(np.float32)
        # the nearest surface within one pixel: 3x3 maximum of the keys, separable (rows, then columns); the float
        # view of the int32 maximum is its d'
        rows_max = np.empty((y1 - y0 + 2, W), np.int32)
        for r in range(y1 - y0 + 2):
            j = y0 + r + _PAD - 1
            for x in range(W):
                i = x + _PAD
                rows_max[r, x] = max(max(zbuf[j, i - 1], zbuf[j, i]), zbuf[j, i + 1])
        near_row = np.empty(W, np.int32)
        near_val = near_row.view(np.float32)
        est_r, land_r, fall_r = np.empty(W, np.float32), np.empty(W, np.bool_), np.empty(W, np.bool_)
        sx_r, sy_r, ex_r, hz_r = np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32), np.empty(
            W, np.float32)
        fx_r, fy_r = np.empty(W, np.float32), np.empty(W, np.float32)
        at = np.empty(W, np.int64)
        g = np.empty((4, W), np.float32)
        for y in range(y0, y1):
            yf = _F(y)
            r = y - y0
            # row-constant parts of the back-projection G (x, y, 1), added in the torch path's order
            r0, r1, r2 = G[0, 1] * yf, G[1, 1] * yf, G[2, 1] * yf
            # -- the candidate (nearest surface, or what landed on the pixel on the same surface), sent back at its
            # depth into frame t-1: the source pixel it falls in
            for x in range(W):
                xf = xs[x]
                near = max(max(rows_max[r, x], rows_max[r + 1, x]), rows_max[r + 2, x])
                near_row[x] = near
                own = zbuf[y + _PAD, x + _PAD]
                near_v = near_val[x] if near >= 0 else _F(0.0)
                own_v = zval[y + _PAD, x + _PAD] if own >= 0 else _F(0.0)
                cand = own_v if near_v - own_v < tol else near_v
                hz = ((G[2, 0] * xf + G[2, 2]) + r2) + cand * e[2]
                inv_h = _F(1.0) / max(hz, _MIN)
                sx = (((G[0, 0] * xf + G[0, 2]) + r0) + cand * e[0]) * inv_h
                sy = (((G[1, 0] * xf + G[1, 2]) + r1) + cand * e[1]) * inv_h
                hz_r[x] = hz
                ex_r[x] = inv_h * cand
                px = np.rint(min(max(sx, _F(-1.0)), _F(W)))
                py = np.rint(min(max(sy, _F(-1.0)), _F(H)))
                at[x] = (np.int64(py) + _PAD) * wp + np.int64(px) + _PAD
            for x in range(W):
                c = at[x]
                g[0, x] = src_flat[c]
                g[1, x] = new_flat[c]
            if has_var:
                for x in range(W):
                    var_out[y, x] = var_flat[at[x]]
            # -- accepted when that pixel's disparity is the one the candidate implies there; its d' is the start
            for x in range(W):
                near = near_row[x]
                landed = (abs(g[0, x] - ex_r[x]) < tol) & (hz_r[x] > _MIN) & (near >= 0)
                est = g[1, x]
                fall_r[x] = (est >= 0) & (near >= 0) & ~landed
                land_r[x] = landed
                est_r[x] = max(est, _F(0.0))
            # -- inverse-warp refinement; the first step decides the fallbacks and re-checks every target
            for step in range(iterations):
                for x in range(W):
                    xf = xs[x]
                    est = est_r[x]
                    hz = ((G[2, 0] * xf + G[2, 2]) + r2) + est * e[2]
                    inv_h = _F(1.0) / max(hz, _MIN)
                    sx = (((G[0, 0] * xf + G[0, 2]) + r0) + est * e[0]) * inv_h
                    sy = (((G[1, 0] * xf + G[1, 2]) + r1) + est * e[1]) * inv_h
                    hz_r[x], sx_r[x], sy_r[x], ex_r[x] = hz, sx, sy, est * inv_h
                    fx0 = np.floor(min(max(sx, _F(-_PAD)), _F(W + 1)))
                    fy0 = np.floor(min(max(sy, _F(-_PAD)), _F(H + 1)))
                    fx_r[x], fy_r[x] = sx - fx0, sy - fy0
                    at[x] = (np.int64(fy0) + _PAD) * wp + np.int64(fx0) + _PAD
                for x in range(W):  # the four source neighbours
                    c = at[x]
                    g[0, x], g[1, x] = src_flat[c], src_flat[c + 1]
                    g[2, x], g[3, x] = src_flat[c + wp], src_flat[c + wp + 1]
                for x in range(W):
                    est, expect, fx, fy = est_r[x], ex_r[x], fx_r[x], fy_r[x]
                    g0, g1, g2, g3 = g[0, x], g[1, x], g[2, x], g[3, x]
                    s0 = abs(g0 - expect) < tol
                    s1 = abs(g1 - expect) < tol
                    s2 = abs(g2 - expect) < tol
                    s3 = abs(g3 - expect) < tol
                    d_src = _lerp(_lerp(g0 if s0 else expect, g1 if s1 else expect, fx),
                                  _lerp(g2 if s2 else expect, g3 if s3 else expect, fx), fy)
                    qz = ((A[2, 2] + sx_r[x] * A[2, 0]) + sy_r[x] * A[2, 1]) + d_src * a[2]
                    new = d_src / max(qz, _MIN)
                    hz_ok = hz_r[x] > _MIN
                    landed = land_r[x]
                    if step == 0:
                        # the nearest neighbour must be on the start's surface, and the step small
                        right, down = np.rint(fx) > 0, np.rint(fy) > 0
                        nearest_same = (s3 if right else s2) if down else (s1 if right else s0)
                        landed = (landed | fall_r[x]) & nearest_same & (abs(new - est) <= tol) & hz_ok
                        land_r[x] = landed
                    est_r[x] = new if hz_ok & (qz > _MIN) & landed else est
            row_lowest = _BIG
            for x in range(W):
                est_out[y, x] = est_r[x]
                landed_out[y, x] = land_r[x]
                row_lowest = min(row_lowest, est_r[x] if land_r[x] else _BIG)
            lowest = min(lowest, row_lowest)
            later[y] = fill_holes and row_lowest >= _BIG
            if not later[y]:
                _fill_row(y, est_out, var_out, landed_out, has_var, fill_holes, _BIG, process_noise, hole_variance,
                          disparity, variance, confidence)
        return lowest

    @_jit(inline="always")
    def _fill_row(y, est, est_var, landed, has_var, fill_holes, image_fill, process_noise, hole_variance,
                  disparity, variance, confidence):
        """Step 3 for row ``y``: the background hole fill (predict.fill_holes_background) and the outputs."""
        W = est.shape[1]
        if fill_holes:
            # nearest landed value on the left (+big: none), then the minimum with the one on the right
            last = _BIG
            for x in range(W):
                if landed[y, x]:
                    last = est[y, x]
                disparity[y, x] = last
            row_fill = image_fill if last >= _BIG else _BIG  # a row without a landed pixel
            last = _BIG
            for x in range(W - 1, -1, -1):
                if landed[y, x]:
                    last = est[y, x]
                disparity[y, x] = min(min(disparity[y, x], last), row_fill)
        else:
            for x in range(W):
                disparity[y, x] = est[y, x] if landed[y, x] else _F(0.0)
        for x in range(W):
            v = (est_var[y, x] + process_noise) if has_var else process_noise
            variance[y, x] = v if landed[y, x] else hole_variance
            confidence[y, x] = _F(1.0) / (_F(1.0) + v) if landed[y, x] else _F(0.0)

    @_jit
    def _fill(est, est_var, landed, has_var, fill_holes, image_fill, process_noise, hole_variance, rows,
              disparity, variance, confidence):
        """Step 3 for the marked ``rows`` (those without a landed pixel, which take the image's fill value)."""
        for y in range(est.shape[0]):
            if rows[y]:
                _fill_row(y, est, est_var, landed, has_var, fill_holes, image_fill, process_noise, hole_variance,
                          disparity, variance, confidence)

    @_jit(inline="always")
    def _look_up(key_d, key_var, key_ok, G, e, iterations, tolerance, surface_tolerance, process_noise, x, y, dv):
        """close_cracks for hole pixel ``(x, y)`` filled with ``dv``: the inverse-warp look-ups in the keyframe (the
        formulas of :func:`egorefine.refine.close_cracks`). Returns ``(accepted, disparity, variance)``."""
        H, W = key_d.shape
        xf, yf = _F(x), _F(y)
        base0 = (G[0, 0] * xf + G[0, 1] * yf) + G[0, 2]
        base1 = (G[1, 0] * xf + G[1, 1] * yf) + G[1, 2]
        base2 = (G[2, 0] * xf + G[2, 1] * yf) + G[2, 2]
        ok = True
        step = _F(0.0)
        var = _F(0.0)
        hz = _F(1.0)
        for _ in range(iterations):
            h2 = base2 + e[2] * dv
            hz = max(h2, _MIN)
            sx = (base0 + e[0] * dv) / hz
            sy = (base1 + e[1] * dv) / hz
            inside = (h2 > _MIN) & (sx >= 0) & (sy >= 0) & (sx <= W - 1) & (sy <= H - 1)
            x0 = min(np.floor(min(max(sx, _F(0.0)), _F(W - 1))), _F(W - 2))
            y0_ = min(np.floor(min(max(sy, _F(0.0)), _F(H - 1))), _F(H - 2))
            ax = min(max(sx - x0, _F(0.0)), _F(1.0))
            ay = min(max(sy - y0_, _F(0.0)), _F(1.0))
            i, j = np.int64(x0), np.int64(y0_)
            c0, c1, c2, c3 = key_d[j, i], key_d[j, i + 1], key_d[j + 1, i], key_d[j + 1, i + 1]
            spread = max(max(c0, c1), max(c2, c3)) - min(min(c0, c1), min(c2, c3))
            sample_ok = (inside & key_ok[j, i] & key_ok[j, i + 1] & key_ok[j + 1, i] & key_ok[j + 1, i + 1]
                         & (spread <= surface_tolerance))
            w0, w1 = (_F(1.0) - ax) * (_F(1.0) - ay), ax * (_F(1.0) - ay)
            w2, w3 = (_F(1.0) - ax) * ay, ax * ay
            value = ((w0 * c0 + w1 * c1) + w2 * c2) + w3 * c3
            var = (((w0 * key_var[j, i] + w1 * key_var[j, i + 1]) + w2 * key_var[j + 1, i])
                   + w3 * key_var[j + 1, i + 1])
            new = value * hz  # d' = d_k / q_z with q_z = 1 / h_z (eq. 1)
            step = abs(new - dv)
            ok = ok & sample_ok
            if sample_ok:
                dv = new
        return ok and step <= tolerance, dv, var * (hz * hz) + process_noise

    @_jit
    def _close_cracks(key_d, key_var, key_ok, G, e, iterations, tolerance, surface_tolerance, process_noise, y0, y1,
                      d_in, var_in, valid_in, conf_in, disparity, variance, valid, confidence):
        """close_cracks for rows ``y0:y1`` of one batch item: the prediction's maps (``*_in``) copied to the outputs,
        and the look-ups in the keyframe for its holes. Returns the number of holes."""
        W = key_d.shape[1]
        holes = 0
        for y in range(y0, y1):
            for x in range(W):
                disparity[y, x] = d_in[y, x]
                variance[y, x] = var_in[y, x]
                confidence[y, x] = conf_in[y, x]
                valid[y, x] = valid_in[y, x]
            for x in range(W):
                if valid_in[y, x]:
                    continue
                holes += 1
                ok, dv, v = _look_up(key_d, key_var, key_ok, G, e, iterations, tolerance, surface_tolerance,
                                     process_noise, x, y, disparity[y, x])
                if ok:
                    disparity[y, x] = dv
                    variance[y, x] = v
                    valid[y, x] = True
                    confidence[y, x] = _F(1.0) / (_F(1.0) + v)
        return holes

    @_jit
    def _finish(key_d, key_var, key_ok, G, e, iterations, tolerance, surface_tolerance, process_noise, low, high,
                y0, y1, disparity, variance, valid, confidence):
        """Rows ``y0:y1`` of one batch item's prediction, in place: its holes' look-ups in the keyframe (when
        ``iterations`` > 0), then values outside ``[low, high)`` made not valid (confidence 0)."""
        W = key_d.shape[1]
        for y in range(y0, y1):
            drow, vrow, crow = disparity[y], valid[y], confidence[y]
            if iterations > 0:
                for x in range(W):
                    if vrow[x]:
                        continue
                    ok, dv, v = _look_up(key_d, key_var, key_ok, G, e, iterations, tolerance, surface_tolerance,
                                         process_noise, x, y, drow[x])
                    if ok:
                        drow[x] = dv
                        variance[y, x] = v
                        vrow[x] = True
                        crow[x] = _F(1.0) / (_F(1.0) + v)
            for x in range(W):
                keep = vrow[x] & (drow[x] >= low) & (drow[x] < high)
                vrow[x] = keep
                crow[x] = crow[x] if keep else _F(0.0)

    @_jit
    def _edge_variance(d, valid, radius, y0, y1, base, has_base, out):
        """Rows ``y0:y1`` of :func:`egorefine.refine.correct.edge_variance` for one batch item: ``(r / 2)^2`` with
        ``r`` the spread of the valid disparities in the window (clipped at the borders), 0 where invalid, plus
        ``base`` where ``has_base``. Window
        maxima and minima separably, rows then columns, each as a few passes over shifted slices (SIMD)."""
        H, W = d.shape
        lo_row, hi_row = max(0, y0 - radius), min(H, y1 + radius)
        n = hi_row - lo_row
        row_max = np.empty((n, W), np.float32)
        row_min = np.empty((n, W), np.float32)
        v_max = np.empty(W, np.float32)
        v_min = np.empty(W, np.float32)
        for j in range(n):
            y = lo_row + j
            drow, vrow = d[y], valid[y]
            for x in range(W):
                ok = vrow[x]
                v_max[x] = drow[x] if ok else -_BIG
                v_min[x] = drow[x] if ok else _BIG
            a, b = row_max[j], row_min[j]
            for x in range(W):
                a[x] = v_max[x]
                b[x] = v_min[x]
            for s in range(1, min(radius, W - 1) + 1):  # the neighbours s columns right, then s columns left
                a_l, m_r, b_l, n_r = a[: W - s], v_max[s:], b[: W - s], v_min[s:]
                for x in range(W - s):
                    a_l[x] = max(a_l[x], m_r[x])
                    b_l[x] = min(b_l[x], n_r[x])
                a_r, m_l, b_r, n_l = a[s:], v_max[: W - s], b[s:], v_min[: W - s]
                for x in range(W - s):
                    a_r[x] = max(a_r[x], m_l[x])
                    b_r[x] = min(b_r[x], n_l[x])
        for y in range(y0, y1):
            for x in range(W):
                v_max[x] = row_max[y - lo_row, x]
                v_min[x] = row_min[y - lo_row, x]
            for k in range(max(0, y - radius), min(H, y + radius + 1)):
                m_k, n_k = row_max[k - lo_row], row_min[k - lo_row]
                for x in range(W):
                    v_max[x] = max(v_max[x], m_k[x])
                    v_min[x] = min(v_min[x], n_k[x])
            vrow, orow = valid[y], out[y]
            for x in range(W):
                spread = max(v_max[x] - v_min[x], _F(0.0)) if vrow[x] else _F(0.0)
                orow[x] = spread * spread * _F(0.25)
            if has_base:
                brow = base[y]
                for x in range(W):
                    orow[x] = brow[x] + orow[x]


    @_jit
    def _expected(kp, disp, valid, M, K, baseline, out):
        """``refiner._expected_positions`` for every batch item and point, in float32 as the torch path computes
        it (bilinear sample, ``Z = f B / d``, unproject, move, project with kornia's ``1e-8`` guard on ``Z'``)."""
        B, N = kp.shape[0], kp.shape[1]
        H, W = disp.shape[1], disp.shape[2]
        dx, dy = min(1, W - 1), min(1, H - 1)
        eps = _F(np.finfo(np.float32).eps)
        for b in range(B):
            fx, fy, cx, cy = K[b, 0, 0], K[b, 1, 1], K[b, 0, 2], K[b, 1, 2]
            fb = fx * baseline[b]
            for n in range(N):
                x, y = kp[b, n, 0], kp[b, n, 1]
                out[b, n, 0], out[b, n, 1] = x, y
                if not (np.isfinite(x) and np.isfinite(y)):
                    continue
                x0 = min(max(np.floor(x), _F(0.0)), _F(max(W - 2, 0)))
                y0 = min(max(np.floor(y), _F(0.0)), _F(max(H - 2, 0)))
                wx = min(max(x - x0, _F(0.0)), _F(1.0))
                wy = min(max(y - y0, _F(0.0)), _F(1.0))
                i, j = np.int64(x0), np.int64(y0)
                if not (valid[b, j, i] and valid[b, j, i + dx] and valid[b, j + dy, i] and valid[b, j + dy, i + dx]):
                    continue
                d00, d01, d10, d11 = disp[b, j, i], disp[b, j, i + dx], disp[b, j + dy, i], disp[b, j + dy, i + dx]
                top = d00 + wx * (d01 - d00)
                bottom = d10 + wx * (d11 - d10)
                d = top + wy * (bottom - top)
                if not d > 0:
                    continue
                Z = fb / max(d, eps)
                X, Y = (x - cx) / fx * Z, (y - cy) / fy * Z
                px = ((M[b, 0, 0] * X + M[b, 0, 1] * Y) + M[b, 0, 2] * Z) + M[b, 0, 3]
                py = ((M[b, 1, 0] * X + M[b, 1, 1] * Y) + M[b, 1, 2] * Z) + M[b, 1, 3]
                pz = ((M[b, 2, 0] * X + M[b, 2, 1] * Y) + M[b, 2, 2] * Z) + M[b, 2, 3]
                scale = _F(1.0) / pz if abs(pz) > _F(1e-8) else _F(1.0)
                u, v = px * scale * fx + cx, py * scale * fy + cy
                if pz > 0 and u >= 0 and u <= W - 1 and v >= 0 and v <= H - 1:
                    out[b, n, 0], out[b, n, 1] = u, v


_workspace_store = threading.local()


def _workspace(H: int, W: int, has_var: bool) -> tuple[np.ndarray, ...]:
    """The calling thread's padded maps for an ``H x W`` splat, kept for the next call of the same size (their
    margins stay ``-big``: the kernels write only the interior)."""
    store = getattr(_workspace_store, "arrays", None)
    if store is None or store[0] != (H, W):
        hp, wp = H + 2 * _PAD + 1, W + 2 * _PAD + 1
        arrays = (np.full((hp, wp), -_BIG, np.float32), np.full((hp, wp), -_BIG, np.float32),
                  np.empty((hp, wp), np.float32), np.empty((hp, wp), np.int32), np.empty((H, W), np.int32),
                  np.empty((H, W), np.int32))
        store = _workspace_store.arrays = ((H, W), arrays)
    key_src, key_new, var_p, zbuf, at, keys = store[1]
    return key_src, key_new, var_p if has_var else var_p[:1, :1], zbuf, at, keys


def hard_splat(d: torch.Tensor, var: torch.Tensor | None, valid: torch.Tensor | None, A: torch.Tensor,
               a: torch.Tensor, G: torch.Tensor, e: torch.Tensor, surface_tolerance: float, refine_iterations: int,
               fill_holes: bool, process_noise: float, hole_variance: float, threads: int | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """Hard splat with ``refine_iterations >= 1`` refinement steps, hole fill and outputs (float32 CPU, no gradient).

    No torch pass over the maps before the kernels: validity (``d >= 0`` and ``valid``) and finiteness are
    tested inside them. A torch op on a full map wakes torch's OpenMP threads, which then spin on the second core
    for a few ms while these kernels want it.

    Args:
        d, var, valid: ``(B, H, W)`` source disparity, its variance and bool validity (None: all).
        A, a, G, e: the pixel-homogeneous motion of ``_splat._pixel_motion`` (float32).
        surface_tolerance, refine_iterations, fill_holes, process_noise, hole_variance: as ``predict_disparity``.
        threads: worker threads (None: ``torch.get_num_threads()``).

    Returns:
        ``(disparity, variance, confidence, landed, hole)`` each ``(B, H, W)``, as ``predict_disparity``'s fields
        (holes filled or 0, ``hole_variance`` and confidence 0 on holes; ``hole = ~landed``); None if ``d`` holds
        NaN or Inf.
    """
    B, H, W = d.shape
    threads = max(1, threads or torch.get_num_threads())
    dn = d.numpy()
    okn = valid.numpy() if valid is not None else np.ones((B, 1, 1), np.bool_)
    varn = var.numpy() if var is not None else np.zeros((B, 1, 1), np.float32)
    An, an, Gn, en = (t.numpy() for t in (A, a, G, e))
    tol = _F(surface_tolerance)
    disparity = np.empty((B, H, W), np.float32)
    variance = np.empty((B, H, W), np.float32)
    confidence = np.empty((B, H, W), np.float32)
    landed = np.empty((B, H, W), np.bool_)
    bands = _bands(H, threads)
    noise, hole = _F(process_noise), _F(hole_variance)

    def item(i: int, run) -> bool:
        key_src, key_new, var_p, zbuf, at, keys = _workspace(H, W, var is not None)
        if any(run(lambda band: _move_sources(dn[i], okn[i], valid is not None, varn[i], var is not None, An[i],
                                              an[i], band[0], band[1], key_src, key_new, var_p, at, keys), bands)):
            return False
        zbuf.fill(-1)
        _scatter(at, keys, zbuf, var_p, var is not None)
        # the scatter is done: its cells and keys buffers hold the estimates now (no fresh pages to fault in)
        est = at.view(np.float32)
        est_var = keys.view(np.float32) if var is not None else est
        later = np.empty(H, np.bool_)
        outs = (disparity[i], variance[i], confidence[i])
        lows = run(lambda band: _targets(zbuf, zbuf.view(np.float32), key_src, key_new, var_p, var is not None,
                                         An[i], an[i], Gn[i], en[i], tol, refine_iterations, band[0], band[1],
                                         est, est_var, landed[i], fill_holes, noise, hole, later, *outs), bands)
        if later.any():  # rows without a landed pixel: the smallest landed value of the image (0 if none)
            low = min(lows)
            image_fill = _F(0.0) if low >= _BIG else _F(low)
            _fill(est, est_var, landed[i], var is not None, fill_holes, image_fill, noise, hole, later, *outs)
        return True

    workers = Workers(threads)
    if not all(item(i, workers.map) for i in range(B)):
        return None
    as_t = torch.from_numpy
    # (numpy's not: a torch op on a full map would wake torch's OpenMP threads beside the next kernels)
    return as_t(disparity), as_t(variance), as_t(confidence), as_t(landed), as_t(np.logical_not(landed))


def close_cracks(disparity: torch.Tensor, variance: torch.Tensor, valid: torch.Tensor, confidence: torch.Tensor,
                 key_disparity: torch.Tensor, key_variance: torch.Tensor, key_valid: torch.Tensor, G: torch.Tensor,
                 e: torch.Tensor, iterations: int, tolerance: float, surface_tolerance: float, process_noise: float,
                 threads: int | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """:func:`egorefine.refine.close_cracks` on float32 CPU maps: new ``(disparity, variance, valid, confidence)``,
    or None where the prediction has no hole (nothing to close).

    Args:
        disparity, variance, valid, confidence: ``(B, H, W)`` the prediction's maps (not changed).
        key_disparity, key_variance, key_valid: ``(B, H, W)`` keyframe maps.
        G, e: ``(B, 3, 3)``, ``(B, 3)`` the back-projection of ``_splat._pixel_motion``.
        iterations, tolerance, surface_tolerance, process_noise: as ``close_cracks``.
        threads: worker threads (None: ``torch.get_num_threads()``).
    """
    B, H, W = disparity.shape
    threads = max(1, threads or torch.get_num_threads())
    # (the copies are made inside the kernel: a torch copy of a full map would wake torch's OpenMP threads)
    maps_in = [t.numpy() for t in (disparity, variance, valid, confidence)]
    outs = [np.empty((B, H, W), np.float32), np.empty((B, H, W), np.float32), np.empty((B, H, W), np.bool_),
            np.empty((B, H, W), np.float32)]
    kd, kv, kok = (t.contiguous().numpy() for t in (key_disparity, key_variance, key_valid))
    Gn, en = G.numpy(), e.numpy()
    bands = _bands(H, threads)
    args = (max(1, int(iterations)), _F(tolerance), _F(surface_tolerance), _F(process_noise))

    def band(job: tuple[int, tuple[int, int]]) -> int:
        i, (y0, y1) = job
        return _close_cracks(kd[i], kv[i], kok[i], Gn[i], en[i], *args, y0, y1, *(m[i] for m in maps_in),
                             *(out[i] for out in outs))

    if sum(Workers(threads).map(band, [(i, rows) for i in range(B) for rows in bands])) == 0:
        return None
    return tuple(torch.from_numpy(out) for out in outs)


def finish_prediction(disparity: torch.Tensor, variance: torch.Tensor, valid: torch.Tensor,
                      confidence: torch.Tensor, key_disparity: torch.Tensor, key_variance: torch.Tensor,
                      key_valid: torch.Tensor, G: torch.Tensor, e: torch.Tensor, iterations: int, tolerance: float,
                      surface_tolerance: float, process_noise: float, low: float, high: float,
                      threads: int | None = None) -> None:
    """The refiner's step after the splat, in place on the prediction's float32 CPU maps ``(B, H, W)`` (``valid``
    bool): :func:`close_cracks`' look-ups for the holes (``iterations`` 0: none), then values outside
    ``[low, high)`` not valid, with confidence 0. One pass, no copy of the maps."""
    B, H, W = disparity.shape
    threads = max(1, threads or torch.get_num_threads())
    maps = [t.numpy() for t in (disparity, variance, valid, confidence)]
    kd, kv, kok = (t.contiguous().numpy() for t in (key_disparity, key_variance, key_valid))
    Gn, en = G.numpy(), e.numpy()
    args = (int(iterations), _F(tolerance), _F(surface_tolerance), _F(process_noise), _F(low), _F(high))

    def band(job: tuple[int, tuple[int, int]]) -> None:
        i, (y0, y1) = job
        _finish(kd[i], kv[i], kok[i], Gn[i], en[i], *args, y0, y1, *(m[i] for m in maps))

    Workers(threads).map(band, [(i, rows) for i in range(B) for rows in _bands(H, threads)])


def edge_variance(disparity: torch.Tensor, valid: torch.Tensor, radius: int, base: torch.Tensor | None = None,
                  threads: int | None = None) -> torch.Tensor:
    """:func:`egorefine.refine.correct.edge_variance` of float32 CPU maps ``(B, H, W)`` (``valid`` bool, ``base``
    float32 or None): one compiled pass instead of ~12 full-map torch ops (memory-bound)."""
    B, H, W = disparity.shape
    threads = max(1, threads or torch.get_num_threads())
    d, ok = disparity.numpy(), valid.numpy()
    has_base = base is not None
    bn = base.numpy() if has_base else d
    out = np.empty((B, H, W), np.float32)
    Workers(threads).map(lambda job: _edge_variance(d[job[0]], ok[job[0]], radius, *job[1], bn[job[0]], has_base,
                                                    out[job[0]]),
                         [(i, rows) for i in range(B) for rows in _bands(H, threads)])
    return torch.from_numpy(out)


def expected_positions(keypoints: torch.Tensor, disparity: torch.Tensor, valid: torch.Tensor, motion: torch.Tensor,
                       K: torch.Tensor, baseline: torch.Tensor) -> torch.Tensor:
    """``refiner._expected_positions`` on float32 CPU tensors: keypoints ``(B, N, 2)``, disparity ``(B, H, W)``,
    valid ``(B, H, W)`` bool, motion ``(B, 4, 4)``, K ``(B, 3, 3)``, baseline ``(B,)``; returns ``(B, N, 2)``."""
    out = np.empty(keypoints.shape, np.float32)
    _expected(keypoints.numpy(), disparity.numpy(), valid.numpy(), motion.numpy(), K.numpy(), baseline.numpy(), out)
    return torch.from_numpy(out)
