"""Pictures of disparity maps: colour maps and the row-profile figure of the paper's argument.

matplotlib is an optional dependency (the ``viz`` extra); colour maps use OpenCV only. :func:`log_rerun` and
:class:`RerunLogger` write a Rerun recording (``.rrd``: images, depth as a point cloud, poses, statistics per frame)
with the optional Rerun SDK (the ``rerun`` extra), imported only when they are called.
"""

from __future__ import annotations

import functools
from pathlib import Path

import cv2
import numpy as np
import torch

from ._rerun import RERUN_ENTITIES, RerunLogger, RerunNotInstalledError, log_rerun

__all__ = ["RERUN_ENTITIES", "RerunLogger", "RerunNotInstalledError", "colorize_disparity",
           "disparity_palette_image", "log_rerun",
           "save_maps_figure", "save_row_figure", "save_trajectory_figure"]

#: colour of pixels without a value in every figure (mid grey: outside the turbo and magma colour maps)
INVALID_GREY = 0.5


def colorize_disparity(
    disparity: torch.Tensor,
    max_disparity: float,
    valid: torch.Tensor | None = None,
    invalid_color: tuple[int, int, int] = (0, 0, 0),
) -> np.ndarray:
    """A ``(H, W)`` disparity map as an ``(H, W, 3)`` uint8 RGB image (turbo colour map, 0 px to ``max_disparity``).

    The colours are those of :func:`disparity_palette_image`'s palette at its indices.

    Args:
        disparity: ``(H, W)`` (or with leading ones) disparity in pixels.
        max_disparity: the disparity shown at the top of the colour map, px.
        valid: same shape, bool; pixels that are False get ``invalid_color`` (default: all valid).
        invalid_color: RGB of invalid pixels; black by default, ``egorefine run`` previews use grey.

    Returns:
        ``(H, W, 3)`` uint8 RGB array (OpenCV's turbo map, in RGB order).

    Example:
        >>> colorize_disparity(torch.ones(4, 5), 8.0).shape
        (4, 5, 3)
    """
    index, palette = disparity_palette_image(disparity, max_disparity, valid, invalid_color)
    return palette[index]


def disparity_palette_image(
    disparity: torch.Tensor,
    max_disparity: float,
    valid: torch.Tensor | None = None,
    invalid_color: tuple[int, int, int] = (0, 0, 0),
) -> tuple[np.ndarray, np.ndarray]:
    """A ``(H, W)`` disparity map as palette indices and the palette: the colour image of
    :func:`colorize_disparity` in a third of the bytes (an indexed-colour PNG stores it as it is).

    Indices 0-254 are the first 255 colours of OpenCV's turbo map: pixel ``d`` gets ``floor(255 d /
    max_disparity)``, clipped to [0, 254] (so 254 from ``254/255 max_disparity`` up); index 255 is ``invalid_color``.

    Args:
        disparity: ``(H, W)`` (or with leading ones) disparity in pixels.
        max_disparity: the disparity at the top of the colour map, px.
        valid: same shape, bool; pixels that are False get index 255 (default: all valid).
        invalid_color: RGB of index 255.

    Returns:
        ``(index, palette)``: ``(H, W)`` uint8 and ``(256, 3)`` uint8 RGB (read-only; shared between calls).

    Example:
        >>> index, palette = disparity_palette_image(torch.tensor([[0.0, 4.0, 9.0]]), 8.0,
        ...                                          torch.tensor([[True, True, False]]), (128, 128, 128))
        >>> index.tolist(), palette[255].tolist()
        ([[0, 127, 255]], [128, 128, 128])
    """
    d = disparity.detach().float().cpu().reshape(disparity.shape[-2:]).numpy()
    index = np.clip(d / max(max_disparity, 1e-6) * 255.0, 0, 254).astype(np.uint8)
    if valid is not None:
        invalid = ~valid.detach().cpu().reshape(d.shape).numpy().astype(bool)
        np.bitwise_or(index, invalid.view(np.uint8) * np.uint8(255), out=index)  # 255 where invalid
    return index, _turbo_palette(tuple(int(c) for c in invalid_color))


