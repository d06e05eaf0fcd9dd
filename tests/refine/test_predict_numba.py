"""The compiled CPU path of the hard splat and of crack closing (egorefine.refine._splat_numba, _predict_numba)
against the torch path, which stays the reference (GPU, float64, autograd)."""

from __future__ import annotations

import pytest
import torch

from egorefine.core import _jit
from egorefine.data import render_sequence
from egorefine.refine import _predict_numba, _splat_numba, close_cracks, predict_disparity
from egorefine.refine.cracks import finish_prediction
from egorefine.refine.predict import Prediction

needs_numba = pytest.mark.skipif(not _predict_numba.AVAILABLE, reason="numba not installed")


@pytest.fixture(scope="module", params=["paper", "kitti"])
def scene(request):
    """A rendered frame and the motion of four frame steps from it (a keyframe predicted four frames ahead)."""
    seq = render_sequence(num_frames=5, height=120, width=160, preset=request.param, seed=2)
    motion = torch.eye(4)
    for m in seq.motions[1:5]:
        motion = m @ motion
    g = torch.Generator().manual_seed(5)
    var = 0.05 + 0.1 * torch.rand(1, 1, 120, 160, generator=g)
    valid = torch.rand(1, 1, 120, 160, generator=g) > 0.02
    return seq.disparity[:1], motion[None], seq.K[None], torch.tensor([seq.baseline]), var, valid


def _both(monkeypatch, fn):
    compiled = fn()
    monkeypatch.setattr(_jit, "AVAILABLE", False)
    reference = fn()
    monkeypatch.setattr(_jit, "AVAILABLE", True)
    return compiled, reference


def _assert_close_predictions(a, b, share=1e-3):
    # Same float32 formulas; torch's vectorised kernels fuse some multiply-adds, so values agree to rounding, and a
    # rounding can tip a discrete decision (which source pixel a target falls in) at a handful of pixels.
    assert (a.valid != b.valid).float().mean() <= share
    both = a.valid & b.valid
    diff = (a.disparity - b.disparity).abs()[both]
    assert (diff > 1e-3).float().mean() <= share and diff.max() < 0.1
    var_diff = (a.variance - b.variance).abs()[both]
    assert (var_diff > 1e-4).float().mean() <= share
    holes = ~a.valid & ~b.valid
    assert (a.variance[holes] == b.variance[holes]).all() and (a.confidence[holes] == 0).all()
    assert torch.isfinite(a.disparity).all() and torch.isfinite(a.variance).all()


@needs_numba
@pytest.mark.parametrize(
    "kwargs",
    [{}, {"fill_holes": False}, {"refine_iterations": 2}, {"surface_tolerance": 0.3, "process_noise": 0.05}],
)
def test_compiled_splat_equals_torch_path(scene, monkeypatch, kwargs):
    d, motion, K, b, var, valid = scene
    a, r = _both(monkeypatch, lambda: predict_disparity(d, motion, K, b, variance=var, valid=valid, **kwargs))
    _assert_close_predictions(a, r)
    assert a.valid.float().mean() > 0.7  # a real prediction (4 steps forward: magnified ground cracks), not empty


@needs_numba
def test_compiled_splat_without_variance(scene, monkeypatch):
    d, motion, K, b, _, _ = scene
    a, r = _both(monkeypatch, lambda: predict_disparity(d, motion, K, b, process_noise=0.02))
    _assert_close_predictions(a, r)
    assert (a.variance[a.valid] == 0.02).all()


@needs_numba
def test_compiled_splat_fills_rows_without_a_landed_pixel(scene, monkeypatch):
    # the camera moves down, the scene's median depth 20 px up: the top rows see nothing of the old frame; the
    # background rule fills a row without a landed pixel with the image's smallest landed value (the compiled splat
    # fills such rows after all bands)
    d, _, K, b, var, valid = scene
    motion = torch.eye(4)[None]
    motion[0, 1, 3] = 20 * b[0] / d.median()  # Y = 20 Z / f, Z = f B / d
    a, r = _both(monkeypatch, lambda: predict_disparity(d, motion, K, b, variance=var, valid=valid))
    _assert_close_predictions(a, r)
    empty = ~a.valid[0, 0].any(1)
    assert 5 < int(empty.sum()) < 60
    assert (a.disparity[0, 0][empty] == a.disparity[a.valid].min()).all()
    assert (a.variance[0, 0][empty] == 100.0).all() and (a.confidence[0, 0][empty] == 0).all()


