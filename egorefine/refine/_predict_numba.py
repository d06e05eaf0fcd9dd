"""CPU inference paths of the refiner's per-pixel steps around the splat, compiled with numba (the hard splat
itself is :mod:`egorefine.refine._splat_numba`'s).

:func:`close_cracks` does the inverse-warp look-ups
of :func:`egorefine.refine.close_cracks` for the hole pixels in one loop (:func:`finish_prediction` the same in
place, with the refiner's search-range check after it), and :func:`edge_variance`
the window spreads of :func:`egorefine.refine.correct.edge_variance` in one pass (bit for bit), and
:func:`expected_positions` the refiner's constant-velocity guess of where its features land (one loop
instead of some forty torch ops on a few hundred points, whose launches cost more than their arithmetic).

They repeat the torch path's float32 formulas in the same order, so the decisions agree with it (values may differ
in the last bits where torch's vectorised kernels fuse a multiply and an add): tests compare the two paths on
rendered sequences.

Used for float32 CPU tensors that need no gradient when numba is installed (``AVAILABLE``); the
torch path stays the reference for GPU tensors, float64 and autograd.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core._jit import AVAILABLE, Workers, frame_bands, thread_count
from ..core._jit import jit as _jit
from ._splat_numba import _BIG, _F, _MIN

__all__ = ["AVAILABLE", "close_cracks", "finish_prediction", "edge_variance", "expected_positions"]


if AVAILABLE:

    @_jit(inline="always")
    def _key_cell(g00, g02, g10, g12, g20, g22, r0, r1, r2, e0, e1, e2, x_max, y_max, xf, dv):
        """Hole pixel ``(xf, y)`` at disparity ``dv`` sent back into the keyframe (G's ``y`` terms in ``r*``):
        ``(inside, h_z, ax, ay, h_z unclamped, column, row)`` of its bilinear look-up cell."""
        base0 = (g00 * xf + r0) + g02
        base1 = (g10 * xf + r1) + g12
        base2 = (g20 * xf + r2) + g22
        h2 = base2 + e2 * dv
        hz = max(h2, _MIN)
        sx = (base0 + e0 * dv) / hz
        sy = (base1 + e1 * dv) / hz
        inside = (h2 > _MIN) & (sx >= 0) & (sy >= 0) & (sx <= x_max) & (sy <= y_max)
        x0 = min(np.floor(min(max(sx, _F(0.0)), x_max)), x_max - _F(1.0))
        y0 = min(np.floor(min(max(sy, _F(0.0)), y_max)), y_max - _F(1.0))
        ax = min(max(sx - x0, _F(0.0)), _F(1.0))
        ay = min(max(sy - y0, _F(0.0)), _F(1.0))
        return inside, hz, ax, ay, h2, np.int32(x0), np.int32(y0)

    @_jit(error_model="numpy")
    def _close_row(key_d, key_var, key_ok, G, e, iterations, tolerance, surface_tolerance, process_noise, y, drow,
                   vrow, var_row, crow, scratch, flags, holes, at):
        """close_cracks for row ``y`` of one batch item's prediction, in place: its hole pixels' inverse-warp
        look-ups in the keyframe (the formulas of :func:`egorefine.refine.close_cracks`, same order). Returns the
        number of holes.

        The holes are first gathered into a list; then each step is a loop over it that only computes (SIMD code,
        as in :mod:`egorefine.refine._splat_numba`: few arrays per loop, the look-up's geometry recomputed rather
        than stored) and one that only gathers the four keyframe neighbours. A hole whose look-up failed cannot be
        accepted any more and leaves the list (most holes are never accepted: disocclusions, the keyframe's holes).
        Work arrays: ``scratch`` ``(11, W)`` float32, ``flags`` ``(2, W)`` bool, ``holes`` ``(W,)`` int32, ``at``
        ``(W,)`` uint32.
        """
        H, W = key_d.shape
        n = 0
        for x in range(W):  # (branch-free: the index is written always, kept when the pixel is a hole)
            holes[n] = x
            n += not vrow[x]
        if n == 0:
            return 0
        count = n
        d_flat, var_flat, ok_flat = key_d.reshape(-1), key_var.reshape(-1), key_ok.reshape(-1)
        uw = np.uint32(W)
        yf = _F(y)
        g00, g02, g10, g12, g20, g22 = G[0, 0], G[0, 2], G[1, 0], G[1, 2], G[2, 0], G[2, 2]
        r0, r1, r2 = G[0, 1] * yf, G[1, 1] * yf, G[2, 1] * yf
        e0, e1, e2 = e[0], e[1], e[2]
        x_max, y_max = _F(W - 1), _F(H - 1)
        dv_r, step_r, var_r, c0, c1, c2, c3, v0, v1, v2, v3 = (
            scratch[0], scratch[1], scratch[2], scratch[3], scratch[4], scratch[5], scratch[6], scratch[7],
            scratch[8], scratch[9], scratch[10])
        ok_r, quad = flags[0], flags[1]  # ok_r: every look-up so far valid
        for k in range(n):
            dv_r[k] = drow[holes[k]]
            ok_r[k] = True
        for step in range(iterations):
            # the look-up cell of the estimate sent back into the keyframe
            for k in range(n):
                _, _, _, _, _, i, j = _key_cell(g00, g02, g10, g12, g20, g22, r0, r1, r2, e0, e1, e2, x_max, y_max,
                                               _F(holes[k]), dv_r[k])
                at[k] = np.uint32(j * W + i)
            for k in range(n):  # its four neighbours (gathers only)
                c = at[k]
                c0[k], c1[k], c2[k], c3[k] = d_flat[c], d_flat[c + 1], d_flat[c + uw], d_flat[c + uw + 1]
                quad[k] = ok_flat[c] & ok_flat[c + 1] & ok_flat[c + uw] & ok_flat[c + uw + 1]
            if step == iterations - 1:  # the variance of the last look-up, carried like the splat's
                for k in range(n):
                    c = at[k]
                    v0[k], v1[k], v2[k], v3[k] = var_flat[c], var_flat[c + 1], var_flat[c + uw], var_flat[c + uw + 1]
                for k in range(n):
                    _, hz, ax, ay, _, _, _ = _key_cell(g00, g02, g10, g12, g20, g22, r0, r1, r2, e0, e1, e2, x_max,
                                                       y_max, _F(holes[k]), dv_r[k])
                    w0, w1 = (_F(1.0) - ax) * (_F(1.0) - ay), ax * (_F(1.0) - ay)
                    w2, w3 = (_F(1.0) - ax) * ay, ax * ay
                    var = ((w0 * v0[k] + w1 * v1[k]) + w2 * v2[k]) + w3 * v3[k]
                    var_r[k] = var * (hz * hz) + process_noise
            # the sample moved forward (eq. 1, d' = d_k h_z) where its four neighbours are valid and on one surface
            for k in range(n):
                dv = dv_r[k]
                inside, hz, ax, ay, _, _, _ = _key_cell(g00, g02, g10, g12, g20, g22, r0, r1, r2, e0, e1, e2, x_max,
                                                        y_max, _F(holes[k]), dv)
                a0, a1, a2, a3 = c0[k], c1[k], c2[k], c3[k]
                spread = max(max(a0, a1), max(a2, a3)) - min(min(a0, a1), min(a2, a3))
                sample_ok = inside & quad[k] & (spread <= surface_tolerance)
                w0, w1 = (_F(1.0) - ax) * (_F(1.0) - ay), ax * (_F(1.0) - ay)
                w2, w3 = (_F(1.0) - ax) * ay, ax * ay
                new = (((w0 * a0 + w1 * a1) + w2 * a2) + w3 * a3) * hz
                step_r[k] = abs(new - dv)
                ok_r[k] = ok_r[k] & sample_ok
                dv_r[k] = new if sample_ok else dv
            if step < iterations - 1:  # a hole whose look-up failed stays one: the next steps skip it
                m = 0
                for k in range(n):
                    holes[m], dv_r[m] = holes[k], dv_r[k]
                    m += ok_r[k]
                n = m
                for k in range(n):
                    ok_r[k] = True
        for k in range(n):  # accepted: the last step moved the estimate by at most the tolerance
            if ok_r[k] and step_r[k] <= tolerance:
                x = holes[k]
                v = var_r[k]
                drow[x] = dv_r[k]
                var_row[x] = v
                vrow[x] = True
                crow[x] = _F(1.0) / (_F(1.0) + v)
        return count

    @_jit
    def _close_cracks(key_d, key_var, key_ok, G, e, iterations, tolerance, surface_tolerance, process_noise, y0, y1,
                      d_in, var_in, valid_in, conf_in, disparity, variance, valid, confidence):
        """close_cracks for rows ``y0:y1`` of one batch item: the prediction's maps (``*_in``) copied to the outputs,
        and the look-ups in the keyframe for its holes. Returns the number of holes."""
        W = key_d.shape[1]
        scratch, flags = np.empty((11, W), np.float32), np.empty((2, W), np.bool_)
        holes, at = np.empty(W, np.int32), np.empty(W, np.uint32)
        n = 0
        for y in range(y0, y1):
            disparity[y, :] = d_in[y]
            variance[y, :] = var_in[y]
            confidence[y, :] = conf_in[y]
            valid[y, :] = valid_in[y]
            n += _close_row(key_d, key_var, key_ok, G, e, iterations, tolerance, surface_tolerance, process_noise, y,
                            disparity[y], valid[y], variance[y], confidence[y], scratch, flags, holes, at)
        return n

    @_jit
    def _finish(key_d, key_var, key_ok, G, e, iterations, tolerance, surface_tolerance, process_noise, low, high,
                y0, y1, disparity, variance, valid, confidence):
        """Rows ``y0:y1`` of one batch item's prediction, in place: its holes' look-ups in the keyframe (when
        ``iterations`` > 0), then values outside ``[low, high)`` made not valid (confidence 0)."""
        W = key_d.shape[1]
        scratch, flags = np.empty((11, W), np.float32), np.empty((2, W), np.bool_)
        holes, at = np.empty(W, np.int32), np.empty(W, np.uint32)
        for y in range(y0, y1):
            drow, vrow, crow = disparity[y], valid[y], confidence[y]
            if iterations > 0:
                _close_row(key_d, key_var, key_ok, G, e, iterations, tolerance, surface_tolerance, process_noise, y,
                           drow, vrow, variance[y], crow, scratch, flags, holes, at)
            for x in range(W):
                keep = vrow[x] & (drow[x] >= low) & (drow[x] < high)
                vrow[x] = keep
                crow[x] = crow[x] if keep else _F(0.0)

    @_jit(inline="always")
    def _larger(a, b):
        """``max(a, b)`` as a select (numba's ``max`` of floats stays scalar code)."""
        return b if b > a else a

    @_jit(inline="always")
    def _smaller(a, b):
        """``min(a, b)`` as a select."""
        return b if b < a else a

    @_jit
    def _edge_variance(d, valid, radius, y0, y1, base, has_base, out):
        """Rows ``y0:y1`` of :func:`egorefine.refine.correct.edge_variance` for one batch item: ``(r / 2)^2`` with
        ``r`` the spread of the valid disparities in the window (clipped at the borders), 0 where invalid, plus
        ``base`` where ``has_base``. Per row, two kinds of SIMD loop: the column extremes over rows ``y - radius ..
        y + radius``, then across columns ``x - radius .. x + radius`` from a buffer whose margins hold the values
        of invalid pixels (which change no extreme: the clipped window)."""
        H, W = d.shape
        col_max = np.full(W + 2 * radius, -_BIG, np.float32)
        col_min = np.full(W + 2 * radius, _BIG, np.float32)
        c_max, c_min = col_max[radius:radius + W], col_min[radius:radius + W]
        w_max, w_min = np.empty(W, np.float32), np.empty(W, np.float32)
        for y in range(y0, y1):
            drow, vrow = d[y], valid[y]
            for x in range(W):
                c_max[x] = drow[x] if vrow[x] else -_BIG
                c_min[x] = drow[x] if vrow[x] else _BIG
            for k in range(max(0, y - radius), min(H, y + radius + 1)):
                dk, vk = d[k], valid[k]
                for x in range(W):
                    c_max[x] = _larger(c_max[x], dk[x] if vk[x] else -_BIG)
                    c_min[x] = _smaller(c_min[x], dk[x] if vk[x] else _BIG)
            for x in range(W):
                w_max[x] = c_max[x]
                w_min[x] = c_min[x]
            for s in range(1, radius + 1):  # the columns s to the left and s to the right
                l_max, r_max = col_max[radius - s:radius - s + W], col_max[radius + s:radius + s + W]
                l_min, r_min = col_min[radius - s:radius - s + W], col_min[radius + s:radius + s + W]
                for x in range(W):
                    w_max[x] = _larger(_larger(w_max[x], l_max[x]), r_max[x])
                    w_min[x] = _smaller(_smaller(w_min[x], l_min[x]), r_min[x])
            brow, orow = base[y], out[y]
            for x in range(W):
                spread = w_max[x] - w_min[x]
                spread = spread if (vrow[x] & (spread > _F(0.0))) else _F(0.0)
                term = spread * spread * _F(0.25)
                orow[x] = brow[x] + term if has_base else term

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
    threads = thread_count(threads)
    # (the copies are made inside the kernel: a torch copy of a full map would wake torch's OpenMP threads)
    maps_in = [t.numpy() for t in (disparity, variance, valid, confidence)]
    outs = [np.empty((B, H, W), np.float32), np.empty((B, H, W), np.float32), np.empty((B, H, W), np.bool_),
            np.empty((B, H, W), np.float32)]
    kd, kv, kok = (t.contiguous().numpy() for t in (key_disparity, key_variance, key_valid))
    Gn, en = G.numpy(), e.numpy()
    bands = frame_bands(H, threads)
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
    threads = thread_count(threads)
    maps = [t.numpy() for t in (disparity, variance, valid, confidence)]
    kd, kv, kok = (t.contiguous().numpy() for t in (key_disparity, key_variance, key_valid))
    Gn, en = G.numpy(), e.numpy()
    args = (int(iterations), _F(tolerance), _F(surface_tolerance), _F(process_noise), _F(low), _F(high))

    def band(job: tuple[int, tuple[int, int]]) -> None:
        i, (y0, y1) = job
        _finish(kd[i], kv[i], kok[i], Gn[i], en[i], *args, y0, y1, *(m[i] for m in maps))

    Workers(threads).map(band, [(i, rows) for i in range(B) for rows in frame_bands(H, threads)])


def edge_variance(disparity: torch.Tensor, valid: torch.Tensor, radius: int, base: torch.Tensor | None = None,
                  threads: int | None = None) -> torch.Tensor:
    """:func:`egorefine.refine.correct.edge_variance` of float32 CPU maps ``(B, H, W)`` (``valid`` bool, ``base``
    float32 or None): one compiled pass instead of ~12 full-map torch ops (memory-bound)."""
    B, H, W = disparity.shape
    threads = thread_count(threads)
    d, ok = disparity.numpy(), valid.numpy()
    has_base = base is not None
    bn = base.numpy() if has_base else d
    out = np.empty((B, H, W), np.float32)
    Workers(threads).map(lambda job: _edge_variance(d[job[0]], ok[job[0]], radius, *job[1], bn[job[0]], has_base,
                                                    out[job[0]]),
                         [(i, rows) for i in range(B) for rows in frame_bands(H, threads)])
    return torch.from_numpy(out)


def expected_positions(keypoints: torch.Tensor, disparity: torch.Tensor, valid: torch.Tensor, motion: torch.Tensor,
                       K: torch.Tensor, baseline: torch.Tensor) -> torch.Tensor:
    """``refiner._expected_positions`` on float32 CPU tensors: keypoints ``(B, N, 2)``, disparity ``(B, H, W)``,
    valid ``(B, H, W)`` bool, motion ``(B, 4, 4)``, K ``(B, 3, 3)``, baseline ``(B,)``; returns ``(B, N, 2)``."""
    out = np.empty(keypoints.shape, np.float32)
    _expected(keypoints.numpy(), disparity.numpy(), valid.numpy(), motion.numpy(), K.numpy(), baseline.numpy(), out)
    return torch.from_numpy(out)
