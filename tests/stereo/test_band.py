"""match_sgm_band: the compiled kernel equals the torch reference, a band around a good prior measures as well as
the full census + SGM matcher, the band's edge is rejected, bad priors raise, a band as wide as the range is the full
matcher without its left-right check, and the refiner fills around its prediction after the first frame."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from egorefine.core import ShapeError, ValueRangeError, dispatch
from egorefine.data import render_sequence
from egorefine.refine import EgoMotionRefiner, StereoOptions, TrackingOptions
from egorefine.refine import refiner as refiner_module
from egorefine.stereo import match_stereo
from egorefine.stereo.band import band_start, match_sgm_band

from ._synthetic import planar_pair

# the full matcher of StereoOptions.dense() without its left-right check
DENSE = StereoOptions.dense().matcher_options()


@pytest.fixture(scope="module")
def frame():
    seq = render_sequence(num_frames=1, preset="paper", scene="hall", height=120, width=160, seed=3)
    return seq.left[:1], seq.right[:1], seq.disparity[:1]


def _wild_prior(truth: torch.Tensor, seed: int) -> torch.Tensor:
    """The truth plus blocks offset by up to +-20 px and 3 px noise: bands that jump between neighbours (depth
    edges, shifts beyond the kernel's margin), bands at both ends of the range, and priors far off."""
    gen = torch.Generator().manual_seed(seed)
    blocks = (torch.rand(1, 1, 6, 8, generator=gen) * 40 - 12).round()
    blocks = F.interpolate(blocks, size=truth.shape[-2:], mode="nearest")
    return truth + blocks + 3 * torch.randn(truth.shape, generator=gen)


def _both_paths(monkeypatch, *args, **kwargs):
    monkeypatch.setattr(dispatch, "ENABLED", True)
    compiled = match_sgm_band(*args, **kwargs)
    monkeypatch.setattr(dispatch, "ENABLED", False)
    reference = match_sgm_band(*args, **kwargs)
    return compiled, reference


@pytest.mark.parametrize("options", [
    {"width": 16},
    {"width": 8, "min_disparity": 2, "sgm_paths": 8},
    {"width": 5, "sgm_p1": 0.3, "sgm_p2": 1.1},  # penalties that are not integers: float32 path costs
    {"width": 16, "block_size": 7, "census_window": 5, "subpixel_fit": "parabola"},
])
def test_compiled_equals_reference(frame, options, monkeypatch):
    # Exact, on any CPU: census window sums are integers; with integer penalties every path cost and sum is an
    # integer below 2**24, exact in the reference's float32 and in the kernel's int32; with others the kernel does
    # the reference's float32 operations (+, -, min, /: each correctly rounded) in its order. The selection then
    # reads the same float32 costs.
    left, right, truth = frame
    compiled, reference = _both_paths(monkeypatch, left, right, _wild_prior(truth, 1), 40, **options)
    assert 0.1 < compiled.valid.float().mean() < 0.99  # both kinds of pixel present
    assert torch.equal(compiled.valid, reference.valid)
    assert torch.equal(compiled.disparity, reference.disparity)
    assert torch.equal(compiled.variance, reference.variance)


@pytest.mark.parametrize("compiled", [True, False])
def test_width_of_the_range_is_the_full_matcher(frame, compiled, monkeypatch):
    monkeypatch.setattr(dispatch, "ENABLED", compiled)
    left, right, truth = frame
    band = match_sgm_band(left, right, _wild_prior(truth, 2), 24, width=24)  # the prior does not matter
    full = match_stereo(left, right, 24, **{**DENSE, "lr_check": False})
    for a, b in zip(band, full, strict=True):
        assert torch.equal(a, b)


def test_band_around_a_noisy_prior_measures_like_the_full_matcher():
    seq = render_sequence(num_frames=1, preset="paper", scene="hall", height=240, width=320, seed=5)
    left, right, truth = seq.left[:1], seq.right[:1], seq.disparity[:1]
    mask = (truth > 0) & ~seq.occluded[:1]
    prior = truth + 2.0 * torch.randn(truth.shape, generator=torch.Generator().manual_seed(0))

    def epe_density(out):
        v = out.valid & mask
        return float((out.disparity - truth).abs()[v].mean()), float(v.sum() / mask.sum())

    full = epe_density(match_stereo(left, right, 32, **DENSE))
    band = epe_density(match_sgm_band(left, right, prior, 32, width=16))
    # measured: full EPE ~0.49 at density ~0.96 (its left-right check removes some), band ~0.40 at ~0.99. Margins
    # of 0.05 px and 0.02: a change of the cost, the paths or the selection moves these by more
    assert band[0] < full[0] + 0.05
    assert band[1] > full[1] - 0.02


def test_band_edge_is_rejected():
    left, right, truth = planar_pair(batch=1, height=64, width=128, seed=4, base=6.0, slope_x=0.02, slope_y=0.02)
    width = 16
    centred = match_sgm_band(left, right, truth + 0.3, 40, width=width)
    assert centred.valid.float().mean() > 0.9
    # the truth one or two px below the band: its cheapest candidate is the band's lowest, rejected everywhere
    prior = truth + width // 2 + 1
    out = match_sgm_band(left, right, prior, 40, width=width)
    assert not bool(out.valid.any())
    # wherever a winner is valid it is inside its band, never on an edge that is not the range's limit
    wild = _wild_prior(truth, 3)
    out = match_sgm_band(left, right, wild, 40, width=width, speckle_size=0)
    lo = band_start(wild, 40, 0, width)
    d, v = out.disparity, out.valid
    assert v.float().mean() > 0.1
    # integer winner in lo + 1 .. lo + width - 2 (or lo = 0, the range's end), then a sub-pixel offset of <= 0.5 px
    assert not bool((v & (d < lo + 0.5) & (lo > 0)).any())
    assert not bool((v & (d > lo + width - 1.5)).any())


def test_band_start():
    prior = torch.tensor([[[[-3.0, 0.4, 7.5, 8.5, 30.0, 1e9]]]])
    # round half to even: 7.5 -> 8, 8.5 -> 8; lo = round - 7, clamped to [0, 32 - 16]
    assert band_start(prior, 32, 0, 16).flatten().tolist() == [0, 0, 1, 1, 16, 16]
    assert band_start(prior, 32, 2, 64).flatten().tolist() == [2] * 6  # the range is narrower than the band


def test_bad_prior_raises(frame):
    left, right, truth = frame
    with pytest.raises(ShapeError, match="prior"):
        match_sgm_band(left, right, truth[..., :-1], 32)
    nan = truth.clone()
    nan[0, 0, 5, 5] = float("nan")
    with pytest.raises(ValueRangeError, match="prior"):
        match_sgm_band(left, right, nan, 32)
    with pytest.raises(ValueRangeError, match="width"):
        match_sgm_band(left, right, truth, 32, width=2)
    with pytest.raises(ValueRangeError, match="max_disparity"):
        match_sgm_band(left, right, truth, 0)


def test_refiner_fills_around_the_prediction_after_the_first_frame(monkeypatch):
    seq = render_sequence(num_frames=5, height=60, width=80)
    calls = []
    band = refiner_module.match_sgm_band

    def counting(*args, **kwargs):
        calls.append(kwargs["width"])
        return band(*args, **kwargs)

    monkeypatch.setattr(refiner_module, "match_sgm_band", counting)
    K, b = seq.K[None], torch.tensor([seq.baseline])
    tracking = TrackingOptions(max_features=64, min_tracks=16)
    outputs = {}
    for fill_band in (12, None):
        refiner = EgoMotionRefiner(max_disparity=16, verify_every=2, fusion="kalman", tracking=tracking,
                                   stereo=StereoOptions(fill_band=fill_band))
        state = None
        for t in range(5):
            out, state = refiner(seq.left[t:t + 1], seq.right[t:t + 1], K, b, state)
        outputs[fill_band] = out
    assert calls == [12, 12]  # frames 2 and 4; frame 0 and the run without a band: the full range
    assert outputs[12].valid.float().mean() > 0.8 * outputs[None].valid.float().mean()
    with pytest.raises(ValueRangeError, match="fill_band"):
        StereoOptions(fill_band=2)
