"""Loader for EuRoC MAV stereo sequences in the ASL folder layout, rectified with OpenCV.

Layout (``root``)::

    mav0/cam0/data.csv, mav0/cam0/data/<timestamp>.png, mav0/cam0/sensor.yaml   (left)
    mav0/cam1/...                                                                (right)
    groundtruth/body_poses.csv  (#time(ns), px, py, pz, qw, qx, qy, qz, ...)   or
    mav0/state_groundtruth_estimate0/data.csv                                    (the dataset's original)
                                                                   (ground truth optional: poses are then None)

``sensor.yaml`` gives ``T_BS`` (sensor-to-body), pinhole ``intrinsics`` (fu, fv, cu, cv) and radial-tangential
``distortion_coefficients``. The camera pose is ``T_WB @ T_BS``; after rectification it is expressed for the
rectified left camera (``X_rect = R1 X_cam0``). Rectification is :func:`egorefine.data.rectify_maps`'s.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..core import DataError, MissingDataError, ValueRangeError
from ._sequence import SequenceMixin
from .calib import StereoCalibration, _remap, _stereo_rectify, rectify_maps
from .folder import read_grey

__all__ = ["EurocSequence", "load_euroc", "read_euroc_sensor"]

# Ground-truth and image time stamps closer than this are the same instant: a millisecond, far below the
# cameras' frame interval (20 Hz).
_TIME_TOLERANCE_NS = 1_000_000


@dataclass
class EurocSequence(SequenceMixin):
    """A (rectified) EuRoC stereo clip.

    Attributes:
        left, right: ``(T, 1, H, W)`` grey images in [0, 1] (rectified unless loaded with ``rectify=False``).
        K: ``(3, 3)`` intrinsics of the rectified left camera (of raw cam0 when not rectified).
        baseline: metres.
        poses: ``(T, 4, 4)`` ``world_T_camera`` of the rectified left camera (raw cam0 when not rectified); None
            for a sequence without ground truth.
        timestamps: ``(T,)`` int64 nanoseconds.

    :func:`load_euroc` builds one from a EuRoC folder; ``len(seq)`` is ``T``, ``seq.to(device, dtype)`` moves it.

    Example:
        >>> poses = torch.eye(4).repeat(2, 1, 1)
        >>> poses[1, 2, 3] = 0.05  # the camera moved 5 cm forward
        >>> seq = EurocSequence(left=torch.zeros(2, 1, 24, 32), right=torch.zeros(2, 1, 24, 32), K=torch.eye(3),
        ...                     baseline=0.11, poses=poses, timestamps=torch.tensor([0, 50_000_000]))
        >>> len(seq), seq.motions.shape, round(seq.motions[1, 2, 3].item(), 6)  # a still point comes 5 cm closer
        (2, torch.Size([2, 4, 4]), -0.05)
    """

    left: torch.Tensor
    right: torch.Tensor
    K: torch.Tensor
    baseline: float
    poses: torch.Tensor | None
    timestamps: torch.Tensor

    def __repr__(self) -> str:
        T, _, H, W = self.left.shape
        return (f"EurocSequence(T={T}, H={H}, W={W}, f={float(self.K[0, 0]):.2f}, baseline={self.baseline:.4f}, "
                f"dtype={self.left.dtype}, device={self.left.device})")

    @property
    def motions(self) -> torch.Tensor | None:
        """``(T, 4, 4)`` ``camera_t_T_camera_{t-1}`` from the ground-truth poses; identity at ``t = 0``; None
        without ground truth."""
        if self.poses is None:
            return None
        m = torch.eye(4, dtype=self.poses.dtype, device=self.poses.device).repeat(len(self), 1, 1)
        if len(self) > 1:
            m[1:] = torch.linalg.inv(self.poses[1:]) @ self.poses[:-1]
        return m


def read_euroc_sensor(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read the numeric lists of an EuRoC camera ``sensor.yaml`` (a small reader: no YAML dependency).

    Args:
        path: the ``sensor.yaml`` of ``mav0/cam0`` or ``mav0/cam1``.

    Returns:
        ``{"T_BS": (4, 4), "intrinsics": (4,), "distortion_coefficients": (4,), "resolution": (2,)}`` float64 arrays:
        the camera's pose in the body frame, ``(fu, fv, cu, cv)`` in pixels, radial-tangential ``(k1, k2, p1, p2)``
        and ``(width, height)``.

    Raises:
        DataError: a list is missing.

    Example:
        >>> import tempfile, pathlib
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "sensor.yaml"
        >>> _ = path.write_text("T_BS:\\n  rows: 4\\n  data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\\n"
        ...                     "intrinsics: [458.6, 457.3, 367.2, 248.4]\\n"
        ...                     "distortion_coefficients: [-0.28, 0.07, 0.0002, 0.00002]\\nresolution: [752, 480]\\n")
        >>> s = read_euroc_sensor(path)
        >>> s["T_BS"].shape, s["resolution"].tolist()
        ((4, 4), [752.0, 480.0])
    """
    text = Path(path).read_text()
    lists = {}
    # "key: [numbers]" possibly spanning lines; T_BS's list is under its own "data:" key.
    block = re.search(r"T_BS:\s*\n(?:\s+\w+:.*\n)*?\s+data:\s*\[([^\]]*)\]", text)
    if block is None:
        raise DataError(f"path: no T_BS block in {os.fspath(path)!r}")
    lists["T_BS"] = np.array([float(v) for v in block.group(1).replace("\n", " ").split(",")]).reshape(4, 4)
    for key in ("intrinsics", "distortion_coefficients", "resolution"):
        m = re.search(rf"^{key}:\s*\[([^\]]*)\]", text, flags=re.MULTILINE)
        if m is None:
            raise DataError(f"path: no {key} list in {os.fspath(path)!r}")
        lists[key] = np.array([float(v) for v in m.group(1).split(",")])
    return lists


