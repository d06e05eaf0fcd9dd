"""Image helpers shared by the stages."""

from __future__ import annotations

import torch
from kornia.color import rgb_to_grayscale

from .dispatch import needs_grad, tracing

__all__ = ["to_grey"]

# Elements per piece of a CPU conversion: ATen's grain size (``at::internal::GRAIN_SIZE``), up to which an
# elementwise op runs on the calling thread instead of waking torch's OpenMP threads.
_PIECE = 32768
# kornia's luma weights (rgb_to_grayscale's defaults), made into tensors of the image's dtype as kornia does
_LUMA = (0.299, 0.587, 0.114)


def to_grey(image: torch.Tensor) -> torch.Tensor:
    """Grey version of an image batch: colour through kornia's luma weights (``rgb_to_grayscale``), grey passed through.

    On the CPU, without autograd or a tracer, kornia's three operations run on pieces of rows, each small enough
    that torch keeps it on the calling thread: an operation over a whole image wakes torch's OpenMP threads, which
    then spin on the other cores for a while, beside the compiled kernels that usually come next, and slow them
    (docs/decisions.md). The operations are kornia's, so the values are too.

    Args:
        image: ``(B, 1, H, W)`` or ``(B, 3, H, W)`` float image.

    Returns:
        ``(B, 1, H, W)``; the input itself when it is grey already.

    Example:
        >>> to_grey(torch.ones(2, 3, 4, 5)).shape
        torch.Size([2, 1, 4, 5])
    """
    if image.shape[1] != 3:
        return image
    B, _, H, W = image.shape
    rows = _PIECE // max(1, B * W)
    if (image.device.type != "cpu" or needs_grad(image) or tracing() or rows == 0 or rows >= H
            or image.dtype not in (torch.float32, torch.float64)):
        return rgb_to_grayscale(image)
    w_r, w_g, w_b = torch.tensor(_LUMA, dtype=image.dtype).unbind()
    out = torch.empty(B, 1, H, W, dtype=image.dtype)
    for y in range(0, H, rows):
        r, g, b = image[:, :, y : y + rows].unbind(dim=1)
        piece = out[:, 0, y : y + rows]
        torch.mul(r, w_r, out=piece)
        torch.addcmul(piece, g, w_g, out=piece)
        torch.addcmul(piece, b, w_b, out=piece)
    return out