@functools.lru_cache(maxsize=8)
def _turbo_palette(invalid_color: tuple[int, int, int]) -> np.ndarray:
    """OpenCV's turbo colour map (RGB), its last entry replaced by ``invalid_color``; read-only, cached."""
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1].copy()
    lut[255] = invalid_color
    lut.flags.writeable = False
    return lut


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _masked(m: torch.Tensor) -> np.ma.MaskedArray:
    """A map as a masked array, non-finite pixels masked (drawn in the colour map's "bad" colour)."""
    a = m.detach().float().cpu().numpy()
    return np.ma.masked_invalid(a)


def _show(ax, m: torch.Tensor, cmap: str, vmin: float, vmax: float, title: str, colorbar: str | None,
          extend: str = "neither"):
    colours = _colormap(cmap)
    im = ax.imshow(_masked(m), cmap=colours, vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    if colorbar is not None:
        ax.figure.colorbar(im, ax=ax, fraction=0.046, pad=0.02, label=colorbar, extend=extend)
    return im


def _colormap(name: str):
    """A copy of matplotlib's colour map ``name`` whose "bad" (NaN, masked) colour is ``INVALID_GREY``."""
    import matplotlib

    return matplotlib.colormaps[name].with_extremes(bad=str(INVALID_GREY))


def _save(fig, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    _pyplot().close(fig)
    return path


def save_maps_figure(
    path: str | Path,
    image: torch.Tensor,
    maps: dict[str, torch.Tensor],
    truth: torch.Tensor | None = None,
    max_disparity: float | None = None,
    max_error: float = 1.0,
    title: str = "",
) -> Path:
    """The left image, disparity maps with a colour bar each, and (given ``truth``) their error maps.

    Pixels without a value (NaN in a map) are drawn grey (``INVALID_GREY``), never as disparity 0; the error
    maps are grey where either the map or the truth has none.

    Args:
        path: PNG to write.
        image: ``(H, W)`` grey left image in [0, 1].
        maps: name -> ``(H, W)`` disparity in pixels, NaN where the method has no value (e.g. ``"stereo"``,
            ``"refined"``).
        truth: ``(H, W)`` true disparity, NaN where unknown; adds a "truth" panel and an error row.
        max_disparity: top of the disparity colour scale, px (default: the largest finite value shown).
        max_error: top of the error colour scale, px (default 1 px: the errors that matter here are sub-pixel);
            larger errors take its top colour (the colour bar's arrow).
        title: figure title.

    Returns:
        ``path``.

    Example:
        >>> import tempfile
        >>> truth = torch.linspace(2.0, 6.0, 32).expand(24, 32)
        >>> refined = truth + 0.1
        >>> refined[:4] = float("nan")  # no value: drawn grey
        >>> path = save_maps_figure(Path(tempfile.mkdtemp()) / "maps.png", torch.rand(24, 32), {"refined": refined},
        ...                         truth=truth, title="one frame")
        >>> path.name, cv2.imread(str(path)).shape  # two rows (maps, errors) of three panels
        ('maps.png', (638, 1188, 3))
    """
    plt = _pyplot()
    panels = dict(maps) if truth is None else {"truth": truth, **maps}
    vmax = max_disparity or max(float(np.nanmax(_masked(m).filled(np.nan))) for m in panels.values())
    rows = 1 if truth is None else 2
    cols = len(panels) + 1
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 2.9 * rows), constrained_layout=True, squeeze=False)
    _show(axes[0, 0], image, "gray", 0.0, 1.0, "left image", None)
    for ax, (name, m) in zip(axes[0, 1:], panels.items(), strict=True):
        _show(ax, m, "turbo", 0.0, vmax, name, "disparity (px)")
    if truth is not None:
        axes[1, 0].axis("off")
        axes[1, 1].axis("off")
        for ax, (name, m) in zip(axes[1, 2:], maps.items(), strict=True):
            _show(ax, (m - truth).abs(), "magma", 0.0, max_error, f"|{name} - truth|", "error (px)", extend="max")
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def save_trajectory_figure(path: str | Path, trajectories: dict[str, torch.Tensor], title: str = "") -> Path:
    """Top view (x right, z forward, metres) of camera positions of several ``world_T_camera`` trajectories.

    The camera frame is X right, Y down, Z forward (docs/method.md), so a rig moving on level ground stays in the x-z
    plane; the first pose of each trajectory is marked with a circle.

    Args:
        path: PNG to write.
        trajectories: name -> ``(T, 4, 4)`` poses ``world_T_camera`` (e.g. ``"estimated"``, ``"truth"``).
        title: figure title.

    Returns:
        ``path``.

    Example:
        >>> import tempfile
        >>> truth = torch.eye(4).repeat(5, 1, 1)
        >>> truth[:, 2, 3] = torch.arange(5.0) * 0.1  # 10 cm forward per frame
        >>> estimated = truth.clone()
        >>> estimated[:, 0, 3] = 0.01  # 1 cm to the side
        >>> path = save_trajectory_figure(Path(tempfile.mkdtemp()) / "trajectory.png",
        ...                               {"estimated": estimated, "truth": truth})
        >>> path.name, cv2.imread(str(path)).shape
        ('trajectory.png', (550, 605, 3))
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 5), constrained_layout=True)
    styles = ["k-", "C1--", "C0-", "C2-", "C3-"]
    for (name, poses), style in zip(trajectories.items(), styles * 2, strict=False):
        p = poses.detach().double().cpu()[:, :3, 3].numpy()
        ax.plot(p[:, 0], p[:, 2], style, lw=1.3, label=name)
        ax.plot(p[:1, 0], p[:1, 2], style[:2].rstrip("-") + "o")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m, forward)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, lw=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title or "trajectory, top view")
    return _save(fig, path)


def save_row_figure(
    path: str | Path,
    row: int,
    curves: dict[str, torch.Tensor],
    maps: dict[str, torch.Tensor] | None = None,
    max_disparity: float | None = None,
    title: str = "",
) -> Path:
    """Disparity along image row ``row`` for several methods, above their maps.

    Args:
        path: PNG to write.
        row: image row to plot.
        curves: name -> ``(H, W)`` disparity map (``NaN`` where a method has no value: a gap in its curve).
        maps: name -> ``(H, W)`` maps to show as images under the plot (default: ``curves``); NaN pixels are drawn
            grey (``INVALID_GREY``), and the last map carries the colour bar.
        max_disparity: colour scale of the maps, px (default: the largest finite value).
        title: figure title.

    Returns:
        ``path``.

    Example:
        >>> import tempfile
        >>> truth = torch.linspace(2.0, 6.0, 32).expand(24, 32)
        >>> stereo = truth.round()  # integer disparities: a staircase along the row
        >>> path = save_row_figure(Path(tempfile.mkdtemp()) / "row.png", 12, {"truth": truth, "stereo": stereo})
        >>> path.name, cv2.imread(str(path)).shape  # the curves above, one map per method below
        ('row.png', (770, 880, 3))
    """
    plt = _pyplot()
    maps = curves if maps is None else maps
    vmax = max_disparity or max(float(np.nanmax(_masked(m).filled(np.nan))) for m in maps.values())
    fig = plt.figure(figsize=(4 * max(len(maps), 2), 7), constrained_layout=True)
    grid = fig.add_gridspec(2, len(maps))
    ax = fig.add_subplot(grid[0, :])
    styles = ["k-", "C0-", "C1-", "C2-", "C3-", "C4-"]
    for (name, m), style in zip(curves.items(), styles * 2, strict=False):
        ax.plot(m[row].detach().cpu().numpy(), style, lw=1.2 if style == "k-" else 1.0, label=name)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("disparity (px)")
    ax.set_title(title or f"disparity along row {row}")
    ax.legend(loc="best", fontsize=8)
    for i, (name, m) in enumerate(maps.items()):
        a = fig.add_subplot(grid[1, i])
        _show(a, m, "turbo", 0.0, vmax, name, "disparity (px)" if i == len(maps) - 1 else None)
        a.axhline(row, color="w", lw=0.6)
    return _save(fig, path)
