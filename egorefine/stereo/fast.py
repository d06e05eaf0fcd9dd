"""Exact integer fast path of the default matcher: SAD of the x-Sobel prefiltered images,
box aggregation, winner-takes-all with sub-pixel fit and left-right / uniqueness checks.

Used by :func:`egorefine.stereo.match_stereo` when no gradient is needed and the compiled form
(:mod:`egorefine.stereo._sad_numba`: float32 CPU tensors, same outputs) does not apply: GPU
tensors, float64, or numba missing. It is also the reference the compiled form is tested
against. The clipped x-Sobel responses are quantised to integers (``round(255 * scale * g)``,
``scale`` sub-grey-levels; for 8-bit images this is exact as in OpenCV's StereoBM) so that the
whole cost volume lives in int16: absolute differences and their box sums are exact integers, and every full-volume pass
moves half the bytes of float32 (CPU int16 kernels are vectorised twice as wide). Only the
winner's, its neighbours' and the runner-up's costs are converted to float.

Every pass is memory-bound, so the work is ordered for the cache: the image is cut into bands of
rows, and a band's volume is built a few disparity planes at a time (raw costs, vertical then
horizontal window sums on the flattened planes, all contiguous). While a plane is in cache it
updates the running minimum, the index of its first occurrence and the right view's minimum
(left-right check); it is also stored, and after the band the winner's neighbours are gathered
from the store with one ``index_select`` and the runner-up (uniqueness) is one reduction over it.
Bands run on several Python threads (torch ops release the GIL), each with one torch thread.

The disparity axis is reversed as in :mod:`egorefine.stereo.cost` (index ``j`` is disparity
``max_disparity - 1 - j``): the shifted right image is then a positive-stride view.
"""

from __future__ import annotations

import math
import threading
from concurrent.futures import ThreadPoolExecutor

import torch
import torch.nn.functional as F

from .cost import prefilter_xsobel

__all__ = ["int_scale", "match_sad_int", "INVALID_VARIANCE"]

_MAX_SCALE = 8
# int16 box sum of a candidate that is out of view (or knocked out): above any real sum
_INVALID = 32767
# the matcher's variance constants (px^2; egorefine.stereo.matching imports them from here):
# where the matcher gives no measurement, and the floor of an integer-rounded match
INVALID_VARIANCE = 1.0e4
_QUANTISATION_VARIANCE = 1.0 / 12.0
# a band's cost plane (B * rows * padded width): 2**16 int16 elements, large enough that an op's fixed
# cost is small beside its work, small enough that a plane, its raw costs and the band's running minima stay
# in a 2 MB L2 cache; a band's stored volume (planes * plane) at most 2**22 elements, 8 MB per worker (the
# sizes were timed against their neighbours: docs/decisions.md, "Sizes of the matchers' work buffers")
_BAND_ELEMENTS = 1 << 16
_VOLUME_ELEMENTS = 1 << 22
# raw costs built at once (int16 elements, B * planes * (rows + 2r) * padded width): 3-4 planes of a band at
# 640x480. Fewer, larger ops cost a little more CPU on one thread but are faster on two: op dispatch holds the
# GIL, so it does not overlap (docs/decisions.md)
_STEP_ELEMENTS = 1 << 18
# on a GPU op launches set the time, not caches: the whole image as one band (up to 4 M elements per plane),
# its whole volume (up to 128 M) and all raw cost planes at once (up to 32 M); several times faster there than
# the CPU sizes, with the same outputs (docs/decisions.md)
_GPU_ELEMENTS = (1 << 22, 1 << 27, 1 << 25)
_MIN_ROWS = 8  # at least this many output rows per band (the 2r halo rows of raw costs are computed twice)


def int_scale(block_size: int, cap: float) -> int:
    """Largest sub-grey-level scale (<= 8) whose box sums of ``|L - R|`` fit int16; 0 if none does."""
    for scale in range(_MAX_SCALE, 0, -1):
        if block_size * block_size * 2 * round(255.0 * scale * cap) < _INVALID:
            return scale
    return 0


