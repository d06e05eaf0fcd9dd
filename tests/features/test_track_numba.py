"""Tests of egorefine.features._track_numba: the compiled track against the torch path (the reference)."""

from __future__ import annotations

import pytest
import torch

import egorefine.features.tracking as tracking
from egorefine.core import dispatch
from egorefine.data import render_sequence
from egorefine.features import _track_numba, build_pyramid, detect, track

needs_numba = pytest.mark.skipif(not _track_numba.AVAILABLE, reason="numba not installed")

# Agreement bounds. Positions repeat the torch path's float32 steps, window sums are added in float64 instead of
# the convolutions' float32 order: measured over the refiner's 20-frame loops on both rigs (~13,000 live
# features), live positions differed by <= 3.7e-4 px, scores by <= 2.2e-4 and fb errors by <= 1.3e-4, with no
# weight differing.
_POS = 2e-3
_VAL = 1e-3
# the refiner's settings (egorefine.refine.refiner, step 1)
_REFINER = {"levels": 3, "fb_predicted": False, "fb_levels": 1}


@pytest.fixture(scope="module")
def frames():
    """Three rendered 640x480 frames (grey), 300 keypoints of frame 0 and a constant-velocity prediction for 1->2."""
    seq = render_sequence(num_frames=3, preset="paper", scene="corridor", motion="forward", seed=0)
    grey = seq.left.mean(dim=1, keepdim=True) if seq.left.shape[1] == 3 else seq.left
    kp, w = detect(grey[0:1], max_features=300)
    with torch.no_grad():
        first = track(grey[0:1], grey[1:2], kp, w)
    ok = first.weights > 0
    kp1 = first.keypoints
    predicted = torch.where(ok.unsqueeze(-1), 2 * kp1 - kp, kp1)
    return grey, kp, w, kp1, first.weights, predicted


def _both(*args, **kw):
    """(torch path, compiled path) outputs of ``track(*args, **kw)`` without gradient."""
    outs = []
    for flag in (False, True):
        dispatch.ENABLED = flag
        try:
            with torch.no_grad():
                outs.append(track(*args, **kw))
        finally:
            dispatch.ENABLED = True
    return outs


def _agree(ref, new, weights):
    live = weights > 0
    assert new.keypoints.dtype == ref.keypoints.dtype and new.weights.dtype == ref.weights.dtype
    assert float((ref.keypoints - new.keypoints).abs().amax(dim=-1)[live].max()) <= _POS
    assert torch.equal(ref.weights, new.weights)
    assert float((ref.score - new.score).abs().max()) <= _VAL
    assert float((ref.fb_error - new.fb_error).abs().max()) <= _VAL
    # empty slots: unchanged keypoints, zero weight / score / fb_error in both
    assert torch.equal(new.keypoints[~live], ref.keypoints[~live])
    assert (new.score[~live] == 0).all() and (new.fb_error[~live] == 0).all()
    # the comparison means something: most features tracked, some rejected
    assert 0.5 * live.sum() < (new.weights > 0).sum() < live.sum()


@needs_numba
@pytest.mark.parametrize("settings", [_REFINER, {}], ids=["refiner", "defaults"])
def test_compiled_matches_torch_without_prediction(frames, settings):
    grey, kp, w = frames[:3]
    ref, new = _both(grey[0:1], grey[1:2], kp, w, **settings)
    _agree(ref, new, w)


@needs_numba
@pytest.mark.parametrize("settings", [_REFINER, {}], ids=["refiner", "defaults"])
def test_compiled_matches_torch_with_prediction_and_pyramids(frames, settings):
    grey, _, _, kp1, w1, predicted = frames
    pyramids = {"prev_pyramid": build_pyramid(grey[1:2], 3), "next_pyramid": build_pyramid(grey[2:3], 3)}
    ref, new = _both(grey[1:2], grey[2:3], kp1, w1, predicted=predicted, **pyramids, **settings)
    _agree(ref, new, w1)
    # a prediction 3 px off sends features to the full search (and, by default, both ways back)
    ref, new = _both(grey[1:2], grey[2:3], kp1, w1, predicted=predicted + 3.0, **settings)
    _agree(ref, new, w1)


