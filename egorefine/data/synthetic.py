"""Synthetic stereo video with exact ground truth: textured boxes ray-cast in torch.

A scene is a list of oriented boxes (the enclosing room is a box seen from inside, so every ray hits a
surface and depth is finite everywhere). A rectified stereo rig moves along a smooth, seeded 6-DoF
trajectory through it. Both images of every pair are rendered from the same Lambertian surfaces, so the
pair is physically consistent and disparity, depth and occlusion come exactly from the geometry.

Conventions (docs/method.md): camera frame X right, Y down, Z forward; the world frame is the first nominal
camera frame (Y down, Z along the direction of travel); disparity ``d = x_left - x_right = f B / Z``;
``poses[t]`` is ``world_T_camera`` of the left camera, ``motions[t] = camera_t_T_camera_{t-1}``.

The world (rig, trajectory, boxes, texture families, lights) is built in :mod:`egorefine.data._world` and each view
ray cast by :mod:`egorefine.data._raycast`; this module renders the stereo pairs of a sequence and their truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..core import ValueRangeError, check_choice, progress
from ._imaging import IMAGING, Cameras, Imaging, resolve_imaging
from ._raycast import _Renderer
from ._sequence import SequenceMixin
from ._world import RigPreset, _build_scene, _lights, _surface_families, _trajectory

__all__ = ["RigPreset", "StereoSequence", "PRESETS", "SCENES", "MOTIONS", "IMAGING", "Imaging", "render_sequence"]


PRESETS: dict[str, RigPreset] = {
    # The paper's rig: 640x480, f = 3.5 mm / 8.8 um = 398 px, B = 8 cm, 7 frames/s, ~0.1 m per frame indoors.
    "paper": RigPreset(480, 640, 398.0, 0.08, 7.0, 0.1, 1.0, 1.2, 0.004, 12.0, "corridor"),
    # KITTI-like: 1242x375, f = 721.5 px, B = 0.54 m, 10 frames/s, ~1 m per frame, depths ~5-80 m.
    "kitti": RigPreset(375, 1242, 721.5377, 0.5372, 10.0, 1.0, 6.0, 1.65, 0.010, 60.0, "street"),
}

SCENES: dict[str, str] = {
    "corridor": "a long corridor (about 3 m wide and 2.7 m high on the paper rig) lined with crates, pillars "
    "and boxes hanging from the ceiling; the end wall closes the view",
    "hall": "a wide hall (about 8 m) with pillars, scattered rotated crates and slanted panels around a free lane",
    "street": "a street canyon: road, building blocks of varying height and setback on both sides, parked "
    "'cars', poles, under a high ceiling that stands in for the sky",
}

MOTIONS: dict[str, str] = {
    "forward": "forward at the preset speed (+-15 %) with small sinusoidal sway, bob, yaw, pitch and roll "
    "(a fraction of a degree per frame)",
    "turn": "forward while yawing +-20 degrees (about 1.2 degrees per frame), a gentle slalom",
    "lateral": "mostly sideways: a lateral sinusoid (peak speed about the preset speed) with slow forward travel",
    "shaky": "forward at 80 % speed with larger, faster pitch/roll/yaw oscillations (hand-held)",
    "still": "nearly still: millimetre jitter and hundredths of a degree (like a hovering drone)",
}


@dataclass
class StereoSequence(SequenceMixin):
    """A rendered (or loaded) rectified stereo sequence with ground truth.

    Attributes:
        left, right: ``(T, 1, H, W)`` grey images in [0, 1].
        disparity: ``(T, 1, H, W)`` left-view disparity in pixels (``f B / depth``).
        depth: ``(T, 1, H, W)`` left-view depth ``Z`` in metres, finite everywhere.
        occluded: ``(T, 1, H, W)`` bool, left pixels whose surface point is hidden in or outside the right image.
        poses: ``(T, 4, 4)`` ``world_T_camera`` of the left camera.
        motions: ``(T, 4, 4)`` ``camera_t_T_camera_{t-1}``; identity at ``t = 0``.
        K: ``(3, 3)`` intrinsics of both (rectified) cameras.
        baseline: metres.
        fps: frames per second.
        exposure: ``(T, 2)`` linear gain of the (left, right) camera at each frame, relative to an ideal camera
            (the camera's gain times the exposure drift; ones for ideal imaging and for loaded sequences).

    :func:`render_sequence` builds one; ``len(seq)`` is ``T``, :meth:`batch` hands frames to the stages and
    ``seq.to(device, dtype)`` moves it.

    Example:
        >>> seq = render_sequence(num_frames=2, height=24, width=32, imaging="ideal")
        >>> len(seq), seq.left.shape, seq.disparity.shape, seq.motions.shape, seq.K.shape
        (2, torch.Size([2, 1, 24, 32]), torch.Size([2, 1, 24, 32]), torch.Size([2, 4, 4]), torch.Size([3, 3]))
        >>> torch.allclose(seq.disparity * seq.depth, seq.K[0, 0] * seq.baseline)  # d = f B / Z
        True
    """

    left: torch.Tensor
    right: torch.Tensor
    disparity: torch.Tensor
    depth: torch.Tensor
    occluded: torch.Tensor
    poses: torch.Tensor
    motions: torch.Tensor
    K: torch.Tensor
    baseline: float
    fps: float
    exposure: torch.Tensor | None = None

    def __repr__(self) -> str:
        T, _, H, W = self.left.shape
        return (f"StereoSequence(T={T}, H={H}, W={W}, f={float(self.K[0, 0]):.2f}, baseline={self.baseline:g}, "
                f"fps={self.fps:g}, dtype={self.left.dtype}, device={self.left.device})")

    def batch(self, t: int | slice) -> dict[str, torch.Tensor]:
        """Frame(s) ``t`` batched: images ``(B,1,H,W)``, ``K`` ``(B,3,3)``, ``baseline`` ``(B,)``.

        >>> seq = render_sequence(num_frames=2, height=24, width=32)
        >>> seq.batch(1)["left"].shape, seq.batch(slice(0, 2))["K"].shape
        (torch.Size([1, 1, 24, 32]), torch.Size([2, 3, 3]))
        """
        idx = slice(t, t + 1) if isinstance(t, int) else t
        left = self.left[idx]
        b = left.shape[0]
        return {
            "left": left,
            "right": self.right[idx],
            "disparity": self.disparity[idx],
            "depth": self.depth[idx],
            "occluded": self.occluded[idx],
            "poses": self.poses[idx],
            "motions": self.motions[idx],
            "K": self.K.expand(b, 3, 3).clone(),
            "baseline": torch.full((b,), self.baseline, dtype=left.dtype, device=left.device),
        }


def _right_pose(pose_l: np.ndarray, B: float) -> np.ndarray:
    pose_r = pose_l.copy()
    pose_r[:3, 3] = pose_l[:3, 3] + B * pose_l[:3, 0]  # right camera: +B along the left camera's x axis
    return pose_r


def _image_motion(renderer: _Renderer, depth: torch.Tensor, pose: np.ndarray, other: np.ndarray,
                  sign: float) -> torch.Tensor:
    """Displacement ``(H, W, 2)`` in pixels of each pixel's scene point between camera ``other`` and ``pose``
    (``sign`` +1: ``other`` is the earlier frame; -1: the later one, so the result still points forward in time)."""
    dt = renderer.dtype
    rel = torch.as_tensor(np.linalg.inv(other) @ pose, device=renderer.device, dtype=dt)  # other_T_pose
    ys, xs = torch.meshgrid(renderer.ys, renderer.xs, indexing="ij")
    cam = torch.stack([(xs - renderer.cx) / renderer.f * depth, (ys - renderer.cy) / renderer.f * depth, depth], -1)
    moved = cam @ rel[:3, :3].T + rel[:3, 3]
    z = moved[..., 2].clamp_min(1e-3 * renderer.scale)  # points behind the other camera: keep the shift finite
    proj = torch.stack([renderer.f * moved[..., 0] / z + renderer.cx, renderer.f * moved[..., 1] / z + renderer.cy], -1)
    return sign * (torch.stack([xs, ys], -1) - proj)


def _render_frames(renderer: _Renderer, poses: np.ndarray, f: float, B: float, noise_std: float,
                   noise_gen: torch.Generator, antialias: bool, show_progress: bool,
                   cameras: Cameras | None = None) -> tuple[list, list, list, list]:
    """Render every frame: left and right images, left depth and the occlusion mask, each ``(H, W)``."""
    dev, dtype = renderer.device, renderer.dtype
    xs = torch.arange(renderer.w, device=dev, dtype=dtype)[None, :]
    num_frames = len(poses)
    blur = cameras is not None and cameras.opts.motion_blur > 0 and num_frames > 1
    lefts, rights, depths, occs = [], [], [], []
    with torch.no_grad():
        for i in progress(range(num_frames), desc="render_sequence", enabled=show_progress):
            pose_l = poses[i]
            pose_r = _right_pose(pose_l, B)
            left, depth, _ = renderer.render_view(pose_l, antialias)
            right, depth_r, faces_r = renderer.render_view(pose_r, antialias)
            # Occlusion: the left point (x, y, Z) lies on the right ray through (x - d, y) at the same depth Z
            # (rectified rig); it is hidden if a face is nearer along that ray, or if it falls outside the image.
            disp = f * B / depth
            occluded = renderer.blocked(faces_r, xs - disp, 1.0 / depth) | (xs - disp < 0.0)
            if cameras is not None:
                j, sign = (i - 1, 1.0) if i > 0 else (1, -1.0)
                flow_l = _image_motion(renderer, depth, pose_l, poses[j], sign) if blur else None
                flow_r = _image_motion(renderer, depth_r, pose_r, _right_pose(poses[j], B), sign) if blur else None
                left = cameras.apply(left, i, 0, flow_l)
                right = cameras.apply(right, i, 1, flow_r)
            if noise_std > 0:
                left = left + noise_std * torch.randn(left.shape, generator=noise_gen, device=dev, dtype=dtype)
                right = right + noise_std * torch.randn(right.shape, generator=noise_gen, device=dev, dtype=dtype)
            lefts.append(left.clamp(0.0, 1.0))
            rights.append(right.clamp(0.0, 1.0))
            depths.append(depth)
            occs.append(occluded)
    return lefts, rights, depths, occs


def render_sequence(
    num_frames: int = 60,
    preset: str = "paper",
    scene: str | None = None,
    motion: str = "forward",
    seed: int = 0,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
    show_progress: bool = False,
    height: int | None = None,
    width: int | None = None,
    focal: float | None = None,
    baseline: float | None = None,
    noise_std: float = 0.0,
    antialias: bool = True,
    num_threads: int | None = 1,
    imaging: str | Imaging = "realistic",
) -> StereoSequence:
    """Render a rectified stereo sequence with exact ground truth.

    By default the images look like a camera's (``imaging="realistic"``): the scene's surfaces wear texture
    families that fit them (painted walls and ceilings, sky, brick, floor tiles, stripes and railings, plain and
    grainy surfaces, printed clutter), thin rails, posts, pipes and poles stand beside the path, and each camera
    adds its own gain, offset, gamma and vignetting, a slow exposure drift, shot and read noise and 8-bit
    quantisation. ``imaging="ideal"`` gives the original images: one rich texture on every surface, identical
    noise-free float cameras. docs/rendering.md tables what each preset and scene contains.

    Args:
        num_frames: ``T`` frames.
        preset: a key of :data:`PRESETS` (``"paper"``: 640x480, f = 398 px, B = 0.08 m, 7 fps, ~0.1 m/frame;
            ``"kitti"``: 1242x375, f = 721.5 px, B = 0.537 m, 10 fps, ~1 m/frame).
        scene: a key of :data:`SCENES`; ``None`` takes the preset's default (``corridor`` / ``street``).
        motion: a key of :data:`MOTIONS`.
        seed: seeds the trajectory phases, the scene layout, the surface textures and the noise.
        device, dtype: where and in which float type to render and return.
        show_progress: show a progress bar on stderr.
        height, width: override the image size; the focal length scales with ``width`` unless ``focal`` is given.
        focal: override the focal length in pixels.
        baseline: override the baseline in metres.
        noise_std: standard deviation of extra additive Gaussian noise (seeded) in [0, 0.2], added after the
            imaging model (so after quantisation); 0 for none. Default 0: the realistic model has its own noise.
        antialias: supersample pixels on geometric edges (4 samples; textures are always band-limited by
            mip-mapping).
        num_threads: torch intra-op threads while rendering on the CPU (restored afterwards); ``None`` keeps the
            current setting.
        imaging: a key of :data:`IMAGING` (``"realistic"``, ``"ideal"``) or an :class:`Imaging` with chosen
            options (e.g. ``Imaging.preset("realistic", noise=0.02, motion_blur=0.5)``). Default
            ``"realistic"``: accuracy measured on ideal images does not carry over to cameras.

    Returns:
        :class:`StereoSequence` with ``left``, ``right``, ``disparity``, ``depth``, ``occluded`` ``(T, 1, H, W)``,
        ``poses``, ``motions`` ``(T, 4, 4)``, ``K`` ``(3, 3)``, ``baseline``, ``fps`` and ``exposure`` ``(T, 2)``.

    Example:
        >>> seq = render_sequence(num_frames=3, height=30, width=40, seed=1)
        >>> seq.left.shape, seq.poses.shape, bool(torch.isfinite(seq.depth).all())
        (torch.Size([3, 1, 30, 40]), torch.Size([3, 4, 4]), True)
        >>> bool((seq.left * 255 == (seq.left * 255).round()).all())  # 8-bit cameras
        True
        >>> ideal = render_sequence(num_frames=1, height=30, width=40, seed=1, imaging="ideal")
        >>> bool(torch.equal(ideal.left[0], ideal.right[0])), seq.exposure.shape
        (False, torch.Size([3, 2]))
    """
    check_choice(preset, list(PRESETS), "preset")
    rig = PRESETS[preset]
    scene = rig.scene if scene is None else scene
    check_choice(scene, list(SCENES), "scene")
    check_choice(motion, list(MOTIONS), "motion")
    if not isinstance(num_frames, int) or num_frames < 1:
        raise ValueRangeError(f"num_frames: expected an int >= 1, got {num_frames!r}")
    if dtype not in (torch.float32, torch.float64):
        raise ValueRangeError(f"dtype: expected torch.float32 or torch.float64, got {dtype}")
    H = rig.height if height is None else int(height)
    W = rig.width if width is None else int(width)
    if H < 2 or W < 2:
        raise ValueRangeError(f"height, width: expected >= 2 pixels, got {H}x{W}")
    f = rig.focal * W / rig.width if focal is None else float(focal)
    B = rig.baseline if baseline is None else float(baseline)
    if num_threads is not None and num_threads < 1:
        raise ValueRangeError(f"num_threads: expected >= 1 or None, got {num_threads}")
    if not (f > 0 and B > 0):
        raise ValueRangeError(f"focal, baseline: expected > 0, got {f}, {B}")
    if not 0.0 <= noise_std <= 0.2:  # also rejects NaN
        raise ValueRangeError(f"noise_std: expected a value in [0, 0.2], got {noise_std!r}")
    opts = resolve_imaging(imaging)
    varied = opts.surfaces == "varied"
    dev = torch.device("cpu") if device is None else torch.device(device)
    K = np.array([[f, 0.0, (W - 1) / 2.0], [0.0, f, (H - 1) / 2.0], [0.0, 0.0, 1.0]])

    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 1]))
    poses = _trajectory(motion, num_frames, rig, rng)
    def gen(stream: int) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence([int(seed), stream]))

    boxes = _build_scene(scene, poses, rig, gen(2), detail_rng=gen(5) if varied else None)
    lights = _lights(scene, boxes, poses, rig)
    families = _surface_families(scene, boxes, gen(4)) if varied else None
    renderer = _Renderer(boxes, lights, rig, K, H, W, gen(3), texture_seed=0, device=dev, dtype=dtype,
                         families=families, family_rng=gen(8) if varied else None)
    cameras = None if opts.is_ideal else Cameras(opts, num_frames, H, W, int(seed), dev, dtype)
    noise_gen = torch.Generator(device=dev).manual_seed(int(seed) + 104729)
    # The renderer runs many medium-sized element-wise ops; on a shared machine the synchronisation of intra-op
    # threads costs far more than it saves (docs/decisions.md), so by default it renders on one thread and
    # restores the caller's setting afterwards.
    threads = torch.get_num_threads()
    if num_threads is not None and dev.type == "cpu":
        torch.set_num_threads(int(num_threads))
    try:
        lefts, rights, depths, occs = _render_frames(renderer, poses, f, B, noise_std, noise_gen, antialias,
                                                     show_progress, cameras)
    finally:
        torch.set_num_threads(threads)
    depth = torch.stack(depths)[:, None]
    poses_t = torch.as_tensor(poses, device=dev, dtype=torch.float64)
    motions = torch.eye(4, dtype=torch.float64, device=dev).repeat(num_frames, 1, 1)
    if num_frames > 1:
        motions[1:] = torch.linalg.inv(poses_t[1:]) @ poses_t[:-1]
    return StereoSequence(
        left=torch.stack(lefts)[:, None],
        right=torch.stack(rights)[:, None],
        disparity=f * B / depth,
        depth=depth,
        occluded=torch.stack(occs)[:, None],
        poses=poses_t.to(dtype),
        motions=motions.to(dtype),
        K=torch.as_tensor(K, device=dev, dtype=dtype),
        baseline=B,
        fps=rig.fps,
        exposure=cameras.exposure if cameras is not None else torch.ones(num_frames, 2, device=dev, dtype=dtype),
    )
