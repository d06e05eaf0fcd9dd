"""Semi-global aggregation (Hirschmueller's SGM) of a cost volume along 3, 4 or 8 scanline paths.

Each path is a loop over one image dimension, vectorised over the batch, the disparities
and the other image dimension. The recursion along a path ``r`` is

    L_r(p, d) = C(p, d) + min(L_r(p-r, d), L_r(p-r, d+-1) + P1, min_k L_r(p-r, k) + P2) - min_k L_r(p-r, k)

and the aggregated cost is the sum over paths. Being a min/sum recursion it is
differentiable almost everywhere (sub-gradients of min), so gradients reach the costs.
"""

from __future__ import annotations

import torch

__all__ = ["SGM_PATHS", "sgm_aggregate", "sgm_stripes"]

#: the path counts :func:`sgm_aggregate` (and ``match_stereo(sgm_paths=...)``) take
SGM_PATHS = (3, 4, 8)

# 3 paths: rows per stripe (about) and the rows above a stripe over which its top-down path starts (see sgm_stripes)
_STRIPE_ROWS = 120
_STRIPE_WARMUP = 24


def sgm_stripes(height: int) -> list[tuple[int, int, int]]:
    """The stripes of the 3-path aggregation: ``(start, stop, path_start)`` rows, a function of ``height`` only.

    With 3 paths the top-down path is the only vertical one, so the whole aggregation and the winner can run in one
    pass down each stripe of rows, the stripes side by side on threads (as OpenCV's 3-way SGBM runs its stripes).
    Each stripe's top-down path starts ``_STRIPE_WARMUP`` rows above it (``path_start``; 0 for the first) rather
    than at the image's top, so it has left its start behind by the stripe's first row: after a few dozen steps a
    path's costs forget where it started. The stripes depend on the height alone, so the results do not depend on
    the number of threads: an even number of stripes of about 120 rows (one up to 120 rows), so that two threads,
    or four, share them evenly.

    Example:
        >>> sgm_stripes(480)
        [(0, 120, 0), (120, 240, 96), (240, 360, 216), (360, 480, 336)]
        >>> sgm_stripes(100)
        [(0, 100, 0)]
    """
    count = max(1, 2 * round(height / (2 * _STRIPE_ROWS)))
    edges = [round(i * height / count) for i in range(count + 1)]
    return [(a, b, max(0, a - _STRIPE_WARMUP)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def _step(prev: torch.Tensor, cost: torch.Tensor, p1: float, p2: float) -> torch.Tensor:
    """One recursion step; ``prev``/``cost`` are ``(B, D, N)``; a zero ``prev`` starts a path (L = C)."""
    m = prev.amin(dim=1, keepdim=True)
    best = torch.minimum(prev, m + p2)
    moved = prev + p1
    # neighbours d-1 and d+1 along the disparity axis (none beyond either end)
    if best.requires_grad:  # out of place: autograd needs the inputs of each minimum
        lower = torch.cat([best[:, :1], torch.minimum(best[:, 1:], moved[:, :-1])], dim=1)
        both = torch.cat([torch.minimum(lower[:, :-1], moved[:, 1:]), lower[:, -1:]], dim=1)
        return cost - m + both
    best[:, 1:] = torch.minimum(best[:, 1:], moved[:, :-1])
    best[:, :-1] = torch.minimum(best[:, :-1], moved[:, 1:])
    return (cost - m).add_(best)


def _shift_last(x: torch.Tensor, dx: int) -> torch.Tensor:
    """``out[..., i] = x[..., i - dx]`` with zeros shifted in (zeros = no predecessor: the path starts)."""
    if dx == 0:
        return x
    zeros = torch.zeros_like(x[..., :1])
    if dx > 0:
        return torch.cat([zeros, x[..., :-1]], dim=-1)
    return torch.cat([x[..., 1:], zeros], dim=-1)


def _scan(vol: torch.Tensor, p1: float, p2: float, reverse: bool, dx: int, acc: torch.Tensor | None = None
          ) -> torch.Tensor:
    """Aggregate ``vol`` ``(N, B, D, M)`` along its first axis; each step's predecessor is shifted by ``dx`` in M.

    Without autograd the path costs are added into ``acc`` in place (no extra volume); with it
    they are stacked and added out of place.
    """
    n = vol.shape[0]
    order = range(n - 1, -1, -1) if reverse else range(n)
    prev = torch.zeros_like(vol[0])
    in_place = acc is not None and not (vol.requires_grad or acc.requires_grad)
    out: list[torch.Tensor] = [prev] * n
    for i in order:
        prev = _step(_shift_last(prev, dx), vol[i], p1, p2)
        if in_place:
            acc[i].add_(prev)
        else:
            out[i] = prev
    if in_place:
        return acc
    stacked = torch.stack(out, dim=0)
    return stacked if acc is None else acc + stacked


def sgm_aggregate(volume: torch.Tensor, p1: float, p2: float, paths: int = 4) -> torch.Tensor:
    """Sum of the SGM path costs of ``volume`` along 3 (horizontal, top-down), 4 (horizontal, vertical) or 8 (plus
    diagonal) paths.

    3 paths are OpenCV's ``StereoSGBM`` 3-way directions (left to right, right to left, top to bottom), the
    top-down one per stripe of rows (``egorefine.stereo.sgm.sgm_stripes``): a quarter less work than 4 paths and
    one pass down each stripe, less accurate where the scene's structure runs along the rows.

    Args:
        volume: ``(B, D, H, W)`` matching costs (lower is better); the disparity axis may be
            in either order (the recursion is symmetric in d).
        p1: penalty of a disparity change of one step between neighbours (>= 0).
        p2: penalty of larger changes (>= p1).
        paths: 3, 4 or 8.

    Returns:
        ``(B, D, H, W)`` aggregated costs, divided by the number of paths (a float32 multiply by ``1 / paths``;
        so their scale stays that of ``volume`` plus penalties). Without autograd about three volumes of extra
        memory are used.

    >>> sgm_aggregate(torch.rand(1, 5, 6, 7), 0.1, 0.5).shape
    torch.Size([1, 5, 6, 7])
    """
    # columns of (B, D, H): the horizontal paths first (left-to-right + right-to-left), then the others
    # added to them in place, in this order (the compiled CPU path adds them in the same order, so its
    # float32 sums are equal to these bit for bit)
    by_col = volume.permute(3, 0, 1, 2).contiguous()
    horizontal = _scan(by_col, p1, p2, True, 0, _scan(by_col, p1, p2, False, 0))
    del by_col
    # rows of (B, D, W): vertical paths (and the diagonals, which shift by one column per row)
    total = horizontal.permute(3, 1, 2, 0).contiguous()
    del horizontal
    by_row = volume.permute(2, 0, 1, 3).contiguous()
    if paths == 3:  # the top-down path per stripe, started above it (its first rows only lead into the stripe)
        parts = []
        for start, stop, path_start in sgm_stripes(by_row.shape[0]):
            path = _scan(by_row[path_start:stop], p1, p2, False, 0)[start - path_start:]
            if total.requires_grad or path.requires_grad:
                parts.append(total[start:stop] + path)
            else:
                total[start:stop].add_(path)
        total = torch.cat(parts) if parts else total
    else:
        shifts = (0, 1, -1) if paths == 8 else (0,)
        for reverse in (False, True):
            for dx in shifts:
                total = _scan(by_row, p1, p2, reverse, dx, total)
    del by_row
    total = total.permute(1, 2, 0, 3)
    # (a multiply by the float32 1 / paths, as the compiled path does: a division by 4 or 8 gives the same bits)
    if total.requires_grad:
        return total * (1.0 / paths)
    return total.mul_(1.0 / paths)
