"""Pictures of disparity maps: colour maps and the row-profile figure of the paper's argument.

matplotlib is an optional dependency (the ``viz`` extra); colour maps use OpenCV only.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

__all__ = ["colorize_disparity", "save_row_figure"]


def colorize_disparity(disparity: torch.Tensor, max_disparity: float, valid: torch.Tensor | None = None) -> np.ndarray:
    """A ``(H, W)`` disparity map as an ``(H, W, 3)`` uint8 RGB image (turbo colour map, invalid = black).

    >>> colorize_disparity(torch.ones(4, 5), 8.0).shape
    (4, 5, 3)
    """
    d = disparity.detach().float().cpu().reshape(disparity.shape[-2:]).numpy()
    scaled = np.clip(d / max(max_disparity, 1e-6) * 255.0, 0, 255).astype(np.uint8)
    rgb = cv2.cvtColor(cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    if valid is not None:
        rgb[~valid.detach().cpu().reshape(d.shape).numpy().astype(bool)] = 0
    return rgb


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
        curves: name -> ``(H, W)`` disparity map (``NaN`` where a method has no value).
        maps: name -> ``(H, W)`` maps to show as images under the plot (default: ``curves``).
        max_disparity: colour scale of the maps.
        title: figure title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    maps = curves if maps is None else maps
    vmax = max_disparity or max(float(torch.nan_to_num(m).max()) for m in maps.values())
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
        a.imshow(torch.nan_to_num(m).detach().cpu().numpy(), cmap="turbo", vmin=0, vmax=vmax)
        a.axhline(row, color="w", lw=0.6)
        a.set_title(name, fontsize=9)
        a.axis("off")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
