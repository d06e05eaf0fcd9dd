"""Tests of egorefine.refine.correct: the paper's gate/gain rule and the Kalman fusion."""

from __future__ import annotations

import pytest
import torch

from egorefine.core import ShapeError, ValueRangeError
from egorefine.geometry import make_intrinsics
from egorefine.refine.correct import (
    QUANTISATION_VARIANCE,
    CorrectDisparity,
    Correction,
    correct_disparity,
    edge_variance,
)
from egorefine.refine.predict import predict_disparity


def _t(rows) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float64)[None, None]


# ----------------------------------------------------------------------------- the paper's rule
def test_paper_rule_exact_on_hand_made_maps():
    e = _t([[2.0, 2.0, 2.0], [2.0, 2.0, 2.0], [2.0, 2.0, 2.0]])
    # differences s - e: just below/above the 0.5 px gate, both signs, exactly at it, large ones
    s = _t([[2.49, 2.51, 1.51], [1.49, 2.5, 1.5], [5.0, 0.0, 2.0]])
    cor = correct_disparity(e, s, None, fusion="paper")
    expected = _t(
        [
            [2.0, 2.0 + 0.4 * 0.51, 2.0],
            [2.0 - 0.4 * 0.51, 2.0, 2.0],  # |e - s| = 0.5 is not > 0.5: kept
            [2.0 + 0.4 * 3.0, 2.0 - 0.4 * 2.0, 2.0],
        ]
    )
    assert torch.allclose(cor.disparity, expected, atol=1e-12)
    assert cor.valid.all()
    fired = _t([[0, 1, 0], [1, 0, 0], [1, 1, 0]])
    assert torch.equal(cor.outlier_count, fired)  # consecutive gate firings, recorded only


def test_paper_rule_gate_and_gain_configurable():
    e = _t([[1.0, 1.0]])
    s = _t([[1.3, 3.0]])
    cor = correct_disparity(e, s, None, fusion="paper", gate=0.25, gain=0.5)
    assert torch.allclose(cor.disparity, _t([[1.15, 2.0]]), atol=1e-12)


def test_paper_rule_validity_and_variance():
    e = _t([[2.0, 2.0, 2.0, 2.0]])
    s = _t([[3.0, 3.0, 3.0, 3.0]])
    e_ok = _t([[1, 0, 1, 0]]).bool()
    s_ok = _t([[1, 1, 0, 0]]).bool()
    P, R = _t([[1.0, 9.0, 1.0, 9.0]]), _t([[0.25, 0.25, 0.25, 0.25]])
    cor = correct_disparity(e, s, s_ok, fusion="paper", predicted_variance=P, measured_variance=R, predicted_valid=e_ok)
    # both valid: gain rule; hole + measurement: take s; no measurement: keep e; neither: keep e, invalid
    assert torch.allclose(cor.disparity, _t([[2.4, 3.0, 2.0, 2.0]]), atol=1e-12)
    assert torch.equal(cor.valid, _t([[1, 1, 1, 0]]).bool())
    # variance: fixed-gain blend (1-a)^2 P + a^2 R; R where s was taken; carried otherwise
    assert torch.allclose(cor.variance, _t([[0.36 * 1.0 + 0.16 * 0.25, 0.25, 1.0, 9.0]]), atol=1e-12)


# ----------------------------------------------------------------------------- Kalman
def test_kalman_update_exact():
    e = _t([[2.0, 2.0, 2.0]])
    s = _t([[2.3, 2.3, 2.0]])
    P = _t([[0.1, 0.3, 0.2]])
    R = _t([[0.1, 0.1, 0.05]])
    cor = correct_disparity(e, s, None, fusion="kalman", predicted_variance=P, measured_variance=R)
    G = P / (P + R)
    assert torch.allclose(cor.disparity, e + G * (s - e), atol=1e-12)
    assert torch.allclose(cor.variance, (1 - G) * P, atol=1e-12)
    # corrects below the paper's 0.5 px gate, which the paper's rule leaves alone
    assert torch.equal(correct_disparity(e, s, None, fusion="paper").disparity, e)


