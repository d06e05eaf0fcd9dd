"""Texture families for the realistic scenes: painted walls, sky, brick, tiles, stripes, plain and grainy surfaces.

Each family is one periodic albedo tile with its mip pyramid (the same :class:`MipTexture` lookup as the
original rich tile, which is the family ``"print"``). Tiles are deterministic (fixed seeds) and cached; what
varies from scene to scene is which family each surface wears, its placement, scale and brightness, all drawn
by the scene builder from the render seed.
"""

from __future__ import annotations

import functools

import torch

from ._texture import MipTexture, _periodic_noise, make_texture, mip_levels

__all__ = ["FAMILIES", "FAMILY_NAMES", "FAMILY_TEXEL", "family_textures", "family_tile"]

FAMILIES: dict[str, str] = {
    "print": "the original rich tile: band-limited noise with soft discs and rectangles (posters, printed boxes, "
    "clutter)",
    "painted": "painted plaster: faint smooth stains and a fainter roller stipple (about 1 % contrast)",
    "sky": "a bright, almost uniform field with a faint smooth variation",
    "plain": "a nearly uniform grey with faint grain (plastic, metal, painted wood)",
    "grain": "fine isotropic grain of medium contrast (asphalt, concrete, carpet)",
    "brick": "running-bond brick courses (bricks 0.25 x 0.0625 m) with per-brick shade and light mortar joints",
    "tiles": "square 0.25 m tiles with per-tile shade and dark grout lines",
    "stripes": "vertical bars with a 0.125 m period (railings, slats, fences)",
}
FAMILY_NAMES: tuple[str, ...] = tuple(FAMILIES)

# Metres per texel of the periodic families, whatever the rig's scale (a brick is a brick); the others use the
# preset's texel size like the original tile.
_PERIOD_TEXEL = 0.25 / 64
FAMILY_TEXEL: dict[str, float | None] = {
    "print": None, "painted": None, "sky": None, "plain": None, "grain": None,
    "brick": _PERIOD_TEXEL, "tiles": _PERIOD_TEXEL, "stripes": _PERIOD_TEXEL,
}

_SIZE = 512  # texels per tile side of the new families
_LEVELS = 10


def _joint(coord: torch.Tensor, period: float, width: float) -> torch.Tensor:
    """Coverage in [0, 1] of joint lines ``width`` texels wide at multiples of ``period`` (one-texel soft edge)."""
    d = torch.remainder(coord + period / 2, period) - period / 2
    return (width / 2 + 0.5 - d.abs()).clamp(0.0, 1.0)


def family_tile(name: str, size: int = _SIZE) -> torch.Tensor:
    """The albedo tile ``(size, size)`` (float64, periodic) of texture family ``name`` (values in ``[0, 1]``)."""
    gen = torch.Generator().manual_seed(1000 + FAMILY_NAMES.index(name))
    y, x = torch.meshgrid(torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64),
                          indexing="ij")
    if name == "painted":
        tile = 0.72 + 0.010 * _periodic_noise(size, 1.3, gen) + 0.005 * _periodic_noise(size, 0.5, gen)  # stipple
    elif name == "sky":
        tile = 0.90 + 0.004 * _periodic_noise(size, 1.8, gen)
    elif name == "plain":
        tile = 0.50 + 0.005 * _periodic_noise(size, 0.6, gen)
    elif name == "grain":
        tile = 0.42 + 0.06 * _periodic_noise(size, 0.25, gen) + 0.025 * _periodic_noise(size, 1.0, gen)
    elif name == "brick":
        course, length = 16.0, 64.0  # texels: 0.0625 m and 0.25 m
        row = torch.floor(y / course)
        shifted = x + (row % 2) * (length / 2)  # running bond: every other course moves half a brick
        col = torch.floor(torch.remainder(shifted, size) / length)
        shade = 0.40 + 0.07 * torch.randn(int(size / course), int(size / length), generator=gen, dtype=torch.float64)
        brick = shade[row.long() % shade.shape[0], col.long() % shade.shape[1]]
        mortar = torch.maximum(_joint(y, course, 2.0), _joint(shifted, length, 2.0))
        tile = brick * (1 - mortar) + 0.66 * mortar + 0.02 * _periodic_noise(size, 0.5, gen)
    elif name == "tiles":
        side = 64.0  # texels: 0.25 m
        shade = 0.62 + 0.03 * torch.randn(int(size / side), int(size / side), generator=gen, dtype=torch.float64)
        t = shade[torch.floor(y / side).long() % shade.shape[0], torch.floor(x / side).long() % shade.shape[1]]
        grout = torch.maximum(_joint(y, side, 2.0), _joint(x, side, 2.0))
        tile = t * (1 - grout) + 0.38 * grout + 0.01 * _periodic_noise(size, 0.7, gen)
    elif name == "stripes":
        bar = _joint(x, 32.0, 12.0)  # 0.125 m period, 4.7 cm bars
        tile = 0.70 * (1 - bar) + 0.25 * bar + 0.01 * _periodic_noise(size, 0.7, gen)
    else:
        raise KeyError(name)
    return tile.clamp(0.0, 1.0)


@functools.lru_cache(maxsize=1)
def _family_levels() -> tuple[torch.Tensor, ...]:
    return tuple(mip_levels(family_tile(name), _LEVELS) for name in FAMILY_NAMES[1:])


@functools.lru_cache(maxsize=4)
def family_textures(device: str = "cpu", dtype: torch.dtype = torch.float32) -> tuple[MipTexture, ...]:
    """One :class:`MipTexture` per name of :data:`FAMILY_NAMES`, in that order, on ``device`` as ``dtype`` (cached)."""
    rest = tuple(MipTexture(lv.to(device=device, dtype=dtype).contiguous(), _SIZE) for lv in _family_levels())
    return (make_texture(0, device=device, dtype=dtype), *rest)