def _read_frames(cam_dir: Path) -> dict[int, Path]:
    """Timestamp -> image file from a camera's ``data.csv``."""
    out = {}
    for line in (cam_dir / "data.csv").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        ts, name = (s.strip() for s in line.split(",")[:2])
        out[int(ts)] = cam_dir / "data" / name
    return out


def _read_groundtruth(root: Path) -> list[tuple] | None:
    """Rows ``(t_ns, px, py, pz, qw, qx, qy, qz)`` with the time as an exact int; None without a ground-truth file."""
    for rel in ("groundtruth/body_poses.csv", "mav0/state_groundtruth_estimate0/data.csv"):
        p = root / rel
        if p.is_file():
            rows = []
            for line in p.read_text().splitlines():
                line = line.strip()
                if line and not line.startswith("#"):
                    parts = line.split(",")
                    rows.append((int(parts[0]), *(float(v) for v in parts[1:8])))
            if not rows:
                raise DataError(f"root: {p} holds no ground-truth rows")
            return rows
    return None


def _quat_to_rot(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _body_poses(rows: list, stamps: list[int]) -> np.ndarray:
    """World_T_body ``(T, 4, 4)`` at ``stamps``: linear interpolation of position, normalised lerp of quaternions."""
    times = np.array([r[0] for r in rows], dtype=np.int64)
    vals = np.array([r[1:] for r in rows], dtype=np.float64)
    out = np.tile(np.eye(4), (len(stamps), 1, 1))
    for k, ts in enumerate(stamps):  # loop over frames
        j = int(np.searchsorted(times, ts))
        near = int(np.argmin(np.abs(times - ts)))
        if abs(int(times[near]) - ts) <= _TIME_TOLERANCE_NS:  # the same instant (re-processed stamps are rounded)
            p, q = vals[near, :3], vals[near, 3:]
        else:
            if j == 0 or j == len(times):
                raise DataError(f"root: no ground truth around frame time {ts} ns")
            a = (ts - times[j - 1]) / float(times[j] - times[j - 1])
            p = (1 - a) * vals[j - 1, :3] + a * vals[j, :3]
            q0, q1 = vals[j - 1, 3:], vals[j, 3:]
            q1 = q1 if np.dot(q0, q1) >= 0 else -q1
            q = (1 - a) * q0 + a * q1
        out[k, :3, :3] = _quat_to_rot(q)
        out[k, :3, 3] = p
    return out


@dataclass
class _EurocIndex:
    """What a EuRoC folder holds, before any image is read: synchronised frames, calibration, ground truth."""

    stamps: list[int]
    left: list[Path]
    right: list[Path]
    calib: StereoCalibration
    world_T_cam0: np.ndarray | None  # (T, 4, 4); None without ground truth


def _index_euroc(root: Path, max_frames: int | None = None) -> _EurocIndex:
    cams = [root / "mav0" / "cam0", root / "mav0" / "cam1"]
    for c in cams:
        if not (c / "data.csv").is_file() or not (c / "sensor.yaml").is_file():
            raise MissingDataError(f"root: {c} lacks data.csv or sensor.yaml (expected the EuRoC ASL layout)")
    if max_frames is not None and max_frames < 1:
        raise ValueRangeError(f"max_frames: expected >= 1 or None, got {max_frames}")
    sensors = [read_euroc_sensor(c / "sensor.yaml") for c in cams]
    frames = [_read_frames(c) for c in cams]
    stamps = sorted(set(frames[0]) & set(frames[1]))
    gt_rows = _read_groundtruth(root)
    if gt_rows is not None:
        gt_t0, gt_t1 = gt_rows[0][0], gt_rows[-1][0]
        stamps = [s for s in stamps if gt_t0 - _TIME_TOLERANCE_NS <= s <= gt_t1 + _TIME_TOLERANCE_NS]
    if max_frames is not None:
        stamps = stamps[:max_frames]
    if not stamps:
        what = " with ground truth" if gt_rows is not None else ""
        raise DataError(f"root: no synchronised stereo frames{what} under {root}")
    Ks, Ds = [], []
    for s in sensors:
        fu, fv, cu, cv = s["intrinsics"]
        Ks.append(np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]]))
        Ds.append(np.asarray(s["distortion_coefficients"], dtype=np.float64))
    w, h = (int(v) for v in sensors[0]["resolution"])
    # cam1_T_cam0 = inv(T_BS1) T_BS0: OpenCV's (R, T) map points of the first camera into the second.
    c1_T_c0 = np.linalg.inv(sensors[1]["T_BS"]) @ sensors[0]["T_BS"]
    calib = StereoCalibration(K1=Ks[0], D1=Ds[0], K2=Ks[1], D2=Ds[1], R=c1_T_c0[:3, :3], T=c1_T_c0[:3, 3],
                              image_size=(h, w), source=f"{cams[0] / 'sensor.yaml'} + {cams[1] / 'sensor.yaml'}")
    world_T_cam0 = None if gt_rows is None else _body_poses(gt_rows, stamps) @ sensors[0]["T_BS"]
    return _EurocIndex(stamps=stamps, left=[frames[0][s] for s in stamps], right=[frames[1][s] for s in stamps],
                       calib=calib, world_T_cam0=world_T_cam0)


