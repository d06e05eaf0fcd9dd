"""Ego-motion of the stereo rig from features tracked between frames ``t-1`` and ``t``.

Three solvers share one entry point, :func:`solve_ego_motion`:

``"linear"``
    The paper's estimator: the weighted least squares of docs/method.md equation (3) over the
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

This module checks the input, samples the depth of each feature and runs the chosen method; the linear solves and
RANSAC are in :mod:`egorefine.motion._linear`, the Levenberg-Marquardt refinement in :mod:`egorefine.motion._lm`.
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
from ._linear import (
    _REFITS,
    _jacobi_scaled,
    _linear_fit,
    _linear_residual,
    _normal_equations,
    _ransac,
    _well_conditioned,
)
from ._lm import _FRONT, _RN, _se3_generators, _twist_exp, _two_stage_lm
from .field import motion_field_jacobian
from .robust import LOSSES, robust_weight

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


# the dtypes the compiled LM and solve accept (they compute in float64)
_KERNEL_DTYPES = (torch.float32, torch.float64)


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

    Depth at each feature comes from the previous disparity (``Z = f B / d``, docs/method.md
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