def test_kalman_gates_outliers_and_resets_when_they_persist():
    e = _t([[2.0, 2.0]])
    s = _t([[5.0, 2.1]])  # 3 px off with sqrt(P + R) = 0.5: an outlier at 3 sigma; 0.1 px: an inlier
    P, R = _t([[0.15, 0.15]]), _t([[0.1, 0.1]])
    kw = dict(fusion="kalman", measured_variance=R, kalman_gate=3.0, reset_after=2)
    first = correct_disparity(e, s, None, predicted_variance=P, **kw)
    assert first.disparity[0, 0, 0, 0] == 2.0 and first.variance[0, 0, 0, 0] == 0.15  # gated out, kept
    assert torch.equal(first.outlier_count, _t([[1.0, 0.0]]))
    second = correct_disparity(
        first.disparity, s, None, predicted_variance=first.variance, outlier_count=first.outlier_count, **kw
    )
    assert second.disparity[0, 0, 0, 0] == 5.0 and second.variance[0, 0, 0, 0] == 0.1  # reset to s, R
    assert torch.equal(second.outlier_count, _t([[0.0, 0.0]]))
    # an inlier in between clears the count
    cleared = correct_disparity(e, _t([[2.1, 2.1]]), None, predicted_variance=P, outlier_count=_t([[1.0, 1.0]]), **kw)
    assert torch.equal(cleared.outlier_count, _t([[0.0, 0.0]]))


def test_kalman_holes_and_missing_measurements():
    e, s = _t([[2.0, 2.0]]), _t([[3.0, 3.0]])
    cor = correct_disparity(
        e,
        s,
        _t([[1, 0]]).bool(),
        fusion="kalman",
        predicted_valid=_t([[0, 1]]).bool(),
        predicted_variance=_t([[100.0, 0.3]]),
        outlier_count=_t([[2.0, 1.0]]),
    )
    assert torch.equal(cor.disparity, _t([[3.0, 2.0]]))
    assert torch.allclose(cor.variance, _t([[QUANTISATION_VARIANCE, 0.3]]))  # default R: integer quantisation
    assert torch.equal(cor.outlier_count, _t([[0.0, 1.0]]))


def test_kalman_reduces_error_on_a_static_scene():
    # A slanted plane seen by a still rig; stereo measures it with N(0, 0.3^2) noise every frame.
    # Predict (identity motion, small process noise) then correct, frame after frame.
    g = torch.Generator().manual_seed(0)
    K = make_intrinsics(50.0, 19.5, 14.5, dtype=torch.float64)
    b = torch.tensor([0.1], dtype=torch.float64)
    truth = 2.0 + 0.02 * torch.arange(40, dtype=torch.float64) + 0.03 * torch.arange(30, dtype=torch.float64)[:, None]
    truth = truth[None, None]
    sigma = 0.3
    eye = torch.eye(4, dtype=torch.float64)[None]

    def run(fusion):
        est = truth + sigma * torch.randn(truth.shape, generator=g, dtype=torch.float64)
        var = torch.full_like(truth, sigma**2)
        valid = torch.ones_like(truth, dtype=torch.bool)
        count = torch.zeros_like(truth)
        rmse = [(est - truth).pow(2).mean().sqrt()]
        for _ in range(15):
            pred = predict_disparity(est, eye, K, b, variance=var, valid=valid, process_noise=1e-4)
            meas = truth + sigma * torch.randn(truth.shape, generator=g, dtype=torch.float64)
            cor = correct_disparity(
                pred.disparity,
                meas,
                None,
                fusion=fusion,
                predicted_variance=pred.variance,
                measured_variance=torch.full_like(truth, sigma**2),
                predicted_valid=pred.valid,
                outlier_count=count,
            )
            est, var, valid, count = cor.disparity, cor.variance, cor.valid, cor.outlier_count
            rmse.append((est - truth).pow(2).mean().sqrt())
        return torch.stack(rmse)

    kalman = run("kalman")
    paper = run("paper")
    assert (kalman[1:] <= kalman[:-1] * 1.05).all()  # decreases (up to noise) as measurements accumulate
    assert kalman[-1] < 0.1  # sigma / sqrt(16) = 0.075 for an ideal average; measured 0.077
    assert kalman[-1] < 0.7 * paper[-1]  # measured 0.077 vs 0.155: the paper rule leaves errors below its gate


