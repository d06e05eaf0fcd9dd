"""Tests of egorefine.stereo.sgm against a naive scanline reference."""

from __future__ import annotations

import pytest
import torch

from egorefine.core import ValueRangeError, _jit, dispatch
from egorefine.stereo import _sgm_numba, match_stereo, sgm_aggregate
from egorefine.stereo.band import match_sgm_band
from egorefine.stereo.sgm import sgm_stripes

from ._synthetic import planar_pair


def _naive_path(vol, p1, p2, dy, dx):
    """Literal SGM recursion along direction (dy, dx), pixel by pixel."""
    b, num, h, w = vol.shape
    out = torch.zeros_like(vol)
    ys = range(h) if dy >= 0 else range(h - 1, -1, -1)
    xs = range(w) if dx >= 0 else range(w - 1, -1, -1)
    for y in ys:
        for x in xs:
            py, px = y - dy, x - dx
            if not (0 <= py < h and 0 <= px < w) or (dy == 0 and dx == 0):
                out[:, :, y, x] = vol[:, :, y, x]
                continue
            prev = out[:, :, py, px]
            m = prev.min(dim=1, keepdim=True).values
            cands = [prev, m.expand_as(prev) + p2]
            cands.append(torch.cat([prev[:, :1] + 1e9, prev[:, :-1] + p1], dim=1))
            cands.append(torch.cat([prev[:, 1:] + p1, prev[:, -1:] + 1e9], dim=1))
            out[:, :, y, x] = vol[:, :, y, x] + torch.stack(cands).min(dim=0).values - m
    return out


def test_sgm_matches_naive_reference():
    gen = torch.Generator().manual_seed(0)
    vol = torch.rand(2, 5, 6, 7, generator=gen, dtype=torch.float64)
    p1, p2 = 0.1, 0.4
    dirs4 = [(0, 1), (0, -1), (1, 0), (-1, 0)]
    ref4 = sum(_naive_path(vol, p1, p2, dy, dx) for dy, dx in dirs4) / 4
    assert torch.allclose(sgm_aggregate(vol, p1, p2, 4), ref4)
    dirs8 = dirs4 + [(1, 1), (1, -1), (-1, 1), (-1, -1)]
    ref8 = sum(_naive_path(vol, p1, p2, dy, dx) for dy, dx in dirs8) / 8
    assert torch.allclose(sgm_aggregate(vol, p1, p2, 8), ref8)


def test_three_paths_are_horizontal_and_top_down_per_stripe():
    """3 paths: left-right, right-left and top-down, the top-down one restarted above each stripe of rows
    (sgm_stripes), each row's sum divided by 3; one stripe below 240 rows, two at 250."""
    gen = torch.Generator().manual_seed(4)
    p1, p2 = 0.1, 0.4
    small = torch.rand(1, 4, 9, 7, generator=gen, dtype=torch.float64)
    ref = sum(_naive_path(small, p1, p2, dy, dx) for dy, dx in [(0, 1), (0, -1), (1, 0)]) / 3
    assert torch.allclose(sgm_aggregate(small, p1, p2, 3), ref)
    tall = torch.rand(1, 3, 250, 4, generator=gen, dtype=torch.float64)
    stripes = sgm_stripes(250)
    assert [(a, b) for a, b, _ in stripes] == [(0, 125), (125, 250)] and stripes[1][2] < 125
    top_down = torch.cat([_naive_path(tall[:, :, start:stop], p1, p2, 1, 0)[:, :, y0 - start:]
                          for y0, stop, start in stripes], dim=2)
    ref = (_naive_path(tall, p1, p2, 0, 1) + _naive_path(tall, p1, p2, 0, -1) + top_down) / 3
    out = sgm_aggregate(tall, p1, p2, 3)
    assert torch.allclose(out, ref)
    # the restart matters (a path through the whole height differs in the second stripe), if only a little
    whole = (_naive_path(tall, p1, p2, 0, 1) + _naive_path(tall, p1, p2, 0, -1) + _naive_path(tall, p1, p2, 1, 0)) / 3
    assert torch.allclose(out[:, :, :125], whole[:, :, :125]) and not torch.equal(out, whole)


def test_sgm_smooths_a_noisy_winner():
    # a constant true disparity with one outlier column of costs: SGM restores the winner there
    vol = torch.ones(1, 6, 8, 8)
    vol[:, 2] = 0.0
    vol[:, :, 4, 4] = 1.0
    vol[:, 4, 4, 4] = 0.8  # spurious, weak minimum at one pixel
    assert vol.argmin(1)[0, 4, 4] == 4
    assert sgm_aggregate(vol, 0.1, 0.5, 4).argmin(1)[0, 4, 4] == 2


