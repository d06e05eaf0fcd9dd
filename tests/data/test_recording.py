"""open_recording on layouts the tests write themselves, and on the real EuRoC clip."""

from __future__ import annotations

import math
from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from egorefine.core import DataError, EgorefineError, MissingDataError, ShapeError, ValueRangeError
from egorefine.data import LAYOUTS, StereoRecording, load_euroc, open_recording, oxts_to_poses

from ._files import kitti_numbers, write_filestorage

F, CX, CY, B = 50.0, 15.5, 11.5, 0.2  # a small rectified rig: focal length and principal point (px), baseline (m)
H, W, DISP = 24, 32, 3  # image size; the right image is the left shifted by DISP px


def _texture(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (H, W + DISP), dtype=np.uint8) for _ in range(n)]


def _write_pairs(left_dir: Path, right_dir: Path, n: int, colour: bool = False, names=None) -> list[np.ndarray]:
    """``n`` pairs of a fronto-parallel plane: right(x) = left(x + DISP). Returns the left images."""
    left_dir.mkdir(parents=True)
    right_dir.mkdir(parents=True)
    lefts = []
    for i, tex in enumerate(_texture(n)):
        left, right = tex[:, :W], tex[:, DISP:]
        if colour:
            left, right = cv2.merge([left] * 3), cv2.merge([right] * 3)
        name = names[i] if names else f"{i:06d}.png"
        cv2.imwrite(str(left_dir / name), left)
        cv2.imwrite(str(right_dir / name), right)
        lefts.append(tex[:, :W])
    return lefts


def _K() -> np.ndarray:
    return np.array([[F, 0.0, CX], [0.0, F, CY], [0.0, 0.0, 1.0]])


def _aligned_rig(path: Path) -> Path:
    """An OpenCV stereoCalibrate file of two identical, aligned, distortion-free cameras B apart."""
    return write_filestorage(path, K1=_K(), D1=np.zeros(5), K2=_K(), D2=np.zeros(5), R=np.eye(3),
                         T=np.array([[-B], [0.0], [0.0]]), image_size=np.array([W, H]))


def _P(tx: float) -> np.ndarray:
    """A rectified projection K [I | (tx, 0, 0)]."""
    return _K() @ np.hstack([np.eye(3), [[tx], [0.0], [0.0]]])


# ---------------------------------------------------------------- folders


def test_folders_unrectified_aligned_rig(tmp_path) -> None:
    lefts = _write_pairs(tmp_path / "left", tmp_path / "right", 3)
    _aligned_rig(tmp_path / "calib.yaml")
    rec = open_recording(tmp_path, "folders")
    assert isinstance(rec, StereoRecording) and len(rec) == 3 and not rec.rectified_input
    assert rec.image_size == (H, W) and rec.names == ["000000", "000001", "000002"]
    assert rec.timestamps is None and rec.poses is None
    assert rec.K.dtype == torch.float64 and rec.K.shape == (3, 3)
    assert rec.baseline == pytest.approx(B, rel=1e-9)
    torch.testing.assert_close(rec.K, torch.from_numpy(_K()), atol=1e-6, rtol=0)
    left, right = rec[1]
    assert left.shape == (1, 1, H, W) and left.dtype == torch.float32 and right.shape == left.shape
    # Aligned identical cameras: rectification is the identity, the pair comes back as written.
    torch.testing.assert_close(left[0, 0], torch.from_numpy(lefts[1]).float() / 255, atol=1e-4, rtol=0)
    assert torch.equal(list(rec)[2][0], rec[-1][0])
    with pytest.raises(IndexError):
        rec[3]


def test_folders_rectified_kitti_calib_colour_frames(tmp_path) -> None:
    lefts = _write_pairs(tmp_path / "image_0", tmp_path / "image_1", 2, colour=True)
    (tmp_path / "calib.txt").write_text(f"P0: {kitti_numbers(_P(0.0))}\nP1: {kitti_numbers(_P(-B))}\n")
    rec = open_recording(tmp_path, "folders")
    assert rec.rectified_input and rec.baseline == pytest.approx(B)
    left, right = rec[0]
    torch.testing.assert_close(left[0, 0], torch.from_numpy(lefts[0]).float() / 255, atol=1 / 255, rtol=0)
    # The plane sits at disparity DISP: right(x) == left(x + DISP).
    torch.testing.assert_close(right[0, 0, :, : W - DISP], left[0, 0, :, DISP:], atol=1 / 255, rtol=0)


