"""Feature tracking by batched local block matching, coarse to fine, with sub-pixel peaks.

The paper (PAPER.md, "Features") tracks keypoints from frame to frame by local block
matching; the tracks feed the least-squares ego-motion of eq. (3). Here every feature of
every batch item is matched at once, with no Python loop over features:

1. Both images go to grey and into an image pyramid (``levels`` levels, each a 3x3 binomial
   blur and a stride-2 subsampling, so a pixel ``x`` of level 0 is ``x / 2^l`` on level ``l``).
2. On the coarsest level the template (``patch_size``^2 around the keypoint in ``prev``) is
   compared with every position of a search window of radius ``search_radius`` around the
   start (the ``predicted`` position, else the keypoint itself) in ``next``. Templates and
   windows are cut at whole pixels (one index gather for all features; the keypoint's
   fractional part is added back to the match), and the cost maps of all features come from
   grouped (depthwise) convolutions with one group per feature.
3. The best integer shift is refined by a parabola through its neighbours in x and y (peak
   refinement); the estimate goes to the next finer level (times 2), which searches only
   ``refine_radius`` around it.
4. On level 0 a few Lucas-Kanade (Gauss-Newton) iterations polish the parabola's estimate:
   the parabola alone is biased by the cost's shape (~0.1-0.3 px), the polish brings the
   error to a few hundredths of a pixel on textured images.
5. A forward-backward check matches the result back from ``next`` into ``prev``, the search
   centred on the keypoint, and rejects features whose round trip misses the start by more
   than ``fb_threshold`` pixels or whose back match lies on its window's edge. The way back
   needs a reach of its own: a wrong match (a look-alike patch, typically at large motion)
   found by the full search comes back to the keypoint itself from a small level-0 window,
   since the keypoint's patch is what it was matched to. So the features found by the full
   search go back coarse to fine over the ``fb_levels`` finest levels (``search_radius`` on
   the coarsest of them; by default all ``levels``, the same reach as the way there); the
   features found next to their prediction (below) go back with one level-0 match of radius
   ``refine_radius``, or skip the check with ``fb_predicted=False``. On the KITTI-like street (forward 1.1 m steps, no
   prediction, 15 pairs of 500 features) the share of accepted tracks off by more than 1 px
   is 6.3 % with the small level-0 window for all, 5.2 % with the earlier level-1-plus-LK
   way back, 5.7 % with ``fb_levels=1``, 4.5 % with 2 and 4.0 % with 3 (the default).

Only the live slots (weight > 0) are matched: empty ones are dropped before and filled in
after (one host synchronisation per call, which also checks the inputs for NaN/Inf). With a
``predicted`` position (e.g. from a constant-velocity model) step 2 first searches level 0
only, ``predicted_radius`` pixels around the prediction; the coarse-to-fine search of steps
2-3 runs only for the features not found there, so a good prediction skips the coarse
levels and a bad one keeps the full reach. A caller that tracks a video can pass the
pyramid of a frame built once (:func:`build_pyramid`) as ``prev_pyramid`` / ``next_pyramid``
to both calls that use that frame.

``soft=True`` replaces the arg-min of step 3 on level 0 by a soft-argmax of
``-cost / temperature`` over a ``refine_radius`` window around the rounded hard estimate
(before the polish of step 4), so that the returned positions have smooth gradients with
respect to both images and the keypoints.

For float32 CPU tensors that need no gradient, hard matching and ``cost="zncc"`` (the
refiner's case), the same steps run compiled (:mod:`egorefine.features._track_numba`, numba;
:func:`egorefine.core.use_compiled` decides): one loop over the live features per stage instead
of a dozen small torch ops per level, about 3x faster at a few hundred features. Its positions
agree with this torch path (the reference, also for GPU tensors, autograd, tracing, ``soft=True``
and the other costs) to float32 rounding and its decisions are the same but for near-ties.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

from ..core import (
    ValueRangeError,
    check_choice,
    check_float,
    check_same_device,
    check_same_dtype,
    check_shape,
    eps_like,
    to_grey,
    use_compiled,
)
from . import _track_numba

__all__ = ["track", "Tracker", "TrackOutput", "build_pyramid"]

_COSTS = ("zncc", "ssd", "sad")


class TrackOutput(NamedTuple):
    """Result of :func:`track`.

    Attributes:
        keypoints: ``(B, N, 2)`` (x, y) positions in ``next``; lost features keep a finite estimate,
            empty slots (input weight 0) their input position.
        weights: ``(B, N)`` input weight times success (0 for lost, failed forward-backward check,
            out of image, too little texture or too low a score).
        score: ``(B, N)`` match quality at the result: ZNCC in [-1, 1] for ``cost="zncc"``, the
            negated mean squared / absolute difference per pixel for ``"ssd"`` / ``"sad"``
            (higher is better in every case).
        fb_error: ``(B, N)`` forward-backward round-trip error in pixels (0 where the check did not
            run: without it, on features already failed, and with ``fb_predicted=False`` on those
            found next to their prediction).
    """

    keypoints: torch.Tensor
    weights: torch.Tensor
    score: torch.Tensor
    fb_error: torch.Tensor


# 3x3 binomial kernel [1, 2, 1]^T [1, 2, 1] / 16 as anti-aliasing, evaluated only at the kept
# (even) pixels by strided slicing: pixel 2i of level l becomes pixel i of level l+1, so
# x_{l+1} = x_l / 2. This costs a fraction of kornia's pyrdown (5x5 blur and bilinear resize),
# which matters here: the pyramid is a large part of the tracking time.
def _pyrdown(x: torch.Tensor) -> torch.Tensor:
    if use_compiled(x):
        return _track_numba.pyrdown(x)  # the same operations compiled
    # The border row/column is repeated by concatenation (cheaper than F.pad's replicate mode).
    x = torch.cat([x[..., :1, :], x, x[..., -1:, :]], dim=-2)
    rows = x[..., 0:-2:2, :] + x[..., 2::2, :] + 2 * x[..., 1:-1:2, :]
    rows = torch.cat([rows[..., :1], rows, rows[..., -1:]], dim=-1)
    return (rows[..., 0:-2:2] + rows[..., 2::2] + 2 * rows[..., 1:-1:2]) * 0.0625


def build_pyramid(image: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """Grey image pyramid used by :func:`track`: level 0 is the (grey) input, each next level half the size.

    A pixel ``(x, y)`` of level 0 lies at ``(x, y) / 2^l`` on level ``l``.

    Args:
        image: ``(B, 1, H, W)`` or ``(B, 3, H, W)`` float image.
        levels: number of levels (>= 1).

    Returns:
        list of ``levels`` tensors ``(B, 1, H_l, W_l)`` with ``H_{l+1} = ceil(H_l / 2)``.

    >>> [p.shape[-1] for p in build_pyramid(torch.rand(1, 3, 32, 40), 3)]
    [40, 20, 10]
    """
    gray = to_grey(image)
    pyr = [gray]
    for _ in range(levels - 1):
        pyr.append(_pyrdown(pyr[-1]))
    return pyr


def _offsets(size: int, like: torch.Tensor) -> torch.Tensor:
    """(size*size, 2) integer (x, y) offsets of a centred square, row-major, in ``like``'s dtype."""
    r = torch.arange(size, device=like.device, dtype=like.dtype) - (size - 1) / 2
    oy, ox = torch.meshgrid(r, r, indexing="ij")
    return torch.stack([ox.reshape(-1), oy.reshape(-1)], dim=-1)