def test_sgm_gradcheck():
    gen = torch.Generator().manual_seed(1)
    vol = torch.rand(1, 4, 4, 5, generator=gen, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda v: sgm_aggregate(v, 0.05, 0.3, 8), (vol,), fast_mode=True)
    tall = torch.rand(1, 2, 245, 2, generator=gen, dtype=torch.float64).requires_grad_()  # two stripes
    assert torch.autograd.gradcheck(lambda v: sgm_aggregate(v, 0.05, 0.3, 3), (tall,), fast_mode=True)


# --- the compiled CPU path (egorefine.stereo._sgm_numba) against the torch path ---------------------------------

_OPTS = {"subpixel": True, "subpixel_fit": "equiangular", "lr_check": True, "lr_threshold": 1,
         "uniqueness_ratio": 0.15, "differentiable": False, "soft_radius": 2, "temperature": 0.2, "cost_floor": 0.1}


def _torch_reference(left, right, max_d, min_d, block, window, p1, p2, paths, opts):
    """The torch path of match_stereo's SGM branch, before texture check and zeroing: (volume, d, valid, var)."""
    from egorefine.stereo.cost import _Features, strip_volume
    from egorefine.stereo.matching import _select

    feat = _Features(left, right, "census", block, max_d, window, True, 31 / 255)
    raw = strip_volume(feat, 0, left.shape[-2], min_d)
    vol = sgm_aggregate(raw, p1, p2, paths)
    ref = vol.clone()  # _select encodes its input in place
    return (ref, *_select(vol, max_d, opts, raw))


def _random_pair(b, h, w, seed, shift=3):
    gen = torch.Generator().manual_seed(seed)
    left = torch.rand(b, 1, h, w, generator=gen)
    right = 0.8 * torch.roll(left, -shift, dims=-1) + 0.2 * torch.rand(b, 1, h, w, generator=gen)
    return left, right


needs_numba = pytest.mark.skipif(not _sgm_numba.AVAILABLE, reason="numba not installed")


@needs_numba
@pytest.mark.parametrize(("max_d", "min_d", "block", "window", "p1", "p2", "paths", "fit", "threads", "max_raw"), [
    (8, 0, 5, 5, 12.5, 75.0, 4, "equiangular", 2, None),
    (12, 3, 3, 7, 0.37, 2.1, 8, "parabola", 1, None),  # penalties not exact in float32, 48-bit census, diagonals
    (9, 0, 7, 3, 4.0, 9.0, 4, "equiangular", 3, None),  # odd band split, odd number of candidates
    # match_stereo's census defaults (x block**2), with its raw-cost check (a bound not exact in float32)
    (8, 0, 5, 7, 800.0, 3200.0, 4, "equiangular", 2, 0.35 * 48 * 25 + 0.1),
    (10, 0, 3, 5, 96.0, 384.0, 8, "parabola", 2, 0.3 * 24 * 9),
    (36, 2, 3, 5, 96.0, 384.0, 4, "parabola", 2, None),  # over 32 candidates: 4 rows per horizontal band
])
def test_numba_equals_torch_path(max_d, min_d, block, window, p1, p2, paths, fit, threads, max_raw):
    left, right = _random_pair(2, 21, 37, seed=max_d, shift=min_d + 3)
    opts = {**_OPTS, "subpixel_fit": fit, "scale": float(block * block), "min_disparity": min_d,
            "max_raw_cost": max_raw}
    ref_vol, ref_d, ref_v, ref_var = _torch_reference(left, right, max_d, min_d, block, window, p1, p2, paths, opts)
    d, v, var, vol = _sgm_numba.census_sgm_select(left, right, max_d, min_d, block, window, p1, p2, paths, opts,
                                                  threads=threads, return_volume=True)
    # the same float32 operations in the same order: equal bit for bit, not just close
    assert torch.equal(vol, ref_vol)
    assert torch.equal(d, ref_d) and torch.equal(v, ref_v) and torch.equal(var, ref_var)
    assert 0.3 < v.float().mean() < 1.0  # the checks pass some pixels and reject others


@needs_numba
@pytest.mark.parametrize(("p1", "p2", "threads"), [(96.0, 384.0, 2), (96.0, 384.0, 1), (0.37, 2.1, 3)])
def test_numba_three_paths_equal_torch_path_across_stripes(p1, p2, threads):
    """The 3-path pass down each stripe (int16 and float32 path costs) against the torch path, at a height of four
    stripes; its volume (returned for this test) too."""
    left, right = _random_pair(1, 370, 40, seed=11)
    opts = {**_OPTS, "scale": 9.0, "min_disparity": 0, "max_raw_cost": None}
    assert len(sgm_stripes(370)) == 4
    ref_vol, ref_d, ref_v, ref_var = _torch_reference(left, right, 12, 0, 3, 5, p1, p2, 3, opts)
    d, v, var, vol = _sgm_numba.census_sgm_select(left, right, 12, 0, 3, 5, p1, p2, 3, opts, threads=threads,
                                                  return_volume=True)
    assert torch.equal(vol, ref_vol)
    assert torch.equal(d, ref_d) and torch.equal(v, ref_v) and torch.equal(var, ref_var)
    assert 0.3 < v.float().mean() < 1.0


