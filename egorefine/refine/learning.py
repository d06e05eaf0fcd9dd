"""Learnable parts of the loop: a small network that scales the matcher's measurement variance.

:class:`~egorefine.refine.EgoMotionRefiner` takes ``confidence_net``: any ``nn.Module`` that maps a ``(B, 3, H, W)``
tensor (the grey left image, the measured disparity divided by ``max_disparity``, the measurement's validity as
0/1) to a ``(B, 1, H, W)`` positive scale of the measurement variance ``R`` used by the fusion. A scale above 1
says "trust this measurement less than the matcher does": in Kalman mode the gain ``P / (P + sR)`` drops and the
gate ``k sqrt(P + sR)`` widens, so the prediction keeps more of its value there. Paper mode's fixed gain does not
read ``R``, so there the network only changes the carried variance.

:class:`ConfidenceNet` is a ready-made such network: a few 3x3 convolutions whose last layer starts at zero, so
that an untrained refiner gives exactly the outputs of one without a network.
"""

from __future__ import annotations

import torch
from torch import nn

from ..core import ShapeError, ValueRangeError

__all__ = ["ConfidenceNet", "CONFIDENCE_INPUTS"]

# channels of the tensor the refiner hands a confidence network: grey left, disparity / max_disparity, validity
CONFIDENCE_INPUTS = 3


class ConfidenceNet(nn.Module):
    """A small convolutional network giving a per-pixel scale of the measurement variance.

    ``scale = exp(bound * tanh(z / bound))`` with ``z`` the output of ``layers`` 3x3 convolutions (``width``
    channels, ReLU between them): smooth, bounded to ``[exp(-bound), exp(bound)]`` (never 0, Inf or NaN for finite
    inputs), and exactly 1 before training because the last convolution starts at zero.

    Args:
        width: channels of the hidden layers (8: a few hundred weights, cheap beside the matcher).
        layers: convolutions in all (>= 1); their 3x3 windows see ``2 * layers + 1`` px.
        bound: the largest log-scale either way (4: the variance may change by up to ~55x).

    Shape:
        - Input: ``(B, 3, H, W)`` as the refiner builds it (module docstring).
        - Output: ``(B, 1, H, W)``, positive.

    Example:
        >>> net = ConfidenceNet()
        >>> x = torch.rand(2, 3, 24, 32)
        >>> s = net(x)
        >>> s.shape, bool((s == 1).all())
        (torch.Size([2, 1, 24, 32]), True)
    """

    def __init__(self, width: int = 8, layers: int = 3, bound: float = 4.0) -> None:
        super().__init__()
        if int(width) < 1 or int(layers) < 1:
            raise ValueRangeError(f"width and layers: expected integers >= 1, got {width}, {layers}")
        if not float(bound) > 0:
            raise ValueRangeError(f"bound: expected > 0, got {bound}")
        chans = [CONFIDENCE_INPUTS] + [int(width)] * (int(layers) - 1) + [1]
        convs = []
        for i, (a, b) in enumerate(zip(chans[:-1], chans[1:], strict=True)):
            convs.append(nn.Conv2d(a, b, 3, padding=1, padding_mode="replicate"))
            if i < len(chans) - 2:
                convs.append(nn.ReLU())
        self.body = nn.Sequential(*convs)
        nn.init.zeros_(self.body[-1].weight)
        nn.init.zeros_(self.body[-1].bias)
        self.bound = float(bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() != 4 or x.shape[1] != CONFIDENCE_INPUTS:
            raise ShapeError(f"x: expected (B, {CONFIDENCE_INPUTS}, H, W), got {tuple(x.shape)}")
        z = self.body(x)
        return torch.exp(self.bound * torch.tanh(z / self.bound))
