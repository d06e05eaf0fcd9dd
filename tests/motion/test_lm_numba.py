"""The compiled CPU form of the exact solve's Levenberg-Marquardt (egorefine.motion._lm_numba) against the torch
path, which stays the reference (GPU, autograd)."""

from __future__ import annotations

import pytest
import torch
from motion_tracks import make_tracks

from egorefine.core import _jit, dispatch
from egorefine.motion import _lm_numba, _solve_numba, solve_ego_motion

needs_numba = pytest.mark.skipif(not _lm_numba.AVAILABLE, reason="numba not installed")
TWISTS = [[0.02, -0.01, 0.1, 0.005, -0.01, 0.003], [0.0, 0.03, 0.08, -0.004, 0.002, 0.01]]


def _both(monkeypatch, tr, **kw):
    args = (tr.points_prev, tr.points_next, tr.disparity, tr.K, tr.baseline)
    compiled = solve_ego_motion(*args, **kw)
    monkeypatch.setattr(dispatch, "ENABLED", False)
    reference = solve_ego_motion(*args, **kw)
    monkeypatch.setattr(dispatch, "ENABLED", True)
    return compiled, reference


@needs_numba
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("kw", [{}, {"loss": "huber"}, {"loss": "l2", "iterations": 6}, {"iterations": 1},
                                {"scale": 0.5, "iterations": 4}])
def test_compiled_lm_equals_torch_path(monkeypatch, dtype, kw):
    # the same steps, acceptance rule and damping in float64: equal to the torch path's rounding. A float32 torch
    # path takes those discrete steps on float32 costs: an input one float32 step away (another CPU's rounding
    # upstream) can end it an iteration off the float64 result, several times 1e-5 in the motion, ~1e-3 in a weight.
    tr = make_tracks(torch.tensor(TWISTS, dtype=dtype), num=300, noise=0.3, outliers=0.1, seed=4)
    a, r = _both(monkeypatch, tr, **kw)
    tol, wtol = (1e-8, 1e-6) if dtype == torch.float64 else (1e-4, 2e-3)
    assert torch.equal(a.ok, r.ok) and a.ok.all()
    assert torch.equal(a.num_inliers, r.num_inliers)
    torch.testing.assert_close(a.motion, r.motion, rtol=0, atol=tol)
    torch.testing.assert_close(a.weights, r.weights, rtol=0, atol=wtol)
    torch.testing.assert_close(a.rms, r.rms, rtol=0, atol=wtol)
    assert a.motion.dtype == dtype


@needs_numba
def test_compiled_lm_batch_item_equals_alone():
    tr = make_tracks(torch.tensor(TWISTS), num=200, noise=0.3, outliers=0.1, seed=2)
    both = solve_ego_motion(tr.points_prev, tr.points_next, tr.disparity, tr.K, tr.baseline)
    for i in range(2):
        s = slice(i, i + 1)
        alone = solve_ego_motion(tr.points_prev[s], tr.points_next[s], tr.disparity[s], tr.K[s], tr.baseline[s])
        assert torch.equal(both.motion[s], alone.motion) and torch.equal(both.weights[s], alone.weights)


def test_torch_path_when_compiled_does_not_apply(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("the compiled LM ran")

    tr = make_tracks(torch.tensor(TWISTS[:1], dtype=torch.float64), num=60, noise=0.2, seed=1)
    monkeypatch.setattr(_lm_numba, "two_stage_lm", refuse)
    points = tr.points_next.clone().requires_grad_(True)
    res = solve_ego_motion(tr.points_prev, points, tr.disparity, tr.K, tr.baseline)  # a gradient is wanted
    res.motion.sum().backward()
    assert torch.isfinite(points.grad).all()
    monkeypatch.setattr(_jit, "AVAILABLE", False)
    solve_ego_motion(tr.points_prev, tr.points_next, tr.disparity, tr.K, tr.baseline)
    monkeypatch.setattr(_jit, "AVAILABLE", True)
    # the torch solve (as after a bad value the compiled solve declines) with the compiled LM inside it
    monkeypatch.setattr(_solve_numba, "solve_compiled", lambda *args, **kwargs: None)
    with pytest.raises(AssertionError, match="compiled LM"):
        solve_ego_motion(tr.points_prev, tr.points_next, tr.disparity, tr.K, tr.baseline)


@needs_numba
def test_compiled_lm_degenerate_input_gives_flag_not_nan():
    tr = make_tracks(torch.tensor(TWISTS[:1]), num=40, seed=3)
    zero = torch.zeros(1, 40)
    res = solve_ego_motion(tr.points_prev, tr.points_next, tr.disparity, tr.K, tr.baseline, weights=zero)
    assert not res.ok.any()
    assert torch.equal(res.motion, torch.eye(4)[None]) and torch.isfinite(res.rms).all()
