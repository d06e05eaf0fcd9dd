"""Accuracy on the Middlebury 'motorcycle' pair that scikit-image ships (no download), against OpenCV."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from egorefine.stereo import match_stereo

cv2 = pytest.importorskip("cv2")
skdata = pytest.importorskip("skimage.data")

NUM_DISPARITIES = 64  # the pair's finite ground truth spans ~7..60 px


@pytest.fixture(scope="module")
def motorcycle():
    left, right, gt = skdata.stereo_motorcycle()  # RGB uint8 (500, 741, 3) x2, float32 disparity (inf = unknown)
    grey_l = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)
    grey_r = cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)
    known = np.isfinite(gt)
    to_t = lambda a: torch.from_numpy(a).float()[None, None] / 255.0  # noqa: E731
    return grey_l, grey_r, gt, known, to_t(grey_l), to_t(grey_r)


def _score(disp: np.ndarray, valid: np.ndarray, gt: np.ndarray, known: np.ndarray) -> tuple[float, float]:
    """(bad-2 rate on pixels marked valid with known truth, density over known-truth pixels)."""
    scored = valid & known
    bad2 = float((np.abs(disp - gt)[scored] > 2.0).mean())
    return bad2, float(scored.sum() / known.sum())


def _opencv_bm(grey_l, grey_r, block_size):
    cv2.setNumThreads(1)
    raw = cv2.StereoBM_create(NUM_DISPARITIES, block_size).compute(grey_l, grey_r)
    return raw.astype(np.float32) / 16.0, raw >= 0


def _opencv_sgbm(grey_l, grey_r, block_size=5):
    cv2.setNumThreads(1)
    area = block_size * block_size
    sgbm = cv2.StereoSGBM_create(0, NUM_DISPARITIES, block_size, P1=8 * area, P2=32 * area,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    raw = sgbm.compute(grey_l, grey_r)
    return raw.astype(np.float32) / 16.0, raw >= 0


@pytest.mark.parametrize("block_size", [9, pytest.param(15, marks=pytest.mark.slow)])
def test_default_matcher_beats_opencv_bm(motorcycle, block_size):
    grey_l, grey_r, gt, known, left, right = motorcycle
    out = match_stereo(left, right, NUM_DISPARITIES, block_size=block_size)
    ours = _score(out.disparity[0, 0].numpy(), out.valid[0, 0].numpy(), gt, known)
    theirs = _score(*_opencv_bm(grey_l, grey_r, block_size), gt, known)
    assert ours[0] <= theirs[0], f"bad-2 {ours[0]:.4f} vs OpenCV BM {theirs[0]:.4f}"
    assert ours[1] >= theirs[1], f"density {ours[1]:.3f} vs OpenCV BM {theirs[1]:.3f}"


@pytest.mark.slow
def test_sgm_beats_opencv_bm_and_sgbm(motorcycle):
    grey_l, grey_r, gt, known, left, right = motorcycle
    out = match_stereo(left, right, NUM_DISPARITIES, cost="census", aggregation="sgm", block_size=5)
    ours = _score(out.disparity[0, 0].numpy(), out.valid[0, 0].numpy(), gt, known)
    bm = _score(*_opencv_bm(grey_l, grey_r, 5), gt, known)
    sgbm = _score(*_opencv_sgbm(grey_l, grey_r, 5), gt, known)
    assert ours[0] < min(bm[0], sgbm[0]), f"bad-2 {ours[0]:.4f} vs BM {bm[0]:.4f} SGBM {sgbm[0]:.4f}"
    assert ours[1] > 0.85


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="issue 17's SGM penalties: denser on this pair (0.90 vs 0.85) but its bad-2 "
                   "rose above the default matcher's (docs/decisions.md)")
def test_sgm_beats_the_default_matcher(motorcycle):
    _, _, gt, known, left, right = motorcycle
    out = match_stereo(left, right, NUM_DISPARITIES, cost="census", aggregation="sgm", block_size=5)
    ours = _score(out.disparity[0, 0].numpy(), out.valid[0, 0].numpy(), gt, known)
    default = _score(*(t[0, 0].numpy() for t in match_stereo(left, right, NUM_DISPARITIES)[:2]), gt, known)
    assert ours[0] < default[0], f"bad-2 {ours[0]:.4f} vs the default matcher {default[0]:.4f}"
