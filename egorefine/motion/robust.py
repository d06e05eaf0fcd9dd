"""Robust kernels for iteratively reweighted least squares on pixel residuals.

Each kernel is given as its loss ``rho(r)`` and its IRLS weight ``rho'(r) / r`` of the
residual norm ``r >= 0`` (pixels) and a scale ``k`` (pixels). Huber is convex (a bad track
keeps some pull, linear in its error); Tukey's biweight is redescending (a track further
than ``k`` from the model gets weight 0, as a moving object or a lost track should).
"""

from __future__ import annotations

import torch

__all__ = ["robust_loss", "robust_weight", "LOSSES"]

LOSSES = ("l2", "huber", "tukey")

# Tuning constants for 95 % efficiency under Gaussian noise of unit scale.
HUBER_K = 1.345
TUKEY_C = 4.685


def robust_loss(r: torch.Tensor, loss: str, scale: float) -> torch.Tensor:
    """Robust loss ``rho(r)`` of residual norms ``r >= 0``: the cost the exact motion solve minimises.

    ``"l2"`` is ``r^2 / 2``; ``"huber"`` is quadratic up to ``1.345 scale``, then linear; ``"tukey"`` (the biweight)
    saturates at ``c^2 / 6`` beyond ``c = 4.685 scale``. Those constants give 95 % efficiency under Gaussian noise of
    standard deviation ``scale``, the textbook choice.

    Args:
        r: residual norms in pixels, any shape, >= 0.
        loss: ``"l2"``, ``"huber"`` or ``"tukey"``.
        scale: the residual scale in pixels (the inlier noise level).

    Returns:
        the loss, ``r``'s shape.

    Example:
        >>> robust_loss(torch.tensor([0.0, 1.0, 100.0]), "tukey", 1.0)
        tensor([0.0000, 0.4776, 3.6582])
    """
    if loss == "l2":
        return 0.5 * r * r
    if loss == "huber":
        k = HUBER_K * scale
        return torch.where(r <= k, 0.5 * r * r, k * (r - 0.5 * k))
    c = TUKEY_C * scale
    s = (1 - (r / c).clamp(max=1.0) ** 2) ** 3
    return c * c / 6 * (1 - s)


def robust_weight(r: torch.Tensor, loss: str, scale: float) -> torch.Tensor:
    """IRLS weight ``rho'(r) / r`` of residual norms ``r >= 0``, in ``[0, 1]``: the weight of a feature in the next
    weighted least-squares solve of eq. (3).

    Args:
        r: residual norms in pixels, any shape, >= 0.
        loss: ``"l2"`` (all weights 1), ``"huber"`` or ``"tukey"`` (0 beyond ``4.685 scale``: an outlier stops pulling).
        scale: the residual scale in pixels.

    Returns:
        weights in ``[0, 1]``, ``r``'s shape.

    Example:
        >>> robust_weight(torch.tensor([0.0, 2.69, 100.0]), "huber", 1.0)
        tensor([1.0000, 0.5000, 0.0135])
    """
    if loss == "l2":
        return torch.ones_like(r)
    if loss == "huber":
        k = HUBER_K * scale
        # k / r only where r > k, so the division never sees r = 0.
        return k / r.clamp_min(k)
    c = TUKEY_C * scale
    return (1 - (r / c).clamp(max=1.0) ** 2) ** 2
