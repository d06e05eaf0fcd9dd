"""Gradients that are right, not only present: ``torch.autograd.gradcheck`` in float64 per stage and through the
refiner's loop, with default options and with the differentiable preset and its learnable parameters.

Images enter through a few smooth directions (``image + sum_i theta_i basis_i``): the check then compares the
analytic and numerical derivative along each direction, which covers every pixel's contribution at the cost of a
handful of probes. Each check also asserts that the hard decisions (winners, validity, the z-buffer) do not change
between probes: gradcheck tests the smooth part, which is all a piecewise-constant decision leaves.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from egorefine.data import render_sequence
from egorefine.features import detect, track
from egorefine.geometry import make_intrinsics
from egorefine.motion import solve_ego_motion
from egorefine.refine import NET_INPUTS, EgoMotionRefiner, correct_disparity, predict_disparity
from egorefine.refine.correct import edge_variance
from egorefine.stereo import match_stereo

F64 = torch.float64
SMALL = dict(max_disparity=12, max_features=48, min_tracks=12)


def _check(fn, *inputs, eps=1e-6, atol=1e-5, rtol=1e-3, projections=3):
    """gradcheck of ``fn`` with each output map reduced to ``projections`` fixed random weightings of it: the same
    check of every input's derivative, at a few backward passes instead of one per output element."""
    weights = {}

    def projected(*args):
        outs = fn(*args)
        outs = outs if isinstance(outs, tuple) else (outs,)
        reduced = []
        for i, out in enumerate(outs):
            if i not in weights:
                g = torch.Generator().manual_seed(i)
                weights[i] = torch.rand((projections, *out.shape), generator=g, dtype=out.dtype) + 0.5
            reduced.append((weights[i] * out).flatten(1).sum(1))
        return tuple(reduced)

    return torch.autograd.gradcheck(projected, inputs, eps=eps, atol=atol, rtol=rtol, fast_mode=False)


def _directions(shape, count, seed):
    """``count`` smooth unit-scale image directions of ``shape`` (low-frequency sinusoids)."""
    g = torch.Generator().manual_seed(seed)
    H, W = shape[-2:]
    y = torch.linspace(0, 1, H, dtype=F64).view(H, 1)
    x = torch.linspace(0, 1, W, dtype=F64).view(1, W)
    out = []
    for _ in range(count):
        fx, fy, px, py = (torch.rand(4, generator=g, dtype=F64) * torch.tensor([3.0, 3.0, 6.28, 6.28], dtype=F64))
        out.append((torch.sin(fx * 6.28 * x + px) * torch.cos(fy * 6.28 * y + py)).expand(shape))
    return torch.stack(out)  # (count, *shape)


@pytest.fixture(scope="module")
def seq():
    """A small realistic sequence with a little continuous noise on top: its 8-bit images tie costs exactly, and
    a probe of 1e-6 would break such ties (a hard decision flipping, not a gradient error)."""
    s = render_sequence(num_frames=4, height=48, width=64, seed=5)
    g = torch.Generator().manual_seed(0)
    return dataclasses.replace(s, left=s.left.double() + 1e-3 * torch.randn(s.left.shape, generator=g, dtype=F64),
                               right=s.right.double() + 1e-3 * torch.randn(s.right.shape, generator=g, dtype=F64))


def _pair(seq, t=0):
    return seq.left[t:t + 1].to(F64), seq.right[t:t + 1].to(F64)


# --------------------------------------------------------------------------- stages


@pytest.mark.parametrize("options", [{}, {"differentiable": True}, {"cost": "zncc", "differentiable": True}])
def test_stereo_gradcheck(seq, options):
    left, right = _pair(seq)
    dirs = _directions(left.shape, 3, seed=1) * 0.01
    # (with a gradient wanted: the float path, whose decisions the probes must keep)
    base = match_stereo(left.requires_grad_(True), right, 12, block_size=5, **options)
    assert base.valid.float().mean() > 0.3

    def disparity(theta_l, theta_r):
        out = match_stereo(left + (theta_l[:, None, None, None, None] * dirs).sum(0),
                           right + (theta_r[:, None, None, None, None] * dirs).sum(0), 12, block_size=5, **options)
        assert torch.equal(out.valid, base.valid)  # the checks are piecewise constant: unchanged across probes
        return out.disparity * out.valid

    zero = torch.zeros(3, dtype=F64, requires_grad=True)
    assert _check(disparity, zero, zero.detach().clone().requires_grad_(True))


