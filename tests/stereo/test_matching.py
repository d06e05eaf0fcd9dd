"""Tests of egorefine.stereo.matching: block_matching / match_stereo / BlockMatching."""

from __future__ import annotations

import pytest
import torch

from egorefine.core import DeviceError, DTypeError, ShapeError, ValueRangeError
from egorefine.metrics import bad_pixel_rate, epe
from egorefine.stereo import INVALID_VARIANCE, BlockMatching, StereoOutput, block_matching, match_stereo

from ._synthetic import planar_pair, visible


@pytest.fixture(scope="module")
def pair():
    return planar_pair(batch=2, height=64, width=96, seed=0)


# ---------------------------------------------------------------- smoke and shapes
def test_shapes_and_types(pair):
    left, right, _ = pair
    out = match_stereo(left, right, 16)
    assert isinstance(out, StereoOutput)
    for t in out:
        assert t.shape == (2, 1, 64, 96)
    assert out.valid.dtype == torch.bool
    assert out.disparity.dtype == torch.float32
    assert torch.isfinite(out.disparity).all() and torch.isfinite(out.variance).all()
    assert (out.disparity[~out.valid] == 0).all()
    assert (out.variance[~out.valid] == INVALID_VARIANCE).all()
    assert (out.variance[out.valid] >= 1 / 12 - 1e-6).all()


def test_colour_input_is_converted_to_grey(pair):
    left, right, _ = pair
    d_grey, v_grey = block_matching(left, right, 16)
    d_rgb, v_rgb = block_matching(left.expand(-1, 3, -1, -1), right.expand(-1, 3, -1, -1), 16)
    assert d_rgb.shape == (2, 1, 64, 96)
    assert torch.equal(v_rgb, v_grey)
    # The grey of three equal channels is the channel to a float32 step (the weights' sum rounds). The integer
    # matcher quantises grey levels, so such a step can tip one pixel's level: a window cost moves by one unit and
    # the sub-pixel fit by ~1e-4 px, more where the cost curve is flat. Far below the matcher's accuracy.
    assert torch.allclose(d_rgb, d_grey, atol=2e-3, rtol=0)


@pytest.mark.parametrize("kw", [
    {}, {"cost": "zncc"}, {"cost": "census"}, {"aggregation": "sgm", "block_size": 5},
    {"aggregation": "sgm", "sgm_paths": 8, "cost": "census", "block_size": 3}, {"subpixel": False},
    {"cost": "census", "census_window": 7}, {"cost": "census", "census_window": 3},
    {"differentiable": True}, {"lr_check": False, "uniqueness_ratio": 0.0, "min_disparity": 3},
])
def test_options_run_and_respect_range(pair, kw):
    left, right, _ = pair
    disparity, valid = block_matching(left, right, 16, **kw)
    assert disparity.shape == valid.shape == (2, 1, 64, 96)
    assert valid.float().mean() > 0.5
    lo = kw.get("min_disparity", 0)
    assert (disparity[valid] >= lo - 0.5).all() and (disparity[valid] <= 15.5).all()
    if kw.get("subpixel") is False:
        assert torch.equal(disparity, disparity.round())


