"""The compiled matchers' texture check and masking (census + SGM, its band), compiled with numba: one pass.

The float path's texture check (:func:`egorefine.stereo.match_stereo`) is
``box_mean_same(|prefilter_xsobel(grey, cap)|, block) >= threshold``: about twenty full-map passes (padding, the
Sobel's differences, the clip, two box sums of shifted additions, the division), then the masking of the matcher's
maps where the check fails. Here each band of rows computes its clipped Sobel rows, their box sums and the decision,
and clears the maps, without a full-map temporary.

The decisions are the float path's pixel for pixel, also for values on the threshold: the same float32 operations
in the same order (the Sobel as ``(D(y-1) + 2 D(y)) + D(y+1)`` of the replicated image, the box sums in the order
of :func:`egorefine.stereo.cost.box_sum_valid`, its sums of power-of-two runs, then the division by ``block**2``).
Rows run as nogil bands on :class:`egorefine.core._jit.Workers`.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core._jit import AVAILABLE, Workers, thread_count
from ..core._jit import jit as _jit
from ..core._jit import split as _split

__all__ = ["AVAILABLE", "mask_rows", "mask_untextured"]


if AVAILABLE:

    @_jit
    def _box_sums(src, n, k, out, ping, pong):
        """``box_sum_valid`` of rows ``[0, n)`` of ``src`` ``(rows, m)`` along the rows, in its order of additions:
        row ``i`` of ``out`` is the sum of rows ``i .. i + k - 1``, as the power-of-two runs that make up ``k``,
        smallest first, each run a sum of two halves. ``ping``, ``pong``: scratch the size of ``src``."""
        m = src.shape[1]
        rows = n - k + 1
        first = True
        offset = 0
        size = 1
        cur = src
        length = n
        flip = False
        while True:
            if k & size:
                for i in range(rows):
                    a, o = cur[offset + i], out[i]
                    if first:
                        for j in range(m):
                            o[j] = a[j]
                    else:
                        for j in range(m):
                            o[j] = o[j] + a[j]
                first = False
                offset += size
            if size * 2 > k:
                break
            nxt = pong if flip else ping
            flip = not flip
            length -= size
            for i in range(length):
                a, b, o = cur[i], cur[i + size], nxt[i]
                for j in range(m):
                    o[j] = a[j] + b[j]
            cur = nxt
            size *= 2

    @_jit
    def _mask_rows(grey, k, cap, threshold, y0, y1, disparity, valid, variance, invalid):
        """Rows ``[y0, y1)`` of the maps ``(H, W)``: ``valid`` and the texture check, ``disparity`` 0 and ``variance``
        ``invalid`` where not valid. ``grey`` ``(H, W)`` float32."""
        H, W = grey.shape
        r = k // 2
        n = y1 - y0 + 2 * r
        wp = W + 2 * r
        gx = np.empty((n, wp), np.float32)  # |clipped Sobel| of the rows y0 - r .. y1 + r, replicated by r
        lo, hi = -cap, cap
        for i in range(n):
            y = min(max(y0 - r + i, 0), H - 1)
            above, own, below = grey[max(y - 1, 0)], grey[y], grey[min(y + 1, H - 1)]
            row = gx[i]
            for x in range(1, W - 1):  # the interior: no clamped index, SIMD code
                g = ((above[x + 1] - above[x - 1]) + np.float32(2.0) * (own[x + 1] - own[x - 1])) + (
                    below[x + 1] - below[x - 1])
                row[x + r] = abs(min(max(g, lo), hi))
            for x in (0, W - 1):
                xm, xq = max(x - 1, 0), min(x + 1, W - 1)
                g = ((above[xq] - above[xm]) + np.float32(2.0) * (own[xq] - own[xm])) + (below[xq] - below[xm])
                row[x + r] = abs(min(max(g, lo), hi))
            for xp in range(r):  # replicated columns
                row[xp] = row[r]
                row[W + r + xp] = row[W + r - 1]
        m = y1 - y0
        vertical = np.empty((m, wp), np.float32)
        ping, pong = np.empty((n, wp), np.float32), np.empty((n, wp), np.float32)
        _box_sums(gx, n, k, vertical, ping, pong)
        # the horizontal sums: the same order along the rows of the transpose
        across = np.ascontiguousarray(vertical.T)
        sums = np.empty((W, m), np.float32)
        _box_sums(across, wp, k, sums, np.empty((wp, m), np.float32), np.empty((wp, m), np.float32))
        area = np.float32(k * k)
        for i in range(m):
            y = y0 + i
            ok, d, var = valid[y], disparity[y], variance[y]
            for x in range(W):
                keep = ok[x] & (sums[x, i] / area >= threshold)
                ok[x] = keep
                d[x] = d[x] if keep else np.float32(0.0)
                var[x] = var[x] if keep else invalid


def mask_rows(grey: np.ndarray, block_size: int, cap: float, threshold: float, y0: int, y1: int,
              disparity: np.ndarray, valid: np.ndarray, variance: np.ndarray, invalid: float) -> None:
    """Rows ``[y0, y1)`` of one map's :func:`mask_untextured`, in place (``grey`` and the maps ``(H, W)`` numpy):
    for a caller that has those rows in cache (the 3-path census + SGM, stripe by stripe)."""
    _mask_rows(grey, int(block_size), np.float32(cap), np.float32(threshold), y0, y1, disparity, valid, variance,
               np.float32(invalid))


def mask_untextured(out: tuple[torch.Tensor, torch.Tensor, torch.Tensor], grey: torch.Tensor, block_size: int,
                    cap: float, threshold: float, invalid: float, threads: int | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A compiled matcher's fresh ``(disparity, valid, variance)`` with the texture check applied and the maps
    cleared where not valid, in place.

    Args:
        out: ``(B, 1, H, W)`` contiguous CPU maps, float32 / bool / float32, written in place.
        grey: ``(B, 1, H, W)`` float32 CPU left image.
        block_size, cap, threshold: the check's window, Sobel clip and threshold (as ``match_stereo``).
        invalid: the variance of a pixel that is not valid.
        threads: worker threads (None: ``torch.get_num_threads()``).

    Returns:
        ``out``.
    """
    disparity, valid, variance = out
    b, _, h, w = grey.shape
    g = grey.detach().contiguous().numpy()
    d, v, var = disparity.numpy(), valid.numpy(), variance.numpy()
    settings = (int(block_size), np.float32(cap), np.float32(threshold))
    threads = thread_count(threads)
    jobs = [(i, rows) for i in range(b) for rows in _split(h, threads, h * w)]
    Workers(threads).map(lambda job: _mask_rows(g[job[0], 0], *settings, *job[1], d[job[0], 0], v[job[0], 0],
                                                var[job[0], 0], np.float32(invalid)), jobs)
    return out
