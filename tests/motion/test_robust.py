"""Tests of egorefine.motion.robust: kernels and their IRLS weights."""

from __future__ import annotations

import pytest
import torch

from egorefine.motion import robust_loss, robust_weight


@pytest.mark.parametrize("loss", ["l2", "huber", "tukey"])
def test_weight_is_derivative_over_r(loss):
    r = torch.linspace(0.05, 8.0, 60, dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(robust_loss(r, loss, 1.0).sum(), r)
    torch.testing.assert_close(robust_weight(r.detach(), loss, 1.0), grad / r.detach(), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("loss", ["l2", "huber", "tukey"])
def test_weights_in_unit_interval_and_one_at_zero(loss):
    r = torch.linspace(0.0, 100.0, 101)
    w = robust_weight(r, loss, 2.0)
    assert (w >= 0).all() and (w <= 1).all() and w[0] == 1


def test_tukey_rejects_beyond_cutoff_and_scale():
    r = torch.tensor([4.6, 4.7, 9.3, 9.4])
    assert robust_weight(r[:2], "tukey", 1.0).tolist()[1] == 0.0
    assert robust_weight(r[:2], "tukey", 1.0)[0] > 0
    w2 = robust_weight(r[2:], "tukey", 2.0)
    assert w2[0] > 0 and w2[1] == 0
    assert torch.isfinite(robust_loss(torch.tensor([1e6]), "tukey", 1.0)).all()
