"""Property-based tests (hypothesis): geometry round trips, a refiner that never returns NaN or Inf, and matching
costs that ignore a constant brightness offset."""

import math

import pytest
import torch

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import egorefine  # noqa: E402
from egorefine.geometry import (  # noqa: E402
    depth_to_disparity,
    disparity_to_depth,
    make_intrinsics,
    project,
    se3_exp,
    se3_log,
    unproject,
)
from egorefine.stereo import match_stereo  # noqa: E402

F64 = torch.float64
floats = st.floats(allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None)
@given(d=st.floats(0.05, 500.0), f=st.floats(50.0, 2000.0), b=st.floats(0.01, 1.0))
def test_disparity_depth_round_trip(d, f, b):
    disp = torch.tensor([[[[d]]]], dtype=F64)
    focal, base = torch.tensor([f], dtype=F64), torch.tensor([b], dtype=F64)
    depth = disparity_to_depth(disp, focal, base)
    assert torch.allclose(depth_to_disparity(depth, focal, base), disp, rtol=1e-12)


@settings(max_examples=60, deadline=None)
@given(x=st.floats(0.0, 640.0), y=st.floats(0.0, 480.0), z=st.floats(0.1, 100.0), f=st.floats(100.0, 1000.0),
       cx=st.floats(100.0, 540.0), cy=st.floats(100.0, 380.0))
def test_project_unproject_round_trip(x, y, z, f, cx, cy):
    K = make_intrinsics(f, cx, cy, dtype=F64)
    px = torch.tensor([[[x, y]]], dtype=F64)
    points = unproject(px, torch.tensor([[z]], dtype=F64), K)
    assert torch.allclose(points[..., 2], torch.tensor(z, dtype=F64))
    assert torch.allclose(project(points, K), px, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(rho=st.lists(st.floats(-5.0, 5.0), min_size=3, max_size=3),
       axis=st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(lambda a: math.hypot(*a) > 1e-3),
       angle=st.one_of(st.floats(0.0, 1e-6), st.floats(1e-6, 3.0)))
def test_se3_log_inverts_exp(rho, axis, angle):
    a = torch.tensor(axis, dtype=F64)
    xi = torch.cat([torch.tensor(rho, dtype=F64), a / a.norm() * angle])[None]
    T = se3_exp(xi)
    assert torch.allclose(T[0, :3, :3] @ T[0, :3, :3].T, torch.eye(3, dtype=F64), atol=1e-12)
    assert torch.allclose(se3_log(T), xi, atol=1e-9)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), h=st.integers(16, 40), w=st.integers(24, 48),
       fusion=st.sampled_from(["paper", "kalman"]), verify_every=st.integers(1, 3),
       dtype=st.sampled_from([torch.float32, torch.float64]), shift=st.integers(0, 4))
def test_refiner_never_returns_nan_and_keeps_its_shapes(seed, h, w, fusion, verify_every, dtype, shift):
    g = torch.Generator().manual_seed(seed)
    base = torch.rand(1, 1, h, w + 8, generator=g, dtype=dtype)
    refiner = egorefine.EgoMotionRefiner(max_disparity=8, verify_every=verify_every, fusion=fusion)
    K = make_intrinsics(30.0, w / 2, h / 2, dtype=dtype)
    baseline = torch.tensor([0.1], dtype=dtype)
    state = None
    for t in range(4):  # random texture drifting sideways, or pure noise on the odd frames
        frame = torch.roll(base, t * shift, dims=-1)
        if t % 2 and seed % 3 == 0:
            frame = torch.rand(frame.shape, generator=g, dtype=dtype)
        left, right = frame[..., 4:w + 4], frame[..., 6:w + 6]
        out, state = refiner(left, right, K, baseline, state)
        for name in ("disparity", "variance", "confidence"):
            value = getattr(out, name)
            assert value.shape == (1, 1, h, w) and value.dtype == dtype, name
            assert torch.isfinite(value).all(), name
        assert out.valid.shape == (1, 1, h, w) and out.valid.dtype == torch.bool
        assert out.motion.shape == (1, 4, 4) and torch.isfinite(out.motion).all()
        assert (out.confidence >= 0).all() and (out.confidence <= 1).all()


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), offset=st.integers(-40, 40), cost=st.sampled_from(["census", "zncc"]))
def test_census_and_zncc_ignore_a_brightness_offset(seed, offset, cost):
    g = torch.Generator().manual_seed(seed)
    # 8-bit levels in steps of 1/256 and an offset of whole steps: the shifted images are exact in float32.
    levels = torch.randint(64, 192, (1, 1, 32, 56), generator=g).to(torch.float32)
    left = levels / 256
    right = torch.roll(levels, -3, dims=-1) / 256
    shifted = (levels + offset) / 256, (torch.roll(levels, -3, dims=-1) + offset) / 256
    a = match_stereo(left, right, 8, cost=cost, block_size=5)
    b = match_stereo(*shifted, 8, cost=cost, block_size=5)
    if cost == "census":  # comparisons of exact values: bit for bit
        assert torch.equal(a.valid, b.valid) and torch.equal(a.disparity, b.disparity)
    else:  # the window means round differently: the same decisions but for rare near-ties
        same = (a.valid == b.valid) & (~a.valid | ((a.disparity - b.disparity).abs() < 1e-3))
        assert same.float().mean() > 0.99