@pytest.mark.parametrize("soft", [pytest.param(False, marks=pytest.mark.slow), True])
def test_tracking_gradcheck(seq, soft):
    prev, nxt = seq.left[:1].to(F64), seq.left[1:2].to(F64)
    kp, w = detect(seq.left[:1].float(), max_features=24, grid=(2, 2))
    # positions a quarter pixel off the grid: the integer search centres on a rounded position (a hard decision
    # that a probe at x.5 would flip)
    kp, w = kp.to(F64).floor() + 0.25, w.to(F64)
    base = track(prev, nxt, kp, w, soft=soft)
    assert base.weights.sum() > 8
    dirs = _directions(prev.shape, 2, seed=2) * 0.01

    def moved(theta, points):
        out = track(prev + (theta[:, None, None, None, None] * dirs).sum(0), nxt, points, w, soft=soft)
        assert torch.equal(out.weights > 0, base.weights > 0)
        return out.keypoints * (out.weights > 0)[..., None]

    assert _check(moved, torch.zeros(2, dtype=F64, requires_grad=True), kp.clone().requires_grad_(True))


@pytest.mark.parametrize("method", ["linear", "robust", "exact"])
def test_motion_solve_gradcheck(method):
    from tests.core.test_dispatch import _tracks

    pts, nxt, disp, K, b, _ = _tracks(F64, n=24)
    # tracks with sub-pixel noise, as real ones: on exact tracks the LM's residuals vanish and whether its last
    # step is accepted (a hard decision) is decided by rounding
    nxt = nxt + 0.2 * torch.randn(nxt.shape, generator=torch.Generator().manual_seed(1), dtype=F64)

    def motion(points, disparity, baseline):
        res = solve_ego_motion(pts, points, disparity, K, baseline, method=method)
        assert res.ok.all()
        return res.motion[:, :3, :]

    inputs = (nxt.clone().requires_grad_(True), disp.clone().requires_grad_(True), b.clone().requires_grad_(True))
    assert _check(motion, *inputs)


def _slanted(H=10, W=14):
    K = make_intrinsics(40.0, (W - 1) / 2, (H - 1) / 2).to(F64)
    x = torch.linspace(0, 1, W, dtype=F64).view(1, W)
    y = torch.linspace(0, 1, H, dtype=F64).view(H, 1)
    return (4.0 + 0.5 * x + 0.3 * y)[None, None].contiguous(), K, torch.tensor([0.1], dtype=F64)


def _motion(params: torch.Tensor) -> torch.Tensor:
    """camera_t_T_camera_{t-1} from (tx, ty, tz, small yaw), differentiable in ``params``."""
    tx, ty, tz, yaw = params.unbind()
    c, s = torch.cos(yaw), torch.sin(yaw)
    one, zero = torch.ones_like(tx), torch.zeros_like(tx)
    rows = [torch.stack([c, zero, s, tx]), torch.stack([zero, one, zero, ty]), torch.stack([-s, zero, c, tz]),
            torch.stack([zero, zero, zero, one])]
    return torch.stack(rows)[None]


@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_prediction_gradcheck(mode):
    d, K, b = _slanted()
    params = torch.tensor([0.01, -0.005, -0.05, 0.004], dtype=F64)
    base = predict_disparity(d, _motion(params), K, b, variance=torch.full_like(d, 0.05), mode=mode)
    assert base.valid.float().mean() > 0.6

    def predicted(disparity, p, variance, noise):
        out = predict_disparity(disparity, _motion(p), K, b, variance=variance, mode=mode, process_noise=noise)
        assert torch.equal(out.valid, base.valid)  # coverage and z-buffer: piecewise constant
        return out.disparity * out.valid, out.variance * out.valid, out.confidence

    inputs = (d.clone().requires_grad_(True), params.clone().requires_grad_(True),
              torch.full_like(d, 0.05).requires_grad_(True), torch.tensor(0.01, dtype=F64, requires_grad=True))
    assert _check(predicted, *inputs)


