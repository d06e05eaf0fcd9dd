"""egorefine.core.dispatch: the one rule that picks a compiled kernel or the torch path, and every public stage run
with gradients on (float32 CPU tensors, the compiled kernels' own case) giving outputs whose graph reaches the
inputs."""

from __future__ import annotations

import pytest
import torch

from egorefine.core import _jit, dispatch, use_compiled
from egorefine.data import render_sequence
from egorefine.features import build_pyramid, detect, replenish, track
from egorefine.geometry import make_intrinsics, project, transform_points, twist_to_motion, unproject
from egorefine.motion import motion_field, solve_ego_motion
from egorefine.refine import (
    EgoMotionRefiner,
    TrackingOptions,
    close_cracks,
    correct_disparity,
    predict_disparity,
    refine_sequence,
)
from egorefine.refine.correct import edge_variance
from egorefine.refine.cracks import finish_prediction
from egorefine.stereo import block_matching, match_residual, match_stereo, match_stereo_regions

needs_numba = pytest.mark.skipif(not _jit.AVAILABLE, reason="numba not installed")
SMALL = dict(max_disparity=16, max_features=64, min_tracks=16)


# --------------------------------------------------------------------------- the rule itself


@needs_numba
def test_compiled_only_for_plain_float32_cpu_tensors_without_gradient(monkeypatch):
    x = torch.rand(1, 1, 4, 4)
    mask = x > 0.5
    assert use_compiled(x, mask, None)  # bool and None entries: device and gradient only
    assert use_compiled(x.long())
    assert not use_compiled(x.double())
    assert use_compiled(x.double(), dtype=(torch.float32, torch.float64))
    assert not use_compiled(x, x.double())  # every float tensor in the kernel's dtype
    assert not use_compiled(x.to("meta"))
    assert not use_compiled(x, torch.nn.Parameter(x))  # a parameter requires grad
    w = x.clone().requires_grad_(True)
    assert not use_compiled(x, w)
    with torch.no_grad():
        assert use_compiled(x, w)  # no graph would be recorded
    with torch.inference_mode():
        assert use_compiled(x, w)
    assert use_compiled(w.detach())
    monkeypatch.setattr(dispatch, "ENABLED", False)
    assert not use_compiled(x)
    monkeypatch.setattr(dispatch, "ENABLED", True)
    monkeypatch.setattr(_jit, "AVAILABLE", False)  # numba missing
    assert not use_compiled(x)


