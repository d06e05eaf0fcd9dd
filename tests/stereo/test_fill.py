"""fill_invalid: one map from a local matcher and a global one."""

from __future__ import annotations

import pytest
import torch

from egorefine.core import ShapeError
from egorefine.stereo import StereoOutput, fill_invalid


def _outputs(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    shape = (2, 1, 5, 7)
    a = StereoOutput(torch.rand(shape, generator=g) * 8, torch.rand(shape, generator=g) > 0.5,
                     torch.rand(shape, generator=g))
    b = StereoOutput(torch.rand(shape, generator=g) * 8, torch.rand(shape, generator=g) > 0.3,
                     torch.rand(shape, generator=g))
    return a, b


def test_primary_where_it_matched_secondary_elsewhere():
    a, b = _outputs()
    out = fill_invalid(a, b)
    assert torch.equal(out.valid, a.valid | b.valid)
    assert torch.equal(out.disparity[a.valid], a.disparity[a.valid])
    assert torch.equal(out.variance[a.valid], a.variance[a.valid])
    rest = ~a.valid
    assert torch.equal(out.disparity[rest], b.disparity[rest]) and torch.equal(out.variance[rest], b.variance[rest])


def test_compiled_and_torch_paths_agree_and_gradients_reach_the_pixels_each_supplies():
    a, b = _outputs(1)
    plain = fill_invalid(a, b)  # float32 CPU, no grad: the compiled pass (egorefine.stereo._fill_numba)
    da, db = a.disparity.clone().requires_grad_(True), b.disparity.clone().requires_grad_(True)
    graded = fill_invalid(StereoOutput(da, a.valid, a.variance), StereoOutput(db, b.valid, b.variance))
    assert torch.equal(graded.disparity.detach(), plain.disparity) and torch.equal(graded.valid, plain.valid)
    assert torch.equal(graded.variance, plain.variance)
    graded.disparity.sum().backward()
    assert torch.equal(da.grad, a.valid.float()) and torch.equal(db.grad, (~a.valid).float())


def test_shapes_must_match():
    a, b = _outputs()
    small = StereoOutput(*(t[:1] for t in b))
    with pytest.raises(ShapeError, match="fill_invalid"):
        fill_invalid(a, small)


def test_compiled_pass_over_bands_equals_the_rule():
    # a map large enough to be split over worker threads
    g = torch.Generator().manual_seed(3)
    shape = (1, 1, 260, 300)
    rand = lambda: torch.rand(shape, generator=g)  # noqa: E731
    a = StereoOutput(rand(), rand() > 0.6, rand())
    b = StereoOutput(rand(), rand() > 0.2, rand())
    out = fill_invalid(a, b)
    assert torch.equal(out.disparity, torch.where(a.valid, a.disparity, b.disparity))
    assert torch.equal(out.variance, torch.where(a.valid, a.variance, b.variance))
    assert torch.equal(out.valid, a.valid | b.valid)
