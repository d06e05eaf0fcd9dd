"""Stereo matching restricted to the regions of a mask: the refiner's measurement of prediction holes.

Between verifications the refiner's prediction has holes where the keyframe saw nothing: surfaces a
foreground edge uncovered (disocclusions) and regions entering the view. Running the whole matcher to
fill them would undo the saving of not running it; :func:`match_stereo_regions` runs it on rectangles
that cover the mask instead:

1. the image is cut into ``tile`` x ``tile`` tiles and a tile is needed where at least ``min_fraction``
   of its pixels are in the mask (scattered single pixels are not worth a matcher call);
2. needed tiles that touch (8-connected) form one box (their bounding rectangle);
3. boxes are merged while matching their union costs less than matching the two apart (the cost model
   of :func:`mask_boxes`: a box's window, margins included, plus a fixed cost per box);
4. on the compiled CPU path (the default matcher: SAD, box aggregation, float32 without gradient) every box
   is matched on its rows and its columns widened by ``margin`` on each side, with the whole search range
   (the right image is read beyond the window): the work is the boxes' area, not the frame's. Costs, the
   winner, the sub-pixel fit and the uniqueness and texture checks of a box pixel equal a full-frame run's;
   the left-right check sees the window's columns, so a competing match more than ``margin`` px outside the
   box is missed (the tests measure how often the two differ). When the windows together would cost more
   than ``full_fraction`` of the frame, that item is matched whole; on every other path (GPU, float64,
   gradients, other costs or aggregations) the frame is matched whole. Either way the output is kept inside
   the boxes only.

A batch is cut item by item: an item's boxes, and so its output, never depend on its batch neighbours.
"""

from __future__ import annotations

import inspect

import cv2
import numpy as np
import torch

from ..core import ValueRangeError, check_shape, to_grey
from ..core.dispatch import needs_grad
from ..core.tiles import tile_shares
from . import _sad_numba, matching
from .matching import COST_FLOORS, INVALID_VARIANCE, StereoOutput, match_stereo

__all__ = ["mask_boxes", "match_stereo_regions"]

Box = tuple[int, int, int, int]  # (y0, y1, x0, x1), half-open pixel ranges


def _costs(b: np.ndarray, W: int, margin: int, extra_rows: int, per_box: int) -> np.ndarray:
    """Work of matching boxes ``(..., 4)``: their windows' pixels (rows plus the ``extra_rows`` a band of the
    kernel sums before its first output row, columns widened by ``margin`` each side) plus ``per_box``."""
    h = b[..., 1] - b[..., 0] + extra_rows
    w = np.minimum(W, b[..., 3] + margin) - np.maximum(0, b[..., 2] - margin)
    return h * w + per_box


def mask_boxes(
    mask: torch.Tensor,
    tile: int = 16,
    min_fraction: float = 0.1,
    margin: int = 32,
    extra_rows: int = 8,
    per_box: int = 4096,
) -> list[Box]:
    """Rectangles covering the dense parts of one mask, merged where matching one costs less than two.

    Args:
        mask: ``(H, W)`` bool.
        tile: tile size, px; a tile is needed where at least ``min_fraction`` of it is in the mask.
        min_fraction: in ``(0, 1]``.
        margin, extra_rows, per_box: the cost model of matching a box ``(y0, y1, x0, x1)``:
            ``(y1 - y0 + extra_rows) * (x1 - x0 + 2 margin) + per_box`` (columns clipped to the image).

    Returns:
        A list of boxes ``(y0, y1, x0, x1)`` (half-open, px, inside the image), sorted; empty when no tile
        is needed.

    >>> m = torch.zeros(64, 96, dtype=torch.bool)
    >>> m[10:40, 60:70] = True
    >>> mask_boxes(m)
    [(0, 48, 48, 80)]
    """
    check_shape(mask, ["H", "W"], "mask")
    H, W = mask.shape
    # each tile's share of mask pixels (tiles cut by the image border: of their pixels inside it)
    need = (tile_shares(mask.detach().cpu().numpy(), tile) >= min_fraction).astype(np.uint8)
    if not need.any():
        return []
    # needed tiles that touch form one box
    count, _, stats, _ = cv2.connectedComponentsWithStats(need, connectivity=8)
    b = np.array([(y * tile, min(H, (y + h) * tile), x * tile, min(W, (x + w) * tile))
                  for x, y, w, h, _ in stats[1:count].tolist()], dtype=np.int64).reshape(-1, 4)
    # greedy merging: join the pair whose union saves the most work, until none saves any
    while len(b) > 1:
        cost = _costs(b, W, margin, extra_rows, per_box)
        lo, hi = np.minimum(b[:, None], b[None, :]), np.maximum(b[:, None], b[None, :])
        union = np.stack([lo[..., 0], hi[..., 1], lo[..., 2], hi[..., 3]], axis=-1)
        saving = cost[:, None] + cost[None, :] - _costs(union, W, margin, extra_rows, per_box)
        np.fill_diagonal(saving, 0)
        i, j = np.unravel_index(int(np.argmax(saving)), saving.shape)
        if saving[i, j] <= 0:
            break
        b = np.concatenate([np.delete(b, [i, j], axis=0), union[i, j][None]])
    return sorted(tuple(int(v) for v in box) for box in b)


