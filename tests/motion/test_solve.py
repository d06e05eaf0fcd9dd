"""Tests of egorefine.motion.solve: ego-motion from tracks against known truth (synthetic scenes)."""

from __future__ import annotations

import math

import pytest
import torch
from motion_tracks import make_tracks

from egorefine.core import DTypeError, ShapeError, ValueRangeError
from egorefine.geometry import make_intrinsics, project, se3_inverse, se3_log, transform_points, unproject
from egorefine.motion import EgoMotion, EgoMotionSolver, motion_field, solve_ego_motion

F64 = torch.float64
METHODS = ["linear", "robust", "exact"]
CASES = {
    "translation": [0.02, -0.01, 0.1, 0.0, 0.0, 0.0],
    "rotation": [0.0, 0.0, 0.0, 0.01, -0.02, 0.005],
    "combined": [0.02, -0.01, 0.1, 0.005, -0.01, 0.003],
    "zero": [0.0] * 6,
}


def _errors(res: EgoMotion, truth: torch.Tensor) -> tuple[float, float]:
    """Translation error (m) and rotation error (deg) of the worst item, in float64 (log map, not acos)."""
    rel = se3_inverse(res.motion.double()) @ truth.double()
    xi = se3_log(rel)
    t_err = (res.motion.double()[:, :3, 3] - truth.double()[:, :3, 3]).norm(dim=-1).max().item()
    return t_err, math.degrees(xi[:, 3:].norm(dim=-1).max().item())


def _solve(tr, method, **kw):
    return solve_ego_motion(tr.points_prev, tr.points_next, tr.disparity, tr.K, tr.baseline, method=method, **kw)


# --------------------------------------------------------------------------- smoke and shapes


@pytest.mark.parametrize("method", METHODS)
def test_smoke_shapes(method):
    tr = make_tracks(torch.tensor([CASES["combined"]] * 2), num=30)
    res = _solve(tr, method)
    assert isinstance(res, EgoMotion)
    assert res.motion.shape == (2, 4, 4) and res.twist.shape == (2, 6)
    assert res.weights.shape == (2, 30) and res.ok.shape == (2,) and res.ok.dtype == torch.bool
    assert res.num_inliers.shape == (2,) and res.rms.shape == (2,)
    assert res.ok.all()
    torch.testing.assert_close(res.motion, EgoMotionSolver(method)(*_args(tr)).motion)


def _args(tr):
    return tr.points_prev, tr.points_next, tr.disparity, tr.K, tr.baseline


@pytest.mark.parametrize("method", METHODS)
def test_twist_and_motion_agree(method):
    from egorefine.geometry import twist_to_motion

    tr = make_tracks(torch.tensor([CASES["combined"]], dtype=F64), num=50, noise=0.2)
    res = _solve(tr, method)
    torch.testing.assert_close(twist_to_motion(res.twist), res.motion, rtol=1e-9, atol=1e-9)


# --------------------------------------------------------------------------- accuracy against truth


@pytest.mark.parametrize("case", CASES)
def test_exact_noise_free_recovers_motion(case):
    tr = make_tracks(torch.tensor([CASES[case]], dtype=F64), num=100)
    t_err, r_err = _errors(_solve(tr, "exact"), tr.motion)
    assert t_err < 1e-6 and r_err < 1e-5
    tr32 = make_tracks(torch.tensor([CASES[case]]), num=100)
    t_err, r_err = _errors(_solve(tr32, "exact"), tr32.motion)
    assert t_err < 1e-5 and r_err < 1e-3  # float32: 10 um, 0.001 deg


def test_linear_solves_equation_3_exactly_on_model_flow():
    """Tracks made by eq. (2) itself: the normal equations of eq. (3) give the twist back to rounding."""
    tr = make_tracks(torch.tensor([CASES["combined"]], dtype=F64), num=40)
    Z = 400.0 * 0.1 / tr.disparity
    nxt = tr.points_prev + motion_field(tr.points_prev, Z, tr.K, tr.twist)
    res = solve_ego_motion(tr.points_prev, nxt, tr.disparity, tr.K, tr.baseline, method="linear")
    torch.testing.assert_close(res.twist, tr.twist, rtol=1e-9, atol=1e-10)
    assert res.rms.item() < 1e-8


