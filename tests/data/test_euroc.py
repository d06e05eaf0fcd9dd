"""The EuRoC loader on the real clip in tests/data/real (the ``euroc_root`` fixture of tests/conftest.py)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from egorefine.core import ValueRangeError
from egorefine.data import EurocSequence, load_euroc, read_euroc_sensor


def _lr_dy(seq: EurocSequence) -> np.ndarray:
    """Vertical offsets of corners tracked from the left to the right image of the first pair (LK, checked back)."""
    L = (seq.left[0, 0].numpy() * 255).astype(np.uint8)
    R = (seq.right[0, 0].numpy() * 255).astype(np.uint8)
    p = cv2.goodFeaturesToTrack(L, 400, 0.01, 8)
    q, st, _ = cv2.calcOpticalFlowPyrLK(L, R, p, None, winSize=(21, 21), maxLevel=3)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(R, L, q, None, winSize=(21, 21), maxLevel=3)
    ok = (st[:, 0] == 1) & (st2[:, 0] == 1) & (np.linalg.norm(back - p, axis=-1)[:, 0] < 0.5)
    return (q - p)[ok, 0, 1]


@pytest.fixture(scope="module")
def euroc(euroc_root) -> EurocSequence:
    return load_euroc(euroc_root, max_frames=3)


def test_shapes_and_rig(euroc: EurocSequence) -> None:
    assert euroc.left.shape == (3, 1, 480, 752) and euroc.right.shape == euroc.left.shape
    assert 0 <= euroc.left.min() and euroc.left.max() <= 1 and euroc.left.std() > 0.05
    assert euroc.K.shape == (3, 3) and euroc.poses.shape == (3, 4, 4)
    assert euroc.timestamps.dtype == torch.int64 and (euroc.timestamps.diff() > 0).all()
    assert 0.105 < euroc.baseline < 0.115
    assert 400 < euroc.K[0, 0] < 480 and euroc.K[0, 0] == euroc.K[1, 1]


def test_rectified_rows_match(euroc: EurocSequence) -> None:
    dy = _lr_dy(euroc)
    assert len(dy) > 50
    assert np.median(np.abs(dy)) < 0.5


def test_raw_images_are_not_rectified(euroc_root) -> None:
    raw = load_euroc(euroc_root, max_frames=1, rectify=False)
    assert raw.left.shape == (1, 1, 480, 752)
    assert 0.105 < raw.baseline < 0.115
    assert np.median(np.abs(_lr_dy(raw))) > 2.0  # the rectification test above can fail


def test_poses_nearly_still_and_rigid(euroc: EurocSequence) -> None:
    P = euroc.poses.double()
    R = P[:, :3, :3]
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand_as(R), atol=1e-5,
                               rtol=0)
    M = euroc.motions.double()
    assert M[1:, :3, 3].norm(dim=-1).max() < 0.01  # a few millimetres per frame
    cos = ((M[1:, :3, :3].diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    assert (torch.acos(cos) * 180 / math.pi).max() < 0.5


def test_rectified_pose_is_cam0_rotated_slightly(euroc: EurocSequence, euroc_root) -> None:
    """Same optical centre as the raw cam0, optical axis turned by the small rectifying rotation only."""
    raw = load_euroc(euroc_root, max_frames=1, rectify=False)
    torch.testing.assert_close(euroc.poses[0, :3, 3], raw.poses[0, :3, 3])
    cos = (euroc.poses[0, :3, 2] * raw.poses[0, :3, 2]).sum().clamp(-1, 1)
    assert torch.acos(cos) * 180 / math.pi < 3.0
    # Ground-truth body poses are a real, moving-free platform above the floor: body z ~ 0.95 m in this clip.
    assert 0.5 < float(raw.poses[0, 2, 3]) < 1.5


def test_read_sensor_yaml(euroc_root) -> None:
    s = read_euroc_sensor(euroc_root / "mav0" / "cam0" / "sensor.yaml")
    assert s["T_BS"].shape == (4, 4) and s["T_BS"][3].tolist() == [0.0, 0.0, 0.0, 1.0]
    assert s["intrinsics"].tolist() == [458.654, 457.296, 367.215, 248.375]
    assert s["resolution"].tolist() == [752, 480] and s["distortion_coefficients"].shape == (4,)


def test_max_frames_and_errors(euroc_root, tmp_path) -> None:
    full = load_euroc(euroc_root, max_frames=2)
    assert len(full) == 2
    with pytest.raises(ValueRangeError, match="max_frames"):
        load_euroc(euroc_root, max_frames=0)
    with pytest.raises(FileNotFoundError, match="ASL layout"):
        load_euroc(tmp_path)
