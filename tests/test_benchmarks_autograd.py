"""benchmarks/autograd.py end to end at a tiny size: its JSON has the expected keys and finite numbers, and a
configuration whose keyword the installed refiner does not take is skipped, not a crash."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks import autograd  # noqa: E402

SMALL = {"max_features": 48, "min_tracks": 12}  # a few features: the torch tracker's cost grows with them
# (ideal imaging: the realistic model's first render in a process costs ~20 s of set-up on a loaded 2-core machine)


def _finite(value) -> bool:
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
    if isinstance(value, list):
        return all(_finite(v) for v in value)
    return not isinstance(value, float) or math.isfinite(value)


def test_benchmark_runs_tiny_and_writes_finite_results(tmp_path, monkeypatch):
    monkeypatch.setattr(autograd, "CONFIGS", [
        {"name": "kalman small", "kwargs": {"fusion": "kalman", **SMALL}},
        {"name": "not yet", "kwargs": {"fusion": "kalman", "no_such_option": True}},
    ])
    autograd.main(["--grad-size", "64x48", "--sizes", "64x48", "--frames", "3", "--repeats", "1",
                   "--backends", "none", "--no-profile", "--imaging", "ideal", "--out", str(tmp_path)])
    payload = json.loads((tmp_path / "autograd.json").read_text())
    assert {"machine", "seed", "configs", "skipped", "grad", "compile"} <= payload.keys()
    assert payload["skipped"] == ["not yet"]
    assert payload["compile"] == []  # --backends none
    assert [(r["config"], r["kind"]) for r in payload["grad"]] == [("kalman small", "prediction"),
                                                                   ("kalman small", "verification")]
    for row in payload["grad"]:
        assert {"nograd", "nograd_torch_path", "forward_grad", "backward"} == row["times"].keys()
        assert all(t["median_ms"] > 0 for t in row["times"].values())
        assert isinstance(row["forward_pass"], bool) and isinstance(row["backward_pass"], bool)
        assert row["grads_finite"] and row["grad_prev_left_finite"]
        assert row["forward_ratio"] > 0 and row["backward_ratio"] > 0
    assert payload["grad"][1]["stereo_ran"]
    assert _finite(payload)
    text = (tmp_path / "autograd.md").read_text()
    assert "kalman small" in text and "not yet" in text