@needs_numba
@pytest.mark.filterwarnings("ignore:`torch.jit.trace` is deprecated")
def test_no_compiled_kernel_while_torch_traces():
    seen = []

    def f(x):
        seen.append(use_compiled(x))
        return x + 1

    x = torch.rand(3)
    torch.jit.trace(f, (x,), check_trace=False)  # (the check would run f once more, eagerly)
    assert seen == [False]

    class M(torch.nn.Module):
        def forward(self, x):
            seen.append(use_compiled(x))  # x is an fx Proxy here
            seen.append(use_compiled(torch.zeros(2)))  # a real tensor, but fx is tracing
            return x + 1

    torch.fx.symbolic_trace(M())
    assert seen[1:] == [False, False]
    seen.clear()
    torch.func.vmap(f)(torch.rand(2, 3))  # functorch's batched wrappers
    torch.func.grad(lambda x: f(x).sum())(torch.rand(3))  # and its gradient-tracking ones
    assert seen == [False, False]

    class Counting(torch.utils._python_dispatch.TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            return func(*args, **(kwargs or {}))

    with Counting():
        assert not use_compiled(x)  # a kernel's work would be invisible to the mode
    assert use_compiled(x)


@needs_numba
def test_no_compiled_kernel_under_torch_compile():
    seen = []

    def f(x):
        compiled = use_compiled(x)
        seen.append(compiled)
        return x + (1.0 if compiled else 2.0)

    x = torch.rand(3)
    out = torch.compile(f, backend="eager", fullgraph=True)(x)
    assert seen == [False] and torch.equal(out, x + 2.0)


# --------------------------------------------------------------------------- every stage with gradients on


@pytest.fixture(scope="module")
def seq():
    return render_sequence(num_frames=3, height=48, width=64, seed=3)


def _rig(seq, dtype=torch.float32):
    return seq.K[None].to(dtype), torch.tensor([seq.baseline], dtype=dtype)


def _grad(output: torch.Tensor, *inputs: torch.Tensor, weight_seed: int = 0) -> list[torch.Tensor | None]:
    """Gradients of a random weighting of ``output`` (no cancellation between pixels) with respect to ``inputs``."""
    if not output.requires_grad:
        return [None for _ in inputs]
    g = torch.Generator().manual_seed(weight_seed)
    weights = torch.rand(output.shape, generator=g, dtype=output.dtype) + 0.5
    return list(torch.autograd.grad((output * weights).sum(), inputs, allow_unused=True, retain_graph=True))


def _reaches(grad: torch.Tensor | None) -> bool:
    """The graph reached the input: a finite gradient that is not all zero."""
    assert grad is None or torch.isfinite(grad).all(), "a non-finite gradient"
    return grad is not None and bool(grad.abs().sum() > 0)


def _pair(seq):
    left = seq.left[:1].clone().requires_grad_(True)
    right = seq.right[:1].clone().requires_grad_(True)
    return left, right


@pytest.mark.parametrize("options", [{}, {"differentiable": True}, {"cost": "zncc"}, {"aggregation": "sgm"},
                                     {"cost": "zncc", "aggregation": "sgm", "differentiable": True}])
def test_stereo_matching_reaches_both_images(seq, options):
    # the hard winner is piecewise constant; the sub-pixel fit (or the soft-argmin) carries the gradient
    left, right = _pair(seq)
    out = match_stereo(left, right, 16, block_size=5, **options)
    assert out.valid.float().mean() > 0.3
    gl, gr = _grad(out.disparity, left, right)
    assert _reaches(gl) and _reaches(gr)
    d, _ = block_matching(left, right, 16, block_size=5, **options)
    assert all(_reaches(g) for g in _grad(d, left, right))


def test_census_matching_has_no_image_gradient(seq):
    # census compares pixels: its costs, and so its disparities, are piecewise constant in the images
    left, right = _pair(seq)
    out = match_stereo(left, right, 16, block_size=5, cost="census", aggregation="sgm")
    assert out.valid.float().mean() > 0.3
    assert not any(_reaches(g) for g in _grad(out.disparity, left, right))


@pytest.mark.parametrize("window", ["fronto", "warped"])
def test_residual_search_reaches_the_images(seq, window):
    left, right = _pair(seq)
    prior = seq.disparity[:1].clone().requires_grad_(True)
    out = match_residual(left, right, prior, radius=2, block_size=5, prior_valid=seq.disparity[:1] > 0,
                         window=window)
    assert out.valid.float().mean() > 0.3
    gl, gr, gp = _grad(out.disparity, left, right, prior)
    assert _reaches(gl) and _reaches(gr)
    # the fronto window scores round(prior) + k: piecewise constant in the prior; the warped one samples along it
    assert _reaches(gp) == (window == "warped")


def test_region_matching_reaches_the_images(seq):
    left, right = _pair(seq)
    mask = torch.zeros(1, 1, *left.shape[-2:], dtype=torch.bool)
    mask[..., 16:32, 24:48] = True
    out = match_stereo_regions(left, right, mask, 16, tile=8, block_size=5)
    assert out.valid[mask].float().mean() > 0.3 and not out.valid[~mask].any()
    assert all(_reaches(g) for g in _grad(out.disparity, left, right))


def test_detection_selects_hard_and_its_subpixel_step_reaches_the_image(seq):
    image = seq.left[:1].clone().requires_grad_(True)
    kp, w = detect(image, max_features=32, grid=(2, 2))
    assert w.sum() > 10 and kp.requires_grad and not w.requires_grad  # the selection is piecewise constant
    assert _reaches(_grad(kp, image)[0])
    with torch.no_grad():  # the same positions as inference (compiled where it applies)
        fast, fast_w = detect(image, max_features=32, grid=(2, 2))
    assert torch.equal(fast_w, w)
    torch.testing.assert_close(fast, kp.detach(), atol=1e-3, rtol=0)
    live_kp = kp[:, :8].detach().clone().requires_grad_(True)
    new_kp, new_w = replenish(image, live_kp, torch.ones(1, 8), max_features=32)
    assert new_w.sum() > 8
    (g,) = _grad(new_kp, live_kp)
    assert _reaches(g) and torch.all(g[0] > 0)  # live tracks pass through unchanged: d(new)/d(live) = 1 there
    assert _reaches(_grad(new_kp[:, 8:], image)[0])  # and the fresh ones carry their detection's graph


def test_pyramid_and_tracking_reach_images_and_keypoints(seq):
    prev = seq.left[:1].clone().requires_grad_(True)
    nxt = seq.left[1:2].clone().requires_grad_(True)
    levels = build_pyramid(prev, 3)
    for level in levels[1:]:
        assert _reaches(_grad(level, prev)[0])
    with torch.no_grad():
        kp, w = detect(seq.left[:1], max_features=32, grid=(2, 2))
    kp = kp.clone().requires_grad_(True)
    for soft in (False, True):
        out = track(prev, nxt, kp, w, soft=soft)
        assert out.weights.sum() > 10
        moved = out.keypoints * out.weights[..., None]
        assert all(_reaches(g) for g in _grad(moved, prev, nxt, kp))


def _tracks(dtype=torch.float32, n=60, seed=0):
    g = torch.Generator().manual_seed(seed)
    K = make_intrinsics(100.0, 40.0, 30.0, 1).to(dtype)
    b = torch.tensor([0.1], dtype=dtype)
    pts = (torch.rand(1, n, 2, generator=g, dtype=dtype) * torch.tensor([80.0, 60.0], dtype=dtype))
    disp = 3.0 + 5.0 * torch.rand(1, n, generator=g, dtype=dtype)
    motion = twist_to_motion(torch.tensor([[0.01, -0.005, 0.05, 0.002, -0.003, 0.001]], dtype=dtype))
    nxt = project(transform_points(motion, unproject(pts, 100.0 * 0.1 / disp, K)), K)
    return pts, nxt, disp, K, b, motion


@pytest.mark.parametrize("method", ["linear", "robust", "exact"])
def test_motion_solve_reaches_tracks_depth_and_rig(method):
    pts, nxt, disp, K, b, truth = _tracks()
    nxt, disp, b = nxt.requires_grad_(True), disp.requires_grad_(True), b.requires_grad_(True)
    res = solve_ego_motion(pts, nxt, disp, K, b, method=method)
    assert res.ok.all()
    if method == "exact":  # equation (3) is first order; the exact model recovers the motion
        torch.testing.assert_close(res.motion.detach(), truth, atol=1e-4, rtol=0)
    assert all(_reaches(g) for g in _grad(res.motion[:, :3, 3], nxt, disp, b))
    twist = torch.tensor([[0.01, -0.005, 0.05, 0.002, -0.003, 0.001]], requires_grad=True)
    flow = motion_field(pts, 100.0 * 0.1 / disp, K, twist)  # (linear in the twist; at rest no depth gradient)
    assert _reaches(_grad(flow, twist)[0]) and _reaches(_grad(flow, disp)[0])


def _wall(dtype=torch.float32, H=24, W=32):
    """A curved wall about 4 px away and a step 0.9 m toward it: 3.6x magnification, cracks beyond the splat's
    tiling (a smooth, uneven surface: sub-pixel look-ups rarely land on pixel centres)."""
    K = make_intrinsics(50.0, (W - 1) / 2, (H - 1) / 2).to(dtype)
    b = torch.tensor([0.1], dtype=dtype)
    x = torch.linspace(0, 1, W, dtype=dtype).view(1, W)
    y = torch.linspace(0, 1, H, dtype=dtype).view(H, 1)
    d = (4.0 + 0.2 * x + 0.1 * y * y)[None, None].contiguous()
    return d, _step(torch.tensor(-0.9, dtype=dtype)), K, b


@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_prediction_reaches_disparity_and_motion_and_confidence_backpropagates(mode):
    d, motion, K, b = _wall()
    motion[0, 2, 3] = -0.3  # 1.3x: the splat tiles it
    d, motion = d.requires_grad_(True), motion.requires_grad_(True)
    var = torch.full_like(d, 0.1).requires_grad_(True)
    pred = predict_disparity(d, motion, K, b, variance=var, mode=mode)
    assert pred.valid.float().mean() > 0.9
    assert all(_reaches(g) for g in _grad(pred.disparity, d, motion))
    assert _reaches(_grad(pred.confidence, var)[0])  # (an in-place fill on a reciprocal's output raised here)
    # variance = var (d'/d)^2 + noise; confidence = 1 / (1 + variance) on valid pixels, 0 on holes
    (gc,) = _grad(pred.confidence, var, weight_seed=1)
    assert torch.all(gc <= 0)


def test_close_cracks_and_finish_prediction_carry_the_graph():
    d, motion, K, b = _wall()
    key_d, key_var = d.clone().requires_grad_(True), torch.full_like(d, 0.1).requires_grad_(True)
    motion = motion.requires_grad_(True)
    pred = predict_disparity(key_d, motion, K, b, variance=key_var)
    holes = ~pred.valid
    assert holes.float().mean() > 0.05
    closed = close_cracks(pred, key_d, key_var, key_d > 0, motion, K, b, process_noise=0.01)
    cracks = holes & closed.valid  # the looked-up pixels
    assert cracks.sum() > 0.5 * holes.sum() and closed.disparity.requires_grad
    assert all(_reaches(g) for g in _grad(closed.disparity * cracks, key_d, motion))
    assert _reaches(_grad(closed.variance * cracks, key_var)[0])
    # the refiner's step: the same look-ups and the range test (hard: piecewise constant)
    pred = predict_disparity(key_d, motion, K, b, variance=key_var)
    done = finish_prediction(pred, key_d, key_var, key_d > 0, motion, K, b, 0.01, True, (0.0, 64.0))
    assert torch.equal(done.valid, closed.valid)
    assert all(_reaches(g) for g in _grad(done.disparity * cracks, key_d, motion))
    torch.testing.assert_close(done.disparity, closed.disparity)
    with torch.no_grad():  # inference: the compiled kernels where they apply, the same values
        pred = predict_disparity(key_d, motion, K, b, variance=key_var)
        fast = close_cracks(pred, key_d, key_var, key_d > 0, motion, K, b, process_noise=0.01)
    assert torch.equal(fast.valid, closed.valid)
    torch.testing.assert_close(fast.disparity, closed.disparity.detach(), atol=1e-4, rtol=0)


def test_close_cracks_gradcheck_float64():
    d, motion, K, b = _wall(torch.float64, H=8, W=10)
    pred = predict_disparity(d, motion, K, b)
    key_ok = torch.ones_like(d, dtype=torch.bool)
    accepted = close_cracks(pred, d, torch.full_like(d, 0.1), key_ok, motion, K, b).valid
    assert (accepted & ~pred.valid).sum() >= 10

    def closed(key_d, key_var, tz):
        out = close_cracks(pred, key_d, key_var, key_ok, _step(tz), K, b, process_noise=0.01)
        assert torch.equal(out.valid, accepted)  # the same pixels accepted at every probe: the smooth part only
        return out.disparity, out.variance

    inputs = (d.clone().requires_grad_(True), torch.full_like(d, 0.1).requires_grad_(True),
              torch.tensor(-0.9, dtype=torch.float64, requires_grad=True))
    assert torch.autograd.gradcheck(closed, inputs, eps=1e-6, atol=1e-6)


def _step(tz: torch.Tensor) -> torch.Tensor:
    """camera_t_T_key: a translation by ``tz`` along the optical axis, differentiable in ``tz``."""
    zero = torch.zeros_like(tz)
    t = torch.stack([zero, zero, tz])
    top = torch.cat([torch.eye(3, dtype=tz.dtype), t[:, None]], dim=1)
    return torch.cat([top, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=tz.dtype)])[None]


