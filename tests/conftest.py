"""Shared fixtures: fixed seeds and a modest thread count so the suite behaves the same everywhere."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

# The one place that names the real data the tests read: small clips shipped in the repository, each folder with a
# README giving its source, licence and what was trimmed. Tests take them through the fixtures below, never by path.
REAL_DATA = Path(__file__).resolve().parent / "data" / "real"


@pytest.fixture(autouse=True)
def _seed_and_threads():
    torch.manual_seed(0)
    torch.set_num_threads(min(2, torch.get_num_threads()))
    yield


def _real_data(name: str) -> Path:
    """``REAL_DATA / name``; a checkout without it is broken, so the test errors instead of skipping."""
    root = REAL_DATA / name
    if not (root / "README.md").is_file():
        raise FileNotFoundError(f"{root}: the real data the tests read ships in the repository under tests/data/real; "
                                "this checkout lacks it")
    return root


@pytest.fixture(scope="session")
def euroc_root() -> Path:
    """The first 40 frames of EuRoC MAV V1_01_easy in the ASL layout (tests/data/real/euroc_v1_01_micro)."""
    return _real_data("euroc_v1_01_micro")


@pytest.fixture(scope="session")
def kitti_root() -> Path:
    """One KITTI raw colour pair, its calibration and a one-sweep LiDAR disparity truth
    (tests/data/real/kitti_velodyne_frame)."""
    return _real_data("kitti_velodyne_frame")


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
