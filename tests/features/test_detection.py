"""Tests of egorefine.features.detection: detect, Detector, replenish, corner_response."""

from __future__ import annotations

import pytest
import torch

from egorefine.core import ShapeError, ValueRangeError
from egorefine.features import Detector, corner_response, detect, replenish

from .helpers import checker_corner, smooth_texture


def test_shapes_and_slots():
    img = smooth_texture(0, batch=2)
    kp, w = detect(img, max_features=64, grid=(4, 4))
    assert kp.shape == (2, 64, 2) and w.shape == (2, 64)
    assert kp.dtype == img.dtype and w.dtype == img.dtype
    assert set(w.unique().tolist()) <= {0.0, 1.0}
    assert torch.isfinite(kp).all()
    # Real keypoints come first; empty slots sit at (0, 0).
    n = w.sum(dim=1).long()
    for b in range(2):
        assert (w[b, : n[b]] == 1).all() and (w[b, n[b] :] == 0).all()
        assert (kp[b, n[b] :] == 0).all()
    # Inside the border and the image.
    real = kp[w > 0]
    assert (real[:, 0] >= 8 - 1).all() and (real[:, 0] <= 160 - 8).all()
    assert (real[:, 1] >= 8 - 1).all() and (real[:, 1] <= 120 - 8).all()


def test_rgb_matches_grey_shape():
    img = smooth_texture(1).expand(1, 3, 120, 160).contiguous()
    kp, w = detect(img, max_features=30, grid=(2, 2))
    kp1, w1 = detect(img[:, :1], max_features=30, grid=(2, 2))
    assert kp.shape == (1, 30, 2)
    # rgb_to_grayscale of equal channels is the same grey image to a float32 step (the weights' sum rounds); the
    # sub-pixel peak fit divides response differences, so positions agree to ~1e-4 px, and within the 1e-3 px that
    # makes two keypoints the same keypoint (test_detect_numba's MATCH). The selection (0/1 weights) is exact.
    torch.testing.assert_close(kp, kp1, atol=1e-3, rtol=0)
    torch.testing.assert_close(w, w1)


@pytest.mark.parametrize("value", [0.0, 0.5, 1.0])
def test_flat_or_black_image_gives_no_features(value):
    img = torch.full((2, 1, 64, 80), value)
    kp, w = detect(img, max_features=100)
    assert kp.shape == (2, 100, 2)
    assert (w == 0).all()
    assert torch.isfinite(kp).all()


def test_quantisation_noise_gives_no_features():
    g = torch.Generator().manual_seed(3)
    img = 0.5 + torch.randint(0, 2, (1, 1, 64, 80), generator=g).float() / 255.0
    _, w = detect(img)
    assert (w == 0).all()


