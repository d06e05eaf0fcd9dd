"""CPU inference path of the hard splat (:func:`egorefine.refine.predict_disparity`), compiled with numba.

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
the two paths on rendered sequences. The compiled steps around the splat (crack closing, the edge variance,
the features' expected positions) are :mod:`egorefine.refine._predict_numba`'s.

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

__all__ = ["AVAILABLE", "hard_splat"]

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