@needs_numba
@pytest.mark.parametrize(("paths", "threads"), [(3, 1), (3, 2), (4, 2)])
def test_match_stereo_compiled_equals_torch_path_with_its_checks(paths, threads, monkeypatch):
    """match_stereo's whole compiled census + SGM path (with 3 paths the left-right and texture checks run in each
    stripe's job) against the torch path: equal maps, on a pair of four stripes with a flat band the texture check
    rejects and a speckle filter."""
    left, right = _random_pair(1, 370, 44, seed=7)
    left[..., 150:190, :] = 0.5  # flat rows: texture 0 (their matches are not valid on either path)
    right[..., 150:190, :] = 0.5
    kw = {"cost": "census", "aggregation": "sgm", "block_size": 5, "sgm_paths": paths, "speckle_size": 20,
          "speckle_range": 1.0}
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    compiled = match_stereo(left, right, 12, **kw)
    monkeypatch.setattr(dispatch, "ENABLED", False)
    reference = match_stereo(left, right, 12, **kw)
    for a, b in zip(compiled, reference, strict=True):
        assert torch.equal(a, b)
    assert not compiled.valid[..., 155:185, :].any() and 0.3 < compiled.valid.float().mean() < 1.0


def test_sgm_paths_choices():
    left, right = _random_pair(1, 20, 30, seed=2)
    with pytest.raises(ValueRangeError, match="sgm_paths"):
        match_stereo(left, right, 8, cost="census", aggregation="sgm", sgm_paths=5)
    out = match_stereo(left, right, 8, cost="census", aggregation="sgm", sgm_paths=3)
    assert out.disparity.shape == (1, 1, 20, 30) and bool(out.valid.any())
    with pytest.raises(ValueRangeError, match="band matcher"):
        match_sgm_band(left, right, torch.full((1, 1, 20, 30), 3.0), 8, width=4, sgm_paths=3)


@needs_numba
def test_match_stereo_numba_equals_torch_on_rendered_pair(monkeypatch):
    left, right, _ = planar_pair(1, 40, 72, seed=3)
    kw = {"cost": "census", "aggregation": "sgm", "block_size": 5}
    fast = match_stereo(left, right, 16, **kw)
    monkeypatch.setattr(_jit, "AVAILABLE", False)
    slow = match_stereo(left, right, 16, **kw)
    for a, b in zip(fast, slow, strict=True):
        assert torch.equal(a, b)
    assert fast.valid.float().mean() > 0.7


@needs_numba
def test_numba_batch_item_equals_alone():
    left, right = _random_pair(2, 18, 30, seed=7)
    kw = {"cost": "census", "aggregation": "sgm", "block_size": 3}
    both = match_stereo(left, right, 8, **kw)
    for i in range(2):
        alone = match_stereo(left[i : i + 1], right[i : i + 1], 8, **kw)
        for a, b in zip(both, alone, strict=True):
            assert torch.equal(a[i : i + 1], b)


