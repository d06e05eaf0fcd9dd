"""CPU inference path of the hard splat (:func:`egorefine.refine.predict_disparity`), compiled with numba.

:func:`egorefine.refine.predict_disparity` in hard mode with refinement is about 30 small torch
passes over the image (moving the points, an ``amax`` scatter, the 3x3 z-buffer maximum, the
gathered check, the refinement's four gathered corners, hole filling), each one reading and
writing full-size maps, the largest part of the refiner's loop on the CPU. Every target pixel's work
depends only on its own values and a few gathered
ones, so here it is three loops:

1. (row bands on threads) move every source point (docs/method.md eq. 1 in inverse-depth form), write the
   padded source maps and each point's z-buffer cell; then (one thread) the scatter of the keys;
2. (row bands on threads) per target pixel: the 3x3 z-buffer maximum, the candidate, the check in
   frame ``t-1``, the start value and the inverse-warp refinement steps;
3. (the same rows) the background hole fill and the outputs; for the refiner (``finish``), each row then also
   gets the step after the splat, its holes looked up in the source maps and the range test
   (:mod:`egorefine.refine._predict_numba`'s kernels, called while the row is in cache).

Step 2 works a row at a time and splits each stage into loops that only compute (LLVM turns them
into SIMD code) and loops that only gather (which would keep a loop scalar), several times faster than
one loop per pixel (timings in docs/decisions.md). What else keeps a compute loop scalar, each found by LLVM's
vectorisation remarks: a test of a loop-invariant flag or a select between two rules inside it, a conversion of
the int64 loop index to float, a float or int64 reduction, more arrays written and read than LLVM makes run-time
overlap checks for. So the loops read a float32 column index, the rules have a loop each, and cheap values are
recomputed rather than stored (the same formulas in the same order: the same bits).

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

from ..core._jit import AVAILABLE, Workers, frame_bands, thread_count
from ..core._jit import jit as _jit

__all__ = ["AVAILABLE", "hard_splat"]

_F = np.float32
# the constants of egorefine.refine.predict, as float32
_MIN = _F(1e-3)  # _MIN_DEPTH_RATIO
_BIG = _F(min(1e30, float(np.finfo(np.float32).max) ** 0.5))  # _big(float32)
_PAD = 2  # margin of the padded source layout (_splat._PAD)
_TOP = _F(np.finfo(np.float32).max)


if AVAILABLE:
    from llvmlite import ir
    from numba.core import types
    from numba.extending import intrinsic

    @intrinsic
    def _key_value(typingctx, key):
        """The float32 whose bits are the int32 z-buffer ``key`` (a register bitcast: numpy's ``view`` of a scalar
        would go through memory)."""
        def codegen(context, builder, signature, args):
            return builder.bitcast(args[0], ir.FloatType())
        return types.float32(types.int32), codegen

    @_jit(inline="always")
    def _lerp(start, end, weight):
        """torch.lerp's formula (exact at weights 0 and 1); both branches computed, one selected (no jump)."""
        low = start + weight * (end - start)
        high = end - (end - start) * (_F(1.0) - weight)
        return low if abs(weight) < _F(0.5) else high

    @_jit
    def _move_sources(d, valid, var, has_var, A, a, y0, y1, key_src, key_new, var_p, at):
        """Step 1 for source rows ``y0:y1`` of one batch item: move the points (eq. 1), write the padded source
        maps (``-big`` where invalid) and each point's z-buffer cell ``at``. ``valid``: ``(H, W)``, or ``(1, W)`` of
        True for all. Returns whether a disparity is not finite or a variance not finite and >= 0 (the caller
        raises: checked here rather than by passes over the maps)."""
        H, W = d.shape
        wp = key_src.shape[1]
        a00, a01, a02, a10, a11, a12 = A[0, 0], A[0, 1], A[0, 2], A[1, 0], A[1, 1], A[1, 2]
        a20, a21, a22 = A[2, 0], A[2, 1], A[2, 2]
        m0, m1, m2 = a[0], a[1], a[2]
        bad = False
        xs = np.arange(W).astype(np.float32)  # (a float32 column index: int64 to float conversions do not vectorise)
        for y in range(y0, y1):
            yf = _F(y)
            r0, r1, r2 = a01 * yf, a11 * yf, a21 * yf
            d_row, ok_row = d[y], valid[min(y, valid.shape[0] - 1)]
            src_row, new_row, at_row = key_src[y + _PAD, _PAD:_PAD + W], key_new[y + _PAD, _PAD:_PAD + W], at[y]
            for x in range(W):  # (no branch inside: a loop-invariant one kept it from vectorising)
                xf = xs[x]
                dv = d_row[x]
                bad |= not np.isfinite(dv)
                pz = ((a20 * xf + a22) + r2) + dv * m2
                ok = (dv >= 0) & (pz > _MIN) & ok_row[x]
                inv = _F(1.0) / max(pz, _MIN)
                src_row[x] = dv if ok else -_BIG
                new_row[x] = dv * inv if ok else -_BIG
                tx = np.rint((((a00 * xf + a02) + r0) + dv * m0) * inv)
                ty = np.rint((((a10 * xf + a12) + r1) + dv * m1) * inv)
                tx = min(max(tx, _F(-_PAD)), _F(W + 1))
                ty = min(max(ty, _F(-_PAD)), _F(H + 1))
                at_row[x] = (np.int32(ty) + _PAD) * np.int32(wp) + np.int32(tx) + _PAD
            if has_var:
                var_row, var_prow = var[y], var_p[y + _PAD, _PAD:_PAD + W]
                for x in range(W):
                    inv = _F(1.0) / max(((a20 * xs[x] + a22) + r2) + d_row[x] * m2, _MIN)
                    v = var_row[x]
                    bad |= not ((v >= _F(0.0)) & (v <= _TOP))  # (NaN fails both)
                    var_prow[x] = v * inv * inv
        if has_var:  # replicated margins: a target just outside takes the border's variance
            for y in range(y0 + _PAD, y1 + _PAD):
                for x in range(_PAD):
                    var_p[y, x] = var_p[y, _PAD]
                for x in range(_PAD + W, wp):
                    var_p[y, x] = var_p[y, _PAD + W - 1]
        return bad

    @_jit
    def _scatter(at, key_new, zbuf, var_p, has_var):
        """Step 1, sequential part: the z-buffer keeps each cell's largest key, the bits of ``d' >= 0`` as int32
        (they order like the values: the maximum is the nearest surface; the ``-big`` of an invalid point is a
        negative key, below the empty cells' -1); the variance's margin rows."""
        H, W = at.shape
        flat = zbuf.reshape(-1)
        keys = key_new.view(np.int32)
        for y in range(H):
            at_row, key_row = at[y], keys[y + _PAD, _PAD:_PAD + W]
            for x in range(W):
                cell = at_row[x]
                flat[cell] = max(key_row[x], flat[cell])  # (stored always: no branch to mispredict)
        if has_var:
            for y in range(_PAD):
                var_p[y, :] = var_p[_PAD, :]
            for y in range(_PAD + H, var_p.shape[0]):
                var_p[y, :] = var_p[_PAD + H - 1, :]

    @_jit(inline="always")
    def _sent_back(G, r0, r1, r2, e0, e1, e2, xf, d):
        """Target pixel ``(xf, y)`` at disparity ``d`` sent back into frame ``t-1`` (G's row terms ``r*`` hold the
        ``y`` parts, added in the torch path's order): ``(h_z, 1 / max(h_z, min), x, y)``."""
        hz = ((G[6] * xf + G[8]) + r2) + d * e2
        inv_h = _F(1.0) / max(hz, _MIN)
        sx = (((G[0] * xf + G[2]) + r0) + d * e0) * inv_h
        sy = (((G[3] * xf + G[5]) + r1) + d * e1) * inv_h
        return hz, inv_h, sx, sy

    @_jit(inline="always")
    def _blend(g0, g1, g2, g3, expect, fx, fy, tol):
        """The four source neighbours blended bilinearly where on the expected surface (``expect`` elsewhere):
        ``(value, on-surface flags of the four)``."""
        s0 = abs(g0 - expect) < tol
        s1 = abs(g1 - expect) < tol
        s2 = abs(g2 - expect) < tol
        s3 = abs(g3 - expect) < tol
        value = _lerp(_lerp(g0 if s0 else expect, g1 if s1 else expect, fx),
                      _lerp(g2 if s2 else expect, g3 if s3 else expect, fx), fy)
        return value, s0, s1, s2, s3

    @_jit(inline="always")
    def _refined(G, r0, r1, r2, e0, e1, e2, a20, a21, a22, m2, tol, W, H, xf, est, g0, g1, g2, g3):
        """One refinement step of target ``(xf, y)`` from ``est``, its four source neighbours ``g*`` gathered:
        ``(new estimate, h_z > min, q_z > min, whether the nearest neighbour is on the start's surface)``."""
        hz, inv_h, sx, sy = _sent_back(G, r0, r1, r2, e0, e1, e2, xf, est)
        fx = sx - np.floor(min(max(sx, _F(-_PAD)), _F(W + 1)))
        fy = sy - np.floor(min(max(sy, _F(-_PAD)), _F(H + 1)))
        d_src, s0, s1, s2, s3 = _blend(g0, g1, g2, g3, est * inv_h, fx, fy, tol)
        qz = ((a22 + sx * a20) + sy * a21) + d_src * m2
        right, down = np.rint(fx) > 0, np.rint(fy) > 0
        nearest_same = (s3 if right else s2) if down else (s1 if right else s0)
        return d_src / max(qz, _MIN), hz > _MIN, qz > _MIN, nearest_same

    @_jit(error_model="numpy")
    def _targets(zbuf, key_src, key_new, var_p, has_var, A, a, G, e, tol, iterations, y0, y1, fill_holes,
                 process_noise, hole_variance, later, landed, hole, disparity, variance, confidence, finish, source):
        """Steps 2 and 3 for target rows ``y0:y1`` of one batch item. A row without a landed pixel is filled later,
        from the whole image (marked in ``later``; its outputs other than ``landed`` and ``hole`` are left to the
        caller). With ``finish[0] >= 0`` each row is also finished as ``_predict_numba._finish`` does (its holes
        looked up in ``source = (d, var, valid)``, the source maps, over ``finish[0]`` steps; values outside
        ``[finish[3], finish[4])`` not valid), while it is in cache: ``landed`` then holds the finished validity,
        ``hole`` the splat's own holes.

        A row at a time, each stage split into loops without gathers (compiled to SIMD code) and loops that only
        gather: with the gathers inside, the loop stays scalar and several times slower. The compute loops touch
        few arrays (each pair of arrays a loop writes and reads needs a run-time overlap check, and LLVM gives up
        vectorising beyond a few) and recompute cheap values rather than store them; a select between two rules
        or a test of a loop-invariant flag inside one, or an int64 to float conversion, also keeps it scalar.
        """
        H, W = landed.shape
        wp = key_src.shape[1]
        uwp = np.uint32(wp)  # (unsigned indices: no test for negative ones in the gathers)
        src_flat, new_flat, var_flat = key_src.reshape(-1), key_new.reshape(-1), var_p.reshape(-1)
        Gt = (G[0, 0], G[0, 1], G[0, 2], G[1, 0], G[1, 1], G[1, 2], G[2, 0], G[2, 1], G[2, 2])
        e0, e1, e2 = e[0], e[1], e[2]
        a20, a21, a22, m2 = A[2, 0], A[2, 1], A[2, 2], a[2]
        xs = np.arange(W).astype(np.float32)  # (a float32 column index, for the reason above)
        # the nearest surface within one pixel: 3x3 maximum of the keys, separable (rows here, columns below)
        rows_max = np.empty((y1 - y0 + 2, W), np.int32)
        for r in range(y1 - y0 + 2):
            z, out = zbuf[y0 + r + _PAD - 1], rows_max[r]
            for x in range(W):
                out[x] = max(max(z[x + _PAD - 1], z[x + _PAD]), z[x + _PAD + 1])
        cand_r, est_r, var_r = np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32)
        g0, g1, g2, g3 = np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32), np.empty(
            W, np.float32)
        land_r, fall_r = np.empty(W, np.bool_), np.empty(W, np.bool_)
        at = np.empty(W, np.uint32)
        close_iters, close_tol, close_surface, low, high = finish
        if close_iters >= 0:  # the finishing step's work rows (_predict_numba._close_row)
            scratch, flags = np.empty((11, W), np.float32), np.empty((2, W), np.bool_)
            holes, cells = np.empty(W, np.int32), np.empty(W, np.uint32)
        for y in range(y0, y1):
            yf = _F(y)
            # row-constant parts of the back-projection G (x, y, 1), added in the torch path's order
            r0, r1, r2 = Gt[1] * yf, Gt[4] * yf, Gt[7] * yf
            m_a, m_b, m_c, z_own = rows_max[y - y0], rows_max[y - y0 + 1], rows_max[y - y0 + 2], zbuf[
                y + _PAD, _PAD:_PAD + W]
            # -- the candidate (nearest surface, or what landed on the pixel on the same surface), sent back at its
            # depth into frame t-1: the source pixel it falls in. cand_r keeps it, -1 where no surface is near.
            for x in range(W):
                near = max(max(m_a[x], m_b[x]), m_c[x])
                own = z_own[x]
                near_v = _key_value(near) if near >= 0 else _F(0.0)
                own_v = _key_value(own) if own >= 0 else _F(0.0)
                cand = own_v if near_v - own_v < tol else near_v
                _, _, sx, sy = _sent_back(Gt, r0, r1, r2, e0, e1, e2, xs[x], cand)
                px = np.rint(min(max(sx, _F(-1.0)), _F(W)))
                py = np.rint(min(max(sy, _F(-1.0)), _F(H)))
                at[x] = np.uint32((np.int32(py) + _PAD) * np.int32(wp) + np.int32(px) + _PAD)
                cand_r[x] = cand if near >= 0 else _F(-1.0)
            if has_var:
                for x in range(W):
                    c = at[x]
                    g0[x], g1[x], var_r[x] = src_flat[c], new_flat[c], var_flat[c]
            else:
                for x in range(W):
                    c = at[x]
                    g0[x], g1[x] = src_flat[c], new_flat[c]
            # -- accepted when that pixel's disparity is the one the candidate implies there; its d' is the start
            # of the refinement, whose first look-up cell is found here too
            for x in range(W):
                xf = xs[x]
                cand = max(cand_r[x], _F(0.0))
                hz, inv_h, _, _ = _sent_back(Gt, r0, r1, r2, e0, e1, e2, xf, cand)
                near_ok = cand_r[x] >= 0
                ok = (abs(g0[x] - inv_h * cand) < tol) & (hz > _MIN) & near_ok
                est = g1[x]
                fall_r[x] = (est >= 0) & near_ok & ~ok
                land_r[x] = ok
                est = max(est, _F(0.0))
                est_r[x] = est
                _, _, sx, sy = _sent_back(Gt, r0, r1, r2, e0, e1, e2, xf, est)
                fx0 = np.floor(min(max(sx, _F(-_PAD)), _F(W + 1)))
                fy0 = np.floor(min(max(sy, _F(-_PAD)), _F(H + 1)))
                at[x] = np.uint32((np.int32(fy0) + _PAD) * np.int32(wp) + np.int32(fx0) + _PAD)
            # -- inverse-warp refinement: the four source neighbours of the estimate sent back, blended where on its
            # surface and moved forward (eq. 1); the first step also decides the fallbacks and re-checks every
            # target (the nearest neighbour on the surface, a small step). Two loops: a select between the two
            # rules inside one keeps it scalar.
            for step in range(iterations):
                if step > 0:
                    for x in range(W):
                        _, _, sx, sy = _sent_back(Gt, r0, r1, r2, e0, e1, e2, xs[x], est_r[x])
                        fx0 = np.floor(min(max(sx, _F(-_PAD)), _F(W + 1)))
                        fy0 = np.floor(min(max(sy, _F(-_PAD)), _F(H + 1)))
                        at[x] = np.uint32((np.int32(fy0) + _PAD) * np.int32(wp) + np.int32(fx0) + _PAD)
                for x in range(W):
                    c = at[x]
                    g0[x], g1[x], g2[x], g3[x] = src_flat[c], src_flat[c + 1], src_flat[c + uwp], src_flat[c + uwp + 1]
                if step == 0:
                    for x in range(W):
                        est = est_r[x]
                        new, hz_ok, qz_ok, nearest_same = _refined(Gt, r0, r1, r2, e0, e1, e2, a20, a21, a22, m2, tol,
                                                                   W, H, xs[x], est, g0[x], g1[x], g2[x], g3[x])
                        ok = (land_r[x] | fall_r[x]) & nearest_same & (abs(new - est) <= tol) & hz_ok
                        land_r[x] = ok
                        est_r[x] = new if hz_ok & qz_ok & ok else est
                else:
                    for x in range(W):
                        est = est_r[x]
                        new, hz_ok, qz_ok, _ = _refined(Gt, r0, r1, r2, e0, e1, e2, a20, a21, a22, m2, tol, W, H,
                                                        xs[x], est, g0[x], g1[x], g2[x], g3[x])
                        est_r[x] = new if hz_ok & qz_ok & land_r[x] else est
            # -- outputs: the background hole fill (predict.fill_holes_background), variance and confidence
            land_out, hole_out, d_out, v_out, c_out = landed[y], hole[y], disparity[y], variance[y], confidence[y]
            count = 0
            for x in range(W):
                land_out[x] = land_r[x]
                hole_out[x] = not land_r[x]
                count += np.int32(land_r[x])  # (an int32 sum: vectorised, where an int64 one would not be)
            later[y] = fill_holes and count == 0
            if later[y]:  # no landed pixel: filled with the image's smallest landed value (by the caller)
                continue
            for x in range(W):
                d_out[x] = est_r[x] if land_r[x] else _F(0.0)
            if fill_holes and count < W:  # each run of holes: the smaller of the landed values on either side
                x = 0
                while x < W:
                    if land_r[x]:
                        x += 1
                        continue
                    start = x
                    while x < W and not land_r[x]:
                        x += 1
                    value = min(d_out[start - 1] if start > 0 else _BIG, d_out[x] if x < W else _BIG)
                    for i in range(start, x):
                        d_out[i] = value
            for x in range(W):
                v = (var_r[x] + process_noise) if has_var else process_noise
                v_out[x] = v if land_r[x] else hole_variance
                c_out[x] = _F(1.0) / (_F(1.0) + v) if land_r[x] else _F(0.0)
            if close_iters >= 0:
                if close_iters > 0:
                    _cracks._close_row(source[0], source[1], source[2], G, e, close_iters, close_tol, close_surface,
                                       process_noise, y, d_out, land_out, v_out, c_out, scratch, flags, holes, cells)
                for x in range(W):
                    keep = land_out[x] & (d_out[x] >= low) & (d_out[x] < high)
                    land_out[x] = keep
                    c_out[x] = c_out[x] if keep else _F(0.0)

    @_jit
    def _fill(image_fill, hole_variance, rows, disparity, variance, confidence):
        """Step 3 for the marked ``rows``, those without a landed pixel: the image's fill value, all holes."""
        for y in range(disparity.shape[0]):
            if rows[y]:
                disparity[y, :] = image_fill
                variance[y, :] = hole_variance
                confidence[y, :] = _F(0.0)


