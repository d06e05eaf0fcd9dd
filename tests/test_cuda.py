"""The CUDA path against the CPU path, stage by stage and for the whole loop (skipped without a GPU).

On the CPU the matcher, SGM and the prediction run compiled (numba); on a GPU the same calls take the
torch paths. These tests render on the CPU, run each stage on both devices and compare, and score the
loop on the GPU against the rendered truth.
"""

from __future__ import annotations

import pytest
import torch

from egorefine.core import _graphs
from egorefine.data import render_sequence
from egorefine.geometry import make_intrinsics, project, transform_points, twist_to_motion, unproject
from egorefine.metrics import epe, translation_error
from egorefine.motion import solve_ego_motion
from egorefine.refine import EgoMotionRefiner, TrackingOptions, predict_disparity
from egorefine.stereo import match_stereo

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
CUDA = torch.device("cuda")
SMALL = dict(max_disparity=24, tracking=TrackingOptions(max_features=150, min_tracks=60))


@pytest.fixture(scope="module")
def seq():
    return render_sequence(num_frames=7, height=120, width=160, seed=3)


def _agree(a_valid, b_valid, a, b, share=1e-3, tol=1e-3):
    """Validity decisions differ on at most ``share`` of the pixels; values on both-valid pixels within ``tol``."""
    a_valid, b_valid, a, b = (x.cpu() for x in (a_valid, b_valid, a, b))
    assert (a_valid != b_valid).float().mean() <= share
    both = a_valid & b_valid
    assert both.float().mean() > 0.5
    assert ((a - b).abs()[both] > tol).float().mean() <= share


@pytest.mark.parametrize("kw", [{}, {"cost": "census", "aggregation": "sgm", "block_size": 5}, {"cost": "zncc"},
                                {"cost": "census", "aggregation": "sgm", "block_size": 5, "sgm_paths": 3}])
def test_stereo_on_cuda_matches_cpu(seq, kw):
    left, right = seq.left[:2], seq.right[:2]
    cpu = match_stereo(left, right, 24, **kw)
    gpu = match_stereo(left.to(CUDA), right.to(CUDA), 24, **kw)
    assert gpu.disparity.device.type == "cuda" and gpu.valid.device.type == "cuda"
    _agree(cpu.valid, gpu.valid, cpu.disparity, gpu.disparity)
    assert torch.isfinite(gpu.variance).all()


def test_three_path_sgm_on_cuda_matches_cpu_across_stripes():
    # 260 rows: two stripes, the second's top-down path started above it, on both devices
    tall = render_sequence(num_frames=1, height=260, width=200, seed=4)
    kw = {"cost": "census", "aggregation": "sgm", "block_size": 5, "sgm_paths": 3}
    cpu = match_stereo(tall.left, tall.right, 32, **kw)
    gpu = match_stereo(tall.left.to(CUDA), tall.right.to(CUDA), 32, **kw)
    _agree(cpu.valid, gpu.valid, cpu.disparity, gpu.disparity)


def test_prediction_on_cuda_matches_cpu(seq):
    motion = seq.motions[2] @ seq.motions[1]  # two frame steps ahead
    args = (seq.disparity[:1], motion[None], seq.K[None], torch.tensor([seq.baseline]))
    cpu = predict_disparity(*args)
    gpu = predict_disparity(*(a.to(CUDA) for a in args))
    _agree(cpu.valid, gpu.valid, cpu.disparity, gpu.disparity)
    # and against the truth two frames on
    err = (gpu.disparity.cpu() - seq.disparity[2:3]).abs()[gpu.valid.cpu()]
    assert err.median() < 0.05


# the second set runs the residual search (torch path on the GPU) and the hole measurement (the whole frame there)
@pytest.mark.parametrize("extra", [{}, {"local_search": 2, "measure_holes": True}])
def test_refiner_on_cuda_tracks_truth_like_cpu(seq, extra):
    runs = {}
    for device in ("cpu", "cuda"):
        refiner = EgoMotionRefiner(verify_every=3, fusion="kalman", **SMALL, **extra)
        K, b = seq.K[None].to(device), torch.tensor([seq.baseline], device=device)
        state, outs = None, []
        for t in range(len(seq.left)):
            out, state = refiner(seq.left[t : t + 1].to(device), seq.right[t : t + 1].to(device), K, b, state)
            outs.append(out)
        runs[device] = outs
    for t, (c, g) in enumerate(zip(runs["cpu"], runs["cuda"], strict=True)):
        assert g.disparity.device.type == "cuda" and g.stereo_ran == c.stereo_ran
        assert torch.isfinite(g.disparity).all() and torch.isfinite(g.variance).all()
        assert bool(g.motion_ok.all())
        truth = seq.disparity[t : t + 1]
        e_cpu = epe(c.disparity, truth, c.valid)
        e_gpu = epe(g.disparity.cpu(), truth, g.valid.cpu())
        # (the CPU path's own error on these frames: 0.19-0.26 px; a broken GPU stage lands far off both bounds)
        assert e_gpu < 0.3 and abs(e_gpu - e_cpu) < 0.02, (t, e_cpu, e_gpu)
        if t:
            assert translation_error(g.motion.cpu(), seq.motions[t][None]).max() < 0.005  # metres, ~0.1 m steps
            assert (g.motion.cpu() - c.motion).abs().max() < 1e-3


