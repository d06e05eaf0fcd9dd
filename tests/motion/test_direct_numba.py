"""The compiled CPU form of the direct photometric refinement (egorefine.motion._direct_numba) against the torch path,
which stays the reference (GPU, float64, autograd)."""

from __future__ import annotations

import pytest
import torch

from egorefine.core import ValueRangeError, dispatch
from egorefine.data import render_sequence
from egorefine.geometry import se3_exp, se3_inverse, se3_log
from egorefine.motion import _direct_numba
from egorefine.motion.direct import DIRECT_STATUS, refine_motion_direct

pytestmark = pytest.mark.skipif(not _direct_numba.AVAILABLE, reason="numba not installed")

# The compiled path sums in float64, the torch path in float32: their motions differ by that rounding, and an
# accept/reject test between two costs within it can take another short path to the same minimum. 0.05 mm and
# 5e-5 rad stay far below what a broken step moves (the starts are millimetres and 0.15 deg off the truth, and a
# wrong Jacobian or a missing brightness term ends them a millimetre or more apart).
TRANSLATION_TOL = 5e-5
ROTATION_TOL = 5e-5
# a start 7 mm and 0.15 deg off the truth, and one 5 mm and 0.1 deg off another way
OFFSETS = [[0.004, -0.003, 0.005, 0.002, -0.001, 0.0015], [-0.003, 0.002, -0.004, -0.001, 0.0015, -0.001]]


@pytest.fixture(scope="module")
def sequences():
    return [render_sequence(num_frames=2, height=120, width=160, seed=seed) for seed in (0, 1, 2)]


def _args(seq):
    return seq.left[:1], seq.left[1:], seq.disparity[:1], seq.K[None], torch.tensor([seq.baseline])


def _start(seq, offset):
    return se3_exp(torch.tensor([offset])) @ seq.motions[1][None].float()


def _both(monkeypatch, *args, **kw):
    """(compiled, torch path) results of the same call; the compiled path must have run once."""
    calls = []
    real = _direct_numba.refine_compiled
    monkeypatch.setattr(_direct_numba, "refine_compiled", lambda *a, **k: calls.append(1) or real(*a, **k))
    compiled = refine_motion_direct(*args, **kw)
    assert len(calls) == 1, "the compiled refinement did not run"
    monkeypatch.setattr(dispatch, "ENABLED", False)
    reference = refine_motion_direct(*args, **kw)
    monkeypatch.setattr(dispatch, "ENABLED", True)
    assert len(calls) == 1
    return compiled, reference


def _assert_same(a, r):
    """Statuses, pixel counts and dtypes equal; motions, brightness and costs within the rounding tolerances."""
    assert torch.equal(a.status, r.status) and torch.equal(a.num_pixels, r.num_pixels)
    for x, y in zip(a, r, strict=True):
        assert x.dtype == y.dtype and x.shape == y.shape
        assert not (x.is_floating_point() and x.isnan().any())
    dt = (a.motion[:, :3, 3] - r.motion[:, :3, 3]).norm(dim=-1)
    rot = se3_log(se3_inverse(a.motion.double()) @ r.motion.double())[:, 3:].norm(dim=-1)
    assert (dt < TRANSLATION_TOL).all() and (rot < ROTATION_TOL).all(), (dt, rot)
    torch.testing.assert_close(a.gain, r.gain, rtol=0, atol=1e-4)
    torch.testing.assert_close(a.offset, r.offset, rtol=0, atol=1e-4)
    torch.testing.assert_close(a.cost_before, r.cost_before, rtol=1e-4, atol=0)
    torch.testing.assert_close(a.cost_after, r.cost_after, rtol=1e-3, atol=0)
    refined = a.status != DIRECT_STATUS["refined"]
    assert torch.equal(a.motion[refined], r.motion[refined])  # the input itself where not refined


@pytest.mark.parametrize("offset", OFFSETS)
def test_compiled_equals_torch_path(monkeypatch, sequences, offset):
    for seq in sequences:
        start = _start(seq, offset)
        a, r = _both(monkeypatch, *_args(seq), start)
        _assert_same(a, r)
        assert a.status.tolist() == [DIRECT_STATUS["refined"]]
        # both moved well away from the start: the tolerances above are not met by doing nothing
        moved = (a.motion[0, :3, 3] - start[0, :3, 3]).norm()
        assert moved > 20 * TRANSLATION_TOL, moved


def test_compiled_equals_torch_path_with_valid_variance_and_settings(monkeypatch, sequences):
    seq = sequences[0]
    prev, img, disp, K, b = _args(seq)
    valid = torch.ones_like(disp, dtype=torch.bool)
    valid[..., 40:80, 60:120] = False
    variance = torch.rand(disp.shape, generator=torch.Generator().manual_seed(0)) * 0.3
    variance[..., :10, :] = float("nan")  # counts as no variance, as in the torch path
    variance[..., 10:14, :] = float("inf")
    start = _start(seq, OFFSETS[0])
    for kw in ({"prev_valid": valid, "prev_variance": variance}, {"levels": 2, "iterations": 6, "cell": 8},
               {"blur": 0.0, "per_cell": 2, "damping": 1e-2}, {"iterations": 0}, {"levels": 1, "min_gradient": 0.0}):
        a, r = _both(monkeypatch, prev, img, disp, K, b, start, **kw)
        _assert_same(a, r)


