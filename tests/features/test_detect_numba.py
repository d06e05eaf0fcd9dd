"""Tests of egorefine.features._detect_numba: the compiled CPU detection agrees with the torch path to float rounding.

The two paths compute the same float32 formulas in different orders (torch's vectorised sums, MKL's sqrt/exp), so
values differ by rounding: the response by ~6e-7 of its peak, refined positions by up to ~1.4e-3 px (the corner point
is solved from sums of absolute pixel coordinates: the float32 ulp at x ~ 1000 is 6e-5). Rounding can also swap two
nearly equal candidates, and exact ties are ordered by different rules (torch.topk's algorithm here, pixel index
there). The bounds below allow for that and no more: a wrong blur, window, rank rule or sub-pixel step breaks them.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from egorefine.core import ShapeError, ValueRangeError, dispatch
from egorefine.data import render_sequence
from egorefine.features import _detect_numba as dn
from egorefine.features import detect, detection, replenish

pytestmark = pytest.mark.skipif(not dn.AVAILABLE, reason="numba is not installed")

MATCH = 1e-3  # px: a compiled keypoint with a torch keypoint this close is the same keypoint
POSITION = 2e-3  # px: the most two refined positions of the same corner may differ by


def _both(fn, monkeypatch, *args, **kwargs):
    """``fn`` on the torch path, then on the compiled path."""
    monkeypatch.setattr(dispatch, "ENABLED", False)
    ref = fn(*args, **kwargs)
    monkeypatch.setattr(dispatch, "ENABLED", True)
    return ref, fn(*args, **kwargs)


def _assert_agree(ref, out, first: bool = True):
    """Per image: the same number of keypoints (weights 0 or 1, empty slots at (0, 0), real ones first unless not
    ``first``: replenish keeps live tracks where they are); at most 1 % (at least 1) of the compiled keypoints
    without a torch keypoint within ``MATCH``; at most 1 % (at least 2: one swapped pair) of the slots holding
    different keypoints; a torch keypoint within 0.05 px of a compiled one within ``POSITION`` of it."""
    (kp_t, w_t), (kp_c, w_c) = ref, out
    assert kp_c.shape == kp_t.shape and w_c.shape == w_t.shape
    assert kp_c.dtype == kp_t.dtype and w_c.dtype == w_t.dtype
    assert torch.equal(w_c.sum(1), w_t.sum(1))
    assert ((w_c == 0) | (w_c == 1)).all() and (kp_c[w_c == 0] == 0).all()
    if first:
        assert torch.equal(w_c, w_t)  # the same count, real ones first
    for b in range(w_c.shape[0]):
        real_c, real_t = w_c[b] > 0, w_t[b] > 0
        count = int(real_c.sum())
        if count == 0:
            continue
        near = torch.cdist(kp_c[b, real_c].double(), kp_t[b, real_t].double()).min(1).values
        assert (near > MATCH).sum() <= max(1, count // 100), near.max()
        assert near[near < 0.05].max() <= POSITION
        moved = ((kp_c[b] - kp_t[b]).norm(dim=-1) > MATCH) | (real_c != real_t)
        assert moved.sum() <= max(2, count // 100)


@pytest.fixture(scope="module")
def frames():
    return {p: render_sequence(num_frames=1, preset=p, seed=0).left for p in ("paper", "kitti")}


def test_applies_only_to_float32_cpu_shi_tomasi():
    img = torch.rand(1, 1, 32, 32)
    assert detection._compiled_applies(img, "gftt")
    assert not detection._compiled_applies(img, "harris")
    assert not detection._compiled_applies(img.double(), "gftt")
    assert not detection._compiled_applies(img[..., :3, :], "gftt")  # kornia's reflected blur needs 4 px


@pytest.mark.parametrize("preset", ["paper", "kitti"])
def test_rendered_frames_agree_with_torch(frames, preset, monkeypatch):
    ref, out = _both(detect, monkeypatch, frames[preset], max_features=1000)
    assert ref[1].sum() == 1000  # full: every slot and the round-robin order are compared
    _assert_agree(ref, out)


def test_response_is_kornias(frames):
    """The kernels' response map equals kornia's gftt_response within 1e-5 of its peak (measured: 6e-7)."""
    from kornia.feature import gftt_response

    img = frames["kitti"][:, :, :120]
    h, w = img.shape[-2:]
    resp = np.empty((h, w), np.float32)
    dn._response_rows(img[0, 0].numpy(), 0, h, dn._gauss7(), resp)
    ref = gftt_response(img)[0, 0].numpy()
    np.testing.assert_allclose(resp, ref, rtol=0, atol=1e-5 * ref.max())


@pytest.mark.parametrize("subpixel", ["gradient", "quadratic", "none"])
def test_random_batch_agrees_with_torch(subpixel, monkeypatch):
    g = torch.Generator().manual_seed(0)
    img = torch.rand(2, 1, 75, 101, generator=g)  # cells cut by the image's edge
    ref, out = _both(detect, monkeypatch, img, max_features=300, grid=(3, 4), subpixel=subpixel)
    assert (ref[1].sum(1) > 50).all()
    _assert_agree(ref, out)


def test_rgb_and_settings_agree_with_torch(monkeypatch):
    g = torch.Generator().manual_seed(1)
    img = torch.rand(1, 3, 64, 96, generator=g)
    settings = dict(max_features=120, grid=(2, 3), nms_radius=2, quality=0.05, min_response=1e-3, border=5)
    ref, out = _both(detect, monkeypatch, img, **settings)
    assert ref[1].sum() > 20
    _assert_agree(ref, out)


def test_non_contiguous_image_agrees_with_torch(monkeypatch):
    g = torch.Generator().manual_seed(8)
    img = torch.rand(2, 1, 90, 70, generator=g).transpose(-1, -2)[:, :, 3:, :]  # (2, 1, 67, 90), strided
    assert not img.is_contiguous()
    ref, out = _both(detect, monkeypatch, img, max_features=100, grid=(2, 2))
    assert ref[1].sum() > 20
    _assert_agree(ref, out)


@pytest.mark.parametrize("value", [0.0, 0.5])
def test_flat_image_gives_no_keypoints(value, monkeypatch):
    img = torch.full((2, 1, 48, 64), value)
    ref, out = _both(detect, monkeypatch, img, max_features=50)
    assert (out[1] == 0).all() and (out[0] == 0).all()
    _assert_agree(ref, out)


@pytest.mark.parametrize("size", [(4, 4), (6, 5), (12, 9)])
def test_images_smaller_than_the_grid(size, monkeypatch):
    g = torch.Generator().manual_seed(2)
    img = torch.rand(2, 1, *size, generator=g)
    ref, out = _both(detect, monkeypatch, img, max_features=40, border=0)  # grid 8 x 8: cells of 1-2 px
    assert ref[1].sum() > 0
    _assert_agree(ref, out)


def test_too_small_image_is_refused_on_both_paths(monkeypatch):
    img = torch.rand(1, 1, 3, 8)
    with pytest.raises(ShapeError, match="image: expected at least 4 px per side"):
        detect(img)
    monkeypatch.setattr(dispatch, "ENABLED", False)
    with pytest.raises(ShapeError, match="image: expected at least 4 px per side"):
        detect(img)


def test_exact_ties_go_by_pixel_index():
    """A checkerboard gives many corners of exactly equal response: with one cell the keypoints come by response,
    equal responses by pixel index; the order is the same twice and for the image alone or in a batch."""
    yy, xx = torch.meshgrid(torch.arange(96), torch.arange(128), indexing="ij")
    img = (((yy // 6) + (xx // 6)) % 2).float().view(1, 1, 96, 128) * 0.8 + 0.1
    kp, w = detect(img, max_features=150, grid=(1, 1), subpixel="none")
    assert w.sum() == 150
    resp = np.empty((96, 128), np.float32)
    dn._response_rows(img[0, 0].numpy(), 0, 96, dn._gauss7(), resp)
    x, y = kp[0].long().T.numpy()
    r, flat = resp[y, x], y * 128 + x
    assert (np.diff(r) <= 0).all()
    ties = np.diff(r) == 0
    assert ties.sum() > 100  # the test is about ties: there are many
    assert (np.diff(flat)[ties] > 0).all()
    batch = torch.cat([torch.rand(1, 1, 96, 128, generator=torch.Generator().manual_seed(6)), img, img.flip(-1)])
    for args in [(img, 200, (4, 4)), (img, 150, (8, 8)), (batch, 150, (8, 8))]:
        once = detect(*args)
        again = detect(*args)
        assert torch.equal(once[0], again[0]) and torch.equal(once[1], again[1])
    alone = detect(img, 150, (8, 8))
    assert torch.equal(once[0][1:2], alone[0]) and torch.equal(once[1][1:2], alone[1])


def test_threads_do_not_change_the_result():
    g = torch.Generator().manual_seed(3)
    img = torch.rand(2, 1, 130, 150, generator=g)
    args = (img, 200, (4, 4), 3, 0.01, 1e-4, 8, "gradient")
    one = dn.detect_compiled(*args, threads=1)
    two = dn.detect_compiled(*args, threads=2)
    assert torch.equal(one[0], two[0]) and torch.equal(one[1], two[1])


def test_batch_item_equals_item_alone():
    g = torch.Generator().manual_seed(4)
    img = torch.rand(3, 1, 60, 80, generator=g)
    kp, w = detect(img, max_features=100)
    kp1, w1 = detect(img[1:2], max_features=100)
    assert torch.equal(kp[1:2], kp1) and torch.equal(w[1:2], w1)


def test_replenish_agrees_with_torch(frames, monkeypatch):
    img = frames["paper"]
    kp, w = detect(img, max_features=500)
    g = torch.Generator().manual_seed(5)
    live = w * (torch.rand(w.shape, generator=g) < 0.4)
    moved = kp + torch.randn(kp.shape, generator=g)
    ref, out = _both(replenish, monkeypatch, img, moved, live)
    assert (out[1] > 0).sum() > live.sum() + 100  # empty slots were filled
    assert torch.equal(out[0][live > 0], moved[live > 0])  # live tracks keep their slots
    _assert_agree(ref, out, first=False)
    ref, out = _both(replenish, monkeypatch, img, moved, live, max_features=600, min_distance=12.5)
    _assert_agree(ref, out, first=False)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_image_raises_on_both_paths(bad, monkeypatch):
    """Both paths raise check_finite's error at the door (on the CPU a numpy test: no torch reduction)."""
    img = torch.rand(2, 1, 40, 50, generator=torch.Generator().manual_seed(7))
    img[1, 0, 33, 7] = bad
    empty = torch.zeros(2, 20, 2), torch.zeros(2, 20)
    for compiled in (False, True):
        monkeypatch.setattr(dispatch, "ENABLED", compiled)
        with pytest.raises(ValueRangeError, match="image: contains NaN or Inf"):
            detect(img)
        with pytest.raises(ValueRangeError, match="image: contains NaN or Inf"):
            replenish(img, *empty)
