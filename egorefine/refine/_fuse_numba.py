"""CPU inference path of :func:`egorefine.refine.correct_disparity`'s Kalman rule (and of the refiner's
take-over of hole measurements, :func:`take_measurements`), compiled with numba.

One loop over the pixels with the torch path's float32 operations in its order (clamps, innovation,
gate, gain, reset, hole take-over, variance floor, validity): the outputs are equal to the torch
path's bit for bit (a test compares them). In torch the rule is some twenty full-map operations,
half of them ``torch.where`` on boolean masks, which is slow on the CPU; here it is one pass.
Rows run as nogil bands on :class:`egorefine.core._jit.Workers`.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core._jit import AVAILABLE, Workers
from ..core._jit import bands as _bands
from ..core._jit import jit as _jit

__all__ = ["AVAILABLE", "confidence", "kalman_fuse", "take_measurements"]

_F = np.float32


if AVAILABLE:

    @_jit
    def _kalman(e, s, m_ok, p_ok, P, R, count, start, stop, prm, has_max, e_out, P_out, c_out, v_out):
        """Flat pixels ``[start, stop)``; ``prm``: ``(kalman_gate, reset_after, min_variance, max_unverified)``."""
        gate, reset_after, floor, most = prm[0], prm[1], prm[2], prm[3]
        for i in range(start, stop):
            ei, si = e[i], s[i]
            Pi, Ri = max(P[i], floor), max(R[i], floor)
            mo, po = m_ok[i], p_ok[i]
            ci = count[i]
            both = mo and po
            innovation = si - ei
            S = Pi + Ri
            outlier = both and abs(innovation) > gate * np.sqrt(S)
            c_next = ci + _F(1.0)
            reset = outlier and c_next >= reset_after
            G = Pi / S
            e_new, P_new = ei, Pi
            if both and not outlier:
                e_new = ei + G * innovation
                P_new = (_F(1.0) - G) * Pi
            if reset:
                e_new, P_new = si, Ri
            c_new = c_next if (outlier and not reset) else (_F(0.0) if both else ci)
            if mo and not po:  # a hole in the prediction: take the measurement
                e_new, P_new, c_new = si, Ri, _F(0.0)
            e_out[i] = e_new
            P_out[i] = max(P_new, floor)
            c_out[i] = c_new
            v_out[i] = mo or (po and (not has_max or Pi <= most))

    @_jit
    def _take(d, var, ok, count, md, mvar, mok, pd, phole, start, stop, prm, has_margin, d_out, var_out, ok_out,
              c_out, conf_out):
        """Flat pixels ``[start, stop)``; ``prm``: ``(max_variance, background_margin)``."""
        most, margin = prm[0], prm[1]
        for i in range(start, stop):
            precise = mvar[i] <= most
            background = has_margin and phole[i] and md[i] <= pd[i] + margin
            take = (not ok[i]) and mok[i] and (precise or background)
            v = mvar[i] if take else var[i]
            valid = ok[i] or take
            d_out[i] = md[i] if take else d[i]
            var_out[i] = v
            c_out[i] = _F(0.0) if take else count[i]
            ok_out[i] = valid
            conf_out[i] = _F(1.0) / (_F(1.0) + v) if valid else _F(0.0)


    @_jit
    def _confidence(valid, variance, start, stop, out):
        """Flat pixels ``[start, stop)``: ``1 / (1 + variance)`` where valid, else 0."""
        for i in range(start, stop):
            out[i] = _F(1.0) / (_F(1.0) + variance[i]) if valid[i] else _F(0.0)


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
    threads = max(1, threads or torch.get_num_threads())
    chunks = _bands(n, threads) if n >= 65536 else [(0, n)]
    Workers(threads).map(lambda c: _kalman(*flat, c[0], c[1], prm, has_max, *outs), chunks)
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
    threads = max(1, threads or torch.get_num_threads())
    chunks = _bands(n, threads) if n >= 65536 else [(0, n)]
    Workers(threads).map(lambda c: _take(*flat, c[0], c[1], prm, has_margin, *outs), chunks)
    return tuple(torch.from_numpy(o).view(shape) for o in outs)


def confidence(valid: torch.Tensor, variance: torch.Tensor, threads: int | None = None) -> torch.Tensor:
    """``1 / (1 + variance)`` where ``valid`` (bool), else 0, of float32 CPU maps, in one pass."""
    shape = variance.shape
    v, var = valid.detach().contiguous().reshape(-1).numpy(), variance.detach().contiguous().reshape(-1).numpy()
    out = np.empty(var.shape[0], np.float32)
    threads = max(1, threads or torch.get_num_threads())
    chunks = _bands(out.shape[0], threads) if out.shape[0] >= 65536 else [(0, out.shape[0])]
    Workers(threads).map(lambda c: _confidence(v, var, c[0], c[1], out), chunks)
    return torch.from_numpy(out).view(shape)
