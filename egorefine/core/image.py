"""Image helpers shared by the stages."""

from __future__ import annotations

import torch
from kornia.color import rgb_to_grayscale

__all__ = ["to_grey"]


def to_grey(image: torch.Tensor) -> torch.Tensor:
    """``(B, 1|3, H, W)`` -> ``(B, 1, H, W)``: colour through kornia's luma weights, grey passed through.

    >>> to_grey(torch.ones(2, 3, 4, 5)).shape
    torch.Size([2, 1, 4, 5])
    """
    return rgb_to_grayscale(image) if image.shape[1] == 3 else image
