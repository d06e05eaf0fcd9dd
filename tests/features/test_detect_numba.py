"""Tests of egorefine.features._detect_numba: the compiled CPU detection equals the torch path."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from egorefine.core import ValueRangeError
from egorefine.data import render_sequence
from egorefine.features import _detect_numba as dn
from egorefine.features import detect, detection, replenish

pytestmark = pytest.mark.skipif(not dn.AVAILABLE, reason="numba is not installed")


def _exact() -> bool:
    """This machine's torch uses the primitives the kernels repeat (MKL's sqrt/exp, the eight-lane sum)."""
    dn._SETUP()
    return dn._SETUP.vml and dn._SETUP.sum8


def _both(fn, monkeypatch, *args, **kwargs):
    """``fn`` on the torch path, then on the compiled path."""
    monkeypatch.setattr(detection, "_COMPILED", False)
    ref = fn(*args, **kwargs)
    monkeypatch.setattr(detection, "_COMPILED", True)
    return ref, fn(*args, **kwargs)


def _assert_same(ref, out):
    """Same weights and slots; positions bit-identical where the primitives match torch's, else within 1e-3 px."""
    (kp_t, w_t), (kp_c, w_c) = ref, out
    assert kp_c.shape == kp_t.shape and w_c.shape == w_t.shape
    assert kp_c.dtype == kp_t.dtype and w_c.dtype == w_t.dtype
    assert torch.equal(w_c, w_t)
    if _exact():
        assert torch.equal(kp_c, kp_t), (kp_c - kp_t).abs().max()
    else:  # pragma: no cover - machines whose torch lacks MKL
        torch.testing.assert_close(kp_c, kp_t, atol=1e-3, rtol=0)


@pytest.fixture(scope="module")
def frames():
    torch.manual_seed(0)
    return {p: render_sequence(num_frames=1, preset=p, seed=0).left for p in ("paper", "kitti")}


def test_applies_only_to_float32_cpu_shi_tomasi():
    img = torch.rand(1, 1, 32, 32)
    assert detection._compiled_applies(img, "gftt")
    assert not detection._compiled_applies(img, "harris")
    assert not detection._compiled_applies(img.double(), "gftt")
    assert not detection._compiled_applies(img[..., :3, :], "gftt")  # kornia's reflected blur needs 4 px


@pytest.mark.parametrize("preset", ["paper", "kitti"])
def test_rendered_frames_match_torch(frames, preset, monkeypatch):
    img = frames[preset]
    ref, out = _both(detect, monkeypatch, img, max_features=1000)
    assert ref[1].sum() == 1000  # full: every slot and the round-robin order are compared
    _assert_same(ref, out)


def test_response_is_kornias(frames):
    """The kernels' response map equals kornia's gftt_response bit for bit (MKL's sqrt where torch uses it)."""
    from kornia.feature import gftt_response

    img = frames["kitti"][:, :, :120]
    h, w = img.shape[-2:]
    resp = np.empty((h, w), np.float32)
    dn._SETUP()
    dn._one_thread_mkl(dn._response_rows)(img[0, 0].numpy(), 0, h, dn._gauss7(), dn._SETUP.vml, resp)
    ref = gftt_response(img)[0, 0].numpy()
    if dn._SETUP.vml:
        assert np.array_equal(resp, ref)
    else:  # pragma: no cover
        np.testing.assert_allclose(resp, ref, rtol=0, atol=1e-6 * ref.max())


@pytest.mark.parametrize("subpixel", ["gradient", "quadratic", "none"])
def test_random_batch_matches_torch(subpixel, monkeypatch):
    g = torch.Generator().manual_seed(0)
    img = torch.rand(2, 1, 75, 101, generator=g)  # cells cut by the image's edge
    ref, out = _both(detect, monkeypatch, img, max_features=300, grid=(3, 4), subpixel=subpixel)
    assert (ref[1].sum(1) > 50).all()
    _assert_same(ref, out)


def test_rgb_and_settings_match_torch(monkeypatch):
    g = torch.Generator().manual_seed(1)
    img = torch.rand(1, 3, 64, 96, generator=g)
    settings = dict(max_features=120, grid=(2, 3), nms_radius=2, quality=0.05, min_response=1e-3, border=5)
    ref, out = _both(detect, monkeypatch, img, **settings)
    assert ref[1].sum() > 20
    _assert_same(ref, out)


def test_non_contiguous_image_matches_torch(monkeypatch):
    g = torch.Generator().manual_seed(8)
    img = torch.rand(2, 1, 90, 70, generator=g).transpose(-1, -2)[:, :, 3:, :]  # (2, 1, 67, 90), strided
    assert not img.is_contiguous()
    ref, out = _both(detect, monkeypatch, img, max_features=100, grid=(2, 2))
    assert ref[1].sum() > 20
    _assert_same(ref, out)


