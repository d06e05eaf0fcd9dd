"""Ego-motion of the stereo rig from features tracked between frames ``t-1`` and ``t``.

Three solvers share one entry point, :func:`solve_ego_motion`:

``"linear"``
    The paper's estimator: the weighted least squares of PAPER.md equation (3) over the
    motion field of equation (2), solved through the normal equations (at least 3
    features). Equation (2) is the instantaneous, first-order model, so for a finite frame
    step the estimate is biased by second-order terms (about ``x * (W / Z)^2`` pixels for a
    forward step ``W``); it is kept as the paper's baseline.
``"robust"``
    The same linear model inside a batched RANSAC (MSAC scoring): all hypotheses of all
    batch items, each from a minimal set of 3 features, are solved as one batched
    normal-equation solve; the best per item is refitted on its inliers (three times; once when
    "exact" follows, whose own kernel re-admits or drops features anyway). The random
    draws come from a seeded generator and are shared by all batch items (each item maps
    them onto its own valid features), so item ``b`` of a batch gives exactly what it gives
    alone.
``"exact"``
    Levenberg-Marquardt on SE(3), started from the robust solution: the 3-D points of frame
    ``t-1`` (unprojected with the previous disparity, in inverse depth so that far points
    stay finite) are moved by the motion and projected into frame ``t``; the reprojection
    error against the tracked positions is minimised with a left-multiplied SE(3)
    increment. A fixed number of iterations keeps shapes and time fixed; a step is taken
    per item only when it lowers that item's robust cost (per-item damping). The first
    half of the iterations uses a Huber kernel on the RANSAC inliers, the second half the
    chosen kernel (Tukey by default, which re-admits inliers that the first-order model
    wrongly rejected and drops moving objects and lost tracks).

Every result carries a per-item quality flag ``ok``: too few features (fewer than
``min_features`` with positive weight, e.g. a textureless or black frame), an (almost)
singular system (features on one 3-D line, all weights zero) or a non-finite solution
give ``ok = False`` and the identity motion instead of NaN, without raising.

On the CPU without gradient (float32/float64), every method runs as one compiled call per batch
(:mod:`egorefine.motion._solve_numba`, the same steps in float64) where :func:`egorefine.core.use_compiled`
allows it; the torch path stays the reference and serves GPU tensors, autograd and tracing.

The normal equations are Jacobi-scaled (unit diagonal) and damped by a small multiple of
the identity (the dtype's epsilon) before a batched Cholesky factorisation, so every
solve is finite; the flag comes from the reciprocal condition number of the scaled
matrix (its extreme eigenvalues), which is invariant to the units of the unknowns.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import torch
from torch import nn

from ..core import (
    ShapeError,
    ValueRangeError,
    _graphs,
    check_choice,
    check_finite,
    check_float,
    check_positive,
    check_same_device,
    check_shape,
    eps_like,
    use_compiled,
)
from ..geometry import motion_to_twist, twist_to_motion
from . import _lm_numba, _solve_numba
from .field import motion_field_jacobian
from .robust import LOSSES, robust_loss, robust_weight

__all__ = ["EgoMotion", "EgoMotionSolver", "solve_ego_motion", "METHODS"]

METHODS = ("linear", "robust", "exact")


class EgoMotion(NamedTuple):
    """Result of :func:`solve_ego_motion`.

    Attributes:
        motion: ``(B, 4, 4)`` rigid motion ``camera_t_T_camera_{t-1}`` (identity where not ``ok``).
        twist: ``(B, 6)`` the paper's ``(U, V, W, alpha, beta, gamma)``;
            ``motion == twist_to_motion(twist)`` (zero where not ``ok``).
        weights: ``(B, N)`` per-feature inlier weights used by the final fit (input weight
            times robust weight; 0 = rejected or no feature; all 0 where not ``ok``).
        ok: ``(B,)`` bool quality flag.
        num_inliers: ``(B,)`` long, features with positive final weight.
        rms: ``(B,)`` weighted RMS residual of the final fit in pixels (of the linear model
            for ``"linear"``/``"robust"``, the reprojection error for ``"exact"``).

    Example:
        >>> from egorefine.geometry import make_intrinsics
        >>> pts = torch.rand(1, 30, 2) * 300
        >>> res = solve_ego_motion(pts, pts, torch.full((1, 30), 8.0), make_intrinsics(400.0, 150.0, 150.0),
        ...                        torch.ones(1))
        >>> res.motion.shape, bool(res.ok), torch.allclose(res.motion, torch.eye(4)[None], atol=1e-4)
        (torch.Size([1, 4, 4]), True, True)
    """

    motion: torch.Tensor
    twist: torch.Tensor
    weights: torch.Tensor
    ok: torch.Tensor
    num_inliers: torch.Tensor
    rms: torch.Tensor


# --------------------------------------------------------------------------- input


def _check_inputs(
    points_prev: torch.Tensor,
    points_next: torch.Tensor,
    disparity_prev: torch.Tensor,
    K: torch.Tensor,
    baseline: torch.Tensor,
    weights: torch.Tensor | None,
    valid_prev: torch.Tensor | None,
    values: bool = True,
) -> None:
    """Shapes, dtypes and devices; with ``values`` also :func:`_check_values`."""
    dims = check_shape(points_prev, ["B", "N", "2"], "points_prev")
    check_shape(points_next, ["B", "N", "2"], "points_next", dims)
    check_shape(K, ["B", "3", "3"], "K", dims)
    check_shape(baseline, ["B"], "baseline", dims)
    if weights is not None:
        check_shape(weights, ["B", "N"], "weights", dims)
    if disparity_prev.dim() == 4:
        check_shape(disparity_prev, ["B", "1", "H", "W"], "disparity_prev", dims)
        if valid_prev is not None:
            check_shape(valid_prev, ["B", "1", "H", "W"], "valid_prev", dims)
    elif disparity_prev.dim() == 2:
        check_shape(disparity_prev, ["B", "N"], "disparity_prev", dims)
        if valid_prev is not None:
            raise ShapeError("valid_prev: only allowed with a disparity map (B, 1, H, W), not per-point disparities")
    else:
        raise ShapeError(
            "disparity_prev: expected a map (B, 1, H, W) or per-point disparities (B, N), "
            f"got shape {tuple(disparity_prev.shape)}"
        )
    for name, t in (
        ("points_prev", points_prev),
        ("points_next", points_next),
        ("disparity_prev", disparity_prev),
        ("K", K),
        ("baseline", baseline),
    ):
        check_float(t, name)
    check_same_device(
        points_prev, "points_prev", points_next=points_next, disparity_prev=disparity_prev, K=K,
        baseline=baseline, weights=weights, valid_prev=valid_prev,
    )  # fmt: skip
    if values:
        _check_values(points_prev, points_next, K, baseline, weights)


def _check_values(
    points_prev: torch.Tensor,
    points_next: torch.Tensor,
    K: torch.Tensor,
    baseline: torch.Tensor,
    weights: torch.Tensor | None,
) -> None:
    """Finite points and ``K``, ``K`` invertible, ``baseline > 0``, weights finite and >= 0 (the compiled solve
    tests these itself and comes here only when one fails, for the error)."""
    check_finite(points_prev, "points_prev")
    check_finite(points_next, "points_next")
    check_finite(K, "K")
    check_positive(baseline, "baseline")
    invertible = (K[:, 0, 0] > 0) & (K[:, 1, 1] > 0) & (torch.linalg.det(K).abs() > torch.finfo(K.dtype).tiny)
    if not bool(invertible.all()):
        raise ValueRangeError("K: not invertible (expected fx > 0, fy > 0 and a non-zero determinant)")
    if weights is not None:
        check_float(weights, "weights")
        if not bool((torch.isfinite(weights) & (weights >= 0)).all()):
            raise ValueRangeError("weights: every entry must be finite and >= 0")


# Largest disparity difference (px) among the 4 pixels a feature's depth is interpolated from.
_MAX_DISPARITY_SPREAD = 1.0


def _disparity_at(
    points: torch.Tensor, disparity: torch.Tensor, valid: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Disparity at the points ``(B, N)`` and where it is usable ``(B, N)`` bool.

    A map is sampled bilinearly (integer coordinates are pixel centres); a sample counts as
    usable only if the point lies inside the image and all 4 pixels it interpolates are finite,
    positive and valid and differ by at most ``_MAX_DISPARITY_SPREAD`` (no depth edge inside
    the stencil). Only those 4 pixels per point are read (gathered), never the whole
    map, so the cost does not grow with the image.
    """
    if disparity.dim() == 2:
        usable = torch.isfinite(disparity) & (disparity > 0)
        return torch.where(usable, disparity, torch.zeros_like(disparity)), usable
    B, _, H, W = disparity.shape
    x, y = points[..., 0], points[..., 1]
    inside = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    x0f = x.detach().floor().clamp(0, W - 1)
    y0f = y.detach().floor().clamp(0, H - 1)
    x0, y0 = x0f.long(), y0f.long()
    x1, y1 = (x0 + 1).clamp(max=W - 1), (y0 + 1).clamp(max=H - 1)
    idx = torch.stack([y0 * W + x0, y0 * W + x1, y1 * W + x0, y1 * W + x1], dim=-1).view(B, -1)  # (B, 4N)
    v = disparity.reshape(B, H * W).gather(1, idx).view(B, -1, 4)
    good = torch.isfinite(v) & (v > 0)
    if valid is not None:
        good = good & valid.reshape(B, H * W).gather(1, idx).view(B, -1, 4).bool()
    v = torch.where(good, v, torch.zeros_like(v))  # no NaN into the products below
    fx, fy = (x - x0f).clamp(0, 1), (y - y0f).clamp(0, 1)
    top = v[..., 0] + fx * (v[..., 1] - v[..., 0])
    bottom = v[..., 2] + fx * (v[..., 3] - v[..., 2])
    sampled = top + fy * (bottom - top)
    # Corners often sit on depth edges: 4 valid neighbours can still straddle a foreground and a background
    # surface, and their blend is a depth that exists nowhere. Such samples are not used.
    straddles = (v.amax(-1) - v.amin(-1)) > _MAX_DISPARITY_SPREAD
    usable = inside & good.all(-1) & ~straddles
    return torch.where(usable, sampled, torch.zeros_like(sampled)), usable


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