@needs_numba
def test_compiled_splat_is_independent_of_threads_batch_and_workspace(scene):
    d, motion, K, b, var, valid = scene
    ref = predict_disparity(d, motion, K, b, variance=var, valid=valid)
    torch.set_num_threads(3)  # more bands than rows per band: threads split the rows differently
    try:
        three = predict_disparity(d, motion, K, b, variance=var, valid=valid)
    finally:
        torch.set_num_threads(2)
    # a second item of another size in between (the kept workspace is resized), then a batch of two
    predict_disparity(d[..., :60, :90].contiguous(), motion, K, b)
    d2 = torch.cat([d.flip(-1), d])
    pair = predict_disparity(d2, motion.expand(2, 4, 4), K.expand(2, 3, 3), b.expand(2),
                             variance=torch.cat([var, var]), valid=torch.cat([valid, valid]))
    for x, y, z in zip(ref, three, pair, strict=True):
        assert torch.equal(x, y) and torch.equal(x, z[1:])


@needs_numba
def test_compiled_splat_z_buffer_across_bands(scene):
    """Points that move into another band's rows (a 20 px vertical shift: most of them, with bands of a few rows):
    one thread (one band) and four give the same maps, bit for bit (the same kernels on one machine: only the split
    of the rows differs)."""
    d, _, K, b, var, valid = scene
    motion = torch.eye(4)[None]
    motion[0, 1, 3] = -20 * b[0] / d.median()
    outs = []
    for threads in (1, 4):
        torch.set_num_threads(threads)
        try:
            outs.append(predict_disparity(d, motion, K, b, variance=var, valid=valid))
        finally:
            torch.set_num_threads(2)
    assert outs[0].valid.float().mean() > 0.25  # a real prediction (the shifted-out rows are holes)
    for x, y in zip(*outs, strict=True):
        assert torch.equal(x, y)


@needs_numba
def test_empty_source_gives_flagged_holes_without_nan():
    d = torch.full((1, 1, 20, 30), -1.0)  # nothing valid
    K = torch.tensor([[[40.0, 0, 15], [0, 40.0, 10], [0, 0, 1]]])
    pred = predict_disparity(d, torch.eye(4)[None], K, torch.tensor([0.1]))
    assert not pred.valid.any() and (pred.disparity == 0).all() and (pred.confidence == 0).all()
    assert (pred.variance == 100.0).all()


def test_torch_path_where_the_compiled_one_does_not_apply(scene, monkeypatch):
    d, motion, K, b, var, valid = scene

    def refuse(*args, **kwargs):
        raise AssertionError("the compiled path ran")

    monkeypatch.setattr(_splat_numba, "hard_splat", refuse)
    monkeypatch.setattr(_jit, "AVAILABLE", True)
    predict_disparity(d.double(), motion, K, b)  # float64
    predict_disparity(d.clone().requires_grad_(True), motion, K, b)  # autograd
    predict_disparity(d, motion, K, b, mode="soft")  # soft splatting
    predict_disparity(d, motion, K, b, refine_iterations=0)  # the coverage splat
    monkeypatch.setattr(_jit, "AVAILABLE", False)
    predict_disparity(d, motion, K, b)  # numba missing
    monkeypatch.setattr(_jit, "AVAILABLE", True)
    with pytest.raises(AssertionError, match="compiled path"):
        predict_disparity(d, motion, K, b)


@needs_numba
@pytest.mark.parametrize("iterations", [1, 2, 3])  # (the compiled steps after the first skip the failed holes)
def test_compiled_crack_closing_equals_torch_path(scene, monkeypatch, iterations):
    d, motion, K, b, var, valid = scene
    pred = predict_disparity(d, motion, K, b, variance=var, valid=valid)
    a, r = _both(monkeypatch, lambda: close_cracks(pred, d, var, valid, motion, K, b, process_noise=0.02,
                                                   iterations=iterations))
    assert torch.equal(a.valid, r.valid)
    assert (a.valid & ~pred.valid).any()  # it closed some
    torch.testing.assert_close(a.disparity, r.disparity, atol=1e-4, rtol=0)
    torch.testing.assert_close(a.variance, r.variance, atol=1e-4, rtol=1e-5)
    # confidence = 1 / (1 + variance) moves by at most as much as the variance does: the variance's bound
    torch.testing.assert_close(a.confidence, r.confidence, atol=1e-4, rtol=0)
    assert torch.equal(a.hole, pred.hole)


