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


SGM = {"cost": "census", "aggregation": "sgm", "block_size": 5}


# (imaging, matcher options, density above, EPE below, bad-2 below): ideal images test the sub-pixel fit on clean
# data, realistic ones (noise, weak texture, camera differences) what users meet. Bounds from what each matcher
# achieves on this render: EPE at about 1.2-1.3 times, density a few points below, bad-2 at a small multiple of a
# rate of a few pixels in a thousand (a floor that a machine's float rounding cannot reach).
@pytest.mark.slow
@pytest.mark.parametrize(
    ("imaging", "kw", "density", "max_epe", "max_bad2"),
    [("ideal", {}, 0.95, 0.1, 0.002), ("ideal", SGM, 0.96, 0.13, 0.002),
     ("realistic", {}, 0.54, 0.36, 0.02), ("realistic", SGM, 0.9, 0.48, 0.04)],
)
def test_subpixel_accuracy_on_rendered_frames(imaging, kw, density, max_epe, max_bad2):
    seq = data.render_sequence(2, preset="paper", height=240, width=320, seed=0, imaging=imaging)
    max_d = int(seq.disparity.max().ceil()) + 4
    out = match_stereo(seq.left, seq.right, max_d, **kw)
    scored = _scored(seq)
    valid = out.valid & scored
    assert valid.sum() / scored.sum() > density
    assert epe(out.disparity, seq.disparity, valid) < max_epe
    assert bad_pixel_rate(out.disparity, seq.disparity, 2.0, valid) < max_bad2


# (imaging, density above, EPE below, bad-1 below): ideal images test the sub-pixel fit on clean data, realistic
# ones (noise, weak texture, camera differences) what users meet. Bounds from what the matcher achieves on this
# render: EPE and bad-1 at about 1.2-1.3 times, density a few points below; the matcher without its sub-pixel fit
# breaks the EPE bound of both and the bad-1 bound of the realistic one.
@pytest.mark.parametrize(("imaging", "density", "max_epe", "max_bad1"),
                         [("ideal", 0.95, 0.14, 0.005), ("realistic", 0.72, 0.32, 0.026)])
def test_subpixel_accuracy_on_a_small_rendered_frame(imaging, density, max_epe, max_bad1):
    seq = data.render_sequence(1, preset="paper", height=72, width=96, seed=3, antialias=False, imaging=imaging)
    out = match_stereo(seq.left, seq.right, 12, block_size=7)
    scored = _scored(seq)
    valid = out.valid & scored
    assert valid.sum() / scored.sum() > density
    assert epe(out.disparity, seq.disparity, valid) < max_epe
    assert bad_pixel_rate(out.disparity, seq.disparity, 1.0, valid) < max_bad1
