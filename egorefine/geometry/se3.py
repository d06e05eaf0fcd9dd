"""Rigid motions: SE(3) exponential/logarithm and the paper's ego-motion twist.

Two parameterisations of a 6-vector appear in egorefine:

* ``se3_exp`` / ``se3_log``: the standard exponential map of SE(3), ``xi = (rho, phi)``
  with translation part first (kornia's :class:`~kornia.geometry.liegroup.Se3` order). We
  write them out rather than call ``Se3`` because its matrices carry an autograd graph
  even for inputs that need no gradient, and near zero rotation we want Taylor series
  for every coefficient (finite values and gradients at exactly zero).
* The paper's ego-motion ``twist = (U, V, W, alpha, beta, gamma)``: the rig's translation
  ``T`` and rotation ``omega`` over one frame step. A static point then moves, relative to
  the rig, by ``-T - omega x P`` (docs/method.md eq. 1). We make that exact for a finite step by
  defining the pose of the new camera in the old one as ``se3_exp(twist)``, so that

      camera_t_T_camera_{t-1} = se3_exp(twist)^-1 = se3_exp(-twist),

  whose first-order action on a point is ``P - T - omega x P``, equation (1).
"""

from __future__ import annotations

import torch

from ..core import check_float, check_shape

__all__ = [
    "se3_exp",
    "se3_log",
    "se3_inverse",
    "transform_points",
    "twist_to_motion",
    "motion_to_twist",
]

# Below this rotation angle (radians) the coefficients free of cancellation (sin t / t, the
# half-angle form of (1 - cos t) / t^2, t / sin t) use their Taylor series, for finite values
# and gradients at exactly zero; the series' truncation error is below 1e-20 there.
_SMALL_ANGLE = 1e-3
# (t - sin t) / t^3 and the logarithm's (1 - t cot(t / 2) / 2) / t^2 lose digits to cancellation
# for small t, which no rewriting removes: in float32 their closed forms are off by 30 % and by a
# factor 6e5 at t = 1e-3, by 2e-5 and 3e-3 (relative) at t = 0.1. Below these angles they use their
# series through t^8, whose truncation error (checked against mpmath) is about 1e-15 relative at
# float64's 0.25 and below 1e-7 at float32's 1.0, where the closed forms are as accurate.
_SERIES_ANGLE_F64 = 0.25
_SERIES_ANGLE_F32 = 1.0