# ----------------------------------------------------------------------------- unverified predictions, depth edges
def test_unverified_predictions_are_valid_only_while_their_variance_allows():
    e, s = _t([[2.0, 2.0, 2.0, 2.0]]), _t([[3.0, 3.0, 3.0, 3.0]])
    s_ok = _t([[0, 0, 1, 0]]).bool()  # stereo rejected pixels 0, 1 and 3
    e_ok = _t([[1, 1, 1, 0]]).bool()
    P = _t([[0.05, 0.2, 0.2, 0.01]])
    kw = dict(predicted_variance=P, predicted_valid=e_ok, measured_variance=_t([[0.1] * 4]))
    cor = correct_disparity(e, s, s_ok, fusion="kalman", max_unverified_variance=0.0625, **kw)
    # 0: unverified, sigma 0.22 px: kept; 1: unverified, sigma 0.45 px: not valid; 2: measured: valid whatever P;
    # 3: neither map: not valid
    assert torch.equal(cor.valid, _t([[1, 0, 1, 0]]).bool())
    free = correct_disparity(e, s, s_ok, fusion="kalman", **kw)
    assert torch.equal(free.valid, _t([[1, 1, 1, 0]]).bool())
    for x, y in zip(cor[:2] + cor[3:], free[:2] + free[3:], strict=True):
        assert torch.equal(x, y)  # only validity changes: values, variances and counts are carried
    # the paper's rule is the paper's: the limit does not apply there
    paper = correct_disparity(e, s, s_ok, fusion="paper", max_unverified_variance=0.0625, **kw)
    for x, y in zip(paper, correct_disparity(e, s, s_ok, fusion="paper", **kw), strict=True):
        assert torch.equal(x, y)
    module = CorrectDisparity(fusion="kalman", max_unverified_variance=0.0625)(e, s, s_ok, **kw)
    for x, y in zip(module, cor, strict=True):
        assert torch.equal(x, y)
    with pytest.raises(ValueRangeError, match="max_unverified_variance"):
        correct_disparity(e, s, s_ok, fusion="kalman", max_unverified_variance=0.0)


def test_edge_variance_on_a_slanted_plane_with_a_box():
    # truth: a plane of slope 0.02 px/px along x, a box 3 px nearer on rows 3-6, columns 4-7; column 0 invalid
    d = (4.0 + 0.02 * torch.arange(12, dtype=torch.float64)).expand(10, 12).clone()
    d[3:7, 4:8] += 3.0
    valid = torch.ones_like(d, dtype=torch.bool)
    valid[:, 0] = False
    var = edge_variance(d[None, None], valid[None, None])[0, 0]
    touches = torch.zeros_like(valid)  # 3x3 window holds box and plane
    touches[2:8, 3:9] = True
    touches[4:6, 5:7] = False
    assert (var[touches] >= (2.96 / 2) ** 2 - 1e-9).all()  # box 3 px above the plane, minus 2 px of slope
    plane = valid & ~touches
    plane[3:7, 4:8] = False
    # on the plane: (slope * 2 px / 2)^2 = 1e-4 * 4; at columns 1 and 11 the window holds 2 valid columns: 1e-4
    expected = torch.full_like(var, 4e-4)
    expected[:, 1] = expected[:, 11] = 1e-4
    assert torch.allclose(var[plane], expected[plane], atol=1e-12)
    assert torch.allclose(var[4:6, 5:7], torch.full((2, 2), 4e-4, dtype=torch.float64), atol=1e-12)  # box inside
    assert (var[:, 0] == 0).all()  # invalid pixels: 0
    wide = edge_variance(d[None, None], valid[None, None], kernel_size=5)[0, 0]
    assert wide[1, 6] >= 2.19 and var[1, 6] == pytest.approx(4e-4)  # two rows above the box: only the 5x5 sees it
    with pytest.raises(ValueRangeError, match="kernel_size"):
        edge_variance(d[None, None], kernel_size=4)
    with pytest.raises(ShapeError, match="valid"):
        edge_variance(d[None, None], valid)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])  # float32: the compiled pass on the CPU
