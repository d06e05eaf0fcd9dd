"""Tests of egorefine.stereo._sad_numba: the compiled default matcher against the torch integer path."""

from __future__ import annotations

import pytest
import torch

import egorefine.stereo.fast as fast
import egorefine.stereo.matching as matching
from egorefine.core import _jit, dispatch
from egorefine.stereo import _sad_numba, match_stereo

from ._synthetic import planar_pair, smooth_texture

needs_numba = pytest.mark.skipif(not _sad_numba.AVAILABLE, reason="numba not installed")
_CAP = 31.0 / 255.0


def _opts(**kw) -> dict:
    return {"subpixel": True, "subpixel_fit": "equiangular", "lr_check": True, "lr_threshold": 1,
            "uniqueness_ratio": 0.15, "texture_threshold": 0.004, "cost_floor": 1e-3, **kw}


@pytest.fixture(scope="module")
def pair():
    # a slanted plane, then the left half of the right image replaced by another texture: occlusion-like
    # mismatches, so that the left-right and uniqueness checks reject a fair share of the pixels
    left, right, _ = planar_pair(batch=2, height=37, width=83, seed=11, base=7.5, slope_x=0.04, slope_y=0.02)
    right = right.clone()
    right[..., :, 20:34] = smooth_texture(2, 37, 14, seed=5)
    return left, right


@needs_numba
@pytest.mark.parametrize(("max_d", "min_d", "block", "kw"), [
    (16, 0, 9, {}),
    (16, 3, 7, {"lr_threshold": 2, "subpixel_fit": "parabola"}),
    (12, 0, 5, {"lr_check": False, "uniqueness_ratio": 0.0}),
    (20, 0, 3, {"lr_threshold": 0, "subpixel": False}),
    (9, 2, 1, {"lr_threshold": 3}),  # 1x1 windows, odd candidate count
    (80, 0, 5, {}),  # more candidates than most columns have in view
])
def test_compiled_equals_torch_integer_path(pair, max_d, min_d, block, kw):
    left, right = pair
    opts = _opts(**kw)
    scale = fast.int_scale(block, _CAP)
    ref = fast.match_sad_int(left, right, max_d, min_d, block, _CAP, scale, opts)
    out = _sad_numba.match_sad_compiled(left, right, max_d, min_d, block, _CAP, scale, opts, threads=2)
    # integer costs are exact and the float tail repeats fast._tail's operations: equal bit for bit
    for a, b in zip(out, ref, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        assert torch.equal(a, b)
    share = ref[1].float().mean()
    assert 0.05 < share < 0.98, f"valid share {share:.3f}: the checks should pass some pixels and reject others"


@needs_numba
@pytest.mark.parametrize("threads", [1, 3])
def test_threads_and_batch_items_do_not_change_the_output(pair, threads):
    left, right = pair
    opts = _opts()
    scale = fast.int_scale(9, _CAP)
    both = _sad_numba.match_sad_compiled(left, right, 16, 0, 9, _CAP, scale, opts, threads=2)
    for i in range(2):
        alone = _sad_numba.match_sad_compiled(left[i : i + 1], right[i : i + 1], 16, 0, 9, _CAP, scale, opts,
                                              threads=threads)
        for a, b in zip(both, alone, strict=True):
            assert torch.equal(a[i : i + 1], b)


@needs_numba
def test_match_stereo_takes_the_compiled_path_for_float32_cpu(pair, monkeypatch):
    left, right = pair
    calls = []
    compiled = _sad_numba.match_sad_compiled
    monkeypatch.setattr(_sad_numba, "match_sad_compiled", lambda *a, **k: calls.append(1) or compiled(*a, **k))
    out = match_stereo(left, right, 16)
    assert calls == [1]
    monkeypatch.setattr(dispatch, "ENABLED", False)
    ref = match_stereo(left, right, 16)
    assert calls == [1]
    for a, b in zip(out, ref, strict=True):
        assert torch.equal(a, b)


def test_torch_path_when_compiled_does_not_apply(pair, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("the compiled path ran")

    left, right = pair
    monkeypatch.setattr(_sad_numba, "match_sad_compiled", refuse)
    monkeypatch.setattr(_jit, "AVAILABLE", False)
    assert match_stereo(left, right, 16).disparity.shape == (2, 1, 37, 83)
    monkeypatch.setattr(_jit, "AVAILABLE", True)
    match_stereo(left.double(), right.double(), 16)  # float64: the torch integer path
    match_stereo(left, right, 16, cost="zncc")  # other costs: the float path
    match_stereo(left.requires_grad_(True), right, 16)  # a gradient is wanted: the float path
    with pytest.raises(AssertionError, match="compiled path"):
        match_stereo(left.detach(), right, 16)


@needs_numba
def test_textureless_pair_is_all_invalid_without_nan():
    flat = torch.full((1, 1, 16, 24), 0.5)
    out = match_stereo(flat, flat, 8, block_size=5)
    assert not out.valid.any()
    assert (out.disparity == 0).all()
    assert (out.variance == matching.INVALID_VARIANCE).all()


@needs_numba
def test_compiled_accuracy_on_a_slanted_plane():
    # known truth: sub-pixel error on a textured plane well under a quarter pixel
    left, right, truth = planar_pair(batch=1, height=48, width=96, seed=2, base=6.3, slope_x=0.02, slope_y=0.01)
    out = match_stereo(left, right, 16)
    inside = out.valid.clone()
    inside[..., :, :24] = False  # the left columns see no match for the larger disparities
    assert inside.float().mean() > 0.5
    err = (out.disparity - truth)[inside].abs()
    assert err.mean() < 0.1, f"EPE {err.mean():.3f}"
