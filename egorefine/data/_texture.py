"""Procedural, periodic, mip-mapped albedo texture shared by every surface of a synthetic scene.

One square tile (``size`` texels, periodic in both directions) is built from band-limited noise with a
natural-image-like spectrum plus soft-edged discs and rectangles (edges and corners for feature trackers).
All mip levels are stored at full resolution and stacked along a depth axis, so a single trilinear
``grid_sample`` over ``(level, v, u)`` performs the whole mip-mapped lookup for every pixel at once.
"""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F

__all__ = ["MipTexture", "make_texture", "mip_levels"]


class MipTexture:
    """A periodic albedo tile with its mip pyramid, sampled with :meth:`sample`.

    Attributes:
        levels: ``(1, 1, L, S + 2, S + 2)`` level ``k`` low-passed for a footprint of ``2**k`` texels,
            circularly padded by one texel so bilinear lookups wrap around the tile.
        size: ``S``, texels per tile side.
    """

    def __init__(self, levels: torch.Tensor, size: int) -> None:
        self.levels = levels
        self.size = size

    @property
    def num_levels(self) -> int:
        return self.levels.shape[2]

    def sample(self, u: torch.Tensor, v: torch.Tensor, footprint: torch.Tensor) -> torch.Tensor:
        """Albedo at texel coordinates ``u, v`` ``(N,)`` (any real value; wrapped) for footprints in texels ``(N,)``."""
        s = self.size
        # Wrap into [0, S) and shift by the one-texel pad; align_corners=True maps index i to -1 + 2 i / (S + 1).
        uu = torch.remainder(u, s) + 1.0
        vv = torch.remainder(v, s) + 1.0
        level = torch.log2(footprint.clamp_min(1.0)).clamp_max(self.num_levels - 1)
        grid = torch.stack(
            [uu * (2.0 / (s + 1)) - 1.0, vv * (2.0 / (s + 1)) - 1.0, level * (2.0 / (self.num_levels - 1)) - 1.0],
            dim=-1,
        )
        out = F.grid_sample(
            self.levels, grid.view(1, 1, 1, -1, 3), mode="bilinear", padding_mode="border", align_corners=True
        )
        return out.view(-1)


def _periodic_noise(size: int, exponent: float, gen: torch.Generator) -> torch.Tensor:
    """White noise shaped to an amplitude spectrum ``1 / f**exponent``; periodic; zero mean, unit std."""
    white = torch.randn(size, size, generator=gen, dtype=torch.float64)
    spec = torch.fft.fft2(white)
    fy = torch.fft.fftfreq(size, dtype=torch.float64)[:, None]
    fx = torch.fft.fftfreq(size, dtype=torch.float64)[None, :]
    r = torch.sqrt(fx * fx + fy * fy).clamp_min(2.0 / size)
    shaped = torch.fft.ifft2(spec * r.pow(-exponent)).real
    shaped = shaped - shaped.mean()
    return shaped / shaped.std()


@functools.lru_cache(maxsize=4)
def make_texture(
    seed: int = 0, size: int = 1024, num_levels: int = 10, device: str = "cpu", dtype: torch.dtype = torch.float32
) -> MipTexture:
    """The procedural albedo tile for ``seed`` on ``device`` as ``dtype`` (cached). Values lie in about [0.08, 0.92]."""
    levels = _texture_levels(seed, size, num_levels)
    return MipTexture(levels.to(device=device, dtype=dtype).contiguous(), size)


@functools.lru_cache(maxsize=2)
def _texture_levels(seed: int, size: int, num_levels: int) -> torch.Tensor:
    """Build the mip stack ``(1, 1, L, S + 2, S + 2)`` (float64, CPU) of the tile for ``seed``."""
    gen = torch.Generator().manual_seed(int(seed) + 7919)
    # Two noise layers: a smooth "stain" layer and a rough fine-grain layer (rich texture at every scale).
    tex = 0.55 * _periodic_noise(size, 1.0, gen) + 0.45 * _periodic_noise(size, 0.55, gen)
    tex = 0.16 * tex
    # Soft-edged discs and rotated rectangles with random grey levels: sharp edges and corners. Each shape is
    # drawn in a small window around it (indices wrap around the periodic tile).
    n_shapes = 140
    cx = torch.rand(n_shapes, generator=gen, dtype=torch.float64) * size
    cy = torch.rand(n_shapes, generator=gen, dtype=torch.float64) * size
    rad = 4.0 + 40.0 * torch.rand(n_shapes, generator=gen, dtype=torch.float64) ** 2
    level = (torch.rand(n_shapes, generator=gen, dtype=torch.float64) - 0.5) * 0.7
    angle = torch.rand(n_shapes, generator=gen, dtype=torch.float64) * math.pi
    aspect = 0.4 + 1.2 * torch.rand(n_shapes, generator=gen, dtype=torch.float64)
    kind = torch.rand(n_shapes, generator=gen, dtype=torch.float64)
    base = 0.5 + tex
    for i in range(n_shapes):  # a loop over a fixed number of shapes, done once per texture
        reach = int(math.ceil(float(rad[i]) * max(1.0, float(aspect[i])) * 1.5)) + 2
        x0, y0 = int(math.floor(float(cx[i]))) - reach, int(math.floor(float(cy[i]))) - reach
        xs = torch.arange(x0, x0 + 2 * reach + 1, dtype=torch.float64)
        ys = torch.arange(y0, y0 + 2 * reach + 1, dtype=torch.float64)
        dx = (xs - cx[i])[None, :]
        dy = (ys - cy[i])[:, None]
        if kind[i] < 0.5:
            dist = torch.sqrt(dx * dx + dy * dy) - rad[i]
        else:
            c, s = math.cos(angle[i]), math.sin(angle[i])
            ax = (c * dx + s * dy).abs() - rad[i]
            ay = (-s * dx + c * dy).abs() - rad[i] * aspect[i]
            dist = torch.maximum(ax, ay)
        alpha = (0.5 - dist).clamp(0.0, 1.0)  # one-texel soft edge
        iy = torch.remainder(ys.long(), size)[:, None]
        ix = torch.remainder(xs.long(), size)[None, :]
        patch = base[iy, ix]
        base[iy, ix] = patch * (1 - alpha) + (0.5 + level[i] + 0.5 * tex[iy, ix]) * alpha
    # Squash smoothly into [0.08, 0.92].
    albedo = 0.5 + 0.42 * torch.tanh((base - 0.5) / 0.42)
    return mip_levels(albedo, num_levels)


def mip_levels(albedo: torch.Tensor, num_levels: int) -> torch.Tensor:
    """Mip stack ``(1, 1, L, S + 2, S + 2)`` of a periodic tile ``(S, S)``: level ``k`` Gaussian-filtered for a
    footprint of ``2**k`` texels (in the Fourier domain, so the tile stays periodic), each padded circularly."""
    size = albedo.shape[-1]
    spec = torch.fft.fft2(albedo)
    fy = torch.fft.fftfreq(size, dtype=torch.float64)[:, None]
    fx = torch.fft.fftfreq(size, dtype=torch.float64)[None, :]
    r2 = fx * fx + fy * fy
    levels = []
    for k in range(num_levels):
        sigma = 0.0 if k == 0 else 0.45 * 2.0**k  # Gaussian prefilter for a footprint of 2**k texels
        lvl = albedo if k == 0 else torch.fft.ifft2(spec * torch.exp(-2.0 * math.pi**2 * sigma**2 * r2)).real
        levels.append(F.pad(lvl[None, None], (1, 1, 1, 1), mode="circular")[0, 0])
    return torch.stack(levels)[None, None]
