"""match_residual: the narrow search around a prior recovers the truth, rejects priors beyond its reach, the
fronto-parallel window reproduces the full matcher's decisions inside its band, and the compiled CPU path agrees
with the torch reference for both windows."""

from __future__ import annotations

import pytest
import torch

import egorefine.stereo.matching as matching
from egorefine.core import ShapeError, ValueRangeError, dispatch
from egorefine.stereo import _residual_numba, match_residual, match_stereo

from ._synthetic import planar_pair, visible


@pytest.fixture(scope="module")
def plane():
    # a slanted plane, disparity 6 .. ~10 px, exact truth
    return planar_pair(batch=2, height=64, width=128, seed=4, base=6.0, slope_x=0.02, slope_y=0.02)


def _smooth_error(shape, amplitude: float, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    noise = (torch.rand(shape, generator=gen) - 0.5) * 2 * amplitude
    return torch.nn.functional.avg_pool2d(noise, 7, 1, 3, count_include_pad=False)


# how far the prior may be off: the warped window searches prior + k, the fronto one round(prior) + k (half a
# pixel less reach); a winner at the band's end is rejected
REACH = {"warped": 1.2, "fronto": 0.5}


@pytest.mark.parametrize("window", ["fronto", "warped"])
@pytest.mark.parametrize("compiled", [True, False])
def test_recovers_truth_from_an_offset_prior(plane, compiled, window, monkeypatch):
    monkeypatch.setattr(dispatch, "ENABLED", compiled)
    left, right, truth = plane
    prior = truth + REACH[window] + _smooth_error(truth.shape, 0.4, 0)  # warped: 0.8 .. 1.6 px off; fronto 0.1 .. 0.9
    out = match_residual(left, right, prior, window=window)
    inner = visible(truth, 8)
    assert out.valid[inner].float().mean() > 0.9
    err = (out.disparity - truth).abs()[out.valid & inner]
    assert err.median() < 0.075 and err.max() < 0.5  # match_stereo on this plane: median 0.044
    assert (out.variance[out.valid] >= 1 / 12).all() and (out.variance[~out.valid] == 1e4).all()
    assert (out.disparity[~out.valid] == 0).all()


@pytest.mark.parametrize("window", ["fronto", "warped"])
def test_prior_beyond_the_radius_is_rejected(plane, window):
    left, right, truth = plane
    out = match_residual(left, right, truth + 3.0, radius=2, window=window)  # the truth lies outside prior +- 2
    assert out.valid.float().mean() < 0.02
    wide = match_residual(left, right, truth + 3.0, radius=4, window=window)
    inner = visible(truth, 8)
    assert wide.valid[inner].float().mean() > 0.9
    assert (wide.disparity - truth).abs()[wide.valid & inner].median() < 0.075


@pytest.mark.parametrize("window", ["fronto", "warped"])
def test_compiled_agrees_with_torch(plane, window, monkeypatch):
    left, right, truth = plane
    prior = truth + _smooth_error(truth.shape, 1.5, 1)
    prior_valid = torch.rand(truth.shape, generator=torch.Generator().manual_seed(2)) > 0.1
    for fit in ("equiangular", "parabola"):
        outs = []
        for compiled in (False, True):
            monkeypatch.setattr(dispatch, "ENABLED", compiled)
            outs.append(match_residual(left, right, prior, radius=3, block_size=7, prior_valid=prior_valid,
                                       subpixel_fit=fit, window=window))
        ref, fast = outs
        assert (ref.valid != fast.valid).float().mean() <= 1e-3
        both = ref.valid & fast.valid
        assert both.float().mean() > 0.5
        torch.testing.assert_close(fast.disparity[both], ref.disparity[both], atol=1e-3, rtol=0)
        torch.testing.assert_close(fast.variance[both], ref.variance[both], atol=0, rtol=1e-3)


@pytest.mark.parametrize("window", ["fronto", "warped"])
def test_compiled_output_does_not_depend_on_the_thread_count(window):
    # taller than one band of rows, so that bands restart their sliding column sums
    left, right, truth = planar_pair(batch=1, height=100, width=96, seed=5, base=6.0, slope_x=0.02, slope_y=0.01)
    prior = truth + _smooth_error(truth.shape, 1.0, 3)
    ok = torch.ones_like(prior, dtype=torch.bool)
    outs = [_residual_numba.match_residual(left, right, prior, ok, 2, 7, False, 0.15, 0.004, 0.01, 31.0 / 255.0,
                                           threads=t, window=window) for t in (1, 2, 3)]
    assert outs[0][1].float().mean() > 0.5
    for out in outs[1:]:
        for a, b in zip(outs[0], out, strict=True):
            assert torch.equal(a, b)


@pytest.mark.parametrize("window", ["fronto", "warped"])
@pytest.mark.parametrize("compiled", [True, False])
def test_masks_and_bad_priors_give_invalid_not_nan(plane, compiled, window, monkeypatch):
    monkeypatch.setattr(dispatch, "ENABLED", compiled)
    left, right, truth = plane
    prior = truth.clone()
    prior[0, 0, 30, 60] = float("nan")
    prior[1, 0, 20, 40] = float("inf")
    prior[1, 0, 50, 20] = 1e12  # far outside the image: no integer overflow, not valid
    keep = torch.ones_like(truth, dtype=torch.bool)
    keep[:, :, 10:20, 50:70] = False
    out = match_residual(left, right, prior, prior_valid=keep, window=window)
    assert torch.isfinite(out.disparity).all() and torch.isfinite(out.variance).all()
    assert not out.valid[0, 0, 30, 60] and not out.valid[1, 0, 20, 40] and not out.valid[1, 0, 50, 20]
    assert not out.valid[:, :, 10:20, 50:70].any()
    assert out.valid[:, :, 40:50, 50:70].all()  # the unmasked plane next to it still matches


@pytest.mark.parametrize("window", ["fronto", "warped"])
def test_textureless_pair_is_invalid(window):
    flat = torch.full((1, 1, 32, 48), 0.5)
    out = match_residual(flat, flat, torch.full_like(flat, 4.0), window=window)
    assert not out.valid.any()


def test_fronto_window_makes_the_full_matchers_decisions_inside_its_band(monkeypatch):
    """Where the full-range matcher's winner lies inside ``round(prior) +- (radius - 1)``, it is also the band's
    winner, with the same neighbours: the fronto-parallel search returns the full matcher's value and variance
    (float64, the matcher's float path; its uniqueness and left-right checks only remove pixels)."""
    monkeypatch.setattr(matching, "_INTEGER_PATH", False)  # float costs, as the residual search's
    left, right, truth = planar_pair(batch=1, height=64, width=128, seed=6, base=9.0, slope_x=0.03, slope_y=-0.02)
    left, right = left.double(), right.double()
    prior = truth.double() + _smooth_error(truth.shape, 2.0, 4).double()  # up to 0.74 px off
    prior[..., :32, :] += 3.0  # and beyond reach in the top half
    full = match_stereo(left, right, 24, block_size=9)
    band = match_residual(left, right, prior, radius=2, block_size=9, window="fronto")
    inner = torch.zeros_like(full.valid)
    inner[..., 4:-4, 4 + 24:-4] = True  # the full matcher's window inside both images at every candidate
    offset = full.disparity - prior.round()
    inside = full.valid & inner & (offset.abs() <= 0.5)  # the integer winner within round(prior) +- 1
    assert inside.float().mean() > 0.2  # of the whole image: most of the bottom half
    assert band.valid[inside].all()
    torch.testing.assert_close(band.disparity[inside], full.disparity[inside], atol=1e-9, rtol=0)
    torch.testing.assert_close(band.variance[inside], full.variance[inside], atol=0, rtol=1e-9)
    # where the winner lies beyond the band, the band's best candidate is mostly at its end: rejected (a local
    # minimum inside the band survives the checks on about 1 % here)
    beyond = full.valid & inner & (offset.abs() >= 2.5)
    assert beyond.float().mean() > 0.2 and band.valid[beyond].float().mean() < 0.03


def test_bad_input():
    img = torch.rand(1, 1, 32, 48)
    with pytest.raises(ValueRangeError, match="radius"):
        match_residual(img, img, torch.zeros_like(img), radius=1)
    with pytest.raises(ValueRangeError, match="block_size"):
        match_residual(img, img, torch.zeros_like(img), block_size=4)
    with pytest.raises(ShapeError, match="prior"):
        match_residual(img, img, torch.zeros(1, 1, 32, 40))
    with pytest.raises(ValueRangeError, match="window"):
        match_residual(img, img, torch.zeros_like(img), window="slanted")


@pytest.mark.parametrize("window", ["fronto", "warped"])
def test_gradcheck(window):
    """The value and the variance are differentiable in both images (float64, torch path)."""
    left, right, truth = planar_pair(batch=1, height=12, width=24, seed=7, base=4.0, slope_x=0.02, slope_y=0.0)
    left, right = left.double().requires_grad_(), right.double().requires_grad_()
    prior = truth.double() + 0.3

    def fn(a, b):
        out = match_residual(a, b, prior, radius=2, block_size=5, window=window)
        return out.disparity, torch.where(out.valid, out.variance, torch.zeros_like(out.variance))

    assert match_residual(left, right, prior, radius=2, block_size=5, window=window).valid.sum() > 20
    assert torch.autograd.gradcheck(fn, (left, right), eps=1e-6, atol=1e-5)
