"""The compiled CPU form of the whole solve (egorefine.motion._solve_numba; exact, robust and linear) against the
torch path, which stays the reference (GPU, autograd)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from motion_tracks import make_tracks

import egorefine.motion.solve as solve
from egorefine.core import DTypeError, ValueRangeError, dispatch
from egorefine.geometry import make_intrinsics, motion_to_twist, project, transform_points, twist_to_motion, unproject
from egorefine.motion import _solve_numba, solve_ego_motion

pytestmark = pytest.mark.skipif(not _solve_numba.AVAILABLE, reason="numba not installed")
TWISTS = [[0.02, -0.01, 0.1, 0.005, -0.01, 0.003], [0.0, 0.03, 0.08, -0.004, 0.002, 0.01]]
F64 = torch.float64
# the compiled path runs in float64: it differs from the torch path by that path's rounding
TOL = {torch.float32: 2e-5, F64: 1e-9}
# The float32 torch path's LM also takes its discrete steps (accept a step, stop) on float32 costs: an input one
# float32 step away (another CPU's rounding upstream) can end it an iteration off the float64 optimum, several times
# TOL in the motion and ~1e-3 in a robust weight. Motion within SOLVE_TOL, weights and rms within 20 SOLVE_TOL;
# float64 takes the same steps as the compiled path.
SOLVE_TOL = {torch.float32: 1e-4, F64: 1e-9}


def _both(monkeypatch, *args, **kw):
    """(compiled, torch path) results of the same call; the compiled path must have run."""
    calls = []
    real = _solve_numba.solve_compiled
    monkeypatch.setattr(_solve_numba, "solve_compiled", lambda *a, **k: calls.append(1) or real(*a, **k))
    compiled = solve_ego_motion(*args, **kw)
    assert calls, "the compiled solve did not run"
    monkeypatch.setattr(dispatch, "ENABLED", False)
    reference = solve_ego_motion(*args, **kw)
    monkeypatch.setattr(dispatch, "ENABLED", True)
    assert len(calls) == 1
    return compiled, reference


def _assert_same(a, r, dtype):
    tol = SOLVE_TOL[dtype]
    assert torch.equal(a.ok, r.ok) and torch.equal(a.num_inliers, r.num_inliers)
    assert torch.equal(a.weights > 0, r.weights > 0)
    torch.testing.assert_close(a.motion, r.motion, rtol=0, atol=tol)
    torch.testing.assert_close(a.weights, r.weights, rtol=0, atol=20 * tol)
    torch.testing.assert_close(a.rms, r.rms, rtol=0, atol=20 * tol)
    for x in a:
        assert x.dtype == r[0].dtype or x.dtype in (torch.bool, torch.long)
        assert not (x.is_floating_point() and x.isnan().any())
    # the twist is the SE(3) log of the motion (the torch path's float32 log loses ~1e-3 to cancellation near
    # 1e-3 rad, so the compiled twist is compared with the float64 log of its own motion)
    exact = motion_to_twist(a.motion.double())
    torch.testing.assert_close(a.twist.double(), torch.where(a.ok[:, None], exact, 0.0), rtol=0, atol=1e-6)
    if dtype == F64:
        torch.testing.assert_close(a.twist, r.twist, rtol=0, atol=tol)


def _args(tr):
    return tr.points_prev, tr.points_next, tr.disparity, tr.K, tr.baseline


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("kw", [{}, {"loss": "huber"}, {"loss": "l2", "iterations": 4}, {"iterations": 0},
                                {"scale": 0.5, "ransac_hypotheses": 16, "seed": 3, "ransac_threshold": 3.0},
                                {"method": "robust"}, {"method": "robust", "ransac_hypotheses": 8, "seed": 5}])
def test_compiled_equals_torch_path_per_point(monkeypatch, dtype, kw):
    tr = make_tracks(torch.tensor(TWISTS, dtype=dtype), num=300, noise=0.3, outliers=0.15, seed=4)
    w = torch.rand(2, 300, generator=torch.Generator().manual_seed(1), dtype=dtype) + 0.5
    w[:, ::7] = 0.0
    a, r = _both(monkeypatch, *_args(tr), weights=w, **kw)
    _assert_same(a, r, dtype)
    assert a.ok.all()
    assert (a.weights[~tr.inlier] == 0).float().mean() > 0.9  # the outlier tracks are rejected
    torch.testing.assert_close(a.motion, tr.motion, rtol=0, atol=5e-3 if kw.get("method") is None else 2e-2)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_compiled_linear_equals_torch_path(monkeypatch, dtype):
    # the paper's estimator (eq. 3): no outliers here, its first-order bias stays within 2 cm
    tr = make_tracks(torch.tensor(TWISTS, dtype=dtype), num=200, noise=0.3, seed=7)
    a, r = _both(monkeypatch, *_args(tr), method="linear")
    _assert_same(a, r, dtype)
    assert a.ok.all() and torch.equal(a.num_inliers, torch.full((2,), 200))
    torch.testing.assert_close(a.twist, r.twist, rtol=0, atol=TOL[dtype])
    torch.testing.assert_close(a.motion, tr.motion, rtol=0, atol=2e-2)


def _map_scene(dtype, B=2, num=400, seed=0, outliers=0.1):
    """A slanted plane (disparity affine in x, y, so bilinear samples are exact) with a nearer box (depth edges),
    an invalid block, NaN and zero disparities, and features partly outside the image."""
    H, W, f, base = 96, 128, 100.0, 0.1
    K = make_intrinsics(f, (W - 1) / 2, (H - 1) / 2, B, dtype=dtype)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    disp = (3 + 0.02 * xs + 0.01 * ys).expand(B, 1, H, W).clone()
    disp[..., 30:60, 50:90] += 4.0
    disp[..., 70:74, 10:40] = float("nan")
    disp[..., 80:84, 90:120] = 0.0
    valid = torch.ones(B, 1, H, W, dtype=torch.bool)
    valid[..., 5:15, 5:30] = False
    gen = torch.Generator().manual_seed(seed)
    pts = torch.rand(B, num, 2, generator=gen, dtype=dtype) * torch.tensor([W + 6.0, H + 6.0], dtype=dtype) - 3
    pts[:, :8] = pts[:, :8].round()  # on pixel centres, the last row and column included
    pts[:, 8] = torch.tensor([W - 1.0, H - 1.0], dtype=dtype)
    d, usable = solve._disparity_at(pts, disp, valid)
    Z = f * base / torch.where(usable, d, torch.full_like(d, 5.0))
    twist = torch.tensor(TWISTS[:B], dtype=dtype)
    nxt = project(transform_points(twist_to_motion(twist), unproject(pts, Z, K)), K)
    nxt = nxt + 0.2 * torch.randn(B, num, 2, generator=gen, dtype=dtype)
    bad = torch.rand(B, num, generator=gen) < outliers
    nxt = torch.where(bad[..., None], nxt + 15.0, nxt)
    return pts, nxt, disp, K, torch.full((B,), base, dtype=dtype), valid, usable, twist


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_compiled_equals_torch_path_on_a_map(monkeypatch, dtype):
    pts, nxt, disp, K, base, valid, usable, twist = _map_scene(dtype)
    assert 0.3 < usable.float().mean() < 0.9  # the usability rules matter here
    for v, method in ((valid, "exact"), (None, "exact"), (valid, "robust"), (valid, "linear")):
        a, r = _both(monkeypatch, pts, nxt, disp, K, base, valid_prev=v, method=method)
        _assert_same(a, r, dtype)
        assert a.ok.all()
        if method != "linear":  # (the outliers pull the linear fit)
            bound = 5e-3 if method == "exact" else 2e-2
            torch.testing.assert_close(a.motion, twist_to_motion(twist), rtol=0, atol=bound)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_sampling_equals_disparity_at(dtype):
    # the kernel's usability decisions are the torch path's, sample by sample (spreads of exactly 1 px included)
    pts, _, disp, _, _, valid, _, _ = _map_scene(dtype, B=1, num=3000, seed=5)
    disp[..., 20:28, 100:110] = torch.tensor([2.0, 3.0, 2.5, 3.5], dtype=dtype).repeat(2)[None, :, None]
    nd = np.float32 if dtype == torch.float32 else np.float64
    for v in (valid, None):
        ref, ref_usable = solve._disparity_at(pts, disp, v)
        out, usable = np.empty(3000), np.empty(3000, np.bool_)
        vv = np.ones(1, np.bool_) if v is None else v.reshape(-1).numpy()
        _solve_numba._sample(pts[0].numpy().astype(nd), disp.reshape(-1).numpy(), vv, v is not None, 96, 128,
                             solve._MAX_DISPARITY_SPREAD, out, usable)
        assert torch.equal(torch.from_numpy(usable), ref_usable[0])
        torch.testing.assert_close(torch.from_numpy(out).to(dtype), ref[0], rtol=TOL[dtype], atol=0)


def test_map_equals_per_point_disparity():
    pts, nxt, disp, K, base, valid, _, _ = _map_scene(torch.float32)
    d, usable = solve._disparity_at(pts, disp.double(), valid)
    per_point = torch.where(usable, d, torch.zeros_like(d)).float()
    a = solve_ego_motion(pts, nxt, disp, K, base, valid_prev=valid)
    b = solve_ego_motion(pts, nxt, per_point, K, base)
    assert torch.equal(a.ok, b.ok) and torch.equal(a.weights > 0, b.weights > 0)
    torch.testing.assert_close(a.motion, b.motion, rtol=0, atol=1e-5)


def test_degenerate_items_flag_not_nan(monkeypatch):
    tr = make_tracks(torch.tensor(TWISTS), num=60, noise=0.2, seed=2)
    w = torch.ones(2, 60)
    w[1] = 0.0  # item 1: no feature
    for method in ("linear", "robust"):
        a, r = _both(monkeypatch, *_args(tr), weights=w, method=method)
        _assert_same(a, r, torch.float32)
        assert a.ok.tolist() == [True, False]
    a, r = _both(monkeypatch, *_args(tr), weights=w)
    _assert_same(a, r, torch.float32)
    assert a.ok.tolist() == [True, False]
    assert torch.equal(a.motion[1], torch.eye(4)) and not a.twist[1].any() and not a.weights[1].any()
    assert a.num_inliers[1] == 0 and a.rms[1] == 0
    few = tr.disparity.clone()
    few[:, 2:] = float("nan")  # only 2 usable features (and min_features 3)
    a, r = _both(monkeypatch, tr.points_prev, tr.points_next, few, tr.K, tr.baseline)
    _assert_same(a, r, torch.float32)
    assert not a.ok.any()
    a, r = _both(monkeypatch, *_args(tr), min_features=61)
    _assert_same(a, r, torch.float32)
    assert not a.ok.any()
    # no features at all: both paths give every item's fallback
    empty = torch.zeros(2, 0, 2)
    for method in ("exact", "robust", "linear"):
        for compiled in (True, False):
            monkeypatch.setattr(dispatch, "ENABLED", compiled)
            e = solve_ego_motion(empty, empty, torch.zeros(2, 0), tr.K, tr.baseline, method=method)
            assert not e.ok.any() and torch.equal(e.motion, torch.eye(4).expand(2, 4, 4))
            assert e.weights.shape == (2, 0) and not e.twist.any() and not e.num_inliers.any()


def test_batch_item_equals_alone():
    pts, nxt, disp, K, base, valid, _, _ = _map_scene(torch.float32)
    w = torch.ones(2, pts.shape[1])
    w[1, 2:] = 0.0  # item 1 fails (2 features), item 0 does not
    both = solve_ego_motion(pts, nxt, disp, K, base, weights=w, valid_prev=valid)
    assert both.ok.tolist() == [True, False]
    for i in range(2):
        s = slice(i, i + 1)
        alone = solve_ego_motion(pts[s], nxt[s], disp[s], K[s], base[s], weights=w[s], valid_prev=valid[s])
        for x, y in zip(both, alone, strict=True):
            assert torch.equal(x[s], y)


def test_mixed_input_dtypes_follow_the_points():
    tr = make_tracks(torch.tensor(TWISTS), num=80, noise=0.2, seed=6)
    a = solve_ego_motion(tr.points_prev, tr.points_next, tr.disparity.double(), tr.K.double(), tr.baseline.double(),
                         weights=torch.ones(2, 80, dtype=F64))
    b = solve_ego_motion(*_args(tr))
    assert a.motion.dtype == torch.float32
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x, y)


def test_torch_path_where_compiled_does_not_apply(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("the compiled solve ran")

    tr = make_tracks(torch.tensor(TWISTS[:1], dtype=F64), num=60, noise=0.2, seed=1)
    monkeypatch.setattr(_solve_numba, "solve_compiled", refuse)
    points = tr.points_next.clone().requires_grad_(True)
    res = solve_ego_motion(tr.points_prev, points, tr.disparity, tr.K, tr.baseline)  # a gradient is wanted
    res.motion.sum().backward()
    assert torch.isfinite(points.grad).all()
    with pytest.raises(DTypeError, match="weights: expected float32 or float64"):  # refused at the door
        solve_ego_motion(*_args(tr), weights=torch.ones(1, 60, dtype=torch.float16))
    monkeypatch.setattr(dispatch, "ENABLED", False)  # the torch path with the torch LM, for comparisons
    solve_ego_motion(*_args(tr))
    monkeypatch.setattr(dispatch, "ENABLED", True)
    with pytest.raises(AssertionError, match="compiled solve"):
        solve_ego_motion(*_args(tr))


@pytest.mark.parametrize(("change", "match"), [
    ({"points_prev": float("nan")}, "points_prev"), ({"points_next": float("inf")}, "points_next"),
    ({"K": float("nan")}, "K"), ({"fx": 0.0}, "K"), ({"baseline": 0.0}, "baseline"), ({"weights": -1.0}, "weights"),
])  # fmt: skip
def test_bad_values_raise_the_torch_paths_errors(change, match):
    tr = make_tracks(torch.tensor(TWISTS), num=20, seed=1)
    args = dict(points_prev=tr.points_prev.clone(), points_next=tr.points_next.clone(), disparity_prev=tr.disparity,
                K=tr.K.clone(), baseline=tr.baseline.clone(), weights=torch.ones(2, 20))
    name, value = next(iter(change.items()))
    if name == "fx":
        args["K"][1, 0, 0] = value
    else:
        args[name].view(-1)[-1] = value
    with pytest.raises(ValueRangeError, match=match):
        solve_ego_motion(**args)
