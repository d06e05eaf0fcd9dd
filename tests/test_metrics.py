import math

import pytest
import torch

from egorefine.core import ShapeError, ValueRangeError
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
    evaluate_trajectory,
    median_error,
    motions_from_poses,
    relative_pose_error,
    rmse,
    rotation_error_deg,
    temporal_consistency,
    tile_shift,
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


def _random_motions(T: int, seed: int) -> torch.Tensor:
    """``T`` seeded float64 frame-to-frame motions of a walking pace, the identity first."""
    g = torch.Generator().manual_seed(seed)
    twists = torch.randn(T, 6, dtype=torch.float64, generator=g) * torch.tensor([0.05, 0.05, 0.1, 0.01, 0.01, 0.01])
    motions = se3_exp(twists)
    motions[0] = torch.eye(4, dtype=torch.float64)
    return motions


def test_trajectory_metrics():
    motions = _random_motions(6, seed=2)
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


def test_motions_from_poses_inverts_compose_and_evaluate_trajectory():
    motions = _random_motions(7, seed=5)
    poses = compose_motions(motions)
    torch.testing.assert_close(motions_from_poses(poses), motions, atol=1e-12, rtol=0)
    # The same motions from another world origin: a perfect estimate, before and after alignment.
    world = se3_exp(torch.tensor([[1.0, 2.0, -0.5, 0.3, 0.2, -0.1]], dtype=torch.float64))[0]
    perfect = evaluate_trajectory(world @ poses, poses)
    assert perfect["ate_rmse_m"] < 1e-9 and perfect["rpe_translation_rmse_m"] < 1e-9
    assert perfect["rpe_rotation_mean_deg"] < 1e-5 and perfect["frames"] == 7.0
    steps = (poses[1:, :3, 3] - poses[:-1, :3, 3]).norm(dim=-1)
    assert perfect["path_length_m"] == pytest.approx(float(steps.sum()))
    # One motion 4 cm too long along x: RPE sees it on that frame only (rmse over the 6 steps).
    wrong = motions.clone()
    wrong[3, 0, 3] += 0.04
    m = evaluate_trajectory(compose_motions(wrong), poses)
    assert m["rpe_translation_rmse_m"] == pytest.approx(0.04 / math.sqrt(6))
    assert m["rpe_rotation_mean_deg"] < 1e-5 and m["ate_rmse_m"] > 0.005
    with pytest.raises(ShapeError, match="at least 2"):
        evaluate_trajectory(poses[:1], poses[:1])


def test_tile_shift_keeps_regional_shifts_and_averages_noise_away():
    g = torch.Generator().manual_seed(3)
    ref = 5 + 20 * torch.rand(2, 1, 96, 128, generator=g)
    noise = 0.3 * torch.randn(ref.shape, generator=g)
    # per-pixel noise: a per-pixel median distance sees it, the tile measure averages it away
    assert (ref + noise - ref).abs().median() > 0.15
    assert tile_shift(ref + noise, ref) < 0.03
    # a region's shift: 3 of the 4 tile columns (9 of each item's 12 tiles) moved by 0.2 px, the rest still
    shifted = ref.clone()
    shifted[..., :, :96] += 0.2
    torch.testing.assert_close(tile_shift(shifted + noise, ref), torch.tensor(0.2), atol=0.03, rtol=0)
    # a masked-out tile does not count; with too few pixels in every tile the result is NaN
    mask = torch.ones_like(ref, dtype=torch.bool)
    mask[..., :, 96:] = False  # the still column is out: every counted tile is shifted
    assert tile_shift(shifted, ref, mask) == pytest.approx(0.2, abs=1e-6)
    assert torch.isnan(tile_shift(ref, ref, torch.zeros_like(mask)))


def test_tile_shift_bad_input():
    x = torch.zeros(1, 1, 64, 64)
    with pytest.raises(ShapeError, match="reference"):
        tile_shift(x, torch.zeros(1, 1, 64, 32))
    with pytest.raises(ShapeError, match="mask"):
        tile_shift(x, x, torch.ones(1, 1, 32, 64, dtype=torch.bool))
    with pytest.raises(ShapeError, match="tile"):
        tile_shift(torch.zeros(1, 1, 16, 64), torch.zeros(1, 1, 16, 64))
    with pytest.raises(ValueRangeError, match="min_share"):
        tile_shift(x, x, min_share=0.0)
    with pytest.raises(ValueRangeError, match="tile"):
        tile_shift(x, x, tile=0)