def _extract_patches(image: torch.Tensor, centres: torch.Tensor, size: int) -> torch.Tensor:
    """``size x size`` patches of ``image`` (B, 1, H, W) around integer ``centres`` (B, N, 2) -> (B, N, size, size).

    ``centres`` hold whole numbers (any dtype); outside the image the border pixel is repeated.
    Integer centres need no interpolation: the patches are exact pixels, gathered by index,
    and the gradient reaches ``image`` (not ``centres``, which are piecewise constant anyway).
    """
    b, _, h, w = image.shape
    n = centres.shape[1]
    c = centres.long()
    r = torch.arange(size, device=image.device) - (size - 1) // 2
    xs = (c[..., 0:1] + r.view(1, 1, size)).clamp(0, w - 1)  # (B, N, s)
    ys = (c[..., 1:2] + r.view(1, 1, size)).clamp(0, h - 1)
    idx = ys.unsqueeze(-1) * w + xs.unsqueeze(-2)  # (B, N, s, s)
    out = image.reshape(b, h * w).gather(1, idx.reshape(b, n * size * size))
    return out.view(b, n, size, size)


def _box_maps(image: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Sums of ``image`` (B, 1, H, W) and of its square over the ``size x size`` box around every
    centre from ``-r`` to ``H - 1 + r`` / ``W - 1 + r`` (``r = size // 2``): (B, 1, H + 2r, W + 2r),
    centre ``(y, x)`` at ``[y + r, x + r]``.

    The image is extended by repeating its border, as :func:`_extract_patches` does. A box centred
    further out holds the same pixels as one centred ``r`` outside, so clamping a centre into the
    map reads the exact sum of a window cut anywhere. Running sums (cumsum, in float64 so that the
    differences do not lose digits) along each axis; used on coarse levels, where the search
    windows of all features together cover more pixels than the image itself.
    """
    r = size // 2
    x = torch.cat([image, image * image], dim=1)
    x = F.pad(x, (2 * r + 1, 2 * r, 2 * r + 1, 2 * r), mode="replicate").double()
    x = x.cumsum(-1)
    x = x[..., size:] - x[..., :-size]
    x = x.cumsum(-2)
    x = (x[..., size:, :] - x[..., :-size, :]).to(image.dtype)
    return x[:, 0:1], x[:, 1:2]


def _cost_map(
    template: torch.Tensor,
    window: torch.Tensor,
    cost: str,
    box: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """Matching cost (lower is better) of every shift: (B, N, p, p), (B, N, S, S) -> (B, N, S-p+1, S-p+1).

    ``"zncc"`` returns ``-ZNCC``, ``"ssd"`` / ``"sad"`` the mean squared / absolute difference.
    ``box``: optional precomputed box sums of the window and of its square at every shift,
    each (B, N, K, K) (see :func:`_box_maps`); otherwise they come from a convolution.
    """
    b, n, p, _ = template.shape
    s = window.shape[-1]
    bn = b * n
    win = window.reshape(1, bn, s, s)
    area = p * p
    if cost == "sad":
        cols = F.unfold(window.reshape(bn, 1, s, s), p)  # (BN, p*p, K*K)
        sad = (cols - template.reshape(bn, area, 1)).abs().mean(dim=1)
        k = s - p + 1
        return sad.view(b, n, k, k)
    # Work on windows offset by the template mean: the sums below then stay small in float32.
    t_mean = template.mean(dim=(-2, -1), keepdim=True)
    t0 = (template - t_mean).reshape(bn, 1, p, p)
    win = (window - t_mean).reshape(1, bn, s, s)
    # Grouped (depthwise) convolutions, one group per feature: the correlation with the
    # zero-mean template, and box sums of the window and of its square (a convolution with
    # ones is much faster than avg_pool2d for these on CPU). Two separate calls stay on the
    # fast depthwise path that a combined two-kernel call falls off.
    corr = F.conv2d(win, t0, groups=bn)[0]  # (BN, K, K)
    k = s - p + 1
    if box is None:
        sums = F.conv2d(torch.cat([win, win * win], dim=0), torch.ones_like(t0), groups=bn)
        w_sum, w_sq = sums[0], sums[1]
    else:
        # Raw sums -> sums of the mean-offset window: sum (w - m) and sum (w - m)^2.
        m = t_mean.reshape(bn, 1, 1)
        raw_sum, raw_sq = box[0].reshape(bn, k, k), box[1].reshape(bn, k, k)
        w_sum = raw_sum - area * m
        w_sq = raw_sq - 2 * m * raw_sum + area * m * m
    t_sq = (t0 * t0).sum(dim=(-2, -1)).view(bn, 1, 1)
    eps = eps_like(window)
    if cost == "ssd":
        # sum (w - t)^2 = sum w^2 - 2 sum w t + sum t^2, with t = t0 (the window was offset by the mean).
        ssd = (w_sq - 2 * corr + t_sq) / area
        return ssd.clamp_min(0).view(b, n, k, k)
    # ZNCC = sum (w - mean_w) t0 / sqrt(sum (w - mean_w)^2 * sum t0^2), as sum mean_w * t0 = 0.
    w_var = torch.addcmul(w_sq, w_sum, w_sum, value=-1.0 / area).clamp_min(0)
    # Clamp under the square root: a flat patch has zero variance (ZNCC 0, finite gradient).
    return (-corr * torch.rsqrt((w_var * t_sq).clamp_min(eps))).view(b, n, k, k)


def _parabola(cm: torch.Tensor, minus: torch.Tensor, plus: torch.Tensor) -> torch.Tensor:
    """Vertex of the parabola through (-1, minus), (0, cm), (1, plus), clamped to half a pixel."""
    curv = (minus - 2 * cm + plus).clamp_min(eps_like(cm))
    return (0.5 * (minus - plus) / curv).clamp(-0.5, 0.5)


def _best_shift(cost_map: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sub-pixel arg-min of cost maps (B, N, K, K).

    Returns shift (B, N, 2) (x, y) relative to the window centre, the cost at the integer
    minimum (B, N), and a flag (B, N) that is True where the minimum lies on the window's edge
    (the true match may lie outside the window).
    """
    b, n, k, _ = cost_map.shape
    flat = cost_map.reshape(b, n, k * k)
    best, idx = flat.min(dim=-1)
    ixy = torch.stack([idx % k, idx // k], dim=-1)  # (B, N, 2) integer (x, y) of the minimum
    edge_xy = (ixy == 0) | (ixy == k - 1)
    on_edge = edge_xy.any(dim=-1)
    # The four neighbours (x-1, x+1, y-1, y+1) in one gather. Indices are clamped into the map;
    # on an edge they may point at a wrong cell, but that axis gets no sub-pixel step anyway
    # (the parabola would be one-sided).
    steps = torch.tensor([-1, 1, -k, k], device=idx.device)
    nb = flat.gather(-1, (idx.unsqueeze(-1) + steps).clamp(0, k * k - 1))  # (B, N, 4)
    sub = _parabola(best.unsqueeze(-1), nb[..., 0::2], nb[..., 1::2])  # (B, N, 2)
    sub = torch.where(edge_xy, torch.zeros_like(sub), sub)
    shift = ixy.to(cost_map.dtype) - (k - 1) / 2 + sub
    return shift, best, on_edge


def _match_level(
    src: torch.Tensor,
    dst: torch.Tensor,
    points: torch.Tensor,
    estimate: torch.Tensor,
    patch_size: int,
    radius: int,
    cost: str,
    temperature: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One level of block matching; ``points`` in ``src`` and ``estimate`` in ``dst`` in this level's px.

    The template is cut at the rounded point and the window at the rounded estimate, so both
    are exact pixels (no interpolation); the point's fractional part is added back to the
    match (the neighbourhood moves as a whole). With ``temperature`` the shift is a
    soft-argmax of ``-cost / temperature`` instead of the arg-min plus parabola.

    Returns the new estimate (B, N, 2), the best cost (B, N) and the on-edge flag (B, N).
    """
    p_int = points.detach().round()
    frac = points - p_int
    centre = (estimate.detach() - frac.detach()).round()
    template = _extract_patches(src, p_int, patch_size)
    window = _extract_patches(dst, centre, patch_size + 2 * radius)
    b, n = points.shape[:2]
    k = 2 * radius + 1
    box = None
    if cost != "sad" and n * k * k > 2 * dst.shape[-2] * dst.shape[-1]:
        # Coarse level: box sums of the whole (small) image, then one gather per shift, are
        # cheaper than box sums window by window.
        box_sum, box_sq = _box_maps(dst, patch_size)
        at = centre + patch_size // 2  # the maps start r before the image (clamped there: exact, see _box_maps)
        box = (_extract_patches(box_sum, at, k), _extract_patches(box_sq, at, k))
    cmap = _cost_map(template, window, cost, box)
    if temperature is None:
        shift, best, on_edge = _best_shift(cmap)
    else:
        b, n, k, _ = cmap.shape
        flat = cmap.reshape(b, n, k * k)
        prob = torch.softmax(-flat / temperature, dim=-1)
        shift = prob @ _offsets(k, prob)
        best = flat.amin(dim=-1)
        on_edge = torch.zeros_like(best, dtype=torch.bool)
    return centre + frac + shift, best, on_edge


def _coarse_to_fine(
    pyr_src: list[torch.Tensor],
    pyr_dst: list[torch.Tensor],
    points: torch.Tensor,
    start: torch.Tensor,
    patch_size: int,
    search_radius: int,
    refine_radius: int,
    cost: str,
    stop_level: int = 0,
    edge_level: int = 0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Hard block matching of ``points`` (level-0 px in src) into dst, starting at ``start`` (level-0 px).

    Runs the levels from the coarsest down to ``stop_level``. Returns the level-0 positions
    (B, N, 2), the best cost of the last level run (B, N) and a flag (B, N) that is True where
    the minimum of level ``edge_level`` lay on its window's edge (all False if that level is
    not run).
    """
    levels = len(pyr_src)
    est = start
    edge = torch.zeros(points.shape[:2], dtype=torch.bool, device=points.device)
    best = torch.zeros(points.shape[:2], dtype=points.dtype, device=points.device)
    for level in range(levels - 1, stop_level - 1, -1):
        scale = 2.0**level
        radius = search_radius if level == levels - 1 else refine_radius
        est_l, best, on_edge = _match_level(
            pyr_src[level],
            pyr_dst[level],
            points / scale,
            est / scale,
            patch_size,
            radius,
            cost,
        )
        est = est_l * scale
        if level == edge_level:
            # Only the last level's edge counts: on a coarser level a minimum on the edge may be a
            # motion just beyond that window, which the finer levels still reach.
            edge = edge | on_edge
    return est, best, edge


def _sample_patches(image: torch.Tensor, centres: torch.Tensor, size: int, mode: str = "bicubic") -> torch.Tensor:
    """Interpolated ``size x size`` patches of ``image`` (B, 1, H, W) at sub-pixel ``centres`` (B, N, 2).

    Differentiable with respect to ``image`` and ``centres``; outside the image the border
    pixel is repeated. Returns (B, N, size, size).
    """
    b, _, h, w = image.shape
    n = centres.shape[1]
    pts = centres.unsqueeze(2) + _offsets(size, centres).view(1, 1, size * size, 2)
    scale = torch.tensor([2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)], device=pts.device, dtype=pts.dtype)
    out = F.grid_sample(image, pts * scale - 1.0, mode=mode, padding_mode="border", align_corners=True)
    return out.view(b, n, size, size)


def _lk_refine(
    src: torch.Tensor,
    dst: torch.Tensor,
    points: torch.Tensor,
    estimate: torch.Tensor,
    patch_size: int,
    iters: int,
    cost: str,
) -> torch.Tensor:
    """Sub-pixel polish of level-0 matches by inverse-compositional Lucas-Kanade (translation only).

    The template is the exact-pixel patch at the rounded point; the matching patch of ``dst``
    is sampled bicubically at the current estimate (bilinear sampling smooths it by an amount
    that depends on the fractional offset, which biased results by ~0.04 px), and each
    iteration solves the 2x2 normal equations ``(sum g g^T) delta = sum g (T - I)`` with the
    template gradient ``g``. For
    ``cost="zncc"`` both patches are normalised to zero mean and equal spread first (gain and
    bias invariant, like ZNCC). Steps are clamped to half a pixel each and the total change to
    one pixel, so a flat or edge-only patch cannot run away. Differentiable (grid_sample).
    """
    p_int = points.detach().round()
    frac = points - p_int
    ext = _extract_patches(src, p_int, patch_size + 2)
    tpl = ext[..., 1:-1, 1:-1]
    gx = 0.5 * (ext[..., 1:-1, 2:] - ext[..., 1:-1, :-2])
    gy = 0.5 * (ext[..., 2:, 1:-1] - ext[..., :-2, 1:-1])
    eps = eps_like(tpl)
    if cost == "zncc":
        # Zero-mean patches need zero-mean gradients: the mean's own gradient would inflate the
        # 2x2 system and shrink every step.
        tpl = tpl - tpl.mean(dim=(-2, -1), keepdim=True)
        t_std = tpl.pow(2).mean(dim=(-2, -1), keepdim=True).clamp_min(eps).sqrt()
        gx = gx - gx.mean(dim=(-2, -1), keepdim=True)
        gy = gy - gy.mean(dim=(-2, -1), keepdim=True)
    sxx = (gx * gx).sum(dim=(-2, -1))
    syy = (gy * gy).sum(dim=(-2, -1))
    sxy = (gx * gy).sum(dim=(-2, -1))
    # Tikhonov term relative to the trace: keeps the 2x2 solve finite on flat patches.
    reg = 1e-3 * (sxx + syy) + eps
    det = ((sxx + reg) * (syy + reg) - sxy * sxy).clamp_min(eps)
    base = estimate.detach() - frac.detach()  # where the rounded point lands, from block matching
    pos = estimate - frac
    for _ in range(iters):
        img = _sample_patches(dst, pos, patch_size)
        if cost == "zncc":
            img = img - img.mean(dim=(-2, -1), keepdim=True)
            i_std = img.pow(2).mean(dim=(-2, -1), keepdim=True).clamp_min(eps).sqrt()
            img = img * (t_std / i_std)
        r = tpl - img
        bx = (gx * r).sum(dim=(-2, -1))
        by = (gy * r).sum(dim=(-2, -1))
        dx = ((syy + reg) * bx - sxy * by) / det
        dy = ((sxx + reg) * by - sxy * bx) / det
        step = torch.stack([dx, dy], dim=-1).clamp(-0.5, 0.5)
        pos = base + (pos + step - base).clamp(-1.0, 1.0)
    return pos + frac


# Subsets of features are padded to a multiple of this many slots: the grouped convolutions
# then see a handful of shapes over a video instead of a new one every frame (a new shape
# costs oneDNN a kernel set-up several times the convolution itself).
_SLOT_STEP = 32


def _first_true(mask: torch.Tensor, count: int) -> torch.Tensor:
    """Slot indices (B, M) of each row of ``mask`` (B, N): its True slots first, in order, then the others.

    ``count`` is the largest number of True slots in a row; ``M`` is ``count`` rounded up to a
    multiple of ``_SLOT_STEP`` (at most ``N``), the extra slots being False ones.
    """
    size = min(mask.shape[1], -(-count // _SLOT_STEP) * _SLOT_STEP)
    order = torch.sort((~mask).to(torch.uint8), dim=1, stable=True).indices
    return order[:, :size]


def _take(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``x`` (B, N, ...) at slots ``idx`` (B, M) -> (B, M, ...)."""
    return x.gather(1, idx.view(*idx.shape, *([1] * (x.dim() - 2))).expand(*idx.shape, *x.shape[2:]))


def _put(x: torch.Tensor, idx: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """Copy of ``x`` (B, N, ...) with slots ``idx`` (B, M) (distinct per row) set to ``values`` (B, M, ...)."""
    return x.scatter(1, idx.view(*idx.shape, *([1] * (x.dim() - 2))).expand(*idx.shape, *x.shape[2:]), values)


def _match_to_level0(
    pyr_src: list[torch.Tensor],
    pyr_dst: list[torch.Tensor],
    points: torch.Tensor,
    start: torch.Tensor,
    patch_size: int,
    search_radius: int,
    refine_radius: int,
    cost: str,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Coarse-to-fine block matching src -> dst down to level 0: coarse levels without autograd, level 0 with.

    Returns level-0 positions (B, N, 2) (differentiable through level 0's sub-pixel step),
    level 0's best cost and its on-edge flag (B, N).
    """
    levels = len(pyr_src)
    with torch.no_grad():
        est, _, _ = _coarse_to_fine(
            [p.detach() for p in pyr_src],
            [p.detach() for p in pyr_dst],
            points.detach(),
            start.detach(),
            patch_size,
            search_radius,
            refine_radius,
            cost,
            1,
            -1,
        )
    radius0 = search_radius if levels == 1 else refine_radius
    # Level 0 with autograd: the parabola links positions to the inputs.
    return _match_level(pyr_src[0], pyr_dst[0], points, est, patch_size, radius0, cost)


def _forward_match(
    pyr_src: list[torch.Tensor],
    pyr_dst: list[torch.Tensor],
    points: torch.Tensor,
    start: torch.Tensor,
    live: torch.Tensor,
    patch_size: int,
    search_radius: int,
    refine_radius: int,
    cost: str,
    predicted_radius: int | None,
    min_score: float | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Level-0 block matching of ``points`` into dst: (positions, best cost, on-edge flag, found flag).

    The found flag (B, N) marks the features that the search around the prediction found.

    With ``predicted_radius`` (and two levels or more) level 0 is first searched only that far
    around ``start``; the full coarse-to-fine search then runs for the ``live`` features not
    found there (minimum on the window's edge or, for ZNCC, score below ``min_score``). A good
    prediction thus skips the coarse levels, a bad one keeps the full reach.
    """
    if predicted_radius is None or len(pyr_src) == 1:
        out, best, edge = _match_to_level0(
            pyr_src, pyr_dst, points, start, patch_size, search_radius, refine_radius, cost
        )
        return out, best, edge, torch.zeros_like(edge)
    out, best, edge = _match_level(pyr_src[0], pyr_dst[0], points, start, patch_size, predicted_radius, cost)
    with torch.no_grad():
        miss = edge
        if min_score is not None and cost == "zncc":
            miss = miss | (-best < min_score)
        retry = live & miss
        count = int(retry.sum(dim=1).max())  # host sync: the size of the second pass
    found = live & ~miss
    if count == 0:
        return out, best, edge, found
    idx = _first_true(retry, count)
    r_out, r_best, r_edge = _match_to_level0(
        pyr_src,
        pyr_dst,
        _take(points, idx),
        _take(start, idx),
        patch_size,
        search_radius,
        refine_radius,
        cost,
    )
    # Padding slots (rows with fewer misses than ``count``) keep their first-pass result.
    sel = _take(retry, idx)
    out = _put(out, idx, torch.where(sel.unsqueeze(-1), r_out, _take(out, idx)))
    best = _put(best, idx, torch.where(sel, r_best, _take(best, idx)))
    edge = _put(edge, idx, torch.where(sel, r_edge, _take(edge, idx)))
    return out, best, edge, found


def _check_values(
    prev: torch.Tensor,
    next: torch.Tensor,  # noqa: A002
    keypoints: torch.Tensor,
    weights: torch.Tensor,
    predicted: torch.Tensor | None,
) -> int:
    """Raise :class:`ValueRangeError` on NaN/Inf in an input; return the largest live-feature count of a row.

    The same tests as ``core.check_finite``, all with one synchronisation (which also fetches
    the count): an image sum is finite exactly when every pixel is (images in [0, 1] cannot
    overflow it; an ``isfinite`` map costs more), the largest magnitude of a small tensor is
    finite exactly when every entry is.
    """
    # Half-precision images are summed in float32: their sum could overflow their own type.
    wide = torch.float32 if prev.element_size() < 4 else prev.dtype
    names = ["prev", "next", "keypoints", "weights", "predicted"]
    stats = [prev.sum(dtype=wide), next.sum(dtype=wide)]
    for t in (keypoints, weights, predicted):
        stats.append(
            t.detach().abs().amax().to(wide) if t is not None and t.numel() > 0 else prev.new_zeros((), dtype=wide)
        )
    count = (weights > 0).sum(dim=1).amax().to(wide) if weights.numel() > 0 else prev.new_zeros((), dtype=wide)
    values = torch.cat([torch.isfinite(torch.stack(stats)).to(wide), count.reshape(1)]).tolist()
    for name, finite in zip(names, values[:5], strict=True):
        if not finite:
            raise ValueRangeError(f"{name}: contains NaN or Inf")
    return int(values[5])


def _check_fb_levels(fb_levels: int | None) -> None:
    if fb_levels is not None and (not isinstance(fb_levels, int) or fb_levels < 1):
        raise ValueRangeError(f"fb_levels: expected None or an int >= 1, got {fb_levels!r}")


def _check_predicted_radius(predicted_radius: int | None) -> None:
    if predicted_radius is not None and (not isinstance(predicted_radius, int) or predicted_radius < 1):
        raise ValueRangeError(f"predicted_radius: expected None or an int >= 1, got {predicted_radius!r}")


def _check_track_settings(
    patch_size: int,
    search_radius: int,
    refine_radius: int,
    levels: int,
    cost: str,
    fb_threshold: float,
    temperature: float,
    lk_iters: int,
) -> None:
    if not isinstance(patch_size, int) or patch_size < 3 or patch_size % 2 == 0:
        raise ValueRangeError(f"patch_size: expected an odd int >= 3, got {patch_size!r}")
    if not isinstance(search_radius, int) or search_radius < 1:
        raise ValueRangeError(f"search_radius: expected an int >= 1, got {search_radius!r}")
    if not isinstance(refine_radius, int) or refine_radius < 1:
        raise ValueRangeError(f"refine_radius: expected an int >= 1, got {refine_radius!r}")
    if not isinstance(levels, int) or levels < 1:
        raise ValueRangeError(f"levels: expected an int >= 1, got {levels!r}")
    check_choice(cost, _COSTS, "cost")
    if not fb_threshold > 0:
        raise ValueRangeError(f"fb_threshold: expected a number > 0, got {fb_threshold!r}")
    if not temperature > 0:
        raise ValueRangeError(f"temperature: expected a number > 0, got {temperature!r}")
    if not isinstance(lk_iters, int) or lk_iters < 0:
        raise ValueRangeError(f"lk_iters: expected an int >= 0, got {lk_iters!r}")


def track(
    prev: torch.Tensor,
    next: torch.Tensor,  # noqa: A002 - the agreed API name
    keypoints: torch.Tensor,
    weights: torch.Tensor,
    predicted: torch.Tensor | None = None,
    patch_size: int = 9,
    search_radius: int = 6,
    refine_radius: int = 2,
    levels: int = 3,
    cost: str = "zncc",
    fb_check: bool = True,
    fb_threshold: float = 1.0,
    min_score: float | None = 0.7,
    min_texture: float = 0.01,
    soft: bool = False,
    temperature: float = 0.02,
    lk_iters: int = 1,
    predicted_radius: int | None = 2,
    fb_predicted: bool = True,
    fb_levels: int | None = None,
    prev_pyramid: list[torch.Tensor] | None = None,
    next_pyramid: list[torch.Tensor] | None = None,
) -> TrackOutput:
    """Track keypoints from ``prev`` to ``next`` by coarse-to-fine block matching.

    The coarsest level searches ``search_radius`` pixels (of that level) around the start,
    every finer level ``refine_radius`` around the estimate from the level above, so the
    reach on level 0 is about ``search_radius * 2^(levels-1) + refine_radius * (2^(levels-1) - 1)``
    pixels (with the defaults: 6 * 4 + 2 * 3 = 30 px) around ``predicted`` (or the keypoint).
    With ``predicted`` and ``predicted_radius``, level 0 is first searched only
    ``predicted_radius`` px around the prediction, and the coarse-to-fine search runs only for
    the live features whose best match there lies on the window's edge or scores below
    ``min_score``: a right prediction costs one level instead of ``levels``.

    Empty slots (weight 0) are not matched: they come back unchanged (at the keypoint) with
    weight, score and fb_error 0.

    A feature fails (weight 0) when its template's standard deviation is below
    ``min_texture``, when level 0's best match lies on the edge of its window, when the
    score is below ``min_score`` (``cost="zncc"`` only; ``None`` to skip), when the result
    lies outside ``next``, or when the forward-backward round trip misses by more than
    ``fb_threshold`` px (``fb_check=True``). Black or textureless frames therefore give
    weights all 0 and no error.

    Positions are differentiable with respect to ``prev``, ``next`` and ``keypoints``
    through the last level's sub-pixel step and the Lucas-Kanade polish (``lk_iters``); the
    integer search before them is piecewise constant. ``soft=True`` makes that step a
    soft-argmax of ``-cost / temperature`` over a ``refine_radius`` window around the rounded
    hard estimate (ZNCC lies in [-1, 1], so temperatures of 0.01-0.1 suit it), whose gradient
    is smooth; the hard path still decides the window and the success flags.

    Args:
        prev: ``(B, C, H, W)`` image the keypoints live in, C in {1, 3}, float in [0, 1].
        next: ``(B, C, H, W)`` image to track into.
        keypoints: ``(B, N, 2)`` (x, y) pixel positions in ``prev``.
        weights: ``(B, N)`` weights; 0 (or less) marks an empty slot (not tracked, returned with weight 0).
        predicted: ``(B, N, 2)`` expected positions in ``next`` to centre the search on, or None.
        patch_size: odd side of the square template.
        search_radius: search radius on the coarsest level (px of that level).
        refine_radius: search radius on the finer levels.
        levels: pyramid levels (1 = no pyramid).
        cost: ``"zncc"`` (default), ``"ssd"`` or ``"sad"`` (slower: no convolution form).
        fb_check: run the forward-backward consistency check.
        fb_threshold: largest round-trip error in px.
        min_score: smallest ZNCC accepted (``cost="zncc"`` only), or None.
        min_texture: smallest standard deviation of the template (intensity units).
        soft: differentiable soft-argmax last step.
        temperature: softmax temperature of the soft step (cost units).
        lk_iters: Lucas-Kanade polish iterations on level 0 (0: the parabola's estimate as is).
        predicted_radius: with ``predicted``, the level-0 radius of the first search around it
            (None: always the full coarse-to-fine search). Ignored without ``predicted``.
        fb_predicted: run the forward-backward check also on the features found by that search
            around the prediction; False lets the prediction's agreement stand in for the check
            there (cheaper; the check then runs only on the features the full search found).
        fb_levels: pyramid levels of the way back for the features found by the full search
            (None: ``levels``, the forward search's reach; at most ``levels``): their back match
            searches ``search_radius`` around the keypoint on level ``fb_levels - 1``, then
            ``refine_radius`` on each finer level. Fewer levels cost less (a few ms per level
            and call when few features are checked) and reject fewer wrong matches (see the
            module notes); 1 is one level-0 match of radius ``search_radius``.
        prev_pyramid, next_pyramid: optional ``build_pyramid(prev, L)`` / ``build_pyramid(next, L)``
            with ``L >= levels`` (e.g. kept from the call that tracked into ``prev``): saves
            building them. Their level 0 is used instead of ``prev`` / ``next``, which then only
            give the shapes (the NaN check looks at the pyramids); the caller keeps them consistent.

    Returns:
        :class:`TrackOutput` with keypoints ``(B, N, 2)``, weights, score and fb_error ``(B, N)``.

    Raises:
        ShapeError: shapes of images, keypoints, weights, predicted or a given pyramid disagree.
        ValueRangeError: NaN/Inf in the inputs, a bad setting or a pyramid with too few levels.

    >>> img = torch.rand(1, 1, 48, 64)
    >>> out = track(img, img, torch.tensor([[[20.0, 24.0]]]), torch.ones(1, 1))
    >>> out.keypoints.shape, out.weights.shape
    (torch.Size([1, 1, 2]), torch.Size([1, 1]))
    """
    dims = check_shape(prev, ["B", "1|3", "H", "W"], "prev")
    check_shape(next, ["B", "1|3", "H", "W"], "next", dims)
    check_shape(keypoints, ["B", "N", "2"], "keypoints", dims)
    check_shape(weights, ["B", "N"], "weights", dims)
    if predicted is not None:
        check_shape(predicted, ["B", "N", "2"], "predicted", dims)
    for name, t in (("prev", prev), ("next", next), ("keypoints", keypoints), ("weights", weights)):
        check_float(t, name)
    if predicted is not None:
        check_float(predicted, "predicted")
    check_same_device(prev, "prev", next=next, keypoints=keypoints, weights=weights, predicted=predicted)
    check_same_dtype(prev, "prev", next=next)
    check_same_dtype(keypoints, "keypoints", weights=weights, predicted=predicted)
    _check_track_settings(patch_size, search_radius, refine_radius, levels, cost, fb_threshold, temperature, lk_iters)
    _check_predicted_radius(predicted_radius)
    _check_fb_levels(fb_levels)
    pyr_prev = _given_pyramid(prev_pyramid, "prev_pyramid", levels, dims)
    pyr_next = _given_pyramid(next_pyramid, "next_pyramid", levels, dims)
    if keypoints.numel() > 0:
        pyr_prev = pyr_prev or build_pyramid(prev, levels)
        pyr_next = pyr_next or build_pyramid(next, levels)
    # NaN/Inf anywhere in an image reaches its coarsest level (every pixel has a positive weight
    # there), so that small level is checked instead of the full image.
    coarse_prev = prev if pyr_prev is None else pyr_prev[-1]
    coarse_next = next if pyr_next is None else pyr_next[-1]
    count = _check_values(coarse_prev, coarse_next, keypoints, weights, predicted)  # one host sync

    keypoints = keypoints.to(prev.dtype)
    start = keypoints if predicted is None else predicted.to(prev.dtype)
    n = keypoints.shape[1]
    live = weights > 0
    if count == 0:  # no features (or an empty batch): nothing to match
        zeros = torch.zeros_like(weights)
        return TrackOutput(keypoints.clone(), weights * zeros, zeros, zeros.clone())
    if _compiled_applies(pyr_prev + pyr_next, (prev, next, keypoints, weights, start), cost, soft):
        # the same steps compiled (egorefine.features._track_numba): float32 CPU inference
        return TrackOutput(*_track_numba.track_compiled(
            pyr_prev, pyr_next, keypoints, weights, start, count, patch_size, search_radius, refine_radius, fb_check,
            fb_threshold, min_score, min_texture, lk_iters, None if predicted is None else predicted_radius,
            fb_predicted, levels if fb_levels is None else min(fb_levels, levels),
        ))
    settings = dict(
        patch_size=patch_size,
        search_radius=search_radius,
        refine_radius=refine_radius,
        cost=cost,
        fb_check=fb_check,
        fb_threshold=fb_threshold,
        min_score=min_score,
        min_texture=min_texture,
        temperature=temperature if soft else None,
        lk_iters=lk_iters,
        predicted_radius=None if predicted is None else predicted_radius,
        fb_predicted=fb_predicted,
        fb_levels=levels if fb_levels is None else min(fb_levels, levels),
    )
    zeros = torch.zeros_like(weights)
    if count > n - _SLOT_STEP:  # (almost) every slot is live: no subset
        out = _track_live(pyr_prev, pyr_next, keypoints, weights, start, **settings)
        return TrackOutput(
            torch.where(live.unsqueeze(-1), out.keypoints, keypoints),
            out.weights,
            out.score * live,
            out.fb_error * live,
        )
    # Only the live slots are matched (empty ones cost as much): the live slots of every row
    # first, as many columns as the fullest row has live features (rounded up, see _first_true).
    idx = _first_true(live, count)
    sub = _track_live(pyr_prev, pyr_next, _take(keypoints, idx), _take(weights, idx), _take(start, idx), **settings)
    sub_live = _take(live, idx)
    return TrackOutput(
        _put(keypoints, idx, torch.where(sub_live.unsqueeze(-1), sub.keypoints, _take(keypoints, idx))),
        _put(weights * zeros, idx, sub.weights),
        _put(zeros, idx, sub.score * sub_live),
        _put(zeros, idx, sub.fb_error * sub_live),
    )


def _compiled_applies(
    pyramids: list[torch.Tensor], tensors: tuple[torch.Tensor, ...], cost: str, soft: bool
) -> bool:
    """The compiled track applies: :func:`~egorefine.core.use_compiled` on every tensor it reads and the kernel's
    limit, hard matching with the ZNCC cost."""
    hard_zncc = not soft and cost == "zncc"
    return hard_zncc and use_compiled(*pyramids, *tensors)


def _given_pyramid(
    pyramid: list[torch.Tensor] | None, name: str, levels: int, dims: dict[str, int]
) -> list[torch.Tensor] | None:
    """Check a caller's pyramid (from :func:`build_pyramid`) and return its first ``levels`` levels."""
    if pyramid is None:
        return None
    if not isinstance(pyramid, (list, tuple)) or len(pyramid) < levels:
        raise ValueRangeError(f"{name}: expected a list of at least levels={levels} tensors from build_pyramid")
    h, w = dims["H"], dims["W"]
    for level in range(levels):
        check_shape(pyramid[level], ["B", "1", "H", "W"], f"{name}[{level}]", {"B": dims["B"], "H": h, "W": w})
        h, w = (h + 1) // 2, (w + 1) // 2
    return list(pyramid[:levels])


def _track_live(
    pyr_prev: list[torch.Tensor],
    pyr_next: list[torch.Tensor],
    keypoints: torch.Tensor,
    weights: torch.Tensor,
    start: torch.Tensor,
    patch_size: int,
    search_radius: int,
    refine_radius: int,
    cost: str,
    fb_check: bool,
    fb_threshold: float,
    min_score: float | None,
    min_texture: float,
    temperature: float | None,
    lk_iters: int,
    predicted_radius: int | None,
    fb_predicted: bool,
    fb_levels: int,
) -> TrackOutput:
    """:func:`track` on pyramids, every slot matched (the caller drops the empty ones beforehand)."""
    h, w = pyr_prev[0].shape[-2:]
    live = weights > 0
    out_kp, best, edge, found = _forward_match(
        pyr_prev,
        pyr_next,
        keypoints,
        start,
        live,
        patch_size,
        search_radius,
        refine_radius,
        cost,
        predicted_radius,
        min_score,
    )
    if temperature is not None:
        # Differentiable step: soft-argmax over a refine_radius window around the hard result.
        out_kp, _, _ = _match_level(
            pyr_prev[0], pyr_next[0], keypoints, out_kp.detach(), patch_size, refine_radius, cost, temperature
        )
    if lk_iters > 0:
        out_kp = _lk_refine(pyr_prev[0], pyr_next[0], keypoints, out_kp, patch_size, lk_iters, cost)
    score = -best.detach()

    with torch.no_grad():
        kp_d = out_kp.detach()
        kp_in = keypoints.detach()
        ok = live & ~edge
        # Template spread (unbiased standard deviation, as Tensor.std but several times cheaper here).
        template = _extract_patches(pyr_prev[0].detach(), kp_in.round(), patch_size).flatten(2)
        spread = (template - template.mean(dim=-1, keepdim=True)).square().sum(dim=-1)
        ok = ok & (spread >= min_texture**2 * (patch_size * patch_size - 1))
        if min_score is not None and cost == "zncc":
            ok = ok & (score >= min_score)
        inside = (kp_d[..., 0] >= 0) & (kp_d[..., 0] <= w - 1) & (kp_d[..., 1] >= 0) & (kp_d[..., 1] <= h - 1)
        ok = ok & inside & torch.isfinite(kp_d).all(dim=-1)
        if fb_check:
            # Track the result back into prev, the search centred on the original keypoint, and
            # measure the round trip; a wrong match lands far from the start or on its window's edge.
            # A feature found by the full search gets a back search with a reach of its own: on
            # the fb_levels finest levels, search_radius on the coarsest of them (a level-0 window
            # of refine_radius around the start mostly confirms a wrong match: the keypoint's own
            # patch is the best fit of a look-alike within a few pixels of it). A feature found
            # next to its prediction comes back with a level-0 match of radius refine_radius,
            # or (fb_predicted=False) the prediction's agreement stands in for the check.
            fb_error, back_ok = _round_trip(
                pyr_prev[:fb_levels],
                pyr_next[:fb_levels],
                kp_in,
                kp_d,
                ok & ~found,
                patch_size,
                search_radius,
                refine_radius,
                cost,
            )
            if fb_predicted:
                near_error, near_ok = _round_trip(
                    pyr_prev[:1], pyr_next[:1], kp_in, kp_d, ok & found, patch_size, refine_radius, refine_radius, cost
                )
                fb_error, back_ok = torch.where(found, near_error, fb_error), back_ok & near_ok
            ok = ok & back_ok & (fb_error <= fb_threshold)
        else:
            fb_error = torch.zeros_like(weights)
    new_w = weights * ok.to(weights.dtype)
    return TrackOutput(out_kp, new_w, score.to(weights.dtype), fb_error.to(weights.dtype))


def _round_trip(
    pyr_prev: list[torch.Tensor],
    pyr_next: list[torch.Tensor],
    kp_in: torch.Tensor,
    kp_out: torch.Tensor,
    check: torch.Tensor,
    patch_size: int,
    radius: int,
    refine_radius: int,
    cost: str,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward-backward round trip of the ``check`` features (B, N): (error in px, not-on-edge flag), both (B, N).

    ``kp_out`` is matched back from ``next`` into ``prev`` around ``kp_in`` (coarse to fine over the
    given levels, ``radius`` on the coarsest); features outside ``check`` get error 0 and pass.
    All features are matched when most are to be checked, else only the subset (one host synchronisation).
    """
    n = check.shape[1]
    count = n if n <= _SLOT_STEP else int(check.sum(dim=1).max())
    if count == 0:
        return torch.zeros_like(kp_in[..., 0]), torch.ones_like(check)

    def back(out: torch.Tensor, start: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if len(pyr_prev) == 1:
            pos, _, edge = _match_level(pyr_next[0], pyr_prev[0], out, start, patch_size, radius, cost)
        else:
            pos, _, edge = _match_to_level0(pyr_next, pyr_prev, out, start, patch_size, radius, refine_radius, cost)
        return pos, edge

    if count > n - _SLOT_STEP:
        pos, edge = back(kp_out, kp_in)
        return torch.where(check, (pos - kp_in).norm(dim=-1), 0.0), ~(edge & check)
    idx = _first_true(check, count)
    sub_in = _take(kp_in, idx)
    pos, edge = back(_take(kp_out, idx), sub_in)
    sel = _take(check, idx)
    err = _put(torch.zeros_like(kp_in[..., 0]), idx, torch.where(sel, (pos - sub_in).norm(dim=-1), 0.0))
    return err, ~_put(torch.zeros_like(check), idx, edge & sel)


class Tracker(torch.nn.Module):
    """Module form of :func:`track`; stores the settings.

    ``forward(prev, next, keypoints, weights, predicted=None, prev_pyramid=None, next_pyramid=None) -> TrackOutput``.

    >>> img = torch.rand(1, 1, 48, 64)
    >>> Tracker(levels=2)(img, img, torch.tensor([[[20.0, 24.0]]]), torch.ones(1, 1)).keypoints.shape
    torch.Size([1, 1, 2])
    """

    def __init__(
        self,
        patch_size: int = 9,
        search_radius: int = 6,
        refine_radius: int = 2,
        levels: int = 3,
        cost: str = "zncc",
        fb_check: bool = True,
        fb_threshold: float = 1.0,
        min_score: float | None = 0.7,
        min_texture: float = 0.01,
        soft: bool = False,
        temperature: float = 0.02,
        lk_iters: int = 1,
        predicted_radius: int | None = 2,
        fb_predicted: bool = True,
        fb_levels: int | None = None,
    ) -> None:
        super().__init__()
        _check_track_settings(
            patch_size, search_radius, refine_radius, levels, cost, fb_threshold, temperature, lk_iters
        )
        _check_predicted_radius(predicted_radius)
        _check_fb_levels(fb_levels)
        self.patch_size = patch_size
        self.search_radius = search_radius
        self.refine_radius = refine_radius
        self.levels = levels
        self.cost = cost
        self.fb_check = fb_check
        self.fb_threshold = fb_threshold
        self.min_score = min_score
        self.min_texture = min_texture
        self.soft = soft
        self.temperature = temperature
        self.lk_iters = lk_iters
        self.predicted_radius = predicted_radius
        self.fb_predicted = fb_predicted
        self.fb_levels = fb_levels

    def forward(
        self,
        prev: torch.Tensor,
        next: torch.Tensor,  # noqa: A002 - the agreed API name
        keypoints: torch.Tensor,
        weights: torch.Tensor,
        predicted: torch.Tensor | None = None,
        prev_pyramid: list[torch.Tensor] | None = None,
        next_pyramid: list[torch.Tensor] | None = None,
    ) -> TrackOutput:
        return track(
            prev,
            next,
            keypoints,
            weights,
            predicted=predicted,
            patch_size=self.patch_size,
            search_radius=self.search_radius,
            refine_radius=self.refine_radius,
            levels=self.levels,
            cost=self.cost,
            fb_check=self.fb_check,
            fb_threshold=self.fb_threshold,
            min_score=self.min_score,
            min_texture=self.min_texture,
            soft=self.soft,
            temperature=self.temperature,
            lk_iters=self.lk_iters,
            predicted_radius=self.predicted_radius,
            fb_predicted=self.fb_predicted,
            fb_levels=self.fb_levels,
            prev_pyramid=prev_pyramid,
            next_pyramid=next_pyramid,
        )

    def extra_repr(self) -> str:
        return (
            f"patch_size={self.patch_size}, search_radius={self.search_radius}, levels={self.levels}, "
            f"cost={self.cost!r}, fb_check={self.fb_check}, soft={self.soft}"
        )
