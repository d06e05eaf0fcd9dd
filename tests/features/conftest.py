"""Shared set-up of the feature tests."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True)
def one_thread():
    """Run each test on one thread, then restore the setting.

    These tests run many small tensor ops (a few hundred features, tiny gradcheck cases),
    which one thread does faster than two; on a busy machine two threads that wait for each
    other made single tests take a minute.
    """
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
