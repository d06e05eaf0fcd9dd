"""Shared fixtures: fixed seeds and a modest thread count so the suite behaves the same everywhere."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(autouse=True)
def _seed_and_threads():
    torch.manual_seed(0)
    torch.set_num_threads(min(2, torch.get_num_threads()))
    yield


@pytest.fixture
def euroc_root() -> Path:
    """The real EuRoC clip shipped beside the repository (../shared/data); skipped when absent."""
    root = SHARED_DATA / "euroc_v1_01_micro"
    if not root.exists():
        pytest.skip(f"EuRoC clip not found at {root}")
    return root


@pytest.fixture
def require_backend():
    """A check that skips the test unless ``torch.compile`` works with the named backend here."""
    def check(backend: str) -> None:
        try:
            works = bool(torch.compile(lambda x: x + 1, backend=backend)(torch.ones(2)).eq(2).all())
        except Exception:  # no C++ compiler, or a backend this build lacks
            works = False
        if not works:
            pytest.skip(f"torch.compile's {backend!r} backend does not work here")
    return check