# the dtypes the compiled LM and solve accept (they compute in float64)
_KERNEL_DTYPES = (torch.float32, torch.float64)


def _two_stage_lm(motion: torch.Tensor, rays: torch.Tensor, target: torch.Tensor, K: torch.Tensor,
                  gate_huber: torch.Tensor, gate_late: torch.Tensor, *, loss: str, first: int, second: int,
                  scale: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The exact method's LM: ``first`` Huber iterations on ``gate_huber``, then ``second`` with ``loss``."""
    return _levenberg_marquardt(motion, rays, target, K, [(gate_huber, "huber", first), (gate_late, loss, second)],
                                scale)




# --------------------------------------------------------------------------- entry point


def solve_ego_motion(
    points_prev: torch.Tensor,
    points_next: torch.Tensor,
    disparity_prev: torch.Tensor,
    K: torch.Tensor,
    baseline: torch.Tensor,
    weights: torch.Tensor | None = None,
    method: str = "exact",
    valid_prev: torch.Tensor | None = None,
    *,
    min_features: int = 3,
    loss: str = "tukey",
    scale: float = 1.0,
    ransac_hypotheses: int = 64,
    ransac_threshold: float = 2.0,
    iterations: int = 3,
    seed: int = 0,
    rcond: float | None = None,
) -> EgoMotion:
    """Ego-motion ``camera_t_T_camera_{t-1}`` of the rig from features tracked from frame ``t-1`` to ``t``.

    Depth at each feature comes from the previous disparity (``Z = f B / d``, PAPER.md
    "Conventions"); a feature whose disparity is missing, non-positive, invalid or outside
    the image gets weight 0. See the module docstring for the three methods.

    Args:
        points_prev: ``(B, N, 2)`` feature positions ``(x, y)`` in frame ``t-1``, pixels.
        points_next: ``(B, N, 2)`` the same features tracked into frame ``t``.
        disparity_prev: disparity of frame ``t-1``: a map ``(B, 1, H, W)`` sampled bilinearly
            at ``points_prev``, or per-point disparities ``(B, N)``; pixels.
        K: ``(B, 3, 3)`` intrinsics of the rectified left camera.
        baseline: ``(B,)`` metres, > 0.
        weights: ``(B, N)`` >= 0 feature weights (0 = no feature); default all 1.
        method: ``"linear"`` (paper, eq. 3), ``"robust"`` (RANSAC around eq. 3) or ``"exact"``
            (SE(3) Levenberg-Marquardt on the reprojection error, from the robust solution; the default: the
            first-order model is biased at the rotations and depth changes of a real frame step).
        valid_prev: ``(B, 1, H, W)`` bool, where ``disparity_prev`` (a map) is valid.
        min_features: fewest features with positive final weight for ``ok`` (3, the minimum that fixes a rigid
            motion).
        loss: kernel of the last ``"exact"`` iterations: ``"tukey"`` (the default: it gives gross track errors
            zero weight and re-admits inliers RANSAC missed), ``"huber"`` or ``"l2"`` (with ``"l2"`` or
            ``"huber"`` only the RANSAC inliers take part).
        scale: residual scale of the robust kernels, pixels (Huber 1.345, Tukey 4.685 times it; 1 px: the size
            of a good track's error).
        ransac_hypotheses: minimal sets per item (``"robust"``/``"exact"``; 64: enough to draw an outlier-free
            set at the outlier shares of tracking, as one batched solve).
        ransac_threshold: inlier threshold of RANSAC on the linear model's residual, pixels;
            it must allow for the first-order model's bias.
        iterations: LM iterations of ``"exact"`` (half Huber on RANSAC inliers, half ``loss``; 3: from the robust
            start LM converges in a few steps).
        seed: seed of RANSAC's generator (fixed: the same tracks give the same motion).
        rcond: smallest reciprocal condition number of the Jacobi-scaled normal matrix
            accepted as ``ok``; default 1e-6 (float32) or 1e-9 (float64).

    Returns:
        :class:`EgoMotion` ``(motion, twist, weights, ok, num_inliers, rms)``.

    Raises:
        ShapeError: shapes of points, weights, disparity and ``valid_prev`` disagree.
        DTypeError: non-float input. DeviceError: tensors on different devices.
        ValueRangeError: NaN/Inf in points or ``K``, ``K`` not invertible, ``baseline <= 0``,
            negative weights, an unknown method or loss.

    Shape:
        ``(B, N, 2), (B, N, 2), (B, 1, H, W) | (B, N), (B, 3, 3), (B,) -> EgoMotion``.

    >>> from egorefine.geometry import make_intrinsics
    >>> pts = torch.rand(2, 20, 2) * 300
    >>> res = solve_ego_motion(pts, pts + 0.5, torch.full((2, 20), 8.0), make_intrinsics(400.0, 150.0, 150.0, 2),
    ...                        torch.full((2,), 0.1), method="linear")
    >>> res.motion.shape, res.ok.tolist()
    (torch.Size([2, 4, 4]), [True, True])
    """
    _check_inputs(points_prev, points_next, disparity_prev, K, baseline, weights, valid_prev, values=False)
    compiled = use_compiled(points_prev, points_next, disparity_prev, K, baseline, weights, valid_prev,
                            dtype=_KERNEL_DTYPES)
    if not compiled:
        _check_values(points_prev, points_next, K, baseline, weights)
    check_choice(method, METHODS, "method")
    check_choice(loss, LOSSES, "loss")
    if min_features < 3:
        raise ValueRangeError(f"min_features: at least 3 features are needed (6 equations), got {min_features}")
    if not scale > 0 or not ransac_threshold > 0:
        raise ValueRangeError(f"scale and ransac_threshold must be > 0, got {scale} and {ransac_threshold}")
    if ransac_hypotheses < 1 or iterations < 0:
        raise ValueRangeError(
            f"ransac_hypotheses must be >= 1 and iterations >= 0, got {ransac_hypotheses} and {iterations}"
        )
    dtype = points_prev.dtype
    if rcond is None:
        rcond = 1e-9 if dtype == torch.float64 else 1e-6
    if compiled:  # CPU inference: one compiled call (None: a bad input value, which the checks below raise)
        out = _solve_numba.solve_compiled(
            points_prev, points_next, disparity_prev, K, baseline, weights, valid_prev, method=method,
            refits=_REFITS.get(method, 1), min_features=min_features,
            loss=loss, scale=scale, ransac_hypotheses=ransac_hypotheses, ransac_threshold=ransac_threshold,
            iterations=iterations, seed=seed, rcond=rcond, max_spread=_MAX_DISPARITY_SPREAD,
        )  # fmt: skip
        if out is not None:
            return EgoMotion(*out)
        _check_values(points_prev, points_next, K, baseline, weights)
    damping = eps_like(points_prev)
    K = K.to(dtype)
    B, N, _ = points_prev.shape
    if N == 0:  # no features: every item's fallback (RANSAC cannot draw from an empty set)
        eye = torch.eye(4, dtype=dtype, device=points_prev.device).expand(B, 4, 4).clone()
        zeros = points_prev.new_zeros(B)
        return EgoMotion(eye, points_prev.new_zeros(B, 6), points_prev.new_zeros(B, 0),
                         torch.zeros(B, dtype=torch.bool, device=points_prev.device),
                         torch.zeros(B, dtype=torch.long, device=points_prev.device), zeros)

    disp, usable = _disparity_at(points_prev, disparity_prev.to(dtype), valid_prev)
    w = torch.ones_like(disp) if weights is None else weights.to(dtype)
    w = torch.where(usable, w, torch.zeros_like(w))
    inv_depth = disp / (K[:, 0, 0] * baseline.to(dtype))[:, None]  # 1/Z = d / (f B)

    # Equation (2) per feature, stacked for equation (3): A x = b with b the tracked displacement.
    A = motion_field_jacobian(points_prev, inv_depth, K).reshape(B, 2 * N, 6)
    b = (points_next - points_prev).reshape(B, 2 * N)

    if method == "linear":
        twist, Hs = _linear_fit(A, b, w, damping)
        w_out = w
        rms_r = _linear_residual(A, b, twist)
    else:
        twist, w_in = _ransac(A, b, w, ransac_hypotheses, ransac_threshold, seed, damping, _REFITS[method])
        if method == "robust":
            w_out = w_in
            Hs = _jacobi_scaled(_normal_equations(A, b, w_in.repeat_interleave(2, dim=1))[0])[0]
            rms_r = _linear_residual(A, b, twist)
    if method == "exact":
        fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]
        rays = torch.stack(
            [(points_prev[..., 0] - K[:, 0, 2, None]) / fx, (points_prev[..., 1] - K[:, 1, 2, None]) / fy,
             torch.ones_like(disp), inv_depth], dim=-1,
        )  # fmt: skip
        # twist_to_motion(twist) = exp(-twist), as the exponential of the 4x4 twist matrix.
        start_twist = torch.where(torch.isfinite(twist), twist, torch.zeros_like(twist))
        start = _twist_exp(-start_twist, _se3_generators(twist))
        first = iterations // 2
        late_gate = w if loss == "tukey" else w_in
        lm_inputs = (start, rays, points_next, K, w_in, late_gate)
        lm = partial(_two_stage_lm, loss=loss, first=first, second=iterations - first, scale=scale)
        if _graphs.usable(*lm_inputs):  # CUDA inference: the ~300 small launches of the LM replayed as one graph
            motion, S, Hs = _graphs.replay(lm, ("lm", loss, first, iterations - first, scale), *lm_inputs)
        elif use_compiled(*lm_inputs, dtype=_KERNEL_DTYPES):  # CPU inference: the same LM compiled (numba)
            motion, S, Hs = _lm_numba.two_stage_lm(*lm_inputs, loss=loss, first=first, second=iterations - first,
                                                   scale=scale)
        else:
            motion, S, Hs = lm(*lm_inputs)
        rms_r = S[..., _RN] * S[..., _FRONT]
        w_out = late_gate * S[..., _FRONT] * robust_weight(S[..., _RN], loss, scale)
        twist = motion_to_twist(motion)

    num = (w_out > 0).sum(1)
    wsum = w_out.sum(1)
    rms = ((w_out * rms_r * rms_r).sum(1) / wsum.clamp_min(eps_like(wsum))).sqrt()
    ok = (num >= min_features) & _well_conditioned(Hs, rcond) & torch.isfinite(twist).all(1) & torch.isfinite(rms)
    # Fallback per item: identity motion, zero twist, no inliers (selected with where, so the
    # finite values of the other branch keep gradients finite).
    twist = torch.where(ok[:, None], twist, torch.zeros_like(twist))
    if method == "exact":
        eye = torch.eye(4, dtype=dtype, device=motion.device).expand(B, 4, 4)
        motion = torch.where(ok[:, None, None], motion, eye)
    else:
        motion = twist_to_motion(twist)
    w_out = torch.where(ok[:, None], w_out, torch.zeros_like(w_out))
    num = torch.where(ok, num, torch.zeros_like(num))
    rms = torch.where(ok, rms, torch.zeros_like(rms))
    return EgoMotion(motion, twist, w_out, ok, num, rms)