@pytest.mark.parametrize("fusion", ["paper", "kalman"])
def test_correction_reaches_prediction_measurement_and_variances(fusion):
    g = torch.Generator().manual_seed(0)
    e = (5.0 + torch.rand(1, 1, 8, 8, generator=g)).requires_grad_(True)
    s = (e.detach() + torch.randn(1, 1, 8, 8, generator=g)).requires_grad_(True)  # some beyond the gate
    P = torch.full_like(e, 0.5).requires_grad_(True)
    R = torch.full_like(e, 0.5).requires_grad_(True)
    ok = torch.ones_like(e, dtype=torch.bool)
    cor = correct_disparity(e, s, ok, fusion=fusion, predicted_variance=P, measured_variance=R, predicted_valid=ok,
                            kalman_gate=3.0)
    ge, gs, gp, gr = _grad(cor.disparity, e, s, P, R)
    assert _reaches(ge) and _reaches(gs)
    # the paper's gain is a constant: its output does not depend on the variances; Kalman's gain P / (P + R) does
    assert _reaches(gp) == _reaches(gr) == (fusion == "kalman")


def test_edge_variance_reaches_the_window_extremes_and_base():
    d = torch.tensor([[[[1.0, 1.0, 5.0, 5.0]]]], requires_grad=True)
    base = torch.full_like(d, 0.1).requires_grad_(True)
    out = edge_variance(d, kernel_size=3, base=base)
    torch.testing.assert_close(out.detach(), torch.tensor([[[[0.1, 4.1, 4.1, 0.1]]]]))
    (gd,) = torch.autograd.grad(out[0, 0, 0, 1], d, retain_graph=True)  # (r / 2)^2 with r = d[2] - d[0]: r / 2
    torch.testing.assert_close(gd, torch.tensor([[[[-2.0, 0.0, 2.0, 0.0]]]]))
    (gb,) = torch.autograd.grad(out.sum(), base)
    assert torch.equal(gb, torch.ones_like(base))


