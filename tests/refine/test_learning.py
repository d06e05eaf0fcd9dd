"""Learnable parts of the refiner: parameters, the confidence and correction networks, training steps, bad inputs."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from egorefine.core import ShapeError, ValueRangeError
from egorefine.data import render_sequence
from egorefine.refine import NET_INPUTS, ConfidenceNet, CorrectionNet, EgoMotionRefiner, measurement_features

SMALL = dict(max_disparity=16, max_features=64, min_tracks=16)


@pytest.fixture(scope="module")
def seq():
    return render_sequence(num_frames=4, height=48, width=64, seed=7)


def _run(refiner, seq, frames=None, grad=False):
    K, b = seq.K[None], torch.tensor([seq.baseline])
    state, outs = None, []
    with torch.set_grad_enabled(grad):
        for t in range(frames or len(seq)):
            out, state = refiner(seq.left[t:t + 1], seq.right[t:t + 1], K, b, state)
            outs.append(out)
    return outs, state


def _loss(outs, seq):
    errs, n = [], 0
    for t, out in enumerate(outs[1:], start=1):
        m = out.valid & (seq.disparity[t:t + 1] > 0)
        errs.append((out.disparity - seq.disparity[t:t + 1]).abs()[m].sum())
        n += int(m.sum())
    return torch.stack(errs).sum() / n


def test_learnable_parameters_are_registered_and_start_at_the_defaults():
    r = EgoMotionRefiner(learnable=True, gain=0.3, gate=0.7, process_noise=0.02, **SMALL)
    names = dict(r.named_parameters())
    assert set(names) == {"gain_logit", "log_gate", "log_process_noise", "log_noise_scale", "log_temperature"}
    assert set(names) <= set(r.state_dict())
    torch.testing.assert_close(r.gain, torch.tensor(0.3))
    torch.testing.assert_close(r.gate, torch.tensor(0.7))
    torch.testing.assert_close(r.process_noise, torch.tensor(0.02))
    torch.testing.assert_close(r.noise_scale, torch.tensor(1.0))
    r = r.to(torch.float64)  # moved by .to()
    assert all(p.dtype == torch.float64 for p in r.parameters())
    fixed = EgoMotionRefiner(**SMALL)
    assert list(fixed.parameters()) == [] and fixed.gain == 0.4 and fixed.process_noise == 0.01


def test_untrained_learnable_refiner_with_a_confidence_net_gives_the_defaults_outputs(seq):
    want, _ = _run(EgoMotionRefiner(fusion="kalman", verify_every=2, **SMALL), seq)
    got, _ = _run(EgoMotionRefiner(fusion="kalman", verify_every=2, learnable=True, confidence_net=ConfidenceNet(),
                                   correction_net=CorrectionNet(), **SMALL), seq)
    for a, e in zip(got, want, strict=True):
        assert torch.equal(a.valid, e.valid)
        torch.testing.assert_close(a.disparity, e.disparity, atol=1e-5, rtol=0)


@pytest.mark.parametrize("fusion", ["paper", "kalman"])
def test_a_few_training_steps_lower_the_loss_and_change_the_parameters(seq, fusion):
    torch.manual_seed(0)
    refiner = EgoMotionRefiner(fusion=fusion, verify_every=2, learnable=True, gate_softness=0.1,
                               confidence_net=ConfidenceNet(width=4) if fusion == "kalman" else None, **SMALL)
    start = {n: p.detach().clone() for n, p in refiner.named_parameters()}
    opt = torch.optim.Adam(refiner.parameters(), lr=0.1)
    losses = []
    for _ in range(4):
        opt.zero_grad()
        loss = _loss(_run(refiner, seq, grad=True)[0], seq)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    final = float(_loss(_run(refiner, seq)[0], seq))
    assert final < losses[0]
    changed = [n for n, p in refiner.named_parameters() if not torch.equal(p.detach(), start[n])]
    # paper mode's gain and gate act on its values; Kalman mode's process noise, noise scale and network
    expected = {"gain_logit", "log_gate"} if fusion == "paper" else {"log_process_noise", "log_noise_scale",
                                                                     "confidence_net.body.4.bias"}
    assert expected <= set(changed)


def test_state_detach_cuts_the_graph_between_frames(seq):
    refiner = EgoMotionRefiner(fusion="kalman", verify_every=5, **SMALL)
    K, b = seq.K[None], torch.tensor([seq.baseline])
    left0 = seq.left[:1].clone().requires_grad_(True)
    _, state = refiner(left0, seq.right[:1], K, b, None)
    assert state.disparity.requires_grad
    cut = state.detach()
    assert not any(isinstance(v, torch.Tensor) and v.requires_grad for v in cut)
    assert not any(t.requires_grad for t in cut.pyramid)
    out, _ = refiner(seq.left[1:2], seq.right[1:2], K, b, cut)
    assert not out.disparity.requires_grad
    torch.testing.assert_close(cut.disparity, state.disparity.detach())


class _Shape(nn.Module):
    def forward(self, x):
        return x[:, :2]


class _NaN(nn.Module):
    def forward(self, x):
        return torch.full_like(x[:, :1], float("nan"))


class _Constant(nn.Module):
    def __init__(self, value):
        super().__init__()
        self.value = value

    def forward(self, x):
        assert x.shape[1] == NET_INPUTS
        return torch.full_like(x[:, :1], self.value)


class _Negative(nn.Module):
    def forward(self, x):
        return -torch.ones_like(x[:, :1])


@pytest.mark.parametrize("net, error", [(_Shape(), ShapeError), (_NaN(), ValueRangeError)])
def test_a_bad_confidence_net_raises_a_typed_error(seq, net, error):
    refiner = EgoMotionRefiner(fusion="kalman", verify_every=1, confidence_net=net, **SMALL)
    with pytest.raises(error, match="confidence_net"):
        _run(refiner, seq, frames=2)


@pytest.mark.parametrize("net, error", [(_Shape(), ShapeError), (_NaN(), ValueRangeError)])
def test_a_bad_correction_net_raises_a_typed_error(seq, net, error):
    refiner = EgoMotionRefiner(fusion="kalman", verify_every=1, correction_net=net, **SMALL)
    with pytest.raises(error, match="correction_net"):
        _run(refiner, seq, frames=1)


@pytest.mark.parametrize("value, shift", [(0.25, 0.25), (-0.5, -0.5), (7.0, 2.0)])  # 7 px: clamped to 2
def test_the_correction_net_offsets_each_valid_measurement(seq, value, shift):
    plain, _ = _run(EgoMotionRefiner(fusion="kalman", **SMALL), seq, frames=1)
    got, _ = _run(EgoMotionRefiner(fusion="kalman", correction_net=_Constant(value), **SMALL), seq, frames=1)
    assert torch.equal(got[0].valid, plain[0].valid)
    m = plain[0].valid
    torch.testing.assert_close(got[0].disparity[m], plain[0].disparity[m] + shift)
    torch.testing.assert_close(got[0].disparity[~m], plain[0].disparity[~m])


def test_gradient_reaches_the_correction_net_from_a_predicted_frame(seq):
    torch.manual_seed(0)
    net = CorrectionNet(width=4, layers=2)
    refiner = EgoMotionRefiner(fusion="kalman", verify_every=5, correction_net=net, **SMALL)
    outs, _ = _run(refiner, seq, frames=3, grad=True)
    assert not outs[2].stereo_ran
    outs[2].disparity[outs[2].valid].sum().backward()
    grad = net.body[-1].bias.grad  # d(sum of predicted disparities)/d(offset): about the count of valid pixels
    assert grad is not None and torch.isfinite(grad).all()
    assert float(grad) > 0.5 * int(outs[2].valid.sum())


def test_measurement_features_channels():
    grey = torch.rand(1, 1, 3, 4)
    d = torch.tensor([[0.0, 3.25, 8.5, 10.0]]).expand(3, 4)[None, None]
    valid = d > 0
    filled = torch.zeros_like(valid)
    filled[..., 0, 1] = True
    x = measurement_features(grey, d, valid, filled, 16)
    assert x.shape == (1, NET_INPUTS, 3, 4)
    torch.testing.assert_close(x[:, 0:1], grey)
    torch.testing.assert_close(x[0, 1, 0], torch.tensor([0.0, 3.25, 8.5, 10.0]) / 16)
    torch.testing.assert_close(x[0, 2, 0], torch.tensor([0.0, 1.0, 1.0, 1.0]))
    torch.testing.assert_close(x[0, 3], filled[0, 0].float())
    torch.testing.assert_close(x[0, 4, 0], torch.tensor([0.0, 0.0, -1.0, 1.0]), atol=1e-5, rtol=0)  # cos 2 pi d
    torch.testing.assert_close(x[0, 5, 0], torch.tensor([0.0, 1.0, 0.0, 0.0]), atol=1e-5, rtol=0)  # sin 2 pi d
    with pytest.raises(ShapeError):
        CorrectionNet()(x[:, :3])


def test_a_negative_scale_is_clamped_never_nan(seq):
    outs, _ = _run(EgoMotionRefiner(fusion="kalman", verify_every=1, confidence_net=_Negative(), **SMALL), seq, 2)
    assert torch.isfinite(outs[1].disparity).all() and torch.isfinite(outs[1].variance).all()


def test_bad_learnable_settings_raise(seq):
    with pytest.raises(ValueRangeError, match="learnable"):
        EgoMotionRefiner(learnable=True, gain=1.0)
    with pytest.raises(ValueRangeError, match="learnable"):
        EgoMotionRefiner(learnable=True, process_noise=0.0)
    with pytest.raises(ValueRangeError, match="confidence_net"):
        EgoMotionRefiner(confidence_net=lambda x: x)
    with pytest.raises(ValueRangeError, match="correction_net"):
        EgoMotionRefiner(correction_net=lambda x: x)
    with pytest.raises(ValueRangeError, match="bound"):
        CorrectionNet(bound=0.0)
    with pytest.raises(ValueRangeError, match="gate_softness"):
        EgoMotionRefiner(gate_softness=-1.0)
    refiner = EgoMotionRefiner(learnable=True, fusion="kalman", verify_every=1, **SMALL)
    with torch.no_grad():
        refiner.log_process_noise.fill_(float("nan"))  # an optimiser step that diverged
    with pytest.raises(ValueRangeError, match="process_noise"):
        _run(refiner, seq, frames=2)


def test_differentiable_preset_sets_its_parts_unless_chosen():
    r = EgoMotionRefiner(differentiable=True, **SMALL)
    assert r.prediction.splat == "soft" and r.tracking.soft and r.correction.gate_softness == 0.1
    assert r._matcher()["differentiable"] is True
    r = EgoMotionRefiner(differentiable=True, splat="hard", soft_tracking=False, gate_softness=0.3, **SMALL)
    assert r.prediction.splat == "hard" and not r.tracking.soft and r.correction.gate_softness == 0.3
    plain = EgoMotionRefiner(**SMALL)
    assert plain.prediction.splat == "hard" and not plain.tracking.soft and plain.correction.gate_softness is None
