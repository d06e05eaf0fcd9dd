"""Shared benchmark plumbing: timing, machine metadata, JSON and the README's tables.

Benchmarks measure ratios against OpenCV in the same run (shared machines are noisy),
interleaving the methods so that a burst of load hits all of them alike, and report
medians with the inter-quartile range.
"""

from __future__ import annotations

import json
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

# OpenMP's wait policy is left as the user's environment has it (by default libgomp spins briefly, then
# sleeps): that is what a user of the library gets. Measured on this 2-core machine when it was quiet
# (2026-11-22): OMP_WAIT_POLICY=PASSIVE slows the refiner's loop of many mid-sized ops from ~41 to ~71 ms
# per frame, ACTIVE (endless spinning) slows OpenCV and the compiled SGM by a third or more, the default
# is within noise of the best for all of them. On a machine that is oversubscribed, PASSIVE is the safer
# choice; the setting in force is stored with every result.
import cv2
import torch

from egorefine.core import machine_info as core_machine_info

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def omp_setting() -> str:
    """The OpenMP wait settings in force, as a short string for tables and JSON."""
    parts = [f"{k}={os.environ[k]}" for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT") if os.environ.get(k)]
    return ", ".join(parts) or "OpenMP default wait policy"


def machine_info() -> dict:
    """The library's machine facts (:func:`egorefine.core.machine_info`) plus the wait policy and the date."""
    return {**core_machine_info(), "omp_wait_policy": omp_setting(), "date": time.strftime("%Y-%m-%d %H:%M:%S")}


def set_threads(n: int) -> None:
    """Give torch and OpenCV the same number of threads."""
    torch.set_num_threads(n)
    cv2.setNumThreads(n)


def time_interleaved(fns: dict[str, Callable[[], object]], repeats: int = 7, warmup: int = 1,
                     burst: int = 1) -> dict[str, dict]:
    """Time several callables round-robin; returns ``{name: {"median_ms", "q1_ms", "q3_ms", "runs"}}``.

    With ``burst > 1`` each turn calls a method ``burst`` times in a row and keeps the last ``burst - 1``
    timings: the steady state of a method called frame after frame (as on a video), still interleaved
    with the others so that a burst of machine load hits all of them alike. (A call right after another
    method pays for that method's leftovers: OpenMP workers still spinning, memory returned to the OS.)
    """
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    samples: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            for i in range(burst):
                t0 = time.perf_counter()
                fn()
                if i > 0 or burst == 1:
                    samples[name].append((time.perf_counter() - t0) * 1e3)
    return {k: summarize(v) for k, v in samples.items()}


def summarize(ms: list[float]) -> dict:
    """Median and quartiles of a list of milliseconds."""
    q = statistics.quantiles(ms, n=4) if len(ms) > 1 else [ms[0]] * 3
    return {"median_ms": statistics.median(ms), "q1_ms": q[0], "q3_ms": q[2], "runs": len(ms)}


def write_json(name: str, payload: dict) -> Path:
    """Write ``benchmarks/results/<name>.json`` with machine metadata added."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    payload = {"machine": machine_info(), **payload}
    path.write_text(json.dumps(payload, indent=2, default=float))
    return path


def markdown_table(header: list[str], rows: list[list[object]]) -> str:
    """A GitHub markdown table; floats are printed with 3 significant decimals."""

    def fmt(v: object) -> str:
        if isinstance(v, float):
            return f"{v:.3f}" if abs(v) < 100 else f"{v:.1f}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def update_readme(section: str, text: str) -> None:
    """Replace the README between ``<!-- BEGIN {section} -->`` and ``<!-- END {section} -->``.

    Also writes ``benchmarks/results/<section>.md``. The README is left alone when it has no
    such markers (the table then lives only in the results folder).
    """
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{section}.md").write_text(text + "\n")
    readme = ROOT / "README.md"
    if not readme.exists():
        return
    begin, end = f"<!-- BEGIN {section} -->", f"<!-- END {section} -->"
    content = readme.read_text()
    if begin not in content or end not in content:
        return
    head, rest = content.split(begin, 1)
    _, tail = rest.split(end, 1)
    readme.write_text(f"{head}{begin}\n{text}\n{end}{tail}")
