"""Small numeric helpers: an epsilon per dtype and safe divisions."""

from __future__ import annotations

import torch

__all__ = ["eps_like", "safe_div"]

# One epsilon per dtype (as theseus' global_params does) rather than a bare 1e-8 that
# vanishes in float16 and is needlessly coarse in float64.
_EPS = {
    torch.float16: 1e-3,
    torch.bfloat16: 1e-2,
    torch.float32: 1e-6,
    torch.float64: 1e-12,
}


def eps_like(x: torch.Tensor) -> float:
    """The epsilon to clamp divisors of ``x``'s dtype with: one per dtype, so it neither vanishes in half precision nor
    is needlessly coarse in float64.

    Args:
        x: a tensor; only its dtype is read.

    Returns:
        Python float: 1e-3 (float16), 1e-2 (bfloat16), 1e-6 (float32, also for other dtypes), 1e-12 (float64).

    Example:
        >>> eps_like(torch.zeros(1, dtype=torch.float64))
        1e-12
    """
    return _EPS.get(x.dtype, 1e-6)


def safe_div(num: torch.Tensor, den: torch.Tensor, eps: float | None = None) -> torch.Tensor:
    """``num / den`` with ``|den|`` clamped away from zero, its sign kept, so values and gradients stay finite.

    Args:
        num: numerator, any shape broadcastable with ``den``.
        den: denominator.
        eps: smallest ``|den|``; default :func:`eps_like` of ``den``.

    Returns:
        the quotient, broadcast shape.

    Example:
        >>> safe_div(torch.tensor([1.0, 1.0]), torch.tensor([0.0, -2.0]))
        tensor([ 1.0000e+06, -5.0000e-01])
    """
    eps = eps_like(den) if eps is None else eps
    sign = torch.where(den < 0, -torch.ones_like(den), torch.ones_like(den))
    return num / (sign * den.abs().clamp_min(eps))