def test_folders_calib_elsewhere_frame_slice_and_times(tmp_path) -> None:
    _write_pairs(tmp_path / "rec" / "cam0", tmp_path / "rec" / "cam1", 5)
    (tmp_path / "rec" / "times.txt").write_text("".join(f"{100 + 0.5 * i}\n" for i in range(5)))
    calib = _aligned_rig(tmp_path / "stereo.json")
    rec = open_recording(tmp_path / "rec", "folders", calib=calib, frames=slice(1, None, 2))
    assert rec.names == ["000001", "000003"] and rec.baseline == pytest.approx(B)
    assert rec.left_files[0].name == "000001.png" and rec.right_files[1].name == "000003.png"
    np.testing.assert_allclose(rec.timestamps, [100.5, 101.5])
    (tmp_path / "rec" / "times.txt").write_text("1.0\n2.0\n")
    with pytest.raises(DataError, match="times.txt has 2 time stamps, expected one per frame \\(5\\)"):
        open_recording(tmp_path / "rec", "folders", calib=calib)


@pytest.fixture
def kitti_frame(kitti_root) -> Path:
    """The real KITTI pair with its calibration (tests/data/real, the ``kitti_root`` fixture of tests/conftest.py)."""
    return kitti_root


def test_folders_real_kitti_frame(kitti_frame) -> None:
    """The KITTI object layout's image_2/image_3 with its calib file: the colour pair's P2/P3."""
    rec = open_recording(kitti_frame, "folders", calib=kitti_frame / "calib" / "000001.txt", camera="colour")
    assert rec.rectified_input and rec.image_size == (375, 1242) and rec.names == ["0000000001"]
    assert float(rec.K[0, 0]) == pytest.approx(721.5377) and rec.baseline == pytest.approx(0.53273, abs=1e-5)
    left, right = rec[0]
    assert left.shape == (1, 1, 375, 1242) and 0 <= float(left.min()) and float(left.max()) <= 1
    assert float(left.std()) > 0.05 and not torch.equal(left, right)
    with pytest.raises(MissingDataError, match="image_0/ \\+ image_1/ \\(camera='grey'\\)"):
        open_recording(kitti_frame, "folders", calib=kitti_frame / "calib" / "000001.txt")


def test_folders_image_size_from_first_frame(tmp_path) -> None:
    _write_pairs(tmp_path / "left", tmp_path / "right", 1)
    write_filestorage(tmp_path / "calib.yml", M1=_K(), M2=_K(), R=np.zeros(3), T=np.array([-B, 0.0, 0.0]))
    rec = open_recording(tmp_path, "folders")
    assert rec.image_size == (H, W) and rec.baseline == pytest.approx(B)


# ---------------------------------------------------------------- euroc (the real clip)


def test_euroc_clip(euroc_root) -> None:
    rec = open_recording(euroc_root, "euroc", frames=slice(0, 4))
    assert len(rec) == 4 and rec.image_size == (480, 752) and not rec.rectified_input
    assert 0.105 < rec.baseline < 0.115
    seq = load_euroc(euroc_root, max_frames=4, dtype=torch.float64)
    torch.testing.assert_close(rec.K, seq.K)
    assert rec.baseline == seq.baseline
    torch.testing.assert_close(rec.poses, seq.poses)
    torch.testing.assert_close(rec[3][1].double(), seq.right[3:4], atol=1e-6, rtol=0)
    assert rec.names[0] == str(int(seq.timestamps[0]))
    np.testing.assert_allclose(rec.timestamps, seq.timestamps.numpy() / 1e9)
    assert (np.diff(rec.timestamps) > 0.04).all() and (np.diff(rec.timestamps) < 0.06).all()  # 20 Hz


def _euroc_without_truth(euroc_root: Path, tmp_path: Path) -> Path:
    root = tmp_path / "own_recording"
    root.mkdir()
    (root / "mav0").symlink_to(euroc_root / "mav0", target_is_directory=True)
    return root


