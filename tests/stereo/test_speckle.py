"""Speckle removal: known regions, both paths equal, OpenCV's rule, bad input, and its use in match_stereo."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import egorefine.stereo.speckle as speckle
from egorefine.core import DTypeError, ShapeError, ValueRangeError, dispatch
from egorefine.stereo import INVALID_VARIANCE, match_stereo, remove_speckles


def _both(disp, valid, max_size, max_diff):
    """(compiled, torch reference) outputs."""
    previous = dispatch.ENABLED
    try:
        out = []
        for compiled in (True, False):
            dispatch.ENABLED = compiled
            out.append(remove_speckles(disp, valid, max_size, max_diff))
    finally:
        dispatch.ENABLED = previous
    return out


def _random_map(seed: int, b: int = 2, h: int = 24, w: int = 31):
    g = torch.Generator().manual_seed(seed)
    # piecewise-constant patches plus noise: regions of many sizes, some linked across small steps
    coarse = torch.randint(0, 6, (b, 1, h // 4 + 1, w // 4 + 1), generator=g).float() * 1.5
    disp = torch.nn.functional.interpolate(coarse, scale_factor=4, mode="nearest")[..., :h, :w].contiguous()
    disp = disp + 0.4 * torch.rand(b, 1, h, w, generator=g)
    noisy = torch.rand(b, 1, h, w, generator=g) < 0.1
    disp = torch.where(noisy, 20 * torch.rand(b, 1, h, w, generator=g), disp)
    valid = torch.rand(b, 1, h, w, generator=g) > 0.15
    return disp, valid


def test_island_removed_and_surface_kept():
    disp = torch.full((1, 1, 10, 12), 5.0)
    disp[..., 2:4, 2:5] = 20.0  # 6 pixels
    disp[..., 7, 9] = 30.0  # 1 pixel
    valid = torch.ones(1, 1, 10, 12, dtype=torch.bool)
    for out in _both(disp, valid, 6, 1.0):
        assert not out[..., 2:4, 2:5].any() and not out[0, 0, 7, 9]
        assert int(out.sum()) == 120 - 7
    for out in _both(disp, valid, 5, 1.0):  # the 6-pixel island is no longer small enough
        assert out[..., 2:4, 2:5].all() and not out[0, 0, 7, 9]


def test_slope_within_range_is_one_region():
    # a ramp of 0.9 px per column links across all of it; 1.1 px per column splits it into columns
    x = torch.arange(12.0).view(1, 1, 1, 12).expand(1, 1, 5, 12)
    valid = torch.ones(1, 1, 5, 12, dtype=torch.bool)
    for out in _both(0.9 * x, valid, 10, 1.0):
        assert out.all()
    for out in _both(1.1 * x, valid, 10, 1.0):
        assert not out.any()


def test_region_joined_only_far_below_is_one_region():
    # two 2-px-wide arms (8 rows each: 16 px) on a background they do not link to, joined by a bar in their last
    # row only, and a staircase whose rows link through one shared column each: the arms
    # alone are small, the U is not; the staircase is one region of 10 px
    disp = torch.full((1, 1, 12, 16), 50.0)
    valid = torch.zeros(1, 1, 12, 16, dtype=torch.bool)
    disp[..., 0:8, 1:3] = 5.0
    disp[..., 0:8, 7:9] = 5.4
    disp[..., 7, 3:7] = 5.2
    valid[..., 0:8, 1:3] = valid[..., 0:8, 7:9] = valid[..., 7, 3:7] = True
    for y in range(5):  # a staircase: row 4 + y covers columns 10 + y and 11 + y
        disp[..., 4 + y, 10:16] = 9.0
        valid[..., 4 + y, 10 + y : 12 + y] = True
    for out in _both(disp, valid, 30, 1.0):
        assert out[..., 0:8, 1:3].all() and out[..., 7, 3:7].all()  # the U: 36 px
        assert not out[..., :, 10:].any()  # the staircase: 10 px
    for out in _both(disp, valid, 9, 1.0):
        assert int(out[..., :, 10:].sum()) == 10
    disp[..., 7, 3:7] = 7.0  # the bar no longer links to the arms: every piece is small
    for out in _both(disp, valid, 30, 1.0):
        assert not out[..., :, :9].any()


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(("max_size", "max_diff"), [(1, 0.5), (9, 1.0), (30, 2.0)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_equals_torch_reference(seed, max_size, max_diff, dtype):
    disp, valid = _random_map(seed)
    disp = disp.to(dtype)
    compiled, reference = _both(disp, valid, max_size, max_diff)
    assert torch.equal(compiled, reference)
    assert not (compiled & ~valid).any()


@pytest.mark.skipif(not speckle.AVAILABLE, reason="numba not installed")
@pytest.mark.parametrize("threads", [2, 3, 7])
def test_compiled_bands_give_the_mask_of_one_band(threads):
    # bands of rows label in parallel and are joined at their seams: regions crossing seams (the tall stripes of
    # _random_map's patches) must come out as from one band, and as the torch reference
    disp, valid = _random_map(6, b=2, h=41, w=29)
    whole = speckle._remove_speckles_compiled(disp, valid, 30, 1.0, threads=1)
    reference = _both(disp, valid, 30, 1.0)[1]
    assert np.array_equal(whole, reference[:, 0].numpy())
    assert np.array_equal(speckle._remove_speckles_compiled(disp, valid, 30, 1.0, threads=threads), whole)


@pytest.mark.skipif(not speckle.AVAILABLE, reason="numba not installed")
@pytest.mark.parametrize("threads", [1, 2, 3])
def test_cleared_pass_equals_the_filter_then_the_clearing(threads):
    # the matcher's path: the mask and the cleared maps in one pass, as remove_speckles then clear_invalid_
    disp, valid = _random_map(4, b=2, h=41, w=29)
    variance = torch.rand(disp.shape, generator=torch.Generator().manual_seed(5))
    expect_valid = remove_speckles(disp, valid, 30, 1.0)
    expect_d, expect_var = disp.clone(), variance.clone()
    speckle.clear_invalid_(expect_valid, expect_d, expect_var, 7.0)
    d, var = disp.clone(), variance.clone()
    got = torch.from_numpy(speckle._remove_speckles_compiled(d, valid, 30, 1.0, threads=threads,
                                                             clear=(var, 7.0)))[:, None]
    assert torch.equal(got, expect_valid)
    assert torch.equal(d, expect_d) and torch.equal(var, expect_var)
    assert (~got).any() and (var == 7.0).sum() == (~got).sum()  # (some removed: the clearing was exercised)
    # the public helper: the same, and None (nothing touched) where its pass does not apply
    d, var = disp.clone(), variance.clone()
    assert torch.equal(speckle.remove_speckles_cleared_(d, valid, var, 30, 1.0, 7.0), expect_valid)
    assert torch.equal(d, expect_d)
    d64 = disp.double()
    assert speckle.remove_speckles_cleared_(d64, valid, variance.double(), 30, 1.0, 7.0) is None
    assert torch.equal(d64, disp.double())


def test_matches_opencv_filter_speckles():
    cv2 = pytest.importorskip("cv2")
    disp, valid = _random_map(3, b=1, h=40, w=50)
    q = torch.round(disp * 16)  # OpenCV's fixed point: 1 px = 16 units, range 1 px = 16
    theirs = np.where(valid[0, 0].numpy(), q[0, 0].numpy(), -16).astype(np.int16)
    cv2.filterSpeckles(theirs, -16, 12, 16)
    for out in _both(q / 16, valid, 12, 1.0):
        assert np.array_equal(out[0, 0].numpy(), theirs >= 0)


def test_batch_items_are_independent():
    disp, valid = _random_map(4, b=3)
    for compiled in (True, False):
        dispatch.ENABLED = compiled
        try:
            whole = remove_speckles(disp, valid, 9)
            alone = torch.cat([remove_speckles(disp[i : i + 1], valid[i : i + 1], 9) for i in range(3)])
        finally:
            dispatch.ENABLED = True
        assert torch.equal(whole, alone)



@pytest.mark.parametrize("backend", ["eager", pytest.param("inductor", marks=pytest.mark.slow)])
def test_torch_compile_gives_the_same_mask(backend, require_backend):
    """Compiled, the filter runs its torch path with the propagation as one ``torch.while_loop`` (where torch has
    it) and gives the mask of both eager paths; inductor once failed on it (C++ that did not compile)."""
    require_backend(backend)
    disp, valid = _random_map(5)
    disp[..., :12, :], valid[..., :12, :] = 30.0, True  # a surface of 372 pixels above the small regions
    compiled = torch.compile(remove_speckles, backend=backend, fullgraph=True)
    for max_size in (9, 200):  # 200: match_stereo's default
        want, reference = _both(disp, valid, max_size, 1.0)
        assert torch.equal(want, reference)
        got = compiled(disp, valid, max_size, 1.0)
        assert torch.equal(got, want)
        assert 0 < int((valid & ~got).sum()) < int(valid.sum())  # some regions removed, not all

def test_bad_input():
    d, v = torch.zeros(1, 1, 4, 4), torch.ones(1, 1, 4, 4, dtype=torch.bool)
    with pytest.raises(ShapeError, match="valid"):
        remove_speckles(d, v[..., :3])
    with pytest.raises(DTypeError, match="valid"):
        remove_speckles(d, v.float())
    with pytest.raises(ValueRangeError, match="max_size"):
        remove_speckles(d, v, -1)
    with pytest.raises(ValueRangeError, match="max_diff"):
        remove_speckles(d, v, 4, float("nan"))
    with pytest.raises(ValueRangeError, match="speckle_size"):
        match_stereo(torch.rand(1, 1, 16, 24), torch.rand(1, 1, 16, 24), 8, block_size=5, speckle_size=2.5)


@pytest.mark.parametrize("options", [{}, {"cost": "census", "aggregation": "sgm", "block_size": 5}])
def test_match_stereo_speckle_option(options):
    g = torch.Generator().manual_seed(0)
    left = torch.rand(1, 1, 40, 64, generator=g)
    right = torch.roll(left, -4, dims=-1) + 0.05 * torch.rand(1, 1, 40, 64, generator=g)
    plain = match_stereo(left, right, 16, **options)
    out = match_stereo(left, right, 16, speckle_size=20, **options)
    expected = remove_speckles(plain.disparity, plain.valid, 20, 1.0)
    assert torch.equal(out.valid, expected)
    assert torch.equal(out.disparity, torch.where(expected, plain.disparity, torch.zeros_like(plain.disparity)))
    assert torch.equal(out.variance[expected], plain.variance[expected])
    assert (out.variance[~expected] == INVALID_VARIANCE).all()


def test_gradient_through_the_filtered_output():
    g = torch.Generator().manual_seed(1)
    left = torch.rand(1, 1, 24, 40, generator=g, dtype=torch.float64, requires_grad=True)
    right = torch.roll(left.detach(), -3, dims=-1).requires_grad_(True)
    out = match_stereo(left, right, 8, block_size=5, differentiable=True, speckle_size=10)
    out.disparity[out.valid].sum().backward()
    assert torch.isfinite(left.grad).all() and torch.isfinite(right.grad).all() and left.grad.abs().sum() > 0


# The SGM option's strong default smoothing carries its winners across unrelated noise in regions large enough to pass
# the speckle filter (docs/decisions.md, issue 17): there its opt-in raw-cost check keeps them out.
@pytest.mark.parametrize("options", [{}, {"cost": "census", "aggregation": "sgm", "block_size": 5,
                                          "census_max_distance": 0.45}])
def test_uncorrelated_images_give_almost_no_valid_pixels(options):
    """Two independent noise images share no surface: with its default speckle filter the matcher marks under 2 %
    of the pixels valid (without it, isolated lucky matches pass every check)."""
    g = torch.Generator().manual_seed(0)
    left, right = torch.rand(1, 1, 120, 160, generator=g), torch.rand(1, 1, 120, 160, generator=g)
    assert match_stereo(left, right, 48, **options).valid.float().mean() < 0.02
    assert match_stereo(left, right, 48, speckle_size=0).valid.float().mean() > 0.05  # what the filter removes
