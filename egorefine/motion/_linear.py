"""Solves of the linear motion model (docs/method.md eq. 3) and the linear algebra the SE(3) refinement shares.

The normal equations are Jacobi-scaled (unit diagonal) and damped by a small multiple of the identity before a
batched Cholesky factorisation (:func:`_solve_normal`), so every solve is finite; :func:`_well_conditioned` flags
the nearly singular ones. :func:`_ransac` is the ``"robust"`` method's batched MSAC around eq. (3).
:mod:`egorefine.motion.solve` explains the methods; :mod:`egorefine.motion._solve_numba` repeats these steps
compiled.
"""

from __future__ import annotations

import torch

from ..core import eps_like

# --------------------------------------------------------------------------- linear algebra


def _solve_normal(H: torch.Tensor, g: torch.Tensor, damping: torch.Tensor | float) -> tuple[torch.Tensor, torch.Tensor]:
    """Solve ``(H + damping * diag(H)) x = g`` for SPD ``H (..., 6, 6)``; returns ``x`` and the scaled ``H``.

    Jacobi scaling makes the diagonal 1, so a damping relative to it is unit-free
    (Marquardt's form); a tiny floor on the diagonal keeps unobservable unknowns (an
    all-zero column, e.g. translation from points at infinity) at exactly zero instead
    of dividing by zero.
    """
    Hs, s = _jacobi_scaled(H)
    eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
    if isinstance(damping, torch.Tensor):
        damping = damping[..., None, None]
    L, _ = torch.linalg.cholesky_ex(Hs + damping * eye)
    # two triangular solves rather than cholesky_solve: for batches on CUDA that one runs MAGMA, which allocates
    # memory on every call, so a CUDA graph cannot record it (cuBLAS's batched triangular solve it can)
    y = torch.linalg.solve_triangular(L, (g * s)[..., None], upper=False)
    x = torch.linalg.solve_triangular(L.mT, y, upper=True)[..., 0] * s
    return x, Hs


def _jacobi_scaled(H: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``S H S`` with unit diagonal and the scales ``s`` (``S = diag(s)``); the diagonal is floored."""
    diag = H.diagonal(dim1=-2, dim2=-1)
    floor = eps_like(H) * diag.amax(-1, keepdim=True).detach() + torch.finfo(H.dtype).tiny
    s = diag.clamp_min(floor).rsqrt()
    return H * s[..., :, None] * s[..., None, :], s


def _well_conditioned(Hs: torch.Tensor, rcond: float) -> torch.Tensor:
    """``(B,)`` bool: the scaled normal matrix has reciprocal condition number above ``rcond``."""
    ev = torch.linalg.eigvalsh(Hs.detach())
    ok = ev[..., 0] > rcond * ev[..., -1].clamp_min(torch.finfo(Hs.dtype).tiny)
    return ok & torch.isfinite(ev).all(-1)


def _normal_equations(A: torch.Tensor, b: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``A^T W A`` and ``A^T W b`` of stacked rows ``A (B, M, 6)``, ``b (B, M)``, ``w (B, M)``.

    One product of ``[A | b]`` with itself: a separate matrix-vector product for ``A^T W b`` is computed by
    another BLAS kernel for a batch of one than for larger batches, so an item's result would depend on its batch.
    """
    Ab = torch.cat([A, b[..., None]], dim=-1)
    G = (Ab * w[..., None]).transpose(-1, -2) @ Ab
    return G[..., :-1, :-1], G[..., :-1, -1]


def _linear_fit(A: torch.Tensor, b: torch.Tensor, w: torch.Tensor, damping: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Equation (3) by the normal equations: ``A (B, 2N, 6)``, ``b (B, 2N)``, feature weights ``w (B, N)``."""
    H, g = _normal_equations(A, b, w.repeat_interleave(2, dim=1))
    return _solve_normal(H, g, damping)


def _linear_residual(A: torch.Tensor, b: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Residual norms ``(B, N)`` in pixels of the linear model: ``|A x - b|`` per feature."""
    r = (A * x[:, None, :]).sum(-1) - b  # (not a matrix-vector product: see _normal_equations)
    return _norm2(r.view(r.shape[0], -1, 2))


def _norm2(r: torch.Tensor) -> torch.Tensor:
    """Norm over the last dim (size 2) with a finite gradient at zero."""
    return ((r * r).sum(-1) + torch.finfo(r.dtype).tiny).sqrt()


# --------------------------------------------------------------------------- robust (RANSAC)


def _ransac(
    A: torch.Tensor,
    b: torch.Tensor,
    w: torch.Tensor,
    hypotheses: int,
    threshold: float,
    seed: int,
    damping: float,
    refits: int = 2,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched MSAC over minimal sets of 3 features, then ``refits`` refits on the inliers.

    Returns the twist ``(B, 6)`` and the inlier weights ``(B, N)`` (input weight on inliers).
    """
    B, M, _ = A.shape
    N = M // 2
    valid = w > 0
    n_valid = valid.sum(1)
    # Valid features first (stable, so the order does not depend on the rest of the batch).
    order = torch.argsort(valid.to(torch.uint8), dim=1, descending=True, stable=True)
    gen = torch.Generator(device=A.device).manual_seed(seed)
    u = torch.rand(hypotheses, 3, generator=gen, device=A.device, dtype=A.dtype)  # shared by all items
    j = (u[None] * n_valid[:, None, None].to(A.dtype)).long()
    j = torch.minimum(j, (n_valid - 1).clamp_min(0)[:, None, None])
    idx = order.gather(1, j.view(B, -1))  # (B, hyp*3)
    A12 = A.view(B, N, 12).gather(1, idx[..., None].expand(-1, -1, 12)).view(B, hypotheses, 6, 6)
    b6 = b.view(B, N, 2).gather(1, idx[..., None].expand(-1, -1, 2)).reshape(B, hypotheses, 6)
    H, g = _normal_equations(A12, b6, torch.ones_like(b6))
    X, _ = _solve_normal(H, g, damping)  # (B, hyp, 6): every hypothesis of every item in one solve
    r = (A @ X.transpose(1, 2)) - b[..., None]  # (B, 2N, hyp)
    r2 = (r * r).view(B, N, 2, hypotheses).sum(2)  # (B, N, hyp)
    cost = (w[..., None] * r2.clamp(max=threshold**2)).sum(1)  # MSAC: truncated squared error
    best = cost.argmin(1)  # (B,)
    inl = valid & (r2.gather(2, best[:, None, None].expand(-1, N, 1))[..., 0] < threshold**2)
    for _ in range(refits - 1):
        x, _ = _linear_fit(A, b, w * inl, damping)
        inl = valid & (_linear_residual(A, b, x) < threshold)
    x, _ = _linear_fit(A, b, w * inl, damping)
    return x, w * inl


# RANSAC's fits on the inliers: "exact" refines anyway (and re-admits inliers with its own kernel), one is enough there
_REFITS = {"robust": 3, "exact": 1}
