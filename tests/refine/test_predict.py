"""Tests of egorefine.refine.predict against analytic plane scenes with exact motion."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from egorefine.core import DTypeError, ShapeError, ValueRangeError
from egorefine.geometry import make_intrinsics, unproject_disparity
from egorefine.refine.predict import PredictDisparity, Prediction, fill_holes_background, predict_disparity

H, W = 120, 160  # the paper's rig (f = 398 px at 640x480, B = 8 cm) scaled down by 4
BASELINE = 0.08


# ----------------------------------------------------------------------------- analytic scene
def _rot(axis: str, deg: float) -> torch.Tensor:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    if axis == "y":
        return torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)
    return torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=torch.float64)


# (normal, offset, bounds in world (x, y)) of planes n . X = offset; None = unbounded.
_PLANES = [
    ((0.0, 0.0, 1.0), 8.0, None),  # back wall 8 m ahead
    ((0.0, 1.0, 0.0), 1.2, None),  # ground 1.2 m below the camera (Y down)
    ((0.0, 0.0, 1.0), 3.0, ((-0.3, 0.4), (-0.5, 0.4))),  # fronto-parallel box face at 3 m
    (  # slanted panel on the left, turned 35 degrees about Y, standing on the ground
        (math.sin(math.radians(35)), 0.0, -math.cos(math.radians(35))),
        -3.2,
        ((-3.0, -0.6), (-1.0, 1.2)),
    ),
]


def _intrinsics() -> torch.Tensor:
    return make_intrinsics(398.0 * W / 640, (W - 1) / 2, (H - 1) / 2, dtype=torch.float64)


def _render(pose: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Exact disparity ``(1, 1, H, W)`` of the plane scene seen from ``world_T_camera`` ``pose``."""
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    ray = torch.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], torch.ones_like(xs)], -1)
    direction, origin = ray @ pose[:3, :3].T, pose[:3, 3]
    depth = torch.full((H, W), math.inf, dtype=torch.float64)
    for normal, offset, bounds in _PLANES:
        n = torch.tensor(normal, dtype=torch.float64)
        den = direction @ n
        den = torch.where(den.abs() < 1e-12, torch.full_like(den, 1e-12), den)
        lam = (offset - origin @ n) / den  # ray parameter = depth Z, since ray_z = 1
        point = origin + lam[..., None] * direction
        hit = lam > 1e-6
        if bounds is not None:
            for axis, (lo, hi) in enumerate(bounds):
                hit &= (point[..., axis] >= lo) & (point[..., axis] <= hi)
        depth = torch.where(hit & (lam < depth), lam, depth)
    return (K[0, 0] * BASELINE / depth)[None, None]


def _poses(n: int) -> list[torch.Tensor]:
    """Rig moving forward 12 cm, right 4 cm, up 1 cm per frame while turning 0.6 deg/frame right, 0.2 up."""
    out = []
    for k in range(n):
        T = torch.eye(4, dtype=torch.float64)
        T[:3, :3] = _rot("y", 0.6 * k) @ _rot("x", 0.2 * k)
        T[:3, 3] = torch.tensor([0.04 * k, -0.01 * k, 0.12 * k], dtype=torch.float64)
        out.append(T)
    return out


@pytest.fixture(scope="module")
def scene():
    K = _intrinsics()
    poses = _poses(11)
    disparity = [_render(p, K[0]) for p in poses]
    motions = [None] + [(torch.linalg.inv(poses[k]) @ poses[k - 1])[None] for k in range(1, 11)]
    return K, torch.tensor([BASELINE], dtype=torch.float64), disparity, motions, poses


def _near_edge(d: torch.Tensor, radius: int = 2, jump: float = 0.3) -> torch.Tensor:
    """Pixels within ``radius`` of a disparity jump above ``jump`` px (where aliasing is expected)."""
    hi = F.max_pool2d(d, 2 * radius + 1, 1, radius)
    lo = -F.max_pool2d(-d, 2 * radius + 1, 1, radius)
    return (hi - lo) > jump


def _fronto(value: float, batch: int = 1, dtype=torch.float64, h: int = 12, w: int = 16) -> torch.Tensor:
    return torch.full((batch, 1, h, w), value, dtype=dtype)


