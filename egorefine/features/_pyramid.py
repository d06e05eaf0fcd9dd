"""The grey image pyramid of the tracker: a 3x3 binomial blur and a stride-2 subsampling per level.

A pixel ``x`` of level 0 lies at ``x / 2^l`` on level ``l``. :func:`build_pyramid` is public (re-exported by
:mod:`egorefine.features` and :mod:`egorefine.features.tracking`): a caller that tracks a video builds each frame's
pyramid once and passes it to both calls that use that frame.
"""

from __future__ import annotations

import torch

from ..core import ValueRangeError, check_shape, to_grey, use_compiled
from . import _track_numba

__all__ = ["build_pyramid"]


# 3x3 binomial kernel [1, 2, 1]^T [1, 2, 1] / 16 as anti-aliasing, evaluated only at the kept
# (even) pixels by strided slicing: pixel 2i of level l becomes pixel i of level l+1, so
# x_{l+1} = x_l / 2. This costs a fraction of kornia's pyrdown (5x5 blur and bilinear resize),
# which matters here: the pyramid is a large part of the tracking time.
def _pyrdown(x: torch.Tensor) -> torch.Tensor:
    if use_compiled(x):
        return _track_numba.pyrdown(x)  # the same operations compiled
    # The border row/column is repeated by concatenation (cheaper than F.pad's replicate mode).
    x = torch.cat([x[..., :1, :], x, x[..., -1:, :]], dim=-2)
    rows = x[..., 0:-2:2, :] + x[..., 2::2, :] + 2 * x[..., 1:-1:2, :]
    rows = torch.cat([rows[..., :1], rows, rows[..., -1:]], dim=-1)
    return (rows[..., 0:-2:2] + rows[..., 2::2] + 2 * rows[..., 1:-1:2]) * 0.0625


def build_pyramid(image: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """Grey image pyramid used by :func:`track`: level 0 is the (grey) input, each next level half the size.

    A pixel ``(x, y)`` of level 0 lies at ``(x, y) / 2^l`` on level ``l``.

    Args:
        image: ``(B, 1, H, W)`` or ``(B, 3, H, W)`` float image.
        levels: number of levels (>= 1).

    Returns:
        list of ``levels`` tensors ``(B, 1, H_l, W_l)`` with ``H_{l+1} = ceil(H_l / 2)``.

    >>> [p.shape[-1] for p in build_pyramid(torch.rand(1, 3, 32, 40), 3)]
    [40, 20, 10]
    """
    gray = to_grey(image)
    pyr = [gray]
    for _ in range(levels - 1):
        pyr.append(_pyrdown(pyr[-1]))
    return pyr


def _given_pyramid(
    pyramid: list[torch.Tensor] | None, name: str, levels: int, dims: dict[str, int]
) -> list[torch.Tensor] | None:
    """Check a caller's pyramid (from :func:`build_pyramid`) and return its first ``levels`` levels."""
    if pyramid is None:
        return None
    if not isinstance(pyramid, (list, tuple)) or len(pyramid) < levels:
        raise ValueRangeError(f"{name}: expected a list of at least levels={levels} tensors from build_pyramid")
    h, w = dims["H"], dims["W"]
    for level in range(levels):
        check_shape(pyramid[level], ["B", "1", "H", "W"], f"{name}[{level}]", {"B": dims["B"], "H": h, "W": w})
        h, w = (h + 1) // 2, (w + 1) // 2
    return list(pyramid[:levels])
