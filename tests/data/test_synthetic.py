"""The synthetic renderer: shapes, determinism, exact ground truth, trajectories and scenes."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from egorefine.core import ValueRangeError
from egorefine.data import MOTIONS, PRESETS, SCENES, StereoSequence, render_sequence

H, W = 120, 160


@pytest.fixture(scope="module")
def seq() -> StereoSequence:
    return render_sequence(num_frames=5, height=H, width=W, seed=3)


@pytest.fixture(scope="module")
def ideal_seq() -> StereoSequence:
    # Identical noise-free cameras: for properties of the scene's shading that camera differences would mask
    # (test_imaging checks the realistic cameras against their drawn gains).
    return render_sequence(num_frames=5, height=H, width=W, seed=3, imaging="ideal")


def _right_pose(pose: torch.Tensor, baseline: float) -> torch.Tensor:
    right = pose.clone()
    right[..., :3, 3] = pose[..., :3, 3] + baseline * pose[..., :3, 0]
    return right


def _rotation_angle(R: torch.Tensor) -> torch.Tensor:
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    return torch.acos(cos)


def test_shapes_and_ranges(seq: StereoSequence) -> None:
    T = 5
    for name in ("left", "right", "disparity", "depth", "occluded"):
        assert getattr(seq, name).shape == (T, 1, H, W), name
    assert seq.occluded.dtype == torch.bool
    assert seq.poses.shape == (T, 4, 4) and seq.motions.shape == (T, 4, 4)
    assert seq.K.shape == (3, 3) and len(seq) == T
    assert seq.left.min() >= 0 and seq.left.max() <= 1 and seq.right.min() >= 0 and seq.right.max() <= 1
    # Intensities well inside [0, 1] and textured.
    assert 0.02 <= seq.left.quantile(0.01) and seq.left.quantile(0.99) <= 0.98
    assert seq.left.std() > 0.08
    # Enclosed scene: finite positive depth everywhere, disparity = f B / Z.
    assert torch.isfinite(seq.depth).all() and (seq.depth > 0).all()
    torch.testing.assert_close(seq.disparity, seq.K[0, 0] * seq.baseline / seq.depth)
    # Paper rig: depths ~1-20 m, so disparities of a few to a few tens of (scaled) pixels.
    assert 0.5 < seq.depth.min() and seq.depth.max() < 25.0
    assert seq.baseline == pytest.approx(0.08) and seq.fps == pytest.approx(7.0)
    assert seq.occluded.float().mean() < 0.15


def test_size_override_scales_intrinsics(seq: StereoSequence) -> None:
    f = 398.0 * W / 640
    expected = torch.tensor([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])
    torch.testing.assert_close(seq.K, expected)
    other = render_sequence(num_frames=1, height=30, width=40, focal=50.0, baseline=0.1)
    assert other.K[0, 0] == 50.0 and other.baseline == 0.1 and other.left.shape == (1, 1, 30, 40)


def test_default_preset_matches_paper_rig() -> None:
    rig = PRESETS["paper"]
    assert (rig.width, rig.height, rig.focal, rig.baseline, rig.fps) == (640, 480, 398.0, 0.08, 7.0)
    kitti = PRESETS["kitti"]
    assert (kitti.width, kitti.height) == (1242, 375) and 700 < kitti.focal < 740 and 0.5 < kitti.baseline < 0.6


def test_deterministic_for_a_seed(seq: StereoSequence) -> None:
    again = render_sequence(num_frames=5, height=H, width=W, seed=3)
    for name in ("left", "right", "depth", "occluded", "poses"):
        assert torch.equal(getattr(seq, name), getattr(again, name)), name
    other = render_sequence(num_frames=2, height=H, width=W, seed=4)
    assert not torch.equal(other.left, seq.left[:2])


def test_noise_is_seeded() -> None:
    a = render_sequence(num_frames=1, height=24, width=32, noise_std=0.01)
    b = render_sequence(num_frames=1, height=24, width=32, noise_std=0.01)
    clean = render_sequence(num_frames=1, height=24, width=32)
    assert torch.equal(a.left, b.left)
    assert 0.005 < (a.left - clean.left).std() < 0.015


def test_motions_are_consistent_with_poses(seq: StereoSequence) -> None:
    P = seq.poses.double()
    torch.testing.assert_close(seq.motions[0], torch.eye(4))
    expected = torch.linalg.inv(P[1:]) @ P[:-1]
    torch.testing.assert_close(seq.motions[1:].double(), expected, atol=1e-5, rtol=0)
    R = P[:, :3, :3]
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand_as(R), atol=1e-6,
                               rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(len(seq), dtype=torch.float64))


def test_paper_motion_is_about_a_tenth_of_a_metre_forward() -> None:
    s = render_sequence(num_frames=40, height=12, width=16, antialias=False)
    step = s.motions[1:, :3, 3]
    # camera_t_T_camera_{t-1}: static points come ~0.1 m closer per frame (forward = +Z).
    assert 0.07 < -step[:, 2].mean() < 0.13
    assert step[:, :2].abs().max() < 0.03
    angles = _rotation_angle(s.motions[1:, :3, :3].double()) * 180 / math.pi
    assert 0.01 < angles.mean() and angles.max() < 1.0  # small rotations, a fraction of a degree per frame


def test_kitti_preset_speed_and_depths() -> None:
    s = render_sequence(num_frames=12, preset="kitti", height=24, width=80, antialias=False)
    assert s.K[0, 0] == pytest.approx(721.5377 * 80 / 1242)
    assert 0.7 < -s.motions[1:, 2, 3].mean() < 1.3
    assert s.depth.min() > 3.0 and s.depth.max() < 120.0
    assert s.fps == 10.0


def test_ground_truth_projects_to_right_image(seq: StereoSequence) -> None:
    """The 3-D point of every left pixel, seen from the right camera, lands at (x - d, y)."""
    K = seq.K.double()
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                            indexing="ij")
    for t in (0, len(seq) - 1):
        Z = seq.depth[t, 0].double()
        cam = torch.stack([(xs - K[0, 2]) / K[0, 0] * Z, (ys - K[1, 2]) / K[1, 1] * Z, Z], -1)
        pose_l = seq.poses[t].double()
        world = cam @ pose_l[:3, :3].T + pose_l[:3, 3]
        pose_r = _right_pose(pose_l, seq.baseline)
        in_r = (world - pose_r[:3, 3]) @ pose_r[:3, :3]
        xr = K[0, 0] * in_r[..., 0] / in_r[..., 2] + K[0, 2]
        yr = K[1, 1] * in_r[..., 1] / in_r[..., 2] + K[1, 2]
        torch.testing.assert_close(xr, xs - seq.disparity[t, 0].double(), atol=1e-3, rtol=0)
        torch.testing.assert_close(yr, ys, atol=1e-3, rtol=0)


def test_matching_points_have_matching_intensity(ideal_seq: StereoSequence) -> None:
    """Lambertian surfaces: left(x, y) == right(x - d, y) on non-occluded pixels (bilinear lookup)."""
    seq = ideal_seq
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    xr = xs - seq.disparity[:, 0]
    grid = torch.stack([xr / (W - 1) * 2 - 1, (ys / (H - 1) * 2 - 1).expand_as(xr)], -1)
    warped = F.grid_sample(seq.right, grid, mode="bilinear", align_corners=True, padding_mode="border")
    ok = ~seq.occluded
    diff = (warped - seq.left).abs()[ok]
    # The same intensities up to resampling of a band-limited texture.
    assert diff.median() < 0.02
    assert diff.quantile(0.9) < 0.06
    # A wrong disparity (+1 px) matches much worse: the test can fail.
    grid_off = grid.clone()
    grid_off[..., 0] -= 2.0 / (W - 1)
    off = F.grid_sample(seq.right, grid_off, mode="bilinear", align_corners=True, padding_mode="border")
    assert (off - seq.left).abs()[ok].median() > 2 * diff.median()


@pytest.mark.parametrize("which", ["realistic", "ideal"])
def test_occlusion_mask_flags_unmatched_pixels(which: str, seq: StereoSequence, ideal_seq: StereoSequence) -> None:
    """Occluded pixels are the ones whose depth disagrees with the right view's surface at (x - d, y)."""
    seq = seq if which == "realistic" else ideal_seq
    # Pixels that leave the right image are occluded.
    xs = torch.arange(W, dtype=torch.float32)
    leaves = (xs - seq.disparity[:, 0]) < 0
    assert seq.occluded[:, 0][leaves].all()
    # Occluded pixels inside the image sit next to depth discontinuities, and their match in the right image is
    # another surface: the intensities disagree far more than on visible pixels.
    # A hidden pixel has a nearer surface within (max disparity) pixels to its right in the same row.
    reach = int(seq.disparity.max().ceil())
    nearer_right = F.max_pool2d(F.pad(seq.disparity, (0, reach), value=0.0), (1, reach + 1), stride=1)
    inside = seq.occluded & ~leaves[:, None]
    assert inside.sum() > 0
    nearer = (nearer_right[inside] > seq.disparity[inside] + 1e-3).float().mean()
    if which == "ideal":
        assert nearer == 1.0
        ys = torch.arange(H, dtype=torch.float32)[:, None].expand(H, W)
        grid = torch.stack([(xs - seq.disparity[:, 0]) / (W - 1) * 2 - 1,
                            (ys / (H - 1) * 2 - 1).expand(len(seq), H, W)], -1)
        warped = F.grid_sample(seq.right, grid, mode="bilinear", align_corners=True, padding_mode="border")
        diff = (warped - seq.left).abs()
        # On identical noise-free cameras (realistic ones differ in gain and noise on visible pixels too).
        assert diff[inside].median() > 3 * diff[~seq.occluded].median()
    else:
        # All but a few: a rail or pole thinner than a pixel can hide a point in the right view while falling
        # between pixel centres of the left one.
        assert nearer > 0.99


