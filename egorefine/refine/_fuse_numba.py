"""CPU inference path of :func:`egorefine.refine.correct_disparity`'s Kalman rule, and of the refiner's steps
around it (``refine._steps``): the take-over of hole measurements (:func:`take_measurements`), the confidence map
(:func:`confidence`) and a verification's recovery rules (:func:`overrule`), compiled with numba.

Each is one loop over the pixels with the torch path's float32 operations in its order (clamps, innovation,
gate, gain, reset, hole take-over, variance floor, validity): the outputs are equal to the torch
path's bit for bit (tests compare them). In torch the Kalman rule is some twenty full-map operations,
half of them ``torch.where`` on boolean masks, which is slow on the CPU; here it is one pass.
Rows run as nogil bands on :class:`egorefine.core._jit.Workers`.

The loops are written for SIMD code: each works on the views ``[start:stop]`` of its arrays with an index from 0
(an index that might be negative makes numba wrap it around, which keeps the loop scalar), decisions are selects
rather than branches, and a division by zero gives inf as in torch (``error_model="numpy"``).
"""

from __future__ import annotations

import numpy as np
import torch

from ..core._jit import AVAILABLE, Workers, thread_count
from ..core._jit import jit as _jit
from ..core._jit import split as _split

__all__ = ["AVAILABLE", "confidence", "kalman_fuse", "overrule", "plausible", "take_measurements"]

_F = np.float32


