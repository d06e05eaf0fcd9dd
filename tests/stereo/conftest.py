"""Stereo tests run torch single-threaded: the many mid-sized tensor ops of the matcher pay an
OpenMP synchronisation each, which on a shared, oversubscribed machine costs far more than the
second thread gains. Results do not depend on it."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True)
def _single_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
