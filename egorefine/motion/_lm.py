"""The ``"exact"`` method's refinement: Levenberg-Marquardt on SE(3) over the reprojection error.

Per-item acceptance of each step and per-item damping, a fixed number of iterations (shapes and time stay fixed),
a left-multiplied increment retracted by a fixed-degree Taylor exponential (:func:`_twist_exp`).
:mod:`egorefine.motion.solve` explains the method; :mod:`egorefine.motion._lm_numba` repeats it compiled.
"""

from __future__ import annotations

import torch

from ..core import eps_like
from ._linear import _jacobi_scaled, _solve_normal
from .robust import robust_loss, robust_weight

# --------------------------------------------------------------------------- exact (SE(3) LM)


# Per-feature state of the LM, packed in one (B, N, 16) tensor so that accepting a step is a
# single torch.where: [du/d(delta) (6), r_u, dv/d(delta) (6), r_v, |r|, in front].
_RN, _FRONT = 14, 15


def _reprojection(motion: torch.Tensor, rays: torch.Tensor, target: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Reprojection residuals of frame ``t-1``'s points in frame ``t`` and their Jacobians, packed ``(B, N, 16)``.

    ``rays (B, N, 4) = (x_n, y_n, 1, 1/Z)``: the point of frame ``t-1`` is ``Z * (x_n, y_n, 1)``;
    projection is invariant to scale, so ``Q = (R P + t) / Z = R (x_n, y_n, 1) + t / Z`` is
    projected instead (finite for points at infinity, ``1/Z = 0``). For a left increment
    ``exp(delta) [R | t]`` with ``delta = (rho, phi)``: ``dQ = rho / Z + phi x Q``. A point
    that ends up behind the camera gets residual norm 1e3 px (a far outlier) and front 0.
    """
    Q = rays @ motion[:, :3, :].transpose(1, 2)  # (B, N, 3)
    X, Y, Z = Q.unbind(-1)
    front = Z > eps_like(Q)
    a = torch.where(front, Z, torch.ones_like(Z)).reciprocal()  # clamp: no division by Z <= 0
    xq, yq = X * a, Y * a
    ar = a * rays[..., 3]
    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]
    ru = fx * xq + K[:, 0, 2, None] - target[..., 0]
    rv = fy * yq + K[:, 1, 2, None] - target[..., 1]
    rn = torch.where(front, (ru * ru + rv * rv + torch.finfo(Q.dtype).tiny).sqrt(), torch.full_like(ru, 1e3))
    zero = torch.zeros_like(xq)
    fxe, fye = fx.expand_as(xq), fy.expand_as(xq)
    xy = xq * yq
    return torch.stack(
        [fxe * ar, zero, -fxe * xq * ar, -fxe * xy, fxe * (1 + xq * xq), -fxe * yq, ru,
         zero, fye * ar, -fye * yq * ar, -fye * (1 + yq * yq), fye * xy, fye * xq, rv,
         rn, front.to(Q.dtype)], dim=-1,
    )  # fmt: skip


def _irls_system(S: torch.Tensor, gate: torch.Tensor, loss: str, scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted normal equations ``(J^T W J, J^T W r)`` from the packed state, one matmul of ``[J | r]``."""
    B, N, _ = S.shape
    omega = gate * S[..., _FRONT] * robust_weight(S[..., _RN], loss, scale)  # IRLS weights
    Jr = S[..., :14].reshape(B, 2 * N, 7)
    G = (Jr * omega.repeat_interleave(2, dim=1)[..., None]).transpose(1, 2) @ Jr  # (B, 7, 7)
    return G[:, :6, :6], G[:, :6, 6]


_GENERATORS: dict[tuple[torch.device, torch.dtype], torch.Tensor] = {}


def _se3_generators(like: torch.Tensor) -> torch.Tensor:
    """The 6 generators of se(3) as ``(6, 16)``: ``delta @ G`` is the 4x4 twist matrix of ``delta = (rho, phi)``.

    Built once per device and dtype (a CUDA graph may not record the host-to-device copies of building it).
    """
    key = (like.device, like.dtype)
    if key not in _GENERATORS:
        G = torch.zeros(6, 4, 4, dtype=like.dtype)
        G[0, 0, 3] = G[1, 1, 3] = G[2, 2, 3] = 1.0
        G[3, 2, 1], G[3, 1, 2] = 1.0, -1.0
        G[4, 0, 2], G[4, 2, 0] = 1.0, -1.0
        G[5, 1, 0], G[5, 0, 1] = 1.0, -1.0
        _GENERATORS[key] = G.view(6, 16).to(like.device)
    return _GENERATORS[key]


def _twist_exp(delta: torch.Tensor, G: torch.Tensor, halvings: int = 3, degree: int = 8) -> torch.Tensor:
    """``exp`` of the 4x4 twist matrices of ``delta (B, 6)`` (``G`` from :func:`_se3_generators`): ``(B, 4, 4)``.

    Scaling and squaring with a fixed Taylor degree, in batched matrix products only: the result of an item does
    not depend on its batch (``torch.linalg.matrix_exp`` rounds differently for B = 1 and B = 2, which lets the
    refiner's batch items drift apart over a few frames), and it is cheaper than ``matrix_exp`` for 4x4 matrices.
    With ``|X| / 2^halvings <= 0.4`` (a rotation up to ~180 degrees) the truncation is below 1e-8; LM increments
    are far smaller.
    """
    X = (delta @ G).view(-1, 4, 4) * (0.5**halvings)
    eye = torch.eye(4, dtype=X.dtype, device=X.device).expand_as(X)
    E = eye + X / degree  # Horner: I + X (I + X/2 (I + X/3 (...)))
    for k in range(degree - 1, 0, -1):
        E = torch.baddbmm(eye, X, E, alpha=1.0 / k)
    for _ in range(halvings):
        E = E @ E
    return E


def _levenberg_marquardt(
    motion: torch.Tensor,
    rays: torch.Tensor,
    target: torch.Tensor,
    K: torch.Tensor,
    stages: list[tuple[torch.Tensor, str, int]],
    scale: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """LM on SE(3) with per-item acceptance; ``stages`` = [(gate (B,N), loss, iterations), ...].

    Returns the motion, the packed per-feature state ``(B, N, 16)`` and the scaled normal matrix.
    """
    B = motion.shape[0]
    lam = torch.full((B,), 1e-4, dtype=motion.dtype, device=motion.device)
    S = _reprojection(motion, rays, target, K)
    G = _se3_generators(motion)
    for gate, loss, iters in stages:
        cost = (gate * robust_loss(S[..., _RN], loss, scale)).sum(1)
        for _ in range(iters):
            # Jacobians -> weighted normal equations (IRLS) -> damped solve -> retraction.
            H, g = _irls_system(S, gate, loss, scale)
            delta, _ = _solve_normal(H, -g, lam)
            # Left-multiplied increment exp(delta) (the same map as geometry.se3_exp).
            trial = _twist_exp(delta, G) @ motion
            S_new = _reprojection(trial, rays, target, K)
            cost_new = (gate * robust_loss(S_new[..., _RN], loss, scale)).sum(1)
            # Keep the step only where that item's robust cost drops; adapt its damping.
            accept = (cost_new < cost) & torch.isfinite(cost_new)
            motion = torch.where(accept[:, None, None], trial, motion)
            S = torch.where(accept[:, None, None], S_new, S)
            cost = torch.where(accept, cost_new, cost)
            lam = torch.where(accept, lam * 0.2, lam * 5.0).clamp(1e-9, 1e6)
    gate, loss, _ = stages[-1]
    H, _ = _irls_system(S, gate, loss, scale)  # at the final state, for the quality flag
    return motion, S, _jacobi_scaled(H)[0]


def _two_stage_lm(motion: torch.Tensor, rays: torch.Tensor, target: torch.Tensor, K: torch.Tensor,
                  gate_huber: torch.Tensor, gate_late: torch.Tensor, *, loss: str, first: int, second: int,
                  scale: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The exact method's LM: ``first`` Huber iterations on ``gate_huber``, then ``second`` with ``loss``."""
    return _levenberg_marquardt(motion, rays, target, K, [(gate_huber, "huber", first), (gate_late, loss, second)],
                                scale)