def _translation(tx: float = 0.0, ty: float = 0.0, tz: float = 0.0, batch: int = 1) -> torch.Tensor:
    M = torch.eye(4, dtype=torch.float64).repeat(batch, 1, 1)
    M[:, :3, 3] = torch.tensor([tx, ty, tz], dtype=torch.float64)
    return M


# ----------------------------------------------------------------------------- smoke, shapes
@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_smoke_shapes(mode):
    K = make_intrinsics(20.0, 7.5, 5.5, batch_size=2, dtype=torch.float64)
    d = torch.rand(2, 1, 12, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) + 1.0
    pred = predict_disparity(d, _translation(0.01, 0.0, 0.02, batch=2), K, torch.tensor([0.1, 0.1]), mode=mode)
    assert isinstance(pred, Prediction)
    for field in pred:
        assert field.shape == (2, 1, 12, 16)
    assert pred.hole.dtype == torch.bool and pred.valid.dtype == torch.bool
    assert torch.equal(pred.valid, ~pred.hole)
    assert torch.isfinite(pred.disparity).all() and torch.isfinite(pred.variance).all()
    assert ((pred.confidence >= 0) & (pred.confidence <= 1)).all()


@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_identity_motion_is_exact(mode):
    g = torch.Generator().manual_seed(1)
    d = 1.0 + 3.0 * torch.rand(1, 1, 12, 16, dtype=torch.float64, generator=g)
    var = torch.rand(1, 1, 12, 16, dtype=torch.float64, generator=g)
    K = make_intrinsics(20.0, 7.5, 5.5, dtype=torch.float64)
    pred = predict_disparity(
        d, torch.eye(4, dtype=torch.float64)[None], K, torch.tensor([0.1]), variance=var, mode=mode, process_noise=0.01
    )
    assert pred.valid.all()
    assert torch.allclose(pred.disparity, d, atol=1e-12)
    assert torch.allclose(pred.variance, var + 0.01, atol=1e-12)
    assert torch.allclose(pred.confidence, 1 / (1 + var + 0.01))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])  # the compiled path's in-kernel test, torch's
@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf])
def test_bad_variance_is_refused(dtype, bad):
    K = make_intrinsics(20.0, 7.5, 5.5, dtype=dtype)
    d, M, b = _fronto(2.0).to(dtype), _translation().to(dtype), torch.tensor([0.1], dtype=dtype)
    var = torch.full_like(d, 0.5)
    predict_disparity(d, M, K, b, variance=var)  # (a good one passes)
    var[..., 3, 5] = bad
    with pytest.raises(ValueRangeError, match="variance"):
        predict_disparity(d, M, K, b, variance=var)


def test_exceptions():
    K = make_intrinsics(20.0, 7.5, 5.5, dtype=torch.float64)
    d, M, b = _fronto(2.0), _translation(), torch.tensor([0.1])
    with pytest.raises(ShapeError, match="disparity"):
        predict_disparity(d[:, :, 0], M, K, b)
    with pytest.raises(ShapeError, match="motion"):
        predict_disparity(d, M[:, :3], K, b)
    with pytest.raises(ShapeError, match="baseline"):
        predict_disparity(d, M, K, torch.tensor([0.1, 0.1]))
    with pytest.raises(ShapeError, match="variance"):
        predict_disparity(d, M, K, b, variance=d[..., :3])
    with pytest.raises(ValueRangeError, match="mode"):
        predict_disparity(d, M, K, b, mode="fuzzy")
    with pytest.raises(ValueRangeError, match="baseline"):
        predict_disparity(d, M, K, torch.tensor([-0.1]))
    with pytest.raises(ValueRangeError, match="disparity"):
        predict_disparity(d * math.nan, M, K, b)
    with pytest.raises(ValueRangeError, match="temperature"):
        predict_disparity(d, M, K, b, temperature=0.0)
    with pytest.raises(DTypeError, match="disparity"):
        predict_disparity(d.long(), M, K, b)


