import os

import numpy as np
import pytest

from egorefine.core import _jit


@pytest.mark.skipif(not _jit.AVAILABLE, reason="numba not installed")
def test_compiles_without_a_cache_location(monkeypatch):
    # numba raises RuntimeError at decoration when no cache directory is writable: compile without caching
    real = _jit.numba.njit

    def njit(*args, cache=False, **kwargs):
        if cache:
            raise RuntimeError("cannot cache function 'f': no locator available for file 'f.py'")
        return real(*args, cache=cache, **kwargs)

    monkeypatch.setattr(_jit.numba, "njit", njit)

    def f(x):
        return x + 1

    assert _jit.jit(f)(1) == 2


def test_workers_map_in_order_and_survive_a_fork():
    # The pools are kept per process: a forked child (a DataLoader worker) must not wait on the parent's threads.
    import multiprocessing as mp

    assert _jit.Workers(2).map(lambda x: x * x, range(5)) == [0, 1, 4, 9, 16]
    assert _jit.Workers(1).map(lambda x: -x, range(3)) == [0, -1, -2]
    if "fork" not in mp.get_all_start_methods():
        pytest.skip("no fork on this platform")
    ctx = mp.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=lambda: queue.put(_jit.Workers(2).map(lambda x: x + 1, range(3))))
    child.start()
    child.join(timeout=20)
    if child.is_alive():
        child.kill()
        pytest.fail("the forked child hung on the parent's pool")
    assert queue.get(timeout=5) == [1, 2, 3]


def test_workers_map_shares_items_with_the_caller_and_is_a_barrier():
    """Every item runs once; the calling thread takes items too; a map inside a pool task does not wait on the busy
    pool (the caller drains it); an exception surfaces once every started item has finished."""
    import threading
    import time

    seen: list[tuple[int, str]] = []
    lock = threading.Lock()

    def slow(x):
        time.sleep(0.01)
        with lock:
            seen.append((x, threading.current_thread().name))
        return 10 * x

    assert _jit.Workers(2).map(slow, range(8)) == [10 * x for x in range(8)]
    assert sorted(x for x, _ in seen) == list(range(8))
    assert any(name == threading.current_thread().name for _, name in seen)  # the caller worked
    nested = _jit.Workers(2).map(lambda x: sum(_jit.Workers(2).map(lambda y: x * y, range(4))), range(4))
    assert nested == [6 * x for x in range(4)]
    finished = []

    def fails(x):
        if x == 0:
            raise ValueError("item 0")
        time.sleep(0.05)
        finished.append(x)

    with pytest.raises(ValueError, match="item 0"):
        _jit.Workers(2).map(fails, range(3))
    count = len(finished)
    time.sleep(0.2)
    assert len(finished) == count  # nothing of that map still runs


def test_frame_bands_cover_the_rows_once_with_a_few_bands_per_thread():
    from egorefine.core._jit import SHARES_PER_THREAD, frame_bands

    for n, threads in ((480, 2), (375, 2), (7, 4), (1, 2), (480, 1)):
        bands = frame_bands(n, threads)
        assert bands[0][0] == 0 and bands[-1][1] == n
        assert all(a[1] == b[0] for a, b in zip(bands[:-1], bands[1:], strict=True))  # contiguous, no overlap
        assert all(start < stop for start, stop in bands)
        assert len(bands) <= (threads * SHARES_PER_THREAD if threads > 1 else 1)
    assert len(frame_bands(480, 2)) == 2 * SHARES_PER_THREAD


def test_scratch_reuses_a_thread_buffer_and_releases_by_prefix():
    import threading

    import numpy as np

    _jit.release_scratch("test.")
    a = _jit.scratch("test.a", (4, 5), np.float32)
    a[:] = 7
    smaller = _jit.scratch("test.a", (3, 2), np.float32)
    assert smaller.shape == (3, 2) and np.shares_memory(a, smaller)  # the kept buffer, viewed
    assert not np.shares_memory(a, _jit.scratch("test.b", (4, 5), np.float32))  # another name, its own
    assert not np.shares_memory(a, _jit.scratch("test.a", (5, 5), np.float32))  # too small: allocated anew
    assert _jit.scratch("test.a", (2,), np.int16).dtype == np.int16  # another type: anew
    other = []
    worker = threading.Thread(target=lambda: other.append(_jit.scratch("test.a", (2,), np.int16)))
    worker.start(), worker.join()
    assert not np.shares_memory(other[0], _jit.scratch("test.a", (2,), np.int16))  # per thread
    kept = _jit.scratch("keep.x", (3,), np.float32)
    _jit.release_scratch("test.")
    assert not np.shares_memory(_jit.scratch("test.b", (4, 5), np.float32), a)
    assert np.shares_memory(kept, _jit.scratch("keep.x", (3,), np.float32))  # another prefix stays
    _jit.release_scratch("keep.")


def _short_loop(a, out):
    # a short loop that LLVM vectorises: int16 products and their minimum
    lo = np.int16(32767)
    for j in range(a.shape[0]):
        v = np.int16(a[j] * np.int16(3))
        out[j] = v
        lo = min(lo, v)
    return lo


@pytest.mark.skipif(not _jit.AVAILABLE, reason="numba not installed")
def test_vectoriser_settings_apply_to_our_kernels_only(capfd):
    # The forced vector width and interleave are set while one of our kernels compiles and reset after: a plain
    # numba function compiled afterwards gets the same machine code as one compiled before, and LLVM's remarks
    # about loops it could not vectorise do not reach stderr, while other output written meanwhile does.
    a = np.arange(40, dtype=np.int16)
    compiled = {}
    for name, options in (("before", {}), ("ours", {"pipeline_class": _jit._compiler(False)}), ("after", {})):
        f = compiled[name] = _jit.numba.njit(**options)(_short_loop)
        out = np.empty_like(a)
        assert f(a, out) == 0 and (out == a * 3).all()
    lines = {k: len(next(iter(f.inspect_asm().values())).splitlines()) for k, f in compiled.items()}
    assert lines["after"] == lines["before"]
    assert lines["ours"] != lines["before"]  # the settings did change our kernel's code

    with _jit._vectoriser_settings():
        os.write(2, b"remark: <unknown>:0:0: loop not vectorized\nkept line\n")
    err = capfd.readouterr().err
    assert "kept line" in err and "remark:" not in err
