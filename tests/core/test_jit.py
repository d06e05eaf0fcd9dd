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