def test_grid_spreads_features():
    img = smooth_texture(2, 240, 320)
    kp, w = detect(img, max_features=200, grid=(4, 4))
    assert int(w.sum()) == 200
    real = kp[0][w[0] > 0]
    cell = (real[:, 1] // 60).long() * 4 + (real[:, 0] // 80).long()
    counts = torch.bincount(cell, minlength=16)
    # Every cell gets some, none hogs the budget (a fair share is 200 / 16 = 12.5).
    assert (counts >= 8).all(), counts
    assert (counts <= 18).all(), counts


def test_textured_cells_fill_slots_left_by_flat_cells():
    img = smooth_texture(4, 120, 160)
    img[..., :, 80:] = 0.5  # right half flat
    kp, w = detect(img, max_features=60, grid=(2, 2))
    assert int(w.sum()) == 60
    assert (kp[0, :, 0] < 80).all()


@pytest.mark.parametrize("response", ["gftt", "harris"])
@pytest.mark.parametrize("x0,y0", [(20.3, 17.8), (23.5, 19.25), (21.77, 20.61)])
def test_subpixel_corner_position(response, x0, y0):
    img = checker_corner(x0, y0)
    kp, w = detect(img, max_features=5, grid=(1, 1), response=response, border=4)
    assert int(w.sum()) >= 1
    err = (kp[0, 0] - torch.tensor([x0, y0])).norm()
    assert err < 0.2, (kp[0, 0], err)


def test_subpixel_beats_integer():
    x0, y0 = 21.3, 18.7
    img = checker_corner(x0, y0)
    truth = torch.tensor([x0, y0])
    kp_s, _ = detect(img, max_features=1, grid=(1, 1))
    kp_i, _ = detect(img, max_features=1, grid=(1, 1), subpixel="none")
    assert (kp_i[0, 0] == kp_i[0, 0].round()).all()
    assert (kp_s[0, 0] - truth).norm() < (kp_i[0, 0] - truth).norm()


def test_deterministic_and_batch_consistent():
    img = smooth_texture(5, batch=3)
    kp, w = detect(img, max_features=50, grid=(3, 3))
    kp2, w2 = detect(img, max_features=50, grid=(3, 3))
    assert torch.equal(kp, kp2) and torch.equal(w, w2)
    for b in range(3):
        kb, wb = detect(img[b : b + 1], max_features=50, grid=(3, 3))
        torch.testing.assert_close(kb[0], kp[b])
        torch.testing.assert_close(wb[0], w[b])


def test_more_slots_than_pixels():
    img = smooth_texture(6, 24, 24)
    kp, w = detect(img, max_features=1000, grid=(2, 2), border=2)
    assert kp.shape == (1, 1000, 2)
    assert 0 < int(w.sum()) < 1000


def test_module_matches_function():
    img = smooth_texture(7)
    settings = dict(max_features=40, grid=(2, 3), response="harris", nms_radius=2, border=6)
    kp, w = detect(img, **settings)
    kp_m, w_m = Detector(**settings)(img)
    assert torch.equal(kp, kp_m) and torch.equal(w, w_m)


def test_corner_response_shape():
    r = corner_response(smooth_texture(8, batch=2), response="harris")
    assert r.shape == (2, 1, 120, 160)
    assert torch.isfinite(r).all()


def test_bad_input():
    with pytest.raises(ShapeError, match="image"):
        detect(torch.rand(1, 2, 32, 32))
    with pytest.raises(ShapeError, match="image"):
        detect(torch.rand(32, 32))
    img = torch.rand(1, 1, 32, 32)
    img[0, 0, 3, 3] = float("nan")
    with pytest.raises(ValueRangeError, match="image"):
        detect(img)
    with pytest.raises(ValueRangeError, match="max_features"):
        detect(torch.rand(1, 1, 32, 32), max_features=0)
    with pytest.raises(ValueRangeError, match="grid"):
        detect(torch.rand(1, 1, 32, 32), grid=(0, 2))
    with pytest.raises(ValueRangeError, match="response"):
        detect(torch.rand(1, 1, 32, 32), response="fast")


# ----------------------------------------------------------------------------- replenish


def test_replenish_keeps_live_tracks_and_fills_empty_slots():
    img = smooth_texture(9, 120, 160)
    kp0, w0 = detect(img, max_features=40, grid=(2, 2))
    # Lose every other track.
    w = w0.clone()
    w[:, 1::2] = 0
    kp, nw = replenish(img, kp0, w, min_distance=6.0, grid=(2, 2))
    assert kp.shape == (1, 40, 2) and nw.shape == (1, 40)
    live = w > 0
    assert torch.equal(kp[live], kp0[live]) and torch.equal(nw[live], w[live])
    new = (~live) & (nw > 0)
    assert int(new.sum()) == int((~live).sum())  # a textured image has enough corners
    d = torch.cdist(kp[new].unsqueeze(0), kp[live].unsqueeze(0))
    assert d.min() >= 6.0
    assert torch.isfinite(kp).all()


def test_replenish_all_live_is_identity_and_more_slots():
    img = smooth_texture(10)
    kp0, w0 = detect(img, max_features=20, grid=(2, 2))
    kp, w = replenish(img, kp0, w0, grid=(2, 2))
    assert torch.equal(kp, kp0) and torch.equal(w, w0)
    kp2, w2 = replenish(img, kp0, w0, max_features=30, grid=(2, 2))
    assert kp2.shape == (1, 30, 2)
    assert torch.equal(kp2[:, :20], kp0)
    assert int(w2.sum()) > 20


def test_replenish_black_image_leaves_empty_slots_empty():
    kp = torch.tensor([[[10.0, 10.0], [0.0, 0.0]]])
    w = torch.tensor([[1.0, 0.0]])
    kp2, w2 = replenish(torch.zeros(1, 1, 32, 32), kp, w)
    assert torch.equal(kp2, kp) and torch.equal(w2, w)


def test_replenish_bad_input():
    img = torch.rand(1, 1, 32, 32)
    with pytest.raises(ShapeError, match="weights"):
        replenish(img, torch.zeros(1, 5, 2), torch.zeros(1, 4))
    with pytest.raises(ShapeError, match="keypoints"):
        replenish(img, torch.zeros(2, 5, 2), torch.zeros(2, 5))
    bad = torch.zeros(1, 5, 2)
    bad[0, 1, 0] = float("nan")
    with pytest.raises(ValueRangeError, match="keypoints"):
        replenish(img, bad, torch.zeros(1, 5))
    with pytest.raises(ValueRangeError, match="max_features"):
        replenish(img, torch.zeros(1, 5, 2), torch.zeros(1, 5), max_features=3)


def test_replenish_without_slots():
    img = torch.rand(1, 1, 32, 32)
    kp, w = replenish(img, torch.zeros(1, 0, 2), torch.zeros(1, 0))
    assert kp.shape == (1, 0, 2) and w.shape == (1, 0)


@pytest.mark.parametrize("radius", [0, 1, 3])
def test_max_filter_matches_max_pool(radius):
    from egorefine.features.detection import _max_filter

    x = torch.rand(2, 1, 17, 23, generator=torch.Generator().manual_seed(0))
    expected = torch.nn.functional.max_pool2d(x, 2 * radius + 1, stride=1, padding=radius)
    assert torch.equal(_max_filter(x, radius), expected)