@pytest.mark.parametrize("case", CASES)
def test_linear_noise_free_has_only_first_order_bias(case):
    """Eq. (2) is first order: its error on a finite step is second order in the motion, small but not zero."""
    tw = torch.tensor([CASES[case]], dtype=F64)
    t_err, r_err = _errors(_solve(make_tracks(tw, num=200), "linear"), make_tracks(tw, num=200).motion)
    t_half, _ = _errors(_solve(make_tracks(tw / 2, num=200), "linear"), make_tracks(tw / 2, num=200).motion)
    if case == "zero":
        assert t_err < 1e-12 and r_err < 1e-9
        return
    assert t_err < 6e-3 and r_err < 0.02  # ~3 mm on a 0.1 m step, depths 2-15 m
    assert t_half / t_err < 0.35  # halving the step roughly quarters the error (0.25)


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("seed", [0, 1])
def test_pixel_noise(case, seed):
    tw = torch.tensor([CASES[case]], dtype=F64)
    tr = make_tracks(tw, num=200, noise=0.3, seed=seed)
    t_err, r_err = _errors(_solve(tr, "exact"), tr.motion)
    assert t_err < 2.5e-3 and r_err < 0.03
    t_lin, _ = _errors(_solve(tr, "linear"), tr.motion)
    assert t_lin < 6e-3


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("seed", [0, 1])
def test_twenty_percent_outliers(case, seed):
    tw = torch.tensor([CASES[case]], dtype=F64)
    tr = make_tracks(tw, num=200, noise=0.3, outliers=0.2, seed=seed)
    t_lin, _ = _errors(_solve(tr, "linear"), tr.motion)
    assert t_lin > 1e-2  # the plain least squares is pulled away by the bad tracks ...
    robust = _solve(tr, "robust")
    t_rob, r_rob = _errors(robust, tr.motion)
    assert t_rob < 6e-3 and r_rob < 0.03  # ... RANSAC stays near the truth ...
    inlier_only = solve_ego_motion(*_args(tr), weights=tr.inlier.to(F64), method="linear")
    assert _errors(robust, inlier_only.motion)[0] < 1.5e-3  # ... and near eq. (3) on the true inliers alone ...
    exact = _solve(tr, "exact")
    t_ex, r_ex = _errors(exact, tr.motion)
    assert t_ex < 2.5e-3 and r_ex < 0.03  # ... and the SE(3) refinement removes the first-order bias.
    for res in (robust, exact):
        kept = res.weights > 0
        assert (kept & tr.inlier).sum() >= 0.97 * tr.inlier.sum()  # inliers kept
        assert (kept & ~tr.inlier).sum() <= 0.05 * (~tr.inlier).sum()  # outliers rejected
        assert res.ok.all()


def test_weights_downweight_features():
    tw = torch.tensor([CASES["combined"]], dtype=F64)
    tr = make_tracks(tw, num=200, outliers=0.3)
    res = solve_ego_motion(*_args(tr), weights=tr.inlier.to(F64), method="linear")
    assert _errors(res, tr.motion)[0] < 6e-3
    assert torch.equal(res.weights > 0, tr.inlier)


# --------------------------------------------------------------------------- disparity maps