_workspace_store = threading.local()


def _workspace(H: int, W: int, has_var: bool) -> tuple[np.ndarray, ...]:
    """The calling thread's padded maps for an ``H x W`` splat, kept for the next call of the same size (their
    margins stay ``-big``: the kernels write only the interior)."""
    store = getattr(_workspace_store, "arrays", None)
    if store is None or store[0] != (H, W):
        hp, wp = H + 2 * _PAD + 1, W + 2 * _PAD + 1
        arrays = (np.full((hp, wp), -_BIG, np.float32), np.full((hp, wp), -_BIG, np.float32),
                  np.empty((hp, wp), np.float32), np.empty((hp, wp), np.int32), np.empty((H, W), np.int32))
        store = _workspace_store.arrays = ((H, W), arrays)
    key_src, key_new, var_p, zbuf, at = store[1]
    return key_src, key_new, var_p if has_var else var_p[:1, :1], zbuf, at


def hard_splat(d: torch.Tensor, var: torch.Tensor | None, valid: torch.Tensor | None, A: torch.Tensor,
               a: torch.Tensor, G: torch.Tensor, e: torch.Tensor, surface_tolerance: float, refine_iterations: int,
               fill_holes: bool, process_noise: float, hole_variance: float, threads: int | None = None,
               finish: tuple[int, float, float, float, float] | None = None
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
        finish: ``(iterations, tolerance, surface_tolerance, low, high)``: also the refiner's step after the splat
            (:func:`egorefine.refine._predict_numba.finish_prediction`, its look-ups in the source maps ``d``,
            ``var``, ``valid``, which must be given), row by row while each is in cache; None: the splat alone.

    Returns:
        ``(disparity, variance, confidence, landed, hole)`` each ``(B, H, W)``, as ``predict_disparity``'s fields
        (holes filled or 0, ``hole_variance`` and confidence 0 on holes; ``hole = ~landed``; with ``finish`` the
        fields after that step, ``hole`` the splat's own holes); None if ``d`` holds NaN or Inf or ``var`` a value
        that is not finite and >= 0.
    """
    if finish is not None and (var is None or valid is None):
        raise ValueError("hard_splat: finish needs the source variance and validity")
    B, H, W = d.shape
    threads = thread_count(threads)
    dn = d.numpy()
    okn = valid.numpy() if valid is not None else np.ones((B, 1, W), np.bool_)
    varn = var.numpy() if var is not None else np.zeros((B, 1, 1), np.float32)
    An, an, Gn, en = (t.numpy() for t in (A, a, G, e))
    tol = _F(surface_tolerance)
    disparity = np.empty((B, H, W), np.float32)
    variance = np.empty((B, H, W), np.float32)
    confidence = np.empty((B, H, W), np.float32)
    landed = np.empty((B, H, W), np.bool_)
    hole = np.empty((B, H, W), np.bool_)
    bands = frame_bands(H, threads)
    noise, hole_var = _F(process_noise), _F(hole_variance)
    # (iterations -1: no finishing step)
    close = (-1, _F(0.0), _F(0.0), _F(0.0), _F(0.0)) if finish is None else (
        int(finish[0]), _F(finish[1]), _F(finish[2]), _F(finish[3]), _F(finish[4]))

    def item(i: int, run) -> bool:
        key_src, key_new, var_p, zbuf, at = _workspace(H, W, var is not None)
        if any(run(lambda band: _move_sources(dn[i], okn[i], varn[i], var is not None, An[i], an[i],
                                              band[0], band[1], key_src, key_new, var_p, at), bands)):
            return False
        zbuf.fill(-1)
        _scatter(at, key_new, zbuf, var_p, var is not None)
        later = np.empty(H, np.bool_)
        outs = (landed[i], hole[i], disparity[i], variance[i], confidence[i])
        source = (dn[i], varn[i], okn[i])
        run(lambda band: _targets(zbuf, key_src, key_new, var_p, var is not None, An[i], an[i], Gn[i], en[i], tol,
                                  refine_iterations, band[0], band[1], fill_holes, noise, hole_var, later, *outs,
                                  close, source), bands)
        if later.any():  # rows without a landed pixel: the smallest landed value of the image (0 if none)
            values = disparity[i][~hole[i]]  # (the splat's landed pixels: finishing changes only holes' values)
            _fill(_F(values.min()) if values.size else _F(0.0), hole_var, later, *outs[2:])
            if finish is not None:  # those rows finished now, after their fill
                for y in np.flatnonzero(later):
                    _cracks._finish(*source, Gn[i], en[i], close[0], *close[1:3], noise, *close[3:], y, y + 1,
                                 disparity[i], variance[i], landed[i], confidence[i])
        return True

    workers = Workers(threads)
    if not all(item(i, workers.map) for i in range(B)):
        return None
    as_t = torch.from_numpy
    return as_t(disparity), as_t(variance), as_t(confidence), as_t(landed), as_t(hole)


# The finishing step's kernels (crack closing). Imported last: _predict_numba takes its constants from this module,
# and the kernels above look the module's functions up when they are first compiled.
from . import _predict_numba as _cracks  # noqa: E402
