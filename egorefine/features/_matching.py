"""Batched block matching of feature patches, the tracker's search (:func:`egorefine.features.track`).

The stages of one search, each on every feature of every batch item at once: cutting templates and windows at
whole pixels (:func:`_extract_patches`), the cost of every shift (:func:`_cost_map`, grouped convolutions, or box
sums of a small coarse level, :func:`_box_maps`), the sub-pixel peak (:func:`_best_shift`, a parabola per axis),
one pyramid level (:func:`_match_level`), the levels coarse to fine (:func:`_coarse_to_fine`,
:func:`_match_to_level0`), the first search around a prediction (:func:`_forward_match`), the Lucas-Kanade polish
(:func:`_lk_refine`) and the forward-backward round trip (:func:`_round_trip`). :mod:`egorefine.features.tracking`
assembles them; :mod:`egorefine.features._track_numba` repeats them compiled.

Subsets of features (the live ones, the ones to search again) are gathered into slots and scattered back
(:func:`_first_true`, :func:`_take`, :func:`_put`), padded to multiples of :data:`_SLOT_STEP`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..core import eps_like

# Subsets of features are padded to a multiple of this many slots: the grouped convolutions
# then see a handful of shapes over a video instead of a new one every frame (a new shape
# costs oneDNN a kernel set-up several times the convolution itself).
_SLOT_STEP = 32


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
    that depends on the fractional offset, a bias towards whole pixels), and each iteration
    solves the 2x2 normal equations ``(sum g g^T) delta = sum g (T - I)`` with the template
    gradient ``g``. For ``cost="zncc"`` both patches are normalised to zero mean and equal
    spread first (gain and bias invariant, like ZNCC). Steps are clamped to half a pixel each and
    the total change to one pixel, so a flat or edge-only patch cannot run away. Differentiable
    (grid_sample).
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