def test_euroc_without_ground_truth(euroc_root, tmp_path) -> None:
    root = _euroc_without_truth(euroc_root, tmp_path)
    rec = open_recording(root, "euroc")
    assert rec.poses is None and len(rec) == 40 and rec.timestamps.shape == (40,)
    assert open_recording(euroc_root / "mav0", "euroc", frames=slice(0, 1)).poses.shape == (1, 4, 4)
    assert 0.105 < rec.baseline < 0.115
    seq = load_euroc(root, max_frames=2)
    assert seq.poses is None and seq.motions is None and seq.left.shape == (2, 1, 480, 752)
    with_truth = load_euroc(euroc_root, max_frames=2)
    torch.testing.assert_close(seq.left, with_truth.left)


def test_euroc_errors(euroc_root, tmp_path) -> None:
    with pytest.raises(ValueRangeError, match="camera: EuRoC has grey cameras only"):
        open_recording(euroc_root, "euroc", camera="colour")
    with pytest.raises(MissingDataError, match="ASL layout"):
        open_recording(tmp_path, "euroc")


# ---------------------------------------------------------------- bad input


def test_unknown_layout_and_options(tmp_path) -> None:
    with pytest.raises(ValueRangeError, match=r"layout: expected one of .*'euroc'.*got 'tum'"):
        open_recording(tmp_path, "tum")
    with pytest.raises(ValueRangeError, match="camera: expected one of"):
        open_recording(tmp_path, "folders", camera="infrared")
    with pytest.raises(ValueRangeError, match="calib: the kitti-raw layout reads its own"):
        open_recording(tmp_path, "kitti-raw", calib=tmp_path / "calib.yaml")
    with pytest.raises(ValueRangeError, match="frames: expected a slice"):
        open_recording(tmp_path, "folders", frames=3)
    assert LAYOUTS == ("folders", "kitti-raw", "kitti-odometry", "euroc", "rosbag")


def test_missing_folders(tmp_path) -> None:
    with pytest.raises(MissingDataError, match="no folder .*nowhere"):
        open_recording(tmp_path / "nowhere", "folders")
    with pytest.raises(MissingDataError, match="holds none of the folder pairs left/ \\+ right/"):
        open_recording(tmp_path, "folders")
    (tmp_path / "left").mkdir()
    with pytest.raises(MissingDataError, match="no folder .*right"):
        open_recording(tmp_path, "folders")


def test_frame_count_mismatch_and_empty(tmp_path) -> None:
    _write_pairs(tmp_path / "left", tmp_path / "right", 3)
    _aligned_rig(tmp_path / "calib.yaml")
    (tmp_path / "right" / "000002.png").unlink()
    with pytest.raises(DataError, match="right holds 2 images, .*left 3; expected one right frame per left"):
        open_recording(tmp_path, "folders")
    for f in (tmp_path / "right").iterdir():
        f.unlink()
    (tmp_path / "right" / "notes.txt").write_text("not an image")
    with pytest.raises(DataError, match="no image files .* in .*right"):
        open_recording(tmp_path, "folders")


def test_unreadable_image_and_wrong_size(tmp_path) -> None:
    _write_pairs(tmp_path / "left", tmp_path / "right", 2)
    _aligned_rig(tmp_path / "calib.yaml")
    (tmp_path / "left" / "000000.png").write_text("this is no PNG")
    with pytest.raises(DataError, match="000000.png' is not an image file"):
        open_recording(tmp_path, "folders")
    cv2.imwrite(str(tmp_path / "left" / "000000.png"), np.zeros((H, W), np.uint8))
    cv2.imwrite(str(tmp_path / "right" / "000001.png"), np.zeros((H + 2, W), np.uint8))
    rec = open_recording(tmp_path, "folders")
    with pytest.raises(DataError, match=f"000001.png is {W}x{H + 2} \\(W x H\\), expected {W}x{H}"):
        rec[1]
    write_filestorage(tmp_path / "calib.yaml", K1=_K(), K2=_K(), R=np.eye(3), T=[-B, 0, 0], image_size=[W + 8, H])
    with pytest.raises(DataError, match=f"is for {W + 8}x{H} images"):
        open_recording(tmp_path, "folders")