# ----------------------------------------------------------------------------- exact small cases
def test_sideways_translation_shifts_by_disparity_and_opens_border_holes():
    # A fronto plane at disparity 4 px; the rig moves right by half a baseline: every point moves
    # left by d * t / B = 2 px exactly; the two rightmost columns enter the view (holes).
    K = make_intrinsics(20.0, 7.5, 5.5, dtype=torch.float64)
    d = _fronto(4.0)
    pred = predict_disparity(d, _translation(tx=-0.05), K, torch.tensor([0.1]), fill_holes=True)
    assert pred.hole[..., -2:].all() and not pred.hole[..., :-2].any()
    assert torch.allclose(pred.disparity, d, atol=1e-12)  # holes filled from the row: also 4
    assert (pred.confidence[pred.hole] == 0).all() and (pred.variance[pred.hole] == 100.0).all()
    # The plane's values cannot show the shift; a marked (invalid) source column can: column 6 lands on 4.
    valid = torch.ones_like(d, dtype=torch.bool)
    valid[..., 6] = False
    marked = predict_disparity(d, _translation(tx=-0.05), K, torch.tensor([0.1]), valid=valid)
    hole_columns = marked.hole[0, 0].all(0).nonzero().flatten().tolist()
    W = d.shape[-1]
    assert hole_columns == [4, W - 2, W - 1]


@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_forward_motion_changes_disparity_to_new_depth(mode):
    # Moving 0.5 m towards a fronto plane at Z = 2 m: d' = f B / 1.5 exactly, variance scaled by (d'/d)^2.
    K = make_intrinsics(20.0, 7.5, 5.5, dtype=torch.float64)
    b = torch.tensor([0.1])
    d = _fronto(20.0 * 0.1 / 2.0)
    var = torch.full_like(d, 0.04)
    pred = predict_disparity(d, _translation(tz=-0.5), K, b, variance=var, mode=mode, process_noise=0.0)
    expected = 20.0 * 0.1 / 1.5
    assert pred.valid.sum() > 0.5 * d.numel()
    assert torch.allclose(pred.disparity[pred.valid], torch.tensor(expected, dtype=torch.float64), atol=1e-10)
    assert torch.allclose(pred.variance[pred.valid], torch.tensor(0.04 * (2.0 / 1.5) ** 2, dtype=torch.float64))
    assert not pred.hole.any()  # zooming in: every target pixel has a source (content leaves the view)
    # zooming out (moving back 0.5 m): the border enters the view and is flagged, the centre is not
    pred = predict_disparity(d, _translation(tz=0.5), K, b, mode=mode)
    assert pred.hole[..., 0, :].all() and pred.hole[..., :, 0].all() and not pred.hole[..., 3:9, 4:12].any()
    assert torch.allclose(pred.disparity[pred.valid], torch.tensor(20.0 * 0.1 / 2.5, dtype=torch.float64))


def test_invalid_sources_are_not_splatted():
    K = make_intrinsics(20.0, 7.5, 5.5, dtype=torch.float64)
    d = _fronto(3.0)
    valid = torch.ones_like(d, dtype=torch.bool)
    valid[..., 4:7, 5:9] = False
    pred = predict_disparity(d, torch.eye(4, dtype=torch.float64)[None], K, torch.tensor([0.1]), valid=valid)
    assert torch.equal(pred.hole, ~valid)
    assert torch.allclose(pred.disparity, d)  # filled from the row neighbours


def test_points_at_infinity_and_all_behind_camera_stay_finite():
    K = make_intrinsics(20.0, 7.5, 5.5, dtype=torch.float64)
    M = torch.eye(4, dtype=torch.float64)[None]
    M[0, :3, :3] = _rot("y", 2.0)
    pred = predict_disparity(torch.zeros(1, 1, 12, 16, dtype=torch.float64), M, K, torch.tensor([0.1]))
    assert torch.isfinite(pred.disparity).all() and (pred.disparity == 0).all() and pred.valid.any()
    # the rig jumps 10 m forward past a plane 2 m ahead: nothing lands, flagged, never NaN
    pred = predict_disparity(_fronto(1.0), _translation(tz=-10.0), K, torch.tensor([0.1]))
    assert pred.hole.all() and torch.isfinite(pred.disparity).all() and (pred.confidence == 0).all()