@pytest.mark.parametrize("value", [0.0, 0.5])
def test_flat_image_gives_no_keypoints(value, monkeypatch):
    img = torch.full((2, 1, 48, 64), value)
    ref, out = _both(detect, monkeypatch, img, max_features=50)
    assert (out[1] == 0).all() and (out[0] == 0).all()
    _assert_same(ref, out)


@pytest.mark.parametrize("size", [(4, 4), (6, 5), (12, 9)])
def test_images_smaller_than_the_grid(size, monkeypatch):
    g = torch.Generator().manual_seed(2)
    img = torch.rand(2, 1, *size, generator=g)
    ref, out = _both(detect, monkeypatch, img, max_features=40, border=0)  # grid 8 x 8: cells of 1-2 px
    assert ref[1].sum() > 0
    _assert_same(ref, out)


def test_too_small_image_keeps_the_torch_error(monkeypatch):
    img = torch.rand(1, 1, 3, 8)
    with pytest.raises(RuntimeError):
        detect(img)
    monkeypatch.setattr(detection, "_COMPILED", False)
    with pytest.raises(RuntimeError):
        detect(img)


@pytest.mark.parametrize("grid, n, partial_sort", [((4, 4), 200, False), ((8, 8), 150, True)])
def test_exact_ties_are_ordered_as_torch_orders_them(grid, n, partial_sort, monkeypatch):
    """A checkerboard gives many corners of exactly equal response in every cell and equal keys across cells:
    the order of equal values is torch.topk's, which the compiled path asks torch for on the torch path's rows
    or, where topk takes std::partial_sort (64 n <= cells x kc), repeats."""
    yy, xx = torch.meshgrid(torch.arange(96), torch.arange(128), indexing="ij")
    img = (((yy // 6) + (xx // 6)) % 2).float().view(1, 1, 96, 128) * 0.8 + 0.1
    resp = detection.corner_response(img)[0, 0]
    peaks = resp[8:-8, 8:-8][resp[8:-8, 8:-8] >= 0.5 * resp.max()]
    assert peaks.unique().numel() < peaks.numel() // 4  # the test is about ties: there are many
    calls = {"cells": 0, "heap": 0}
    cell_order, top_keys = dn._cell_order, dn._top_keys

    def count_cells(*args):
        calls["cells"] += 1
        return cell_order(*args)

    def count_heap(*args):
        calls["heap"] += 1
        return top_keys(*args)

    monkeypatch.setattr(dn, "_cell_order", count_cells)
    monkeypatch.setattr(dn, "_top_keys", count_heap)
    ref, out = _both(detect, monkeypatch, img, max_features=n, grid=grid)
    assert ref[1].sum() == n
    _assert_same(ref, out)
    assert calls["cells"] > 0  # equal strengths in a cell were ordered by torch.topk
    assert calls["heap"] == int(partial_sort and dn._SETUP.heap)


def test_partial_sort_is_torch_topk():
    """The repeated std::partial_sort gives torch.topk's indices, equal values included."""
    dn._SETUP()
    if not dn._SETUP.heap:  # pragma: no cover - another torch.topk: the compiled path then calls it instead
        pytest.skip("torch.topk is not libstdc++'s partial sort here")
    g = torch.Generator().manual_seed(6)
    for size, k in [(64000, 1000), (640, 10), (64, 1)]:
        vals = torch.randint(0, 20, (size,), generator=g).float()
        vals[torch.rand(size, generator=g) < 0.7] = -5.0
        top = dn._partial_sort(vals.numpy().copy(), k)
        assert np.array_equal(top, vals.topk(k).indices.numpy())


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


def test_replenish_matches_torch(frames, monkeypatch):
    img = frames["paper"]
    kp, w = detect(img, max_features=500)
    g = torch.Generator().manual_seed(5)
    live = w * (torch.rand(w.shape, generator=g) < 0.4)
    moved = kp + torch.randn(kp.shape, generator=g)
    ref, out = _both(replenish, monkeypatch, img, moved, live)
    assert (out[1] > 0).sum() > live.sum() + 100  # empty slots were filled
    _assert_same(ref, out)
    ref, out = _both(replenish, monkeypatch, img, moved, live, max_features=600, min_distance=12.5)
    _assert_same(ref, out)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_image_raises_on_both_paths(bad, monkeypatch):
    """The compiled path checks the pixels in its first pass (no torch reduction) and raises check_finite's error."""
    img = torch.rand(2, 1, 40, 50, generator=torch.Generator().manual_seed(7))
    img[1, 0, 33, 7] = bad
    empty = torch.zeros(2, 20, 2), torch.zeros(2, 20)
    for compiled in (False, True):
        monkeypatch.setattr(detection, "_COMPILED", compiled)
        with pytest.raises(ValueRangeError, match="image: contains NaN or Inf"):
            detect(img)
        with pytest.raises(ValueRangeError, match="image: contains NaN or Inf"):
            replenish(img, *empty)
