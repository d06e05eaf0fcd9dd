"""Tests of egorefine.stereo.fast: the exact int16 path of the default SAD box matcher against the float path."""

from __future__ import annotations

import pytest
import torch

import egorefine.stereo.fast as fast
import egorefine.stereo.matching as matching
from egorefine.metrics import epe
from egorefine.stereo import match_stereo

from ._synthetic import planar_pair, visible


def _both(left, right, max_d, **kw):
    """(float path, integer path) outputs of match_stereo."""
    previous = matching._INTEGER_PATH
    try:
        matching._INTEGER_PATH = False
        ref = match_stereo(left, right, max_d, **kw)
        matching._INTEGER_PATH = True
        new = match_stereo(left, right, max_d, **kw)
    finally:
        matching._INTEGER_PATH = previous
    return ref, new


def _u8(x: torch.Tensor) -> torch.Tensor:
    return (x * 255).round() / 255


@pytest.fixture(scope="module")
def pair():
    return planar_pair(batch=2, height=48, width=80, seed=7, base=6.5, slope_x=0.03, slope_y=0.01)


def test_int_scale():
    cap = 31.0 / 255.0
    assert fast.int_scale(9, cap) == 6  # 81 * 2 * 186 = 30132 < 32767
    assert fast.int_scale(15, cap) == 2
    assert fast.int_scale(21, cap) == 1
    assert fast.int_scale(23, cap) == 0  # 529 * 62 > 32767: the float path is used
    for k in (3, 9, 15, 21):
        s = fast.int_scale(k, cap)
        assert k * k * 2 * round(255 * s * cap) < fast._INVALID


@pytest.mark.parametrize("k", [1, 3, 5, 9, 15])
def test_box_sums_against_unfold(k):
    gen = torch.Generator().manual_seed(k)
    x = torch.randint(0, 300, (2, 3, 20, 31), generator=gen, dtype=torch.int16)
    rows = fast._box_rows(x, k, torch.empty(2, 3, 21 - k, 31, dtype=torch.int16))
    assert torch.equal(rows, x.unfold(2, k, 1).sum(-1).to(torch.int16))
    pairs = torch.empty_like(x)
    cols = fast._box_cols(x, k, torch.empty(2, 3, 20, 32 - k, dtype=torch.int16), pairs)
    assert torch.equal(cols, x.unfold(3, k, 1).sum(-1).to(torch.int16))


@pytest.mark.parametrize("kw", [
    {}, {"block_size": 5}, {"block_size": 15}, {"min_disparity": 3}, {"subpixel": False},
    {"subpixel_fit": "parabola"}, {"lr_check": False, "uniqueness_ratio": 0.0}, {"lr_threshold": 2},
])
def test_integer_path_equals_float_path_on_8bit_images(pair, kw):
    # 8-bit grey levels: the quantised costs are the float costs exactly (up to the float path's rounding)
    left, right, _ = pair
    ref, new = _both(_u8(left), _u8(right), 16, **kw)
    agree = (ref.valid == new.valid).float().mean()
    assert agree >= 0.995, f"validity agreement {agree:.4f}"
    both = ref.valid & new.valid
    assert both.float().mean() > 0.5
    assert (ref.disparity[both] - new.disparity[both]).abs().max() < 1e-3
    assert torch.allclose(ref.variance[both], new.variance[both], rtol=1e-2, atol=1e-4)
    assert (new.disparity[~new.valid] == 0).all()
    assert (new.variance[~new.valid] == matching.INVALID_VARIANCE).all()
    assert (new.variance[new.valid] >= 1 / 12 - 1e-6).all()
    assert new.disparity.dtype == ref.disparity.dtype


def test_integer_path_close_to_float_path_on_float_images(pair):
    # continuous grey levels are quantised to 1/(255 * 6) of a grey level: near-ties may flip, the rest agrees
    left, right, gt = pair
    ref, new = _both(left, right, 16)
    assert (ref.valid == new.valid).float().mean() >= 0.99
    both = ref.valid & new.valid
    close = (ref.disparity[both] - new.disparity[both]).abs() < 0.02
    assert close.float().mean() > 0.99
    scored = visible(gt, 5)
    assert abs(epe(ref.disparity, gt, ref.valid & scored) - epe(new.disparity, gt, new.valid & scored)) < 0.01


def test_strips_and_batch_do_not_change_the_result(pair, monkeypatch):
    left, right, _ = pair
    ref = match_stereo(left, right, 16)
    monkeypatch.setattr(fast, "_STRIP_ELEMENTS", 1)  # _MIN_ROWS rows per strip
    # 3 disparities per raw-cost chunk (B=2, 8 + 8 halo rows, 80 + 8 columns; 16 = 5 * 3 + 1)
    monkeypatch.setattr(fast, "_CHUNK_ELEMENTS", 3 * 2 * 16 * 88)
    rows = match_stereo(left, right, 16)
    assert torch.equal(ref.valid, rows.valid) and torch.equal(ref.disparity, rows.disparity)
    one = match_stereo(left[1:], right[1:], 16)
    assert torch.equal(ref.valid[1:], one.valid) and torch.equal(ref.disparity[1:], one.disparity)


def test_gradient_requests_take_the_float_path(pair):
    left, right, _ = pair
    left = left[:1].clone().requires_grad_(True)
    out = match_stereo(left, right[:1], 16, differentiable=True)
    out.disparity.sum().backward()
    assert left.grad is not None and torch.isfinite(left.grad).all()


def test_large_block_falls_back_to_the_float_path():
    left, right, gt = planar_pair(batch=1, height=40, width=64, seed=3, base=5.0, slope_x=0.0, slope_y=0.0)
    out = match_stereo(left, right, 12, block_size=25)  # int_scale(25) == 0
    assert out.valid.float().mean() > 0.2
    assert (out.disparity[out.valid] - 5.0).abs().max() < 0.5


def test_threaded_strips_equal_serial(pair, monkeypatch):
    # with several torch threads the strips run in a thread pool (one torch thread each)
    left, right, _ = pair
    monkeypatch.setattr(fast, "_STRIP_ELEMENTS", 1)  # several strips per worker
    ref = match_stereo(left, right, 16)  # the stereo tests run torch single-threaded (conftest)
    torch.set_num_threads(2)
    try:
        out = match_stereo(left, right, 16)
        assert torch.get_num_threads() == 2  # restored after the pool
    finally:
        torch.set_num_threads(1)
    assert torch.equal(ref.valid, out.valid) and torch.equal(ref.disparity, out.disparity)
    assert torch.equal(ref.variance, out.variance)
