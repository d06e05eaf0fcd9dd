"""Synthetic images with known geometry for the feature tests (seeded, no files)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def smooth_texture(seed: int, height: int = 120, width: int = 160, batch: int = 1) -> torch.Tensor:
    """Multi-scale random texture in [0, 1] (sum of bicubically upsampled noise octaves), seeded."""
    g = torch.Generator().manual_seed(seed)
    out = torch.zeros(batch, 1, height, width, dtype=torch.float64)
    for cell, amp in [(32, 1.0), (16, 0.7), (8, 0.5), (4, 0.35)]:
        noise = torch.rand(batch, 1, height // cell + 3, width // cell + 3, generator=g, dtype=torch.float64)
        up = F.interpolate(noise, scale_factor=cell, mode="bicubic", align_corners=False)
        out += amp * up[..., :height, :width]
    lo = out.amin(dim=(1, 2, 3), keepdim=True)
    hi = out.amax(dim=(1, 2, 3), keepdim=True)
    return ((out - lo) / (hi - lo)).float()


def checker_corner(x0: float, y0: float, height: int = 40, width: int = 48, supersample: int = 16) -> torch.Tensor:
    """An X-junction (two dark and two bright quadrants) meeting at (x0, y0), area-anti-aliased."""
    s = supersample
    offs = (torch.arange(s, dtype=torch.float64) + 0.5) / s - 0.5
    ys = torch.arange(height, dtype=torch.float64).view(-1, 1, 1, 1) + offs.view(1, 1, s, 1)
    xs = torch.arange(width, dtype=torch.float64).view(1, -1, 1, 1) + offs.view(1, 1, 1, s)
    bright = ((xs - x0) * (ys - y0) > 0).double()
    img = 0.2 + 0.6 * bright.mean(dim=(2, 3))
    return img.float().view(1, 1, height, width)