def test_missing_calibration_and_empty_slice(tmp_path) -> None:
    _write_pairs(tmp_path / "left", tmp_path / "right", 2)
    with pytest.raises(MissingDataError, match="calib: no calibration file in"):
        open_recording(tmp_path, "folders")
    with pytest.raises(MissingDataError, match="calib: no calibration file at .*nope.yaml"):
        open_recording(tmp_path, "folders", calib=tmp_path / "nope.yaml")
    _aligned_rig(tmp_path / "calib.yaml")
    with pytest.raises(DataError, match="frames: slice\\(5, None, None\\) selects no frame of the 2"):
        open_recording(tmp_path, "folders", frames=slice(5, None))


def test_recording_checks_its_arguments(tmp_path) -> None:
    files = [tmp_path / "a.png", tmp_path / "b.png"]
    K = torch.from_numpy(_K())
    with pytest.raises(ShapeError, match="names: expected one entry per frame \\(2\\), got 1"):
        StereoRecording(files, files, K, B, (H, W), names=["a"])
    with pytest.raises(ShapeError, match="poses: expected one entry per frame"):
        StereoRecording(files, files, K, B, (H, W), names=["a", "b"], poses=torch.eye(4)[None])
    with pytest.raises(ValueRangeError, match="baseline: expected > 0"):
        StereoRecording(files, files, K, -B, (H, W), names=["a", "b"])


def test_errors_are_typed() -> None:
    assert issubclass(DataError, EgorefineError) and issubclass(DataError, ValueError)
    assert issubclass(MissingDataError, DataError) and issubclass(MissingDataError, FileNotFoundError)


# ---------------------------------------------------------------- kitti-raw

# The vehicle drives east, climbs and turns left: frame k is k metres east, 0.1 k m up, yawed 0.05 k rad.
_STEP_M, _CLIMB_M, _YAW_RAD, _LAT, _LON = 1.0, 0.1, 0.05, 49.0, 8.4
_T_IMU_TO_VELO = np.array([-0.81, 0.32, -0.80])  # identity rotation: the LiDAR 0.8 m behind, 0.3 m left of the IMU
# KITTI's axes: camera x right = -velo y, camera y down = -velo z, camera z forward = velo x.
_VELO_R_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
_TX = {0: 0.0, 1: -0.54, 2: 0.06, 3: -0.47}  # P_rect_0c[0, 3] / fx, metres