# ---------------------------------------------------------------- bad input
def test_exceptions():
    img = torch.rand(1, 1, 16, 24)
    with pytest.raises(ShapeError, match="left"):
        block_matching(img[0], img, 8)
    with pytest.raises(ShapeError, match="right"):
        block_matching(img, torch.rand(1, 1, 16, 20), 8)
    with pytest.raises(ShapeError, match="right"):
        block_matching(img, torch.rand(2, 1, 16, 24), 8)
    with pytest.raises(DeviceError, match="right"):
        block_matching(img, torch.rand(1, 1, 16, 24, device="meta"), 8)
    with pytest.raises(DTypeError, match="left"):
        block_matching((img * 255).to(torch.uint8), img, 8)
    with pytest.raises(DTypeError, match="right"):
        block_matching(img, (img * 255).to(torch.uint8), 8)
    for bad in (0, -3, 24, 30):
        with pytest.raises(ValueRangeError, match="max_disparity"):
            block_matching(img, img, bad)
    with pytest.raises(DTypeError, match="max_disparity"):
        block_matching(img, img, 8.0)
    with pytest.raises(ValueRangeError, match="min_disparity"):
        block_matching(img, img, 8, min_disparity=8)
    nan = img.clone()
    nan[0, 0, 3, 4] = float("nan")
    with pytest.raises(ValueRangeError, match="left"):
        block_matching(nan, img, 8)
    inf = img.clone()
    inf[0, 0, 1, 1] = float("inf")
    with pytest.raises(ValueRangeError, match="right"):
        block_matching(img, inf, 8)
    with pytest.raises(ValueRangeError, match="block_size"):
        block_matching(img, img, 8, block_size=4)
    with pytest.raises(ValueRangeError, match="cost"):
        block_matching(img, img, 8, cost="ssd")
    with pytest.raises(ValueRangeError, match="cost"):
        block_matching(img, img, 8, cost="census", differentiable=True)
    with pytest.raises(ValueRangeError, match="aggregation"):
        block_matching(img, img, 8, aggregation="tree")
    with pytest.raises(ValueRangeError, match="sgm_paths"):
        block_matching(img, img, 8, aggregation="sgm", sgm_paths=6)
    with pytest.raises(ValueRangeError, match="census_window"):
        block_matching(img, img, 8, cost="census", census_window=9)
    with pytest.raises(ValueRangeError, match="soft_radius"):
        block_matching(img, img, 8, differentiable=True, soft_radius=0)
    with pytest.raises(ValueRangeError, match="temperature"):
        block_matching(img, img, 8, differentiable=True, temperature=0.0)
    with pytest.raises(ValueRangeError, match="uniqueness_ratio"):
        block_matching(img, img, 8, uniqueness_ratio=-0.1)
    with pytest.raises(ValueRangeError, match="uniqueness_ratio"):
        block_matching(img, img, 8, uniqueness_ratio="0.1")
    with pytest.raises(ValueRangeError, match="sgm_p1"):
        block_matching(img, img, 8, aggregation="sgm", sgm_p1=float("nan"))
    with pytest.raises(ValueRangeError, match="sgm_p2"):
        block_matching(img, img, 8, aggregation="sgm", sgm_p1=2.0, sgm_p2=1.0)
    for bad in (-0.1, 1.5, "0.3"):
        with pytest.raises(ValueRangeError, match="census_max_distance"):
            block_matching(img, img, 8, cost="census", aggregation="sgm", census_max_distance=bad)


def test_uniqueness_default_per_aggregation(pair):
    # None takes the aggregation's ratio: the same output as that ratio given explicitly
    left, right, _ = pair
    for aggregation, ratio in (("box", 0.15), ("sgm", 0.1)):
        kw = {"aggregation": aggregation, "cost": "census", "block_size": 5}
        implicit, explicit = match_stereo(left, right, 16, **kw), match_stereo(left, right, 16, uniqueness_ratio=ratio,
                                                                                **kw)
        for a, b in zip(implicit, explicit, strict=True):
            assert torch.equal(a, b)


@pytest.mark.parametrize("kw", [{}, {"cost": "zncc"}, {"cost": "census"}, {"aggregation": "sgm", "block_size": 5},
                                {"differentiable": True}])
def test_textureless_gives_all_invalid(kw):
    flat = torch.full((1, 1, 24, 40), 0.4)
    out = match_stereo(flat, flat, 8, **kw)
    assert not out.valid.any()
    assert (out.disparity == 0).all()
    assert torch.isfinite(out.variance).all()


