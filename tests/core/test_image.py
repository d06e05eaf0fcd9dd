"""egorefine.core.to_grey: kornia's luma conversion, on the CPU a piece of rows at a time."""

from __future__ import annotations

import pytest
import torch
from kornia.color import rgb_to_grayscale

from egorefine.core import image as image_module
from egorefine.core import to_grey


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(1, 3, 500, 741), (2, 3, 97, 640), (3, 3, 10, 9)])
def test_to_grey_is_kornias_conversion(shape, dtype):
    """Large images go in pieces (below ATen's grain size), small ones in one call: the values are kornia's, to the
    last bit where the same torch kernels run (here up to an ulp, in case a kernel's remainder loop differs from its
    vector body); a wrong weight would be off by about 1e-3."""
    g = torch.Generator().manual_seed(1)
    x = torch.rand(*shape, generator=g, dtype=dtype)
    out = to_grey(x)
    assert out.shape == (shape[0], 1, *shape[2:]) and out.dtype == dtype
    torch.testing.assert_close(out, rgb_to_grayscale(x), rtol=0, atol=1e-7)


def test_to_grey_pieces_and_passthrough():
    x = torch.rand(1, 3, 500, 741)
    assert 1 < -(-500 // (image_module._PIECE // 741))  # more than one piece: the piecewise path runs
    grey = torch.rand(1, 1, 4, 5)
    assert to_grey(grey) is grey
    # with a gradient kornia's own call runs, and the gradient reaches the colour image
    y = x[..., :40, :50].clone().requires_grad_()
    to_grey(y).sum().backward()
    torch.testing.assert_close(y.grad[0, :, 0, 0], torch.tensor([0.299, 0.587, 0.114]))
