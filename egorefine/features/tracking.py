"""Feature tracking by batched local block matching, coarse to fine, with sub-pixel peaks.

The paper (docs/method.md, "The loop", step 2) tracks keypoints from frame to frame by local block
matching; the tracks feed the least-squares ego-motion of eq. (3). Here every feature of
every batch item is matched at once, with no Python loop over features:

1. Both images go to grey and into an image pyramid (``levels`` levels, each a 3x3 binomial
   blur and a stride-2 subsampling, so a pixel ``x`` of level 0 is ``x / 2^l`` on level ``l``;
   :func:`build_pyramid`).
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
   the parabola alone is biased by the shape of the cost around its minimum, which the polish,
   fitting the image itself, does not share.
5. A forward-backward check matches the result back from ``next`` into ``prev``, the search
   centred on the keypoint, and rejects features whose round trip misses the start by more
   than ``fb_threshold`` pixels or whose back match lies on its window's edge. The way back
   needs a reach of its own: a wrong match (a look-alike patch, typically at large motion)
   found by the full search comes back to the keypoint itself from a small level-0 window,
   since the keypoint's patch is what it was matched to. So the features found by the full
   search go back coarse to fine over the ``fb_levels`` finest levels (``search_radius`` on
   the coarsest of them; by default all ``levels``, the same reach as the way there); the
   features found next to their prediction (below) go back with one level-0 match of radius
   ``refine_radius``, or skip the check with ``fb_predicted=False``. Each level of the way back
   rejects more wrong matches, at the cost of a search; the share of wrong tracks per setting
   is in the design decisions of the documentation (docs/decisions.md).

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
of a dozen small torch ops per level, whose launch overhead dominates at a few hundred features.
Its positions agree with this torch path (the reference, also for GPU tensors, autograd, tracing,
``soft=True`` and the other costs) to float32 rounding and its decisions are the same but for
near-ties.

The module assembles the stages: the pyramid is in :mod:`egorefine.features._pyramid`, the block
matching itself (cost maps, sub-pixel peaks, the levels, the polish, the round trip) in
:mod:`egorefine.features._matching`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from ..core import (
    ValueRangeError,
    check_choice,
    check_float,
    check_same_device,
    check_same_dtype,
    check_shape,
    use_compiled,
)
from ..core.check import _host_array
from . import _track_numba
from ._matching import (
    _SLOT_STEP,
    _extract_patches,
    _first_true,
    _forward_match,
    _lk_refine,
    _match_level,
    _put,
    _round_trip,
    _take,
)
from ._matching import _box_maps as _box_maps  # noqa: F401 - kept importable here, where the tests reach it
from ._pyramid import _given_pyramid, build_pyramid

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

    Example:
        >>> img = torch.rand(1, 1, 64, 64)
        >>> out = track(img, img, torch.tensor([[[32.0, 32.0]]]), torch.ones(1, 1))
        >>> out.keypoints.shape, out.weights.shape, out.score.shape, out.fb_error.shape
        (torch.Size([1, 1, 2]), torch.Size([1, 1]), torch.Size([1, 1]), torch.Size([1, 1]))
    """

    keypoints: torch.Tensor
    weights: torch.Tensor
    score: torch.Tensor
    fb_error: torch.Tensor


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
    names = ["prev", "next", "keypoints", "weights", "predicted"]
    arrays = [None if t is None else _host_array(t) for t in (prev, next, keypoints, weights, predicted)]
    if all(a is not None for a in arrays[:4]) and (predicted is None or arrays[4] is not None):
        # CPU: numpy's sums and maxima on the tensors' memory, a fraction of the torch ops' launch cost
        for name, a in zip(names, arrays, strict=True):
            if a is not None and a.size and not np.isfinite(a.sum() if name in ("prev", "next") else np.abs(a).max()):
                raise ValueRangeError(f"{name}: contains NaN or Inf")
        return int((arrays[3] > 0).sum(axis=1).max()) if weights.numel() > 0 else 0
    # Half-precision images are summed in float32: their sum could overflow their own type.
    wide = torch.float32 if prev.element_size() < 4 else prev.dtype
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
        patch_size: odd side of the square template in px; default 9, large enough for a distinctive ZNCC
            and small enough to stay on one surface.
        search_radius: search radius on the coarsest level (px of that level); default 6, which with the
            default levels reaches about 30 px on level 0.
        refine_radius: search radius on the finer levels; default 2, covering the coarser level's sub-pixel
            error after doubling with room to spare.
        levels: pyramid levels (1 = no pyramid); default 3.
        cost: ``"zncc"`` (default), ``"ssd"`` or ``"sad"`` (slower: no convolution form).
        fb_check: run the forward-backward consistency check (default: wrong matches are what biases the
            motion solve).
        fb_threshold: largest round-trip error in px; default 1.0, a right match comes back to within a
            fraction of a pixel.
        min_score: smallest ZNCC accepted (``cost="zncc"`` only), or None; default 0.7, a patch that still
            looks like its template under noise and small viewpoint change.
        min_texture: smallest standard deviation of the template (intensity units); default 0.01, about
            2.5 grey levels of an 8-bit image: a flatter patch gives no stable match.
        soft: differentiable soft-argmax last step (default off: the hard step is what inference wants).
        temperature: softmax temperature of the soft step (cost units); default 0.02.
        lk_iters: Lucas-Kanade polish iterations on level 0 (0: the parabola's estimate as is); default 1,
            the first step removes most of the parabola's bias.
        predicted_radius: with ``predicted``, the level-0 radius of the first search around it
            (None: always the full coarse-to-fine search); default 2 px: a small window, so a right
            prediction costs one cheap level-0 search and a wrong one is sent on to the full search.
            Ignored without ``predicted``.
        fb_predicted: run the forward-backward check also on the features found by that search
            around the prediction; False lets the prediction's agreement stand in for the check
            there (cheaper; the check then runs only on the features the full search found).
        fb_levels: pyramid levels of the way back for the features found by the full search
            (None: ``levels``, the forward search's reach; at most ``levels``): their back match
            searches ``search_radius`` around the keypoint on level ``fb_levels - 1``, then
            ``refine_radius`` on each finer level. Fewer levels cost less (a search per level)
            and reject fewer wrong matches (see the module notes); 1 is one level-0 match of radius
            ``search_radius``.
        prev_pyramid, next_pyramid: optional ``build_pyramid(prev, L)`` / ``build_pyramid(next, L)``
            with ``L >= levels`` (e.g. kept from the call that tracked into ``prev``): saves
            building them. Their level 0 is used instead of ``prev`` / ``next``, which then only
            give the shapes (the NaN check looks at the pyramids); the caller keeps them consistent.

    Returns:
        :class:`TrackOutput` with keypoints ``(B, N, 2)``, weights, score and fb_error ``(B, N)``.

    Raises:
        ShapeError: shapes of images, keypoints, weights, predicted or a given pyramid disagree.
        ValueRangeError: NaN/Inf in the inputs, a bad setting or a pyramid with too few levels.

    Example:
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


class Tracker(torch.nn.Module):
    """Module form of :func:`track`: stores the settings; ``forward`` calls the function.

    Args:
        patch_size, search_radius, refine_radius, levels, cost, fb_check, fb_threshold: as in :func:`track`.
        min_score, min_texture, soft, temperature, lk_iters, predicted_radius, fb_predicted, fb_levels: as in
            :func:`track`, with its defaults; all settings are checked here, at construction.

    ``forward(prev, next, keypoints, weights, predicted=None, prev_pyramid=None, next_pyramid=None) -> TrackOutput``,
    shapes as in :func:`track`.

    Example:
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
