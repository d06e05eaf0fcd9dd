"""How the synthetic cameras turn scene radiance into images: blur, photometry, sensor noise, 8-bit output."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np
import torch
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d

from ..core import DTypeError, ValueRangeError, check_choice

__all__ = ["IMAGING", "Imaging", "resolve_imaging"]

# (low, high) of every numeric option, checked by Imaging.__post_init__.
_RANGES: dict[str, tuple[float, float]] = {
    "noise": (0.0, 0.2),
    "shot_share": (0.0, 1.0),
    "gain": (0.0, 0.5),
    "offset": (0.0, 0.2),
    "gamma": (0.0, 0.5),
    "vignetting": (0.0, 0.9),
    "exposure_drift": (0.0, 0.5),
    "defocus": (0.0, 10.0),
    "motion_blur": (0.0, 1.0),
}
_SURFACES = ("varied", "tile")


@dataclass(frozen=True)
class Imaging:
    """What the two synthetic cameras do to the scene's radiance, and which surfaces the scene wears.

    Per frame and camera, in this order: blur (defocus, motion), a linear gain (the camera's gain times the
    exposure drift of the frame) and vignetting, shot plus read noise on that linear signal, the camera's
    response (gamma and black offset), clipping to [0, 1] and quantisation. Every random draw comes from the
    render seed. :data:`IMAGING` holds the presets; :meth:`preset` derives a variant of one by name.

    Attributes:
        noise: standard deviation of the sensor noise at mid-grey (signal 0.5), as a fraction of full scale,
            in [0, 0.2]. Default 0.01: about 2.5 grey levels of an 8-bit camera, a well-lit industrial sensor.
        shot_share: share of the noise variance at mid-grey that is shot noise (variance proportional to the
            signal); the rest is read noise (constant variance). In [0, 1]; default 0.7, a sensor in good light.
        bits: quantisation of the output to ``2**bits`` levels; 0 keeps floats. Default 8, what cameras deliver.
        gain: scale of the per-camera gain: the right-to-left gain ratio is ``exp(+-g)`` with ``g`` drawn in
            ``[gain / 2, gain]``. In [0, 0.5]; default 0.03 (cameras of one model differ by a few percent).
        offset: per-camera black offset drawn in ``[-offset, offset]``, fraction of full scale; default 0.01.
        gamma: per-camera response exponent drawn in ``[1 - gamma, 1 + gamma]``; default 0.04.
        vignetting: brightness loss at the image corners (quadratic in the radius), drawn per camera within
            +-20 % of this value around a centre shifted by up to 3 % of the image size; in [0, 0.9]; default
            0.2, a typical wide-angle lens.
        exposure_drift: amplitude of a slow, smooth log-gain drift over the sequence (auto exposure): two
            sinusoids with periods of 40-120 frames common to both cameras plus a quarter of that per camera.
            In [0, 0.5]; default 0.04.
        defocus: Gaussian blur sigma in pixels, 0 for none (default: the renderer already band-limits).
        motion_blur: exposure time as a fraction of the frame interval; each pixel is averaged along its
            ground-truth image motion over that time (occlusion ignored). In [0, 1]; default 0 (short exposure).
        surfaces: ``"varied"``: each surface wears a texture family fitting its kind (painted walls and
            ceilings, sky, brick, tiles, stripes, plain and grainy surfaces, printed clutter) and the scenes gain
            thin structures (rails, posts, poles, pipes); ``"tile"``: the original scene geometry with one rich
            texture on every surface.

    Example:
        >>> opts = Imaging.preset("realistic", noise=0.02)
        >>> opts.noise, opts.bits, IMAGING["ideal"].noise
        (0.02, 8, 0.0)
    """

    noise: float = 0.01
    shot_share: float = 0.7
    bits: int = 8
    gain: float = 0.03
    offset: float = 0.01
    gamma: float = 0.04
    vignetting: float = 0.2
    exposure_drift: float = 0.04
    defocus: float = 0.0
    motion_blur: float = 0.0
    surfaces: str = "varied"

    def __post_init__(self) -> None:
        for name, (lo, hi) in _RANGES.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise DTypeError(f"Imaging.{name}: expected a number in [{lo:g}, {hi:g}], got {v!r}")
            if not (lo <= v <= hi):  # also rejects NaN
                raise ValueRangeError(f"Imaging.{name}: expected a value in [{lo:g}, {hi:g}], got {v!r}")
        if isinstance(self.bits, bool) or not isinstance(self.bits, int) or not 0 <= self.bits <= 16:
            raise ValueRangeError(f"Imaging.bits: expected an int in [0, 16] (0: no quantisation), got {self.bits!r}")
        check_choice(self.surfaces, _SURFACES, "Imaging.surfaces")

    @classmethod
    def preset(cls, name: str, **changes: float | int | str) -> Imaging:
        """The preset ``name`` of :data:`IMAGING` with some options changed; unknown names raise ``ValueRangeError``."""
        check_choice(name, list(IMAGING), "imaging")
        known = [f.name for f in fields(cls)]
        for key in changes:
            check_choice(key, known, "Imaging option")
        return replace(IMAGING[name], **changes)

    @property
    def is_ideal(self) -> bool:
        """True when the cameras are perfect (no blur, photometry, noise or quantisation)."""
        return all(getattr(self, n) == 0 for n in _RANGES if n != "shot_share") and self.bits == 0


IMAGING: dict[str, Imaging] = {
    "realistic": Imaging(),
    "ideal": Imaging(noise=0.0, bits=0, gain=0.0, offset=0.0, gamma=0.0, vignetting=0.0, exposure_drift=0.0,
                     surfaces="tile"),
}


def resolve_imaging(imaging: str | Imaging) -> Imaging:
    """An :class:`Imaging` from a preset name or an instance (typed errors otherwise)."""
    if isinstance(imaging, Imaging):
        return imaging
    if not isinstance(imaging, str):
        raise DTypeError(f"imaging: expected a preset name {list(IMAGING)} or an Imaging, got {type(imaging).__name__}")
    check_choice(imaging, list(IMAGING), "imaging")
    return IMAGING[imaging]


class Cameras:
    """The drawn photometry of a stereo pair for a sequence, applied frame by frame with :meth:`apply`.

    Attributes:
        exposure: ``(T, 2)`` linear gain of the (left, right) camera at each frame (camera gain times drift).
    """

    def __init__(self, opts: Imaging, num_frames: int, height: int, width: int, seed: int,
                 device: torch.device, dtype: torch.dtype) -> None:
        self.opts = opts
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 6]))
        # Gain: a common part and a left-right split of magnitude in [gain / 2, gain] with a random sign.
        common = rng.uniform(-0.5, 0.5)
        split = rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 1.0)
        log_gain = opts.gain * np.array([common - split / 2, common + split / 2])
        self.offset = opts.offset * rng.uniform(-1.0, 1.0, 2)
        self.gamma = 1.0 + opts.gamma * rng.uniform(-1.0, 1.0, 2)
        vig = opts.vignetting * rng.uniform(0.8, 1.2, 2)
        centre = rng.uniform(-0.03, 0.03, (2, 2)) * np.array([width, height])
        # Exposure drift: smooth log-gain sinusoids, zero-mean over a period.
        t = np.arange(num_frames, dtype=np.float64)
        per = rng.uniform(40.0, 120.0, 4)
        ph = rng.uniform(0.0, 2 * math.pi, 4)
        drift = opts.exposure_drift * (0.6 * np.sin(2 * math.pi * t / per[0] + ph[0])
                                       + 0.4 * np.sin(2 * math.pi * t / per[1] + ph[1]))
        own = 0.25 * opts.exposure_drift * np.sin(2 * math.pi * t[:, None] / per[2:] + ph[2:])
        self.exposure = torch.as_tensor(np.exp(log_gain + drift[:, None] + own), device=device, dtype=dtype)
        ys = torch.arange(height, device=device, dtype=dtype)[:, None] - (height - 1) / 2
        xs = torch.arange(width, device=device, dtype=dtype)[None, :] - (width - 1) / 2
        corner2 = ((height - 1) / 2) ** 2 + ((width - 1) / 2) ** 2 + 1e-12
        self.vignette = [
            (1.0 - float(vig[c]) * ((xs - float(centre[c, 0])) ** 2 + (ys - float(centre[c, 1])) ** 2) / corner2)
            .clamp_min(0.05) for c in range(2)
        ]
        # Noise variance at signal s: read + shot * s, with the requested total at s = 0.5.
        self.read_var = (1.0 - opts.shot_share) * opts.noise**2
        self.shot_coef = opts.shot_share * opts.noise**2 / 0.5
        state = np.random.SeedSequence([int(seed), 7]).generate_state(1)[0]
        self.gen = torch.Generator(device=device).manual_seed(int(state))

    def noise_sigma(self, signal: torch.Tensor) -> torch.Tensor:
        """Standard deviation of the sensor noise at linear signal ``signal`` (any shape)."""
        return (self.read_var + self.shot_coef * signal.clamp_min(0.0)).sqrt()

    def apply(self, radiance: torch.Tensor, frame: int, cam: int, flow: torch.Tensor | None) -> torch.Tensor:
        """Image ``(H, W)`` that camera ``cam`` (0 left, 1 right) records at ``frame`` from ``radiance`` ``(H, W)``.

        ``flow`` ``(H, W, 2)``: image displacement of each pixel over one frame interval (for motion blur).
        """
        o = self.opts
        x = radiance
        if o.motion_blur > 0 and flow is not None:
            x = _motion_blur(x, flow * o.motion_blur)
        if o.defocus > 0:
            k = 2 * math.ceil(3.0 * o.defocus) + 1
            x = gaussian_blur2d(x[None, None], (k, k), (o.defocus, o.defocus), border_type="replicate")[0, 0]
        x = (x * self.exposure[frame, cam] * self.vignette[cam]).clamp(0.0, 1.0)
        if o.noise > 0:
            x = x + self.noise_sigma(x) * torch.randn(x.shape, generator=self.gen, device=x.device, dtype=x.dtype)
            x = x.clamp(0.0, 1.0)
        if o.gamma > 0:
            x = x.pow(float(self.gamma[cam]))
        x = (x + float(self.offset[cam])).clamp(0.0, 1.0)
        if o.bits > 0:
            levels = float(2**o.bits - 1)
            x = torch.round(x * levels) / levels
        return x


def _motion_blur(image: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """Average of ``image`` ``(H, W)`` sampled along each pixel's displacement ``shift`` ``(H, W, 2)`` in pixels."""
    H, W = image.shape
    taps = int(min(max(math.ceil(float(shift.norm(dim=-1).max())) + 1, 2), 9))
    ys, xs = torch.meshgrid(torch.arange(H, device=image.device, dtype=image.dtype),
                            torch.arange(W, device=image.device, dtype=image.dtype), indexing="ij")
    s = torch.linspace(0.0, 1.0, taps, device=image.device, dtype=image.dtype)[:, None, None]
    px = xs + s * shift[..., 0]
    py = ys + s * shift[..., 1]
    grid = torch.stack([px * (2.0 / max(W - 1, 1)) - 1.0, py * (2.0 / max(H - 1, 1)) - 1.0], -1)  # (taps, H, W, 2)
    out = F.grid_sample(image[None, None].expand(taps, 1, H, W), grid, mode="bilinear", padding_mode="border",
                        align_corners=True)
    return out.mean(0)[0]