@pytest.mark.parametrize("fusion", ["paper", "kalman"])
def test_refiner_forward_reaches_the_first_left_image(seq, fusion):
    K, b = _rig(seq)
    left0 = seq.left[:1].clone().requires_grad_(True)
    refiner = EgoMotionRefiner(verify_every=5, fusion=fusion, **SMALL)
    state, outs = None, []
    for t in range(3):
        out, state = refiner(left0 if t == 0 else seq.left[t:t + 1], seq.right[t:t + 1], K, b, state)
        outs.append(out)
    assert [o.stereo_ran for o in outs] == [True, False, False]
    for o in outs:
        assert _reaches(_grad(o.disparity, left0)[0])
    # the matcher's variance is smooth in its costs, and a prediction's carries the splat's (backpropagating
    # through it raised): every frame's confidence reaches the first image
    for o in outs:
        assert _reaches(_grad(o.confidence, left0)[0])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_refine_sequence_gradient_after_a_prediction_frame(seq, dtype):
    """d(disparity[t]) / d(left[0]) for t = 2, after the prediction frame 1: through the keyframe's stereo and
    the prediction with its crack look-ups (the compiled look-up cut it: exactly zero)."""
    K, b = _rig(seq, dtype)
    lefts = seq.left[:, None].to(dtype).requires_grad_(True)
    res = refine_sequence(lefts, seq.right[:, None].to(dtype), K, b, verify_every=5, **SMALL)
    assert res.disparity.dtype == dtype
    assert res.stereo_ran.tolist() == [True, False, False]
    (g,) = _grad(res.disparity[2], lefts)
    assert _reaches(g[0])
    # frames 1 and 2 reach it through the tracks (sub-pixel steps) and the motion solved from them
    assert _reaches(g[1]) and _reaches(g[2])