@pytest.mark.parametrize("fusion", ["paper", "kalman"])
@pytest.mark.parametrize("gate_softness", [None, 0.1])
def test_correction_gradcheck(fusion, gate_softness):
    g = torch.Generator().manual_seed(3)
    e = 5.0 + torch.rand(1, 1, 6, 6, generator=g, dtype=F64)
    s = e + torch.randn(1, 1, 6, 6, generator=g, dtype=F64)
    # keep every innovation away from the hard gates (they are piecewise constant there)
    gap = (s - e).abs()
    s = torch.where((gap - 0.5).abs() < 0.05, s + 0.2, s)
    ok = torch.ones_like(e, dtype=torch.bool)

    def corrected(pred, meas, P, R, gain, gate):
        out = correct_disparity(pred, meas, ok, fusion=fusion, gate=gate, gain=gain, predicted_variance=P,
                                measured_variance=R, predicted_valid=ok, kalman_gate=3.0,
                                gate_softness=gate_softness)
        return out.disparity, out.variance

    inputs = (e.requires_grad_(True), s.requires_grad_(True), torch.full_like(e, 0.3).requires_grad_(True),
              torch.full_like(e, 0.2).requires_grad_(True), torch.tensor(0.4, dtype=F64, requires_grad=True),
              torch.tensor(0.5, dtype=F64, requires_grad=True))
    assert _check(corrected, *inputs)


def test_soft_gate_tends_to_the_hard_rule():
    e = torch.tensor([[[[1.0, 2.0, 3.0]]]], dtype=F64)
    s = torch.tensor([[[[1.3, 2.7, 5.0]]]], dtype=F64)
    for fusion in ("paper", "kalman"):
        hard = correct_disparity(e, s, None, fusion=fusion, kalman_gate=1.0, reset_after=1)
        soft = correct_disparity(e, s, None, fusion=fusion, kalman_gate=1.0, reset_after=1, gate_softness=1e-4)
        torch.testing.assert_close(soft.disparity, hard.disparity)
        torch.testing.assert_close(soft.variance, hard.variance)
        wide = correct_disparity(e, s, None, fusion=fusion, kalman_gate=1.0, reset_after=1, gate_softness=1.0)
        assert not torch.allclose(wide.disparity, hard.disparity)  # a wide gate blends


def test_edge_variance_gradcheck():
    d, _, _ = _slanted(6, 8)
    d = d + torch.linspace(0, 2, 8, dtype=F64).view(1, 8) ** 2  # distinct window extremes

    def edges(disparity, base):
        return edge_variance(disparity, kernel_size=3, base=base)

    assert _check(edges, d.requires_grad_(True), torch.full_like(d, 0.1).requires_grad_(True))


# --------------------------------------------------------------------------- the loop, three frames


def _loop(seq, refiner, theta, fx_shift, dirs, verify_pattern):
    """Three frames; left[0] moved along ``dirs`` by ``theta``; K's focal length shifted by ``fx_shift``."""
    K = seq.K[None].to(F64) + fx_shift * torch.diag(torch.tensor([1.0, 1.0, 0.0], dtype=F64))  # fx and fy
    b = torch.tensor([seq.baseline], dtype=F64)
    state, outs = None, []
    for t in range(3):
        left, right = _pair(seq, t)
        if t == 0:
            left = left + (theta[:, None, None, None, None] * dirs).sum(0)
        out, state = refiner(left, right, K, b, state)
        outs.append(out)
    assert [o.stereo_ran for o in outs] == verify_pattern
    return outs


# (one case per fusion in the test command; the rest, about a minute, with the slow checks)
@pytest.mark.parametrize("fusion, verify_every", [("kalman", 2), ("paper", 5),
                                                  pytest.param("paper", 2, marks=pytest.mark.slow),
                                                  pytest.param("kalman", 5, marks=pytest.mark.slow)])
