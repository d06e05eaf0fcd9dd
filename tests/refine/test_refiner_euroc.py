"""The refiner on real stereo video: the EuRoC V1_01 clip, where the vehicle is almost still."""

from __future__ import annotations

import pytest
import torch

from egorefine.data import load_euroc
from egorefine.metrics import rotation_error_deg, tile_shift, translation_error
from egorefine.refine import EgoMotionRefiner, predict_disparity


def _run(seq, **options):
    K, b = seq.K[None], torch.tensor([seq.baseline])
    refiner = EgoMotionRefiner(max_disparity=64, verify_every=5, **options)
    state, disparity, valid, motion = None, [], [], []
    for t in range(len(seq.left)):
        out, state = refiner(seq.left[t : t + 1], seq.right[t : t + 1], K, b, state)
        disparity.append(out.disparity)
        valid.append(out.valid)
        motion.append(out.motion)
        assert out.motion_ok.all() and torch.isfinite(out.disparity).all()
    return torch.cat(disparity), torch.cat(valid), torch.cat(motion)


def _first_map_moved(d, v, m, seq):
    """d_0 moved to every frame by the accumulated estimated motion, and the pixels to compare there."""
    moved = [m[0]]
    for step in m[1:]:
        moved.append(step @ moved[-1])
    T = len(d)
    K, b = seq.K[None].expand(T, 3, 3), torch.full((T,), seq.baseline)
    w = predict_disparity(d[:1].expand(T, -1, -1, -1).contiguous(), torch.stack(moved), K, b,
                          valid=v[:1].expand(T, -1, -1, -1).contiguous(), fill_holes=False)
    return w.disparity, w.valid & v & (w.disparity > 1.0)


# (fusion, stable share above, largest tile drift below, largest per-pixel drift below or None): from what each
# fusion achieves on the clip, density a few points below it, drift about 1.2-1.3 times it (paper mode's tile drift
# is a few thousandths of a pixel: 0.01 px, a floor that float rounding on another machine cannot reach)
DRIFT = {"paper": (0.6, 0.01, 0.04), "kalman": (0.78, 0.045, None)}


@pytest.mark.parametrize("fusion", ["paper", "kalman"])
def test_static_camera_does_not_drift(euroc_root, fusion):
    """Drift against the first map moved by the estimated motion, per 32 px tile (the shift a region shares; d_0's
    per-pixel noise averages away) on every frame, both fusions; per pixel too in paper mode, whose map stays near
    d_0 (Kalman's converges to the mean of the measurements, which differs from d_0 per pixel by d_0's own noise:
    benchmarks/euroc_static.py). Bounds in ``DRIFT``; the motion's at about 1.5 times what the solve achieves."""
    min_stable, max_tile, max_pixel = DRIFT[fusion]
    seq = load_euroc(euroc_root)
    assert len(seq.left) == 40
    d, v, m = _run(seq, fusion=fusion)
    # Stable pixels: valid on every frame, with a real disparity (> 1 px) on the first.
    stable = v.all(0) & (d[0] > 1.0)
    assert stable.float().mean() > min_stable
    ref, ok = _first_map_moved(d, v, m, seq)
    assert ok[-1].float().mean() > min_stable
    tile = torch.stack([tile_shift(d[t : t + 1], ref[t : t + 1], ok[t : t + 1]) for t in range(len(d))])
    assert tile.max() < max_tile, f"{fusion}: a tile's median drift reached {tile.max():.4f} px"
    if max_pixel is not None:
        pixel = torch.stack([(d[t] - ref[t]).abs()[ok[t]].median() for t in range(len(d))])
        assert pixel.max() < max_pixel, f"median |d_t - W_t(d_0)| reached {pixel.max():.4f} px"
    # The ground truth moves < 0.6 mm and a few hundredths of a degree per frame; the estimate must agree (an
    # estimate frozen at the identity misses the rotation by several times the bound).
    gt = torch.linalg.inv(seq.poses[1:]) @ seq.poses[:-1]
    assert translation_error(m[1:], gt).max() < 7e-4
    assert rotation_error_deg(m[1:], gt).max() < 0.035
    assert m[1:, :3, 3].norm(dim=-1).max() < 6e-4


def test_kalman_mode_converges_on_a_still_camera(euroc_root):
    """Kalman fusion averages the keyframes' measurements: against the per-pixel mean of per-frame stereo (the best
    reference a still scene gives) its error must not grow after frame 0 and must end well below the first map's,
    and the map must not be shifted from that mean (the loop adds no bias of its own). Bounds from what the loop
    achieves on the clip: the last error at 0.6 times the first (about 1.2 times the measured ratio), the median
    signed difference within 0.04 px (about 1.3 times the largest measured), the share a few points below."""
    from egorefine.stereo import match_stereo

    seq = load_euroc(euroc_root)
    K, b = seq.K[None], torch.tensor([seq.baseline])
    stereo = [match_stereo(seq.left[t : t + 1], seq.right[t : t + 1], 64) for t in range(len(seq.left))]
    sd, sv = torch.cat([o.disparity for o in stereo]), torch.cat([o.valid for o in stereo])
    reference = (sd * sv).sum(0) / sv.sum(0).clamp(min=1)
    refiner = EgoMotionRefiner(max_disparity=64, verify_every=5, fusion="kalman")
    state, disparity, valid = None, [], []
    for t in range(len(seq.left)):
        out, state = refiner(seq.left[t : t + 1], seq.right[t : t + 1], K, b, state)
        disparity.append(out.disparity)
        valid.append(out.valid)
    d, v = torch.cat(disparity), torch.cat(valid)
    ok = v.all(0) & (d[0] > 1.0) & (sv.float().mean(0) >= 0.5)
    assert ok.float().mean() > 0.65
    error = torch.stack([(d[t] - reference).abs()[ok].median() for t in range(len(d))])
    assert (error - error[0]).max() < 0.01, f"error against the mean map grew by {(error - error[0]).max():.3f} px"
    assert error[-1] < 0.6 * error[0], f"{error[0]:.3f} -> {error[-1]:.3f} px"
    bias = torch.stack([(d[t] - reference)[ok].median() for t in range(len(d))])
    assert bias.abs().max() < 0.04, f"median d_t - mean map reached {bias.abs().max():.3f} px"
