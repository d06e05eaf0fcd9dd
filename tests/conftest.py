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