def test_loop_gradcheck_default_options(seq, fusion, verify_every):
    """d(refined disparity of frames 1 and 2) / d(left image of frame 0, focal length), defaults otherwise:
    through the keyframe's stereo, the tracks, the motion solve, the prediction and (every 2) the correction."""
    refiner = EgoMotionRefiner(verify_every=verify_every, fusion=fusion, **SMALL)
    pattern = [True, False, False] if verify_every == 5 else [True, False, True]
    dirs = _directions((1, 1, 48, 64), 2, seed=4) * 0.005
    zero = torch.zeros(2, dtype=F64)
    # (with a gradient wanted, as in the probes: the matcher's float path, whose decisions they must keep)
    base = _loop(seq, refiner, zero.clone().requires_grad_(True), torch.zeros((), dtype=F64), dirs, pattern)

    def refined(theta, fx_shift):
        outs = _loop(seq, refiner, theta, fx_shift, dirs, pattern)
        for o, b in zip(outs, base, strict=True):
            assert torch.equal(o.valid, b.valid)
        return tuple(o.disparity * o.valid for o in outs[1:])

    assert _check(refined, zero.clone().requires_grad_(True), torch.zeros((), dtype=F64, requires_grad=True))


@pytest.mark.parametrize("fusion", [pytest.param("paper", marks=pytest.mark.slow), "kalman"])
def test_loop_gradcheck_learnable_parameters(seq, fusion):
    """The differentiable preset with learnable parameters and both networks: d(frame 2 at a verification) /
    d(every parameter)."""
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Conv2d(NET_INPUTS, 1, 1), torch.nn.Softplus())  # (few weights: few probes)
    offset = torch.nn.Conv2d(NET_INPUTS, 1, 1)
    with torch.no_grad():
        offset.weight.mul_(0.1)
    refiner = EgoMotionRefiner(verify_every=2, fusion=fusion, differentiable=True, learnable=True,
                               confidence_net=net, correction_net=offset, **SMALL).double()
    names = [n for n, _ in refiner.named_parameters()]
    assert {"gain_logit", "log_gate", "log_process_noise", "log_noise_scale", "log_temperature"} <= set(names)
    values = [p.detach().clone() for _, p in refiner.named_parameters()]
    K, b = seq.K[None].to(F64), torch.tensor([seq.baseline], dtype=F64)

    def refined(*probe):
        # the probes stand in for the parameters (torch.func.functional_call): gradcheck perturbs them
        weights = dict(zip(names, probe, strict=True))
        state, outs = None, []
        for t in range(3):
            left, right = _pair(seq, t)
            out, state = torch.func.functional_call(refiner, weights, (left, right, K, b, state))
            outs.append(out)
        assert [o.stereo_ran for o in outs] == [True, False, True]
        return outs[2].disparity * outs[2].valid, outs[1].disparity * outs[1].valid

    probe = tuple(v.clone().requires_grad_(True) for v in values)
    assert _check(refined, *probe, atol=1e-4)


def test_gradients_agree_between_float32_and_float64(seq):
    """The float32 torch path's gradient of a loss after a prediction frame matches float64's."""
    grads = {}
    for dtype in (torch.float32, F64):
        refiner = EgoMotionRefiner(verify_every=5, fusion="kalman", **SMALL)
        left0 = seq.left[:1].to(dtype).clone().requires_grad_(True)
        K, b = seq.K[None].to(dtype), torch.tensor([seq.baseline], dtype=dtype)
        state = None
        for t in range(3):
            out, state = refiner(left0 if t == 0 else seq.left[t:t + 1].to(dtype), seq.right[t:t + 1].to(dtype),
                                 K, b, state)
        loss = (out.disparity * out.valid).sum()
        (grads[dtype],) = torch.autograd.grad(loss, left0)
    g32, g64 = grads[torch.float32].double(), grads[F64]
    assert g64.abs().sum() > 0
    assert (g32 - g64).norm() <= 0.05 * g64.norm()


@pytest.mark.parametrize("subpixel", ["gradient", "quadratic"])
def test_detection_subpixel_gradcheck(seq, subpixel):
    image = seq.left[:1].clone()
    kp, w = detect(image.requires_grad_(True), max_features=16, grid=(2, 2), subpixel=subpixel)
    assert w.sum() >= 8
    dirs = _directions(image.shape, 2, seed=6) * 0.01

    def positions(theta):
        out, weights = detect(image.detach() + (theta[:, None, None, None, None] * dirs).sum(0), max_features=16,
                              grid=(2, 2), subpixel=subpixel)
        assert torch.equal(weights, w) and torch.equal(out.detach().floor(), kp.detach().floor())
        return out

    assert _check(positions, torch.zeros(2, dtype=F64, requires_grad=True))
