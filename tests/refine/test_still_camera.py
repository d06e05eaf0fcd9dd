"""A rendered, nearly still camera with truth: the refined map's error must not accumulate (no drift)."""

from __future__ import annotations

import pytest
import torch

from egorefine.data import render_sequence
from egorefine.refine import EgoMotionRefiner
from egorefine.stereo import match_stereo

FRAMES = 60


@pytest.fixture(scope="module")
def still():
    return render_sequence(num_frames=FRAMES, preset="paper", motion="still", seed=21, height=60, width=80)


@pytest.mark.parametrize("fusion", ["paper", "kalman"])
def test_error_against_truth_does_not_grow_on_a_still_camera(still, fusion):
    """Median |d_t - truth_t| on every frame at most the first map's + 0.01 px, and over the second half below
    per-frame stereo's (the map averages measurements instead of wandering). benchmarks/euroc_static.py runs the
    same at 400 frames."""
    K, b = still.K[None], torch.tensor([still.baseline])
    scored = ~still.occluded & (still.disparity > 0)
    refiner = EgoMotionRefiner(max_disparity=16, verify_every=5, fusion=fusion)
    state, error, stereo_error = None, [], []
    for t in range(FRAMES):
        left, right, truth = still.left[t : t + 1], still.right[t : t + 1], still.disparity[t : t + 1]
        out, state = refiner(left, right, K, b, state)
        assert torch.isfinite(out.disparity).all() and out.valid[scored[t : t + 1]].float().mean() > 0.6
        error.append((out.disparity - truth).abs()[out.valid & scored[t : t + 1]].median())
        s = match_stereo(left, right, 16)
        stereo_error.append((s.disparity - truth).abs()[s.valid & scored[t : t + 1]].median())
    error, stereo_error = torch.stack(error), torch.stack(stereo_error)
    assert (error - error[0]).max() < 0.01, f"error grew by {(error - error[0]).max():.3f} px"
    half = FRAMES // 2
    assert error[half:].mean() < stereo_error[half:].mean(), (error[half:].mean(), stereo_error[half:].mean())
