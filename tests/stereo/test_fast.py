"""Tests of egorefine.stereo.fast: the exact int16 path of the default SAD box matcher against the float path."""

from __future__ import annotations

import pytest
import torch

import egorefine.stereo.fast as fast
import egorefine.stereo.matching as matching
from egorefine.metrics import epe
from egorefine.stereo import match_stereo

from ._synthetic import planar_pair, visible


def _both(left, right, max_d, **kw):
    """(float path, integer path) outputs of match_stereo."""
    previous = matching._INTEGER_PATH
    try:
        matching._INTEGER_PATH = False
        ref = match_stereo(left, right, max_d, **kw)
        matching._INTEGER_PATH = True
        new = match_stereo(left, right, max_d, **kw)
    finally:
        matching._INTEGER_PATH = previous
    return ref, new


def _u8(x: torch.Tensor) -> torch.Tensor:
    return (x * 255).round() / 255


@pytest.fixture(scope="module")
def pair():
    return planar_pair(batch=2, height=48, width=80, seed=7, base=6.5, slope_x=0.03, slope_y=0.01)


def test_int_scale():
    cap = 31.0 / 255.0
    assert fast.int_scale(9, cap) == 6  # 81 * 2 * 186 = 30132 < 32767
    assert fast.int_scale(15, cap) == 2
    assert fast.int_scale(21, cap) == 1
    assert fast.int_scale(23, cap) == 0  # 529 * 62 > 32767: the float path is used
    for k in (3, 9, 15, 21):
        s = fast.int_scale(k, cap)
        assert k * k * 2 * round(255 * s * cap) < fast._INVALID


@pytest.mark.parametrize("kw", [
    {}, {"block_size": 5}, {"block_size": 15}, {"min_disparity": 3}, {"subpixel": False},
    {"subpixel_fit": "parabola"}, {"lr_check": False, "uniqueness_ratio": 0.0}, {"lr_threshold": 2},
])
def test_integer_path_equals_float_path_on_8bit_images(pair, kw):
    # 8-bit grey levels: the quantised costs are the float costs exactly (up to the float path's rounding)
    left, right, _ = pair
    ref, new = _both(_u8(left), _u8(right), 16, **kw)
    agree = (ref.valid == new.valid).float().mean()
    assert agree >= 0.995, f"validity agreement {agree:.4f}"
    both = ref.valid & new.valid
    assert both.float().mean() > 0.5
    assert (ref.disparity[both] - new.disparity[both]).abs().max() < 1e-3
    assert torch.allclose(ref.variance[both], new.variance[both], rtol=1e-2, atol=1e-4)
    assert (new.disparity[~new.valid] == 0).all()
    assert (new.variance[~new.valid] == matching.INVALID_VARIANCE).all()
    assert (new.variance[new.valid] >= 1 / 12 - 1e-6).all()
    assert new.disparity.dtype == ref.disparity.dtype


def test_integer_path_close_to_float_path_on_float_images(pair):
    # continuous grey levels are quantised to 1/(255 * 6) of a grey level: near-ties may flip, the rest agrees
    left, right, gt = pair
    ref, new = _both(left, right, 16)
    assert (ref.valid == new.valid).float().mean() >= 0.99
    both = ref.valid & new.valid
    close = (ref.disparity[both] - new.disparity[both]).abs() < 0.02
    assert close.float().mean() > 0.99
    scored = visible(gt, 5)
    assert abs(epe(ref.disparity, gt, ref.valid & scored) - epe(new.disparity, gt, new.valid & scored)) < 0.01