def test_edge_variance_adds_a_base_in_the_same_pass(dtype):
    g = torch.Generator().manual_seed(3)
    d = (4.0 + 3.0 * (torch.rand(2, 1, 9, 13, generator=g) > 0.7)).to(dtype)
    valid = torch.rand(2, 1, 9, 13, generator=g) > 0.1
    base = torch.rand(2, 1, 9, 13, generator=g).to(dtype)
    alone = edge_variance(d, valid)
    assert alone.max() > 2.0  # edges are there
    assert torch.equal(edge_variance(d, valid, base=base), base + alone)
    with_grad = base.clone().requires_grad_()
    edge_variance(d, valid, base=with_grad).sum().backward()  # the base keeps its gradient
    assert torch.equal(with_grad.grad, torch.ones_like(base))
    with pytest.raises(ShapeError, match="base"):
        edge_variance(d, valid, base=base[0])


def test_edge_variance_lets_the_measurement_win_at_edges():
    # a prediction with a box edge one pixel off (columns 3 hold the box's 6 px instead of the plane's 3 px);
    # stereo measures the truth. With the edge term the Kalman update takes the measurement at the edge.
    truth = torch.full((1, 1, 4, 8), 3.0, dtype=torch.float64)
    truth[..., 4:] = 6.0
    pred = truth.clone()
    pred[..., 3] = 6.0
    P = torch.full_like(pred, 0.05)
    R = torch.full_like(pred, 0.02)
    kw = dict(fusion="kalman", measured_variance=R, kalman_gate=1e6)  # gate off: the fusion alone decides
    plain = correct_disparity(pred, truth, None, predicted_variance=P, **kw)
    edged = correct_disparity(pred, truth, None, predicted_variance=P + edge_variance(pred), **kw)
    err_plain = (plain.disparity - truth).abs()[..., 3]
    err_edged = (edged.disparity - truth).abs()[..., 3]
    assert (err_plain > 0.8).all()  # G = 0.05 / 0.07: 3 * 0.29 = 0.86 px off, a bad-0.5 pixel
    assert (err_edged < 0.03).all()  # P = 0.05 + 2.25: G = 0.991, 0.026 px off
    interior = torch.ones(8, dtype=torch.bool)
    interior[2:6] = False  # away from the edge the update is the same
    assert torch.equal(plain.disparity[..., interior], edged.disparity[..., interior])


# ----------------------------------------------------------------------------- checks, batch, module, gradients
def test_exceptions():
    e = torch.ones(1, 1, 3, 4)
    with pytest.raises(ShapeError, match="measured"):
        correct_disparity(e, torch.ones(1, 1, 3, 5), None)
    with pytest.raises(ShapeError, match="predicted_variance"):
        correct_disparity(e, e, None, predicted_variance=torch.ones(1, 3, 4))
    with pytest.raises(ShapeError, match="predicted"):
        correct_disparity(e[0], e[0], None)
    with pytest.raises(ValueRangeError, match="fusion"):
        correct_disparity(e, e, None, fusion="average")
    with pytest.raises(ValueRangeError, match="gain"):
        correct_disparity(e, e, None, gain=1.5)
    with pytest.raises(ValueRangeError, match="reset_after"):
        correct_disparity(e, e, None, fusion="kalman", reset_after=0)