def _rz(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _write_kitti_raw(root: Path, n: int, oxts: bool = True, extrinsics: bool = True) -> Path:
    date = root / "2011_09_26"
    drive = date / "2011_09_26_drive_0001_sync"
    for a, b in ((0, 1), (2, 3)):
        _write_pairs(drive / f"image_{a:02d}" / "data", drive / f"image_{b:02d}" / "data", n, colour=a == 2,
                     names=[f"{i:010d}.png" for i in range(n)])
    stamps = "".join(f"2011-09-26 13:02:{25 + i // 10:02d}.{(i % 10) * 10 + 3:02d}0000001\n" for i in range(n))
    (drive / "image_00" / "timestamps.txt").write_text(stamps)
    text = "calib_time: 09-Jan-2012 13:57:47\ncorner_dist: 9.950000e-02\n"
    for c, tx in _TX.items():
        text += (f"S_rect_{c:02d}: {W} {H}\nR_rect_{c:02d}: {kitti_numbers(np.eye(3))}\n"
                 f"P_rect_{c:02d}: {kitti_numbers(_P(tx))}\n")
    (date / "calib_cam_to_cam.txt").write_text(text)
    if extrinsics:
        (date / "calib_imu_to_velo.txt").write_text(f"calib_time: 25-May-2012 16:47:16\nR: {kitti_numbers(np.eye(3))}\n"
                                                     f"T: {kitti_numbers(_T_IMU_TO_VELO)}\n")
        (date / "calib_velo_to_cam.txt").write_text(f"R: {kitti_numbers(_VELO_R_CAM.T)}\nT: 0 0 0\n"
                                                     "delta_f: 0 0\ndelta_c: 0 0\n")
    if oxts:
        (drive / "oxts" / "data").mkdir(parents=True)
        metres_per_degree = math.cos(_LAT * math.pi / 180) * math.pi * 6378137.0 / 180
        for i in range(n):
            rec = [_LAT, _LON + i * _STEP_M / metres_per_degree, 110.0 + i * _CLIMB_M, 0.0, 0.0, i * _YAW_RAD]
            rec += [0.0] * 24
            (drive / "oxts" / "data" / f"{i:010d}.txt").write_text(" ".join(repr(v) for v in rec) + "\n")
    return drive


def test_kitti_raw_poses_follow_the_encoded_drive(tmp_path) -> None:
    drive = _write_kitti_raw(tmp_path, 4)
    rec = open_recording(drive, "kitti-raw", camera="colour")
    assert len(rec) == 4 and rec.rectified_input and rec.image_size == (H, W)
    assert rec.baseline == pytest.approx(0.06 + 0.47) and rec.names[1] == "0000000001"
    # image_02 has no timestamps.txt in this drive: image_00's stand in.
    assert rec.timestamps.shape == (4,) and np.diff(rec.timestamps) == pytest.approx([0.1] * 3, abs=1e-6)
    assert rec.poses.shape == (4, 4, 4) and rec.poses.dtype == torch.float64
    for k in range(4):
        R_world_imu = _rz(k * _YAW_RAD)
        # Camera 2's centre: 0.06 m left of camera 0 (velo +y), which sits at the LiDAR's origin.
        centre_imu = np.array([0.0, 0.06, 0.0]) - _T_IMU_TO_VELO
        expected_t = np.array([k * _STEP_M, 0.0, k * _CLIMB_M]) + R_world_imu @ centre_imu
        np.testing.assert_allclose(rec.poses[k, :3, 3].numpy(), expected_t, atol=1e-6)
        np.testing.assert_allclose(rec.poses[k, :3, :3].numpy(), R_world_imu @ _VELO_R_CAM, atol=1e-9)
    left, right = rec[2]
    torch.testing.assert_close(right[0, 0, :, : W - DISP], left[0, 0, :, DISP:], atol=1 / 255, rtol=0)


def test_kitti_raw_grey_timestamps_and_no_extrinsics(tmp_path) -> None:
    drive = _write_kitti_raw(tmp_path, 12, extrinsics=False)
    rec = open_recording(drive, "kitti-raw", frames=slice(9, 12))
    assert rec.baseline == pytest.approx(0.54) and rec.poses is None
    start = datetime(2011, 9, 26, 13, 2, 25, tzinfo=timezone.utc).timestamp()
    np.testing.assert_allclose(rec.timestamps, start + np.array([0.930000001, 1.030000001, 1.130000001]),
                               rtol=0, atol=1e-6)


def test_kitti_raw_bad_input(tmp_path) -> None:
    drive = _write_kitti_raw(tmp_path, 3)
    (drive / "oxts" / "data" / "0000000002.txt").unlink()
    with pytest.raises(DataError, match="oxts/data has 2 OXTS records, expected one per frame \\(3\\)"):
        open_recording(drive, "kitti-raw")
    (drive / "image_00" / "timestamps.txt").write_text("yesterday\n" * 3)
    with pytest.raises(DataError, match="timestamps.txt: expected lines 'YYYY-MM-DD hh:mm:ss"):
        open_recording(drive, "kitti-raw")
    (drive.parent / "calib_cam_to_cam.txt").unlink()
    with pytest.raises(MissingDataError, match="no calib_cam_to_cam.txt in .*drive_0001_sync or .*2011_09_26"):
        open_recording(drive, "kitti-raw")
    with pytest.raises(MissingDataError, match="no folder .*image_02/data"):
        open_recording(tmp_path, "kitti-raw", camera="colour")
    extract = tmp_path / "2011_09_26_drive_0001_extract"
    extract.mkdir()
    with pytest.raises(DataError, match="unrectified '_extract' download"):
        open_recording(extract, "kitti-raw")


def test_oxts_to_poses_turn_and_latitude_scale() -> None:
    """A quarter turn in place is a pure rotation; 0.001 degree of longitude is scaled by cos(latitude)."""
    rec = np.array([[60.0, 10.0, 5.0, 0.0, 0.0, 0.2], [60.0, 10.0, 5.0, 0.0, 0.0, 0.2 + math.pi / 2],
                    [60.0, 10.001, 5.0, 0.0, 0.0, 0.2]])
    poses = oxts_to_poses(rec)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(poses[1][:3, :3], _rz(math.pi / 2), atol=1e-12)
    np.testing.assert_allclose(poses[1][:3, 3], 0.0, atol=1e-9)
    east = 0.5 * math.pi * 6378137.0 / 180 * 0.001  # cos(60 deg) = 0.5
    np.testing.assert_allclose(poses[2][:3, 3], _rz(-0.2) @ [east, 0.0, 0.0], atol=1e-6)


# ---------------------------------------------------------------- kitti-odometry


def _write_odometry(root: Path, n: int, poses: bool = True) -> Path:
    seq = root / "dataset" / "sequences" / "07"
    for a, b in ((0, 1), (2, 3)):
        _write_pairs(seq / f"image_{a}", seq / f"image_{b}", n, colour=a == 2)
    (seq / "calib.txt").write_text("".join(f"P{c}: {kitti_numbers(_P(tx))}\n" for c, tx in _TX.items())
                                   + f"Tr: {kitti_numbers(np.eye(3, 4))}\n")
    (seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(n)))
    if poses:
        (root / "dataset" / "poses").mkdir()
        rows = [np.hstack([_rz(0.1 * i).T, [[0.0], [0.0], [2.0 * i]]]) for i in range(n)]  # forward 2 m a frame
        (root / "dataset" / "poses" / "07.txt").write_text("".join(kitti_numbers(r) + "\n" for r in rows))
    return seq


