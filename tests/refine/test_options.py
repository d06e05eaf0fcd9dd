"""The refiner's grouped options: validation at construction, the flat keywords' deprecation path."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from egorefine.core import ValueRangeError
from egorefine.data import render_sequence
from egorefine.refine import (
    CorrectionOptions,
    EgoMotionRefiner,
    PredictionOptions,
    ScheduleOptions,
    SearchOptions,
    StereoOptions,
    TrackingOptions,
    refine_sequence,
)
from egorefine.refine.options import GROUPS, LEGACY_KEYWORDS


@pytest.mark.parametrize("cls, field, value", [
    (StereoOptions, "block_size", 8), (StereoOptions, "cost", "ssd"), (StereoOptions, "min_disparity", -1),
    (StereoOptions, "uniqueness_ratio", 1.0), (StereoOptions, "speckle_size", -5), (StereoOptions, "speckle_range", 0),
    (StereoOptions, "lr_threshold", 1.5),
    (TrackingOptions, "max_features", 0), (TrackingOptions, "min_tracks", -1),
    (PredictionOptions, "splat", "blob"), (PredictionOptions, "process_noise", -0.1),
    (CorrectionOptions, "gain", 0.0), (CorrectionOptions, "gain", 1.5), (CorrectionOptions, "kalman_gate", 0.0),
    (CorrectionOptions, "reset_after", 0), (CorrectionOptions, "edge_kernel", 2),
    (CorrectionOptions, "gate_softness", -1.0), (SearchOptions, "local_search", 1), (SearchOptions, "block", 4),
    (SearchOptions, "window", "round"), (SearchOptions, "max_hole_variance", 0.0),
    (ScheduleOptions, "min_coverage", -0.5),
])
def test_a_bad_field_fails_where_it_is_written(cls, field, value):
    with pytest.raises(ValueRangeError, match=field):
        cls(**{field: value})


def test_groups_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        TrackingOptions().max_features = 3


def test_every_legacy_keyword_names_a_field_of_its_group():
    for key, (group, field) in LEGACY_KEYWORDS.items():
        assert field in {f.name for f in dataclasses.fields(GROUPS[group])}, key


def test_flat_keywords_warn_and_give_the_grouped_refiner():
    with pytest.warns(DeprecationWarning, match=r"tracking=TrackingOptions\(max_features=\.\.\., min_tracks=\.\.\.\)"):
        old = EgoMotionRefiner(max_features=64, min_tracks=16, local_search=2, gain=0.3)
    new = EgoMotionRefiner(tracking=TrackingOptions(max_features=64, min_tracks=16),
                           search=SearchOptions(local_search=2), correction=CorrectionOptions(gain=0.3))
    for group in GROUPS:
        assert getattr(old, group) == getattr(new, group)
    assert old.tracking.max_features == 64 and old.search.local_search == 2 and old.gain == 0.3


def test_flat_keywords_apply_on_top_of_a_group_and_unknown_ones_fail():
    with pytest.warns(DeprecationWarning):
        r = EgoMotionRefiner(tracking=TrackingOptions(max_features=64), min_tracks=8)
    assert (r.tracking.max_features, r.tracking.min_tracks) == (64, 8)
    with pytest.raises(TypeError, match="max_feature"):
        EgoMotionRefiner(max_feature=64)
    with pytest.raises(ValueRangeError, match="tracking"):
        EgoMotionRefiner(tracking={"max_features": 64})


def test_old_and_new_forms_give_the_same_maps():
    seq = render_sequence(num_frames=3, height=48, width=64, seed=2)
    K, b = seq.K[None], torch.tensor([seq.baseline])
    with pytest.warns(DeprecationWarning):
        old = refine_sequence(seq.left, seq.right, K, b, verify_every=2, fusion="kalman", max_disparity=16,
                              max_features=64, min_tracks=16, process_noise=0.02)
    new = refine_sequence(seq.left, seq.right, K, b, verify_every=2, fusion="kalman", max_disparity=16,
                          tracking=TrackingOptions(max_features=64, min_tracks=16),
                          prediction=PredictionOptions(process_noise=0.02))
    assert torch.equal(old.valid, new.valid) and torch.equal(old.disparity, new.disparity)


def test_stereo_options_reach_the_verification_matcher():
    """The matcher settings of StereoOptions are the ones the refiner's frame-0 stereo uses."""
    from egorefine.stereo import match_stereo

    seq = render_sequence(num_frames=1, height=48, width=64, seed=2)
    K, b = seq.K[None], torch.tensor([seq.baseline])
    options = StereoOptions(cost="census", aggregation="sgm", block_size=5, uniqueness_ratio=0.0, speckle_size=20,
                            speckle_range=2.0, lr_threshold=2)
    out, _ = EgoMotionRefiner(max_disparity=16, stereo=options)(seq.left[:1], seq.right[:1], K, b)
    want = match_stereo(seq.left[:1], seq.right[:1], 16, **options.matcher_options())
    assert torch.equal(out.valid, want.valid)
    torch.testing.assert_close(out.disparity[want.valid], want.disparity[want.valid])
    default = match_stereo(seq.left[:1], seq.right[:1], 16, cost="census", aggregation="sgm", block_size=5)
    assert not torch.equal(default.valid, want.valid)  # the settings change the result, so the check can fail


