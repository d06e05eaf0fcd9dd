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
    """Read a PFM file (Middlebury, SceneFlow) as a float32 tensor, top row first.

    PFM stores rows bottom to top, with the byte order in the sign of the header's scale; both are undone here. Values
    are returned as stored (the scale's magnitude is not applied, as the Middlebury tools do not).

    Args:
        path: the ``.pfm`` file.

    Returns:
        ``(C, H, W)`` float32, C = 1 (``Pf``) or 3 (``PF``).

    Raises:
        ValueRangeError: the file is not a PFM file or is truncated.

    Example:
        >>> import tempfile, pathlib
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "d.pfm"
        >>> write_pfm(path, torch.tensor([[1.5, 2.0], [0.0, 3.25]]))
        >>> read_pfm(path)
        tensor([[[1.5000, 2.0000],
                 [0.0000, 3.2500]]])
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
    """Write a float map as a PFM file (float32), top row first.

    Args:
        path: file to write.
        data: ``(H, W)``, ``(C, H, W)`` or ``(1, C, H, W)`` tensor or array with C = 1 or 3, top row first.
        little_endian: byte order, stored as the sign of the scale; default little-endian, what current machines
            and readers use.
        scale: the header's scale magnitude (> 0); values are stored as they are. Default 1.

    Raises:
        ShapeError: not 1 or 3 channels.
        ValueRangeError: ``scale <= 0``.

    Example:
        >>> import tempfile, pathlib
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "d.pfm"
        >>> write_pfm(path, torch.ones(1, 4, 5))
        >>> read_pfm(path).shape
        torch.Size([1, 4, 5])
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
    """Read a KITTI disparity PNG (16-bit, ``disparity = value / 256``, 0 = no disparity).

    Args:
        path: the ``.png`` file.

    Returns:
        disparity ``(1, H, W)`` float32 in pixels (0 where invalid) and validity ``(1, H, W)`` bool.

    Raises:
        FileNotFoundError: no readable image at ``path``.
        ValueRangeError: the image is not a single-channel 16-bit PNG.

    Example:
        >>> import tempfile, pathlib
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "d.png"
        >>> write_kitti_disparity(path, torch.tensor([[1.5, 0.0]]))
        >>> read_kitti_disparity(path)
        (tensor([[[1.5000, 0.0000]]]), tensor([[[ True, False]]]))
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
    """Write a disparity map as a KITTI uint16 PNG, ``value = round(256 d)``: 1/256 px steps up to 256 px.

    Pixels that are invalid (``valid`` False), non-finite or not positive are written as 0; valid disparities are
    clipped to ``[1/256, 65535/256]`` so they stay distinguishable from invalid ones.

    Args:
        path: the ``.png`` file to write.
        disparity: ``(H, W)``, ``(1, H, W)`` or ``(1, 1, H, W)`` tensor or array, pixels.
        valid: bool of ``H x W`` pixels (any of those shapes), or None: every finite, positive pixel is valid.

    Raises:
        ShapeError: more than one channel, or ``valid`` of another size.
        ValueRangeError: the PNG could not be written.

    Example:
        >>> import tempfile, pathlib
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "d.png"
        >>> write_kitti_disparity(path, torch.full((1, 1, 4, 5), 12.25))
        >>> float(read_kitti_disparity(path)[0].max())
        12.25
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