def test_bands_and_batch_do_not_change_the_result(pair, monkeypatch):
    left, right, _ = pair
    ref = match_stereo(left, right, 16)
    monkeypatch.setattr(fast, "_BAND_ELEMENTS", 1)  # _MIN_ROWS rows per band (48 rows: 6 bands)
    monkeypatch.setattr(fast, "_STEP_ELEMENTS", 1)  # one plane at a time
    rows = match_stereo(left, right, 16)
    assert torch.equal(ref.valid, rows.valid) and torch.equal(ref.disparity, rows.disparity)
    assert torch.equal(ref.variance, rows.variance)
    monkeypatch.setattr(fast, "_BAND_ELEMENTS", 2 * 11 * 88)  # 11 rows per band: a shorter last band
    odd = match_stereo(left, right, 16)
    assert torch.equal(ref.valid, odd.valid) and torch.equal(ref.disparity, odd.disparity)
    one = match_stereo(left[1:], right[1:], 16)
    assert torch.equal(ref.valid[1:], one.valid) and torch.equal(ref.disparity[1:], one.disparity)


def _reference(left, right, max_d, min_d=0, block=9, lr_check=True, lr_threshold=1, uniqueness_ratio=0.15,
               texture_threshold=0.004, subpixel=True, subpixel_fit="equiangular"):
    """The integer matcher's decisions written plainly over the whole volume (int32, no bands, no buffers)."""
    cap = 31.0 / 255.0
    scale = fast.int_scale(block, cap)
    r = block // 2
    num = max_d - min_d
    b, _, h, w = left.shape
    inv = fast._INVALID
    lq = fast._quantise(left, cap, scale, (r, r, r, r))[1].int()
    rq = fast._quantise(right, cap, scale, (r + max_d, r, r, r))[1].int()
    ds = [max_d - 1 - j for j in range(num)]
    planes = []
    for d in ds:
        raw = (lq - rq[..., max_d - d : max_d - d + w + 2 * r]).abs()
        box = raw.unfold(2, block, 1).sum(-1).unfold(3, block, 1).sum(-1)[:, 0]  # (B, H, W)
        box[..., :d] = inv  # x - d < 0
        planes.append(box)
    vol = torch.stack(planes, 1)  # (B, num, H, W), index j: disparity max_d - 1 - j
    best = vol.amin(1, keepdim=True)
    j = (vol == best).int().argmax(1, keepdim=True)  # first (lowest) index of the minimum
    jm, jp = (j - 1).clamp_min(0), (j + 1).clamp_max(num - 1)
    c_plus, c_minus = vol.gather(1, jm), vol.gather(1, jp)
    ok = (best < inv) & (j > 0) & (c_plus < inv)
    inner = ok & (j < num - 1) & (c_minus < inv)
    if min_d > 0:
        ok &= j < num - 1
    x = torch.arange(w).view(1, 1, 1, w)
    if lr_check:
        guard = min(lr_threshold, num - 1)
        right_min = torch.full((b, 1, h, w), inv, dtype=vol.dtype)
        for jj, d in enumerate(ds):
            right_min[..., : w - d] = torch.minimum(right_min[..., : w - d], vol[:, jj : jj + 1, :, d:])
        near = best.clone()
        for dj in range(-guard, guard + 1):
            # cost_right(x - d, d - dj) = vol[j + dj] at column x - dj (_INVALID outside the volume)
            moved = torch.full_like(vol, inv)
            if dj >= 0:
                moved[..., dj:] = vol[..., : w - dj]
            else:
                moved[..., :dj] = vol[..., -dj:]
            jn = j + dj
            inside = (jn >= 0) & (jn < num)
            near = torch.minimum(near, torch.where(inside, moved.gather(1, jn.clamp(0, num - 1)), inv))
        xr = (x - (max_d - 1 - j)).clamp_min(0)
        ok &= near <= right_min.gather(3, xr)
    if uniqueness_ratio > 0:
        knocked = vol.scatter(1, torch.cat([jm, j, jp], 1), inv)
        ok &= knocked.amin(1, keepdim=True).float() > best.float() * (1 + uniqueness_ratio)
    c_level = round(255.0 * scale * cap)
    texture = (lq - c_level).abs().unfold(2, block, 1).sum(-1).unfold(3, block, 1).sum(-1)
    ok &= texture.to(torch.int16) >= texture_threshold * block * block * 255.0 * scale
    opts = {"subpixel": subpixel, "subpixel_fit": subpixel_fit, "cost_floor": 1e-3}
    disparity, variance = torch.empty(b, 1, h, w), torch.empty(b, 1, h, w)
    costs = torch.cat([c_plus, c_minus], 1).to(torch.int16)
    fast._tail(j, costs, best.to(torch.int16), ok, inner, max_d, 1.0 / (255.0 * scale), float(block * block), opts,
               (disparity, variance))
    return disparity, ok, variance


