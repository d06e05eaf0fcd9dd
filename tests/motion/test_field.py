"""Tests of egorefine.motion.field: the motion field of docs/method.md equation (2)."""

from __future__ import annotations

import pytest
import torch

from egorefine.core import DTypeError, ShapeError
from egorefine.geometry import make_intrinsics, project, transform_points, twist_to_motion, unproject
from egorefine.motion import motion_field, motion_field_jacobian

F64 = torch.float64


def _scene(n: int = 50, seed: int = 0, dtype: torch.dtype = F64):
    gen = torch.Generator().manual_seed(seed)
    K = make_intrinsics(398.0, 319.5, 239.5, dtype=dtype)
    pts = torch.rand(1, n, 2, generator=gen, dtype=dtype) * torch.tensor([600.0, 440.0], dtype=dtype) + 20
    Z = torch.rand(1, n, generator=gen, dtype=dtype) * 13 + 2
    return pts, Z, K


def test_smoke_shapes():
    pts, Z, K = _scene(7)
    flow = motion_field(pts, Z, K, torch.zeros(1, 6, dtype=F64))
    assert flow.shape == (1, 7, 2)
    assert torch.equal(flow, torch.zeros_like(flow))
    assert motion_field_jacobian(pts, 1 / Z, K).shape == (1, 7, 2, 6)


def test_matches_equation_2_written_out():
    """With fx == fy == f the flow is exactly the paper's formula, coordinates relative to (cx, cy)."""
    pts, Z, K = _scene(20)
    twist = torch.tensor([[0.03, -0.02, 0.1, 0.01, -0.02, 0.015]], dtype=F64)
    U, V, W, al, be, ga = twist[0]
    f = 398.0
    x, y = pts[..., 0] - 319.5, pts[..., 1] - 239.5
    u = (-U * f + x * W) / Z + al * x * y / f - be * (f + x * x / f) + ga * y
    v = (-V * f + y * W) / Z + al * (f + y * y / f) - be * x * y / f - ga * x
    flow = motion_field(pts, Z, K, twist)
    torch.testing.assert_close(flow, torch.stack([u, v], -1), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    "twist",
    [
        [0.0, 0.0, 0.1, 0.0, 0.0, 0.0],  # forward
        [0.05, -0.03, 0.0, 0.0, 0.0, 0.0],  # sideways
        [0.0, 0.0, 0.0, 0.02, -0.01, 0.03],  # rotation
        [0.03, -0.02, 0.1, 0.01, -0.02, 0.015],  # combined
    ],
)
def test_sign_convention_first_order(twist):
    """Flow of eq. (2) == true displacement under twist_to_motion(eps * twist) to first order in eps."""
    pts, Z, K = _scene(40)
    tw = torch.tensor([twist], dtype=F64)
    P = unproject(pts, Z, K)
    errs = []
    for eps in (1e-2, 5e-3):
        moved = project(transform_points(twist_to_motion(eps * tw), P), K)
        flow = motion_field(pts, Z, K, eps * tw)
        disp = moved - pts
        scale = disp.norm(dim=-1).max()
        # First order: the relative error is O(eps) (a few 1e-3 here), never O(1) (a sign error).
        assert (flow - disp).norm(dim=-1).max() < 0.05 * scale
        errs.append((flow - disp).norm(dim=-1).max())
    # The remainder is second order: halving the motion quarters it (ratio ~0.25); a sideways
    # translation keeps Z and is exact (remainder at rounding level).
    assert errs[0] < 1e-10 or 0.2 < errs[1] / errs[0] < 0.3


def test_anisotropic_focal_matches_finite_displacement():
    gen = torch.Generator().manual_seed(1)
    K = make_intrinsics(400.0, 300.0, 200.0, focal_y=380.0, dtype=F64)
    pts = torch.rand(1, 30, 2, generator=gen, dtype=F64) * 400 + 20
    Z = torch.rand(1, 30, generator=gen, dtype=F64) * 8 + 2
    tw = 1e-4 * torch.tensor([[0.3, -0.2, 1.0, 0.1, -0.2, 0.15]], dtype=F64)
    moved = project(transform_points(twist_to_motion(tw), unproject(pts, Z, K)), K)
    torch.testing.assert_close(motion_field(pts, Z, K, tw), moved - pts, rtol=1e-3, atol=1e-7)


def test_zero_depth_is_finite():
    pts, Z, K = _scene(3)
    Z = Z.clone()
    Z[0, 0] = 0.0
    Z.requires_grad_(True)
    flow = motion_field(pts, Z, K, torch.ones(1, 6, dtype=F64))
    flow.sum().backward()
    assert torch.isfinite(flow).all() and torch.isfinite(Z.grad).all()


def test_batch_consistency():
    pts, Z, K = _scene(10)
    pts2, Z2, _ = _scene(10, seed=3)
    tw = torch.tensor([[0.0, 0.0, 0.1, 0.0, 0.01, 0.0], [0.02, 0.0, 0.0, 0.01, 0.0, -0.01]], dtype=F64)
    batch = motion_field(torch.cat([pts, pts2]), torch.cat([Z, Z2]), K.expand(2, 3, 3), tw)
    torch.testing.assert_close(batch[1:], motion_field(pts2, Z2, K, tw[1:]))


def test_gradcheck():
    pts, Z, K = _scene(3)
    tw = torch.tensor([[0.03, -0.02, 0.1, 0.01, -0.02, 0.015]], dtype=F64)
    args = (pts.requires_grad_(True), Z.requires_grad_(True), K.requires_grad_(True), tw.requires_grad_(True))
    assert torch.autograd.gradcheck(motion_field, args)


def test_exceptions():
    pts, Z, K = _scene(4)
    tw = torch.zeros(1, 6, dtype=F64)
    with pytest.raises(ShapeError, match="depth"):
        motion_field(pts, Z[:, :3], K, tw)
    with pytest.raises(ShapeError, match="twist"):
        motion_field(pts, Z, K, torch.zeros(1, 3, dtype=F64))
    with pytest.raises(ShapeError, match="K"):
        motion_field(pts, Z, K.expand(2, 3, 3), tw)
    with pytest.raises(DTypeError, match="points"):
        motion_field(pts.long(), Z, K, tw)
