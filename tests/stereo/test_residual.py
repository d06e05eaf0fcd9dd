"""match_residual: the narrow search around a prior recovers the truth, rejects priors beyond its reach, and the
compiled CPU path agrees with the torch reference."""

from __future__ import annotations

import pytest
import torch

import egorefine.stereo.residual as residual
from egorefine.core import ShapeError, ValueRangeError
from egorefine.stereo import _residual_numba, match_residual

from ._synthetic import planar_pair, visible


@pytest.fixture(scope="module")
def plane():
    # a slanted plane, disparity 6 .. ~10 px, exact truth
    return planar_pair(batch=2, height=64, width=128, seed=4, base=6.0, slope_x=0.02, slope_y=0.02)


def _smooth_error(shape, amplitude: float, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    noise = (torch.rand(shape, generator=gen) - 0.5) * 2 * amplitude
    return torch.nn.functional.avg_pool2d(noise, 7, 1, 3, count_include_pad=False)


@pytest.mark.parametrize("compiled", [True, False])
def test_recovers_truth_from_an_offset_prior(plane, compiled, monkeypatch):
    monkeypatch.setattr(residual, "_COMPILED", compiled)
    left, right, truth = plane
    prior = truth + 1.2 + _smooth_error(truth.shape, 0.5, 0)  # off by 0.7 .. 1.7 px
    out = match_residual(left, right, prior)
    inner = visible(truth, 8)
    assert out.valid[inner].float().mean() > 0.9
    err = (out.disparity - truth).abs()[out.valid & inner]
    assert err.median() < 0.075 and err.max() < 0.5  # match_stereo on this plane: median 0.044
    assert (out.variance[out.valid] >= 1 / 12).all() and (out.variance[~out.valid] == 1e4).all()
    assert (out.disparity[~out.valid] == 0).all()


def test_prior_beyond_the_radius_is_rejected(plane):
    left, right, truth = plane
    out = match_residual(left, right, truth + 3.0, radius=2)  # the truth lies outside prior +- 2
    assert out.valid.float().mean() < 0.02
    wide = match_residual(left, right, truth + 3.0, radius=4)
    inner = visible(truth, 8)
    assert wide.valid[inner].float().mean() > 0.9
    assert (wide.disparity - truth).abs()[wide.valid & inner].median() < 0.075


def test_compiled_agrees_with_torch(plane, monkeypatch):
    left, right, truth = plane
    prior = truth + _smooth_error(truth.shape, 1.5, 1)
    prior_valid = torch.rand(truth.shape, generator=torch.Generator().manual_seed(2)) > 0.1
    for fit in ("equiangular", "parabola"):
        outs = []
        for compiled in (False, True):
            monkeypatch.setattr(residual, "_COMPILED", compiled)
            outs.append(match_residual(left, right, prior, radius=3, block_size=7, prior_valid=prior_valid,
                                       subpixel_fit=fit))
        ref, fast = outs
        assert (ref.valid != fast.valid).float().mean() <= 1e-3
        both = ref.valid & fast.valid
        assert both.float().mean() > 0.5
        torch.testing.assert_close(fast.disparity[both], ref.disparity[both], atol=1e-3, rtol=0)
        torch.testing.assert_close(fast.variance[both], ref.variance[both], atol=0, rtol=1e-3)


def test_compiled_output_does_not_depend_on_the_thread_count():
    # taller than one band of rows, so that bands restart their sliding column sums
    left, right, truth = planar_pair(batch=1, height=100, width=96, seed=5, base=6.0, slope_x=0.02, slope_y=0.01)
    prior = truth + _smooth_error(truth.shape, 1.0, 3)
    ok = torch.ones_like(prior, dtype=torch.bool)
    outs = [_residual_numba.match_residual(left, right, prior, ok, 2, 7, False, 0.15, 0.004, 0.01, 31.0 / 255.0,
                                           threads=t) for t in (1, 2, 3)]
    assert outs[0][1].float().mean() > 0.5
    for out in outs[1:]:
        for a, b in zip(outs[0], out, strict=True):
            assert torch.equal(a, b)


@pytest.mark.parametrize("compiled", [True, False])
def test_masks_and_bad_priors_give_invalid_not_nan(plane, compiled, monkeypatch):
    monkeypatch.setattr(residual, "_COMPILED", compiled)
    left, right, truth = plane
    prior = truth.clone()
    prior[0, 0, 30, 60] = float("nan")
    prior[1, 0, 20, 40] = float("inf")
    keep = torch.ones_like(truth, dtype=torch.bool)
    keep[:, :, 10:20, 50:70] = False
    out = match_residual(left, right, prior, prior_valid=keep)
    assert torch.isfinite(out.disparity).all() and torch.isfinite(out.variance).all()
    assert not out.valid[0, 0, 30, 60] and not out.valid[1, 0, 20, 40]
    assert not out.valid[:, :, 10:20, 50:70].any()
    assert out.valid[:, :, 40:50, 50:70].all()  # the unmasked plane next to it still matches


def test_textureless_pair_is_invalid():
    flat = torch.full((1, 1, 32, 48), 0.5)
    out = match_residual(flat, flat, torch.full_like(flat, 4.0))
    assert not out.valid.any()


def test_bad_input():
    img = torch.rand(1, 1, 32, 48)
    with pytest.raises(ValueRangeError, match="radius"):
        match_residual(img, img, torch.zeros_like(img), radius=1)
    with pytest.raises(ValueRangeError, match="block_size"):
        match_residual(img, img, torch.zeros_like(img), block_size=4)
    with pytest.raises(ShapeError, match="prior"):
        match_residual(img, img, torch.zeros(1, 1, 32, 40))
