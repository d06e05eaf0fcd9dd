"""The instantaneous motion field of a rigidly moving camera, docs/method.md equation (2).

For a feature at pixel ``(x, y)`` with depth ``Z`` and the rig's ego-motion
``twist = (U, V, W, alpha, beta, gamma)`` (translation ``T`` and rotation ``omega`` over one
frame), equation (2) gives its image velocity ``(u, v)``. It is linear in the twist, so it
is written here as a ``(2, 6)`` Jacobian per feature; the flow is that Jacobian times the
twist, and the least-squares solve of equation (3) stacks the same Jacobians.

Internally the Jacobian takes inverse depth ``1 / Z`` (which is ``d / (f B)`` for a stereo
disparity ``d``): points at infinity then have a finite (rotation-only) row instead of a
division by zero.
"""

from __future__ import annotations

import torch

from ..core import check_float, check_shape, eps_like

__all__ = ["motion_field", "motion_field_jacobian"]


def motion_field_jacobian(points: torch.Tensor, inv_depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Jacobian of equation (2) with respect to the twist, ``(B, N, 2, 6)``.

    Row 0 is ``du / d(U, V, W, alpha, beta, gamma)``, row 1 is ``dv / d(...)``. Coordinates are
    taken relative to the principal point; with ``fx != fy`` the equation is applied in
    normalised coordinates and scaled back, which reduces to (2) when ``fx == fy == f``.

    Args:
        points: ``(B, N, 2)`` pixel coordinates ``(x, y)`` in frame ``t-1``.
        inv_depth: ``(B, N)`` inverse depth ``1 / Z`` in 1/m (0 = at infinity).
        K: ``(B, 3, 3)`` intrinsics.

    Returns:
        ``(B, N, 2, 6)``.

    >>> from egorefine.geometry import make_intrinsics
    >>> motion_field_jacobian(torch.zeros(1, 4, 2), torch.ones(1, 4), make_intrinsics(100.0, 0.0, 0.0)).shape
    torch.Size([1, 4, 2, 6])
    """
    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]  # (B,1)
    cx, cy = K[:, 0, 2, None], K[:, 1, 2, None]
    xn = (points[..., 0] - cx) / fx  # normalised image coordinates, (B,N)
    yn = (points[..., 1] - cy) / fy
    zero = torch.zeros_like(xn)
    fx, fy = fx.expand_as(xn), fy.expand_as(xn)
    # Equation (2), u = fx * un, v = fy * vn with
    #   un = (-U + xn W) / Z + alpha xn yn - beta (1 + xn^2) + gamma yn
    #   vn = (-V + yn W) / Z + alpha (1 + yn^2) - beta xn yn - gamma xn
    row_u = torch.stack(
        [-fx * inv_depth, zero, fx * xn * inv_depth, fx * xn * yn, -fx * (1 + xn * xn), fx * yn], dim=-1
    )
    row_v = torch.stack(
        [zero, -fy * inv_depth, fy * yn * inv_depth, fy * (1 + yn * yn), -fy * xn * yn, -fy * xn], dim=-1
    )
    return torch.stack([row_u, row_v], dim=-2)


def motion_field(points: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, twist: torch.Tensor) -> torch.Tensor:
    """Image flow of static points under the rig's ego-motion, docs/method.md equation (2).

    The flow is the instantaneous (first-order) model: for a finite frame step it agrees
    with the true displacement of the projection up to second-order terms in the motion
    (see :func:`egorefine.motion.solve_ego_motion` with ``method="exact"`` for the exact model).

    Args:
        points: ``(B, N, 2)`` pixel coordinates ``(x, y)`` in frame ``t-1``.
        depth: ``(B, N)`` depth ``Z`` in metres (clamped to the dtype's epsilon before dividing).
        K: ``(B, 3, 3)`` intrinsics in pixels.
        twist: ``(B, 6)`` = ``(U, V, W, alpha, beta, gamma)``: translation (m) and rotation (rad)
            of the rig over the step; ``camera_t_T_camera_{t-1} = twist_to_motion(twist)``.

    Returns:
        ``(B, N, 2)`` flow ``(u, v)`` in pixels.

    Raises:
        ShapeError: shapes disagree. DTypeError: non-float input.

    >>> from egorefine.geometry import make_intrinsics
    >>> K = make_intrinsics(400.0, 320.0, 240.0)
    >>> twist = torch.tensor([[0.0, 0.0, 0.1, 0.0, 0.0, 0.0]])  # moving forward 0.1 m
    >>> motion_field(torch.tensor([[[420.0, 240.0]]]), torch.tensor([[2.0]]), K, twist)  # expands
    tensor([[[5., 0.]]])
    """
    dims = check_shape(points, ["B", "N", "2"], "points")
    check_shape(depth, ["B", "N"], "depth", dims)
    check_shape(K, ["B", "3", "3"], "K", dims)
    check_shape(twist, ["B", "6"], "twist", dims)
    for name, t in (("points", points), ("depth", depth), ("K", K), ("twist", twist)):
        check_float(t, name)
    # Clamp before dividing: a zero depth gives a large finite flow, not Inf, and a finite gradient.
    inv_depth = 1.0 / depth.clamp_min(eps_like(depth))
    J = motion_field_jacobian(points, inv_depth, K)
    return (J @ twist[:, None, :, None])[..., 0]