@pytest.mark.filterwarnings("ignore:Dynamo does not know how to trace the builtin")  # (graph breaks: eager there)
@pytest.mark.parametrize("backend", ["eager", pytest.param("inductor", marks=pytest.mark.slow)])
def test_torch_compile_of_the_refiner_matches_eager(backend, require_backend):
    """With the rule, dynamo never reaches a compiled kernel (it handed one a 0-d array on frame 0): the compiled
    refiner runs the torch paths and gives eager's torch-path outputs. ``"eager"`` checks dynamo's tracing alone;
    ``"inductor"`` (slow: minutes of code generation on a small CPU) also the generated code."""
    require_backend(backend)
    seq = render_sequence(num_frames=3, height=32, width=48, seed=1)
    K, b = _rig(seq)
    tracking = TrackingOptions(max_features=32, min_tracks=8)
    refiner = EgoMotionRefiner(verify_every=2, max_disparity=12, tracking=tracking)
    compiled = torch.compile(refiner, backend=backend)

    def run(model):
        state, outs = None, []
        for t in range(3):
            out, state = model(seq.left[t:t + 1], seq.right[t:t + 1], K, b, state)
            outs.append(out)
        return outs

    with torch.no_grad():
        got = run(compiled)
        dispatch.ENABLED = False
        try:
            want = run(refiner)
        finally:
            dispatch.ENABLED = True
    # inductor's code sums in other orders than eager's kernels (vectorised reductions): float32 rounding
    # differences, which the motion solve and the prediction frames carry on, far below the float32 refiner's
    # own distance to a float64 run (here about 100 times below); the eager backend runs eager's kernels
    atol_disparity, atol_motion = (1e-5, 1e-5) if backend == "eager" else (1e-3, 1e-4)
    for a, e in zip(got, want, strict=True):
        assert a.stereo_ran == e.stereo_ran
        assert torch.equal(a.valid, e.valid)
        torch.testing.assert_close(a.disparity, e.disparity, atol=atol_disparity, rtol=0)
        torch.testing.assert_close(a.motion, e.motion, atol=atol_motion, rtol=0)