def _quantise(grey: torch.Tensor, cap: float, scale: int, pad: tuple[int, int, int, int]
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """Clipped x-Sobel ``g`` and, padded (replicate), as non-negative int16 ``round(255 * scale * (g + cap))``."""
    g = prefilter_xsobel(grey, cap)
    c = round(255.0 * scale * cap)
    q = (F.pad(g, pad, mode="replicate") * (255.0 * scale)).round_().clamp_(-c, c).add_(c)
    return g, q.to(torch.int16).contiguous()


def match_sad_int(left: torch.Tensor, right: torch.Tensor, max_d: int, min_d: int, block: int, cap: float,
                  scale: int, opts: dict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Disparity, validity and variance of the box-aggregated SAD matcher, computed in integers.

    Same decisions and formulas as ``egorefine.stereo.matching._select`` on the float volume
    (up to its float rounding; a right-view tie within ``lr_threshold`` of the left winner passes
    the left-right check here).

    Bands of rows, each built a few disparity planes at a time (see the module docstring); the
    output does not depend on the band size or the number of threads.

    Args:
        left, right: ``(B, 1, H, W)`` grey float images (no gradient needed).
        max_d, min_d, block, cap: search range, odd window size, prefilter clip level.
        scale: quantisation scale from :func:`int_scale` (>= 1).
        opts: the matcher's settings (``subpixel``, ``subpixel_fit``, ``lr_check``, ``lr_threshold``,
            ``uniqueness_ratio``, ``texture_threshold``, ``cost_floor``).

    Returns:
        ``(disparity, valid, variance)`` each ``(B, 1, H, W)`` (0 and ``INVALID_VARIANCE`` where invalid).
    """
    lr_check, lr_threshold, uniqueness_ratio = opts["lr_check"], opts["lr_threshold"], opts["uniqueness_ratio"]
    b, _, h, w = left.shape
    r = block // 2
    num = max_d - min_d
    dev = left.device
    # the left-right check reads the stored costs of disparities d +- guard at columns x -+ guard:
    # guard planes and columns of _INVALID around the real ones (one plane at least: the sub-pixel
    # neighbours of the range's end planes read a guard plane)
    guard = min(lr_threshold, num - 1) if lr_check else 0
    gp = max(1, guard)
    extra = max(0, guard - r)  # padding columns beyond the window's, so that a row holds the guard columns
    pad = r + extra
    s = w + 2 * pad  # row stride of every plane buffer (the raw costs' padded width)
    shift = guard - extra  # a plane's box sum at flat position i lands at i + shift in the store
    pads = ((pad, pad, r, r), (pad + max_d, pad, r, r))  # the right image: max_d more columns on the left
    planes = num + 2 * gp
    threads = torch.get_num_threads()
    band_elements, volume_elements, step_elements = (
        (_BAND_ELEMENTS, _VOLUME_ELEMENTS, _STEP_ELEMENTS) if dev.type == "cpu" else _GPU_ELEMENTS)
    rows = max(_MIN_ROWS, min(band_elements // max(1, b * s), volume_elements // max(1, b * planes * s)))
    bands = -(-h // rows)
    workers = min(threads, bands) if dev.type == "cpu" else 1
    if workers > 1:
        bands = -(-bands // workers) * workers  # as many bands per worker
    rows = -(-h // bands)
    # disparity planes whose raw costs and window sums are built at once: fewer, larger ops
    step = max(1, min(num, step_elements // max(1, b * (rows + 2 * r) * s)))
    half = r  # pairs of columns per window beside its first column: box_k[x] = x[x] + sum_i p[x + 1 + 2 i]
    x_idx = torch.arange(w, device=dev).view(1, 1, 1, w)
    # flat buffer offsets: volume (B, planes, rows, s), then right view minima (B, rows, max_d + w)
    s_p = rows * s
    s_b = planes * s_p
    vol_size = b * s_b
    y_idx = torch.arange(rows, device=dev).view(1, rows, 1)
    b_idx = torch.arange(b, device=dev).view(b, 1, 1)
    at_winner = b_idx * s_b + gp * s_p + y_idx * s + guard + x_idx.view(1, 1, w)  # plane j = 0 at x
    # flat indices per pixel for the winner j: plane j at x (the winner), planes j -+ 1 at x (sub-pixel fit;
    # the uniqueness check knocks these three out), plane j + dj at column x - dj (left-right check), then
    # the right view's minimum at x - d = x - (max_d - 1 - j); all but the first are gathered
    parts = [at_winner, at_winner - s_p, at_winner + s_p]
    parts += [at_winner + dj * (s_p - 1) for dj in range(-guard, guard + 1) if dj]
    n_vol = len(parts)
    if lr_check:
        parts.append(vol_size + b_idx * (rows * (max_d + w)) + y_idx * (max_d + w) + x_idx.view(1, 1, w) + 1)
    # (int32 index arithmetic is half the bytes; int64 only for a buffer beyond its range)
    index_dtype = torch.int32 if vol_size + b * rows * (max_d + w) < 2**31 else torch.int64
    base = torch.stack(parts, 1).to(index_dtype)  # (B, K, rows, W)
    j_values = torch.arange(num, dtype=torch.int16, device=dev).unbind(0)  # 0-d tensors: cheaper to pass than ints

    dtype = left.dtype
    unit = 1.0 / (255.0 * scale)
    area = float(block * block)
    disparity = torch.empty((b, 1, h, w), dtype=dtype, device=dev)
    variance = torch.empty_like(disparity)
    valid = torch.empty((b, 1, h, w), dtype=torch.bool, device=dev)
    # texture check: the window sum of the quantised |x-Sobel| against the threshold on the window mean
    c_level = round(255.0 * scale * cap)
    # sum >= threshold, the threshold rounded to float32 as in the float comparison, then up to an integer
    t_need = float(torch.tensor(opts["texture_threshold"] * area * 255.0 * scale, dtype=torch.float32))
    t_need = min(max(math.ceil(t_need), -_INVALID), _INVALID)

    def run(next_band) -> None:
        """Match the bands handed out by ``next_band`` (None when done) with this call's own buffers."""
        # raw costs and their window sums of `step` disparity planes at a time
        raw = torch.empty((b, step, rows + 2 * r, s), dtype=torch.int16, device=dev)
        vert = torch.empty((b, step, rows * s), dtype=torch.int16, device=dev)
        pairs = torch.empty((b, step, rows * s), dtype=torch.int16, device=dev)
        # one flat buffer: the band's volume, then the right view's minima with max_d columns of left padding
        # (read at x - d < 0 by pixels that are invalid anyway)
        buf = torch.full((vol_size + b * rows * (max_d + w),), _INVALID, dtype=torch.int16, device=dev)
        vol = buf[:vol_size].view(b, planes, rows, s)
        flat = vol.view(b, planes, rows * s)
        right_min_all = buf[vol_size:].view(b, rows, max_d + w)[..., max_d:]
        small = torch.empty((3, b, rows, w), dtype=torch.int16, device=dev)
        index = torch.empty((b * len(parts) * rows * w,), dtype=index_dtype, device=dev)
        j32 = torch.empty((b, 2, rows, w), dtype=index_dtype, device=dev)
        t_sum = torch.empty((b, rows * s), dtype=torch.int16, device=dev)

        cache: dict[int, tuple] = {}

        def boxes(n: int, m: int) -> tuple:
            """Views of the raw / window sum buffers for ``m`` planes of a band of ``n`` rows."""
            size = n * s
            length = size - 2 * r  # box sums of a flat plane (the last 2r positions have no full window)
            raw_m, vert_m, pairs_m = raw[:, :m, : n + 2 * r], vert[:, :m, :size], pairs[:, :m, : size - 1]
            return (raw_m, vert_m.view(b, m, n, s), vert_m[..., :-1], vert_m[..., 1:], vert_m[..., :length], pairs_m,
                    raw_m.as_strided((b, m, n, block, s), (raw.stride(0), raw.stride(1), s, s, 1)),
                    pairs_m.as_strided((b, m, half, length), (pairs.stride(0), pairs.stride(1), 2, 1), 1))

        def box_sums(left_: torch.Tensor, right_: torch.Tensor | int, views_: tuple, out: torch.Tensor) -> None:
            """``out`` (B, m, flat length) = window sums of ``|left_ - right_|``: rows, then pairs of flat columns."""
            raw_m, vert4, vert_lo, vert_hi, vert_head, pairs_m, rows_view, col_windows = views_
            torch.sub(left_, right_, out=raw_m).abs_()
            torch.sum(rows_view, dim=3, dtype=torch.int16, out=vert4)
            if half:
                torch.add(vert_lo, vert_hi, out=pairs_m)
                torch.sum(col_windows, dim=2, dtype=torch.int16, out=out)
                out.add_(vert_head)
            else:
                out.copy_(vert_head)

        def views(n: int) -> tuple:
            """Views of the buffers for a band of ``n`` rows, made once: a view costs as much Python time as an op."""
            if n not in cache:
                size = n * s
                length = size - 2 * r
                running = (*small[..., :n, :].unbind(0), right_min_all[:, :n])  # best, its index, mask, right min
                right_min = running[3]
                costs = vol[:, gp : gp + num, :n, guard : guard + w].unbind(1)
                planes_ = [(cost, cost[..., :d] if d > 0 else None,
                            (right_min[..., : w - d], cost[..., d:]) if lr_check and d < w else None, jt)
                           for cost, d, jt in zip(costs, range(max_d - 1, min_d - 1, -1), j_values, strict=True)]
                j1 = [min(num, j0 + step) for j0 in range(0, num, step)]
                steps_ = [(boxes(n, j1_ - j0), flat[:, gp + j0 : gp + j1_, shift : shift + length], planes_[j0:j1_])
                          for j0, j1_ in zip(range(0, num, step), j1, strict=True)]
                t_sum_n = t_sum[:, :size]
                texture = (boxes(n, 1), t_sum_n[:, :length].unsqueeze(1),
                           t_sum_n.view(b, 1, n, s)[..., extra : extra + w])
                cache[n] = (steps_, running, index[: b * len(parts) * n * w].view(b, -1, n, w), j32[:, :, :n].unbind(1),
                            texture)
            return cache[n]

        while (y0 := next_band()) is not None:
            y1 = min(h, y0 + rows)
            n = y1 - y0
            steps_, running, index_n, (j_int, j_step), (t_views, t_flat, texture) = views(n)
            best, jbest, mask, right_min = running
            best.fill_(_INVALID)
            jbest.zero_()
            right_min.fill_(_INVALID)
            lv = lq[:, :, y0 : y1 + 2 * r]
            # the right image shifted by each disparity (plane j: d = max_d - 1 - j), as views (B, step, rows, s)
            shifted = rq[:, 0, y0 : y1 + 2 * r].unfold(2, s, 1)[:, :, 1 : 1 + num].permute(0, 2, 1, 3).split(step, 1)
            for rv, (views_, dst, planes_m) in zip(shifted, steps_, strict=True):
                # raw costs |L - R_d| of `step` planes and their window sums, stored as planes j..
                box_sums(lv, rv, views_, dst)
                for cost, out_of_view, lr_pair, jt in planes_m:
                    if out_of_view is not None:
                        out_of_view.fill_(_INVALID)  # x - d < 0: out of the right view
                    # running minimum and the index of its first occurrence (lowest j: largest disparity on ties)
                    torch.lt(cost, best, out=mask)
                    torch.minimum(best, cost, out=best)
                    torch.maximum(jbest, torch.mul(mask, jt, out=mask), out=jbest)
                    if lr_pair is not None:
                        # the right view's minimum at xr over d: cost_right(xr, d) = cost_left(xr + d, d)
                        torch.minimum(*lr_pair, out=lr_pair[0])
            if guard:
                vol[:, gp : gp + num, :n, :guard].fill_(_INVALID)
                vol[:, gp : gp + num, :n, guard + w : 2 * guard + w].fill_(_INVALID)
            bst = best.unsqueeze(1)
            jb = jbest.unsqueeze(1)
            # one gather from the flat buffer: the costs around the winner and the right view's minimum at x - d
            # (int32 index arithmetic of one dtype: mixed-dtype ops take a slow path)
            j_int = j_int.unsqueeze(1).copy_(jb)
            torch.add(base[:, :n_vol, :n], torch.mul(j_int, s_p, out=j_step.unsqueeze(1)), out=index_n[:, :n_vol])
            if lr_check:
                torch.add(base[:, n_vol:, :n], j_int, out=index_n[:, n_vol:])
            vals = buf.index_select(0, index_n[:, 1:].reshape(-1)).view(b, -1, n, w)
            c_plus, c_minus = vals[:, :1], vals[:, 1:2]  # reversed: j - 1 is d + 1
            hi = torch.maximum(bst, c_plus)
            ok = hi < _INVALID  # (a guard plane reads _INVALID: j > 0)
            inner = torch.maximum(hi, c_minus) < _INVALID  # interior minimum: the sub-pixel fit is defined
            if min_d > 0:
                ok &= jb < num - 1
            if lr_check:
                # left-right check (right view from the same volume: cost_right(xr, d) = cost_left(xr + d, d)):
                # the right view's minimum at xr = x - d must be reached by a disparity within lr_threshold
                # of d, i.e. by cost_right(x - d, d + dj) = cost_left(x + dj, d + dj) for some |dj| <= guard
                near = torch.minimum(bst, vals[:, 2 : 2 + 2 * guard].amin(dim=1, keepdim=True)) if guard else bst
                ok &= near <= vals[:, -1:]
            if uniqueness_ratio > 0:
                # runner-up beyond +-1 px of the winner: knock out the winner and its neighbours, then one minimum
                buf.index_fill_(0, index_n[:, :3].reshape(-1).long(), _INVALID)
                second = vol[:, gp : gp + num, :n, guard : guard + w].amin(dim=1, keepdim=True).float()
                ok &= second > bst.float() * (1 + uniqueness_ratio)
            # texture check in integers: window sum of |x-Sobel| (quantised, replicate borders) >= the threshold,
            # the windows summed as the costs' (flat rows, then pairs of columns)
            box_sums(lv, c_level, t_views, t_flat)
            ok &= texture >= t_need
            valid[..., y0:y1, :] = ok
            _tail(jb, vals[:, :2], bst, ok, inner, max_d, unit, area, opts,
                  (disparity[..., y0:y1, :], variance[..., y0:y1, :]))

    starts = iter(range(0, h, rows))
    lock = threading.Lock()

    def next_band() -> int | None:
        with lock:
            return next(starts, None)

    if workers < 2:
        lq, rq = (_quantise(image, cap, scale, p)[1] for image, p in zip((left, right), pads, strict=True))
        run(next_band)
        return disparity, valid, variance
    # CPU with several threads: bands in parallel, each worker single-threaded and taking the next band
    # when done. Intra-op threading of the many mid-sized ops costs more in thread wake-ups than it gains
    # (slower, not faster, with 2 threads: docs/decisions.md); the ops release the GIL, so Python threads run bands
    # concurrently.
    def quantised(image: torch.Tensor, p: tuple[int, int, int, int]) -> torch.Tensor:
        torch.set_num_threads(1)
        return _quantise(image, cap, scale, p)[1]

    def worker(_: int) -> None:
        torch.set_num_threads(1)
        run(next_band)

    try:
        with ThreadPoolExecutor(workers) as pool:
            lq, rq = (f.result() for f in [pool.submit(quantised, image, p)
                                           for image, p in zip((left, right), pads, strict=True)])
            list(pool.map(worker, range(workers)))
    finally:
        torch.set_num_threads(threads)
    return disparity, valid, variance


def _tail(j: torch.Tensor, costs: torch.Tensor, best: torch.Tensor, valid: torch.Tensor, inner: torch.Tensor,
          max_d: int, unit: float, area: float, opts: dict, out: tuple[torch.Tensor, ...]) -> None:
    """Sub-pixel fit and variance of one band (the formulas of ``matching._select``), written into ``out``.

    ``costs`` ``(B, 2, n, W)``: the integer costs at the winner's d + 1 and d - 1; ``best`` at d. 0/1 float factors
    replace torch.where (where and masked_fill on bool masks are far slower than arithmetic on CPU);
    band-sized temporaries stay in cache.
    """
    disparity, variance = out
    dtype = disparity.dtype
    f = costs.to(dtype).mul_(unit)
    cp, cm, c0 = f[:, 0:1], f[:, 1:2], best.to(dtype).mul_(unit)
    inner = inner.view(torch.uint8).to(dtype)
    keep = valid.view(torch.uint8).to(dtype)
    curvature = cm - 2 * c0 + cp
    eps = torch.finfo(dtype).eps * 16 * area
    if opts["subpixel_fit"] == "parabola":
        denom = 2 * curvature
    else:  # equiangular (V-shaped) fit
        denom = 2 * (torch.maximum(cm, cp) - c0)
    torch.sub(max_d - 1, j, out=disparity)
    if opts["subpixel"]:
        disparity += ((cm - cp) / denom.clamp_min(eps)).clamp_(-0.5, 0.5).mul_(inner)
    disparity.mul_(keep)
    var = ((c0 + opts["cost_floor"] * area) / (curvature.clamp_min_(0) + eps)).square_().mul_(0.25)
    var = var.add_(_QUANTISATION_VARIANCE).clamp_max_(INVALID_VARIANCE).sub_(1).mul_(inner).add_(1)
    # INVALID_VARIANCE where invalid (0/1 factors: exact)
    torch.mul(var, keep, out=variance).add_(keep.neg_().add_(1).mul_(INVALID_VARIANCE))
