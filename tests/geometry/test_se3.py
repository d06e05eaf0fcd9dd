import math

import pytest
import torch

from egorefine.core import ShapeError
from egorefine.geometry import (
    motion_to_twist,
    se3_exp,
    se3_inverse,
    se3_log,
    transform_points,
    twist_to_motion,
)


@pytest.mark.parametrize("scale", [0.0, 1e-7, 1e-4, 1e-2, 0.3, 1.0])
def test_exp_log_round_trip(scale):
    g = torch.Generator().manual_seed(1)
    xi = torch.randn(8, 6, dtype=torch.float64, generator=g) * scale
    # The logarithm is the principal one: keep rotation angles below pi.
    angle = xi[:, 3:].norm(dim=-1, keepdim=True)
    xi[:, 3:] *= (3.0 / angle.clamp_min(3.0)).clamp(max=1.0)
    T = se3_exp(xi)
    R = T[:, :3, :3]
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand_as(R))
    torch.testing.assert_close(se3_log(T), xi, atol=1e-12, rtol=1e-9)
    torch.testing.assert_close(se3_exp(se3_log(T)), T)


def test_rodrigues_against_known_rotation():
    # 90 degrees about Z maps X to Y.
    xi = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, torch.pi / 2]], dtype=torch.float64)
    p = transform_points(se3_exp(xi), torch.tensor([[[1.0, 0.0, 0.0]]], dtype=torch.float64))
    torch.testing.assert_close(p, torch.tensor([[[0.0, 1.0, 0.0]]], dtype=torch.float64))


def test_gradients_finite_at_zero_rotation():
    xi = torch.zeros(2, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(se3_exp, (xi,))
    T = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1).requires_grad_()
    se3_log(T).pow(2).sum().backward()
    assert torch.isfinite(T.grad).all()
    xi = (torch.randn(2, 6, dtype=torch.float64) * 0.2).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: se3_log(se3_exp(x)), (xi,))


def test_inverse_and_transform():
    T = se3_exp(torch.randn(3, 6, dtype=torch.float64) * 0.5)
    torch.testing.assert_close(T @ se3_inverse(T), torch.eye(4, dtype=torch.float64).expand_as(T))
    p = torch.randn(3, 10, 3, dtype=torch.float64)
    torch.testing.assert_close(transform_points(se3_inverse(T), transform_points(T, p)), p)


def test_twist_matches_equation_1_to_first_order():
    # docs/method.md eq. (1): a static point moves by -T - omega x P relative to the rig.
    twist = torch.tensor([[0.01, -0.02, 0.1, 0.002, -0.003, 0.001]], dtype=torch.float64)
    P = torch.tensor([[[1.0, -0.5, 5.0], [-2.0, 1.0, 10.0]]], dtype=torch.float64)
    moved = transform_points(twist_to_motion(twist), P)
    T, omega = twist[:, None, :3], twist[:, None, 3:]
    first_order = P - T - torch.cross(omega.expand_as(P), P, dim=-1)
    # The remainder is second order in the step: |omega| * (|T| + |omega||P|) ~ 1e-4 here.
    assert (moved - first_order).abs().max() < 5e-4
    torch.testing.assert_close(motion_to_twist(twist_to_motion(twist)), twist)


def test_bad_shapes():
    with pytest.raises(ShapeError, match="xi"):
        se3_exp(torch.zeros(6))
    with pytest.raises(ShapeError, match="T"):
        se3_log(torch.zeros(2, 3, 4))


# Angles on both sides of every switch between series and closed forms (1e-3 rad, float64's
# 0.25 and float32's 1.0), where cancellation in (t - sin t) / t^3 and in the logarithm's
# V^-1 coefficient used to cost float32 up to 16 % of the translation.
_ANGLES = [0.0, 5e-4, 1.01e-3, 1.5e-3, 3e-3, 1e-2, 0.1, 0.24, 0.26, 0.5, 0.99, 1.01, 2.0, 3.0]


def _twists(angle: float) -> torch.Tensor:
    g = torch.Generator().manual_seed(3)
    axis = torch.nn.functional.normalize(torch.randn(64, 3, dtype=torch.float64, generator=g), dim=-1)
    rho = torch.randn(64, 3, dtype=torch.float64, generator=g)
    return torch.cat([rho, angle * axis], dim=-1)


@pytest.mark.parametrize("angle", _ANGLES)
def test_float32_maps_keep_float32_accuracy(angle):
    xi = _twists(angle)
    T = se3_exp(xi)
    # float32 inputs and arithmetic against the float64 result: a few float32 ulps of |xi| ~ 1-3.
    assert (se3_exp(xi.float()).double() - T).abs().max() < 2e-6
    assert (se3_log(T.float()).double() - xi).abs().max() < 2e-6


@pytest.mark.parametrize("angle", _ANGLES)
def test_float64_maps_against_exact_rotation(angle):
    xi = _twists(angle)
    T = se3_exp(xi)
    # Rodrigues' formula with the angle's own sin and cos: no small-angle handling is needed
    # for the rotation itself; the logarithm checks the translation coefficients.
    k = xi[:, 3:] / max(angle, 1e-300)
    K = torch.zeros(64, 3, 3, dtype=torch.float64)
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K = K - K.transpose(1, 2)
    eye = torch.eye(3, dtype=torch.float64)
    R = eye + math.sin(angle) * K + 2 * math.sin(angle / 2) ** 2 * (K @ K)
    # entries of at most 1: a handful of float64 steps (2.2e-16) from sin, cos and the products, whose last bits
    # another CPU's kernels round differently; a wrong term of the series is many orders larger
    torch.testing.assert_close(T[:, :3, :3], R, atol=1e-14, rtol=0)
    torch.testing.assert_close(se3_log(T), xi, atol=1e-13, rtol=0)


@pytest.mark.parametrize("angle", _ANGLES)
def test_compiled_solve_maps_match_torch(angle):
    numba_solve = pytest.importorskip("egorefine.motion._solve_numba")
    if not numba_solve.AVAILABLE:
        pytest.skip("numba not installed")
    from egorefine.geometry.se3 import _SMALL_ANGLE

    twists = _twists(angle)
    motions = twist_to_motion(twists)
    M, tw = torch.empty(4, 4, dtype=torch.float64), torch.empty(6, dtype=torch.float64)
    for twist, motion in zip(twists, motions, strict=True):
        numba_solve._motion_of(twist.numpy(), _SMALL_ANGLE**2, M.numpy())
        torch.testing.assert_close(M, motion, atol=1e-14, rtol=0)
        numba_solve._twist_of(motion.numpy(), torch.finfo(torch.float64).tiny, _SMALL_ANGLE**2, tw.numpy())
        torch.testing.assert_close(tw, twist, atol=1e-13, rtol=0)
