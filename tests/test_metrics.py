import math

import pytest
import torch

from egorefine.core import ShapeError
from egorefine.geometry import se3_exp
from egorefine.metrics import (
    absolute_trajectory_error,
    bad_pixel_rate,
    compose_motions,
    d1_error,
    density,
    distinct_levels,
    epe,
    evaluate_disparity,
    median_error,
    relative_pose_error,
    rmse,
    rotation_error_deg,
    temporal_consistency,
    translation_error,
)


def test_hand_computed_values():
    gt = torch.tensor([[10.0, 10.0, 100.0, 4.0]])
    pred = torch.tensor([[10.5, 14.0, 104.0, 4.0]])
    assert epe(pred, gt).item() == pytest.approx((0.5 + 4 + 4 + 0) / 4)
    assert bad_pixel_rate(pred, gt, 1.0).item() == pytest.approx(0.5)
    # D1: 14 vs 10 (4 px, 40 %) is an outlier; 104 vs 100 (4 px, 4 %) is not.
    assert d1_error(pred, gt).item() == pytest.approx(0.25)
    assert rmse(pred, gt).item() == pytest.approx(math.sqrt((0.25 + 16 + 16) / 4))
    assert median_error(pred, gt).item() in (0.5, 4.0)


def test_mask_and_empty_mask():
    gt, pred = torch.ones(1, 1, 2, 2), torch.ones(1, 1, 2, 2)
    pred[0, 0, 0, 0] = 5.0
    mask = torch.ones(1, 1, 2, 2, dtype=torch.bool)
    mask[0, 0, 0, 0] = False
    assert epe(pred, gt, mask).item() == 0.0
    assert torch.isnan(epe(pred, gt, torch.zeros_like(mask)))
    assert density(mask).item() == pytest.approx(0.75)
    with pytest.raises(ShapeError, match="mask"):
        epe(pred, gt, mask[0])


def test_evaluate_disparity_separates_density_from_errors():
    gt = torch.full((1, 1, 4, 4), 8.0)
    pred = gt + 0.25
    valid = torch.ones_like(gt, dtype=torch.bool)
    valid[..., :2, :] = False
    pred[..., :2, :] = 100.0  # wrong but marked invalid: must not count as error
    m = evaluate_disparity(pred, gt, valid)
    assert m["epe"] == pytest.approx(0.25) and m["bad-0.5"] == 0.0 and m["density"] == pytest.approx(0.5)


def test_levels_and_temporal():
    row = torch.tensor([3.0, 3.0, 3.0004, 4.0])
    assert distinct_levels(row) == 2
    gt = torch.zeros(3, 1, 2, 2)
    seq = torch.stack([torch.zeros(1, 2, 2), torch.ones(1, 2, 2), torch.ones(1, 2, 2)])
    assert temporal_consistency(seq, gt).item() == pytest.approx(0.5)


def test_motion_errors():
    a = se3_exp(torch.tensor([[0.1, 0.0, 0.0, 0.0, 0.0, 0.0]]))
    b = se3_exp(torch.tensor([[0.1, 0.0, 0.03, 0.0, math.radians(2.0), 0.0]]))
    assert rotation_error_deg(a, b).item() == pytest.approx(2.0, abs=1e-3)
    assert translation_error(a, a).item() == 0.0
    # Small angles survive float32 (acos of the trace would return 0 below ~0.02 degrees).
    c = se3_exp(torch.tensor([[0.0, 0.0, 0.0, math.radians(0.003), 0.0, 0.0]]))
    assert rotation_error_deg(a, c @ a).item() == pytest.approx(0.003, rel=0.05)


def test_trajectory_metrics():
    g = torch.Generator().manual_seed(2)
    twists = torch.randn(6, 6, dtype=torch.float64, generator=g) * torch.tensor([0.05, 0.05, 0.1, 0.01, 0.01, 0.01])
    motions = se3_exp(twists)
    motions[0] = torch.eye(4, dtype=torch.float64)
    poses = compose_motions(motions)
    # Composing back: camera_t_T_camera_{t-1} = inv(pose_t) @ pose_{t-1}.
    torch.testing.assert_close(torch.linalg.inv(poses[1:]) @ poses[:-1], motions[1:])
    assert relative_pose_error(motions, motions)["translation_rmse_m"] == 0.0
    # A whole trajectory moved rigidly is perfect after alignment, not before.
    world = se3_exp(torch.tensor([[0.3, -0.2, 1.0, 0.2, -0.1, 0.4]], dtype=torch.float64))[0]
    moved = world @ poses
    assert absolute_trajectory_error(moved, poses) < 1e-9
    assert absolute_trajectory_error(moved, poses, align=False) > 0.5
    # A known offset of 3 cm on every position is exactly the RMSE without alignment.
    shifted = poses.clone()
    shifted[:, 0, 3] += 0.03
    assert absolute_trajectory_error(shifted, poses, align=False) == pytest.approx(0.03)
