"""Disparity file formats: PFM (Middlebury, SceneFlow) and KITTI's 16-bit disparity PNG.

PFM: a text header ``PF`` (3 channels) or ``Pf`` (1 channel), ``width height``, and a scale whose sign gives the
byte order (negative: little endian), then float32 rows stored bottom to top.
KITTI: uint16 PNG with ``disparity = value / 256``; 0 marks pixels without ground truth.
"""

from __future__ import annotations

import os
import struct
import zlib

import cv2
import numpy as np
import torch

from ..core import ShapeError, ValueRangeError, check_choice, use_compiled
from . import _png_numba

__all__ = ["PNG_ENCODINGS", "write_png", "read_pfm", "write_pfm", "read_kitti_disparity", "write_kitti_disparity"]

PathLike = str | os.PathLike

#: The PNG encodings :func:`write_png` knows. ``"fast"`` stores the rows as they are (no row filter, deflate's
#: "stored" blocks): the file is the raw pixels plus a few bytes of framing, written at about the speed of copying
#: them. ``"small"`` predicts each row from the one above (PNG's "up" filter) and deflates the differences with
#: zlib's fastest setting that finds runs (level 1, run-length matches only): smaller files for more time (16-bit
#: maps of sensor data shrink least, masks and previews most; docs/cli.md).
PNG_ENCODINGS = ("fast", "small")

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_rows(image: np.ndarray, png: str) -> np.ndarray:
    """The image's scanlines as PNG stores them before deflate: ``(H, 1 + row bytes)`` uint8, each a filter-type
    byte and the row's samples (big-endian), as they are (``"fast"``) or minus the row above (``"small"``)."""
    h = image.shape[0]
    raw = image.astype(image.dtype.newbyteorder(">"), copy=False).reshape(h, -1).view(np.uint8)
    rows = np.empty((h, 1 + raw.shape[1]), np.uint8)
    rows[:, 0] = 0  # filter type 0: none
    rows[:, 1:] = raw
    return rows if png == "fast" else _up_filtered(rows)


def write_png(path: PathLike, image: np.ndarray, png: str = "fast", palette: np.ndarray | None = None) -> None:
    """Write a grey, RGB or palette image of 8 or 16 bits as a PNG, in the encoding ``png``.

    Both encodings hold the same pixels and are read by any PNG reader; they differ in size and in the time it
    takes to write them (:data:`PNG_ENCODINGS`).

    Args:
        path: the file to write (its suffix is not looked at).
        image: ``(H, W)`` grey or ``(H, W, 3)`` RGB (PNG's channel order, not OpenCV's), uint8 or uint16; with
            ``palette``, ``(H, W)`` uint8 indices into it.
        png: ``"fast"`` (default: stored, not deflated) or ``"small"`` (filtered and deflated).
        palette: ``(N, 3)`` uint8 RGB colours, ``N <= 256``, for an indexed-colour PNG; default None.

    Raises:
        ShapeError: not one of those shapes and types, or an index beyond the palette.
        ValueRangeError: an unknown ``png``.
        OSError: the file system's error (no space, no permission).

    Example:
        >>> import tempfile, pathlib, cv2
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "a.png"
        >>> write_png(path, np.array([[0, 513], [65535, 7]], np.uint16))
        >>> cv2.imread(str(path), cv2.IMREAD_UNCHANGED).tolist()
        [[0, 513], [65535, 7]]
        >>> write_png(path, np.array([[0, 1]], np.uint8), "small", palette=np.array([[255, 0, 0], [0, 0, 9]], np.uint8))
        >>> cv2.imread(str(path)).tolist()  # OpenCV expands the colours, in its BGR order
        [[[0, 0, 255], [9, 0, 0]]]
    """
    check_choice(png, PNG_ENCODINGS, "png")
    if palette is not None:
        if image.dtype != np.uint8 or image.ndim != 2:
            raise ShapeError(f"image: expected (H, W) uint8 indices with a palette, got {image.dtype} "
                             f"{tuple(image.shape)}")
        if palette.dtype != np.uint8 or palette.ndim != 2 or palette.shape[1] != 3 or not 0 < len(palette) <= 256:
            raise ShapeError(f"palette: expected (N, 3) uint8 with 1 <= N <= 256, got {palette.dtype} "
                             f"{tuple(palette.shape)}")
        if image.size and int(image.max()) >= len(palette):
            raise ShapeError(f"image: index {int(image.max())} beyond the palette's {len(palette)} colours")
    elif image.dtype not in (np.uint8, np.uint16) or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise ShapeError(f"image: expected (H, W) or (H, W, 3) uint8 or uint16, got {image.dtype} "
                         f"{tuple(image.shape)}")
    h, w = image.shape[:2]
    colour_type = 3 if palette is not None else 0 if image.ndim == 2 else 2  # palette, grey, RGB
    _write_rows(path, _png_rows(image, png), w, 8 * image.itemsize, colour_type, png, palette)