class EgoMotionSolver(nn.Module):
    """Module form of :func:`solve_ego_motion`: stores the method and settings; ``forward`` calls the function.

    Args:
        method: ``"exact"`` (default: the linear solve of eq. (3) is biased by its first-order model on finite
            steps), ``"robust"`` or ``"linear"`` (the paper's).
        min_features, loss, scale, ransac_hypotheses, ransac_threshold, iterations, seed, rcond: as in
            :func:`solve_ego_motion`, with its defaults.

    ``forward(points_prev, points_next, disparity_prev, K, baseline, weights=None, valid_prev=None) -> EgoMotion``,
    shapes as in :func:`solve_ego_motion`.

    Example:
        >>> from egorefine.geometry import make_intrinsics
        >>> solver = EgoMotionSolver(method="robust")
        >>> pts = torch.rand(1, 30, 2) * 300
        >>> solver(pts, pts, torch.full((1, 30), 8.0), make_intrinsics(400.0, 150.0, 150.0), torch.ones(1)).twist.shape
        torch.Size([1, 6])
    """

    def __init__(
        self,
        method: str = "exact",
        *,
        min_features: int = 3,
        loss: str = "tukey",
        scale: float = 1.0,
        ransac_hypotheses: int = 64,
        ransac_threshold: float = 2.0,
        iterations: int = 3,
        seed: int = 0,
        rcond: float | None = None,
    ) -> None:
        super().__init__()
        check_choice(method, METHODS, "method")
        check_choice(loss, LOSSES, "loss")
        self.method = method
        self.settings = {
            "min_features": min_features,
            "loss": loss,
            "scale": scale,
            "ransac_hypotheses": ransac_hypotheses,
            "ransac_threshold": ransac_threshold,
            "iterations": iterations,
            "seed": seed,
            "rcond": rcond,
        }

    def forward(
        self,
        points_prev: torch.Tensor,
        points_next: torch.Tensor,
        disparity_prev: torch.Tensor,
        K: torch.Tensor,
        baseline: torch.Tensor,
        weights: torch.Tensor | None = None,
        valid_prev: torch.Tensor | None = None,
    ) -> EgoMotion:
        return solve_ego_motion(
            points_prev, points_next, disparity_prev, K, baseline, weights, self.method, valid_prev, **self.settings
        )

    def extra_repr(self) -> str:
        return f"method={self.method!r}, " + ", ".join(f"{k}={v!r}" for k, v in self.settings.items())