# ---------------------------------------------------------------- gradients
def _tiny_pair(seed: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    # a fractional shift: no exactly-zero SAD term (|x| has no derivative at 0)
    left, right, _ = planar_pair(batch=1, height=7, width=12, seed=seed, base=1.6, slope_x=0.0, slope_y=0.0)
    # keep the x-Sobel response under the prefilter's clip so that gradients are not cut
    return (0.5 + 0.05 * left).double().requires_grad_(), (0.5 + 0.05 * right).double().requires_grad_()


@pytest.mark.parametrize("kw", [
    {"differentiable": True},
    {"differentiable": True, "cost": "zncc"},
    {"subpixel": True},
    {"subpixel": True, "subpixel_fit": "parabola", "cost": "zncc"},
    {"differentiable": True, "aggregation": "sgm"},
    {"differentiable": True, "soft_radius": None},
])
def test_gradcheck(kw):
    left, right = _tiny_pair()
    opts = {"block_size": 3, "lr_check": False, "uniqueness_ratio": 0.0, "texture_threshold": 0.0, **kw}

    def fn(a, b):
        return block_matching(a, b, 5, **opts)[0]

    assert torch.autograd.gradcheck(fn, (left, right), eps=1e-6, atol=1e-4, fast_mode=True)


def test_differentiable_gradients_reach_both_images(pair):
    left, right, gt = pair
    left = left[:1].clone().requires_grad_()
    right = right[:1].clone().requires_grad_()
    disparity, valid = block_matching(left, right, 16, differentiable=True)
    loss = ((disparity - gt[:1]).abs() * valid).sum()
    loss.backward()
    for g in (left.grad, right.grad):
        assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0


# ---------------------------------------------------------------- consistency
def test_function_equals_module(pair):
    left, right, _ = pair
    kw = {"block_size": 7, "cost": "zncc", "uniqueness_ratio": 0.1}
    d_fn, v_fn = block_matching(left, right, 16, **kw)
    d_mod, v_mod = BlockMatching(16, **kw)(left, right)
    assert torch.equal(d_fn, d_mod) and torch.equal(v_fn, v_mod)
    assert "max_disparity=16" in repr(BlockMatching(16, **kw))


@pytest.mark.parametrize("kw", [{}, {"aggregation": "sgm", "block_size": 5}, {"differentiable": True}])
def test_batch_item_equals_alone(pair, kw):
    left, right, _ = pair
    d_all, v_all = block_matching(left, right, 16, **kw)
    for b in range(2):
        d_one, v_one = block_matching(left[b : b + 1], right[b : b + 1], 16, **kw)
        assert torch.equal(v_all[b : b + 1], v_one)
        assert torch.allclose(d_all[b : b + 1], d_one, atol=1e-5)


def test_strips_do_not_change_the_result(pair, monkeypatch):
    import egorefine.stereo.matching as m

    left, right, _ = pair
    monkeypatch.setattr(m, "_INTEGER_PATH", False)  # the float path (tests/stereo/test_fast.py: integer path)
    d_ref, v_ref = block_matching(left, right, 16)
    monkeypatch.setattr(m, "_STRIP_ELEMENTS", 1)  # one row per strip
    d_rows, v_rows = block_matching(left, right, 16)
    assert torch.equal(v_ref, v_rows)
    assert torch.allclose(d_ref, d_rows, atol=1e-5)


# ---------------------------------------------------------------- accuracy against known truth
# (matcher options, EPE below): about 1.3 times what each cost achieves on this plane. Integer disparities on a
# slanted plane are off by a quarter pixel on average, so a matcher without its sub-pixel fit fails every case.
@pytest.mark.parametrize(("kw", "max_epe"), [({}, 0.08), ({"cost": "zncc"}, 0.085),
                                             ({"cost": "census", "block_size": 7}, 0.04),
                                             ({"aggregation": "sgm", "cost": "census", "block_size": 5}, 0.055)])
def test_subpixel_accuracy_on_textured_plane(kw, max_epe):
    left, right, gt = planar_pair(batch=1, height=80, width=112, seed=1, base=5.5, slope_x=0.03, slope_y=-0.01)
    out = match_stereo(left, right, 24, **kw)
    scored = visible(gt, 5)
    valid = out.valid & scored
    density = valid.sum() / scored.sum()
    assert density > 0.9
    assert epe(out.disparity, gt, valid) < max_epe
    assert bad_pixel_rate(out.disparity, gt, 1.0, valid) < 0.01


def test_differentiable_accuracy_on_textured_plane():
    left, right, gt = planar_pair(batch=1, height=80, width=112, seed=2, base=7.0, slope_x=0.02, slope_y=0.02)
    out = match_stereo(left, right, 24, differentiable=True)
    scored = visible(gt, 5)
    valid = out.valid & scored
    assert valid.sum() / scored.sum() > 0.9
    assert epe(out.disparity, gt, valid) < 0.3


def test_min_disparity_restricts_the_search():
    left, right, gt = planar_pair(batch=1, height=48, width=96, seed=4, base=10.0, slope_x=0.0, slope_y=0.0)
    out = match_stereo(left, right, 16, min_disparity=8)
    assert out.valid.float().mean() > 0.5
    assert (out.disparity[out.valid] - 10.0).abs().max() < 0.5
    assert (out.disparity[out.valid] >= 8).all()


def test_variance_grows_with_noise():
    left, right, gt = planar_pair(batch=1, height=64, width=96, seed=5)
    gen = torch.Generator().manual_seed(0)
    noisy = (right + 0.08 * torch.randn(right.shape, generator=gen)).clamp(0, 1)
    clean = match_stereo(left, right, 16)
    dirty = match_stereo(left, noisy, 16)
    both = clean.valid & dirty.valid
    assert dirty.variance[both].median() > clean.variance[both].median()
