"""The refiner on real stereo video: the EuRoC V1_01 clip, where the vehicle is almost still."""

from __future__ import annotations

import torch

from egorefine.data import load_euroc
from egorefine.metrics import rotation_error_deg, translation_error
from egorefine.refine import EgoMotionRefiner


def test_static_camera_does_not_drift(euroc_root):
    seq = load_euroc(euroc_root)
    assert len(seq.left) == 40
    K, b = seq.K[None], torch.tensor([seq.baseline])
    refiner = EgoMotionRefiner(max_disparity=64, verify_every=5)  # defaults: paper fusion, exact motion
    state, disparity, valid, motion = None, [], [], []
    for t in range(len(seq.left)):
        out, state = refiner(seq.left[t : t + 1], seq.right[t : t + 1], K, b, state)
        disparity.append(out.disparity)
        valid.append(out.valid)
        motion.append(out.motion)
        assert out.motion_ok.all() and torch.isfinite(out.disparity).all()
    d, v, m = torch.cat(disparity), torch.cat(valid), torch.cat(motion)
    # Stable pixels: valid on every frame, with a real disparity (> 1 px) on the first.
    stable = v.all(0) & (d[0] > 1.0)
    assert stable.float().mean() > 0.5
    drift = torch.stack([(d[t] - d[0]).abs()[stable].median() for t in range(len(d))])
    assert drift.max() < 0.1, f"median |d_t - d_0| reached {drift.max():.3f} px"
    # The ground truth moves < 0.6 mm and a few hundredths of a degree per frame; the estimate must agree.
    gt = torch.linalg.inv(seq.poses[1:]) @ seq.poses[:-1]
    assert translation_error(m[1:], gt).max() < 2e-3
    assert rotation_error_deg(m[1:], gt).max() < 0.1
    assert m[1:, :3, 3].norm(dim=-1).max() < 2e-3


def test_kalman_mode_converges_on_a_still_camera(euroc_root):
    """Kalman fusion averages the keyframes' measurements: against the per-pixel mean of per-frame stereo (the best
    reference a still scene gives) its error must not grow after frame 0 and must end well below the first map's."""
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
    assert ok.float().mean() > 0.3
    error = torch.stack([(d[t] - reference).abs()[ok].median() for t in range(len(d))])
    assert (error - error[0]).max() < 0.01, f"error against the mean map grew by {(error - error[0]).max():.3f} px"
    assert error[-1] < 0.7 * error[0], f"{error[0]:.3f} -> {error[-1]:.3f} px"
