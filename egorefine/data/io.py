"""Disparity file formats: PFM (Middlebury, SceneFlow) and KITTI's 16-bit disparity PNG.

PFM: a text header ``PF`` (3 channels) or ``Pf`` (1 channel), ``width height``, and a scale whose sign gives the
byte order (negative: little endian), then float32 rows stored bottom to top.
KITTI: uint16 PNG with ``disparity = value / 256``; 0 marks pixels without ground truth.
"""

from __future__ import annotations

import os

import cv2
import numpy as np
import torch

from ..core import ShapeError, ValueRangeError

__all__ = ["read_pfm", "write_pfm", "read_kitti_disparity", "write_kitti_disparity"]

PathLike = str | os.PathLike


def _as_chw(data: torch.Tensor | np.ndarray, name: str) -> np.ndarray:
    """``(H, W)``, ``(C, H, W)`` or ``(1, C, H, W)`` tensor/array -> float32 numpy ``(C, H, W)``."""
    arr = data.detach().cpu().numpy() if isinstance(data, torch.Tensor) else np.asarray(data)
    if arr.ndim == 4 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise ShapeError(f"{name}: expected shape (H, W), (C, H, W) or (1, C, H, W), got {tuple(arr.shape)}")
    return arr.astype(np.float32, copy=False)


def _read_token(f, path: PathLike) -> bytes:
    """Next whitespace-separated header token of a PFM file."""
    token = b""
    while True:
        c = f.read(1)
        if not c:
            raise ValueRangeError(f"path: {os.fspath(path)!r} ends inside the PFM header")
        if c.isspace():
            if token:
                return token
            continue
        token += c


def read_pfm(path: PathLike) -> torch.Tensor:
    """Read a PFM file as a float32 tensor ``(C, H, W)`` (C = 1 or 3), top row first.

    Raises:
        ValueRangeError: the file is not a PFM file or is truncated.
    """
    with open(path, "rb") as f:
        magic = _read_token(f, path)
        if magic not in (b"PF", b"Pf"):
            raise ValueRangeError(f"path: {os.fspath(path)!r} is not a PFM file (magic {magic!r})")
        channels = 3 if magic == b"PF" else 1
        try:
            width, height = int(_read_token(f, path)), int(_read_token(f, path))
            scale = float(_read_token(f, path))
        except ValueError as err:
            raise ValueRangeError(f"path: {os.fspath(path)!r} has a malformed PFM header") from err
        if width <= 0 or height <= 0 or scale == 0:
            raise ValueRangeError(f"path: {os.fspath(path)!r} has a bad PFM header ({width}x{height}, {scale})")
        dtype = np.dtype("<f4") if scale < 0 else np.dtype(">f4")
        count = width * height * channels
        data = np.frombuffer(f.read(count * 4), dtype=dtype)
    if data.size != count:
        raise ValueRangeError(f"path: {os.fspath(path)!r} is truncated ({data.size} of {count} values)")
    img = data.reshape(height, width, channels)[::-1]  # rows are stored bottom to top
    return torch.from_numpy(img.transpose(2, 0, 1).astype(np.float32, order="C", copy=True))


def write_pfm(path: PathLike, data: torch.Tensor | np.ndarray, little_endian: bool = True, scale: float = 1.0) -> None:
    """Write ``data`` ``(H, W)``, ``(C, H, W)`` or ``(1, C, H, W)`` with C = 1 or 3 as a PFM file (float32).

    Args:
        path: file to write.
        data: the map, top row first.
        little_endian: byte order (stored as the sign of the scale).
        scale: the header's scale magnitude (> 0); values are stored as they are.
    """
    arr = _as_chw(data, "data")
    if arr.shape[0] not in (1, 3):
        raise ShapeError(f"data: expected 1 or 3 channels, got shape {tuple(arr.shape)}")
    if not scale > 0:
        raise ValueRangeError(f"scale: expected > 0, got {scale}")
    channels, height, width = arr.shape
    rows = np.ascontiguousarray(arr.transpose(1, 2, 0)[::-1], dtype="<f4" if little_endian else ">f4")
    header = f"{'PF' if channels == 3 else 'Pf'}\n{width} {height}\n{-scale if little_endian else scale:g}\n"
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(rows.tobytes())


def read_kitti_disparity(path: PathLike) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a KITTI disparity PNG: disparity ``(1, H, W)`` float32 in pixels and validity ``(1, H, W)`` bool.

    Raises:
        FileNotFoundError: no readable image at ``path``.
        ValueRangeError: the image is not a single-channel 16-bit PNG.
    """
    raw = cv2.imread(os.fspath(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise FileNotFoundError(f"path: cannot read an image at {os.fspath(path)!r}")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise ValueRangeError(f"path: expected a single-channel uint16 PNG, got {raw.dtype} with shape {raw.shape}")
    valid = raw > 0
    disp = raw.astype(np.float32) / 256.0
    return torch.from_numpy(disp)[None], torch.from_numpy(valid)[None]


def write_kitti_disparity(
    path: PathLike, disparity: torch.Tensor | np.ndarray, valid: torch.Tensor | np.ndarray | None = None
) -> None:
    """Write disparity ``(H, W)``, ``(1, H, W)`` or ``(1, 1, H, W)`` as a KITTI uint16 PNG (``value = round(256 d)``).

    Pixels that are invalid (``valid`` False), non-finite or not positive are written as 0; valid disparities are
    clipped to ``[1/256, 65535/256]`` so they stay distinguishable from invalid ones.
    """
    d = _as_chw(disparity, "disparity")
    if d.shape[0] != 1:
        raise ShapeError(f"disparity: expected one channel, got shape {tuple(d.shape)}")
    d = d[0]
    ok = np.isfinite(d) & (d > 0)
    if valid is not None:
        v = valid.detach().cpu().numpy() if isinstance(valid, torch.Tensor) else np.asarray(valid)
        v = v.reshape(v.shape[-2:]) if v.size == d.size else v
        if v.shape != d.shape:
            raise ShapeError(f"valid: expected {d.shape} pixels, got shape {tuple(v.shape)}")
        ok &= v.astype(bool)
    value = np.where(ok, np.clip(np.round(np.nan_to_num(d) * 256.0), 1, 65535), 0).astype(np.uint16)
    if not cv2.imwrite(os.fspath(path), value):
        raise ValueRangeError(f"path: could not write a PNG to {os.fspath(path)!r}")