@pytest.mark.parametrize("kw", [
    {}, {"block": 5}, {"block": 3, "lr_threshold": 3}, {"min_d": 2}, {"lr_check": False}, {"uniqueness_ratio": 0.0},
    {"lr_threshold": 2, "subpixel_fit": "parabola"}, {"block": 1, "lr_threshold": 0},
])
def test_integer_path_equals_plain_reference(pair, kw, monkeypatch):
    # bit for bit: bands, the stored volume, the running minimum and the gathers change nothing
    left, right, _ = pair
    left, right = _u8(left), _u8(right)
    max_d = 16
    ref = _reference(left, right, max_d, **kw)
    opts = {"subpixel": True, "subpixel_fit": kw.get("subpixel_fit", "equiangular"),
            "lr_check": kw.get("lr_check", True), "lr_threshold": kw.get("lr_threshold", 1),
            "uniqueness_ratio": kw.get("uniqueness_ratio", 0.15), "cost_floor": 1e-3, "texture_threshold": 0.004}
    block = kw.get("block", 9)
    scale = fast.int_scale(block, 31.0 / 255.0)
    monkeypatch.setattr(fast, "_BAND_ELEMENTS", 2 * 13 * 100)  # several bands, the last one shorter
    # planes built 3 at a time for the default window (B = 2, 12 + 8 rows, 88 columns; 16 = 5 * 3 + 1)
    monkeypatch.setattr(fast, "_STEP_ELEMENTS", 3 * 2 * 20 * 88)
    out = fast.match_sad_int(left, right, max_d, kw.get("min_d", 0), block, 31.0 / 255.0, scale, opts)
    assert ref[1].float().mean() > 0.05  # not a vacuous comparison (1x1 windows: ~9 % valid)
    assert torch.equal(out[1], ref[1])
    assert torch.equal(out[0], ref[0])
    assert torch.equal(out[2], ref[2])


def test_gradient_requests_take_the_float_path(pair):
    left, right, _ = pair
    left = left[:1].clone().requires_grad_(True)
    out = match_stereo(left, right[:1], 16, differentiable=True)
    out.disparity.sum().backward()
    assert left.grad is not None and torch.isfinite(left.grad).all()


def test_large_block_falls_back_to_the_float_path():
    left, right, gt = planar_pair(batch=1, height=40, width=64, seed=3, base=5.0, slope_x=0.0, slope_y=0.0)
    out = match_stereo(left, right, 12, block_size=25)  # int_scale(25) == 0
    assert out.valid.float().mean() > 0.2
    assert (out.disparity[out.valid] - 5.0).abs().max() < 0.5


def test_threaded_strips_equal_serial(pair, monkeypatch):
    # with several torch threads the strips run in a thread pool (one torch thread each)
    left, right, _ = pair
    monkeypatch.setattr(fast, "_BAND_ELEMENTS", 1)  # several bands per worker
    ref = match_stereo(left, right, 16)  # the stereo tests run torch single-threaded (conftest)
    torch.set_num_threads(2)
    try:
        out = match_stereo(left, right, 16)
        assert torch.get_num_threads() == 2  # restored after the pool
    finally:
        torch.set_num_threads(1)
    assert torch.equal(ref.valid, out.valid) and torch.equal(ref.disparity, out.disparity)
    assert torch.equal(ref.variance, out.variance)