def _hat(phi: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrices ``(B, 3, 3)`` of vectors ``(B, 3)``: ``hat(a) @ b == a x b``."""
    zero = torch.zeros_like(phi[:, 0])
    x, y, z = phi.unbind(-1)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).view(-1, 3, 3)


def _series_angle(dtype: torch.dtype) -> float:
    return _SERIES_ANGLE_F64 if dtype == torch.float64 else _SERIES_ANGLE_F32


def _coefficients(theta2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``A = sin t / t``, ``B = (1 - cos t) / t^2``, ``C = (t - sin t) / t^3`` from ``t^2``, safe at zero."""
    small = theta2 < _SMALL_ANGLE**2
    # Replace small angles by 1 before the closed forms so their (unused) branch has no 0/0.
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = t2.sqrt()
    a = torch.where(small, 1 - theta2 / 6 + theta2**2 / 120, torch.sin(t) / t)
    # 1 - cos t = 2 sin^2(t / 2): no cancellation.
    half = torch.sin(0.5 * t) / t
    b = torch.where(small, 0.5 - theta2 / 24 + theta2**2 / 720, 2 * half * half)
    series = theta2 < _series_angle(theta2.dtype) ** 2
    t2 = torch.where(series, torch.ones_like(theta2), theta2)
    t = t2.sqrt()
    c_series = 1 / 6 - theta2 / 120 + theta2**2 / 5040 - theta2**3 / 362880 + theta2**4 / 39916800
    c = torch.where(series, c_series, (t - torch.sin(t)) / (t2 * t))
    return a, b, c


def _log_coefficient(theta2: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``D = (1 - A / (2 B)) / t^2`` of ``V^-1 = I - W / 2 + D W^2``, from ``t^2`` and :func:`_coefficients`'s A, B."""
    series = theta2 < _series_angle(theta2.dtype) ** 2
    safe_t2 = torch.where(series, torch.ones_like(theta2), theta2)
    d_series = 1 / 12 + theta2 / 720 + theta2**2 / 30240 + theta2**3 / 1209600 + theta2**4 / 47900160
    return torch.where(series, d_series, (1 - a / (2 * b)) / safe_t2)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Exponential map of SE(3): a twist ``xi = (rho, phi)``, translation part first, to a rigid motion.

    ``R = I + A W + B W^2`` (Rodrigues) and ``t = V rho`` with the left Jacobian ``V = I + B W + C W^2``,
    ``W = hat(phi)``; the coefficients switch to their Taylor series at small angles, so values and gradients are finite
    at ``phi = 0`` (see the module notes for the switch points).

    Args:
        xi: ``(B, 6)`` twists ``(rho, phi)``: ``rho`` in metres, ``phi`` an axis-angle in radians.

    Returns:
        ``(B, 4, 4)`` rigid motions in ``xi``'s dtype.

    Example:
        >>> se3_exp(torch.zeros(1, 6))[0]
        tensor([[1., 0., 0., 0.],
                [0., 1., 0., 0.],
                [0., 0., 1., 0.],
                [0., 0., 0., 1.]])
    """
    check_shape(xi, ["B", "6"], "xi")
    check_float(xi, "xi")
    rho, phi = xi[:, :3], xi[:, 3:]
    W = _hat(phi)
    W2 = W @ W
    a, b, c = (k[:, None, None] for k in _coefficients((phi * phi).sum(-1)))
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(W)
    R = eye + a * W + b * W2  # Rodrigues
    V = eye + b * W + c * W2  # left Jacobian of SO(3)
    top = torch.cat([R, (V @ rho[..., None])], dim=-1)
    bottom = torch.zeros_like(top[:, :1])
    bottom[..., 3] = 1.0
    return torch.cat([top, bottom], dim=1)


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """Logarithm map of SE(3): a rigid motion to its twist ``(rho, phi)``, the inverse of :func:`se3_exp`.

    The rotation angle comes from ``atan2`` (finite gradient at zero rotation, unlike ``acos``); valid for rotations
    below pi, where the axis is unique.

    Args:
        T: ``(B, 4, 4)`` rigid motions.

    Returns:
        ``(B, 6)`` twists ``(rho, phi)``, translation part first.

    Example:
        >>> xi = torch.tensor([[0.1, 0.0, 0.2, 0.0, 0.05, 0.0]], dtype=torch.float64)
        >>> torch.allclose(se3_log(se3_exp(xi)), xi)
        True
    """
    check_shape(T, ["B", "4", "4"], "T")
    check_float(T, "T")
    R, t = T[:, :3, :3], T[:, :3, 3]
    # 2 sin(theta) * axis, from the antisymmetric part of R.
    vee = torch.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], dim=-1)
    cos = 0.5 * (R.diagonal(dim1=1, dim2=2).sum(-1) - 1)
    # atan2 instead of acos: acos has an infinite derivative at cos = 1 (zero rotation).
    # The norm is taken of a clamped square so its gradient is finite at vee = 0.
    sin = 0.5 * (vee * vee).sum(-1).clamp_min(torch.finfo(T.dtype).tiny).sqrt()
    theta = torch.atan2(sin, cos)
    theta2 = theta * theta
    small = theta2 < _SMALL_ANGLE**2
    safe_sin = torch.where(small, torch.ones_like(sin), sin)
    # phi = theta / (2 sin theta) * vee; theta / sin theta = 1 + theta^2 / 6 + 7 theta^4 / 360 near zero.
    scale = torch.where(small, 1 + theta2 / 6 + 7 * theta2**2 / 360, theta / safe_sin)
    phi = 0.5 * scale[:, None] * vee
    # V^-1 = I - W / 2 + D W^2 with D = (1 - A / (2 B)) / theta^2 (series near zero).
    a, b, _ = _coefficients(theta2)
    d = _log_coefficient(theta2, a, b)
    W = _hat(phi)
    eye = torch.eye(3, dtype=T.dtype, device=T.device).expand_as(W)
    V_inv = eye - 0.5 * W + d[:, None, None] * (W @ W)
    rho = (V_inv @ t[..., None])[..., 0]
    return torch.cat([rho, phi], dim=-1)


def se3_inverse(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid motions in closed form, ``[R^T | -R^T t]``: cheaper and more exact than a general inverse.

    Args:
        T: ``(B, 4, 4)`` rigid motions ``dst_T_src``.

    Returns:
        ``(B, 4, 4)`` motions ``src_T_dst``.

    Example:
        >>> T = se3_exp(torch.tensor([[0.1, 0.0, 0.2, 0.0, 0.05, 0.0]]))
        >>> torch.allclose(se3_inverse(T) @ T, torch.eye(4), atol=1e-6)
        True
    """
    check_shape(T, ["B", "4", "4"], "T")
    R_t = T[:, :3, :3].transpose(1, 2)
    out = torch.zeros_like(T)
    out[:, :3, :3] = R_t
    out[:, :3, 3] = -(R_t @ T[:, :3, 3:4])[..., 0]
    out[:, 3, 3] = 1.0
    return out


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply rigid motions ``dst_T_src`` to 3-D points given in the frame ``src``: ``R p + t``.

    Args:
        T: ``(B, 4, 4)`` rigid motions ``dst_T_src``.
        points: ``(B, N, 3)`` points in ``src``.

    Returns:
        ``(B, N, 3)`` the points in ``dst``.

    Example:
        >>> T = twist_to_motion(torch.tensor([[0.0, 0.0, 0.1, 0.0, 0.0, 0.0]]))  # 0.1 m forward
        >>> transform_points(T, torch.tensor([[[0.0, 0.0, 2.0]]]))
        tensor([[[0.0000, 0.0000, 1.9000]]])
    """
    dims = check_shape(T, ["B", "4", "4"], "T")
    check_shape(points, ["B", "N", "3"], "points", dims)
    return points @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]


def twist_to_motion(twist: torch.Tensor) -> torch.Tensor:
    """The paper's ego-motion ``(U, V, W, alpha, beta, gamma)`` as the rigid motion ``camera_t_T_camera_{t-1}``.

    A static point moves relative to the rig by ``-T - omega x P`` (docs/method.md eq. 1), with ``T = (U, V, W)`` the
    rig's translation and ``omega = (alpha, beta, gamma)`` its rotation over the step. The finite-step motion is
    ``se3_exp(-twist)``, whose first-order action on a point is exactly eq. (1).

    Args:
        twist: ``(B, 6)`` ``(U, V, W)`` in metres and ``(alpha, beta, gamma)`` in radians.

    Returns:
        ``(B, 4, 4)`` motions ``camera_t_T_camera_{t-1}``.

    Example:
        >>> M = twist_to_motion(torch.tensor([[0.0, 0.0, 0.1, 0.0, 0.0, 0.0]]))
        >>> M[0, 2, 3]  # moving forward 0.1 m brings static points 0.1 m closer
        tensor(-0.1000)
    """
    return se3_exp(-twist)


def motion_to_twist(motion: torch.Tensor) -> torch.Tensor:
    """The paper's twist of a rigid motion ``camera_t_T_camera_{t-1}``: the inverse of :func:`twist_to_motion`.

    Args:
        motion: ``(B, 4, 4)`` motions ``camera_t_T_camera_{t-1}``, rotations below pi.

    Returns:
        ``(B, 6)`` ``(U, V, W, alpha, beta, gamma)``, metres and radians.

    Example:
        >>> twist = torch.tensor([[0.0, 0.01, 0.1, 0.002, -0.01, 0.0]], dtype=torch.float64)
        >>> torch.allclose(motion_to_twist(twist_to_motion(twist)), twist)
        True
    """
    return -se3_log(motion)
