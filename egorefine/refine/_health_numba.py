"""CPU inference path of :func:`egorefine.refine.health.disagreeing_regions`, compiled with numba.

One pass over the pixels per row of tiles: the pixels valid in both maps and those of them that differ by more
than the threshold are counted per column (SIMD code), the columns summed per tile, and each tile's decision
written over its pixels. The decision repeats the torch path's float32 formulas (``avg_pool2d``'s shares: a count
over the tile's pixels inside the image, compared as there), so the two paths agree bit for bit (a test compares
them). Tile rows run as nogil bands on :class:`egorefine.core._jit.Workers`.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core._jit import AVAILABLE, Workers, thread_count
from ..core._jit import jit as _jit
from ..core._jit import split as _split

__all__ = ["AVAILABLE", "disagreeing_regions"]


if AVAILABLE:

    @_jit
    def _regions(predicted, predicted_ok, measured, measured_ok, tile, px, min_support, share, row0, row1, out):
        """Tile rows ``[row0, row1)`` of the ``(H, W)`` maps of one item into ``out`` ``(H, W)`` bool: a tile is
        set where its share of pixels valid in both maps is at least ``min_support`` and the share of those that
        differ by more than ``px`` exceeds ``share`` times it (float32 shares of its pixels inside the image)."""
        H, W = predicted.shape
        columns = np.empty(W, np.int32)  # per column: both + (off << 16), each at most tile**2 < 2**16
        decision = np.empty(W, np.bool_)
        for ty in range(row0, row1):
            y0, y1 = ty * tile, min(H, ty * tile + tile)
            for x in range(W):
                columns[x] = 0
            for y in range(y0, y1):
                p, po, m, mo = predicted[y], predicted_ok[y], measured[y], measured_ok[y]
                for x in range(W):
                    both = po[x] & mo[x]
                    far = abs(p[x] - m[x]) > px
                    columns[x] += (np.int32(1 + (1 << 16)) if far else np.int32(1)) if both else np.int32(0)
            for x0 in range(0, W, tile):
                x1 = min(W, x0 + tile)
                total = 0
                for x in range(x0, x1):
                    total += columns[x]
                area = np.float32((y1 - y0) * (x1 - x0))
                support, share_off = np.float32(total & 0xFFFF) / area, np.float32(total >> 16) / area
                region = (support >= min_support) & (share_off > share * support)
                for x in range(x0, x1):
                    decision[x] = region
            for y in range(y0, y1):
                row = out[y]
                for x in range(W):
                    row[x] = decision[x]


def disagreeing_regions(predicted: torch.Tensor, predicted_valid: torch.Tensor, measured: torch.Tensor,
                        measured_valid: torch.Tensor, tile: int, px: float, min_support: float, share: float,
                        threads: int | None = None) -> torch.Tensor:
    """:func:`egorefine.refine.health.disagreeing_regions`' rule on float32 CPU maps ``(B, 1, H, W)`` (bool
    masks), with its constants as arguments: ``(B, 1, H, W)`` bool."""
    B, _, H, W = predicted.shape
    p, po, m, mo = (t.detach().contiguous()[:, 0].numpy() for t in (predicted, predicted_valid, measured,
                                                                    measured_valid))
    out = torch.empty(predicted.shape, dtype=torch.bool)
    o = out[:, 0].numpy()
    threads = thread_count(threads)
    rows = -(-H // tile)
    jobs = [(b, band) for b in range(B) for band in _split(rows, threads, H * W)]
    settings = (np.float32(px), np.float32(min_support), np.float32(share))
    Workers(threads).map(lambda job: _regions(p[job[0]], po[job[0]], m[job[0]], mo[job[0]], tile, *settings, *job[1],
                                              o[job[0]]), jobs)
    return out
