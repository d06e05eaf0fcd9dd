"""open_recording on layouts the tests write themselves, and on the real EuRoC clip."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from egorefine.core import DataError, EgorefineError, MissingDataError, ValueRangeError
from egorefine.data import LAYOUTS, StereoRecording, load_euroc, open_recording

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


def _write_opencv(path: Path, **mats) -> Path:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in mats.items():
        fs.write(k, np.asarray(v, dtype=np.float64))
    fs.release()
    return path


def _aligned_rig(path: Path) -> Path:
    """An OpenCV stereoCalibrate file of two identical, aligned, distortion-free cameras B apart."""
    return _write_opencv(path, K1=_K(), D1=np.zeros(5), K2=_K(), D2=np.zeros(5), R=np.eye(3),
                         T=np.array([[-B], [0.0], [0.0]]), image_size=np.array([W, H]))


def _kitti_row(M: np.ndarray) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(M).reshape(-1))


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
    (tmp_path / "calib.txt").write_text(f"P0: {_kitti_row(_P(0.0))}\nP1: {_kitti_row(_P(-B))}\n")
    rec = open_recording(tmp_path, "folders")
    assert rec.rectified_input and rec.baseline == pytest.approx(B)
    left, right = rec[0]
    torch.testing.assert_close(left[0, 0], torch.from_numpy(lefts[0]).float() / 255, atol=1 / 255, rtol=0)
    # The plane sits at disparity DISP: right(x) == left(x + DISP).
    torch.testing.assert_close(right[0, 0, :, : W - DISP], left[0, 0, :, DISP:], atol=1 / 255, rtol=0)


def test_folders_calib_elsewhere_and_frame_slice(tmp_path) -> None:
    _write_pairs(tmp_path / "rec" / "cam0", tmp_path / "rec" / "cam1", 5)
    calib = _aligned_rig(tmp_path / "stereo.json")
    rec = open_recording(tmp_path / "rec", "folders", calib=calib, frames=slice(1, None, 2))
    assert rec.names == ["000001", "000003"] and rec.baseline == pytest.approx(B)
    assert rec.left_files[0].name == "000001.png" and rec.right_files[1].name == "000003.png"


def test_folders_image_size_from_first_frame(tmp_path) -> None:
    _write_pairs(tmp_path / "left", tmp_path / "right", 1)
    _write_opencv(tmp_path / "calib.yml", M1=_K(), M2=_K(), R=np.zeros(3), T=np.array([-B, 0.0, 0.0]))
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
    assert LAYOUTS == ("folders", "kitti-raw", "kitti-odometry", "euroc")


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
    _write_opencv(tmp_path / "calib.yaml", K1=_K(), K2=_K(), R=np.eye(3), T=[-B, 0, 0], image_size=[W + 8, H])
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


def test_errors_are_typed() -> None:
    assert issubclass(DataError, EgorefineError) and issubclass(DataError, ValueError)
    assert issubclass(MissingDataError, DataError) and issubclass(MissingDataError, FileNotFoundError)
