"""Bad input at the door of the public API: each case gets a typed error naming the argument (issue 20)."""

import numpy as np
import pytest
import torch

import egorefine
from egorefine.core import DTypeError, ShapeError, StateError, ValueRangeError
from egorefine.features import detect, track
from egorefine.geometry import make_intrinsics
from egorefine.motion import solve_ego_motion
from egorefine.refine import correct_disparity, predict_disparity
from egorefine.stereo import match_stereo

H, W = 24, 32


def _pair(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    left = torch.rand(1, 1, H, W, generator=g)
    return left, torch.roll(left, -2, dims=-1)


def _K(dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return make_intrinsics(40.0, W / 2, H / 2).to(dtype)


BASELINE = torch.tensor([0.1])


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda a, b: egorefine.EgoMotionRefiner(max_disparity=8)(a, b, _K(), BASELINE), "left"),
        (lambda a, b: match_stereo(a, b, 8), "left"),
        (lambda a, b: detect(a), "image"),
        (lambda a, b: egorefine.refine_sequence(a[None], b[None], _K(), BASELINE, max_disparity=8), "left"),
    ],
)
def test_images_in_0_255_refused(call, name):
    left, right = (255.0 * x for x in _pair())
    with pytest.raises(ValueRangeError, match=rf"{name}: expected values in \[0, 1\].*1/255"):
        call(left, right)


def test_images_slightly_outside_accepted():
    left, right = _pair()
    out, _ = egorefine.EgoMotionRefiner(max_disparity=8)(left * 1.05, right - 0.02, _K(), BASELINE)
    assert out.disparity.shape == (1, 1, H, W)


@pytest.mark.parametrize(
    ("edit", "error", "match"),
    [
        (lambda K: K.mul(0.0), ValueRangeError, "K: expected fx, fy > 0"),
        (lambda K: K.index_put((torch.tensor([0]), torch.tensor([2]), torch.tensor([2])), torch.tensor(0.0)),
         ValueRangeError, r"last row \(0, 0, 1\)"),
        (lambda K: K.index_put((torch.tensor([0]), torch.tensor([0]), torch.tensor([2])), torch.tensor(float("nan"))),
         ValueRangeError, "K: contains NaN"),
        (lambda K: K.long(), DTypeError, "K: expected a floating-point tensor"),
    ],
)
def test_refiner_checks_K_on_frame_0(edit, error, match):
    left, right = _pair()
    with pytest.raises(error, match=match):
        egorefine.EgoMotionRefiner(max_disparity=8)(left, right, edit(_K()), BASELINE, None)


def test_refiner_checks_K_on_later_frames():
    left, right = _pair()
    refiner = egorefine.EgoMotionRefiner(max_disparity=8)
    _, state = refiner(left, right, _K(), BASELINE)
    with pytest.raises(ValueRangeError, match="K: expected fx, fy > 0"):
        refiner(left, right, _K() * 0.0, BASELINE, state)


def test_refiner_refuses_dtype_change_mid_sequence():
    left, right = _pair()
    refiner = egorefine.EgoMotionRefiner(max_disparity=8)
    _, state = refiner(left, right, _K(), BASELINE)
    with pytest.raises(StateError, match="state: carried in torch.float32, but left is torch.float64"):
        refiner(left.double(), right.double(), _K(torch.float64), BASELINE.double(), state)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_refused_at_the_door(dtype):
    left, right = (x.to(dtype) for x in _pair())
    with pytest.raises(DTypeError, match=f"left: expected float32 or float64, got {dtype}"):
        egorefine.EgoMotionRefiner(max_disparity=8)(left, right, _K(), BASELINE)
    with pytest.raises(DTypeError, match="expected float32 or float64"):
        match_stereo(left, right, 8)
    with pytest.raises(DTypeError, match="image: expected float32 or float64"):
        detect(left)
    with pytest.raises(DTypeError, match="expected float32 or float64"):
        egorefine.refine_sequence(left[None], right[None], _K(), BASELINE, max_disparity=8)
    pts = torch.rand(1, 8, 2) * 20
    with pytest.raises(DTypeError, match="expected float32 or float64"):
        solve_ego_motion(pts.to(dtype), pts.to(dtype), torch.full((1, 8), 4.0).to(dtype), _K().to(dtype),
                         BASELINE.to(dtype))