def test_kalman_mode_fills_the_box_matchers_holes_from_sgm():
    """Kalman mode's default verification: the box matcher where it matched, census + SGM in its holes; paper mode,
    the differentiable preset and an SGM matcher do not fill."""
    from egorefine.stereo import match_stereo
    from egorefine.stereo.scale import match_half_resolution

    seq = render_sequence(num_frames=1, height=60, width=80, seed=2)
    K, b = seq.K[None], torch.tensor([seq.baseline])
    kalman = EgoMotionRefiner(max_disparity=16, fusion="kalman")
    assert kalman.stereo.fill is True
    assert EgoMotionRefiner(fusion="paper").stereo.fill is False
    assert EgoMotionRefiner(fusion="kalman", differentiable=True).stereo.fill is False
    assert EgoMotionRefiner(fusion="kalman", stereo=StereoOptions.dense()).stereo.fill is False
    assert EgoMotionRefiner(fusion="paper", stereo=StereoOptions(fill=True)).stereo.fill is True
    box = match_stereo(seq.left[:1], seq.right[:1], 16)
    dense = StereoOptions.dense().matcher_options()
    # the default fill matches at half resolution (fill_scale=2); fill_scale=1 at full resolution
    for scale, sgm in ((2, match_half_resolution(seq.left[:1], seq.right[:1], 16, **dense)),
                       (1, match_stereo(seq.left[:1], seq.right[:1], 16, **dense))):
        refiner = kalman if scale == 2 else EgoMotionRefiner(max_disparity=16, fusion="kalman",
                                                                   stereo=StereoOptions(fill_scale=1))
        out, _ = refiner(seq.left[:1], seq.right[:1], K, b)
        assert torch.equal(out.valid, box.valid | sgm.valid)
        assert (sgm.valid & ~box.valid).sum() > 0.1 * box.valid.sum()  # the fill adds pixels, so the check can fail
        torch.testing.assert_close(out.disparity[box.valid], box.disparity[box.valid])
        filled = sgm.valid & ~box.valid
        torch.testing.assert_close(out.disparity[filled], sgm.disparity[filled])
    with pytest.raises(ValueRangeError, match="fill"):
        StereoOptions(fill="yes")
    with pytest.raises(ValueRangeError, match="fill_scale"):
        StereoOptions(fill_scale=3)


def test_the_filled_loop_is_denser_than_its_box_matcher_and_stays_accurate():
    """On realistic imaging the filled Kalman loop marks far more pixels valid than the box-only one, at an error
    little above the box-only loop's. Bounds from what the two loops achieve on this seed: EPE at about 1.2 times
    each loop's, the filled loop's density a few points below its own and at least 20 points above the box-only
    loop's, its EPE at most 1.5 times the box-only loop's (about 1.15 times their measured ratio), and on every frame
    a median signed error (a bias of the whole map) within 0.05 px, half the smallest shift tools/mutants.py plants."""
    seq = render_sequence(num_frames=6, height=120, width=160, seed=3)
    K, b = seq.K[None], torch.tensor([seq.baseline])
    scores = {}
    for fill in (True, False):
        refiner = EgoMotionRefiner(max_disparity=24, verify_every=5, fusion="kalman", stereo=StereoOptions(fill=fill))
        state, err, n, known = None, 0.0, 0, 0
        for t in range(len(seq)):
            out, state = refiner(seq.left[t : t + 1], seq.right[t : t + 1], K, b, state)
            scored = ~seq.occluded[t : t + 1] & (seq.disparity[t : t + 1] > 0)
            m = out.valid & scored
            error = (out.disparity - seq.disparity[t : t + 1])[m]
            assert error.median().abs() < 0.05, (fill, t, float(error.median()))
            err += float(error.abs().sum())
            n, known = n + int(m.sum()), known + int(scored.sum())
        scores[fill] = (err / n, n / known)
    (epe, density), (box_epe, box_density) = scores[True], scores[False]
    assert density > 0.95 and density > box_density + 0.2, scores
    assert epe < 0.31 and box_epe < 0.24 and epe < 1.5 * box_epe, scores


