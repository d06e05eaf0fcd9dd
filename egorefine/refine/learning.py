"""Learnable parts of the loop: small networks that read each stereo measurement and adjust it before fusion.

:class:`~egorefine.refine.EgoMotionRefiner` takes two optional networks, both handed the same ``(B, NET_INPUTS, H,
W)`` tensor of :func:`measurement_features` (the grey left image, the measured disparity divided by
``max_disparity``, the measurement's validity, where it came from the hole fill, and the sub-pixel phase of the
disparity as its cosine and sine):

- ``confidence_net`` maps it to a ``(B, 1, H, W)`` positive scale of the measurement variance ``R``. A scale above 1
  says "trust this measurement less than the matcher does": in Kalman mode the gain ``P / (P + sR)`` drops and the
  gate ``k sqrt(P + sR)`` widens, so the prediction keeps more of its value there. Paper mode's fixed gain does not
  read ``R``, so there the network only changes the carried variance.
- ``correction_net`` maps it to a ``(B, 1, H, W)`` offset in px added to the measured disparity where it is valid:
  a learned correction of the matcher's systematic errors (the sub-pixel fit's pull towards whole pixels, the
  fill's bias at depth edges), which every predicted frame until the next verification inherits.

:class:`ConfidenceNet` and :class:`CorrectionNet` are ready-made such networks: a few 3x3 convolutions whose last
layer starts at zero, so that an untrained refiner gives exactly the outputs of one without a network.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..core import ShapeError, ValueRangeError

__all__ = ["ConfidenceNet", "CorrectionNet", "NET_INPUTS", "measurement_features"]

# channels of measurement_features: grey left, disparity / max_disparity, validity, filled, cos and sin of the phase
NET_INPUTS = 6


def measurement_features(grey: torch.Tensor, disparity: torch.Tensor, valid: torch.Tensor,
                         filled: torch.Tensor | None, max_disparity: float) -> torch.Tensor:
    """The tensor a refiner hands its networks for one stereo measurement.

    Channels, in order: ``grey``; ``disparity / max_disparity`` (0 where not valid); ``valid`` as 0/1; ``filled``
    as 0/1 (pixels the hole fill supplied; zeros where there is no fill); ``cos(2 pi d)`` and ``sin(2 pi d)`` of
    the disparity ``d`` in px (0 where not valid): the sub-pixel phase, on which a sub-pixel fit's bias depends,
    as a smooth input a convolution can use.

    Args:
        grey: ``(B, 1, H, W)`` left image in [0, 1].
        disparity: ``(B, 1, H, W)`` measured disparity, px.
        valid: ``(B, 1, H, W)`` bool, the measurement's validity.
        filled: ``(B, 1, H, W)`` bool, or None (no fill).
        max_disparity: the stereo search's upper end, px (the disparity channel's scale).

    Returns:
        ``(B, NET_INPUTS, H, W)`` in ``grey``'s dtype.

    Example:
        >>> d = torch.full((1, 1, 4, 5), 10.25)
        >>> x = measurement_features(torch.rand(1, 1, 4, 5), d, d > 0, None, 32)
        >>> x.shape, round(float(x[0, 5, 0, 0]), 3)
        (torch.Size([1, 6, 4, 5]), 1.0)
    """
    dtype = grey.dtype
    m = valid.to(dtype)
    d = disparity.to(dtype) * m
    phase = 2 * math.pi * d
    f = torch.zeros_like(m) if filled is None else filled.to(dtype)
    return torch.cat([grey, d / max_disparity, m, f, torch.cos(phase) * m, torch.sin(phase) * m], dim=1)


def _conv_body(width: int, layers: int) -> nn.Sequential:
    """``layers`` 3x3 convolutions from NET_INPUTS channels to 1, ReLU between them, the last one zero."""
    if int(width) < 1 or int(layers) < 1:
        raise ValueRangeError(f"width and layers: expected integers >= 1, got {width}, {layers}")
    chans = [NET_INPUTS] + [int(width)] * (int(layers) - 1) + [1]
    convs: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(chans[:-1], chans[1:], strict=True)):
        convs.append(nn.Conv2d(a, b, 3, padding=1, padding_mode="replicate"))
        if i < len(chans) - 2:
            convs.append(nn.ReLU())
    body = nn.Sequential(*convs)
    nn.init.zeros_(body[-1].weight)
    nn.init.zeros_(body[-1].bias)
    return body


class _BoundedConvNet(nn.Module):
    """The shared body of the ready-made networks: ``_conv_body`` and a positive ``bound`` on its squashed
    output; a subclass says in ``_squash`` how ``bound * tanh(z / bound)`` becomes its output."""

    def __init__(self, width: int, layers: int, bound: float) -> None:
        super().__init__()
        if not float(bound) > 0:
            raise ValueRangeError(f"bound: expected > 0, got {bound}")
        self.body = _conv_body(width, layers)
        self.bound = float(bound)

    def _squash(self, z: torch.Tensor) -> torch.Tensor:
        return z

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() != 4 or x.shape[1] != NET_INPUTS:
            raise ShapeError(f"x: expected (B, {NET_INPUTS}, H, W), got {tuple(x.shape)}")
        return self._squash(self.bound * torch.tanh(self.body(x) / self.bound))


class ConfidenceNet(_BoundedConvNet):
    """A small convolutional network giving a per-pixel scale of the measurement variance.

    ``scale = exp(bound * tanh(z / bound))`` with ``z`` the output of ``layers`` 3x3 convolutions (``width``
    channels, ReLU between them): smooth, bounded to ``[exp(-bound), exp(bound)]`` (never 0, Inf or NaN for finite
    inputs), and exactly 1 before training because the last convolution starts at zero.

    Args:
        width: channels of the hidden layers (8: a few hundred weights, cheap beside the matcher).
        layers: convolutions in all (>= 1); their 3x3 windows see ``2 * layers + 1`` px.
        bound: the largest log-scale either way (4: the variance may change by up to ~55x).

    Shape:
        - Input: ``(B, NET_INPUTS, H, W)``, :func:`measurement_features`.
        - Output: ``(B, 1, H, W)``, positive.

    Example:
        >>> net = ConfidenceNet()
        >>> x = torch.rand(2, NET_INPUTS, 24, 32)
        >>> s = net(x)
        >>> s.shape, bool((s == 1).all())
        (torch.Size([2, 1, 24, 32]), True)
    """

    def __init__(self, width: int = 8, layers: int = 3, bound: float = 4.0) -> None:
        super().__init__(width, layers, bound)

    def _squash(self, z: torch.Tensor) -> torch.Tensor:
        return torch.exp(z)


class CorrectionNet(_BoundedConvNet):
    """A small convolutional network giving a per-pixel offset of the measured disparity, in px.

    ``offset = bound * tanh(z / bound)`` with ``z`` the output of ``layers`` 3x3 convolutions (``width`` channels,
    ReLU between them): smooth, within ``(-bound, bound)``, and exactly 0 before training because the last
    convolution starts at zero. Meant for the sub-pixel part of a matcher's error, hence the default bound of
    one pixel: whole-pixel mismatches are for the fusion's gate, not for a correction.

    Args:
        width: channels of the hidden layers (16).
        layers: convolutions in all (>= 1; 4: a 9x9 px view, about the matcher's block and its neighbours).
        bound: the largest offset either way, px (1).

    Shape:
        - Input: ``(B, NET_INPUTS, H, W)``, :func:`measurement_features`.
        - Output: ``(B, 1, H, W)``, px.

    Example:
        >>> net = CorrectionNet()
        >>> x = torch.rand(2, NET_INPUTS, 24, 32)
        >>> o = net(x)
        >>> o.shape, bool((o == 0).all())
        (torch.Size([2, 1, 24, 32]), True)
    """

    def __init__(self, width: int = 16, layers: int = 4, bound: float = 1.0) -> None:
        super().__init__(width, layers, bound)