def _plane_scene(dtype=F64, n=150):
    """A slanted plane: disparity affine in (x, y), so bilinear sampling of the map is exact."""
    H, W = 120, 160
    K = make_intrinsics(150.0, 79.5, 59.5, dtype=dtype)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    dmap = (4.0 + 0.02 * xs + 0.04 * ys)[None, None]
    gen = torch.Generator().manual_seed(5)
    pts = torch.rand(1, n, 2, generator=gen, dtype=dtype) * torch.tensor([W - 11.0, H - 11.0], dtype=dtype) + 5
    d = 4.0 + 0.02 * pts[..., 0] + 0.04 * pts[..., 1]
    bl = torch.tensor([0.1], dtype=dtype)
    from egorefine.geometry import twist_to_motion

    motion = twist_to_motion(torch.tensor([CASES["combined"]], dtype=dtype))
    nxt = project(transform_points(motion, unproject(pts, 150.0 * 0.1 / d, K)), K)
    return pts, nxt, dmap, d, K, bl, motion


@pytest.mark.parametrize("method", METHODS)
def test_disparity_map_equals_per_point(method):
    pts, nxt, dmap, d, K, bl, motion = _plane_scene()
    a = solve_ego_motion(pts, nxt, dmap, K, bl, method=method)
    b = solve_ego_motion(pts, nxt, d, K, bl, method=method)
    torch.testing.assert_close(a.motion, b.motion, rtol=1e-9, atol=1e-9)
    if method == "exact":
        assert _errors(a, motion)[0] < 1e-6


def test_valid_mask_nan_and_outside_points_get_zero_weight():
    pts, nxt, dmap, d, K, bl, motion = _plane_scene()
    valid = torch.ones_like(dmap, dtype=torch.bool)
    valid[..., :, :60] = False  # left part of the map invalid
    dmap = dmap.clone()
    dmap[..., 100:, :] = float("nan")  # bottom rows unknown
    pts = pts.clone()
    pts[0, :5] = torch.tensor([-3.0, 50.0], dtype=F64)  # outside the image
    res = solve_ego_motion(pts, nxt, dmap, K, bl, method="exact", valid_prev=valid)
    assert res.ok.all() and torch.isfinite(res.motion).all()
    bad = (pts[..., 0] < 60) | (pts[..., 1] > 99)  # bilinear: any invalid neighbour makes it unusable
    assert (res.weights[bad] == 0).all() and (res.weights[~bad] > 0).all()
    assert _errors(res, motion)[0] < 1e-6


# --------------------------------------------------------------------------- degenerate input


@pytest.mark.parametrize("method", METHODS)
def test_degenerate_cases_flag_and_identity(method):
    base = make_tracks(torch.tensor([CASES["combined"]] * 5, dtype=F64), num=40)
    pp, pn, d = base.points_prev.clone(), base.points_next.clone(), base.disparity.clone()
    w = torch.ones(5, 40, dtype=F64)
    # item 1: only 2 features
    w[1, 2:] = 0
    # item 2: all weights zero
    w[2] = 0
    # item 3: every feature on one 3-D line (rotation about it is unobservable)
    s = torch.linspace(0, 1, 40, dtype=F64)[:, None]
    line = torch.tensor([-1.0, -0.5, 4.0], dtype=F64) + s * torch.tensor([2.0, 0.8, 6.0], dtype=F64)
    from egorefine.geometry import twist_to_motion

    K1 = base.K[:1]
    pp[3] = project(line[None], K1)[0]
    pn[3] = project(transform_points(twist_to_motion(base.twist[:1]), line[None]), K1)[0]
    d[3] = 400.0 * 0.1 / line[:, 2]
    # item 4: black frame: no disparity anywhere
    d[4] = 0
    res = solve_ego_motion(pp, pn, d, base.K, base.baseline, w, method=method)
    assert res.ok.tolist() == [True, False, False, False, False]
    eye = torch.eye(4, dtype=F64).expand(4, 4, 4)
    assert torch.equal(res.motion[1:], eye) and torch.equal(res.twist[1:], torch.zeros(4, 6, dtype=F64))
    assert (res.weights[1:] == 0).all() and (res.num_inliers[1:] == 0).all()
    for t in res:
        assert torch.isfinite(t.double()).all()
    assert _errors(EgoMotion(*(t[:1] for t in res)), base.motion[:1])[0] < 6e-3


