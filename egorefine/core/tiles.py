"""Per-tile shares of a mask, in numpy (no torch pass over a full map on the CPU)."""

from __future__ import annotations

import numpy as np

__all__ = ["tile_shares"]


def tile_shares(mask: np.ndarray, tile: int) -> np.ndarray:
    """Share of True pixels in each ``tile`` x ``tile`` block of the last two axes of ``mask``.

    Blocks cut by the far image borders count only their own pixels, as ``avg_pool2d(..., ceil_mode=True)`` does.
    numpy, because on the CPU a torch reduction over a full map wakes torch's OpenMP threads, which then spin beside
    the compiled kernels that run next.

    Args:
        mask: ``(..., H, W)`` bool (or 0/1) array.
        tile: block size in pixels, >= 1.

    Returns:
        ``(..., ceil(H / tile), ceil(W / tile))`` float64 shares in [0, 1].

    Example:
        >>> m = np.zeros((5, 6), bool); m[:4, :4] = True; m[4, 5] = True
        >>> tile_shares(m, 4).tolist()  # the bottom-right block holds 2 pixels, one of them True
        [[1.0, 0.0], [0.0, 0.5]]
    """
    H, W = mask.shape[-2:]
    h, w = -(-H // tile), -(-W // tile)
    padded = np.zeros((*mask.shape[:-2], h * tile, w * tile), dtype=np.int32)
    padded[..., :H, :W] = mask
    counts = padded.reshape(*mask.shape[:-2], h, tile, w, tile).sum(axis=(-3, -1))
    rows = np.minimum(tile, H - tile * np.arange(h))[:, None]
    cols = np.minimum(tile, W - tile * np.arange(w))[None, :]
    return counts / (rows * cols)