def test_fill_holes_background_rule():
    d = torch.tensor([[[[5.0, 0.0, 0.0, 2.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 3.0, 0.0, 7.0, 0.0]]]])
    filled, empty = fill_holes_background(d, d == 0)
    expected = torch.tensor([[[[5.0, 2.0, 2.0, 2.0, 2.0], [2.0, 2.0, 2.0, 2.0, 2.0], [3.0, 3.0, 3.0, 7.0, 7.0]]]])
    assert torch.equal(filled, expected)  # row 1 has nothing: the image's smallest, 2
    assert not empty.any()
    filled, empty = fill_holes_background(d, torch.ones_like(d, dtype=torch.bool))
    assert empty.all() and (filled == 0).all()


def test_no_fill_gives_flagged_zeros():
    K = make_intrinsics(20.0, 7.5, 5.5, dtype=torch.float64)
    pred = predict_disparity(_fronto(4.0), _translation(tx=-0.05), K, torch.tensor([0.1]), fill_holes=False)
    assert (pred.disparity[pred.hole] == 0).all() and pred.hole.sum() == 24


# ----------------------------------------------------------------------------- accuracy against truth
@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_single_step_accuracy(scene, mode):
    K, b, disparity, motions, _ = scene
    for k in (1, 5, 10):
        pred = predict_disparity(disparity[k - 1], motions[k], K, b, mode=mode)
        err = (pred.disparity - disparity[k]).abs()
        inner = pred.valid & ~_near_edge(disparity[k])
        assert err[pred.valid].mean() < 0.02  # measured <= 0.018 px
        assert err[inner].max() < 0.1  # measured <= 0.063 px (creases where planes meet)
        assert (err[pred.valid] > 0.5).float().mean() < 0.01  # edge aliasing, measured <= 0.8 %


@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_ten_frames_of_prediction_alone_keep_epe_bounded(scene, mode):
    # Frame 0's exact disparity predicted frame after frame with the exact motions, no stereo.
    K, b, disparity, motions, _ = scene
    d, var, valid = disparity[0], None, None
    for k in range(1, 11):
        pred = predict_disparity(d, motions[k], K, b, variance=var, valid=valid, mode=mode)
        err = (pred.disparity - disparity[k]).abs()
        inner = pred.valid & ~_near_edge(disparity[k])
        assert err[pred.valid].mean() < 0.05, k  # measured <= 0.045 px over the 10 frames
        assert err[inner].mean() < 0.004, k  # smooth surfaces: measured <= 0.0023 px (one refinement step)
        assert (err[pred.valid] > 0.5).float().mean() < 0.025, k  # edges drifting, measured <= 1.6 %
        d, var, valid = pred.disparity, pred.variance, pred.valid
    # the variance grew by the process noise each frame (and by the depth change)
    assert (pred.variance[pred.valid] >= 10 * 0.01 - 1e-9).all()


def test_refinement_beats_plain_splatting(scene):
    K, b, disparity, motions, _ = scene
    inner = ~_near_edge(disparity[1])
    errs = []
    for iterations in (0, 1, 2):
        pred = predict_disparity(disparity[0], motions[1], K, b, refine_iterations=iterations)
        errs.append((pred.disparity - disparity[1]).abs()[pred.valid & inner].mean())
    assert errs[2] < 0.1 * errs[0]  # measured 0.00009 vs 0.0046 px
    assert errs[1] < 0.15 * errs[0]  # the default single step: measured 0.00035 px


@pytest.mark.parametrize("mode", ["hard", "soft"])
@pytest.mark.parametrize("iterations", [0, 1, 2])
def test_in_place_path_equals_autograd_path(scene, mode, iterations):
    # Without gradients the work is done in place; with them, out of place. Same numbers either way.
    K, b, disparity, motions, _ = scene
    g = torch.Generator().manual_seed(4)
    var = 0.1 + torch.rand(1, 1, H, W, dtype=torch.float64, generator=g)
    valid = torch.rand(1, 1, H, W, generator=g) > 0.02
    kwargs = dict(variance=var, valid=valid, mode=mode, refine_iterations=iterations)
    fast = predict_disparity(disparity[4], motions[5], K, b, **kwargs)
    slow = predict_disparity(disparity[4].clone().requires_grad_(True), motions[5], K, b, **kwargs)
    assert slow.disparity.requires_grad and not fast.disparity.requires_grad
    for x, y in zip(fast, slow, strict=True):
        assert torch.allclose(x, y.detach(), atol=1e-10, rtol=0)


