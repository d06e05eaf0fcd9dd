"""The default matcher and the SGM option on a real KITTI frame with LiDAR truth (tests/data/real).

The truth is one raw Velodyne sweep projected into the left image (sparse, about 4 % of the pixels,
wrong at some occlusion edges), so only pixels with truth are scored: bad-1 and bad-3 over the pixels
both marked valid and with truth, density over the pixels with truth. The bounds sit a few percent beyond
what the matchers score on this frame (error rates about 1.05-1.08 times, densities 1-2 points below;
benchmarks/results/real.md has the full comparison with OpenCV): the frame is fixed and the matchers'
decisions move by a handful of pixels between machines, while a matcher without its sub-pixel fit raises
bad-1 by over a tenth. OpenCV runs as its users run it (benchmarks/_opencv.py, as benchmarks/real.py).
Issue 17's targets against OpenCV: the SGM option's against SGBM is met and tested; the default matcher's
against StereoBM is held as a strict xfail until it is met.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from egorefine.data import read_kitti_disparity
from egorefine.metrics import bad_pixel_rate, density
from egorefine.stereo import match_stereo

cv2 = pytest.importorskip("cv2")
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks._opencv import compute, stereo_bm, stereo_sgbm  # noqa: E402

MAX_DISPARITY = 128  # the LiDAR truth reaches 69 px; the same range as benchmarks/real.py
SGM = {"cost": "census", "aggregation": "sgm", "block_size": 5}
NO_SPECKLE = {"speckle_size": 0}  # the matcher without its default speckle filter


@pytest.fixture(scope="module")
def kitti(kitti_root):
    """Colour pair (1, 3, H, W) RGB in [0, 1], grey uint8 pair for OpenCV, truth (1, 1, H, W) and its mask."""
    bgr = [cv2.imread(str(kitti_root / cam / "0000000001.png"), cv2.IMREAD_COLOR) for cam in ("image_2", "image_3")]
    assert all(a is not None for a in bgr), f"{kitti_root}: cv2.imread could not read the pair"
    colour = [torch.from_numpy(a[..., ::-1].copy()).permute(2, 0, 1)[None].float() / 255.0 for a in bgr]
    grey = [cv2.cvtColor(a, cv2.COLOR_BGR2GRAY) for a in bgr]
    truth, known = read_kitti_disparity(kitti_root / "gt_disp_velo_image_2.png")
    return colour, grey, truth[None], known[None]


def _score(disparity: torch.Tensor, valid: torch.Tensor, truth: torch.Tensor, known: torch.Tensor):
    """(bad-2, bad-3) over valid pixels with truth, density over pixels with truth, bad-1 over valid pixels with
    truth."""
    scored = valid & known
    return (float(bad_pixel_rate(disparity, truth, 2.0, scored)), float(bad_pixel_rate(disparity, truth, 3.0, scored)),
            float(density(valid, known)), float(bad_pixel_rate(disparity, truth, 1.0, scored)))


@pytest.mark.parametrize(("options", "max_bad1", "max_bad3", "min_density"), [
    pytest.param({}, 0.29, 0.115, 0.27, id="default"),
    # the SGM bounds failed before its penalties and checks were tuned for noisy weak texture (issue 17)
    pytest.param(SGM, 0.27, 0.095, 0.82, id="sgm"),
    pytest.param(NO_SPECKLE, 0.37, 0.20, 0.34, id="default-no-speckle"),
    pytest.param({**SGM, **NO_SPECKLE}, 0.285, 0.11, 0.84, id="sgm-no-speckle"),
])
def test_bad3_and_density_on_lidar_truth(kitti, options, max_bad1, max_bad3, min_density):
    """bad-1 (where the sub-pixel fit shows), bad-3 (gross errors) and density against the LiDAR truth."""
    (left, right), _, truth, known = kitti
    with torch.no_grad():
        out = match_stereo(left, right, MAX_DISPARITY, **options)
    _, bad3, dens, bad1 = _score(out.disparity, out.valid, truth, known)
    assert bad1 <= max_bad1, f"bad-1 {bad1:.4f} above {max_bad1}"
    assert bad3 <= max_bad3, f"bad-3 {bad3:.4f} above {max_bad3}"
    assert dens >= min_density, f"density {dens:.4f} below {min_density}"


def _opencv(name: str):
    """OpenCV's matcher as its users configure it (grey input, cn = 1), as benchmarks/real.py runs it."""
    return stereo_bm(MAX_DISPARITY) if name == "bm" else stereo_sgbm(MAX_DISPARITY)


@pytest.mark.parametrize(("options", "opencv", "density_allowance"), [
    pytest.param({}, "bm", 0.0, id="default-vs-bm", marks=pytest.mark.xfail(
        strict=True, reason="issue 17 target not met yet on this frame (benchmarks/results/real.md)")),
    pytest.param(SGM, "sgbm", 0.03, id="sgm-vs-sgbm"),
])
def test_issue17_target_against_opencv(kitti, options, opencv, density_allowance):
    """Lower bad-2 than OpenCV's counterpart at a density at most ``density_allowance`` below its."""
    (left, right), (grey_l, grey_r), truth, known = kitti
    with torch.no_grad():
        out = match_stereo(left, right, MAX_DISPARITY, **options)
    ours = _score(out.disparity, out.valid, truth, known)
    cv2.setNumThreads(1)
    disp, valid = compute(_opencv(opencv), grey_l, grey_r)
    theirs = _score(torch.from_numpy(disp)[None, None], torch.from_numpy(valid)[None, None], truth, known)
    assert ours[0] < theirs[0], f"bad-2 {ours[0]:.4f} vs OpenCV {opencv} {theirs[0]:.4f}"
    assert ours[2] >= theirs[2] - density_allowance, f"density {ours[2]:.3f} vs OpenCV {opencv} {theirs[2]:.3f}"