def test_the_box_matchers_own_count_is_carried_only_with_a_fill():
    """With a fill the failure check compares the box matcher's count with its count at the last accepted
    verification (RefinerState.matched); without one it stays None and the prediction's validity is the reference."""
    from egorefine.stereo import match_stereo

    seq = render_sequence(num_frames=3, height=60, width=80, seed=2)
    K, b = seq.K[None], torch.tensor([seq.baseline])
    for fusion, filled in (("kalman", True), ("paper", False)):
        refiner = EgoMotionRefiner(max_disparity=16, verify_every=1, fusion=fusion)
        state = None
        for t in range(3):
            _, state = refiner(seq.left[t : t + 1], seq.right[t : t + 1], K, b, state)
        if filled:
            box = match_stereo(seq.left[2:3], seq.right[2:3], 16)
            assert state.matched.tolist() == [int(box.valid.sum())]
        else:
            assert state.matched is None


def test_the_fill_searches_up_to_the_predictions_largest_value_plus_its_margin(monkeypatch):
    """StereoOptions.fill_margin: the first frame's fill searches the full range; a later verification's only up to
    the prediction's largest value plus the margin, the candidate count rounded up to a multiple of 32; with
    ``fill_margin=None``, or a band fill, every fill searches the full range."""
    from egorefine.refine import refiner as refiner_module

    seq = render_sequence(num_frames=4, height=60, width=160, seed=4)
    K, b = seq.K[None], torch.tensor([seq.baseline])
    assert float(seq.disparity.amax()) + 8 + 1 < 64  # the cut range lies below max_disparity on this scene
    fill, predict = refiner_module._fill_matcher, refiner_module.predict_finished
    seen, largest = [], []

    def spy_fill(left, right, max_disparity, *args):
        seen.append(max_disparity)
        return fill(left, right, max_disparity, *args)

    def spy_predict(*args, **kwargs):
        pred = predict(*args, **kwargs)
        largest.append(float(pred.disparity.amax()))
        return pred

    monkeypatch.setattr(refiner_module, "_fill_matcher", spy_fill)
    monkeypatch.setattr(refiner_module, "predict_finished", spy_predict)
    for options, expect_cut in ((StereoOptions(), True), (StereoOptions(fill_margin=None), False),
                                (StereoOptions(fill_band=12), False)):
        seen.clear(), largest.clear()
        refiner = EgoMotionRefiner(max_disparity=96, verify_every=3, fusion="kalman", stereo=options)
        state = None
        for t in range(len(seq)):
            _, state = refiner(seq.left[t : t + 1], seq.right[t : t + 1], K, b, state)
        assert seen[0] == 96  # the first frame: no prediction
        later = seen[1:]
        assert len(later) == 1  # frame 3
        if expect_cut:
            need = int(torch.tensor(largest[-1]).ceil()) + 8 + 1
            assert later[0] == 32 * -(-need // 32) < 96
        else:
            assert later[0] == 96
    with pytest.raises(ValueRangeError, match="fill_margin"):
        StereoOptions(fill_margin=-1)


def test_a_surface_nearer_than_the_cut_range_is_still_measured_by_the_first_matcher():
    """With the fill's range cut by a prediction that knows nothing of a near surface, that surface keeps a
    full-range measurement: the box matcher searches the whole range at every verification, and the fill adds no
    value where the box matcher has one."""
    g = torch.Generator().manual_seed(0)
    right = torch.rand(1, 1, 48, 128, generator=g)
    true = 40  # a fronto-parallel surface at 40 px, beyond the cut range of a prediction of about 2 px
    left = torch.roll(right, true, dims=-1)
    refiner = EgoMotionRefiner(max_disparity=64, fusion="kalman")
    prior = torch.full((1, 1, 48, 128), 2.0)
    assert refiner._fill_range(prior, torch.tensor([True])) == 32
    out, matched = refiner._stereo(left, right, 5, prior=prior, prior_ok=torch.tensor([True]))
    inside = matched[..., :, true + 8 : -8]
    assert inside.float().mean() > 0.9
    # (the sub-pixel fit on white noise moves a value by up to ~0.13 px; the cut range ends 8 px below the truth)
    torch.testing.assert_close(out.disparity[..., :, true + 8 : -8][inside],
                               torch.full_like(out.disparity[..., :, true + 8 : -8][inside], float(true)),
                               atol=0.3, rtol=0)
