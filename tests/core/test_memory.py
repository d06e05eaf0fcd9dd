"""egorefine.core.memory: freed memory kept for reuse (glibc)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

from egorefine.core import memory
from egorefine.core.memory import keep_freed_memory

# A child process that allocates eight 1.2 MB maps (a frame's), writes every page and frees them, twenty times, and
# prints the page faults of those cycles (after one cycle to warm up); argv[1] "1" calls keep_freed_memory first.
_CHILD = """
import importlib.util, resource, sys
import numpy as np
spec = importlib.util.spec_from_file_location("memory", sys.argv[2])  # the module alone: no torch to import
memory = importlib.util.module_from_spec(spec)
spec.loader.exec_module(memory)
kept = memory.keep_freed_memory() if sys.argv[1] == "1" else None
def cycle():
    maps = [np.empty((480, 640), np.float32) for _ in range(8)]
    for a in maps:
        a.fill(1.0)
cycle()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    cycle()
print(kept, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _clean_env(extra: dict | None) -> dict:
    """This process's environment without settings of glibc's allocator (a machine's own tuning would make the
    untouched child reuse its maps too), plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
    return {**env, **(extra or {})}


def _child(tune: bool, env: dict | None = None) -> tuple[str, int]:
    out = subprocess.run([sys.executable, "-c", _CHILD, "1" if tune else "0", memory.__file__], capture_output=True,
                         text=True, check=True, env=_clean_env(env)).stdout.split()
    return out[0], int(out[1])


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_freed_maps_are_reused_instead_of_faulted_in():
    # untouched, glibc hands the freed maps back to the system (the heap's top beyond its trim threshold): each
    # cycle faults in their 20 x 300 pages again
    pages = 20 * 8 * 480 * 640 * 4 // 4096
    _, faults = _child(tune=False)
    assert faults > pages // 2
    kept, faults = _child(tune=True)
    assert kept == "True" and faults < pages // 20  # the maps reuse the freed memory
    kept, faults = _child(tune=True, env={"EGOREFINE_KEEP_FREED_MEMORY": "0"})
    assert kept == "False" and faults > pages // 2


def test_keep_freed_memory_is_idempotent():
    assert keep_freed_memory() == keep_freed_memory()
