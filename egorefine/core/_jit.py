"""Optional numba compilation for the CPU inference paths (egorefine.stereo._sgm_numba,
egorefine.refine._splat_numba, egorefine.refine._predict_numba and the other ``_*_numba`` modules).

numba is a dependency, but the package stays importable without it: ``AVAILABLE`` is then False
and callers take their torch path (which is also the reference for GPU tensors and autograd).
"""

from __future__ import annotations

import contextlib
import itertools
import os
import sys
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

__all__ = ["AVAILABLE", "MIN_SPLIT_PIXELS", "VECTOR_OPTIONS", "Workers", "bands", "frame_bands", "jit", "numba",
           "SHARES_PER_THREAD", "split"]

try:
    import numba
except ImportError:  # pragma: no cover - exercised by the fallback tests through the flags
    numba = None

AVAILABLE = numba is not None


def jit(fn=None, inline: str = "never", fastmath: bool | set[str] = False, error_model: str = "python",
        noalias: bool = False):
    """``numba.njit(cache=True, nogil=True)``, by default without fast-math (the kernels repeat the torch path's
    float32 operations; ``fastmath`` takes numba's flags for a kernel whose order of additions need not follow
    it); without a writable cache location numba cannot cache, so it only compiles.

    ``error_model="numpy"`` lets a float division by zero give inf or NaN as in numpy instead of raising: the
    check numba otherwise puts in front of every division keeps a loop with one from becoming SIMD code.

    ``noalias=True`` is a promise that no memory the kernel writes through one array argument is reached
    through another (distinct rows of one array are fine; an array passed twice, as input and output, is
    not): its array pointers are then marked ``noalias`` for LLVM, which drops the run-time overlap checks it
    otherwise runs in front of every vectorised loop. Where an inner loop is short (a few dozen disparity
    candidates) and entered once per pixel, those checks cost more than the loop. A broken promise gives
    wrong results silently, so only kernels whose callers are all in view take it.

    Every kernel compiles with the loop-vectoriser settings :data:`VECTOR_OPTIONS` (one 16-lane vector per loop
    step), set for its compilation only."""
    if fn is None:
        return lambda f: jit(f, inline, fastmath, error_model, noalias)
    options = dict(nogil=True, fastmath=fastmath, inline=inline, error_model=error_model,
                   pipeline_class=_compiler(noalias))
    try:
        return numba.njit(cache=True, **options)(fn)
    except RuntimeError:  # "cannot cache function ...: no locator available"
        return numba.njit(cache=False, **options)(fn)


# LLVM loop-vectoriser settings for every kernel compiled here, ``{option: (value, LLVM's default)}``. The loops over
# disparity candidates (and other short rows) have a run-time trip count of a few dozen; left to its cost model,
# LLVM unrolls each vector loop so that one pass of its vector body takes 64 int16 lanes (two 512-bit or four 256-bit
# vectors) and runs every shorter remainder one element at a time, so that a loop over fewer than 64 candidates gets
# no SIMD code at all. One 16-lane vector per step, not unrolled, covers any multiple of 16 on AVX2 and AVX-512 alike
# (docs/decisions.md, "Vector width of the kernels").
VECTOR_OPTIONS = {"force-vector-interleave": ("1", "0"), "force-vector-width": ("16", "0")}


_DEPTH = [0]  # nesting of compilations (numba compiles one at a time, under its compiler lock)


@contextlib.contextmanager
def _vectoriser_settings():
    """:data:`VECTOR_OPTIONS` set while a kernel compiles, LLVM's defaults after (other numba code in the process
    keeps them). A forced vector width makes LLVM print a remark to the process's stderr for every loop it cannot
    vectorise; those lines are dropped, anything else written there meanwhile is passed on."""
    if _DEPTH[0]:  # a callee compiling inside its caller's compilation: the settings are in place
        yield
        return
    import llvmlite.binding as llvm

    def set_options(which: int) -> None:
        for name, values in VECTOR_OPTIONS.items():
            llvm.set_option("egorefine", f"-{name}={values[which]}")

    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no stderr to filter
        saved = None
    log = tempfile.TemporaryFile() if saved is not None else None
    _DEPTH[0] += 1
    try:
        if log is not None:
            os.dup2(log.fileno(), 2)
        set_options(0)
        yield
    finally:
        _DEPTH[0] -= 1
        set_options(1)
        if log is not None:
            os.dup2(saved, 2)
            os.close(saved)
            log.seek(0)
            kept = [line for line in log.read().splitlines(keepends=True) if not line.startswith(b"remark: ")]
            log.close()
            if kept:
                os.write(2, b"".join(kept))


_COMPILERS: dict[bool, type] = {}


def _compiler(noalias: bool) -> type:
    """numba's default compiler under :func:`_vectoriser_settings`, and with ``noalias`` its flag of that name set
    (every array argument's data pointer marked ``noalias``; numba has the flag but no ``njit`` option for it)."""
    if noalias not in _COMPILERS:
        from numba.core import compiler

        class Compiler(compiler.Compiler):
            def __init__(self, typingctx, targetctx, library, args, return_type, flags, locals):
                if noalias:
                    flags = flags.copy()
                    flags.noalias = True
                super().__init__(typingctx, targetctx, library, args, return_type, flags, locals)

            def _compile_core(self):
                with _vectoriser_settings():
                    return super()._compile_core()

        _COMPILERS[noalias] = Compiler
    return _COMPILERS[noalias]


