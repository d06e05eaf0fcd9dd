"""close_cracks: magnification cracks closed with exact values, disocclusions left as holes."""

from __future__ import annotations

import pytest
import torch

from egorefine.core import ShapeError
from egorefine.geometry import make_intrinsics
from egorefine.refine import close_cracks, predict_disparity

H, W, F_PX, BASE = 32, 48, 50.0, 0.1


def _setup(disparity: torch.Tensor, motion: torch.Tensor):
    B = disparity.shape[0]
    K = make_intrinsics(F_PX, (W - 1) / 2, (H - 1) / 2).to(disparity.dtype).expand(B, 3, 3)
    b = torch.full((B,), BASE, dtype=disparity.dtype)
    pred = predict_disparity(disparity, motion, K, b)
    ones = torch.ones_like(disparity)
    return pred, close_cracks(pred, disparity, 0.1 * ones, disparity > 0, motion, K, b, process_noise=0.01), K, b


def _translation(tx: float = 0.0, tz: float = 0.0, dtype=torch.float64) -> torch.Tensor:
    m = torch.eye(4, dtype=dtype)[None]
    m[0, 0, 3], m[0, 2, 3] = tx, tz  # camera_t_T_key: a static point moves by (tx, 0, tz)
    return m


def test_closes_magnification_cracks_with_exact_values():
    # A wall 1.25 m ahead (4 px), the camera 0.9 m closer: everything in view is magnified 3.6 times, past
    # what the splat tiles, yet the keyframe saw every pixel of the new view.
    d = torch.full((1, 1, H, W), 4.0, dtype=torch.float64)
    pred, closed, _, _ = _setup(d, _translation(tz=-0.9))
    truth = 4.0 * 1.25 / 0.35
    assert (~pred.valid).float().mean() > 0.05  # the cracks are there
    assert closed.valid.all()
    torch.testing.assert_close(closed.disparity, torch.full_like(d, truth), atol=1e-6, rtol=0)
    # carried variance: var_k * (d' / d_k)^2 + process noise, on the looked-up pixels
    looked_up = ~pred.valid
    expected = 0.1 * (truth / 4.0) ** 2 + 0.01
    torch.testing.assert_close(closed.variance[looked_up], torch.full_like(closed.variance[looked_up], expected))
    assert torch.all(closed.confidence[looked_up] > 0)
    # splatted pixels are untouched
    assert torch.equal(closed.disparity[pred.valid], pred.disparity[pred.valid])


def test_disocclusion_stays_a_hole():
    # A near square (8 px) in front of a wall (2 px); the camera slides sideways. The strip of wall the square
    # hid at the keyframe opens up: the background rule fills it with the wall's value, but sent back at the
    # wall's depth it lands on the square, so it must stay a hole. Everything else must be valid and exact.
    d = torch.full((1, 1, H, W), 2.0, dtype=torch.float64)
    d[..., 10:22, 18:30] = 8.0
    motion = _translation(tx=0.05)  # the wall moves 1 px, the square 4 px
    pred, closed, _, _ = _setup(d, motion)
    truth = torch.full_like(d, 2.0)
    truth = torch.roll(truth, 1, dims=-1)
    truth[..., 10:22, 22:34] = 8.0  # the square moved 4 px right
    seen = torch.ones_like(d, dtype=torch.bool)
    seen[..., 10:22, 19:22] = False  # wall behind the square at the keyframe (columns 18..29 hid wall 19..30)
    seen[..., :, :1] = False  # entered the view
    assert bool((~pred.valid[..., 10:22, 19:22]).all())  # the disoccluded strip is a hole, to close or not
    assert torch.equal(pred.disparity[..., 10:22, 19:22], truth[..., 10:22, 19:22])  # ... filled with the wall
    assert not bool((closed.valid & ~seen).any()), "a disoccluded pixel was accepted"
    ok = closed.valid & seen
    assert ok.float().sum() >= seen.float().sum() - 24  # at most a few edge pixels left out
    torch.testing.assert_close(closed.disparity[ok], truth[ok], atol=1e-6, rtol=0)


def test_no_holes_returns_the_prediction_unchanged():
    d = torch.full((2, 1, H, W), 3.0)
    pred, closed, _, _ = _setup(d, torch.eye(4)[None].expand(2, 4, 4).contiguous())
    assert pred.valid.all() and closed is pred


def test_batch_items_are_independent():
    d = torch.full((1, 1, H, W), 4.0, dtype=torch.float64)
    d2 = d.clone()
    d2[..., 10:22, 18:30] = 8.0
    m1, m2 = _translation(tz=-0.9), _translation(tx=0.05)
    _, c1, K, b = _setup(d, m1)
    _, c2, _, _ = _setup(d2, m2)
    both_d, both_m = torch.cat([d, d2]), torch.cat([m1, m2])
    pred = predict_disparity(both_d, both_m, K.expand(2, 3, 3), b.expand(2))
    both = close_cracks(pred, both_d, 0.1 * torch.ones_like(both_d), both_d > 0, both_m, K.expand(2, 3, 3), b.expand(2),
                        process_noise=0.01)
    for i, c in enumerate((c1, c2)):
        assert torch.equal(both.valid[i], c.valid[0])
        torch.testing.assert_close(both.disparity[i], c.disparity[0])


def test_bad_shapes():
    d = torch.full((1, 1, H, W), 4.0)
    pred, _, K, b = _setup(d, torch.eye(4)[None])
    with pytest.raises(ShapeError, match="key_disparity"):
        close_cracks(pred, d[0], d, d > 0, torch.eye(4)[None], K, b)
    with pytest.raises(ShapeError, match="motion"):
        close_cracks(pred, d, d, d > 0, torch.eye(4), K, b)