@pytest.mark.parametrize("method", METHODS)
def test_degenerate_gradients_finite(method):
    tr = make_tracks(torch.tensor([CASES["combined"]] * 2, dtype=F64), num=20, noise=0.1)
    w = torch.ones(2, 20, dtype=F64)
    w[1] = 0
    pp = tr.points_prev.clone().requires_grad_(True)
    pn = tr.points_next.clone().requires_grad_(True)
    d = tr.disparity.clone().requires_grad_(True)
    res = solve_ego_motion(pp, pn, d, tr.K, tr.baseline, w, method=method)
    (res.twist.sum() + res.motion.sum()).backward()
    for g in (pp.grad, pn.grad, d.grad):
        assert torch.isfinite(g).all()
    assert pp.grad[0].abs().sum() > 0  # the good item does get a gradient


# --------------------------------------------------------------------------- batch and gradients


@pytest.mark.parametrize("dtype", [F64, torch.float32])
@pytest.mark.parametrize("method", METHODS)
def test_batch_consistency(method, dtype):
    # Bit for bit: every product is batched the same way for one item as for several (no matrix-vector product
    # or matrix_exp, whose kernels round differently for a batch of one).
    tw = torch.tensor([CASES["combined"], CASES["rotation"], CASES["translation"]], dtype=dtype)
    tr = make_tracks(tw, num=80, noise=0.3, outliers=0.2, seed=3)
    w = torch.ones(3, 80, dtype=dtype)
    w[1, 40:] = 0  # a different feature count in one item
    full = solve_ego_motion(*_args(tr), w, method=method)
    for b in range(3):
        one = solve_ego_motion(
            tr.points_prev[b : b + 1], tr.points_next[b : b + 1], tr.disparity[b : b + 1], tr.K[b : b + 1],
            tr.baseline[b : b + 1], w[b : b + 1], method=method,
        )  # fmt: skip
        for x, y in zip(full, one, strict=True):
            assert torch.equal(x[b : b + 1], y)


def test_gradcheck_linear_solve():
    tr = make_tracks(torch.tensor([CASES["combined"]], dtype=F64), num=6, noise=0.5)

    def fn(pp, pn, d):
        return solve_ego_motion(pp, pn, d, tr.K, tr.baseline, method="linear").twist

    args = tuple(t.clone().requires_grad_(True) for t in (tr.points_prev, tr.points_next, tr.disparity))
    assert torch.autograd.gradcheck(fn, args)


def test_gradcheck_exact_solve():
    """Two LM steps from the robust start (far from convergence, each step is clearly accepted:
    near convergence the accept test compares costs equal to rounding and is not differentiable)."""
    tr = make_tracks(torch.tensor([CASES["combined"]], dtype=F64), num=6, noise=0.05)

    def fn(pn):
        return solve_ego_motion(
            tr.points_prev, pn, tr.disparity, tr.K, tr.baseline, method="exact", loss="l2", iterations=2
        ).twist

    assert torch.autograd.gradcheck(fn, (tr.points_next.clone().requires_grad_(True),), atol=1e-5)


# --------------------------------------------------------------------------- bad input