def test_kitti_odometry_colour_poses_moved_to_camera_2(tmp_path) -> None:
    seq = _write_odometry(tmp_path, 3)
    rec = open_recording(seq, "kitti-odometry", camera="colour")
    assert rec.rectified_input and rec.baseline == pytest.approx(0.53) and rec.names == ["000000", "000001", "000002"]
    np.testing.assert_allclose(rec.timestamps, [0.0, 0.1, 0.2])
    for k in range(3):
        R0 = _rz(0.1 * k).T
        # Camera 2 sits 0.06 m left of camera 0 (along camera 0's -x), same orientation.
        np.testing.assert_allclose(rec.poses[k, :3, 3].numpy(), [0.0, 0.0, 2.0 * k] + R0 @ [-0.06, 0.0, 0.0],
                                   atol=1e-9)
        np.testing.assert_allclose(rec.poses[k, :3, :3].numpy(), R0, atol=1e-12)
    grey = open_recording(seq, "kitti-odometry", frames=slice(-1, None))
    assert grey.baseline == pytest.approx(0.54) and grey.names == ["000002"]
    np.testing.assert_allclose(grey.poses[0, :3, 3].numpy(), [0.0, 0.0, 4.0], atol=1e-9)


def test_kitti_odometry_without_poses_and_bad_input(tmp_path) -> None:
    seq = _write_odometry(tmp_path, 2, poses=False)
    rec = open_recording(seq, "kitti-odometry")
    assert rec.poses is None and len(rec) == 2
    (tmp_path / "dataset" / "poses").mkdir()
    (tmp_path / "dataset" / "poses" / "07.txt").write_text("1 0 0 0 0 1 0 0 0 0 1\n" * 2)
    with pytest.raises(DataError, match="07.txt: expected 12 numbers per line"):
        open_recording(seq, "kitti-odometry")
    (tmp_path / "dataset" / "poses" / "07.txt").write_text(kitti_numbers(np.eye(3, 4)) + "\n")
    with pytest.raises(DataError, match="07.txt has 1 poses, expected one per frame \\(2\\)"):
        open_recording(seq, "kitti-odometry")
    (seq / "times.txt").write_text("0.0\nsoon\n")
    with pytest.raises(DataError, match="times.txt is not a text file of numbers"):
        open_recording(seq, "kitti-odometry")
    (seq / "calib.txt").unlink()
    with pytest.raises(MissingDataError, match="no calib.txt in .*07 \\(expected a KITTI odometry sequence"):
        open_recording(seq, "kitti-odometry")
