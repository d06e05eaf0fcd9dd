"""Stereo sequences stored as two folders of image files (one per camera), matched by sorted file name."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import torch

from ..core import DataError, MissingDataError, ShapeError, ValueRangeError

__all__ = ["ImageFolderSequence", "read_grey"]


def read_grey(path: str | os.PathLike, device: torch.device | str | None = None,
              dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Read an image file as a grey tensor in [0, 1] (8- or 16-bit, grey or colour), as the stages take it.

    Colour files go to grey with OpenCV's luma weights; integer files are scaled by their type's maximum.

    Args:
        path: the image file (any format OpenCV decodes: PNG, JPEG, TIFF, ...).
        device: device of the result; default torch's default device.
        dtype: dtype of the result; default float32, the library's working type.

    Returns:
        ``(1, 1, H, W)`` tensor in [0, 1].

    Raises:
        MissingDataError: no file at ``path`` (a ``FileNotFoundError`` too).
        DataError: the file is not an image OpenCV can decode.

    Example:
        >>> import tempfile, pathlib, cv2, numpy as np
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "left.png"
        >>> _ = cv2.imwrite(str(path), np.full((24, 32), 255, np.uint8))
        >>> img = read_grey(path)
        >>> img.shape, float(img.max())
        (torch.Size([1, 1, 24, 32]), 1.0)
    """
    if not Path(path).is_file():
        raise MissingDataError(f"path: no image file at {os.fspath(path)!r}")
    raw = cv2.imread(os.fspath(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise DataError(f"path: {os.fspath(path)!r} is not an image file OpenCV can decode")
    return torch.from_numpy(_grey(raw))[None, None].to(device=device, dtype=dtype)


def _grey(raw: np.ndarray, code: int | None = None) -> np.ndarray:
    """A decoded image (``(H, W)`` or ``(H, W, C)``; colour in OpenCV's BGR(A) order unless the conversion ``code``
    says otherwise) as ``(H, W)`` float32 grey in [0, 1]: colour through the luma weights, integers scaled by their
    type's maximum."""
    if raw.ndim == 3:
        if code is None:
            code = cv2.COLOR_BGRA2GRAY if raw.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        raw = cv2.cvtColor(raw, code)
    if raw.dtype == np.uint8:
        return np.divide(raw, 255.0, dtype=np.float32)  # one pass; the same values as a cast, then a division
    if raw.dtype == np.uint16:
        return np.divide(raw, 65535.0, dtype=np.float32)
    return np.clip(raw.astype(np.float32), 0.0, 1.0)


class ImageFolderSequence:
    """Left/right image pairs from two folders, sorted by file name, as grey tensors.

    Args:
        left_dir, right_dir: folders of the left and right camera's frames.
        pattern: glob pattern of the frame files in both folders.
        device, dtype: where and as what the frames are returned.

    Indexing (``seq[t]``, negative indices too) and iteration yield ``(left, right)``, each ``(1, 1, H, W)``
    float in [0, 1]; ``len(seq)`` is the number of pairs.

    Raises:
        FileNotFoundError: a folder does not exist.
        ValueRangeError: no frames, or the folders hold different numbers of frames.

    Example:
        >>> import tempfile, pathlib
        >>> root = pathlib.Path(tempfile.mkdtemp())
        >>> for side in ("left", "right"):
        ...     (root / side).mkdir()
        ...     for t in range(3):
        ...         _ = cv2.imwrite(str(root / side / f"{t:06d}.png"), np.zeros((24, 32), np.uint8))
        >>> seq = ImageFolderSequence(root / "left", root / "right")
        >>> len(seq), seq[0][0].shape, seq[-1][1].shape
        (3, torch.Size([1, 1, 24, 32]), torch.Size([1, 1, 24, 32]))
    """

    def __init__(self, left_dir: str | os.PathLike, right_dir: str | os.PathLike, pattern: str = "*.png",
                 device: torch.device | str | None = None, dtype: torch.dtype = torch.float32) -> None:
        folders = []
        for name, d in (("left_dir", left_dir), ("right_dir", right_dir)):
            p = Path(d)
            if not p.is_dir():
                raise FileNotFoundError(f"{name}: {os.fspath(d)!r} is not a folder")
            folders.append(sorted(f for f in p.glob(pattern) if f.is_file()))
        self.left_files, self.right_files = folders
        if not self.left_files:
            raise ValueRangeError(f"left_dir: no files match {pattern!r} in {os.fspath(left_dir)!r}")
        if len(self.left_files) != len(self.right_files):
            raise ValueRangeError(
                f"right_dir: {len(self.right_files)} files match {pattern!r}, but left_dir has {len(self.left_files)}"
            )
        self.device, self.dtype = device, dtype

    def __len__(self) -> int:
        return len(self.left_files)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        if not -len(self) <= index < len(self):
            raise IndexError(f"index: {index} out of range for {len(self)} frames")
        left = read_grey(self.left_files[index], self.device, self.dtype)
        right = read_grey(self.right_files[index], self.device, self.dtype)
        if left.shape != right.shape:
            raise ShapeError(f"right: frame {index} has shape {tuple(right.shape)}, left {tuple(left.shape)}")
        return left, right

    def __iter__(self) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        for i in range(len(self)):
            yield self[i]
