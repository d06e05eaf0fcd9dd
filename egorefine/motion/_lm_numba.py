"""CPU inference path of the exact solve's Levenberg-Marquardt (egorefine.motion.solve) compiled with numba.

The torch version is ~100 small operator launches per iteration on ``(B, N, 16)`` tensors; the
arithmetic is a few thousand multiply-adds per feature, so on the CPU the launches set its time
(about half of the exact solve's). Here one loop over the features per step does the reprojection
with its Jacobians, the IRLS normal equations and the robust cost, and the 6x6 damped solve and
the SE(3) retraction are unrolled small-matrix code. The steps, acceptance rule and damping
schedule are the torch version's (:func:`egorefine.motion._lm._levenberg_marquardt`), computed
in float64 whatever the input dtype; results agree with the torch path to its float rounding
(a test compares them), not bit for bit.

``AVAILABLE`` is False when numba cannot be imported; callers then use the torch path, which
stays the reference for GPU tensors and autograd.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core import eps_like
from ..core._jit import AVAILABLE
from ..core._jit import jit as _jit
from .robust import HUBER_K, TUKEY_C

__all__ = ["AVAILABLE", "two_stage_lm"]

_LOSS_CODES = {"l2": 0, "huber": 1, "tukey": 2}

if AVAILABLE:

    @_jit(inline="always")
    def _rho(r, code, k):
        """robust.robust_loss for one residual norm (``k``: the kernel's scaled constant)."""
        if code == 0:
            return 0.5 * r * r
        if code == 1:
            return 0.5 * r * r if r <= k else k * (r - 0.5 * k)
        t = min(r / k, 1.0)
        s = 1.0 - t * t
        return k * k / 6.0 * (1.0 - s * s * s)

    @_jit(inline="always")
    def _weight(r, code, k):
        """robust.robust_weight for one residual norm."""
        if code == 0:
            return 1.0
        if code == 1:
            return k / max(r, k)
        t = min(r / k, 1.0)
        s = 1.0 - t * t
        return s * s

    @_jit
    def _reproject(M, rays, target, cam, eps, tiny, S):
        """_lm._reprojection for one item: the packed state ``S (N, 16)`` of the motion ``M (4, 4)``."""
        fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
        for i in range(rays.shape[0]):
            q = rays[i]
            X = M[0, 0] * q[0] + M[0, 1] * q[1] + M[0, 2] * q[2] + M[0, 3] * q[3]
            Y = M[1, 0] * q[0] + M[1, 1] * q[1] + M[1, 2] * q[2] + M[1, 3] * q[3]
            Z = M[2, 0] * q[0] + M[2, 1] * q[1] + M[2, 2] * q[2] + M[2, 3] * q[3]
            front = Z > eps
            a = 1.0 / Z if front else 1.0
            xq, yq = X * a, Y * a
            ar = a * q[3]
            ru = fx * xq + cx - target[i, 0]
            rv = fy * yq + cy - target[i, 1]
            s = S[i]
            # [du/d(delta) (6), r_u, dv/d(delta) (6), r_v, |r|, in front], delta = (rho, phi)
            s[0], s[1], s[2] = fx * ar, 0.0, -fx * xq * ar
            s[3], s[4], s[5] = -fx * xq * yq, fx * (1 + xq * xq), -fx * yq
            s[6] = ru
            s[7], s[8], s[9] = 0.0, fy * ar, -fy * yq * ar
            s[10], s[11], s[12] = -fy * (1 + yq * yq), fy * xq * yq, fy * xq
            s[13] = rv
            s[14] = np.sqrt(ru * ru + rv * rv + tiny) if front else 1.0e3
            s[15] = 1.0 if front else 0.0

    @_jit
    def _cost(S, gate, code, k):
        total = 0.0
        for i in range(S.shape[0]):
            total += gate[i] * _rho(S[i, 14], code, k)
        return total

    @_jit
    def _system(S, gate, code, k, H, g):
        """IRLS normal equations ``H = sum w (Ju Ju^T + Jv Jv^T)``, ``g = sum w (Ju ru + Jv rv)``."""
        H[:] = 0.0
        g[:] = 0.0
        for i in range(S.shape[0]):
            s = S[i]
            w = gate[i] * s[15] * _weight(s[14], code, k)
            if w == 0.0:
                continue
            for a in range(6):
                ua, va = w * s[a], w * s[7 + a]
                g[a] += ua * s[6] + va * s[13]
                for b in range(a, 6):
                    H[a, b] += ua * s[b] + va * s[7 + b]
        for a in range(6):
            for b in range(a):
                H[a, b] = H[b, a]

    @_jit
    def _scale(H, eps, tiny, s):
        """_linear._jacobi_scaled: the scales ``s`` (unit diagonal of ``S H S``, the diagonal floored)."""
        top = H[0, 0]
        for a in range(1, 6):
            top = max(top, H[a, a])
        floor = eps * top + tiny
        for a in range(6):
            s[a] = 1.0 / np.sqrt(max(H[a, a], floor))

    @_jit
    def _damped_step(H, g, lam, eps, tiny, delta):
        """_linear._solve_normal(H, -g, lam): Jacobi scaling, ``+ lam I``, Cholesky, two triangular solves.
        A matrix that is not positive definite gives NaN (the step is then rejected, as in the torch path)."""
        s = np.empty(6)
        _scale(H, eps, tiny, s)
        L = np.zeros((6, 6))
        for a in range(6):
            for b in range(a + 1):
                v = H[a, b] * s[a] * s[b] + (lam if a == b else 0.0)
                for c in range(b):
                    v -= L[a, c] * L[b, c]
                if a == b:
                    L[a, a] = np.sqrt(v) if v > 0.0 else np.nan
                else:
                    L[a, b] = v / L[b, b]
        y = np.empty(6)
        for a in range(6):
            v = -g[a] * s[a]
            for c in range(a):
                v -= L[a, c] * y[c]
            y[a] = v / L[a, a]
        for a in range(5, -1, -1):
            v = y[a]
            for c in range(a + 1, 6):
                v -= L[c, a] * delta[c]
            delta[a] = v / L[a, a]
        for a in range(6):
            delta[a] *= s[a]

    @_jit
    def _matmul4(A, B, out):
        for r in range(4):
            for c in range(4):
                out[r, c] = A[r, 0] * B[0, c] + A[r, 1] * B[1, c] + A[r, 2] * B[2, c] + A[r, 3] * B[3, c]

    @_jit
    def _twist_exp(delta, E):
        """_lm._twist_exp: exp of the 4x4 twist matrix by 3 halvings and a degree-8 Taylor series (Horner)."""
        X = np.zeros((4, 4))
        f = 0.125  # 0.5 ** 3 halvings
        X[0, 3], X[1, 3], X[2, 3] = delta[0] * f, delta[1] * f, delta[2] * f
        X[2, 1], X[1, 2] = delta[3] * f, -delta[3] * f
        X[0, 2], X[2, 0] = delta[4] * f, -delta[4] * f
        X[1, 0], X[0, 1] = delta[5] * f, -delta[5] * f
        T = np.empty((4, 4))
        for r in range(4):
            for c in range(4):
                E[r, c] = (1.0 if r == c else 0.0) + X[r, c] / 8.0
        for k in range(7, 0, -1):
            _matmul4(X, E, T)
            for r in range(4):
                for c in range(4):
                    E[r, c] = (1.0 if r == c else 0.0) + T[r, c] / k
        for _ in range(3):
            _matmul4(E, E, T)
            E[:] = T

    @_jit
    def lm_item(M, rays, target, cam, gate_huber, gate_late, codes, ks, iters, eps, tiny, S, Hs):
        """Both stages of the LM for one batch item: ``M (4, 4)`` is updated in place, ``S (N, 16)`` receives the
        packed state and ``Hs (6, 6)`` the Jacobi-scaled normal matrix at the final state (also called by
        :mod:`egorefine.motion._solve_numba`, which runs the whole exact solve compiled)."""
        N = rays.shape[0]
        S_new = np.empty((N, 16))
        H = np.empty((6, 6))
        g = np.empty(6)
        delta = np.empty(6)
        E = np.empty((4, 4))
        trial = np.empty((4, 4))
        s = np.empty(6)
        lam = 1e-4
        _reproject(M, rays, target, cam, eps, tiny, S)
        for stage in range(2):
            gate = gate_huber if stage == 0 else gate_late
            code, k = codes[stage], ks[stage]
            cost = _cost(S, gate, code, k)
            for _ in range(iters[stage]):
                _system(S, gate, code, k, H, g)
                _damped_step(H, g, lam, eps, tiny, delta)
                _twist_exp(delta, E)
                _matmul4(E, M, trial)
                _reproject(trial, rays, target, cam, eps, tiny, S_new)
                cost_new = _cost(S_new, gate, code, k)
                if cost_new < cost and np.isfinite(cost_new):  # keep the step only where the cost drops
                    M[:] = trial
                    S[:] = S_new
                    cost = cost_new
                    lam *= 0.2
                else:
                    lam *= 5.0
                lam = min(max(lam, 1e-9), 1e6)
        # the scaled normal matrix at the final state, for the quality flag
        _system(S, gate_late, codes[1], ks[1], H, g)
        _scale(H, eps, tiny, s)
        for r in range(6):
            for c in range(6):
                Hs[r, c] = H[r, c] * s[r] * s[c]

    @_jit
    def _lm(motion, rays, target, cams, gates, codes, ks, iters, eps, tiny, S_out, Hs_out):
        """Both stages of the LM for every batch item; ``motion`` is updated in place."""
        for b in range(rays.shape[0]):
            lm_item(motion[b], rays[b], target[b], cams[b], gates[0, b], gates[1, b], codes, ks, iters, eps, tiny,
                    S_out[b], Hs_out[b])

def two_stage_lm(motion: torch.Tensor, rays: torch.Tensor, target: torch.Tensor, K: torch.Tensor,
                 gate_huber: torch.Tensor, gate_late: torch.Tensor, *, loss: str, first: int, second: int,
                 scale: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`egorefine.motion._lm._two_stage_lm` for CPU tensors without gradient, compiled.

    Args:
        motion: ``(B, 4, 4)`` start; rays ``(B, N, 4)``; target ``(B, N, 2)``; K ``(B, 3, 3)``;
            gate_huber, gate_late ``(B, N)``: the two stages' feature weights.
        loss, first, second, scale: the late stage's kernel and the two stages' iteration counts, the kernels' scale.

    Returns:
        ``(motion (B, 4, 4), packed state (B, N, 16), Jacobi-scaled normal matrix (B, 6, 6))`` in the input dtype.
    """
    dtype = motion.dtype

    def f64(t: torch.Tensor) -> np.ndarray:
        return np.ascontiguousarray(t.detach().numpy(), dtype=np.float64)

    m = f64(motion).copy()
    cams = np.stack([f64(K[:, 0, 0]), f64(K[:, 1, 1]), f64(K[:, 0, 2]), f64(K[:, 1, 2])], axis=1)
    gates = np.stack([f64(gate_huber), f64(gate_late)])
    codes = np.array([_LOSS_CODES["huber"], _LOSS_CODES[loss]], dtype=np.int64)
    kernel = {0: 1.0, 1: HUBER_K, 2: TUKEY_C}
    ks = np.array([kernel[c] * scale for c in codes], dtype=np.float64)
    B, N = rays.shape[:2]
    S = np.empty((B, N, 16))
    Hs = np.empty((B, 6, 6))
    _lm(m, f64(rays), f64(target), cams, gates, codes, ks, np.array([first, second], dtype=np.int64),
        eps_like(motion), float(torch.finfo(dtype).tiny), S, Hs)
    return tuple(torch.from_numpy(x).to(dtype) for x in (m, S, Hs))
