"""Tests of egorefine.stereo.cost against naive per-disparity references."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from egorefine.stereo import COSTS, census_transform, cost_volume, prefilter_xsobel
from egorefine.stereo.cost import box_sum_valid


def _pad(x, r):
    h, w = x.shape[-2:]
    rows, cols = torch.arange(-r, h + r).clamp(0, h - 1), torch.arange(-r, w + r).clamp(0, w - 1)
    return x[..., rows, :][..., cols]  # replicate (works for the integer census strings too)


def _naive_volume(left, right, max_d, min_d, k, cost):
    """Loop over disparities; windows read from the replicate-padded images, like the fast path."""
    r = k // 2
    if cost == "sad":
        left, right = prefilter_xsobel(left), prefilter_xsobel(right)
    if cost == "census":
        left, right = census_transform(left), census_transform(right)
    w = left.shape[-1]
    lp, rp = _pad(left, r), _pad(right, r)
    cols = torch.arange(w + 2 * r)
    out = []
    for d in range(min_d, max_d):
        shifted = rp[..., (cols - d).clamp_min(0)]  # right pixel x - d (left of the image: column 0)
        if cost == "sad":
            raw = (lp - shifted).abs()
        elif cost == "census":
            x = torch.bitwise_xor(lp, shifted)
            raw = sum(((x >> b) & 1) for b in range(24)).to(torch.float64)
        if cost == "zncc":
            lw = lp.unfold(2, k, 1).unfold(3, k, 1)
            rw = shifted.unfold(2, k, 1).unfold(3, k, 1)
            lz = lw - lw.mean(dim=(-1, -2), keepdim=True)
            rz = rw - rw.mean(dim=(-1, -2), keepdim=True)
            cov = (lz * rz).mean(dim=(-1, -2))
            sd = torch.sqrt(lz.pow(2).mean(dim=(-1, -2)) + 1e-4) * torch.sqrt(rz.pow(2).mean(dim=(-1, -2)) + 1e-4)
            c = 1 - cov / sd
        else:
            c = F.avg_pool2d(raw, k, stride=1)
        out.append(torch.where(torch.arange(w) < d, torch.inf, c))
    return torch.cat(out, dim=1)


@pytest.mark.parametrize("cost", COSTS)
@pytest.mark.parametrize("min_d", [0, 2])
def test_cost_volume_matches_naive_reference(cost, min_d):
    gen = torch.Generator().manual_seed(0)
    left = torch.rand(2, 1, 11, 19, generator=gen, dtype=torch.float64)
    right = torch.rand(2, 1, 11, 19, generator=gen, dtype=torch.float64)
    fast = cost_volume(left, right, 7, min_d, block_size=5, cost=cost)
    slow = _naive_volume(left, right, 7, min_d, 5, cost)
    assert fast.shape == (2, 7 - min_d, 11, 19)
    inside = torch.isfinite(slow)
    assert torch.allclose(fast[inside], slow[inside], atol=1e-9)
    assert (fast[~inside] > 1e3).all()  # out-of-view candidates carry the invalid cost


def test_integer_shift_is_the_volume_minimum():
    gen = torch.Generator().manual_seed(1)
    right = torch.rand(1, 1, 20, 40, generator=gen)
    left = torch.cat([right[..., :1].expand(-1, -1, -1, 5), right[..., :-5]], dim=-1)  # left(x) = right(x - 5)
    for cost in COSTS:
        vol = cost_volume(left, right, 12, block_size=5, cost=cost)
        assert (vol.argmin(dim=1)[..., 3:-3, 12:-3] == 5).all(), cost


def test_box_sum_valid_against_unfold():
    gen = torch.Generator().manual_seed(2)
    x = torch.rand(3, 4, 30, generator=gen, dtype=torch.float64)
    for k in (1, 2, 3, 5, 7, 9, 13, 16):
        ref = x.unfold(-1, k, 1).sum(-1)
        assert torch.allclose(box_sum_valid(x, k, -1), ref), k


def test_census_bits():
    img = torch.zeros(1, 1, 3, 3)
    img[0, 0, 0, 0] = -1.0  # the only darker neighbour of the centre: bit 0
    assert census_transform(img, 3)[0, 0, 1, 1] == 1
    assert census_transform(torch.full((1, 1, 5, 5), 0.5), 5).eq(0).all()


def test_prefilter_equals_kornia_sobel():
    from kornia.filters import spatial_gradient

    gen = torch.Generator().manual_seed(5)
    x = torch.rand(2, 1, 9, 11, generator=gen, dtype=torch.float64)
    ref = spatial_gradient(x, mode="sobel", order=1, normalized=False)[:, :, 0].clamp(-0.3, 0.3)
    assert torch.allclose(prefilter_xsobel(x, cap=0.3), ref)


def test_prefilter_caps_and_gradcheck():
    gen = torch.Generator().manual_seed(3)
    x = torch.rand(1, 1, 6, 7, generator=gen, dtype=torch.float64)
    y = prefilter_xsobel(x, cap=0.2)
    assert y.abs().max() <= 0.2
    small = (0.5 + 0.01 * x).requires_grad_()
    assert torch.autograd.gradcheck(lambda t: prefilter_xsobel(t), (small,), fast_mode=True)


@pytest.mark.parametrize("cost", ["sad", "zncc"])
def test_cost_volume_gradcheck(cost):
    gen = torch.Generator().manual_seed(4)
    left = (0.5 + 0.02 * torch.rand(1, 1, 5, 9, generator=gen, dtype=torch.float64)).requires_grad_()
    right = (0.5 + 0.02 * torch.rand(1, 1, 5, 9, generator=gen, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: cost_volume(a, b, 3, block_size=3, cost=cost), (left, right),
                                    fast_mode=True)
