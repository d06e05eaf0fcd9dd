"""Half-resolution matching: the way back to full resolution on known maps, both paths equal, a known shift
matched, bad input."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from egorefine.core import ShapeError, ValueRangeError, dispatch
from egorefine.stereo import INVALID_VARIANCE, StereoOutput
from egorefine.stereo.scale import _double, _halve, match_half_resolution

# float32 rounding of a blend of four values of a few tens of px: far below this, on any CPU
_TOL = 1e-4


def _paths(monkeypatch, fn, *args):
    """(compiled, torch reference) results of ``fn(*args)``."""
    out = []
    for compiled in (True, False):
        monkeypatch.setattr(dispatch, "ENABLED", compiled)
        out.append(fn(*args))
    return out


def _half_map(h: int, w: int, values: torch.Tensor, valid: torch.Tensor | None = None) -> StereoOutput:
    valid = torch.ones(1, 1, h, w, dtype=torch.bool) if valid is None else valid
    return StereoOutput(torch.where(valid, values, 0.0), valid, torch.where(valid, 0.1, INVALID_VARIANCE))


@pytest.mark.parametrize("compiled", [True, False])
def test_slanted_plane_comes_back_without_steps(monkeypatch, compiled):
    """A half-resolution ramp is a full-resolution ramp of the same slope per full px: the blend reproduces it at
    every inner pixel (2 x 2 blocks of one value would be off by a quarter of the slope per px)."""
    monkeypatch.setattr(dispatch, "ENABLED", compiled)
    h, w = 12, 16
    rows = torch.arange(h, dtype=torch.float32).view(1, 1, h, 1).expand(1, 1, h, w)
    half = _half_map(h, w, 5.0 + 0.4 * rows)  # 0.4 half px per half row: a road seen by a tilted camera
    out = _double(half, 2 * h, 2 * w, smooth=1.0, low=0.0, high=64.0)
    y = torch.arange(2 * h, dtype=torch.float32).view(1, 1, -1, 1)
    truth = 2.0 * (5.0 + 0.4 * (y / 2 - 0.25))  # full pixel y sits at half-resolution row y / 2 - 1/4
    inner = (slice(None), slice(None), slice(1, -1), slice(None))
    assert bool(out.valid.all())
    torch.testing.assert_close(out.disparity[inner], truth.expand(1, 1, 2 * h, 2 * w)[inner], rtol=0, atol=_TOL)
    torch.testing.assert_close(out.variance, torch.full_like(out.variance, 0.4))


@pytest.mark.parametrize("compiled", [True, False])
def test_depth_edge_stays_sharp_and_holes_stay_holes(monkeypatch, compiled):
    """Across a step larger than ``smooth`` every pixel keeps its own block's value (nothing in between is made
    up); an invalid block is invalid at full resolution and does not leak into its neighbours' blend."""
    monkeypatch.setattr(dispatch, "ENABLED", compiled)
    h, w = 6, 8
    values = torch.where(torch.arange(w).view(1, 1, 1, w) < 4, 10.0, 20.0).expand(1, 1, h, w).clone()
    valid = torch.ones(1, 1, h, w, dtype=torch.bool)
    valid[0, 0, 2, 6] = False
    out = _double(_half_map(h, w, values, valid), 2 * h, 2 * w, smooth=1.0, low=0.0, high=64.0)
    assert set(out.disparity[out.valid].unique().tolist()) == {20.0, 40.0}
    assert not bool(out.valid[0, 0, 4:6, 12:14].any())
    assert bool(out.valid.sum() == 4 * (h * w - 1))
    assert bool((out.variance[~out.valid] == INVALID_VARIANCE).all()) and bool((out.disparity[~out.valid] == 0).all())


def test_range_and_odd_sizes(monkeypatch):
    """Odd full-resolution sizes crop the last block; values outside [low, high) are not valid."""
    h, w = 5, 7
    values = torch.arange(h * w, dtype=torch.float32).view(1, 1, h, w)
    for compiled in (True, False):
        monkeypatch.setattr(dispatch, "ENABLED", compiled)
        out = _double(_half_map(h, w, values), 9, 13, smooth=0.0, low=4.0, high=30.0)
        assert out.disparity.shape == (1, 1, 9, 13)
        kept = out.disparity[out.valid]
        assert bool(((kept >= 4.0) & (kept < 30.0)).all())
        blocks = (2 * values >= 4.0) & (2 * values < 30.0)  # smooth 0 on a ramp of 1: no blend, each its block
        assert torch.equal(out.valid, blocks.repeat_interleave(2, -2).repeat_interleave(2, -1)[..., :9, :13])
        assert int(out.valid.sum()) == 48


def test_paths_agree(monkeypatch):
    """The numba kernels and the torch reference give the same maps (random blocks, holes, steps)."""
    g = torch.Generator().manual_seed(3)
    b, h, w = 2, 13, 18
    values = 20 * torch.rand(b, 1, h, w, generator=g)
    values = torch.where(torch.rand(b, 1, h, w, generator=g) < 0.5, values.round(), values)  # ties for smooth
    valid = torch.rand(b, 1, h, w, generator=g) > 0.2
    half = StereoOutput(torch.where(valid, values, 0.0), valid, torch.rand(b, 1, h, w, generator=g))
    compiled, reference = _paths(monkeypatch, _double, half, 2 * h - 1, 2 * w, 1.0, 1.0, 38.0)
    assert torch.equal(compiled.valid, reference.valid)
    torch.testing.assert_close(compiled.disparity, reference.disparity, rtol=0, atol=_TOL)
    torch.testing.assert_close(compiled.variance, reference.variance)
    image = torch.rand(b, 1, 2 * h - 1, 2 * w + 1, generator=g)
    small_c, small_r = _paths(monkeypatch, _halve, image)
    assert small_c.shape == (b, 1, h, w + 1)
    torch.testing.assert_close(small_c, small_r, rtol=0, atol=1e-6)
    torch.testing.assert_close(small_r[..., :-1, :-1], F.avg_pool2d(image[..., :-1, :-1], 2), rtol=0, atol=1e-6)


@pytest.mark.parametrize("compiled", [True, False])
def test_known_shift_matched_at_full_resolution(monkeypatch, compiled):
    """A pair shifted by a known whole number of px (even: the half-resolution images are shifted exactly) is
    matched to it, in full-resolution px, over nearly the whole image."""
    monkeypatch.setattr(dispatch, "ENABLED", compiled)
    g = torch.Generator().manual_seed(0)
    left = F.interpolate(torch.rand(1, 1, 40, 56, generator=g), scale_factor=2, mode="bilinear")
    right = torch.roll(left, -8, dims=-1)
    out = match_half_resolution(left, right, 24, cost="census", aggregation="sgm")
    inner = out.valid[..., 4:-4, 24:-4]
    assert float(inner.float().mean()) > 0.9
    err = (out.disparity[..., 4:-4, 24:-4][inner] - 8.0).abs()
    assert float(err.median()) < 0.1


def test_bad_input():
    left = torch.rand(1, 1, 16, 24)
    with pytest.raises(ValueRangeError, match="max_disparity"):
        match_half_resolution(left, left, 4, min_disparity=2)
    with pytest.raises(ValueRangeError, match="smooth"):
        match_half_resolution(left, left, 8, smooth=-1.0)
    with pytest.raises(ShapeError, match="right"):
        match_half_resolution(left, left[..., :20], 8)
