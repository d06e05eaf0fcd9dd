"""Accuracy against the synthetic renderer's exact ground truth (egorefine.data.render_sequence)."""

from __future__ import annotations

import pytest
import torch

from egorefine.metrics import bad_pixel_rate, epe
from egorefine.stereo import match_stereo

data = pytest.importorskip("egorefine.data")


def _scored(seq) -> torch.Tensor:
    """Textured surfaces with defined truth: not occluded in (nor outside) the right view."""
    w = seq.disparity.shape[-1]
    x = torch.arange(w).view(1, 1, 1, w)
    return (~seq.occluded) & torch.isfinite(seq.disparity) & (x >= seq.disparity)


@pytest.mark.slow
@pytest.mark.parametrize("kw", [{}, {"cost": "census", "aggregation": "sgm", "block_size": 5}])
def test_subpixel_accuracy_on_rendered_frames(kw):
    seq = data.render_sequence(2, preset="paper", height=240, width=320, seed=0)
    max_d = int(seq.disparity.max().ceil()) + 4
    out = match_stereo(seq.left, seq.right, max_d, **kw)
    scored = _scored(seq)
    valid = out.valid & scored
    assert valid.sum() / scored.sum() > 0.9
    assert epe(out.disparity, seq.disparity, valid) < 0.25
    assert bad_pixel_rate(out.disparity, seq.disparity, 2.0, valid) < 0.01


def test_subpixel_accuracy_on_a_small_rendered_frame():
    seq = data.render_sequence(1, preset="paper", height=72, width=96, seed=3, antialias=False)
    out = match_stereo(seq.left, seq.right, 12, block_size=7)
    scored = _scored(seq)
    valid = out.valid & scored
    assert valid.sum() / scored.sum() > 0.9
    assert epe(out.disparity, seq.disparity, valid) < 0.25