def _seen_in_first_frame(k, K, b, disparity, poses) -> torch.Tensor:
    """Pixels of frame k whose surface point was visible in frame 0 (truth, nearest-pixel test)."""
    P = unproject_disparity(disparity[k], K, b)[0]
    T = torch.linalg.inv(poses[0]) @ poses[k]
    Q = P @ T[:3, :3].T + T[:3, 3]
    u = K[0, 0, 0] * Q[..., 0] / Q[..., 2] + K[0, 0, 2]
    v = K[0, 1, 1] * Q[..., 1] / Q[..., 2] + K[0, 1, 2]
    inside = (u > -0.5) & (u < W - 0.5) & (v > -0.5) & (v < H - 0.5) & (Q[..., 2] > 0)
    d0 = disparity[0][0, 0][v.round().clamp(0, H - 1).long(), u.round().clamp(0, W - 1).long()]
    return inside & ((d0 - K[0, 0, 0] * b[0] / Q[..., 2]).abs() < 0.3)


def test_disoccluded_and_entering_pixels_are_flagged(scene):
    K, b, disparity, motions, poses = scene
    d, var, valid = disparity[0], None, None
    for k in range(1, 11):
        pred = predict_disparity(d, motions[k], K, b, variance=var, valid=valid)
        seen = _seen_in_first_frame(k, K, b, disparity, poses)
        hole = pred.hole[0, 0]
        assert (hole & ~seen).sum() > 0.75 * (~seen).sum(), k  # measured >= 85 % (the rest: edge aliasing)
        assert (hole & seen).sum() < 0.03 * seen.sum(), k  # measured <= 2.6 % (chained: edge pixels drop out)
        assert (pred.confidence[pred.hole] == 0).all()
        assert torch.isfinite(pred.disparity).all() and (pred.disparity[pred.hole] > 0).all()  # never silent zeros
        d, var, valid = pred.disparity, pred.variance, pred.valid
    # the background rule fills holes close to the truth here (back wall, ground)
    assert (pred.disparity - disparity[10]).abs()[pred.hole].mean() < 0.5  # measured 0.37 px


@pytest.mark.parametrize("forward", [1.2, 2.0, 3.0])
def test_large_forward_motion_keeps_the_ground_dense_and_correct(forward):
    # A single step of 1.2-3 m towards the scene magnifies the ground near the camera by 2 and more per axis.
    # Hard mode: the magnified ground stays landed (no cracks between rows, whose disparities differ by more
    # than the tolerance after the zoom), and where the inverse warp cannot settle the pixel is a hole, never
    # a wrong value.
    K, b = _intrinsics(), torch.tensor([BASELINE], dtype=torch.float64)
    p0, p1 = torch.eye(4, dtype=torch.float64), torch.eye(4, dtype=torch.float64)
    p1[2, 3] = forward
    d0, d1 = _render(p0, K[0]), _render(p1, K[0])
    pred = predict_disparity(d0, (torch.linalg.inv(p1) @ p0)[None], K, b)
    seen = _seen_in_first_frame(1, K, b, [d0, d1], [p0, p1])
    valid = pred.valid[0, 0]
    err = (pred.disparity - d1).abs()[0, 0]
    inner = valid & ~_near_edge(d1)[0, 0]
    share = {1.2: 0.995, 2.0: 0.97, 3.0: 0.85}[forward]  # measured 0.9995, 0.981, 0.900 (coverage test: 0.97, 0.78)
    assert (valid & seen).sum() > share * seen.sum()
    assert (err[valid] > 0.5).float().mean() < 0.02  # measured <= 1.3 % (coverage test at 2 m: 20 %)
    assert err[inner].mean() < 0.03  # measured <= 0.019 px