def _matcher_settings(options: dict) -> dict:
    """:func:`match_stereo`'s defaults updated with ``options`` (which must be its arguments)."""
    settings = {name: p.default for name, p in inspect.signature(match_stereo).parameters.items()
                if p.default is not inspect.Parameter.empty}
    unknown = set(options) - set(settings)
    if unknown:
        raise ValueRangeError(f"options: not arguments of match_stereo: {sorted(unknown)}")
    settings["speckle_size"] = 0  # off unless asked for: windows cut the regions the filter sizes
    settings = {**settings, **options}
    if settings["uniqueness_ratio"] is None:  # match_stereo's default for the aggregation
        settings["uniqueness_ratio"] = matching.UNIQUENESS_RATIOS.get(settings["aggregation"], 0.0)
    return settings


def match_stereo_regions(
    left: torch.Tensor,
    right: torch.Tensor,
    mask: torch.Tensor,
    max_disparity: int,
    tile: int = 16,
    min_fraction: float = 0.1,
    margin: int = 32,
    full_fraction: float = 0.6,
    **options,
) -> StereoOutput:
    """:func:`~egorefine.stereo.match_stereo` on the dense parts of ``mask`` only (module docstring).

    Args:
        left, right: ``(B, 1|3, H, W)`` rectified images in [0, 1].
        mask: ``(B, 1, H, W)`` bool, the pixels that need a measurement.
        max_disparity: search range ``[min_disparity, max_disparity)`` as :func:`match_stereo`'s.
        tile, min_fraction: which parts of the mask are matched (see :func:`mask_boxes`).
        margin: columns on each side of a box that the compiled path's left-right check sees.
        full_fraction: match the whole frame when the boxes' windows would cost more than this share of it.
        **options: passed to :func:`match_stereo` (``min_disparity``, ``block_size``, ``cost``, ...).

    Returns:
        :class:`~egorefine.stereo.StereoOutput`, each ``(B, 1, H, W)``: the matcher's output inside the boxes,
        invalid (disparity 0, ``INVALID_VARIANCE``) elsewhere.

    Raises:
        ShapeError, DTypeError, ValueRangeError: bad input, naming the argument.

    >>> left = torch.rand(1, 1, 48, 96, generator=torch.Generator().manual_seed(0))
    >>> right = torch.roll(left, -4, dims=-1)
    >>> mask = torch.zeros(1, 1, 48, 96, dtype=torch.bool)
    >>> mask[..., 16:32, 64:80] = True
    >>> out = match_stereo_regions(left, right, mask, 16, block_size=5)
    >>> bool(out.valid[0, 0, 24, 70]), bool(out.valid[0, 0, 24, 10]), round(float(out.disparity[0, 0, 24, 70]))
    (True, False, 4)
    """
    dims = check_shape(left, ["B", "1|3", "H", "W"], "left")
    check_shape(mask, ["B", "1", "H", "W"], "mask", dims)
    if int(tile) != tile or tile < 1:
        raise ValueRangeError(f"tile: expected a positive integer, got {tile}")
    if not 0.0 < float(min_fraction) <= 1.0:
        raise ValueRangeError(f"min_fraction: expected 0 < min_fraction <= 1, got {min_fraction}")
    if int(margin) != margin or margin < 0:
        raise ValueRangeError(f"margin: expected an integer >= 0, got {margin}")
    settings = _matcher_settings(options)
    grey_l, grey_r = to_grey(left), to_grey(right)
    matching._check_inputs(grey_l, grey_r, max_disparity, *(settings[k] for k in (
        "min_disparity", "block_size", "cost", "aggregation", "subpixel_fit", "sgm_paths", "temperature",
        "differentiable", "soft_radius", "census_window")))
    B, _, H, W = grey_l.shape
    grey_r = grey_r.to(grey_l.dtype)
    # Item by item (the boxes depend on the data): an item's output does not depend on its neighbours.
    extra = settings["block_size"] - 1
    boxes = [mask_boxes(mask[b, 0].bool(), tile, min_fraction, int(margin), extra) for b in range(B)]
    if not any(boxes):
        if grey_l.device.type == "cpu" and grey_l.dtype in (torch.float32, torch.float64):
            # numpy's fills: torch's would wake its OpenMP threads beside the refiner's next kernels
            dtype = np.float32 if grey_l.dtype == torch.float32 else np.float64
            return StereoOutput(torch.from_numpy(np.zeros(grey_l.shape, dtype)),
                                torch.from_numpy(np.zeros(grey_l.shape, np.bool_)),
                                torch.from_numpy(np.full(grey_l.shape, INVALID_VARIANCE, dtype)))
        return StereoOutput(torch.zeros_like(grey_l), torch.zeros_like(grey_l, dtype=torch.bool),
                            torch.full_like(grey_l, INVALID_VARIANCE))
    scale = matching._integer_scale(settings["cost"], settings["aggregation"], settings["prefilter"],
                                    settings["block_size"], settings["prefilter_cap"],
                                    settings["differentiable"] or needs_grad(grey_l, grey_r),
                                    max_disparity - settings["min_disparity"])
    # match_stereo would run the compiled SAD kernel: on windows here (the speckle filter needs whole regions)
    if scale and matching._compiled_sad(grey_l, grey_r) and not settings["speckle_size"]:
        # an item whose windows would cost more than full_fraction of the frame is matched whole
        work = [int(_costs(np.array(item, dtype=np.int64).reshape(-1, 4), W, int(margin), extra, 0).sum())
                for item in boxes]
        windows = [[(0, H, 0, W)] if cost > full_fraction * H * W else item
                   for item, cost in zip(boxes, work, strict=True)]
        opts = {k: settings[k] for k in ("subpixel", "subpixel_fit", "lr_check", "lr_threshold", "uniqueness_ratio",
                                  "texture_threshold")}
        opts["cost_floor"] = COST_FLOORS["sad"]
        out = StereoOutput(*_sad_numba.match_sad_windows(
            grey_l, grey_r, windows, int(margin), max_disparity, settings["min_disparity"], settings["block_size"],
            settings["prefilter_cap"], scale, opts))
        if windows == boxes:  # every item matched on its boxes: the kernel wrote nothing outside them
            return out
    else:
        out = match_stereo(grey_l, grey_r, max_disparity, **{**options, "speckle_size": settings["speckle_size"]})
    inside = torch.zeros(B, 1, H, W, dtype=torch.bool, device=left.device)
    for b, item in enumerate(boxes):
        for y0, y1, x0, x1 in item:
            inside[b, :, y0:y1, x0:x1] = True
    return StereoOutput(out.disparity * inside, out.valid & inside,
                        torch.where(inside, out.variance, torch.full_like(out.variance, INVALID_VARIANCE)))