@needs_numba
@pytest.mark.parametrize(
    "settings",
    [
        {"patch_size": 7, "search_radius": 4, "refine_radius": 1, "levels": 2, "lk_iters": 0, "min_score": None},
        {"patch_size": 11, "levels": 1, "search_radius": 9, "lk_iters": 3, "fb_check": False},
        {"predicted_radius": None, "fb_levels": 2, "fb_threshold": 0.3, "min_texture": 0.05},
    ],
)
def test_compiled_matches_torch_other_settings(frames, settings):
    grey, _, _, kp1, w1, predicted = frames
    ref, new = _both(grey[1:2], grey[2:3], kp1[:, :96], w1[:, :96], predicted=predicted[:, :96], **settings)
    _agree(ref, new, w1[:, :96])


@needs_numba
def test_thread_count_does_not_change_the_result(frames):
    grey, _, _, kp1, w1, predicted = frames
    pyr = (build_pyramid(grey[1:2], 3), build_pyramid(grey[2:3], 3))
    args = (*pyr, kp1, w1, predicted, int((w1 > 0).sum()), 9, 6, 2, True, 1.0, 0.7, 0.01, 1, 2, True, 3)
    one, two = _track_numba.track_compiled(*args, threads=1), _track_numba.track_compiled(*args, threads=2)
    for a, b in zip(one, two, strict=True):
        assert torch.equal(a, b)


@needs_numba
def test_batch_items_and_empty_slots(frames):
    grey, kp, w, kp1, w1, predicted = frames
    # two pairs in a batch, the second with every third slot emptied and one negative weight
    w2 = w1.clone()
    w2[:, ::3] = 0
    w2[0, 1] = -1.0
    prev, nxt = torch.cat([grey[0:1], grey[1:2]]), torch.cat([grey[1:2], grey[2:3]])
    kps, ws = torch.cat([kp, kp1]), torch.cat([w, w2])
    pred = torch.cat([kp, predicted])
    ref, new = _both(prev, nxt, kps, ws, predicted=pred, **_REFINER)
    _agree(ref, new, ws)
    assert new.weights[1, 1] == 0 and new.weights[1, 0] == 0
    # Item b of the batch == the same item alone, for the accepted features. (A rejected feature's estimate may
    # differ, in the torch path as well: whether its coarse level takes window sums from box maps depends on the
    # batch's largest feature count, and those sums differ from the window's own where the window's centre lies
    # outside the image.)
    for b in range(2):
        one = track(prev[b:b + 1], nxt[b:b + 1], kps[b:b + 1], ws[b:b + 1], predicted=pred[b:b + 1], **_REFINER)
        assert torch.equal(one.weights, new.weights[b:b + 1])
        kept = one.weights[0] > 0
        assert float((one.keypoints[0] - new.keypoints[b]).abs()[kept].max()) <= _POS


@needs_numba
def test_dispatch_condition(frames, monkeypatch):
    grey, kp, w = frames[:3]
    calls = []
    real = _track_numba.track_compiled
    monkeypatch.setattr(_track_numba, "track_compiled", lambda *a, **k: calls.append(1) or real(*a, **k))
    prev, nxt, kp8, w8 = grey[0:1], grey[1:2], kp[:, :8], w[:, :8]
    with torch.no_grad():
        track(prev, nxt, kp8, w8)
        assert len(calls) == 1
        for kw in ({"soft": True}, {"cost": "ssd"}, {"cost": "sad"}):
            track(prev, nxt, kp8, w8, **kw)
        track(prev.double(), nxt.double(), kp8, w8)
    track(prev, nxt, kp8.clone().requires_grad_(), w8)  # a gradient is wanted
    monkeypatch.setattr(dispatch, "ENABLED", False)
    with torch.no_grad():
        track(prev, nxt, kp8, w8)
    assert len(calls) == 1
    # the compiled path's copy of the torch path's subset padding
    assert _track_numba._SLOT_STEP == tracking._SLOT_STEP


@pytest.mark.parametrize("shape", [(2, 1, 37, 50), (1, 1, 1, 4), (1, 1, 5, 1), (1, 1, 1, 1)])
def test_compiled_pyramid_equals_torch_path(shape, monkeypatch):
    image = torch.rand(shape, generator=torch.Generator().manual_seed(1))
    fast = build_pyramid(image, 4)
    monkeypatch.setattr(dispatch, "ENABLED", False)
    reference = build_pyramid(image, 4)
    assert [p.shape for p in fast] == [p.shape for p in reference]
    for a, b in zip(fast, reference, strict=True):
        assert torch.equal(a, b)  # the same float32 operations in the same order
