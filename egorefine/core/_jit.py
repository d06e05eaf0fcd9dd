"""Optional numba compilation for the CPU inference paths (egorefine.stereo._sgm_numba,
egorefine.refine._predict_numba).

numba is a dependency, but the package stays importable without it: ``AVAILABLE`` is then False
and callers take their torch path (which is also the reference for GPU tensors and autograd).
"""

from __future__ import annotations

__all__ = ["AVAILABLE", "jit", "numba"]

try:
    import numba
except ImportError:  # pragma: no cover - exercised by the fallback tests through the flags
    numba = None

AVAILABLE = numba is not None


def jit(fn=None, inline: str = "never"):
    """``numba.njit(cache=True, nogil=True)`` without fast-math (the kernels repeat the torch path's float32
    operations); without a writable cache location numba cannot cache, so it only compiles."""
    if fn is None:
        return lambda f: jit(f, inline)
    try:
        return numba.njit(cache=True, nogil=True, fastmath=False, inline=inline)(fn)
    except RuntimeError:  # "cannot cache function ...: no locator available"
        return numba.njit(cache=False, nogil=True, fastmath=False, inline=inline)(fn)
