"""Synthetic rectified pairs with exact disparity for the stereo tests (a local stand-in for the renderer)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d


def smooth_texture(batch: int, height: int, width: int, seed: int, sigma: float = 1.2) -> torch.Tensor:
    """Band-limited random texture in [0, 1] (multi-scale blurred noise), ``(B, 1, H, W)``."""
    gen = torch.Generator().manual_seed(seed)
    pad = 2 * int(27 * sigma) + 2  # blur a larger canvas, then crop: no border effects
    tex = torch.zeros(batch, 1, height + 2 * pad, width + 2 * pad, dtype=torch.float64)
    for s, w in ((sigma, 1.0), (3 * sigma, 1.5), (9 * sigma, 2.0)):
        noise = torch.rand(tex.shape, generator=gen, dtype=torch.float64)
        k = 2 * int(3 * s) + 1
        tex += w * gaussian_blur2d(noise, (k, k), (s, s), border_type="reflect")
    tex = tex[..., pad : pad + height, pad : pad + width]
    tex = tex - tex.amin(dim=(2, 3), keepdim=True)
    return tex / tex.amax(dim=(2, 3), keepdim=True)


def planar_pair(batch: int = 1, height: int = 64, width: int = 96, seed: int = 0, base: float = 6.0,
                slope_x: float = 0.02, slope_y: float = 0.01) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Left/right float32 images of a textured plane with left-view disparity ``base + sx*x + sy*y``.

    The left image *is* the texture; the right image samples it at ``x = xr + d(x)`` (solved exactly for a
    plane), so ``disparity`` is exact. Returns ``(left, right, disparity)``, each ``(B, 1, H, W)``.
    """
    left = smooth_texture(batch, height, width, seed)
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                            indexing="ij")
    disparity = base + slope_x * xs + slope_y * ys
    # right pixel xr sees the left point x with x - d(x) = xr  =>  x = (xr + base + sy*y) / (1 - sx)
    x_src = (xs + base + slope_y * ys) / (1.0 - slope_x)
    grid = torch.stack([2 * x_src / (width - 1) - 1, 2 * ys / (height - 1) - 1], dim=-1)
    right = F.grid_sample(left, grid.expand(batch, -1, -1, -1), mode="bicubic", padding_mode="border",
                          align_corners=True).clamp(0, 1)
    return left.float(), right.float(), disparity.expand(batch, 1, height, width).float().clone()


def visible(disparity: torch.Tensor, margin: int) -> torch.Tensor:
    """Pixels whose right-view match lies inside the image with ``margin`` px to spare on every side."""
    _, _, h, w = disparity.shape
    x = torch.arange(w).view(1, 1, 1, w)
    y = torch.arange(h).view(1, 1, h, 1)
    xr = x - disparity
    return (xr >= margin) & (x < w - margin) & (y >= margin) & (y < h - margin)