@needs_numba
@pytest.mark.parametrize("fill", [True, False])
def test_compiled_finish_equals_torch_path(scene, monkeypatch, fill):
    # the refiner's step after the splat: cracks closed (or not), values outside the range made not valid; the
    # compiled path works in place on the prediction it is given
    d, motion, K, b, var, valid = scene
    pred = predict_disparity(d, motion, K, b, variance=var, valid=valid)
    low, high = pred.disparity[pred.valid].quantile(torch.tensor([0.1, 0.9])).tolist()  # cuts both ends
    assert ((pred.disparity < low) & pred.valid).any() and ((pred.disparity >= high) & pred.valid).any()

    def run():
        fresh = Prediction(*(t.clone() for t in pred))
        return fresh, finish_prediction(fresh, d, var, valid, motion, K, b, 0.02, fill, (low, high))

    (given, a), (_, r) = _both(monkeypatch, run)
    assert a.disparity is given.disparity and a.valid is given.valid  # in place
    assert torch.equal(a.valid, r.valid)
    assert not ((a.disparity < low) | (a.disparity >= high))[a.valid].any()
    assert (a.confidence[~a.valid] == 0).all()
    closed = a.valid & ~pred.valid
    assert bool(closed.any()) == fill
    torch.testing.assert_close(a.disparity, r.disparity, atol=1e-4, rtol=0)
    torch.testing.assert_close(a.variance, r.variance, atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(a.confidence, r.confidence, atol=1e-4, rtol=0)  # 1 / (1 + variance): as above


@needs_numba
@pytest.mark.parametrize("fill", [True, False])
@pytest.mark.parametrize("empty_rows", [False, True])
def test_fused_finish_equals_the_two_steps(scene, fill, empty_rows):
    # predict_finished runs the splat and the step after it in one pass on the compiled path: the same kernels'
    # formulas on the same values as the two separate calls, so the same bits (one machine, one build). With empty
    # rows (no landed pixel: filled from the whole image after the pass, then finished) too.
    from egorefine.refine.cracks import predict_finished

    d, motion, K, b, var, valid = scene
    if empty_rows:  # source rows not splatted (negative: no point) but valid for the look-ups: their target rows
        d = d.clone()  # stay empty in the splat, and the step after it finds values there
        d[..., 40:52, :] = -d[..., 40:52, :]
    pred = predict_disparity(d, motion, K, b, variance=var, valid=valid, process_noise=0.02)
    low, high = pred.disparity[pred.valid].quantile(torch.tensor([0.1, 0.9])).tolist()
    if empty_rows:
        assert (~pred.valid).all(-1).any()  # some rows have no landed pixel
    two = finish_prediction(pred, d, var, valid, motion, K, b, 0.02, fill, (low, high))
    one = predict_finished(d, motion, K, b, var, valid, "hard", 0.02, fill, (low, high))
    for name in ("disparity", "variance", "valid", "confidence"):
        assert torch.equal(getattr(one, name), getattr(two, name)), name
    assert torch.equal(one.hole, pred.hole)  # the splat's own holes


@needs_numba
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_compiled_splat_rejects_non_finite_disparity(scene, bad):
    # The compiled path tests finiteness inside its kernels (no torch pass over the map): the same typed error.
    from egorefine.core import ValueRangeError

    d, motion, K, b, var, valid = scene
    d2 = torch.cat([d, d.clone()])
    d2[1, 0, 60, 80] = bad  # one pixel of the second item
    with pytest.raises(ValueRangeError, match="disparity"):
        predict_disparity(d2, motion.expand(2, 4, 4), K.expand(2, 3, 3), b.expand(2))


@needs_numba
@pytest.mark.parametrize("kernel_size", [1, 3, 5])
def test_compiled_edge_variance_equals_torch_path(scene, monkeypatch, kernel_size):
    # Maxima and minima of the same float32 values: bit for bit, borders (the window clipped) and invalid pixels too.
    from egorefine.refine.correct import edge_variance

    d, *_, valid = scene
    d2, v2 = torch.cat([d, d.flip(-1)]), torch.cat([valid, ~valid])
    a, r = _both(monkeypatch, lambda: edge_variance(d2, v2, kernel_size))
    assert torch.equal(a, r)
    assert (a[~v2] == 0).all() and (a.amax() > 0 if kernel_size > 1 else a.amax() == 0)
