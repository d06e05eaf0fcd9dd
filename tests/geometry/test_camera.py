import pytest
import torch

from egorefine.core import ShapeError, ValueRangeError
from egorefine.geometry import (
    depth_to_disparity,
    disparity_to_depth,
    make_intrinsics,
    pixel_grid,
    project,
    unproject,
    unproject_disparity,
)


def _K(batch: int = 2, dtype=torch.float32):
    K = make_intrinsics(398.0, 320.0, 240.0, batch_size=batch, dtype=dtype)
    if batch > 1:
        K[1] = make_intrinsics(500.0, 300.0, 200.0, focal_y=510.0, dtype=dtype)[0]
    return K


def test_disparity_depth_round_trip_per_batch():
    d = torch.rand(2, 1, 4, 5) * 20 + 0.5
    f, b = torch.tensor([398.0, 721.0]), torch.tensor([0.08, 0.54])
    z = disparity_to_depth(d, f, b)
    torch.testing.assert_close(z[1], 721.0 * 0.54 / d[1])
    torch.testing.assert_close(depth_to_disparity(z, f, b), d)


def test_paper_depth_layers():
    # docs/method.md: with f*B = 31.84, 1 px of disparity is 31.8 m, 2 px 15.9 m, 3 px 10.6 m.
    z = disparity_to_depth(torch.tensor([[1.0, 2.0, 3.0]]), torch.tensor([398.0]), torch.tensor([0.08]))
    torch.testing.assert_close(z, torch.tensor([[31.84, 15.92, 10.6133]]), atol=1e-3, rtol=0)


def test_zero_disparity_is_finite_with_finite_gradient():
    d = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    z = disparity_to_depth(d, torch.tensor([398.0], dtype=torch.float64), torch.tensor([0.08], dtype=torch.float64))
    z.sum().backward()
    assert torch.isfinite(z).all() and torch.isfinite(d.grad).all()


def test_project_unproject_round_trip():
    K = _K()
    px = torch.rand(2, 50, 2) * torch.tensor([640.0, 480.0])
    z = torch.rand(2, 50) * 10 + 1
    pts = unproject(px, z, K)
    torch.testing.assert_close(pts[..., 2], z)
    torch.testing.assert_close(project(pts, K), px, atol=1e-3, rtol=0)


def test_unproject_disparity_matches_pointwise_unproject():
    K = _K()
    d = torch.rand(2, 1, 6, 7) * 10 + 1
    base = torch.tensor([0.08, 0.5])
    pts = unproject_disparity(d, K, base)
    assert pts.shape == (2, 6, 7, 3)
    grid = pixel_grid(6, 7).reshape(1, -1, 2).expand(2, -1, -1)
    z = disparity_to_depth(d, K[:, 0, 0], base).reshape(2, -1)
    torch.testing.assert_close(pts.reshape(2, -1, 3), unproject(grid, z, K))


def test_gradcheck_camera_functions():
    K = _K(1, torch.float64)
    px = (torch.rand(1, 4, 2, dtype=torch.float64) * 100).requires_grad_()
    z = (torch.rand(1, 4, dtype=torch.float64) + 1).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: unproject(a, b, K), (px, z))
    pts = (torch.rand(1, 4, 3, dtype=torch.float64) + torch.tensor([0, 0, 2.0], dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda p: project(p, K), (pts,))
    d = (torch.rand(1, 1, 2, 3, dtype=torch.float64) + 1).requires_grad_()
    base = torch.tensor([0.1], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: unproject_disparity(x, K, base), (d,))


def test_bad_input():
    K = _K()
    with pytest.raises(ShapeError, match="K: expected shape"):
        project(torch.zeros(2, 3, 3), torch.eye(3))
    with pytest.raises(ShapeError, match="depth: dimension N must be 3"):
        unproject(torch.zeros(2, 3, 2), torch.ones(2, 4), K)
    with pytest.raises(ValueRangeError, match="baseline"):
        unproject_disparity(torch.ones(2, 1, 3, 3), K, torch.tensor([0.1, -0.1]))
    with pytest.raises(ShapeError, match="baseline"):
        disparity_to_depth(torch.ones(2, 1, 3, 3), torch.ones(2), torch.ones(3))