def test_gradients_on_cuda(seq):
    left = seq.left[:1].to(CUDA).requires_grad_(True)
    out = match_stereo(left, seq.right[:1].to(CUDA), 24, differentiable=True)
    out.disparity[out.valid].sum().backward()
    assert left.grad is not None and torch.isfinite(left.grad).all() and left.grad.abs().sum() > 0
    disparity = seq.disparity[:1].to(CUDA).requires_grad_(True)
    pred = predict_disparity(disparity, seq.motions[1][None].to(CUDA), seq.K[None].to(CUDA),
                             torch.tensor([seq.baseline], device=CUDA), mode="soft")
    pred.disparity.sum().backward()
    assert torch.isfinite(disparity.grad).all() and disparity.grad.abs().sum() > 0


def _tracks(twist: torch.Tensor, num: int = 300, seed: int = 0):
    """Points at 2-15 m seen in frame t-1, moved by ``twist_to_motion(twist)``, projected, with 0.3 px noise."""
    B = twist.shape[0]
    gen = torch.Generator().manual_seed(seed)
    K = make_intrinsics(400.0, 319.5, 239.5, B)
    pts = torch.rand(B, num, 2, generator=gen) * torch.tensor([600.0, 440.0]) + 20.0
    Z = torch.rand(B, num, generator=gen) * 13.0 + 2.0
    nxt = project(transform_points(twist_to_motion(twist), unproject(pts, Z, K)), K)
    nxt = nxt + 0.3 * torch.randn(B, num, 2, generator=gen)
    baseline = torch.full((B,), 0.1)
    return pts, nxt, 400.0 * 0.1 / Z, K, baseline


def test_solve_graph_replay_equals_eager(monkeypatch):
    # the LM of the exact solve is replayed from a CUDA graph for inference: the same kernels, so the same bits
    twist = torch.tensor([[0.02, -0.01, 0.1, 0.005, -0.01, 0.003], [0.0, 0.03, 0.08, -0.004, 0.002, 0.01]])
    for seed in (0, 1, 2):  # the first call records, the next ones replay on other values
        args = [a.to(CUDA) for a in _tracks(twist, seed=seed)]
        graphed = solve_ego_motion(*args)
        monkeypatch.setattr(_graphs, "ENABLED", False)
        eager = solve_ego_motion(*args)
        monkeypatch.setattr(_graphs, "ENABLED", True)
        for a, b in zip(graphed, eager, strict=True):
            assert torch.equal(a, b)
        assert translation_error(graphed.motion.cpu(), twist_to_motion(twist)).max() < 0.005
    assert any(key[0][0] == "lm" and entry is not None for key, entry in _graphs._graphs.items()), "nothing replayed"


@pytest.mark.parametrize("paths", [4, 3])
def test_sgm_graph_replay_equals_eager(seq, monkeypatch, paths):
    # SGM's scanline recursion on CUDA is replayed from a CUDA graph for inference: bit for bit the eager result
    kw = {"cost": "zncc", "aggregation": "sgm", "block_size": 5, "sgm_paths": paths}
    for t in range(3):  # the first call records, the next ones replay on other frames
        left, right = seq.left[t : t + 1].to(CUDA), seq.right[t : t + 1].to(CUDA)
        graphed = match_stereo(left, right, 24, **kw)
        monkeypatch.setattr(_graphs, "ENABLED", False)
        eager = match_stereo(left, right, 24, **kw)
        monkeypatch.setattr(_graphs, "ENABLED", True)
        for a, b in zip(graphed, eager, strict=True):
            assert torch.equal(a, b)
        assert graphed.valid.float().mean() > 0.5
    assert any(key[0][0] == "sgm" and entry is not None for key, entry in _graphs._graphs.items()), "nothing replayed"


def test_prediction_graph_replay_equals_eager(seq, monkeypatch):
    # the hard splat on CUDA is replayed from a CUDA graph for inference: bit for bit the eager result
    K, b = seq.K[None].to(CUDA), torch.tensor([seq.baseline], device=CUDA)
    g = torch.Generator().manual_seed(3)
    var = (0.05 + 0.1 * torch.rand(1, 1, 120, 160, generator=g)).to(CUDA)
    for t in range(3):  # the first call records, the next ones replay on other frames and motions
        args = (seq.disparity[t : t + 1].to(CUDA), seq.motions[t + 1][None].to(CUDA), K, b)
        graphed = predict_disparity(*args, variance=var)
        monkeypatch.setattr(_graphs, "ENABLED", False)
        eager = predict_disparity(*args, variance=var)
        monkeypatch.setattr(_graphs, "ENABLED", True)
        for a, e in zip(graphed, eager, strict=True):
            assert torch.equal(a, e)
        assert graphed.valid.float().mean() > 0.9
    assert any(key[0][0] == "predict" and entry is not None for key, entry in _graphs._graphs.items()), "not replayed"