if AVAILABLE:

    @_jit(error_model="numpy")
    def _kalman(e, s, m_ok, p_ok, P, R, count, start, stop, prm, has_max, e_out, P_out, c_out, v_out):
        """Flat pixels ``[start, stop)``; ``prm``: ``(kalman_gate, reset_after, min_variance, max_unverified)``."""
        gate, reset_after, floor, most = prm[0], prm[1], prm[2], prm[3]
        e, s, m_ok, p_ok, P, R, count = (e[start:stop], s[start:stop], m_ok[start:stop], p_ok[start:stop],
                                         P[start:stop], R[start:stop], count[start:stop])
        e_out, P_out, c_out, v_out = e_out[start:stop], P_out[start:stop], c_out[start:stop], v_out[start:stop]
        for i in range(e.shape[0]):
            ei, si = e[i], s[i]
            Pi, Ri = max(P[i], floor), max(R[i], floor)
            mo, po = m_ok[i], p_ok[i]
            ci = count[i]
            both = mo & po
            innovation = si - ei
            S = Pi + Ri
            outlier = both & (abs(innovation) > gate * np.sqrt(S))
            c_next = ci + _F(1.0)
            reset = outlier & (c_next >= reset_after)
            G = Pi / S
            fuse = both & (not outlier)
            measurement = reset | (mo & (not po))  # a reset, or a hole in the prediction: take the measurement
            e_new = si if measurement else (ei + G * innovation if fuse else ei)
            P_new = Ri if measurement else ((_F(1.0) - G) * Pi if fuse else Pi)
            e_out[i] = e_new
            P_out[i] = max(P_new, floor)
            c_out[i] = c_next if (outlier & (not reset)) else (_F(0.0) if mo else ci)
            v_out[i] = mo | (po & ((not has_max) | (Pi <= most)))

    @_jit(error_model="numpy")
    def _take(d, var, ok, count, md, mvar, mok, pd, phole, start, stop, prm, has_margin, d_out, var_out, ok_out,
              c_out, conf_out):
        """Flat pixels ``[start, stop)``; ``prm``: ``(max_variance, background_margin)``."""
        most, margin = prm[0], prm[1]
        d, var, ok, count = d[start:stop], var[start:stop], ok[start:stop], count[start:stop]
        md, mvar, mok, pd, phole = md[start:stop], mvar[start:stop], mok[start:stop], pd[start:stop], phole[start:stop]
        d_out, var_out, ok_out = d_out[start:stop], var_out[start:stop], ok_out[start:stop]
        c_out, conf_out = c_out[start:stop], conf_out[start:stop]
        for i in range(d.shape[0]):
            precise = mvar[i] <= most
            background = has_margin & phole[i] & (md[i] <= pd[i] + margin)
            take = (not ok[i]) & mok[i] & (precise | background)
            v = mvar[i] if take else var[i]
            valid = ok[i] | take
            d_out[i] = md[i] if take else d[i]
            var_out[i] = v
            c_out[i] = _F(0.0) if take else count[i]
            ok_out[i] = valid
            c = _F(1.0) / (_F(1.0) + v)
            conf_out[i] = c if valid else _F(0.0)

    @_jit(error_model="numpy")
    def _confidence(valid, variance, start, stop, out):
        """Flat pixels ``[start, stop)``: ``1 / (1 + variance)`` where valid, else 0."""
        valid, variance, out = valid[start:stop], variance[start:stop], out[start:stop]
        for i in range(out.shape[0]):
            c = _F(1.0) / (_F(1.0) + variance[i])
            out[i] = c if valid[i] else _F(0.0)

    @_jit(inline="always")
    def _rule(ci, pi, mi, region, whole, kept):
        """The recovery rules of one pixel: ``mi`` (the measurement) where the item restarts (``whole``) or in a
        region of an item not kept, ``pi`` (the prediction) where the item is kept, else ``ci``."""
        return mi if (whole | (region & (not kept))) else (pi if kept else ci)

    @_jit
    def _overrule(corrected, predicted, measured, regions, keep, restart, start, stop, out):
        """One map of the recovery rules, items ``(B, N)`` and flat pixels ``[start, stop)``: an item in
        ``restart`` takes ``measured``, one in ``keep`` ``predicted``, the others ``measured`` in ``regions`` and
        ``corrected`` elsewhere. ``predicted`` and ``measured`` None: 0 in their place (the outlier count). Masks
        come as bytes (uint8 0/1: numba's bool arrays make a select of bools scalar code)."""
        for b in range(corrected.shape[0]):
            whole, kept = restart[b] != 0, (keep[b] != 0) & (restart[b] == 0)
            c, r, o = corrected[b, start:stop], regions[b, start:stop], out[b, start:stop]
            if predicted is None:  # (measured too)
                zero = c.dtype.type(0)  # (0 of the count's dtype)
                for i in range(c.shape[0]):
                    ci = c[i]  # (loaded whatever is chosen: a load under a condition keeps the loop scalar)
                    o[i] = _rule(ci, zero, zero, r[i] != 0, whole, kept)
            else:
                p, m = predicted[b, start:stop], measured[b, start:stop]
                for i in range(c.shape[0]):
                    o[i] = _rule(c[i], p[i], m[i], r[i] != 0, whole, kept)

    @_jit
    def _overrule_inplace(corrected, predicted, measured, regions, keep, restart, start, stop):
        """_overrule with ``out`` = ``corrected``, a block of pixels at a time through a small buffer: a loop that
        stores a select of a value and the one it loads from the same place is turned into conditional stores,
        which stay scalar code; two loops (the selects into the buffer, its copy back) are SIMD code."""
        block = 256
        buf = np.empty(block, corrected.dtype)
        for b in range(corrected.shape[0]):
            whole, kept = restart[b] != 0, (keep[b] != 0) & (restart[b] == 0)
            c, r = corrected[b, start:stop], regions[b, start:stop]
            p, m = (c, c) if predicted is None else (predicted[b, start:stop], measured[b, start:stop])
            zero = c.dtype.type(0)
            for s0 in range(0, c.shape[0], block):
                n = min(block, c.shape[0] - s0)
                cb, rb, pb, mb = c[s0:s0 + n], r[s0:s0 + n], p[s0:s0 + n], m[s0:s0 + n]
                if predicted is None:  # (measured too: the outlier count, 0 where taken)
                    for i in range(n):
                        buf[i] = _rule(cb[i], zero, zero, rb[i] != 0, whole, kept)
                else:
                    for i in range(n):
                        buf[i] = _rule(cb[i], pb[i], mb[i], rb[i] != 0, whole, kept)
                for i in range(n):
                    cb[i] = buf[i]

    @_jit
    def _within(x, low, high):
        """Whether every entry of the flat ``x`` lies in ``[low, high]`` (NaN does not)."""
        inside = True
        for i in range(x.shape[0]):
            v = x[i]
            inside &= (v >= low) & (v <= high)
        return inside


def _bytes(a: np.ndarray) -> np.ndarray:
    """A bool array's bytes (uint8 0/1, a view), other arrays as they are."""
    return a.view(np.uint8) if a.dtype == np.bool_ else a


