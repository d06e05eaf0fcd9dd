"""CPU inference path of :func:`egorefine.stereo.fill_invalid`, compiled with numba: one pass over the pixels.

``numpy.where`` with a mask that changes from pixel to pixel (the holes of a local matcher) is one pass per output
and slow on such masks; here the three outputs come from one pass, a select per pixel over the mask's bytes. The
outputs are the torch path's values (a pick, no arithmetic). Rows run as nogil bands on
:class:`egorefine.core._jit.Workers`.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core._jit import AVAILABLE, Workers, thread_count
from ..core._jit import jit as _jit
from ..core._jit import split as _split

__all__ = ["AVAILABLE", "fill_invalid"]


if AVAILABLE:

    @_jit
    def _fill(keep, d1, v1, d2, v2, ok2, start, stop, d_out, v_out, ok_out):
        """Flat pixels ``[start, stop)``: the primary's values where ``keep`` (uint8 0/1), the secondary's elsewhere."""
        keep, d1, v1, d2, v2, ok2 = (keep[start:stop], d1[start:stop], v1[start:stop], d2[start:stop],
                                     v2[start:stop], ok2[start:stop])
        d_out, v_out, ok_out = d_out[start:stop], v_out[start:stop], ok_out[start:stop]
        for i in range(keep.shape[0]):
            k = keep[i] != 0
            a, b, c, e = d1[i], d2[i], v1[i], v2[i]  # (both loaded: a select, not a branch, so SIMD code)
            d_out[i] = a if k else b
            v_out[i] = c if k else e
            ok_out[i] = keep[i] | ok2[i]


def fill_invalid(primary: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
                 secondary: tuple[torch.Tensor, torch.Tensor, torch.Tensor], threads: int | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(disparity, valid, variance)`` of :func:`egorefine.stereo.fill_invalid` for float32 CPU maps ``(B, 1, H,
    W)`` with bool masks, in one pass."""
    shape = primary[0].shape
    d1, ok1, v1 = (t.detach().contiguous().reshape(-1).numpy() for t in primary)
    d2, ok2, v2 = (t.detach().contiguous().reshape(-1).numpy() for t in secondary)
    n = d1.shape[0]
    d_out, v_out, ok_out = np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.uint8)
    threads = thread_count(threads)
    keep, other = ok1.view(np.uint8), ok2.view(np.uint8)
    Workers(threads).map(lambda c: _fill(keep, d1, v1, d2, v2, other, c[0], c[1], d_out, v_out, ok_out),
                         _split(n, threads))
    return (torch.from_numpy(d_out).view(shape), torch.from_numpy(ok_out.view(np.bool_)).view(shape),
            torch.from_numpy(v_out).view(shape))
