"""The 16-bit maps of :mod:`egorefine.data.results` turned into PNG scanlines in one compiled pass (numba).

The numpy path of :func:`egorefine.data.write_kitti_disparity` and of the confidence writer scales the map, clips it,
rounds it, converts it to uint16, masks it, swaps its bytes to PNG's big-endian order and copies the rows behind
their filter bytes: seven passes over the map, about as long as writing the file. Here each value goes once from the
float32 map to its two bytes in the scanline. The operations are numpy's, in its order (a float32 product, the
lower clip taking NaN to the bound as ``np.fmax`` does, the upper clip, ``rint``'s ties to even), so the bytes are
the same (``tests/data/test_io.py``).

Used where :func:`egorefine.core.use_compiled` allows it (numba importable, the dispatch rule); the numpy path stays
the reference.
"""

from __future__ import annotations

import numpy as np

from ..core._jit import AVAILABLE
from ..core._jit import jit as _jit

__all__ = ["AVAILABLE", "scaled_rows"]


if AVAILABLE:

    @_jit
    def _rows(values, ok, has_ok, scale, low, high, rows):
        """``rows`` ``(H, 1 + 2 W)`` uint8: each row's filter byte 0 ("none") and the big-endian uint16 of
        ``rint(min(fmax(values * scale, low), high))``, 0 where ``ok`` is False (``has_ok``; else ``ok`` is unused)."""
        H, W = values.shape
        for y in range(H):
            v, o, out = values[y], ok[y if has_ok else 0], rows[y]
            out[0] = 0
            for x in range(W):
                s = v[x] * scale
                s = s if s >= low else low  # (NaN fails the test: the bound, as np.fmax gives)
                s = s if s < high else high
                q = np.uint16(np.rint(s))
                q = q if (o[x] or not has_ok) else np.uint16(0)
                out[1 + 2 * x] = np.uint8(q >> 8)
                out[2 + 2 * x] = np.uint8(q & 255)


def scaled_rows(values: np.ndarray, scale: float, low: float, high: float, ok: np.ndarray | None = None
                ) -> np.ndarray:
    """PNG scanlines (filter "none") of the uint16 ``rint(clip(values * scale, low, high))``, 0 where ``ok`` is False.

    Args:
        values: ``(H, W)`` float32 map (C-contiguous).
        scale, low, high: the scale and the clip bounds (NaN becomes ``low``).
        ok: ``(H, W)`` bool, or None (every pixel written).

    Returns:
        ``(H, 1 + 2 W)`` uint8: what :func:`egorefine.data.io._png_rows` gives for that uint16 image with ``"fast"``.
    """
    h, w = values.shape
    rows = np.empty((h, 1 + 2 * w), np.uint8)
    mask = np.ones((1, 1), np.bool_) if ok is None else np.ascontiguousarray(ok)
    _rows(np.ascontiguousarray(values, np.float32), mask, ok is not None, np.float32(scale), np.float32(low),
          np.float32(high), rows)
    return rows
