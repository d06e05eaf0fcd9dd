"""Per-frame result files of ``egorefine run``: disparity, valid mask, confidence and a colour preview.

Every writer goes through :func:`atomic_path`: the file is written under a temporary name in the same folder and
renamed into place (:func:`os.replace`), so a run that stops half-way never leaves a truncated file under a final
name.

Formats (``fmt``):

- ``"png16"``: KITTI's 16-bit PNG, ``disparity = value / 256``, 0 = no disparity (invalid); confidence as a 16-bit
  PNG with ``confidence = value / 65535``.
- ``"pfm"``: float32 PFM, invalid pixels ``+inf`` (the Middlebury convention for "unknown"); confidence as PFM.
- ``"npy"``: float32 NumPy array ``(H, W)``, invalid pixels NaN; confidence as npy.

The valid mask is an 8-bit PNG (255 = valid, 0 = not) and the preview an RGB PNG in every format. A disparity file
marks non-positive values invalid (KITTI's PNG cannot store a valid 0, and a point at infinity has no depth to
refine), so a valid pixel of disparity 0 is valid in the mask and invalid in the disparity file.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from ..core import ShapeError, ValueRangeError, check_choice
from .io import (
    PNG_ENCODINGS,
    _write_uint16_map,
    read_kitti_disparity,
    read_pfm,
    write_kitti_disparity,
    write_pfm,
    write_png,
)

__all__ = [
    "DISPARITY_FORMATS",
    "atomic_path",
    "read_disparity",
    "write_confidence",
    "write_disparity",
    "write_mask",
    "write_preview",
]

PathLike = str | os.PathLike

#: format name -> file suffix of the disparity and confidence files
DISPARITY_FORMATS = {"png16": ".png", "pfm": ".pfm", "npy": ".npy"}

# The mask is always written in the "small" PNG encoding: a two-valued image deflates to a small fraction of its size
# at about the cost of storing it. The other writers take a ``png`` encoding (io.PNG_ENCODINGS).


@contextlib.contextmanager
def atomic_path(path: PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; renamed to ``path`` when the block ends without an error.

    The temporary name keeps the suffix (OpenCV picks the image format from it) and starts with a dot, so a listing
    of ``*.png`` never sees it. On an error the temporary file is removed and ``path`` is left as it was.

    Args:
        path: the final file name.

    Example:
        >>> import tempfile
        >>> target = Path(tempfile.mkdtemp()) / "a.txt"
        >>> with atomic_path(target) as tmp:
        ...     _ = tmp.write_text("done")
        >>> target.read_text(), sorted(p.name for p in target.parent.iterdir())
        ('done', ['a.txt'])
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def _plane(x: torch.Tensor | np.ndarray, name: str) -> np.ndarray:
    """``(H, W)``, ``(1, H, W)`` or ``(1, 1, H, W)`` -> numpy ``(H, W)``."""
    arr = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    while arr.ndim > 2 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 2:
        raise ShapeError(f"{name}: expected shape (H, W), (1, H, W) or (1, 1, H, W), got {tuple(arr.shape)}")
    return arr


def _check_format(fmt: str) -> str:
    if fmt not in DISPARITY_FORMATS:
        raise ValueRangeError(f"fmt: expected one of {sorted(DISPARITY_FORMATS)}, got {fmt!r}")
    return DISPARITY_FORMATS[fmt]


def _write_float(path: Path, values: np.ndarray, fmt: str) -> None:
    if fmt == "pfm":
        write_pfm(path, values)
    else:
        with open(path, "wb") as f:  # np.save on a name would append ".npy" to the temporary name
            np.save(f, values)


def write_disparity(
    stem: PathLike,
    disparity: torch.Tensor | np.ndarray,
    valid: torch.Tensor | np.ndarray,
    fmt: str = "png16",
    png: str = "fast",
) -> Path:
    """Write one disparity map in ``fmt``, its invalid pixels marked as the format marks them.

    Args:
        stem: the file name without suffix (the format's suffix is added).
        disparity: ``(H, W)`` (or ``(1, H, W)``, ``(1, 1, H, W)``) disparity in pixels.
        valid: same shape, bool; pixels that are False (and non-finite or non-positive disparities) are invalid.
        fmt: ``"png16"`` (default: KITTI's format, read by its devkit and most stereo tools; 1/256 px steps),
            ``"pfm"`` or ``"npy"`` (float32, lossless).
        png: the PNG encoding of ``"png16"``, a name in :data:`~egorefine.data.PNG_ENCODINGS`: ``"fast"``
            (default: stored, not deflated; the pixels are the same either way) or ``"small"`` (deflated).

    Returns:
        The written file.

    Example:
        >>> import tempfile
        >>> d = torch.tensor([[1.5, 2.0], [0.0, 3.25]])
        >>> p = write_disparity(Path(tempfile.mkdtemp()) / "f", d, d > 0)
        >>> p.suffix, read_disparity(p)[0].tolist(), read_disparity(p)[1].tolist()
        ('.png', [[1.5, 2.0], [0.0, 3.25]], [[True, True], [False, True]])
    """
    path = Path(os.fspath(stem) + _check_format(fmt))
    check_choice(png, PNG_ENCODINGS, "png")
    d = _plane(disparity, "disparity").astype(np.float32, copy=False)
    v = _plane(valid, "valid").astype(bool, copy=False)
    if v.shape != d.shape:
        raise ShapeError(f"valid: expected shape {d.shape} of disparity, got {v.shape}")
    with atomic_path(path) as tmp:
        if fmt == "png16":
            write_kitti_disparity(tmp, d, v, png)
        else:
            ok = v & np.isfinite(d) & (d > 0)
            _write_float(tmp, np.where(ok, d, np.inf if fmt == "pfm" else np.nan).astype(np.float32), fmt)
    return path


def write_confidence(
    stem: PathLike, confidence: torch.Tensor | np.ndarray, fmt: str = "png16", png: str = "fast"
) -> Path:
    """Write a confidence map in [0, 1]: a 16-bit PNG ``value = round(65535 c)`` for ``"png16"``, else float32.

    Args:
        stem: the file name without suffix.
        confidence: ``(H, W)`` (or with leading ones) values in [0, 1] (clipped), e.g. the refiner's
            ``1 / (1 + variance)``.
        fmt: as in :func:`write_disparity`.
        png: as in :func:`write_disparity`.

    Returns:
        The written file.

    Example:
        >>> import tempfile
        >>> import cv2
        >>> p = write_confidence(Path(tempfile.mkdtemp()) / "c", torch.tensor([[0.0, 0.5], [1.0, 2.0]]))
        >>> p.suffix, cv2.imread(str(p), cv2.IMREAD_UNCHANGED).tolist()
        ('.png', [[0, 32768], [65535, 65535]])
    """
    path = Path(os.fspath(stem) + _check_format(fmt))
    check_choice(png, PNG_ENCODINGS, "png")
    c = _plane(confidence, "confidence")
    with atomic_path(path) as tmp:
        if fmt == "png16":
            # (NaN -> 0)
            _write_uint16_map(tmp, np.ascontiguousarray(c, np.float32), 65535.0, 0.0, 65535.0, None, png)
        else:
            c = np.clip(np.nan_to_num(c.astype(np.float32)), 0.0, 1.0)
            _write_float(tmp, c, fmt)
    return path


def write_mask(path: PathLike, mask: torch.Tensor | np.ndarray) -> Path:
    """Write a boolean mask as an 8-bit PNG, 255 where True and 0 elsewhere (written atomically).

    Args:
        path: the ``.png`` file to write.
        mask: ``(H, W)`` (or with leading ones) bool or 0/1 tensor or array.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ShapeError: not one ``(H, W)`` plane.
        OSError: the file system's error (no space, no permission).

    Example:
        >>> import tempfile, pathlib, cv2
        >>> path = write_mask(pathlib.Path(tempfile.mkdtemp()) / "valid.png", torch.tensor([[True, False]]))
        >>> cv2.imread(str(path), cv2.IMREAD_UNCHANGED).tolist()
        [[255, 0]]
    """
    path = Path(path)
    m = _plane(mask, "mask").astype(bool)
    with atomic_path(path) as tmp:
        write_png(tmp, m.astype(np.uint8) * 255, "small")
    return path


def write_preview(path: PathLike, image: np.ndarray, png: str = "fast", palette: np.ndarray | None = None) -> Path:
    """Write a colour image (e.g. :func:`egorefine.viz.colorize_disparity`) as a PNG (written atomically).

    Args:
        path: the ``.png`` file to write.
        image: ``(H, W, 3)`` uint8 array, RGB order; or, with ``palette``, ``(H, W)`` uint8 indices into it (e.g.
            from :func:`egorefine.viz.disparity_palette_image`: an indexed-colour PNG, a third of the bytes).
        png: the PNG encoding, as in :func:`write_disparity`.
        palette: ``(N, 3)`` uint8 RGB colours, ``N <= 256``; default None (``image`` is RGB).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ShapeError: not an ``(H, W, 3)`` uint8 array (or ``(H, W)`` with a palette).
        ValueRangeError: an unknown ``png``.

    Example:
        >>> import tempfile, pathlib, numpy as np
        >>> write_preview(pathlib.Path(tempfile.mkdtemp()) / "preview.png", np.zeros((4, 5, 3), np.uint8)).suffix
        '.png'
    """
    path = Path(path)
    if palette is None and (image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8):
        raise ShapeError(f"rgb: expected an (H, W, 3) uint8 image, got {image.dtype} {tuple(image.shape)}")
    check_choice(png, PNG_ENCODINGS, "png")
    with atomic_path(path) as tmp:
        write_png(tmp, image, png, palette)
    return path


def read_disparity(path: PathLike) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a disparity map written in any of the formats above (told by the suffix).

    Args:
        path: a ``.png`` (KITTI 16-bit, 0 = invalid), ``.pfm`` or ``.npy`` file (non-finite or non-positive values
            are invalid).

    Returns:
        ``(disparity, valid)``, each ``(H, W)``: float32 pixels (0 where invalid) and bool.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueRangeError: an unknown suffix, or a file that is not a single-channel map.

    Example:
        >>> import tempfile
        >>> d = torch.tensor([[1.5, -1.0]])
        >>> disparity, valid = read_disparity(write_disparity(Path(tempfile.mkdtemp()) / "d", d, d > 0, fmt="npy"))
        >>> disparity.tolist(), valid.tolist()
        ([[1.5, 0.0]], [[True, False]])
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise FileNotFoundError(f"path: no file at {os.fspath(path)!r}")
    if suffix == ".png":
        d, _ = read_kitti_disparity(path)
        d = d[0].numpy()
    elif suffix == ".pfm":
        d = read_pfm(path).numpy()
        if d.shape[0] != 1:
            raise ValueRangeError(f"path: {os.fspath(path)!r} has {d.shape[0]} channels, expected a disparity map")
        d = d[0]
    elif suffix == ".npy":
        try:
            d = np.load(path, allow_pickle=False)
        except ValueError as err:
            raise ValueRangeError(f"path: {os.fspath(path)!r} is not a NumPy array file ({err})") from None
        d = _plane(d, os.fspath(path)).astype(np.float32)
    else:
        raise ValueRangeError(f"path: {os.fspath(path)!r}: expected a .png, .pfm or .npy disparity map")
    valid = np.isfinite(d) & (d > 0)
    return torch.from_numpy(np.where(valid, d, 0).astype(np.float32)), torch.from_numpy(valid)
