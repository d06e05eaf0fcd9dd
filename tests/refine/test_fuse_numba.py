"""The compiled Kalman rule of correct_disparity equals the torch rule bit for bit."""

from __future__ import annotations

import pytest
import torch

from egorefine.core import dispatch
from egorefine.refine import _fuse_numba, correct_disparity


@pytest.mark.parametrize("shape", [(2, 1, 48, 64), (1, 1, 300, 301)])  # the second: bands of pixels on threads
@pytest.mark.parametrize("options", [{}, {"max_unverified_variance": 0.0625},
                                     {"reset_after": 2, "kalman_gate": 3.0, "min_variance": 1e-3}])
def test_compiled_kalman_equals_torch(options, shape, monkeypatch):
    """Bit for bit: the kernel does the torch path's float32 operations one by one (no fused multiply-add, which
    numba does not form without fast-math), each correctly rounded on any CPU, and selects instead of branches."""
    gen = torch.Generator().manual_seed(0)
    e = torch.rand(shape, generator=gen) * 40
    s = e + torch.randn(shape, generator=gen) * 0.6
    m_ok = torch.rand(shape, generator=gen) > 0.1
    p_ok = torch.rand(shape, generator=gen) > 0.1
    P = torch.rand(shape, generator=gen) * 0.2
    R = torch.rand(shape, generator=gen) * 0.2 + 0.05
    count = (torch.rand(shape, generator=gen) * 3).floor()
    outs = []
    for compiled in (False, True):
        monkeypatch.setattr(dispatch, "ENABLED", compiled)
        outs.append(correct_disparity(e, s, m_ok, fusion="kalman", predicted_variance=P, measured_variance=R,
                                      predicted_valid=p_ok, outlier_count=count, **options))
    for ref, fast in zip(*outs, strict=True):
        assert torch.equal(ref, fast)
    # every branch was exercised: fused, outliers (kept and reset), holes taken, measurement missing
    ref = outs[0]
    assert ((ref.disparity != e) & (ref.disparity != s)).any() and (ref.disparity == s).any()
    assert ((ref.disparity == e) & m_ok & p_ok).any()


def test_gradient_takes_the_torch_path():
    e = torch.rand(1, 1, 8, 8, requires_grad=True)
    out = correct_disparity(e, e.detach() + 0.1, None, fusion="kalman")
    out.disparity.sum().backward()
    assert e.grad is not None and torch.isfinite(e.grad).all()


def test_compiled_confidence_equals_the_formula():
    g = torch.Generator().manual_seed(4)
    variance = torch.rand(2, 1, 300, 400, generator=g) * 3.0  # more pixels than one chunk: threads split it
    valid = torch.rand(2, 1, 300, 400, generator=g) > 0.3
    out = _fuse_numba.confidence(valid, variance)
    assert torch.equal(out, valid.to(variance.dtype) / (1.0 + variance))  # bit for bit


@pytest.mark.parametrize("margin", [0.5, None])
def test_compiled_hole_take_over_equals_torch(margin, monkeypatch):
    """The refiner's take-over of hole measurements, random maps large enough to be split into bands: bit for bit
    (selects of the inputs and one correctly rounded division)."""
    from egorefine.refine._steps import _take_hole_measurements
    from egorefine.refine.predict import Prediction
    from egorefine.stereo import StereoOutput

    g = torch.Generator().manual_seed(7)
    shape = (2, 1, 200, 330)
    d, var = torch.rand(shape, generator=g) * 30, torch.rand(shape, generator=g)
    valid, count = torch.rand(shape, generator=g) > 0.4, (torch.rand(shape, generator=g) * 3).floor()
    meas = StereoOutput(d + torch.randn(shape, generator=g), torch.rand(shape, generator=g) > 0.2,
                        torch.rand(shape, generator=g) * 0.5)
    hole = torch.rand(shape, generator=g) > 0.5
    pred = Prediction(d + torch.randn(shape, generator=g), var, hole, ~hole, torch.zeros(shape))
    outs = []
    for compiled in (True, False):
        monkeypatch.setattr(dispatch, "ENABLED", compiled)
        outs.append(_take_hole_measurements(d, var, valid, count, meas, pred, 0.2, margin))
    for fast, ref in zip(*outs, strict=True):
        assert torch.equal(fast, ref)
    assert (outs[1][2] & ~valid).any()  # some holes were taken