def kalman_fuse(e: torch.Tensor, s: torch.Tensor, m_ok: torch.Tensor, p_ok: torch.Tensor, P: torch.Tensor,
                R: torch.Tensor, count: torch.Tensor, kalman_gate: float, reset_after: int, min_variance: float,
                max_unverified_variance: float | None, threads: int | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The Kalman rule on float32 CPU maps ``(B, 1, H, W)`` (bool masks): ``(disparity, variance, valid, count)``."""
    shape = e.shape
    flat = [t.detach().contiguous().reshape(-1).numpy() for t in (e, s, m_ok, p_ok, P, R, count)]
    n = flat[0].shape[0]
    outs = (np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.bool_))
    has_max = max_unverified_variance is not None
    prm = np.array([kalman_gate, reset_after, min_variance, max_unverified_variance if has_max else 0.0], np.float32)
    threads = thread_count(threads)
    Workers(threads).map(lambda c: _kalman(*flat, c[0], c[1], prm, has_max, *outs), _split(n, threads))
    d, var, cnt, valid = (torch.from_numpy(o).view(shape) for o in outs)
    return d, var, valid, cnt


def take_measurements(disparity: torch.Tensor, variance: torch.Tensor, valid: torch.Tensor, count: torch.Tensor,
                      meas_disparity: torch.Tensor, meas_variance: torch.Tensor, meas_valid: torch.Tensor,
                      pred_disparity: torch.Tensor, pred_hole: torch.Tensor, max_variance: float,
                      background_margin: float | None, threads: int | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The refiner's take-over of hole measurements (``refiner._take_hole_measurements``) on float32 CPU maps
    ``(B, 1, H, W)`` (bool masks): new ``(disparity, variance, valid, count, confidence)`` in one pass."""
    shape = disparity.shape
    flat = [t.detach().contiguous().reshape(-1).numpy() for t in (
        disparity, variance, valid, count, meas_disparity, meas_variance, meas_valid, pred_disparity, pred_hole)]
    n = flat[0].shape[0]
    outs = (np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.bool_), np.empty(n, np.float32),
            np.empty(n, np.float32))
    has_margin = background_margin is not None
    prm = np.array([max_variance, background_margin if has_margin else 0.0], np.float32)
    threads = thread_count(threads)
    Workers(threads).map(lambda c: _take(*flat, c[0], c[1], prm, has_margin, *outs), _split(n, threads))
    return tuple(torch.from_numpy(o).view(shape) for o in outs)


def confidence(valid: torch.Tensor, variance: torch.Tensor, threads: int | None = None) -> torch.Tensor:
    """``1 / (1 + variance)`` where ``valid`` (bool), else 0, of float32 CPU maps, in one pass."""
    shape = variance.shape
    v, var = valid.detach().contiguous().reshape(-1).numpy(), variance.detach().contiguous().reshape(-1).numpy()
    out = np.empty(var.shape[0], np.float32)
    threads = thread_count(threads)
    Workers(threads).map(lambda c: _confidence(v, var, c[0], c[1], out), _split(out.shape[0], threads))
    return torch.from_numpy(out).view(shape)


def overrule(maps: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor],
             predicted: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
             measured: tuple[torch.Tensor, torch.Tensor, torch.Tensor], keep: torch.Tensor, restart: torch.Tensor,
             regions: torch.Tensor, threads: int | None = None, inplace: bool = False
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A verification's recovery rules (``refine._steps._overrule``) on CPU maps ``(B, 1, H, W)``: ``maps`` the
    corrected ``(disparity, variance, valid, outliers)``, ``predicted`` and ``measured`` ``(disparity, variance,
    valid)`` (float32, bool masks), ``regions`` bool, ``keep`` and ``restart`` ``(B,)`` bool; new ``maps``, or with
    ``inplace`` (contiguous ``maps`` that nothing else reads) ``maps`` themselves, changed."""
    B, shape = maps[0].shape[0], maps[0].shape
    items = [_bytes(t.detach().contiguous().reshape(B, -1).numpy())
             for t in (*maps, *predicted, *measured, regions)]
    corrected, pm, mm, reg = items[:4], items[4:7], items[7:10], items[10]
    flags = [_bytes(t.detach().contiguous().numpy()) for t in (keep, restart)]
    threads = thread_count(threads)
    work = [(k, c) for k in range(4) for c in _split(reg.shape[1], threads)]
    if inplace:
        Workers(threads).map(lambda job: _overrule_inplace(corrected[job[0]], pm[job[0]] if job[0] < 3 else None,
                                                           mm[job[0]] if job[0] < 3 else None, reg, *flags,
                                                           *job[1]), work)
        return maps
    outs = [np.empty_like(c) for c in corrected]
    Workers(threads).map(lambda job: _overrule(corrected[job[0]], pm[job[0]] if job[0] < 3 else None,
                                               mm[job[0]] if job[0] < 3 else None, reg, *flags, *job[1],
                                               outs[job[0]]), work)
    return tuple(torch.from_numpy(o).view(m.dtype).view(shape) for o, m in zip(outs, maps, strict=True))


def plausible(maps: tuple[torch.Tensor, ...], variances: tuple[torch.Tensor | None, ...]) -> bool:
    """Whether the float32 CPU ``maps`` are finite and the ``variances`` (None entries skipped) finite and
    ``>= 0``: the tests of :func:`egorefine.core.check_finite` and :func:`~egorefine.core.check_variance` in one
    compiled pass per tensor, without their messages (a caller that gets False runs those to raise)."""
    top = np.finfo(np.float32).max  # (float32 bounds: float64 ones would convert every entry)
    return (all(_within(t.detach().contiguous().reshape(-1).numpy(), -top, top) for t in maps)
            and all(_within(t.detach().contiguous().reshape(-1).numpy(), _F(0.0), top)
                    for t in variances if t is not None))