def thread_count(threads: int | None = None) -> int:
    """The worker threads a compiled kernel uses: ``threads`` when given, else ``torch.get_num_threads()``; at
    least 1. The one rule every kernel's wrapper follows."""
    return max(1, threads or torch.get_num_threads())


_scratch = threading.local()


def scratch(name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
    """The calling thread's reusable work array ``name``: a view of a kept buffer, allocated anew only when it is
    too small or of another type (a call with a smaller shape reuses it; fresh pages of image-sized arrays on every
    call cost a sizeable share of a kernel call). Its contents are whatever the last user left. Names carry their
    module's prefix (``"sgm.cost"``), so that :func:`release_scratch` can free one module's buffers."""
    arrays = getattr(_scratch, "arrays", None)
    if arrays is None:
        arrays = _scratch.arrays = {}
    size = int(np.prod(shape))
    flat = arrays.get(name)
    if flat is None or flat.size < size or flat.dtype != dtype:
        arrays.pop(name, None)  # free the old one before allocating the new
        flat = arrays[name] = np.empty(size, dtype=dtype)
    return flat[:size].reshape(shape)


def release_scratch(prefix: str) -> None:
    """Free the calling thread's :func:`scratch` buffers whose names start with ``prefix``."""
    arrays = getattr(_scratch, "arrays", {})
    for name in [k for k in arrays if k.startswith(prefix)]:
        del arrays[name]


def bands(n: int, parts: int) -> list[tuple[int, int]]:
    """``[start, stop)`` ranges that split ``n`` rows (or columns) into at most ``parts`` nearly equal bands."""
    step = -(-n // max(1, parts))
    return [(start, min(n, start + step)) for start in range(0, n, step)]


# Shares of a kernel's work per worker thread (row bands of the splat, crack closing and the edge variance; the
# tracker's features): Workers.map deals items one at a time, so with a few shares per thread a worker that wakes
# late takes fewer of them, where with one share each the frame waits for its share (docs/decisions.md, "Shares
# per thread").
SHARES_PER_THREAD = 4


def frame_bands(n: int, threads: int) -> list[tuple[int, int]]:
    """:func:`bands` of ``n`` rows for ``threads`` workers, :data:`SHARES_PER_THREAD` per worker (one band for one
    thread: nothing to balance)."""
    return bands(n, threads * SHARES_PER_THREAD if threads > 1 else 1)


# Work below this many pixels runs as one job: a thread hand-off costs more than splitting it saves.
MIN_SPLIT_PIXELS = 1 << 16


def split(n: int, threads: int, pixels: int | None = None) -> list[tuple[int, int]]:
    """:func:`bands` of ``n`` rows (or pixels) over ``threads``, or the one band ``[(0, n)]`` where the work,
    ``pixels`` (default ``n``), is below :data:`MIN_SPLIT_PIXELS`."""
    return bands(n, threads) if (n if pixels is None else pixels) >= MIN_SPLIT_PIXELS else [(0, n)]


class Workers:
    """A pool of ``threads`` Python threads for nogil kernels (none for one thread); ``map`` is a barrier.

    Threads rather than numba's ``parallel=True``, whose threading layer can clash with torch's OpenMP. The pools
    are kept per thread count for the process's lifetime (starting threads on every call costs a sizeable share of
    a kernel call), and per process: a child forked from this one (a ``DataLoader`` worker) has none of the parent's
    threads, so it starts its own pool instead of waiting on one whose threads do not exist there.
    """

    _pools: dict[tuple[int, int], ThreadPoolExecutor] = {}
    _lock = threading.Lock()

    def __init__(self, threads: int) -> None:
        self.pool = None
        self.threads = max(1, threads)
        if threads > 1:
            key = (os.getpid(), threads)
            with Workers._lock:
                self.pool = Workers._pools.get(key)
                if self.pool is None:
                    self.pool = Workers._pools[key] = ThreadPoolExecutor(threads, thread_name_prefix="egorefine")

    def map(self, fn, items) -> list:
        """``[fn(item) for item in items]``, shared by the calling thread and the pool; returns when all are done.

        The calling thread works too, and every thread takes the next item not yet taken: a pool thread that
        wakes late (a hand-off costs tens of microseconds, more on a virtual machine whose idle core sleeps) takes
        fewer items instead of holding everyone up, and the caller never sleeps while work is left. The first
        exception is raised once every item taken has finished."""
        items = list(items)
        if self.pool is None or len(items) < 2:
            return [fn(item) for item in items]
        results = [None] * len(items)
        taken = itertools.count()  # (its next() is atomic under the GIL)

        def drain() -> None:
            k = next(taken)
            while k < len(items):
                results[k] = fn(items[k])
                k = next(taken)

        helpers = [self.pool.submit(drain) for _ in range(min(self.threads, len(items)) - 1)]
        try:
            drain()
        finally:
            for job in helpers:
                if not job.cancel():  # started (or done): wait for it; one never started has nothing to wait for
                    job.result()
        return results