@pytest.mark.parametrize("compiled", [True, False])  # float32 CPU maps: a compiled scan decides, else the checks
@pytest.mark.parametrize(("name", "value", "message"), [
    ("predicted", float("nan"), "predicted: contains NaN or Inf"),
    ("measured", float("-inf"), "measured: contains NaN or Inf"),
    ("predicted_variance", -0.5, "predicted_variance: expected finite values >= 0"),
    ("measured_variance", float("inf"), "measured_variance: expected finite values >= 0"),
    ("measured_variance", float("nan"), "measured_variance: expected finite values >= 0"),
])
def test_values_are_checked_on_both_paths(compiled, name, value, message, monkeypatch):
    from egorefine.core import dispatch

    monkeypatch.setattr(dispatch, "ENABLED", compiled)
    maps = {key: torch.full((1, 1, 30, 40), 0.5) for key in ("predicted", "measured", "predicted_variance",
                                                             "measured_variance")}
    maps[name][0, 0, 17, 23] = value
    with pytest.raises(ValueRangeError, match=message):
        correct_disparity(fusion="kalman", measured_valid=None, **maps)
    maps[name][0, 0, 17, 23] = 0.0  # -0.0 and 0 pass
    maps["predicted_variance"][0, 0, 3, 4] = -0.0
    correct_disparity(fusion="kalman", measured_valid=None, **maps)


@pytest.mark.parametrize("fusion", ["paper", "kalman"])
def test_batch_consistency_and_module(fusion):
    g = torch.Generator().manual_seed(2)
    e = 2 + torch.rand(3, 1, 6, 7, generator=g, dtype=torch.float64)
    s = e + torch.randn(3, 1, 6, 7, generator=g, dtype=torch.float64)
    P = torch.rand(3, 1, 6, 7, generator=g, dtype=torch.float64)
    s_ok = torch.rand(3, 1, 6, 7, generator=g) > 0.2
    e_ok = torch.rand(3, 1, 6, 7, generator=g) > 0.2
    count = torch.randint(0, 2, (3, 1, 6, 7), generator=g).double()
    kw = dict(predicted_variance=P, predicted_valid=e_ok, outlier_count=count)
    batched = correct_disparity(e, s, s_ok, fusion=fusion, **kw)
    assert isinstance(batched, Correction)
    for i in range(3):
        alone = correct_disparity(
            e[i : i + 1], s[i : i + 1], s_ok[i : i + 1], fusion=fusion, **{k: v[i : i + 1] for k, v in kw.items()}
        )
        for x, y in zip(batched, alone, strict=True):
            assert torch.equal(x[i : i + 1], y)
    module = CorrectDisparity(fusion=fusion, gate=0.3, gain=0.6, kalman_gate=2.0, reset_after=3)
    out = module(e, s, s_ok, **kw)
    ref = correct_disparity(e, s, s_ok, fusion=fusion, gate=0.3, gain=0.6, kalman_gate=2.0, reset_after=3, **kw)
    for x, y in zip(out, ref, strict=True):
        assert torch.equal(x, y)


@pytest.mark.parametrize("fusion", ["paper", "kalman"])
def test_gradcheck(fusion):
    # innovations away from the gates: |s - e| in {0.2, 0.9, 1.4} against gate 0.5 / 3 sigma = 3.3 px
    e = _t([[2.0, 2.0, 2.0], [3.0, 3.0, 3.0]]).requires_grad_(True)
    s = _t([[2.2, 2.9, 0.6], [3.2, 2.1, 4.4]]).requires_grad_(True)
    P = _t([[0.5, 1.0, 0.8], [0.6, 0.7, 0.9]]).requires_grad_(True)
    R = _t([[0.3, 0.4, 0.5], [0.2, 0.3, 0.4]]).requires_grad_(True)

    def f(e_, s_, P_, R_):
        c = correct_disparity(e_, s_, None, fusion=fusion, predicted_variance=P_, measured_variance=R_)
        return c.disparity, c.variance

    assert torch.autograd.gradcheck(f, (e, s, P, R), eps=1e-6, atol=1e-7)