def test_depth_is_consistent_over_time(seq: StereoSequence) -> None:
    """Points of frame t-1 moved by motions[t] land on frame t's surfaces: exact depth and poses.

    Inverse depth of a plane is affine in pixel coordinates, so bilinear interpolation of 1 / Z at frame t is
    exact wherever the four neighbouring pixels see the same face.
    """
    K = seq.K.double()
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                            indexing="ij")
    for t in range(1, len(seq)):
        Z = seq.depth[t - 1, 0].double()
        cam = torch.stack([(xs - K[0, 2]) / K[0, 0] * Z, (ys - K[1, 2]) / K[1, 1] * Z, Z], -1).reshape(-1, 3)
        M = seq.motions[t].double()
        moved = cam @ M[:3, :3].T + M[:3, 3]
        x = K[0, 0] * moved[:, 0] / moved[:, 2] + K[0, 2]
        y = K[1, 1] * moved[:, 1] / moved[:, 2] + K[1, 2]
        inside = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
        grid = torch.stack([x / (W - 1) * 2 - 1, y / (H - 1) * 2 - 1], -1)[inside].view(1, 1, -1, 2)
        inv_t = F.grid_sample(1.0 / seq.depth[t : t + 1].double(), grid, align_corners=True).view(-1)
        rel = (inv_t * moved[inside, 2] - 1.0).abs()
        assert inside.sum() > 0.5 * H * W
        assert (rel < 1e-4).float().mean() > 0.85  # the rest: near depth edges, or hidden at frame t
        assert rel.median() < 1e-5