def test_torch_path_when_numba_is_off_or_not_applicable(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("the compiled path ran")

    left, right = _random_pair(1, 12, 20, seed=2)
    kw = {"cost": "census", "aggregation": "sgm", "block_size": 3}
    monkeypatch.setattr(_sgm_numba, "census_sgm_select", refuse)
    monkeypatch.setattr(_jit, "AVAILABLE", False)
    out = match_stereo(left, right, 6, **kw)
    assert out.disparity.shape == (1, 1, 12, 20)
    monkeypatch.setattr(_jit, "AVAILABLE", True)
    match_stereo(left.double(), right.double(), 6, **kw)  # float64: torch path
    match_stereo(left, right, 6, **{**kw, "cost": "sad"})  # SGM of other costs: torch path
    with pytest.raises(AssertionError, match="compiled path"):
        match_stereo(left, right, 6, **kw)


@needs_numba
def test_numba_textureless_pair_is_all_invalid_without_nan():
    flat = torch.full((1, 1, 16, 24), 0.5)
    out = match_stereo(flat, flat, 8, cost="census", aggregation="sgm", block_size=5)
    assert not out.valid.any()
    assert torch.isfinite(out.disparity).all() and torch.isfinite(out.variance).all()
    _, v, var, vol = _sgm_numba.census_sgm_select(flat, flat, 8, 0, 5, 5, 12.5, 75.0, 4,
                                                  {**_OPTS, "scale": 25.0, "min_disparity": 0}, return_volume=True)
    assert torch.isfinite(vol).all() and torch.isfinite(var).all()


def _sgm_buffer_sizes() -> set[int]:
    """Sizes of the SGM path's kept buffers on this thread (core._jit.scratch, names "sgm.*")."""
    from egorefine.core import _jit

    return {a.size for name, a in getattr(_jit._scratch, "arrays", {}).items() if name.startswith("sgm.")}


@needs_numba
def test_reused_work_volumes_do_not_leak_between_calls():
    # The work volumes are kept per thread and reused by the next call that fits in them: a call on other images
    # (and on a smaller size, which takes a view of the same buffers) in between must not change a result.
    kw = {"cost": "census", "aggregation": "sgm", "block_size": 5}
    _sgm_numba.release_workspace()
    left, right = _random_pair(1, 20, 36, seed=11)
    first = match_stereo(left, right, 8, **kw)
    assert _sgm_buffer_sizes() == {20 * 36 * 8}
    other_l, other_r = _random_pair(1, 20, 36, seed=12, shift=5)
    match_stereo(other_l, other_r, 8, **kw)
    match_stereo(*_random_pair(1, 15, 28, seed=13), 6, **kw)  # a smaller size: views of the same buffers
    assert _sgm_buffer_sizes() == {20 * 36 * 8}
    match_stereo(*_random_pair(1, 15, 28, seed=13), 16, **kw)  # a larger volume: the buffers are replaced
    assert _sgm_buffer_sizes() == {15 * 28 * 16}
    again = match_stereo(left, right, 8, **kw)
    for a, b in zip(first, again, strict=True):
        assert torch.equal(a, b)
    _sgm_numba.release_workspace()
    assert _sgm_buffer_sizes() == set()


@needs_numba
def test_raw_cost_check_rejects_what_matches_nothing():
    # two unrelated noise images: the default penalties make regions that agree left to right and pass the speckle
    # filter; the opt-in raw-cost check (census_max_distance) keeps them out
    g = torch.Generator().manual_seed(0)
    left, right = torch.rand(1, 1, 120, 160, generator=g), torch.rand(1, 1, 120, 160, generator=g)
    kw = {"cost": "census", "aggregation": "sgm", "block_size": 5}
    assert match_stereo(left, right, 48, **kw).valid.float().mean() > 0.05
    assert match_stereo(left, right, 48, census_max_distance=0.45, **kw).valid.float().mean() < 0.005
    # a textured plane keeps its matches
    pl, pr, _ = planar_pair(1, 40, 72, seed=3)
    assert match_stereo(pl, pr, 16, census_max_distance=0.35, **kw).valid.float().mean() > 0.7


@pytest.mark.parametrize("block", [1, 5, 9])
def test_compiled_texture_check_equals_the_torch_one(block):
    """The compiled matchers' texture check (egorefine.stereo._texture_numba) makes the float path's decisions pixel
    for pixel, also at values on the threshold (an image of 1/255 steps, as 8-bit input gives), and clears the maps
    where it fails; the same on one thread and on two (bands of rows)."""
    from egorefine.stereo._texture_numba import AVAILABLE, mask_untextured
    from egorefine.stereo.cost import box_mean_same, prefilter_xsobel

    if not AVAILABLE:
        pytest.skip("numba is not installed")
    g = torch.Generator().manual_seed(block)
    grey = (torch.rand(2, 1, 23, 31, generator=g) * 8).round() / 255.0
    grey[0, :, :, :10] = 0.5  # a flat region: texture 0
    cap, threshold = 31.0 / 255.0, 0.004
    textured = box_mean_same(prefilter_xsobel(grey, cap).abs(), block) >= threshold
    matched = torch.rand(2, 1, 23, 31, generator=g) > 0.2
    for threads in (1, 2):
        d, var = torch.rand(2, 1, 23, 31, generator=g) + 1.0, torch.rand(2, 1, 23, 31, generator=g) + 1.0
        out = mask_untextured((d.clone(), matched.clone(), var.clone()), grey, block, cap, threshold, 99.0,
                              threads=threads)
        keep = matched & textured
        assert torch.equal(out[1], keep)
        assert torch.equal(out[0], torch.where(keep, d, 0.0)) and torch.equal(out[2], torch.where(keep, var, 99.0))
    assert textured.any() and not textured[0, :, :, :8 - block // 2].any()
