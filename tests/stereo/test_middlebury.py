"""Accuracy on the Middlebury 'motorcycle' pair that scikit-image ships (no download), against OpenCV.

OpenCV runs as its users run it and as ``benchmarks/real.py`` runs it (``benchmarks/_opencv.py``: uniqueness,
speckle filter and left-right check on; SGBM 3-way with P1 = 8 bs^2, P2 = 32 bs^2 on grey images); our matchers
get the colour pair as a user passes it (``egorefine.core.to_grey`` inside). Issue 17's targets: the SGM option
below SGBM's bad-2 at most 3 points less dense (met), the default matcher below StereoBM's bad-2 at no lower
density (not met at StereoBM's block 9: held as a strict xfail, and what holds instead is tested: bad-2 close to
StereoBM's at a clearly higher density).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from egorefine.stereo import match_stereo

cv2 = pytest.importorskip("cv2")
skdata = pytest.importorskip("skimage.data")
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks._opencv import compute, stereo_bm, stereo_sgbm  # noqa: E402

NUM_DISPARITIES = 64  # the pair's finite ground truth spans ~7..60 px
SGM = {"cost": "census", "aggregation": "sgm", "block_size": 5}


@pytest.fixture(scope="module")
def motorcycle():
    """Grey uint8 pair for OpenCV, truth, its mask, colour pair (1, 3, H, W) RGB in [0, 1] for ours."""
    left, right, gt = skdata.stereo_motorcycle()  # RGB uint8 (500, 741, 3) x2, float32 disparity (inf = unknown)
    grey_l = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)
    grey_r = cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)
    known = np.isfinite(gt) & (gt > 0)
    to_t = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None].float() / 255.0  # noqa: E731
    return grey_l, grey_r, gt, known, to_t(left), to_t(right)


def _score(disp: np.ndarray, valid: np.ndarray, gt: np.ndarray, known: np.ndarray) -> tuple[float, float]:
    """(bad-2 rate on pixels marked valid with known truth, density over known-truth pixels)."""
    scored = valid & known
    bad2 = float((np.abs(disp - gt)[scored] > 2.0).mean())
    return bad2, float(scored.sum() / known.sum())


def _ours(left, right, gt, known, **options) -> tuple[float, float]:
    with torch.no_grad():
        out = match_stereo(left, right, NUM_DISPARITIES, **options)
    return _score(out.disparity[0, 0].numpy(), out.valid[0, 0].numpy(), gt, known)


def _opencv(matcher, grey_l, grey_r, gt, known) -> tuple[float, float]:
    cv2.setNumThreads(1)
    return _score(*compute(matcher, grey_l, grey_r), gt, known)


def test_default_matcher_is_close_to_opencv_bm_and_denser(motorcycle):
    """What holds where issue 17's target does not: at StereoBM's block 9 (our default window) the default matcher's
    bad-2 is at most 1.1 times StereoBM's, at a density at least 5 points above StereoBM's. Both bounds sit a few
    percent (bad-2) and a few points (density) beyond what the matcher scores on this pair
    (benchmarks/results/real.md), so that a regression of either shows."""
    grey_l, grey_r, gt, known, left, right = motorcycle
    ours = _ours(left, right, gt, known)
    theirs = _opencv(stereo_bm(NUM_DISPARITIES, 9), grey_l, grey_r, gt, known)
    assert ours[0] <= 1.1 * theirs[0], f"bad-2 {ours[0]:.4f} vs OpenCV BM {theirs[0]:.4f}"
    assert ours[1] >= theirs[1] + 0.05, f"density {ours[1]:.3f} vs OpenCV BM {theirs[1]:.3f}"


@pytest.mark.parametrize("block_size", [
    pytest.param(9, marks=pytest.mark.xfail(strict=True, reason="issue 17's target is not met at block 9: the "
                                            "default matcher's bad-2 is a little above StereoBM's "
                                            "(benchmarks/results/real.md)")),
    pytest.param(15, marks=pytest.mark.slow),
])
def test_default_matcher_beats_opencv_bm(motorcycle, block_size):
    """Issue 17's target: lower bad-2 than StereoBM with the same window, at no lower density."""
    grey_l, grey_r, gt, known, left, right = motorcycle
    ours = _ours(left, right, gt, known, block_size=block_size)
    theirs = _opencv(stereo_bm(NUM_DISPARITIES, block_size), grey_l, grey_r, gt, known)
    assert ours[0] < theirs[0], f"bad-2 {ours[0]:.4f} vs OpenCV BM {theirs[0]:.4f}"
    assert ours[1] >= theirs[1], f"density {ours[1]:.3f} vs OpenCV BM {theirs[1]:.3f}"


@pytest.mark.slow
def test_sgm_beats_opencv_sgbm(motorcycle):
    """Issue 17's target for the SGM option: lower bad-2 than SGBM 3-way at a density at most 3 points below."""
    grey_l, grey_r, gt, known, left, right = motorcycle
    ours = _ours(left, right, gt, known, **SGM)
    sgbm = _opencv(stereo_sgbm(NUM_DISPARITIES), grey_l, grey_r, gt, known)
    assert ours[0] < sgbm[0], f"bad-2 {ours[0]:.4f} vs SGBM {sgbm[0]:.4f}"
    assert ours[1] >= sgbm[1] - 0.03, f"density {ours[1]:.3f} vs SGBM {sgbm[1]:.3f}"


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="issue 17's SGM penalties: denser on this pair but its bad-2 rose above the "
                   "default matcher's (docs/decisions.md)")
def test_sgm_beats_the_default_matcher(motorcycle):
    _, _, gt, known, left, right = motorcycle
    ours = _ours(left, right, gt, known, **SGM)
    default = _ours(left, right, gt, known)
    assert ours[0] < default[0], f"bad-2 {ours[0]:.4f} vs the default matcher {default[0]:.4f}"
