"""egorefine.core._graphs: CUDA-graph replay is used only for CUDA tensors without autograd (its replay is checked
against eager calls on a GPU in tests/test_cuda.py)."""

from __future__ import annotations

import pytest
import torch

from egorefine.core import _graphs


def test_not_usable_on_cpu_or_with_autograd(monkeypatch):
    assert not _graphs.usable(torch.zeros(2))
    if torch.cuda.is_available():
        x = torch.zeros(2, device="cuda")
        assert _graphs.usable(x)
        assert not _graphs.usable(x.requires_grad_(True))
        monkeypatch.setattr(_graphs, "ENABLED", False)
        assert not _graphs.usable(torch.zeros(2, device="cuda"))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_replay_follows_new_inputs_and_falls_back_when_recording_fails():
    def affine(x, y):
        return (x * 2 + y, x - y)

    for k in range(3):  # recorded on the first call, replayed with new values on the next ones
        x, y = torch.full((4,), float(k), device="cuda"), torch.arange(4.0, device="cuda")
        out = _graphs.replay(affine, ("test-affine",), x, y)
        for a, b in zip(out, affine(x, y), strict=True):
            assert torch.equal(a, b)

    def host_sync(x):
        return (x * float(x.sum()),)  # a host synchronisation cannot be recorded

    x = torch.ones(3, device="cuda")
    with pytest.warns(RuntimeWarning, match="cannot be recorded"):
        out = _graphs.replay(host_sync, ("test-sync",), x)
    assert torch.equal(out[0], x * 3)
    assert torch.equal(_graphs.replay(host_sync, ("test-sync",), x)[0], x * 3)  # eager from then on, no warning
