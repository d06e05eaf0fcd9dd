"""The refiner's status flags and its recovery from frames the method does not expect (issue 20): swapped cameras,
an occluder, black and noise frames."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from egorefine.data import render_sequence
from egorefine.refine import EgoMotionRefiner, Status
from egorefine.refine.health import disagreeing_regions, exposure_jumped, stereo_failed, tracking_collapsed
from egorefine.stereo import match_stereo

T, V, MAXD = 22, 5, 24


def test_tracking_collapsed():
    before = torch.tensor([300, 300, 10])
    after = torch.tensor([200, 40, 0])
    assert tracking_collapsed(before, after).tolist() == [False, True, False]  # too few tracks to judge the last


def test_exposure_jumped():
    img = torch.full((3, 1, 8, 8), 0.4)
    assert exposure_jumped(img, img * torch.tensor([1.1, 1.5, 0.5])[:, None, None, None]).tolist() == [False, True,
                                                                                                         True]


def test_stereo_failed():
    pred = torch.ones(2, 1, 4, 4, dtype=torch.bool)
    meas = pred.clone()
    meas[1, :, :3] = False  # a quarter left
    assert stereo_failed(meas, pred).tolist() == [False, True]


def test_disagreeing_regions_need_support_and_a_majority():
    e = torch.full((1, 1, 16, 16), 5.0)
    s = e.clone()
    s[..., :8, :8] = 7.0  # tile (0, 0): all off
    s[..., :8, 8:12] = 7.0  # tile (0, 1): half off (not a majority)
    ok = torch.ones_like(e, dtype=torch.bool)
    sparse = ok.clone()
    sparse[..., 8:, :8] = False
    sparse[..., 8, 0] = True  # tile (1, 0): one pixel of support
    s[..., 8, 0] = 9.0
    region = disagreeing_regions(e, ok, s, sparse)[0, 0, ::8, ::8]
    assert region.tolist() == [[True, False], [False, False]]


def _scenario(kind: str, seq):
    left, right, truth, occ = seq.left.clone(), seq.right.clone(), seq.disparity.clone(), seq.occluded.clone()
    g = torch.Generator().manual_seed(3)
    H, W = left.shape[-2:]
    if kind == "swap":  # the cables swapped for five frames: no truth there
        bad = slice(8, 13)
        left[bad], right[bad] = seq.right[bad].clone(), seq.left[bad].clone()
        occ[bad] = True
    elif kind == "occluder":  # a textured plane 12 px away covers the left third from frame 10 on
        d, w3 = 12, W // 3
        tex = F.avg_pool2d(torch.rand(1, 1, H, W, generator=g) * 0.6 + 0.2, 3, 1, 1)[0]
        left[10:, :, :, :w3] = tex[:, :, :w3]
        right[10:, :, :, : w3 - d] = tex[:, :, d:w3]
        truth[10:, :, :, :w3] = float(d)
        occ[10:, :, :, :w3] = False
        occ[10:, :, :, :d] = True
        bad = slice(10, 11)
    else:  # two black or two noise frames
        bad = slice(10, 12)
        if kind == "black":
            left[bad], right[bad] = 0.0, 0.0
        else:
            left[bad] = torch.rand(left[bad].shape, generator=g)
            right[bad] = torch.rand(right[bad].shape, generator=g)
        occ[bad] = True
    return left, right, truth, occ, bad


def _epe(d, v, truth, ok) -> float:
    m = v & ok
    return float((d - truth).abs()[m].mean()) if bool(m.any()) else float("nan")


def _run(fusion, left, right, K, b):
    refiner = EgoMotionRefiner(max_disparity=MAXD, verify_every=V, fusion=fusion)
    state, outs = None, []
    for t in range(T):
        out, state = refiner(left[t : t + 1], right[t : t + 1], K, b, state)
        outs.append(out)
    return outs


@pytest.fixture(scope="module")
def sequence():
    return render_sequence(num_frames=T, height=96, width=128, seed=11)


@pytest.mark.parametrize("fusion", ["paper", "kalman"])
@pytest.mark.parametrize(
    ("kind", "expected"),
    [
        ("swap", {10: Status.MEASUREMENT_REJECTED}),
        ("occluder", {10: Status.PREDICTION_RESET}),
        ("black", {10: Status.MOTION_FAILED}),
        ("noise", {10: Status.MOTION_FAILED}),
    ],
)
def test_recovers_within_verify_every(sequence, fusion, kind, expected):
    """From the first verification after the disturbance on, the error is within 1.5x of the larger of per-frame
    stereo's and the undisturbed run's (paper mode's own error grows between verifications even undisturbed), and
    the frame that caused it carries its flag."""
    K, b = sequence.K[None], torch.tensor([sequence.baseline])
    left, right, truth, occ, bad = _scenario(kind, sequence)
    ok = (truth > 0) & ~occ
    clean = _run(fusion, sequence.left, sequence.right, K, b)
    outs = _run(fusion, left, right, K, b)
    for t, bit in expected.items():
        assert int(outs[t].status[0]) & int(bit), f"frame {t}: status {Status(int(outs[t].status[0]))!r}"
    checked = [t for t in range(bad.stop, T) if t % V == 0]
    assert checked
    for t in checked:
        stereo = match_stereo(left[t : t + 1], right[t : t + 1], MAXD)
        reference = max(_epe(stereo.disparity[0], stereo.valid[0], truth[t], ok[t]),
                        _epe(clean[t].disparity[0], clean[t].valid[0], truth[t], ok[t]))
        got = _epe(outs[t].disparity[0], outs[t].valid[0], truth[t], ok[t])
        assert got <= 1.5 * reference, f"frame {t}: EPE {got:.3f} px against {reference:.3f}"


def test_ordinary_frames_raise_no_flag_but_resets(sequence):
    """On an undisturbed sequence nothing but an occasional region reset is flagged."""
    K, b = sequence.K[None], torch.tensor([sequence.baseline])
    for fusion in ("paper", "kalman"):
        for out in _run(fusion, sequence.left, sequence.right, K, b):
            assert int(out.status[0]) & ~int(Status.PREDICTION_RESET) == 0


@pytest.mark.parametrize("shape", [(2, 1, 37, 53), (1, 1, 24, 40), (3, 1, 100, 7), (1, 1, 300, 301)])
def test_disagreeing_regions_compiled_and_torch_agree(shape, monkeypatch):
    """The compiled pass and the torch path decide alike, tiles cut by the borders included (the last shape is
    split into bands of tile rows). Bit for bit: both count 0/1 pixels exactly and divide in float32."""
    from egorefine.core import dispatch

    g = torch.Generator().manual_seed(sum(shape))
    e = torch.rand(shape, generator=g) * 3
    s = e + (torch.rand(shape, generator=g) > 0.4).float() * 2
    ev, sv = torch.rand(shape, generator=g) > 0.3, torch.rand(shape, generator=g) > 0.2
    compiled = disagreeing_regions(e, ev, s, sv)
    monkeypatch.setattr(dispatch, "ENABLED", False)
    reference = disagreeing_regions(e, ev, s, sv)
    assert compiled.any() and not compiled.all()
    assert torch.equal(compiled, reference)


@pytest.mark.parametrize("shape", [(4, 1, 12, 17), (4, 1, 260, 270)])  # the second: bands of pixels on threads
def test_overrule_compiled_and_torch_agree(shape, monkeypatch):
    """The recovery rules compiled (CPU, no gradient) and in torch give the same maps, for every combination of
    an item's keep and restart."""
    from egorefine.core import dispatch
    from egorefine.refine._steps import _overrule
    from egorefine.refine.predict import Prediction
    from egorefine.stereo import StereoOutput

    g = torch.Generator().manual_seed(5)

    def maps():
        return (torch.rand(shape, generator=g) * 9, torch.rand(shape, generator=g),
                torch.rand(shape, generator=g) > 0.3, torch.randint(0, 3, shape, generator=g).float())

    corrected = maps()
    p, m = maps(), maps()
    pred = Prediction(p[0], p[1], ~p[2], p[2], torch.zeros(shape))
    meas = StereoOutput(m[0], m[2], m[1])
    keep, restart = torch.tensor([False, True, False, True]), torch.tensor([False, False, True, True])
    regions = torch.rand(shape, generator=g) > 0.5
    fast = _overrule(corrected, pred, meas, keep, restart, regions)
    mine = tuple(t.clone() for t in corrected)
    in_place = _overrule(mine, pred, meas, keep, restart, regions, owned=True)
    assert all(a is b for a, b in zip(in_place, mine, strict=True))  # written in place: the same tensors back
    monkeypatch.setattr(dispatch, "ENABLED", False)
    reference = _overrule(corrected, pred, meas, keep, restart, regions)
    for a, b, c in zip(fast, reference, in_place, strict=True):
        assert torch.equal(a, b) and torch.equal(c, b)
    assert torch.equal(fast[0][1], pred.disparity[1]) and torch.equal(fast[0][2], meas.disparity[2])
    assert torch.equal(fast[0][3], meas.disparity[3]) and (fast[3][1:] == 0).all()
    take = regions[0]
    assert torch.equal(fast[0][0][take], meas.disparity[0][take]) and (fast[3][0][take] == 0).all()
    assert torch.equal(fast[0][0][~take], corrected[0][0][~take])


def test_owned_maps_share_no_memory_with_the_others():
    from egorefine.refine._steps import _owned

    a, b = torch.zeros(2, 3), torch.ones(2, 3)
    other = torch.zeros(4)
    assert _owned((a, b), other, (torch.ones(1), 3), None)
    assert not _owned((a, b), (other, a[1]))  # a view of a map, inside a tuple (a state's pyramid)
    assert not _owned((a, a.view(3, 2)))  # two maps on one memory
    assert not _owned((a, b), 1, b.view(-1))
