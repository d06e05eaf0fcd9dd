"""A long run (slow): 2,000 frames at a small size without memory growth, NaN, or error above per-frame stereo's.

Run with ``pytest -m slow tests/refine/test_long_run.py``.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from egorefine.data import render_sequence
from egorefine.refine import EgoMotionRefiner
from egorefine.stereo import match_stereo

FRAMES = 2000


def _rss_bytes() -> int:
    """Resident set size of this process (Linux), in bytes."""
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    return pages * 4096


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="reads the resident size from /proc")
def test_two_thousand_frames():
    # A 50-frame clip played forwards and backwards: every frame has exact truth, and the motion reverses at the ends.
    seq = render_sequence(num_frames=50, height=60, width=80, seed=7)
    order = [t for _ in range(math.ceil(FRAMES / 98)) for t in (*range(50), *range(48, 0, -1))][:FRAMES]
    K, b = seq.K[None], torch.tensor([seq.baseline])
    truth_ok = (seq.disparity > 0) & ~seq.occluded
    stereo_err = []
    for t in range(50):
        s = match_stereo(seq.left[t : t + 1], seq.right[t : t + 1], 16)
        ok = s.valid[0] & truth_ok[t]
        stereo_err.append(float((s.disparity[0] - seq.disparity[t]).abs()[ok].mean()))
    refiner = EgoMotionRefiner(max_disparity=16, verify_every=5, fusion="kalman")
    state, errors, rss = None, [], {}
    for i, t in enumerate(order):
        out, state = refiner(seq.left[t : t + 1], seq.right[t : t + 1], K, b, state)
        assert torch.isfinite(out.disparity).all() and torch.isfinite(out.variance).all()
        ok = out.valid[0] & truth_ok[t]
        errors.append(float((out.disparity[0] - seq.disparity[t]).abs()[ok].mean()))
        if i in (100, FRAMES - 1):
            rss[i] = _rss_bytes()
    growth = rss[FRAMES - 1] / rss[100] - 1.0
    assert growth < 0.05, f"resident memory grew by {growth:.1%} between frame 100 and {FRAMES}"
    refined = sum(errors[100:]) / len(errors[100:])
    per_frame = sum(stereo_err[t] for t in order[100:]) / len(order[100:])
    assert refined <= per_frame, f"refined EPE {refined:.3f} px above per-frame stereo's {per_frame:.3f}"
    print(f"rss growth {growth:.2%}, refined EPE {refined:.4f} px, per-frame stereo {per_frame:.4f} px")
