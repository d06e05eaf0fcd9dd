"""Semi-global aggregation (Hirschmueller's SGM) of a cost volume along 4 or 8 scanline paths.

Each path is a loop over one image dimension, vectorised over the batch, the disparities
and the other image dimension. The recursion along a path ``r`` is

    L_r(p, d) = C(p, d) + min(L_r(p-r, d), L_r(p-r, d+-1) + P1, min_k L_r(p-r, k) + P2) - min_k L_r(p-r, k)

and the aggregated cost is the sum over paths. Being a min/sum recursion it is
differentiable almost everywhere (sub-gradients of min), so gradients reach the costs.
"""

from __future__ import annotations

import torch

__all__ = ["sgm_aggregate"]


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
    """Sum of the SGM path costs of ``volume`` along 4 (horizontal, vertical) or 8 (plus diagonal) paths.

    Args:
        volume: ``(B, D, H, W)`` matching costs (lower is better); the disparity axis may be
            in either order (the recursion is symmetric in d).
        p1: penalty of a disparity change of one step between neighbours (>= 0).
        p2: penalty of larger changes (>= p1).
        paths: 4 or 8.

    Returns:
        ``(B, D, H, W)`` aggregated costs, divided by the number of paths (so their scale
        stays that of ``volume`` plus penalties). Without autograd about three volumes of
        extra memory are used.

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
    shifts = (0, 1, -1) if paths == 8 else (0,)
    for reverse in (False, True):
        for dx in shifts:
            total = _scan(by_row, p1, p2, reverse, dx, total)
    del by_row
    total = total.permute(1, 2, 0, 3)
    if total.requires_grad:
        return total / paths
    return total.div_(paths)