def test_bad_input_raises_typed_errors():
    tr = make_tracks(torch.tensor([CASES["combined"]]), num=10)
    pp, pn, d, K, bl = _args(tr)
    with pytest.raises(ShapeError, match="points_next"):
        solve_ego_motion(pp, pn[:, :9], d, K, bl)
    with pytest.raises(ShapeError, match="weights"):
        solve_ego_motion(pp, pn, d, K, bl, torch.ones(1, 9))
    with pytest.raises(ShapeError, match="disparity_prev"):
        solve_ego_motion(pp, pn, d[:, :5], K, bl)
    with pytest.raises(ShapeError, match="disparity_prev"):
        solve_ego_motion(pp, pn, torch.ones(1, 8, 8), K, bl)
    with pytest.raises(ShapeError, match="valid_prev"):
        solve_ego_motion(pp, pn, torch.ones(1, 1, 8, 8), K, bl, valid_prev=torch.ones(1, 1, 8, 9, dtype=torch.bool))
    with pytest.raises(ShapeError, match="valid_prev"):
        solve_ego_motion(pp, pn, d, K, bl, valid_prev=torch.ones(1, 1, 8, 8, dtype=torch.bool))
    with pytest.raises(ShapeError, match="K"):
        solve_ego_motion(pp, pn, d, K[:, :2], bl)
    with pytest.raises(ShapeError, match="baseline"):
        solve_ego_motion(pp, pn, d, K, torch.ones(2))
    with pytest.raises(ValueRangeError, match="K"):
        solve_ego_motion(pp, pn, d, torch.zeros(1, 3, 3), bl)
    with pytest.raises(ValueRangeError, match="baseline"):
        solve_ego_motion(pp, pn, d, K, torch.zeros(1))
    with pytest.raises(ValueRangeError, match="baseline"):
        solve_ego_motion(pp, pn, d, K, -bl)
    bad = pn.clone()
    bad[0, 3, 1] = float("nan")
    with pytest.raises(ValueRangeError, match="points_next"):
        solve_ego_motion(pp, bad, d, K, bl)
    with pytest.raises(ValueRangeError, match="points_prev"):
        solve_ego_motion(bad, pn, d, K, bl)
    with pytest.raises(ValueRangeError, match="weights"):
        solve_ego_motion(pp, pn, d, K, bl, -torch.ones(1, 10))
    with pytest.raises(ValueRangeError, match="method"):
        solve_ego_motion(pp, pn, d, K, bl, method="nonlinear")
    with pytest.raises(ValueRangeError, match="loss"):
        EgoMotionSolver(loss="cauchy")
    with pytest.raises(DTypeError, match="points_prev"):
        solve_ego_motion(pp.long(), pn, d, K, bl)


@pytest.mark.parametrize("method", METHODS)
def test_black_frame_through_detect_and_track(method):
    """A black frame: the detector finds nothing, the solve flags it and returns the identity, no exception."""
    features = pytest.importorskip("egorefine.features")
    black = torch.zeros(2, 1, 48, 64)
    kp, w = features.detect(black, max_features=20)
    out = features.track(black, black, kp, w)
    K = make_intrinsics(60.0, 31.5, 23.5, 2)
    res = solve_ego_motion(kp, out.keypoints, torch.zeros(2, 1, 48, 64), K, torch.full((2,), 0.1), out.weights, method)
    assert not res.ok.any()
    assert torch.equal(res.motion, torch.eye(4).expand(2, 4, 4)) and (res.num_inliers == 0).all()


def test_twist_exponential_matches_se3_exp_and_ignores_the_batch():
    # The LM retraction: scaling and squaring in batched products; equal to the closed form to rounding for the
    # increments LM takes (and well beyond), and an item's result independent of its batch neighbours.
    from egorefine.geometry import se3_exp
    from egorefine.motion._lm import _se3_generators, _twist_exp

    g = torch.Generator().manual_seed(3)
    scales = torch.logspace(-4, 0, 16, dtype=torch.float64)[:, None]
    delta = torch.randn(16, 6, generator=g, dtype=torch.float64) * scales
    G = _se3_generators(delta)
    # (the bound is the degree-8 Taylor truncation at the largest increment here, a property of the formula and the
    # same on every CPU; float64 rounding adds a few steps of 2.2e-16)
    torch.testing.assert_close(_twist_exp(delta, G), se3_exp(delta), atol=1e-12, rtol=0)
    d32 = delta.float()
    both = _twist_exp(d32, G.float())
    for i in (0, 7, 15):  # the same kernels on one machine, a batch of 16 and of 1: bit for bit
        assert torch.equal(both[i : i + 1], _twist_exp(d32[i : i + 1], G.float()))