def test_track_mixed_dtypes():
    left, right = _pair()
    kp, w = torch.tensor([[[10.0, 12.0]]]), torch.ones(1, 1)
    with pytest.raises(DTypeError, match="next: torch.float64, but prev is torch.float32"):
        track(left, right.double(), kp, w)
    with pytest.raises(DTypeError, match="weights: torch.float64, but keypoints is torch.float32"):
        track(left, right, kp, w.double())


def _maps():
    e = torch.full((1, 1, 4, 5), 3.0)
    s = torch.full((1, 1, 4, 5), 3.2)
    return e, s


@pytest.mark.parametrize("which", ["predicted", "measured"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_correct_disparity_refuses_non_finite_maps(which, bad):
    e, s = _maps()
    (e if which == "predicted" else s)[0, 0, 1, 2] = bad
    with pytest.raises(ValueRangeError, match=f"{which}: contains NaN or Inf"):
        correct_disparity(e, s, None)


@pytest.mark.parametrize("bad", [float("nan"), -1.0])
@pytest.mark.parametrize("which", ["predicted_variance", "measured_variance"])
def test_correct_disparity_refuses_bad_variance(which, bad):
    e, s = _maps()
    var = torch.full_like(e, 0.1)
    var[0, 0, 0, 0] = bad
    kwargs = {which: var}
    with pytest.raises(ValueRangeError, match=f"{which}: expected finite values >= 0"):
        correct_disparity(e, s, None, fusion="kalman", **kwargs)


@pytest.mark.parametrize("bad", [float("nan"), -1.0])
def test_predict_disparity_refuses_bad_variance(bad):
    d = torch.full((1, 1, 6, 8), 4.0)
    var = torch.full_like(d, 0.1)
    var[0, 0, 2, 3] = bad
    with pytest.raises(ValueRangeError, match="variance: expected finite values >= 0"):
        predict_disparity(d, torch.eye(4)[None], make_intrinsics(10.0, 4.0, 3.0), torch.tensor([1.0]), variance=var)


@pytest.mark.parametrize("cx", [float("nan"), None])
def test_predict_disparity_refuses_bad_K(cx):
    d = torch.full((1, 1, 6, 8), 4.0)
    K = make_intrinsics(10.0, 4.0, 3.0)
    if cx is None:
        K[0, 2] = torch.tensor([0.0, 0.0, 0.0])  # singular
        match = r"last row \(0, 0, 1\)"
    else:
        K[0, 0, 2] = cx
        match = "K: contains NaN"
    with pytest.raises(ValueRangeError, match=match):
        predict_disparity(d, torch.eye(4)[None], K, torch.tensor([1.0]))


def test_empty_and_tiny_inputs():
    left, right = _pair()
    with pytest.raises(ShapeError, match="left: expected a batch of at least one image"):
        egorefine.EgoMotionRefiner(max_disparity=8)(left[:0], right[:0], _K()[:0], BASELINE[:0])
    with pytest.raises(ShapeError, match="lefts: expected at least one frame"):
        egorefine.refine_sequence(left[None][:0], right[None][:0], _K(), BASELINE, max_disparity=8)
    with pytest.raises(ShapeError, match="image: expected at least 4 px per side"):
        detect(torch.rand(1, 1, 3, 3))
    with pytest.raises(DTypeError, match="lefts: expected a torch.Tensor, got ndarray"):
        egorefine.refine_sequence(np.zeros((2, 1, H, W), np.float32), np.zeros((2, 1, H, W), np.float32), _K(),
                                  BASELINE, max_disparity=8)