@pytest.mark.parametrize(
    ("scene", "motion"),
    [
        ("corridor", "forward"),
        pytest.param("corridor", "turn", marks=pytest.mark.slow),
        pytest.param("hall", "lateral", marks=pytest.mark.slow),
        pytest.param("hall", "shaky", marks=pytest.mark.slow),
        pytest.param("street", "still", marks=pytest.mark.slow),
    ],
)
def test_scenes_and_motions_stay_enclosed(scene: str, motion: str) -> None:
    s = render_sequence(num_frames=60, scene=scene, motion=motion, height=12, width=16, antialias=False, seed=1)
    assert torch.isfinite(s.depth).all()
    # The camera stays inside the room and clear of obstacles for 60 frames.
    assert s.depth.min() > 0.3
    assert s.left.std() > 0.03


def test_all_scene_and_motion_names_render() -> None:
    for scene in SCENES:
        for motion in MOTIONS:
            s = render_sequence(num_frames=2, scene=scene, motion=motion, height=8, width=10, antialias=False)
            assert torch.isfinite(s.depth).all(), (scene, motion)


def test_float64_and_batch_helper() -> None:
    s = render_sequence(num_frames=3, height=16, width=20, dtype=torch.float64)
    assert s.left.dtype == torch.float64 and s.poses.dtype == torch.float64
    b = s.batch(slice(1, 3))
    assert b["left"].shape == (2, 1, 16, 20) and b["K"].shape == (2, 3, 3) and b["baseline"].shape == (2,)
    assert torch.equal(b["left"], s.left[1:3])
    s32 = s.to(dtype=torch.float32)
    assert s32.left.dtype == torch.float32 and s32.occluded.dtype == torch.bool


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueRangeError, match="preset"):
        render_sequence(num_frames=1, preset="nope")
    with pytest.raises(ValueRangeError, match="scene"):
        render_sequence(num_frames=1, scene="nope")
    with pytest.raises(ValueRangeError, match="motion"):
        render_sequence(num_frames=1, motion="nope")
    with pytest.raises(ValueRangeError, match="num_frames"):
        render_sequence(num_frames=0)
    with pytest.raises(ValueRangeError, match="baseline"):
        render_sequence(num_frames=1, height=8, width=8, baseline=-1.0)


def test_repr_is_compact(seq: StereoSequence) -> None:
    text = repr(seq)
    assert text.startswith("StereoSequence(T=5, H=120, W=160") and len(text) < 200
