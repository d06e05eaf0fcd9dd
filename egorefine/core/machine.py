"""What machine and which libraries a run used: printed by ``egorefine info`` and CI, stored by the benchmarks."""

from __future__ import annotations

import os
import platform

import numpy as np
import torch

__all__ = ["cpu_model", "machine_info", "simd_flags"]

# Environment variables that set thread counts or OpenMP's behaviour; each is reported when set.
_THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS",
                     "OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OPENBLAS_CORETYPE")


def cpu_model() -> str:
    """The processor's model name (``/proc/cpuinfo`` on Linux, else ``platform.processor()``).

    Returns:
        e.g. ``"AMD EPYC 7B13"``; the machine type (``"x86_64"``) where no model name can be read.

    Example:
        >>> isinstance(cpu_model(), str) and len(cpu_model()) > 0
        True
    """
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.lower().startswith(("model name", "hardware", "cpu model")):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def simd_flags() -> list[str]:
    """The vector instruction sets the processor reports that decide float kernels' widths (Linux only).

    Returns:
        The ones present among ``sse4_2, avx, avx2, fma, avx512f, neon/asimd``; empty where ``/proc/cpuinfo``
        cannot be read.

    Example:
        >>> set(simd_flags()) <= {"sse4_2", "avx", "avx2", "fma", "avx512f", "asimd", "neon"}
        True
    """
    wanted = ("sse4_2", "avx", "avx2", "fma", "avx512f", "asimd", "neon")
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.lower().startswith(("flags", "features")):
                    present = set(line.split(":", 1)[1].split())
                    return [flag for flag in wanted if flag in present]
    except OSError:
        pass
    return []


def machine_info() -> dict[str, object]:
    """The processor, library versions and thread counts in force, as a flat dict.

    Float kernels differ between CPUs (SIMD width, fused multiply-add) and between thread counts (the order of
    a parallel reduction), so a test log or a benchmark result is read with this beside it. numba and OpenCV are
    reported when installed (numba is optional at run time).

    Returns:
        ``{"python", "platform", "cpu", "simd", "cpus", "torch", "torch_threads", "numpy", "numba", "numba_threads",
        "opencv", "opencv_threads", "cuda", "env"}``; ``env`` holds the thread-related environment variables that
        are set (``OMP_NUM_THREADS``, ``NUMBA_NUM_THREADS``, ``OMP_WAIT_POLICY``, ...).

    Example:
        >>> info = machine_info()
        >>> info["torch_threads"] >= 1 and info["torch"] == torch.__version__
        True
    """
    info: dict[str, object] = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu": cpu_model(),
        "simd": " ".join(simd_flags()) or None,
        "cpus": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "numpy": np.__version__,
        "numba": None,
        "numba_threads": None,
        "opencv": None,
        "opencv_threads": None,
        "cuda": torch.cuda.is_available(),
    }
    try:
        import numba

        info["numba"], info["numba_threads"] = numba.__version__, numba.get_num_threads()
    except ImportError:
        pass
    try:
        import cv2

        info["opencv"], info["opencv_threads"] = cv2.__version__, cv2.getNumThreads()
    except ImportError:
        pass
    info["env"] = {k: os.environ[k] for k in _THREAD_VARIABLES if os.environ.get(k)}
    return info