def _up_filtered(rows: np.ndarray) -> np.ndarray:
    """``"fast"`` scanlines (filter "none") as ``"small"`` stores them before deflate (filter "up")."""
    out = np.empty_like(rows)
    out[:, 0] = 2  # filter type 2: up (the first row's "above" is zeros: the row itself)
    out[0, 1:] = rows[0, 1:]
    np.subtract(rows[1:, 1:], rows[:-1, 1:], out=out[1:, 1:])  # modulo 256, as PNG's filters are
    return out


def _write_uint16_map(path: PathLike, values: np.ndarray, scale: float, low: float, high: float,
                      ok: np.ndarray | None, png: str) -> None:
    """A float32 map ``(H, W)`` written as the 16-bit grey PNG of ``rint(clip(values * scale, low, high))``, 0 where
    ``ok`` (bool, same shape; None: all) is False; the values' scanlines in one compiled pass where the dispatch
    rule allows (:mod:`egorefine.data._png_numba`), else numpy's passes: the same bytes."""
    if use_compiled(torch.from_numpy(values)):
        rows = _png_numba.scaled_rows(values, scale, low, high, ok)
        _write_rows(path, rows if png == "fast" else _up_filtered(rows), values.shape[1], 16, 0, png, None)
        return
    value = np.multiply(values, scale, dtype=np.float32)
    np.fmax(value, low, out=value)  # NaN -> low (fmax takes the number)
    np.minimum(value, high, out=value)
    value = np.rint(value, out=value).astype(np.uint16)
    if ok is not None:
        value *= ok
    write_png(path, value, png)


def _write_rows(path: PathLike, rows: np.ndarray, w: int, bit_depth: int, colour_type: int, png: str,
                palette: np.ndarray | None) -> None:
    """The PNG file of the scanlines ``rows`` (:func:`_png_rows`'s, for ``png``)."""
    h = rows.shape[0]
    chunks = [(b"IHDR", struct.pack(">IIBBBBB", w, h, bit_depth, colour_type, 0, 0, 0))]
    if palette is not None:
        chunks.append((b"PLTE", np.ascontiguousarray(palette).tobytes()))
    if png == "fast":
        pixels = zlib.compress(rows, 0)
    else:
        deflate = zlib.compressobj(1, zlib.DEFLATED, 15, 8, zlib.Z_RLE)
        pixels = deflate.compress(rows) + deflate.flush()
    chunks += [(b"IDAT", pixels), (b"IEND", b"")]
    with open(path, "wb") as f:
        f.write(_PNG_SIGNATURE)
        for kind, data in chunks:
            f.write(struct.pack(">I", len(data)) + kind)
            f.write(data)
            f.write(struct.pack(">I", zlib.crc32(data, zlib.crc32(kind))))


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
    path: PathLike,
    disparity: torch.Tensor | np.ndarray,
    valid: torch.Tensor | np.ndarray | None = None,
    png: str = "fast",
) -> None:
    """Write a disparity map as a KITTI uint16 PNG, ``value = round(256 d)``: 1/256 px steps up to 256 px.

    Pixels that are invalid (``valid`` False), non-finite or not positive are written as 0; valid disparities are
    clipped to ``[1/256, 65535/256]`` so they stay distinguishable from invalid ones.

    Args:
        path: the ``.png`` file to write.
        disparity: ``(H, W)``, ``(1, H, W)`` or ``(1, 1, H, W)`` tensor or array, pixels.
        valid: bool of ``H x W`` pixels (any of those shapes), or None: every finite, positive pixel is valid.
        png: the PNG encoding, a name in :data:`PNG_ENCODINGS` (default ``"fast"``: stored, not deflated).

    Raises:
        ShapeError: more than one channel, or ``valid`` of another size.
        ValueRangeError: an unknown ``png``.
        OSError: the file system's error (no space, no permission).

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
    ok = (d > 0) & (d < np.inf)  # NaN compares False
    if valid is not None:
        v = valid.detach().cpu().numpy() if isinstance(valid, torch.Tensor) else np.asarray(valid)
        v = v.reshape(v.shape[-2:]) if v.size == d.size else v
        if v.shape != d.shape:
            raise ShapeError(f"valid: expected {d.shape} pixels, got shape {tuple(v.shape)}")
        ok &= v.astype(bool, copy=False)
    # (NaN -> 1 too; invalid pixels are written as 0)
    _write_uint16_map(path, np.ascontiguousarray(d, np.float32), 256.0, 1.0, 65535.0, ok, png)

