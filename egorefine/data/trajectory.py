"""Trajectory files in the two text formats that evaluation tools (``evo``, the TUM and KITTI devkits) read.

TUM: one pose per line, ``timestamp tx ty tz qx qy qz qw`` (seconds, metres, a unit quaternion with the scalar
last), space separated, lines starting with ``#`` are comments.
KITTI: one pose per line, the 12 numbers of the top three rows of the ``4 x 4`` matrix, row by row; no timestamps.

Both store ``world_T_camera`` poses: the camera's position in the world is the last column.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion

from ..core import ShapeError, ValueRangeError, check_shape

__all__ = ["read_trajectory", "write_kitti_poses", "write_tum"]

PathLike = str | os.PathLike

# 17 significant digits: a float64 written and read back is the same number, so a file round-trips exactly.
_NUMBER = "{:.17g}"


def _pose_rows(poses: torch.Tensor) -> np.ndarray:
    check_shape(poses, ["T", "4", "4"], "poses")
    return poses.detach().to("cpu", torch.float64).numpy()


def write_tum(path: PathLike, poses: torch.Tensor, timestamps: np.ndarray | torch.Tensor | None = None) -> Path:
    """Write ``world_T_camera`` poses as a TUM trajectory file.

    Args:
        path: the text file to write.
        poses: ``(T, 4, 4)`` rigid transforms ``world_T_camera``.
        timestamps: ``(T,)`` seconds; default the frame index (0, 1, 2, ...), which keeps the file valid where a
            sequence has no clock.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Example:
        >>> import tempfile
        >>> p = write_tum(Path(tempfile.mkdtemp()) / "t.txt", torch.eye(4)[None].repeat(2, 1, 1))
        >>> p.read_text().splitlines()[-1]
        '1 0 0 0 0 0 0 1'
    """
    rows = _pose_rows(poses)
    T = rows.shape[0]
    stamps = np.arange(T, dtype=np.float64) if timestamps is None else np.asarray(timestamps, dtype=np.float64)
    if stamps.shape != (T,):
        raise ShapeError(f"timestamps: expected shape ({T},) to match poses, got {tuple(stamps.shape)}")
    # kornia gives (w, x, y, z); TUM stores (x, y, z, w). The sign is fixed so that w >= 0 (q and -q are one turn).
    q = rotation_matrix_to_quaternion(torch.from_numpy(rows[:, :3, :3]).contiguous()).numpy()
    q = np.where(q[:, :1] < 0, -q, q)
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for stamp, pose, (w, x, y, z) in zip(stamps, rows, q, strict=True):
        values = [*pose[:3, 3], x, y, z, w]
        lines.append(" ".join([f"{stamp:.9f}".rstrip("0").rstrip("."), *(_NUMBER.format(v) for v in values)]))
    path = Path(path)
    path.write_text("\n".join(lines) + "\n")
    return path


def write_kitti_poses(path: PathLike, poses: torch.Tensor) -> Path:
    """Write ``world_T_camera`` poses as a KITTI pose file (12 numbers a line: the top 3x4 block, row by row).

    Args:
        path: the text file to write.
        poses: ``(T, 4, 4)`` rigid transforms ``world_T_camera``.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Example:
        >>> import tempfile
        >>> p = write_kitti_poses(Path(tempfile.mkdtemp()) / "k.txt", torch.eye(4)[None])
        >>> p.read_text()
        '1 0 0 0 0 1 0 0 0 0 1 0\\n'
    """
    rows = _pose_rows(poses)
    path = Path(path)
    path.write_text("".join(" ".join(_NUMBER.format(v) for v in pose[:3].reshape(-1)) + "\n" for pose in rows))
    return path


def read_trajectory(path: PathLike) -> tuple[np.ndarray | None, torch.Tensor]:
    """Read a TUM or KITTI trajectory file; the format is told by the number of columns (8 or 12).

    Args:
        path: the text file. Blank lines and lines starting with ``#`` are skipped; numbers may be separated by
            spaces, tabs or commas.

    Returns:
        ``(timestamps, poses)``: ``(T,)`` seconds (None for a KITTI file) and ``(T, 4, 4)`` float64
        ``world_T_camera``.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueRangeError: a line is not numbers, the lines differ in length, the column count is neither 8 nor 12,
            a quaternion is zero, or the file holds no pose.

    Example:
        >>> import tempfile
        >>> p = write_kitti_poses(Path(tempfile.mkdtemp()) / "k.txt", torch.eye(4)[None].repeat(3, 1, 1))
        >>> stamps, poses = read_trajectory(p)
        >>> stamps is None, poses.shape
        (True, torch.Size([3, 4, 4]))
    """
    name = os.fspath(path)
    with open(path) as f:
        text = f.read()
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            rows.append([float(v) for v in line.replace(",", " ").split()])
        except ValueError:
            raise ValueRangeError(f"{name}: line {number} is not a row of numbers: {line[:60]!r}") from None
        if len(rows[-1]) != len(rows[0]):
            raise ValueRangeError(f"{name}: line {number} has {len(rows[-1])} numbers, the first row {len(rows[0])}")
    if not rows:
        raise ValueRangeError(f"{name}: holds no pose")
    data = np.asarray(rows, dtype=np.float64)
    T = data.shape[0]
    poses = np.tile(np.eye(4), (T, 1, 1))
    if data.shape[1] == 12:
        poses[:, :3, :] = data.reshape(T, 3, 4)
        return None, torch.from_numpy(poses)
    if data.shape[1] != 8:
        raise ValueRangeError(f"{name}: expected 8 columns (TUM) or 12 (KITTI), got {data.shape[1]}")
    q = data[:, [7, 4, 5, 6]]  # (w, x, y, z) for kornia
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    if (norm < 1e-12).any():
        raise ValueRangeError(f"{name}: line {int(np.argmin(norm[:, 0])) + 1} of poses has a zero quaternion")
    poses[:, :3, :3] = quaternion_to_rotation_matrix(torch.from_numpy(q / norm)).numpy()
    poses[:, :3, 3] = data[:, 1:4]
    return data[:, 0].copy(), torch.from_numpy(poses)