def test_brightness_change_gain_and_offset(monkeypatch, sequences):
    seq = sequences[1]
    prev, img, disp, K, b = _args(seq)
    a, r = _both(monkeypatch, prev, img * 1.15 + 0.02, disp, K, b, _start(seq, OFFSETS[1]))
    _assert_same(a, r)
    assert a.status.tolist() == [DIRECT_STATUS["refined"]]
    assert abs(a.gain.item() - 1.15) < 0.03 and abs(a.offset.item() - 0.02) < 0.02


def test_batch_equals_torch_path_and_items_alone(monkeypatch, sequences):
    s0, s1 = sequences[0], sequences[2]
    args = [torch.cat([x, y]) for x, y in zip(_args(s0), _args(s1), strict=True)]
    start = torch.cat([_start(s0, OFFSETS[0]), _start(s1, OFFSETS[1])])
    args[2] = args[2].clone()
    args[2][1] = 0.0  # item 1: no valid disparity
    a, r = _both(monkeypatch, *args, start)
    _assert_same(a, r)
    assert a.status.tolist() == [DIRECT_STATUS["refined"], DIRECT_STATUS["too few pixels"]]
    alone = refine_motion_direct(*(x[:1] for x in args), start[:1])
    for x, y in zip(a, alone, strict=True):
        assert torch.equal(x[:1], y)


def test_bad_input_returns_the_input_flagged_never_nan(monkeypatch, sequences):
    seq = sequences[0]
    prev, img, disp, K, b = _args(seq)
    start = _start(seq, OFFSETS[0])
    nan_disp = torch.full_like(disp, float("nan"))
    cases = {
        "black": (prev, torch.zeros_like(img), disp),
        "no disparity": (prev, img, torch.zeros_like(disp)),
        "nan disparity": (prev, img, nan_disp),
        "flat": (torch.full_like(prev, 0.5), img, disp),
        "overexposed": (prev, (img * 4).clamp(max=1.0), disp),
    }
    for name, (p, i, d) in cases.items():
        a, r = _both(monkeypatch, p, i, d, K, b, start)
        _assert_same(a, r)
        if name != "overexposed":
            assert a.status.item() != DIRECT_STATUS["refined"], name
        if a.status.item() != DIRECT_STATUS["refined"]:
            assert torch.equal(a.motion, start), name
            assert a.gain.item() == 1.0 and a.offset.item() == 0.0
            assert torch.equal(a.cost_after, a.cost_before)
    for name in ("no disparity", "nan disparity", "flat"):
        a = refine_motion_direct(*cases[name], K, b, start)
        assert a.status.item() == DIRECT_STATUS["too few pixels"], name


def test_thread_count_does_not_change_the_result(sequences):
    seq = sequences[1]
    args = [torch.cat([x, x]) for x in _args(seq)]
    start = torch.cat([_start(seq, OFFSETS[0]), _start(seq, OFFSETS[1])])
    one = _direct_numba.refine_compiled(args[0], args[1], args[2], None, None, args[3], args[4], start, 3, 4, 16, 4,
                                        0.01, 0.01, 64, 1e-3, 1.0, 0.5, threads=1)
    two = _direct_numba.refine_compiled(args[0], args[1], args[2], None, None, args[3], args[4], start, 3, 4, 16, 4,
                                        0.01, 0.01, 64, 1e-3, 1.0, 0.5, threads=2)
    for x, y in zip(one, two, strict=True):
        assert torch.equal(x, y)


def test_torch_path_where_compiled_does_not_apply(monkeypatch, sequences):
    def refuse(*args, **kwargs):
        raise AssertionError("the compiled refinement ran")

    seq = sequences[0]
    prev, img, disp, K, b = _args(seq)
    start = _start(seq, OFFSETS[0])
    monkeypatch.setattr(_direct_numba, "refine_compiled", refuse)
    out = refine_motion_direct(prev.double(), img.double(), disp.double(), K.double(), b.double(), start.double(),
                               levels=1, iterations=1)
    assert out.motion.dtype == torch.float64
    grad = img.clone().requires_grad_(True)  # a gradient is wanted
    refine_motion_direct(prev, grad, disp, K, b, start, levels=1, iterations=1).motion.sum().backward()
    assert grad.grad is not None
    with pytest.raises(ValueRangeError, match="smaller than one cell"):  # refused before either path
        refine_motion_direct(prev[..., :8, :], img[..., :8, :], disp[..., :8, :], K, b, start)
    monkeypatch.setattr(dispatch, "ENABLED", True)
    with pytest.raises(AssertionError, match="compiled refinement"):
        refine_motion_direct(prev, img, disp, K, b, start)
