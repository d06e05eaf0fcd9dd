"""The C allocator's handling of freed memory: kept for reuse rather than handed back to the system every frame.

A frame of the refiner's loop allocates and frees several full-size maps (outputs, the matchers' work maps). With
glibc's default settings much of that memory goes back to the system as soon as it is freed (blocks above the
dynamic ``mmap`` threshold are unmapped; the top of a heap beyond the trim threshold is released), so the next
frame's maps are fresh pages and every page's first write is a page fault. On a virtual machine that costs as much
as some of the kernels that write them (docs/decisions.md, "Freed memory kept for reuse").

:func:`keep_freed_memory` pins glibc's two thresholds at the ceiling its own dynamic rule would reach (``mmap``
only for blocks of 32 MiB and more) and keeps up to 64 MiB free at a heap's top. The refiner calls it once, on its
first frame on the CPU; set ``EGOREFINE_KEEP_FREED_MEMORY=0`` to leave the allocator as it is. It is process-wide
and cannot be undone (glibc drops its dynamic thresholds once one is set), and a no-op where the C library is not
glibc (macOS, Windows, musl).
"""

from __future__ import annotations

import ctypes
import os
import platform
import threading

__all__ = ["keep_freed_memory"]

# glibc's mallopt parameters (malloc.h) and the values set
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD = 32 << 20  # glibc's own upper bound for its dynamic threshold on 64-bit systems
_TRIM_THRESHOLD = 64 << 20
_ENV = "EGOREFINE_KEEP_FREED_MEMORY"

_lock = threading.Lock()
_state: dict[str, bool] = {}


def keep_freed_memory() -> bool:
    """Have glibc keep freed memory for reuse (see the module docstring); once per process.

    Returns:
        True where the thresholds are set (by this call or an earlier one), False where they are not: not glibc,
        ``mallopt`` refused them, or ``EGOREFINE_KEEP_FREED_MEMORY`` is ``0`` (read on the first call).

    Example:
        >>> from egorefine.core.memory import keep_freed_memory
        >>> keep_freed_memory() in (True, False)
        True
    """
    with _lock:
        if "set" not in _state:
            _state["set"] = _set_thresholds()
        return _state["set"]


def _set_thresholds() -> bool:
    if os.environ.get(_ENV, "1").strip() == "0" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    # (mallopt returns 1 on success, 0 on error)
    return mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD) == 1 and mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD) == 1
