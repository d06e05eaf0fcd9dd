"""EgoMotionRefiner and refine_sequence: the API contract, bad input and accuracy against truth."""

from __future__ import annotations

import pytest
import torch

import egorefine
from egorefine.core import StateError, ValueRangeError
from egorefine.data import render_sequence
from egorefine.metrics import rotation_error_deg, translation_error
from egorefine.refine import EgoMotionRefiner, RefinerState, refine_sequence

SMALL = dict(max_disparity=24, max_features=150, min_tracks=60)


@pytest.fixture(scope="module")
def small_seq():
    return render_sequence(num_frames=7, height=120, width=160, seed=3)


def _run(seq, refiner, frames=None, batch=1):
    K = seq.K[None].expand(batch, 3, 3)
    b = torch.full((batch,), seq.baseline)
    state, outs = None, []
    for t in range(frames or len(seq.left)):
        left = seq.left[t : t + 1].expand(batch, -1, -1, -1)
        right = seq.right[t : t + 1].expand(batch, -1, -1, -1)
        out, state = refiner(left, right, K, b, state)
        outs.append(out)
    return outs, state


def test_api_contract_and_schedule(small_seq):
    outs, state = _run(small_seq, EgoMotionRefiner(verify_every=3, **SMALL))
    assert [o.stereo_ran for o in outs] == [True, False, False, True, False, False, True]
    first = outs[0]
    assert first.disparity.shape == (1, 1, 120, 160) and first.valid.dtype == torch.bool
    torch.testing.assert_close(first.motion, torch.eye(4)[None])
    assert isinstance(state, RefinerState) and state.frame == 6 and state.since_stereo == 0
    for o in outs:
        assert torch.isfinite(o.disparity).all() and torch.isfinite(o.variance).all()
        assert o.motion.shape == (1, 4, 4) and o.motion_ok.all()


def test_motion_follows_the_rig(small_seq):
    outs, _ = _run(small_seq, EgoMotionRefiner(verify_every=3, **SMALL))
    motion = torch.cat([o.motion for o in outs[1:]])
    gt = small_seq.motions[1:]
    # Between 0.1 m steps, a 160x120 image with a 20 px focal-to-width ratio scaled down 4x still pins the
    # motion to a few percent: bound the translation error at 15 % of the step, rotation at 0.2 degrees.
    step = gt[:, :3, 3].norm(dim=-1)
    assert (translation_error(motion, gt) < 0.15 * step).all()
    assert (rotation_error_deg(motion, gt) < 0.2).all()


def test_batch_items_are_independent(small_seq):
    refiner = EgoMotionRefiner(verify_every=3, **SMALL)
    single, _ = _run(small_seq, refiner, frames=4)
    double, _ = _run(small_seq, refiner, frames=4, batch=2)
    for s, d in zip(single, double, strict=True):
        # Batched matrix products sum in another order: agreement to 1e-3 px, not bit for bit.
        torch.testing.assert_close(d.disparity[1:], s.disparity, atol=1e-3, rtol=0)
        torch.testing.assert_close(d.motion[1:], s.motion, atol=1e-5, rtol=0)


def test_refine_sequence_matches_loop(small_seq):
    res = refine_sequence(small_seq.left[:4], small_seq.right[:4], small_seq.K, small_seq.baseline,
                          verify_every=3, **SMALL)
    outs, _ = _run(small_seq, EgoMotionRefiner(verify_every=3, **SMALL), frames=4)
    assert res.disparity.shape == (4, 1, 1, 120, 160) and res.motion.shape == (4, 1, 4, 4)
    assert res.stereo_ran.tolist() == [True, False, False, True]
    torch.testing.assert_close(res.disparity[-1], outs[-1].disparity)


def test_right_is_only_needed_on_verification_frames(small_seq):
    refiner = EgoMotionRefiner(verify_every=3, **SMALL)
    K, b = small_seq.K[None], torch.tensor([small_seq.baseline])
    out, state = refiner(small_seq.left[:1], small_seq.right[:1], K, b)
    out, state = refiner(small_seq.left[1:2], None, K, b, state)
    assert not out.stereo_ran
    out, state = refiner(small_seq.left[2:3], None, K, b, state)
    with pytest.raises(ValueRangeError, match="right: frame 3 needs stereo"):
        refiner(small_seq.left[3:4], None, K, b, state)


def test_bad_state_and_inputs(small_seq):
    refiner = EgoMotionRefiner(verify_every=3, **SMALL)
    K, b = small_seq.K[None], torch.tensor([small_seq.baseline])
    _, state = refiner(small_seq.left[:1], small_seq.right[:1], K, b)
    smaller = torch.nn.functional.interpolate(small_seq.left[1:2], size=(60, 80))
    with pytest.raises(StateError, match="frames may not change size"):
        refiner(smaller, smaller, K, b, state)
    with pytest.raises(StateError, match="batch size"):
        refiner(small_seq.left[1:3], small_seq.right[1:3], K.expand(2, 3, 3), b.expand(2), state)
    with pytest.raises(StateError, match="frames may not change device"):
        refiner(small_seq.left[1:2], None, K, b, state._replace(image=state.image.to("meta")))
    with pytest.raises(ValueRangeError, match="baseline"):
        refiner(small_seq.left[1:2], None, K, -b, state)
    with pytest.raises(ValueRangeError, match="fusion"):
        EgoMotionRefiner(fusion="median")
    with pytest.raises(ValueRangeError, match="verify_every"):
        EgoMotionRefiner(verify_every=0)


def test_black_frame_falls_back_to_stereo_without_nan(small_seq):
    refiner = EgoMotionRefiner(verify_every=10, **SMALL)
    K, b = small_seq.K[None], torch.tensor([small_seq.baseline])
    _, state = refiner(small_seq.left[:1], small_seq.right[:1], K, b)
    black = torch.zeros_like(small_seq.left[1:2])
    out, state = refiner(black, black, K, b, state)
    assert out.stereo_ran and not out.motion_ok.any()
    torch.testing.assert_close(out.motion, torch.eye(4)[None])
    assert torch.isfinite(out.disparity).all() and not out.valid.any()
    out, state = refiner(small_seq.left[2:3], small_seq.right[2:3], K, b, state)
    assert torch.isfinite(out.disparity).all()


def test_top_level_api_names():
    assert egorefine.EgoMotionRefiner is EgoMotionRefiner and egorefine.refine_sequence is refine_sequence


def test_adaptive_schedule_runs_stereo_when_coverage_drops():
    # Sideways motion brings new columns into view: the prediction for frame 1 covers ~95.6 % of the
    # image (frame 0's stereo covered ~96.8 %), so a 96 % coverage threshold must call stereo, 90 % must not.
    seq = render_sequence(num_frames=2, height=120, width=160, motion="lateral", seed=3)
    fixed, _ = _run(seq, EgoMotionRefiner(verify_every=100, **SMALL))
    strict, _ = _run(seq, EgoMotionRefiner(verify_every=100, adaptive=True, min_coverage=0.96, **SMALL))
    lenient, _ = _run(seq, EgoMotionRefiner(verify_every=100, adaptive=True, min_coverage=0.9, min_confidence=0.0,
                                            **SMALL))
    assert [o.stereo_ran for o in fixed] == [True, False]
    assert [o.stereo_ran for o in strict] == [True, True]
    assert [o.stereo_ran for o in lenient] == [True, False]
