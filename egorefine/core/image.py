"""Image helpers shared by the stages."""

from __future__ import annotations

import torch
from kornia.color import rgb_to_grayscale

__all__ = ["to_grey"]


def to_grey(image: torch.Tensor) -> torch.Tensor:
    """Grey version of an image batch: colour through kornia's luma weights (``rgb_to_grayscale``), grey passed through.

    Args:
        image: ``(B, 1, H, W)`` or ``(B, 3, H, W)`` float image.

    Returns:
        ``(B, 1, H, W)``; the input itself when it is grey already.

    Example:
        >>> to_grey(torch.ones(2, 3, 4, 5)).shape
        torch.Size([2, 1, 4, 5])
    """
    return rgb_to_grayscale(image) if image.shape[1] == 3 else image