# ----------------------------------------------------------------------------- batch, module, gradients
@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_batch_consistency(scene, mode):
    K, b, disparity, motions, _ = scene
    d = torch.cat([disparity[0], disparity[4]])
    M = torch.cat([motions[1], motions[5]])
    var = torch.rand(2, 1, H, W, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    batched = predict_disparity(d, M, K.expand(2, 3, 3), b.expand(2), variance=var, mode=mode)
    for i in range(2):
        alone = predict_disparity(d[i : i + 1], M[i : i + 1], K, b, variance=var[i : i + 1], mode=mode)
        for x, y in zip(batched, alone, strict=True):
            assert torch.allclose(x[i : i + 1], y, atol=1e-12)


def test_module_equals_function(scene):
    K, b, disparity, motions, _ = scene
    module = PredictDisparity(mode="soft", process_noise=0.02, temperature=0.2, refine_iterations=1)
    out = module(disparity[2], motions[3], K, b)
    ref = predict_disparity(
        disparity[2], motions[3], K, b, mode="soft", process_noise=0.02, temperature=0.2, refine_iterations=1
    )
    for x, y in zip(out, ref, strict=True):
        assert torch.equal(x, y)


def _tiny_inputs():
    # A slanted plane seen by a 5x6 camera; a small motion landing every point at a sub-pixel offset
    # (0.3 px), so that no hard decision flips under gradcheck's perturbations.
    K = make_intrinsics(6.0, 2.5, 2.0, dtype=torch.float64)
    xs = torch.arange(6, dtype=torch.float64)
    d = (2.0 + 0.05 * xs + 0.03 * torch.arange(5, dtype=torch.float64)[:, None]).expand(5, 6)[None, None].clone()
    M = _translation(tx=-0.013, ty=0.004, tz=-0.002)
    return d, M, K, torch.tensor([0.1], dtype=torch.float64)


@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_gradcheck(mode):
    d, M, K, b = _tiny_inputs()
    d.requires_grad_(True)
    var = torch.full_like(d, 0.1).requires_grad_(True)

    def f(disp, variance):
        p = predict_disparity(disp, M, K, b, variance=variance, mode=mode)
        return p.disparity, p.variance

    assert torch.autograd.gradcheck(f, (d, var), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("mode", ["hard", "soft"])
@pytest.mark.parametrize("iterations", [0, 2])
def test_gradcheck_motion(mode, iterations):
    d, M, K, b = _tiny_inputs()
    t = M[:, :3, 3].clone().requires_grad_(True)

    def f(trans):
        motion = torch.cat([torch.cat([M[:, :3, :3], trans[..., None]], -1), M[:, 3:]], 1)
        return predict_disparity(d, motion, K, b, mode=mode, refine_iterations=iterations).disparity

    assert torch.autograd.gradcheck(f, (t,), eps=1e-6, atol=1e-6)


def test_gradients_finite_with_holes_and_zero_disparity():
    K = make_intrinsics(20.0, 7.5, 5.5, dtype=torch.float64)
    d = _fronto(4.0)
    d[..., 3:5, 3:5] = 0.0
    d.requires_grad_(True)
    for mode in ("hard", "soft"):
        pred = predict_disparity(d, _translation(tx=-0.05, tz=-0.1), K, torch.tensor([0.1]), mode=mode)
        (g,) = torch.autograd.grad((pred.disparity + pred.variance).sum(), d)
        assert torch.isfinite(g).all()


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_ten_frames_on_rendered_sequence(mode):
    # The synthetic renderer's exact disparity and motions (paper rig at 160x120, forward motion).
    data = pytest.importorskip("egorefine.data")
    seq = data.render_sequence(11, preset="paper", seed=0, height=H, width=W, dtype=torch.float64)
    K, b = seq.K[None], torch.tensor([seq.baseline], dtype=torch.float64)
    d, var, valid = seq.disparity[:1], None, None
    for k in range(1, 11):
        pred = predict_disparity(d, seq.motions[k : k + 1], K, b, variance=var, valid=valid, mode=mode)
        truth = seq.disparity[k : k + 1]
        err = (pred.disparity - truth).abs()
        inner = pred.valid & ~_near_edge(truth)
        assert err[pred.valid].mean() < 0.05, k  # measured <= 0.027 px
        assert err[inner].mean() < 0.015, k  # measured <= 0.0079 px
        assert (err[pred.valid] > 0.5).float().mean() < 0.02, k  # measured <= 1.2 %
        d, var, valid = pred.disparity, pred.variance, pred.valid
