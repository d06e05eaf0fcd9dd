"""Small-region (speckle) removal: invalidate connected patches of similar disparity that are too small.

A wrong match on weak texture or noise rarely agrees with its neighbours over a large area, while a
surface does: pixels are linked to their 4 neighbours when both are valid and their disparities differ
by at most ``max_diff`` px, and every connected region of at most ``max_size`` pixels is marked
invalid (the rule of OpenCV's ``filterSpeckles``, on float disparities).

Two paths with the same output. The torch reference (any device) propagates the smallest pixel index
along the links for ``max_size - 1`` steps: a region of at most ``max_size`` pixels spans no more steps,
so its label is then final; a region whose labels still differ across a link is larger and kept. The
CPU path (numba, float32 and float64) labels runs of linked pixels along the rows and joins them across rows in
a union-find forest (bands of rows in parallel, then the seams between bands), and writes the mask by runs.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..core import DTypeError, ValueRangeError, check_shape, use_compiled
from ..core._jit import AVAILABLE, thread_count
from ..core._jit import bands as _bands
from ..core._jit import jit as _jit
from ..core.dispatch import _is_compiling
from ._sad_numba import _run

__all__ = ["remove_speckles"]

_while_loop = getattr(torch, "while_loop", None)  # None in older torch

if AVAILABLE:

    @_jit(inline="always")
    def _root(parent, i):
        """The root of ``i`` in the union-find forest ``parent``, halving the path on the way."""
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    @_jit(inline="always")
    def _join(parent, a, b):
        """Join the trees of runs ``a`` and ``b``: the higher root points at the lower (a parent's number stays below
        its child's)."""
        ra, rb = _root(parent, a), _root(parent, b)
        if ra < rb:
            parent[rb] = ra
        elif rb < ra:
            parent[ra] = rb

    @_jit(inline="always")
    def _join_rows(d, up, y, max_diff, start, stop, parent, first, end):
        """Join the runs of row ``y`` with those of row ``y - 1`` they overlap: each overlap of two runs not yet in one
        tree is read up to its first linked pixel pair (``d``, ``up``: the two rows' disparities)."""
        i, i_end = first[y - 1], end[y - 1]
        k, k_end = first[y], end[y]
        while i < i_end and k < k_end:
            lo, hi = max(start[i], start[k]), min(stop[i], stop[k])
            if lo < hi and _root(parent, i) != _root(parent, k):
                for x in range(lo, hi):
                    if abs(d[x] - up[x]) <= max_diff:
                        _join(parent, i, k)
                        break
            if stop[i] <= stop[k]:
                i += 1
            else:
                k += 1

    @_jit
    def _label_rows(disp, valid, y0, y1, max_diff, start, stop, parent, size, first, end):
        """The runs of rows ``[y0, y1)`` of one map ``(H, W)`` and their joins within those rows.

        Along a row, linked pixels form runs, each ``[start, stop)`` with ``size`` pixels; row ``y``'s are numbered
        ``first[y] .. end[y]``, in scan order from ``y0 * W`` (a row has at most ``W``). Bands of rows label in
        parallel: each touches its rows' runs only.
        """
        W = disp.shape[1]
        n = y0 * W
        for y in range(y0, y1):
            d, v = disp[y], valid[y]
            first[y] = n
            x = 0
            while x < W:
                if not v[x]:
                    x += 1
                    continue
                x0 = x
                x += 1
                while x < W and v[x] and abs(d[x] - d[x - 1]) <= max_diff:
                    x += 1
                start[n], stop[n], parent[n], size[n] = x0, x, n, x - x0
                n += 1
            end[y] = n
            if y > y0:
                _join_rows(d, disp[y - 1], y, max_diff, start, stop, parent, first, end)

    @_jit
    def _settle_regions(disp, seams, max_diff, start, stop, parent, size, first, end):
        """Join the runs across the rows ``seams`` (each band's first row) with the row above, then point every run
        at its root and gather the region sizes there, in one pass in run order (every parent, numbered below its
        child, is settled first)."""
        H = disp.shape[0]
        for y in seams:
            _join_rows(disp[y], disp[y - 1], y, max_diff, start, stop, parent, first, end)
        for y in range(H):
            for i in range(first[y], end[y]):
                p = parent[i]
                if p != i:
                    p = parent[p]
                    parent[i] = p
                    size[p] += size[i]

    @_jit
    def _region_mask(max_size, y0, y1, start, stop, parent, size, first, end, out, disparity, variance, fill):
        """Rows ``[y0, y1)`` of ``out`` ``(H, W)``: the pixels of runs in regions of more than ``max_size`` pixels
        (the runs settled: each points at its root), each run written as a span. With ``disparity`` and
        ``variance`` ``(H, W)`` (else ``(0, 0)``), also clears them where ``out`` is False (0 and ``fill``)."""
        W = out.shape[1]
        clear = disparity.shape[0] > 0
        for y in range(y0, y1):
            o = out[y]
            for x in range(W):
                o[x] = False
            for i in range(first[y], end[y]):
                keep = size[parent[i]] > max_size
                for x in range(start[i], stop[i]):
                    o[x] = keep
            if clear:
                d, var = disparity[y], variance[y]
                for x in range(W):
                    keep = o[x]
                    d[x] = d[x] if keep else 0.0
                    var[x] = var[x] if keep else fill

    @_jit
    def _clear_invalid(valid, disparity, variance, fill):
        """In place: ``disparity`` 0 and ``variance`` ``fill`` where ``valid`` is False (flat arrays of one length);
        one vectorised pass, where numpy's masked assignment takes several."""
        for i in range(valid.shape[0]):
            keep = valid[i]
            disparity[i] = disparity[i] if keep else 0.0
            variance[i] = variance[i] if keep else fill


def clear_invalid_(valid: torch.Tensor, disparity: torch.Tensor, variance: torch.Tensor, fill: float) -> None:
    """Set ``disparity`` to 0 and ``variance`` to ``fill`` in place where ``valid`` is False, compiled (the CPU
    inference path of :func:`egorefine.stereo.match_stereo` after its speckle filter: no torch pass over the maps).

    Args:
        valid: ``(B, 1, H, W)`` bool CPU tensor.
        disparity, variance: ``(B, 1, H, W)`` contiguous float32 CPU tensors, written in place.
        fill: the variance of an invalid pixel.

    >>> d, var = torch.ones(1, 1, 1, 3), torch.ones(1, 1, 1, 3)
    >>> clear_invalid_(torch.tensor([[[[True, False, True]]]]), d, var, 9.0)
    >>> d.flatten().tolist(), var.flatten().tolist()
    ([1.0, 0.0, 1.0], [1.0, 9.0, 1.0])
    """
    if AVAILABLE and all(t.is_contiguous() for t in (valid, disparity, variance)):
        _clear_invalid(valid.numpy().reshape(-1), disparity.numpy().reshape(-1), variance.numpy().reshape(-1),
                       np.float32(fill))
    else:
        disparity.masked_fill_(~valid, 0.0)
        variance.masked_fill_(~valid, fill)

def _remove_speckles_compiled(disp: torch.Tensor, valid: torch.Tensor, max_size: int, max_diff: float,
                              threads: int | None = None, clear: tuple[torch.Tensor, float] | None = None
                              ) -> np.ndarray:
    """The CPU path of :func:`remove_speckles`: ``(B, H, W)`` bool. Bands of rows label their runs on
    ``threads`` threads (None: ``torch.get_num_threads()``), then each map's seams are joined and its region sizes
    gathered (one thread), and the bands write the mask. ``clear``: ``(variance, fill)``, with ``disp`` contiguous:
    the removed pixels of ``disp`` and ``variance`` ``(B, 1, H, W)`` are also set to 0 and ``fill``, in place, in
    the same pass (:func:`clear_invalid_` after it)."""
    d = np.ascontiguousarray(disp[:, 0].numpy())
    v = np.ascontiguousarray(valid[:, 0].numpy())
    b, h, w = d.shape
    diff = np.array(max_diff, dtype=d.dtype)[()]
    threads = thread_count(threads)
    runs = [tuple(np.empty(h * w, np.int32) for _ in range(4)) + (np.empty(h, np.int64), np.empty(h, np.int64))
            for _ in range(b)]
    bands = _bands(h, threads)
    jobs = [(i, band) for i in range(b) for band in bands]
    _run(threads, lambda job: _label_rows(d[job[0]], v[job[0]], *job[1], diff, *runs[job[0]]), jobs)
    out = np.empty((b, h, w), np.bool_)
    seams = np.array([y0 for y0, _ in bands[1:]], np.int64)
    for i in range(b):
        _settle_regions(d[i], seams, diff, *runs[i])
    # the maps cleared with the mask: (disparity, variance) per item, or empty ones (nothing cleared)
    if clear is None:
        none = np.empty((0, 0), d.dtype)
        cleared, fill = [(none, none)] * b, d.dtype.type(0)
    else:
        var = clear[0][:, 0].numpy()
        cleared, fill = [(d[i], var[i]) for i in range(b)], var.dtype.type(clear[1])
    _run(threads, lambda job: _region_mask(max_size, *job[1], *runs[job[0]], out[job[0]], *cleared[job[0]], fill),
         jobs)
    return out


def _links(disp: torch.Tensor, valid: torch.Tensor, max_diff: float, dim: int) -> torch.Tensor:
    """Links between neighbours along ``dim`` (-1: x, -2: y): both valid, disparities within ``max_diff``."""
    n = disp.shape[dim]
    a, b = disp.narrow(dim, 0, n - 1), disp.narrow(dim, 1, n - 1)
    return valid.narrow(dim, 0, n - 1) & valid.narrow(dim, 1, n - 1) & ((b - a).abs() <= max_diff)


def _ends(pairs: torch.Tensor, dim: int) -> torch.Tensor:
    """How many marked neighbour pairs along ``dim`` each pixel is in (``pairs``: one shorter there), int64.

    Counts, not a bool mask: a bool padded or or-ed into overlapping ``narrow`` views of a bool tensor (the first
    form) made torch.compile's inductor backend emit C++ that does not compile (a masked bool load typed two
    ways). Only whether a region's sum is 0 matters, which the counts keep.
    """
    first, second = ((0, 1), (1, 0)) if dim == -1 else ((0, 0, 0, 1), (0, 0, 1, 0))  # F.pad: last dim first
    pairs = pairs.long()
    return F.pad(pairs, first) + F.pad(pairs, second)


def _propagate_(label: torch.Tensor, links: dict[int, torch.Tensor], none: int) -> torch.Tensor:
    """One step, in place: each linked pair along x, then along y, both get the smaller label (``none``: no link)."""
    for dim, link in links.items():
        n = label.shape[dim]
        lo, hi = label.narrow(dim, 0, n - 1), label.narrow(dim, 1, n - 1)
        # the smaller label of each linked pair, given to both (each minimum is a new tensor before its copy)
        best = torch.where(link, torch.minimum(lo, hi), none)
        lo.copy_(torch.minimum(lo, best))
        hi.copy_(torch.minimum(hi, best))
    return label


def _settle(label: torch.Tensor, links: dict[int, torch.Tensor], steps: int, none: int) -> torch.Tensor:
    """``label`` after ``steps`` propagation steps (in place in eager mode).

    Eager: a Python loop. Under ``torch.compile``, ``torch.while_loop`` with one step as its body: dynamo unrolls
    a Python loop, and ``steps`` is the speckle size (hundreds), so the unrolled graph took inductor minutes of
    code generation, growing with the size and per input shape; the loop's graph holds one step whatever the
    count. The body steps a copy (a loop body must not change its inputs). Without ``torch.while_loop`` (older
    torch) compiling unrolls the loop.
    """
    if _is_compiling() and _while_loop is not None:
        # the count as a carried tensor: as a Python int it turns symbolic once dynamo recompiles for another
        # max_size, and inductor's loop code lost that symbol (a NameError in its wrapper)
        _, label = _while_loop(lambda n, _: n > 0, lambda n, lab: (n - 1, _propagate_(lab.clone(), links, none)),
                               (torch.full((), steps, dtype=torch.int64, device=label.device), label))
        return label
    for _ in range(steps):
        _propagate_(label, links, none)
    return label


def _remove_speckles_torch(disp: torch.Tensor, valid: torch.Tensor, max_size: int, max_diff: float) -> torch.Tensor:
    b, _, h, w = disp.shape
    total = b * h * w
    # int32 labels where they fit: the propagation below reads and writes them max_size times
    dtype = torch.int32 if total < 2**31 - 1 else torch.int64
    index = torch.arange(total, device=disp.device, dtype=dtype).view(b, 1, h, w)
    none = torch.full_like(index, total)  # the label of invalid pixels (and of "no link")
    label = torch.where(valid, index, none)
    links = {dim: _links(disp, valid, max_diff, dim) for dim in (-1, -2)}
    # a region of s <= max_size pixels spans at most s - 1 links
    label = _settle(label, links, max_size - 1, total)
    # a region whose labels still differ across one of its links has not settled: it is large
    unsettled = torch.zeros_like(label, dtype=torch.long)  # per pixel: its links across which labels differ
    for dim, link in links.items():
        n = label.shape[dim]
        unsettled = unsettled + _ends(link & (label.narrow(dim, 0, n - 1) != label.narrow(dim, 1, n - 1)), dim)
    flat = label.flatten().long()
    size = torch.zeros(total + 1, dtype=torch.long, device=disp.device).index_add_(0, flat, valid.flatten().long())
    open_ = torch.zeros(total + 1, dtype=torch.long, device=disp.device).index_add_(0, flat, unsettled.flatten())
    small = (size[flat] <= max_size) & (open_[flat] == 0)
    return valid & ~small.view(b, 1, h, w)


def remove_speckles(disparity: torch.Tensor, valid: torch.Tensor, max_size: int = 100,
                    max_diff: float = 1.0) -> torch.Tensor:
    """Validity without the small regions of similar disparity (speckles).

    Args:
        disparity: ``(B, 1, H, W)`` disparity in px (values where ``valid`` is False are ignored).
        valid: ``(B, 1, H, W)`` bool, the pixels that have a disparity.
        max_size: regions of at most this many pixels are removed (OpenCV's ``speckleWindowSize``; 0: none).
        max_diff: neighbours whose disparities differ by at most this many px belong to one region
            (OpenCV's ``speckleRange``, there in 1/16 px for SGBM).

    Returns:
        ``(B, 1, H, W)`` bool: ``valid`` with the pixels of small regions set False.

    Raises:
        ShapeError, DTypeError, ValueRangeError: bad input, naming the argument.

    >>> d = torch.full((1, 1, 8, 8), 5.0); d[..., 2:4, 2:4] = 20.0  # a 4-pixel island
    >>> int(remove_speckles(d, torch.ones(1, 1, 8, 8, dtype=torch.bool), max_size=10).sum())
    60
    """
    _check_inputs(disparity, valid, max_size, max_diff)
    if max_size == 0:
        return valid
    disp = disparity.detach()  # the filter reads values only: a gradient elsewhere does not matter
    if use_compiled(disp, valid, dtype=(torch.float32, torch.float64)):
        return torch.from_numpy(_remove_speckles_compiled(disp, valid, max_size, max_diff))[:, None]
    return _remove_speckles_torch(disp, valid, max_size, max_diff)


def _check_inputs(disparity: torch.Tensor, valid: torch.Tensor, max_size: int, max_diff: float) -> None:
    """:func:`remove_speckles`'s checks."""
    dims = check_shape(disparity, ["B", "1", "H", "W"], "disparity")
    check_shape(valid, ["B", "1", "H", "W"], "valid", dims)
    if valid.dtype != torch.bool:
        raise DTypeError(f"valid: expected a bool tensor, got {valid.dtype}")
    if isinstance(max_size, bool) or not isinstance(max_size, int) or max_size < 0:
        raise ValueRangeError(f"max_size: expected an int >= 0, got {max_size!r}")
    if not max_diff >= 0:
        raise ValueRangeError(f"max_diff: expected >= 0, got {max_diff}")


def remove_speckles_cleared_(disparity: torch.Tensor, valid: torch.Tensor, variance: torch.Tensor, max_size: int,
                             max_diff: float, fill: float) -> torch.Tensor | None:
    """:func:`remove_speckles` that also sets ``disparity`` to 0 and ``variance`` to ``fill`` in place where the
    result is False, in the compiled pass that writes the mask (a matcher's fresh outputs: no pass of its own).

    Args:
        disparity, variance: ``(B, 1, H, W)`` contiguous float32 CPU maps, written in place.
        valid, max_size, max_diff: as :func:`remove_speckles`.
        fill: the variance of a pixel that is not valid.

    Returns:
        the new validity ``(B, 1, H, W)``; None (nothing done) where the compiled path does not apply (not
        contiguous float32 CPU maps of one dtype, a gradient needed, ``max_size`` 0): the caller then runs
        :func:`remove_speckles` and clears the maps itself.

    >>> d, var = torch.full((1, 1, 4, 4), 5.0), torch.ones(1, 1, 4, 4)
    >>> d[..., 1, 1] = 20.0  # a 1-pixel island
    >>> valid = remove_speckles_cleared_(d, torch.ones(1, 1, 4, 4, dtype=torch.bool), var, 2, 1.0, 9.0)
    >>> bool(valid[0, 0, 1, 1]), float(d[0, 0, 1, 1]), float(var[0, 0, 1, 1]), int(valid.sum())
    (False, 0.0, 9.0, 15)
    """
    _check_inputs(disparity, valid, max_size, max_diff)
    if max_size == 0 or not (disparity.is_contiguous() and variance.is_contiguous()) or variance.shape != \
            disparity.shape or not use_compiled(disparity, variance, valid, dtype=(torch.float32,)):
        return None
    return torch.from_numpy(_remove_speckles_compiled(disparity, valid, max_size, max_diff,
                                                      clear=(variance, fill)))[:, None]
