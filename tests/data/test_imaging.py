"""Realistic imaging in the renderer: the noise model, photometric differences, blur, texture families, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from egorefine.core import DTypeError, ValueRangeError
from egorefine.data import FAMILIES, IMAGING, PRESETS, Imaging, render_sequence
from egorefine.data._families import FAMILY_NAMES, family_tile
from egorefine.data._world import _build_scene, _surface_families, _trajectory

H, W = 96, 128
REFERENCE = Path(__file__).with_name("ideal_reference.npz")


def _render(imaging: str | Imaging, **kw) -> object:
    args = {"num_frames": 2, "height": H, "width": W, "seed": 3, "antialias": False, **kw}
    return render_sequence(imaging=imaging, **args)


def _warp_right(seq) -> tuple[torch.Tensor, torch.Tensor]:
    """Right images sampled at (x - d, y), and a mask of non-occluded pixels away from depth edges."""
    T, _, h, w = seq.left.shape
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    xr = xs - seq.disparity[:, 0]
    grid = torch.stack([xr / (w - 1) * 2 - 1, (ys / (h - 1) * 2 - 1).expand_as(xr)], -1)
    warped = F.grid_sample(seq.right, grid, mode="bilinear", align_corners=True, padding_mode="border")
    d = seq.disparity
    smooth = (F.max_pool2d(d, 5, 1, 2) + F.max_pool2d(-d, 5, 1, 2)) < 0.05
    return warped, ~seq.occluded & smooth & (xr[:, None] > 2)


# ------------------------------------------------------------------------------------------------- ideal path


# The stored render was made on one CPU; a correct renderer on another must pass and a changed one must fail.
# Geometry (which face a ray hits, depth, occlusion) uses only correctly rounded float32 products, sums, quotients
# and comparisons of coefficients set up in float64, so it comes out the same on every IEEE CPU. Shading does not:
# exp, rsqrt, log2, the small matmuls, short sums and the trilinear lookup round differently with another SIMD
# width or FMA (last bits), and at texel coordinates of several thousand one float32 step is ~5e-4 texel, so
# intensities move by many float32 steps of their own (6e-8 near 1.0). The bounds hold renders whose every
# shading value is jittered by a couple of dozen float32 steps (far beyond what vector and scalar kernels differ
# by): all but 1 % of the pixels within 5e-5, every pixel within 5e-4. Changing one texture constant by 1 % (the
# contrast, the squash, the mip prefilter) moves half the pixels or more by over 1e-4, the largest by ~1e-3: it fails.
REPRO_BULK, REPRO_MAX, REPRO_SHARE = 5e-5, 5e-4, 0.01


def _assert_reproduces(actual: torch.Tensor, expected: torch.Tensor, what: str, relative: bool = False) -> None:
    """Every element within REPRO_MAX, and all but REPRO_SHARE of them within REPRO_BULK (of |expected| if relative)."""
    err = (actual - expected).abs()
    if relative:
        err = err / expected.abs()
    share = float((err > REPRO_BULK).float().mean())
    assert float(err.max()) <= REPRO_MAX, f"{what}: largest difference {float(err.max()):.3g} > {REPRO_MAX:g}"
    assert share <= REPRO_SHARE, f"{what}: {share:.1%} of the elements differ by more than {REPRO_BULK:g}"


def test_ideal_reproduces_the_images_from_before_realistic_imaging() -> None:
    """The stored render was made by the renderer before imaging= existed (same cases, same seeds)."""
    ref = np.load(REFERENCE)
    cases = [("paper", "corridor", "forward"), ("paper", "hall", "shaky"), ("kitti", "street", "turn")]
    for preset, scene, motion in cases:
        s = render_sequence(num_frames=2, preset=preset, scene=scene, motion=motion, seed=5, height=24, width=40,
                            imaging="ideal")
        for name in ("left", "right"):
            _assert_reproduces(getattr(s, name), torch.from_numpy(ref[f"{preset}_{scene}_{name}"]), f"{scene} {name}")
        # Depth in metres (up to ~60 m on the KITTI rig, where one float32 step is 4e-6): the same bounds, relative
        # (geometry, so it comes out the same on every CPU; the bounds only spare a float64 set-up's last bit).
        _assert_reproduces(s.depth, torch.from_numpy(ref[f"{preset}_{scene}_depth"]), f"{scene} depth", relative=True)
        # Occlusion is geometry, so exact; besides, in these cases no pixel lies within many float32 steps of its
        # decision, so not even a last-bit change of the set-up could flip one.
        assert torch.equal(s.occluded, torch.from_numpy(ref[f"{preset}_{scene}_occluded"])), scene
        assert torch.equal(s.exposure, torch.ones(2, 2))  # ideal cameras: exactly one, by construction
    s = render_sequence(num_frames=1, height=24, width=32, seed=2, noise_std=0.02, imaging="ideal")
    _assert_reproduces(s.left, torch.from_numpy(ref["noisy_left"]), "noisy left")
    _assert_reproduces(s.right, torch.from_numpy(ref["noisy_right"]), "noisy right")


def test_ideal_preset_is_ideal_and_realistic_is_the_default() -> None:
    assert IMAGING["ideal"].is_ideal and not IMAGING["realistic"].is_ideal
    a = render_sequence(num_frames=1, height=24, width=32, seed=1)
    b = render_sequence(num_frames=1, height=24, width=32, seed=1, imaging="realistic")
    assert torch.equal(a.left, b.left) and torch.equal(a.right, b.right)
    assert 0.005 <= IMAGING["realistic"].noise <= 0.02 and IMAGING["realistic"].bits == 8


# --------------------------------------------------------------------------------------------------- sensor


@pytest.mark.parametrize("shot_share", [0.0, 0.7, 1.0])
def test_noise_follows_the_shot_plus_read_model(shot_share: float) -> None:
    noise = 0.02
    clean = _render(Imaging.preset("ideal", noise=0.0))
    noisy = _render(Imaging.preset("ideal", noise=noise, shot_share=shot_share))
    x, y = clean.left, noisy.left
    var = (1 - shot_share) * noise**2 + shot_share * noise**2 / 0.5 * x
    ok = (x > 0.08) & (x < 0.9)  # no clipping within 4 sigma
    z = ((y - x) / var.sqrt())[ok]
    assert 0.96 < z.std() < 1.04 and z.mean().abs() < 0.03
    # The measured std in a dark and a bright band matches the model there (shot noise grows with the signal).
    for lo, hi in ((0.1, 0.3), (0.6, 0.9)):
        band = (x > lo) & (x < hi)
        expected = var[band].mean().sqrt()
        assert (y - x)[band].std() == pytest.approx(float(expected), rel=0.06), (lo, hi)


def test_default_noise_is_about_one_percent_and_output_is_8_bit() -> None:
    seq = _render("realistic")
    no_noise = _render(Imaging.preset("realistic", noise=0.0))
    mid = (no_noise.left > 0.3) & (no_noise.left < 0.7)
    sigma = (seq.left - no_noise.left)[mid].std()
    assert 0.005 < sigma < 0.02
    for img in (seq.left, seq.right):
        assert torch.equal(img * 255, (img * 255).round())
        assert img.min() >= 0 and img.max() <= 1
    four = _render(Imaging.preset("realistic", bits=4))
    assert torch.unique(four.left).numel() <= 16
    floats = _render(Imaging.preset("realistic", bits=0))
    assert not torch.equal(floats.left * 255, (floats.left * 255).round())


# ----------------------------------------------------------------------------------------------- photometry


def test_left_and_right_gains_differ_as_drawn() -> None:
    gain = 0.1
    seq = _render(Imaging.preset("ideal", gain=gain))
    warped, ok = _warp_right(seq)
    ratio = (warped / seq.left)[ok]
    expected = seq.exposure[:, 1] / seq.exposure[:, 0]
    assert float(ratio.median()) == pytest.approx(float(expected[0]), abs=0.005)
    # The right-to-left ratio is exp(+-g) with g in [gain / 2, gain]; constant without exposure drift.
    log_ratio = expected.log().abs()
    assert ((log_ratio >= gain / 2 - 1e-6) & (log_ratio <= gain + 1e-6)).all()
    torch.testing.assert_close(seq.exposure[0], seq.exposure[1])
    ideal = _render("ideal")
    torch.testing.assert_close(seq.left, (ideal.left * seq.exposure[:, 0, None, None, None]).clamp(0, 1))


def test_vignetting_darkens_the_corners_and_gamma_bends_the_response() -> None:
    ideal = _render("ideal")
    vig = _render(Imaging.preset("ideal", vignetting=0.3))
    ratio = vig.left / ideal.left
    centre = ratio[..., H // 2 - 4 : H // 2 + 4, W // 2 - 4 : W // 2 + 4]
    assert (centre - 1).abs().max() < 0.01
    corners = torch.stack([ratio[..., :3, :3], ratio[..., :3, -3:], ratio[..., -3:, :3], ratio[..., -3:, -3:]])
    assert 0.6 < corners.mean() < 0.8
    assert not torch.allclose(vig.left, vig.right)  # each camera its own lens
    gam = _render(Imaging.preset("ideal", gamma=0.2))
    exponent = gam.left.log() / ideal.left.log()
    assert 0.8 <= exponent.mean() <= 1.2 and exponent.std() < 1e-3


def test_exposure_drifts_slowly_and_shows_in_the_images() -> None:
    seq = render_sequence(num_frames=30, height=12, width=16, antialias=False, seed=2,
                          imaging=Imaging.preset("ideal", exposure_drift=0.1))
    ideal = render_sequence(num_frames=30, height=12, width=16, antialias=False, seed=2, imaging="ideal")
    e = seq.exposure
    step = (e[1:] / e[:-1]).log().abs()
    assert step.max() < 0.02  # smooth: under 2 % from one frame to the next
    assert (e.max(0).values / e.min(0).values > 1.02).all()  # but it does drift over the sequence
    assert not torch.allclose(e[:, 0], e[:, 1])  # partly per camera
    measured = (seq.left / ideal.left).flatten(1).median(1).values
    torch.testing.assert_close(measured, e[:, 0], atol=1e-4, rtol=0)


def test_blur_softens_along_the_image_motion() -> None:
    def grads(img: torch.Tensor) -> tuple[float, float]:
        return float((img[..., :, 1:] - img[..., :, :-1]).abs().mean()), float(
            (img[..., 1:, :] - img[..., :-1, :]).abs().mean())

    sharp = _render("ideal", motion="lateral", num_frames=3)
    blurred = _render(Imaging.preset("ideal", motion_blur=1.0), motion="lateral", num_frames=3)
    gx0, gy0 = grads(sharp.left)
    gx1, gy1 = grads(blurred.left)
    # Sideways motion: horizontal detail is smeared, vertical detail much less.
    assert gx1 < 0.9 * gx0 and gx1 / gx0 < gy1 / gy0 - 0.05
    defocus = _render(Imaging.preset("ideal", defocus=1.5))
    gx2, gy2 = grads(defocus.left)
    gx_ref, gy_ref = grads(_render("ideal").left)
    assert gx2 < 0.8 * gx_ref and gy2 < 0.8 * gy_ref


def test_seeded_determinism() -> None:
    a, b = _render("realistic"), _render("realistic")
    for name in ("left", "right", "exposure"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    c = _render("realistic", seed=4)
    assert not torch.equal(a.left, c.left) and not torch.equal(a.exposure, c.exposure)


# --------------------------------------------------------------------------------------------------- scenes


def test_texture_families_have_their_character() -> None:
    def grad_energy(t: torch.Tensor) -> float:
        return float(((t.roll(1, 0) - t) ** 2 + (t.roll(1, 1) - t) ** 2).mean().sqrt())

    tiles = {name: family_tile(name) for name in FAMILY_NAMES[1:]}
    busy = grad_energy(tiles["grain"])
    for weak in ("painted", "sky", "plain"):
        assert grad_energy(tiles[weak]) < 0.15 * busy, weak
        assert tiles[weak].std() < 0.02, weak
    assert grad_energy(tiles["sky"]) < grad_energy(tiles["painted"])

    def periodic_share(profile: torch.Tensor, period: int) -> float:
        """Share of the profile's (non-DC) spectral energy at the harmonics of ``period`` texels."""
        spec = torch.fft.rfft(profile - profile.mean()).abs() ** 2
        harmonics = spec[profile.numel() // period :: profile.numel() // period]
        return float(harmonics.sum() / spec[1:].sum())

    assert periodic_share(tiles["brick"].mean(1), 16) > 0.9  # mortar courses every 16 texels (0.0625 m)
    assert periodic_share(tiles["tiles"].mean(1), 64) > 0.8 and periodic_share(tiles["tiles"].mean(0), 64) > 0.8
    assert periodic_share(tiles["stripes"].mean(0), 32) > 0.9  # bars every 0.125 m
    assert periodic_share(tiles["grain"].mean(0), 32) < 0.3  # the test can fail: random grain is not periodic
    assert set(FAMILY_NAMES) == set(FAMILIES)


def test_realistic_scenes_have_weak_texture_where_ideal_ones_do_not() -> None:
    def weak_fraction(img: torch.Tensor) -> float:
        mean = F.avg_pool2d(img, 7, 1, 3, count_include_pad=False)
        var = F.avg_pool2d(img * img, 7, 1, 3, count_include_pad=False) - mean * mean
        return float((var.clamp_min(0).sqrt() < 0.01).float().mean())

    clean = Imaging.preset("realistic", noise=0.0, bits=0)
    for scene in ("corridor", "hall", "street"):
        preset = "kitti" if scene == "street" else "paper"
        real = _render(clean, scene=scene, preset=preset, height=120, width=160)
        ideal = _render("ideal", scene=scene, preset=preset, height=120, width=160)
        assert weak_fraction(real.left) > 0.2, scene
        assert weak_fraction(ideal.left) < 0.05, scene


@pytest.mark.parametrize("scene", ["corridor", "hall", "street"])
def test_families_and_thin_structures_per_scene(scene: str) -> None:
    rig = PRESETS["kitti" if scene == "street" else "paper"]
    rng = np.random.default_rng
    poses = _trajectory("forward", 30, rig, rng(0))
    base = _build_scene(scene, poses, rig, rng(1))
    detailed = _build_scene(scene, poses, rig, rng(1), detail_rng=rng(2))
    # The original layout is kept and thin structures are added after it.
    assert len(detailed) > len(base)
    for a, b in zip(base, detailed, strict=False):
        assert np.array_equal(a.centre, b.centre) and np.array_equal(a.half, b.half)
    thin = detailed[len(base):]
    assert all(sorted(b.half)[1] <= 0.03 * rig.scale for b in thin if b.kind != "railing")  # two thin axes
    # Nothing thin stands in the camera's lane.
    pos = poses[:, :3, 3]
    for b in thin:
        assert b.centre[0] - b.half[0] > pos[:, 0].max() + 0.5 * rig.scale or \
            b.centre[0] + b.half[0] < pos[:, 0].min() - 0.5 * rig.scale
    fam = _surface_families(scene, detailed, rng(3))
    names = {FAMILY_NAMES[i] for i in fam}
    assert np.array_equal(fam, _surface_families(scene, detailed, rng(3)))  # deterministic for a seed
    room = [FAMILY_NAMES[i] for i in fam[:6]]  # sides, ceiling, floor, back, end
    assert room[2] == ("sky" if scene == "street" else "painted")
    assert room[3] in (("grain",) if scene == "street" else ("tiles", "grain"))
    assert {"plain"} <= names and len(names) >= 4


# ---------------------------------------------------------------------------------------------------- errors


def test_bad_imaging_raises_typed_errors() -> None:
    with pytest.raises(ValueRangeError, match="imaging"):
        render_sequence(num_frames=1, height=8, width=8, imaging="photoreal")
    with pytest.raises(DTypeError, match="imaging"):
        render_sequence(num_frames=1, height=8, width=8, imaging=0.01)  # type: ignore[arg-type]
    with pytest.raises(ValueRangeError, match="Imaging.noise"):
        Imaging(noise=0.3)
    with pytest.raises(ValueRangeError, match="Imaging.noise"):
        Imaging(noise=-0.01)
    with pytest.raises(ValueRangeError, match="Imaging.noise"):
        Imaging(noise=float("nan"))
    with pytest.raises(DTypeError, match="Imaging.gain"):
        Imaging(gain="3%")  # type: ignore[arg-type]
    with pytest.raises(ValueRangeError, match="Imaging.bits"):
        Imaging(bits=20)
    with pytest.raises(ValueRangeError, match="Imaging.surfaces"):
        Imaging(surfaces="marble")
    with pytest.raises(ValueRangeError, match="nosie"):
        Imaging.preset("realistic", nosie=0.01)
    with pytest.raises(ValueRangeError, match="imaging"):
        Imaging.preset("cinematic")
    with pytest.raises(ValueRangeError, match="noise_std"):
        render_sequence(num_frames=1, height=8, width=8, noise_std=0.25)
