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