def _rectified_poses(world_T_cam: np.ndarray | None, calib: StereoCalibration) -> np.ndarray | None:
    """``world_T_rect`` of the rectified left camera from the raw left camera's poses (``X_rect = R1 X_cam``)."""
    if world_T_cam is None:
        return None
    cam_T_rect = np.eye(4)
    cam_T_rect[:3, :3] = _stereo_rectify(calib)[0].T
    return world_T_cam @ cam_T_rect


def load_euroc(
    root: str | os.PathLike,
    max_frames: int | None = None,
    rectify: bool = True,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> EurocSequence:
    """Load a EuRoC MAV stereo clip (ASL layout), rectified for stereo, with its ground-truth poses where present.

    Args:
        root: folder holding ``mav0`` (and, optionally, ``groundtruth/body_poses.csv``; with ground truth, only
            frames inside its time span are kept).
        max_frames: keep at most this many of the first synchronised frames.
        rectify: undistort and rectify both cameras with :func:`egorefine.data.rectify_maps` (``stereoRectify``,
            zero-disparity principal points, ``alpha = 0``: no invalid border); otherwise return the raw images
            with cam0's pinhole ``K``.
        device, dtype: where and as what the tensors are returned.

    Returns:
        :class:`EurocSequence`; its ``poses`` are None without ground truth.

    Raises:
        MissingDataError: ``root`` is not in the ASL layout, or a listed image is absent.
        DataError: a sensor.yaml or image that does not parse; no synchronised frames.
        ValueRangeError: ``max_frames < 1``.

    Example:
        >>> import tempfile, pathlib, cv2
        >>> root = pathlib.Path(tempfile.mkdtemp())
        >>> for cam, x in (("cam0", 0.0), ("cam1", 0.1)):  # cam1 10 cm right of cam0, both without distortion
        ...     (root / "mav0" / cam / "data").mkdir(parents=True)
        ...     _ = (root / "mav0" / cam / "sensor.yaml").write_text(
        ...         f"T_BS:\\n  rows: 4\\n  data: [1, 0, 0, {x}, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\\n"
        ...         "intrinsics: [40, 40, 16, 12]\\ndistortion_coefficients: [0, 0, 0, 0]\\nresolution: [32, 24]\\n")
        ...     _ = (root / "mav0" / cam / "data.csv").write_text("#timestamp,filename\\n0,0.png\\n50000000,1.png\\n")
        ...     for name in ("0.png", "1.png"):
        ...         _ = cv2.imwrite(str(root / "mav0" / cam / "data" / name), np.zeros((24, 32), np.uint8))
        >>> seq = load_euroc(root)
        >>> seq.left.shape, seq.K.shape, round(seq.baseline, 6), seq.timestamps.tolist(), seq.poses is None
        (torch.Size([2, 1, 24, 32]), torch.Size([3, 3]), 0.1, [0, 50000000], True)
    """
    index = _index_euroc(Path(root), max_frames)
    calib = index.calib
    if rectify:
        maps, K, baseline = rectify_maps(calib)
        poses = _rectified_poses(index.world_T_cam0, calib)
    else:
        maps, K, baseline = None, calib.K1, float(np.linalg.norm(calib.T))
        poses = index.world_T_cam0
    lefts, rights = [], []
    for files, out, i in ((index.left, lefts, 0), (index.right, rights, 1)):
        for f in files:  # loop over frames (file reads)
            img = read_grey(f).numpy()[0, 0]
            out.append(torch.from_numpy(img if maps is None else _remap(img, maps[i])))
    return EurocSequence(
        left=torch.stack(lefts)[:, None].to(device=device, dtype=dtype),
        right=torch.stack(rights)[:, None].to(device=device, dtype=dtype),
        K=torch.as_tensor(K, dtype=dtype, device=device),
        baseline=baseline,
        poses=None if poses is None else torch.as_tensor(poses, dtype=dtype, device=device),
        timestamps=torch.tensor(index.stamps, dtype=torch.int64, device=device),
    )
