"""Corner detection: gradient response, non-maximum suppression, grid bucketing, sub-pixel peaks.

The paper (docs/method.md, "The loop", step 2) uses a fast gradient-based keypoint detector and tracks the
keypoints frame to frame. Here the response is kornia's Shi-Tomasi (``gftt_response``) or
Harris (``harris_response``) map; local maxima are kept by a max-pool comparison; an image
grid spreads the keypoints (each cell gives its best corner before any cell gives its
second best); the peak is refined to sub-pixel precision by a quadratic fit of the response
over its 3x3 neighbourhood. The output always has ``max_features`` slots: ``(B, N, 2)``
positions and ``(B, N)`` weights that are 1 for a real keypoint and 0 for an empty slot,
whose position is (0, 0). A black or textureless image gives no keypoints (all weights 0).

:func:`replenish` keeps live tracks in their slots and fills the empty slots with fresh,
well separated detections; a tracker calls it when the live count drops ("detection re-runs
only when tracks thin out").

For float32 CPU images with the Shi-Tomasi response (the refiner's case), the same steps run
compiled (:mod:`egorefine.features._detect_numba`, numba) where :func:`egorefine.core.use_compiled` allows
it, in a few passes over the image instead of some forty full-image operator launches: the same selection rule
and formulas, agreeing with this path to float rounding (the same keypoints but for a rare swap of two nearly
equal candidates, positions to float32 rounding of the corner solve; exact ties go by pixel index instead of
``torch.topk``'s order; the differences and timings measured are in docs/decisions.md). The torch path stays
the reference for GPU tensors, float64, Harris and tracing. Detection is a hard selection: keypoints and weights
carry no gradient on either path.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from kornia.feature import gftt_response, harris_response

from ..core import (
    ValueRangeError,
    check_choice,
    check_finite,
    check_float,
    check_image,
    check_same_device,
    check_shape,
    eps_like,
    to_grey,
    use_compiled,
)
from ..core.dispatch import needs_grad
from . import _detect_numba
from ._peaks import _MIN_SIDE, _subpixel_offsets

__all__ = ["detect", "Detector", "replenish", "corner_response"]

_RESPONSES = ("gftt", "harris")
_SUBPIXEL = ("gradient", "quadratic", "none")


def corner_response(image: torch.Tensor, response: str = "gftt", k: float = 0.04) -> torch.Tensor:
    """Corner strength of every pixel, in units of squared intensity gradient.

    ``"gftt"`` is the smaller eigenvalue of the structure tensor (Shi-Tomasi); ``"harris"``
    is ``det - k * trace^2``, returned as ``sign(R) * sqrt(|R|)`` so that both share one unit
    and one absolute threshold. Gradients are kornia's normalised Sobel, the structure
    tensor is smoothed with kornia's 7x7 Gaussian (sigma 1).

    Args:
        image: ``(B, 1, H, W)`` or ``(B, 3, H, W)`` float image in [0, 1].
        response: ``"gftt"`` or ``"harris"``.
        k: the Harris constant.

    Returns:
        ``(B, 1, H, W)`` response.

    >>> corner_response(torch.rand(2, 3, 16, 20)).shape
    torch.Size([2, 1, 16, 20])
    """
    check_image(image, "image", min_size=_MIN_SIDE)
    check_choice(response, _RESPONSES, "response")
    gray = to_grey(image)
    if response == "gftt":
        return gftt_response(gray)
    r = harris_response(gray, k=k)
    return torch.sign(r) * r.abs().sqrt()


def _max_filter(x: torch.Tensor, radius: int) -> torch.Tensor:
    """Maximum over the ``(2 radius + 1)^2`` square around every pixel of ``x`` (B, 1, H, W).

    Separable (rows, then columns) with shifted slices: the same result as
    ``F.max_pool2d(x, 2 radius + 1, stride=1, padding=radius)``, with ``2 (2 radius + 1)`` maxima per
    pixel instead of ``(2 radius + 1)^2``, which is much cheaper on CPU for the 7x7 window used here.
    """
    if radius == 0:
        return x
    h, w = x.shape[-2:]
    k = 2 * radius + 1
    y = F.pad(x, (radius, radius, 0, 0), value=float("-inf"))
    rows = y[..., 0:w]
    for i in range(1, k):
        rows = torch.maximum(rows, y[..., i : i + w])
    y = F.pad(rows, (0, 0, radius, radius), value=float("-inf"))
    out = y[..., 0:h, :]
    for i in range(1, k):
        out = torch.maximum(out, y[..., i : i + h, :])
    return out


def _gradient_offsets(
    gray: torch.Tensor, ix: torch.Tensor, iy: torch.Tensor, radius: int = 3, iters: int = 2
) -> torch.Tensor:
    """Sub-pixel corner positions from image gradients (Foerstner's corner point).

    A corner ``q`` is the point that every nearby edge passes through: each pixel ``p`` with
    gradient ``g`` satisfies ``g . (q - p) = 0``. The weighted least-squares solution is
    ``q = (sum w g g^T)^-1 sum w g g^T p`` over a ``(2 radius + 1)^2`` window with Gaussian
    weights ``w`` around the current estimate; ``iters`` re-centred passes. Exact for ideal
    (also blurred or anti-aliased) L- and X-junctions, where a fit of the response peak is
    biased. Returns offsets (B, N, 2) from the integer peaks, limited to 1.5 px; where the
    2x2 system is ill-conditioned (no corner) the offset is 0.
    """
    b, _, h, w = gray.shape
    flat = gray.reshape(b, h * w)
    size = 2 * radius + 1
    r = torch.arange(-radius - 1, radius + 2, device=gray.device)  # one extra pixel for the Sobel
    base = torch.stack([ix, iy], dim=-1).to(gray.dtype)  # (B, N, 2)
    est = base
    eps = eps_like(gray)
    sigma2 = (0.6 * radius) ** 2
    n = ix.shape[1]
    for _ in range(iters):
        cx = est[..., 0].round().long()
        cy = est[..., 1].round().long()
        xs = (cx.unsqueeze(-1) + r).clamp(0, w - 1)  # (B, N, s + 2); clamping repeats the border
        ys = (cy.unsqueeze(-1) + r).clamp(0, h - 1)
        idx = (ys.unsqueeze(-1) * w + xs.unsqueeze(-2)).reshape(b, n * (size + 2) ** 2)
        patch = flat.gather(1, idx).view(b, n, size + 2, size + 2)
        # Sobel gradients of the windows only (kornia's normalised 3x3 Sobel, as in corner_response),
        # far cheaper than a gradient image for a few hundred corners.
        dx = patch[..., 2:] - patch[..., :-2]  # (B, N, s + 2, s)
        gx = (dx[..., :-2, :] + 2 * dx[..., 1:-1, :] + dx[..., 2:, :]) / 8
        dy = patch[..., 2:, :] - patch[..., :-2, :]  # (B, N, s, s + 2)
        gy = (dy[..., :-2] + 2 * dy[..., 1:-1] + dy[..., 2:]) / 8
        xs, ys = xs[..., 1:-1], ys[..., 1:-1]
        px = xs.unsqueeze(-2).to(gray.dtype).expand(b, n, size, size)
        py = ys.unsqueeze(-1).to(gray.dtype).expand(b, n, size, size)
        wgt = torch.exp(-((px - est[..., 0, None, None]) ** 2 + (py - est[..., 1, None, None]) ** 2) / (2 * sigma2))
        axx = (wgt * gx * gx).sum(dim=(-2, -1))
        axy = (wgt * gx * gy).sum(dim=(-2, -1))
        ayy = (wgt * gy * gy).sum(dim=(-2, -1))
        bx = (wgt * (gx * gx * px + gx * gy * py)).sum(dim=(-2, -1))
        by = (wgt * (gx * gy * px + gy * gy * py)).sum(dim=(-2, -1))
        det = axx * ayy - axy * axy
        good = det > 1e-3 * (axx + ayy) ** 2 + eps
        det_safe = torch.where(good, det, torch.ones_like(det))
        qx = (ayy * bx - axy * by) / det_safe
        qy = (axx * by - axy * bx) / det_safe
        q = torch.stack([qx, qy], dim=-1)
        q = base + (q - base).clamp(-1.5, 1.5)
        est = torch.where(good.unsqueeze(-1), q, est)
    return est - base


def _check_settings(max_features: int, grid: tuple[int, int], nms_radius: int, border: int) -> None:
    if not isinstance(max_features, int) or max_features < 1:
        raise ValueRangeError(f"max_features: expected an int >= 1, got {max_features!r}")
    if len(grid) != 2 or any((not isinstance(g, int)) or g < 1 for g in grid):
        raise ValueRangeError(f"grid: expected two ints >= 1 (rows, cols), got {grid!r}")
    if not isinstance(nms_radius, int) or nms_radius < 0:
        raise ValueRangeError(f"nms_radius: expected an int >= 0, got {nms_radius!r}")
    if not isinstance(border, int) or border < 0:
        raise ValueRangeError(f"border: expected an int >= 0, got {border!r}")


def detect(
    image: torch.Tensor,
    max_features: int = 500,
    grid: tuple[int, int] = (8, 8),
    response: str = "gftt",
    nms_radius: int = 3,
    quality: float = 0.01,
    min_response: float = 1e-4,
    border: int = 8,
    subpixel: str = "gradient",
    k: float = 0.04,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Detect up to ``max_features`` corners per image, spread over a grid, at sub-pixel positions.

    A pixel is a candidate when its response (:func:`corner_response`) is the maximum of its
    ``(2 * nms_radius + 1)^2`` neighbourhood, at least ``min_response`` (absolute: a black or
    flat image has none) and at least ``quality`` times the image's strongest response, and it
    lies ``border`` pixels or more inside the image. The image is cut into ``grid`` cells;
    candidates are taken round-robin over the cells (each cell's best, then each cell's
    second best, ...; ties broken by response), so textured cells fill the slots that
    textureless cells leave empty. Positions (pixel centres at integer coordinates) are
    refined to sub-pixel precision with ``subpixel="gradient"`` (Foerstner's corner point: the
    least-squares intersection of the edges around the peak, exact for ideal junctions) or
    ``"quadratic"`` (a 2-D quadratic fit of the response over the 3x3 neighbourhood: cheaper,
    but biased on sharp corners, whose response peak is not a quadratic), or not at all (``"none"``).

    Selection is discrete (piecewise constant in the image); the sub-pixel step is smooth: with an ``image``
    that requires grad, the keypoints carry the gradient of their sub-pixel offsets (``"gradient"`` or
    ``"quadratic"``), the weights none.

    Args:
        image: ``(B, 1, H, W)`` or ``(B, 3, H, W)`` float image in [0, 1].
        max_features: the number of slots N (500: the refiner's budget on a 640x480 frame).
        grid: (rows, cols) of the bucketing grid (8 x 8: features over the whole view, which conditions the
            motion solve better than a cluster on the richest texture).
        response: ``"gftt"`` (Shi-Tomasi, the default: it has no constant to tune) or ``"harris"``.
        nms_radius: radius of the non-maximum suppression window (3 px: neighbours stay apart by more than
            the tracker's sub-pixel step can confuse).
        quality: relative threshold, a fraction of each image's maximum response (0.01, OpenCV's
            ``goodFeaturesToTrack`` habit).
        min_response: absolute threshold in squared-gradient units (kornia's Sobel of [0, 1] images; 1e-4: a
            black or flat image has no corners, whatever ``quality`` says).
        border: keypoints closer than this to the image edge are dropped (8 px: the tracker's patch and its
            search stay inside the image).
        subpixel: ``"gradient"`` (the default: exact for ideal junctions), ``"quadratic"`` or ``"none"``.
        k: the Harris constant (``response="harris"`` only; 0.04, the usual value).

    Returns:
        keypoints ``(B, N, 2)`` as (x, y) pixels, and weights ``(B, N)`` in {0, 1}; empty slots
        are at (0, 0) with weight 0. Real keypoints come first, in selection order.

    >>> kp, w = detect(torch.rand(2, 1, 64, 80), max_features=50, grid=(2, 2))
    >>> kp.shape, w.shape
    (torch.Size([2, 50, 2]), torch.Size([2, 50]))
    """
    check_image(image, "image", min_size=_MIN_SIDE)
    check_choice(response, _RESPONSES, "response")
    check_choice(subpixel, _SUBPIXEL, "subpixel")
    _check_settings(max_features, tuple(grid), nms_radius, border)
    settings = (max_features, tuple(grid), response, nms_radius, quality, min_response, border, subpixel, k)
    if subpixel == "none" or not needs_grad(image):
        with torch.no_grad():
            return _detect(image, *settings)
    # the selection without a graph (the torch path, for the pixels it chose), the sub-pixel step with one
    with torch.no_grad():
        _, weights, ix, iy = _detect(image, *settings, pixels=True)
    kp = torch.stack([ix, iy], dim=-1).to(image.dtype)
    kp = kp + _offsets(image, ix, iy, response, k, subpixel)
    return kp * weights.unsqueeze(-1), weights


def _offsets(image: torch.Tensor, ix: torch.Tensor, iy: torch.Tensor, response: str, k: float,
             subpixel: str) -> torch.Tensor:
    """Sub-pixel offsets ``(B, N, 2)`` of the integer peaks ``(ix, iy)`` by the ``subpixel`` method."""
    if subpixel == "gradient":
        return _gradient_offsets(to_grey(image), ix, iy)
    return _subpixel_offsets(corner_response(image, response, k)[:, 0], ix, iy)


def _detect(
    image: torch.Tensor,
    n: int,
    grid: tuple[int, int],
    response: str,
    nms_radius: int,
    quality: float,
    min_response: float,
    border: int,
    subpixel: str,
    k: float,
    pixels: bool = False,
) -> tuple[torch.Tensor, ...]:
    """The detection: ``(keypoints, weights)``; with ``pixels`` (always the torch path) also the integer peaks
    ``(ix, iy)``, each ``(B, N)``."""
    b, _, h, w = image.shape
    if not pixels and _compiled_applies(image, response):
        # the same steps compiled (egorefine.features._detect_numba): float32 CPU inference, agreeing to rounding
        return _detect_numba.detect_compiled(
            to_grey(image), n, grid, nms_radius, quality, min_response, border, subpixel
        )
    resp = corner_response(image, response, k)  # (B, 1, H, W)
    # Non-maximum suppression by comparison with a max-pooled copy.
    pooled = _max_filter(resp, nms_radius)
    peak_max = resp.flatten(1).amax(dim=1).view(b, 1, 1, 1)
    threshold = torch.clamp(peak_max * quality, min=min_response)
    keep = (resp >= pooled) & (resp >= threshold)
    inner = torch.zeros(h, w, dtype=torch.bool, device=image.device)
    inner[border : h - border, border : w - border] = True
    keep = keep & inner
    # Normalised strength in [0, 0.5]: a tie-breaker that never outranks a round.
    strength = 0.5 * resp / peak_max.clamp_min(eps_like(resp))

    gy, gx = grid
    ch, cw = math.ceil(h / gy), math.ceil(w / gx)
    pad_h, pad_w = gy * ch - h, gx * cw - w
    invalid = -float(n + 2)
    score = torch.where(keep, strength, torch.full_like(strength, invalid))
    score = F.pad(score, (0, pad_w, 0, pad_h), value=invalid)  # (B, 1, gy*ch, gx*cw)
    cells = score.view(b, gy, ch, gx, cw).permute(0, 1, 3, 2, 4).reshape(b, gy * gx, ch * cw)
    kc = min(ch * cw, n)
    cell_val, cell_idx = cells.topk(kc, dim=2)  # sorted, best first in each cell
    rank = torch.arange(kc, device=image.device, dtype=resp.dtype).view(1, 1, kc)
    # Round-robin key: every cell's r-th best outranks any cell's (r+1)-th best.
    key = torch.where(cell_val > invalid, cell_val - rank, torch.full_like(cell_val, invalid))
    key = key.reshape(b, gy * gx * kc)
    cell_of = torch.arange(gy * gx, device=image.device).view(1, gy * gx, 1).expand(b, gy * gx, kc).reshape(b, -1)
    within = cell_idx.reshape(b, -1)
    if key.shape[1] < n:  # fewer pixels than slots: pad with invalid candidates
        extra = n - key.shape[1]
        key = F.pad(key, (0, extra), value=invalid)
        cell_of = F.pad(cell_of, (0, extra))
        within = F.pad(within, (0, extra))
    top_key, top = key.topk(n, dim=1)
    valid = top_key > invalid
    cell = cell_of.gather(1, top)
    pos = within.gather(1, top)
    iy = (cell // gx) * ch + pos // cw
    ix = (cell % gx) * cw + pos % cw
    # Invalid slots may point into the padding: clamp so that the gathers below stay in range.
    ix = torch.where(valid, ix, torch.zeros_like(ix)).clamp(0, w - 1)
    iy = torch.where(valid, iy, torch.zeros_like(iy)).clamp(0, h - 1)
    kp = torch.stack([ix, iy], dim=-1).to(resp.dtype)
    if subpixel == "gradient":
        kp = kp + _gradient_offsets(to_grey(image), ix, iy)
    elif subpixel == "quadratic":
        kp = kp + _subpixel_offsets(resp[:, 0], ix, iy)
    weights = valid.to(resp.dtype)
    kp = kp * weights.unsqueeze(-1)
    return (kp, weights, ix, iy) if pixels else (kp, weights)


def _compiled_applies(image: torch.Tensor, response: str) -> bool:
    """The compiled detection applies: :func:`~egorefine.core.use_compiled` (float32 CPU, no tracing) and the
    kernel's limits, the Shi-Tomasi response on an image of 4 x 4 pixels or more (kornia's reflected 7x7 blur needs
    4; smaller images keep the torch path's error). :func:`detect` asks under ``no_grad``: a selection has no
    gradient on either path."""
    shi_tomasi, large_enough = response == "gftt", min(image.shape[-2:]) >= _MIN_SIDE
    return shi_tomasi and large_enough and use_compiled(image)


class Detector(torch.nn.Module):
    """Module form of :func:`detect`: stores the settings; ``forward(image) -> (keypoints, weights)``.

    Args:
        max_features, grid, response, nms_radius, quality, min_response, border, subpixel, k: as in :func:`detect`,
            with its defaults (checked here, at construction).

    ``forward(image)``: ``(B, 1|3, H, W)`` in [0, 1] -> keypoints ``(B, N, 2)`` and weights ``(B, N)``.

    Example:
        >>> kp, w = Detector(max_features=20, grid=(2, 2))(torch.rand(1, 1, 48, 48))
        >>> kp.shape
        torch.Size([1, 20, 2])
    """

    def __init__(
        self,
        max_features: int = 500,
        grid: tuple[int, int] = (8, 8),
        response: str = "gftt",
        nms_radius: int = 3,
        quality: float = 0.01,
        min_response: float = 1e-4,
        border: int = 8,
        subpixel: str = "gradient",
        k: float = 0.04,
    ) -> None:
        super().__init__()
        check_choice(response, _RESPONSES, "response")
        check_choice(subpixel, _SUBPIXEL, "subpixel")
        _check_settings(max_features, tuple(grid), nms_radius, border)
        self.max_features = max_features
        self.grid = tuple(grid)
        self.response = response
        self.nms_radius = nms_radius
        self.quality = quality
        self.min_response = min_response
        self.border = border
        self.subpixel = subpixel
        self.k = k

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return detect(
            image,
            max_features=self.max_features,
            grid=self.grid,
            response=self.response,
            nms_radius=self.nms_radius,
            quality=self.quality,
            min_response=self.min_response,
            border=self.border,
            subpixel=self.subpixel,
            k=self.k,
        )

    def extra_repr(self) -> str:
        return f"max_features={self.max_features}, grid={self.grid}, response={self.response!r}"


def replenish(
    image: torch.Tensor,
    keypoints: torch.Tensor,
    weights: torch.Tensor,
    max_features: int | None = None,
    min_distance: float = 8.0,
    **detect_kwargs,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Keep the live tracks in their slots and fill the empty slots with fresh detections.

    Live tracks (``weights > 0``) keep slot, position and weight. Fresh corners from
    :func:`detect` on ``image`` that lie at least ``min_distance`` pixels from every live
    track fill the empty slots in the detector's order (round-robin over the grid), with
    weight 1. Slots beyond what the image offers stay empty (weight 0, position (0, 0)).

    Args:
        image: ``(B, 1, H, W)`` or ``(B, 3, H, W)`` float image in [0, 1] (the frame the
            keypoints live in).
        keypoints: ``(B, N, 2)`` current tracks.
        weights: ``(B, N)`` their weights; 0 marks an empty or lost slot.
        max_features: slots of the result, ``M >= N`` (default N); slots N..M-1 start empty.
        min_distance: minimum distance in pixels between a new keypoint and any live track.
        **detect_kwargs: passed to :func:`detect` (``grid``, ``response``, ``border``, ...).

    Returns:
        keypoints ``(B, M, 2)`` and weights ``(B, M)``.

    >>> img = torch.rand(1, 1, 64, 64)
    >>> kp, w = replenish(img, torch.zeros(1, 10, 2), torch.zeros(1, 10), grid=(2, 2))
    >>> kp.shape, w.shape
    (torch.Size([1, 10, 2]), torch.Size([1, 10]))
    """
    dims = check_image(image, "image", min_size=_MIN_SIDE)
    check_shape(keypoints, ["B", "N", "2"], "keypoints", dims)
    check_shape(weights, ["B", "N"], "weights", dims)
    check_float(keypoints, "keypoints")
    check_float(weights, "weights")
    check_same_device(image, "image", keypoints=keypoints, weights=weights)
    check_finite(keypoints, "keypoints")
    check_finite(weights, "weights")
    n = dims["N"]
    m = n if max_features is None else max_features
    if not isinstance(m, int) or m < n:
        raise ValueRangeError(f"max_features: expected an int >= N = {n} (the slots of keypoints), got {m!r}")
    if not min_distance >= 0:
        raise ValueRangeError(f"min_distance: expected a number >= 0, got {min_distance!r}")
    b = dims["B"]
    if m == 0 or b == 0:  # no slots to fill
        return keypoints.clone(), weights.clone()
    if m > n:
        keypoints = F.pad(keypoints, (0, 0, 0, m - n))
        weights = F.pad(weights, (0, m - n))
    # Enough candidates to fill every slot even when some fall next to live tracks.
    cand, cand_w = detect(image, max_features=2 * m, **detect_kwargs)
    cand = cand.to(keypoints.dtype)
    live = weights > 0
    with torch.no_grad():
        if use_compiled(cand, cand_w, keypoints, live):
            # the same float32 distances without the (B, 2M, M) map
            usable = _detect_numba.usable_compiled(cand, cand_w, keypoints, live, min_distance)
        else:
            d2 = (cand.unsqueeze(2) - keypoints.detach().unsqueeze(1)).pow(2).sum(-1)  # (B, 2M, M)
            d2 = torch.where(live.unsqueeze(1), d2, torch.full_like(d2, float("inf")))
            usable = (cand_w > 0) & (d2.amin(dim=2) >= min_distance**2)
        # Usable candidates first, in detection order (stable sort keeps the order).
        order = torch.sort(usable.to(torch.uint8), dim=1, descending=True, stable=True).indices
        n_usable = usable.sum(dim=1, keepdim=True)
        empty = ~live
        slot_rank = empty.long().cumsum(dim=1) - 1  # j-th empty slot gets the j-th usable candidate
        fill = empty & (slot_rank < n_usable)
        pick = order.gather(1, slot_rank.clamp(0, cand.shape[1] - 1))
    fresh = cand.gather(1, pick.unsqueeze(-1).expand(b, m, 2))  # (outside no_grad: a detection's graph stays)
    zeros = torch.zeros_like(keypoints)
    new_kp = torch.where(live.unsqueeze(-1), keypoints, torch.where(fill.unsqueeze(-1), fresh, zeros))
    new_w = torch.where(live, weights, fill.to(weights.dtype))
    return new_kp, new_w
