"""Synthetic stereo video with exact ground truth: textured boxes ray-cast in torch.

A scene is a list of oriented boxes (the enclosing room is a box seen from inside, so every ray hits a
surface and depth is finite everywhere). A rectified stereo rig moves along a smooth, seeded 6-DoF
trajectory through it. Both images of every pair are rendered from the same Lambertian surfaces, so the
pair is physically consistent and disparity, depth and occlusion come exactly from the geometry.

Conventions (PAPER.md): camera frame X right, Y down, Z forward; the world frame is the first nominal
camera frame (Y down, Z along the direction of travel); disparity ``d = x_left - x_right = f B / Z``;
``poses[t]`` is ``world_T_camera`` of the left camera, ``motions[t] = camera_t_T_camera_{t-1}``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..core import ValueRangeError, check_choice, progress
from ._families import FAMILY_NAMES, FAMILY_TEXEL, family_textures
from ._imaging import IMAGING, Cameras, Imaging, resolve_imaging
from ._sequence import SequenceMixin
from ._texture import make_texture

__all__ = ["RigPreset", "StereoSequence", "PRESETS", "SCENES", "MOTIONS", "IMAGING", "Imaging", "render_sequence"]


@dataclass(frozen=True)
class RigPreset:
    """A stereo rig and the scale of the world it moves through.

    Attributes:
        height, width: image size in pixels.
        focal: focal length in pixels (square pixels; principal point at the image centre).
        baseline: metres.
        fps: frames per second.
        speed: nominal forward travel per frame in metres.
        scale: spatial scale of the scenes (room widths, object sizes) relative to the indoor rig.
        cam_height: height of the camera above the floor in metres.
        texel: metres per texel of the surface texture at level 0.
        far: how far the scene extends beyond the end of the trajectory, metres.
        scene: the default scene.

    :data:`PRESETS` holds the rigs :func:`render_sequence` renders with; its ``height``, ``width``, ``focal`` and
    ``baseline`` arguments override a preset's (the focal length follows the width), the rest set the world.

    Example:
        >>> rig = PRESETS["paper"]
        >>> (rig.height, rig.width), rig.focal, rig.baseline, rig.scene
        ((480, 640), 398.0, 0.08, 'corridor')
        >>> round(rig.focal * rig.baseline / 2.0, 2)  # disparity of a surface 2 m away, px (d = f B / Z)
        15.92
    """

    height: int
    width: int
    focal: float
    baseline: float
    fps: float
    speed: float
    scale: float
    cam_height: float
    texel: float
    far: float
    scene: str


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


# ----------------------------------------------------------------------------------------------- trajectory


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _trajectory(motion: str, num_frames: int, preset: RigPreset, rng: np.random.Generator) -> np.ndarray:
    """Smooth 6-DoF ``world_T_camera`` poses ``(T, 4, 4)`` (float64) of the left camera."""
    deg = math.pi / 180.0
    v, s = preset.speed, preset.scale
    # (speed factor, yaw, pitch, roll amplitudes in degrees, their periods in frames, sway x / bob y in metres)
    table = {
        "forward": (1.0, 2.0, 1.0, 1.2, (50, 70), (35, 50), (40, 60), 0.04 * s, 0.02 * s),
        "turn": (1.0, 20.0, 1.0, 2.0, (90, 110), (35, 50), (40, 60), 0.03 * s, 0.02 * s),
        "lateral": (0.35, 1.0, 0.5, 0.5, (50, 70), (35, 50), (40, 60), min(v * 60 / (2 * math.pi), 0.8 * s), 0.02 * s),
        "shaky": (0.8, 3.0, 2.5, 3.0, (20, 30), (15, 25), (18, 28), 0.03 * s, 0.03 * s),
        "still": (0.0, 0.05, 0.05, 0.05, (40, 60), (30, 50), (30, 50), 0.003 * s, 0.002 * s),
    }
    k_v, a_yaw, a_pitch, a_roll, p_yaw, p_pitch, p_roll, a_x, a_y = table[motion]
    ph = rng.uniform(0, 2 * math.pi, size=6)
    per = [rng.uniform(*p) for p in (p_yaw, p_pitch, p_roll)]
    p_x = 60.0 if motion == "lateral" else rng.uniform(40, 60)
    p_y, p_v = rng.uniform(25, 35), rng.uniform(30, 50)
    t = np.arange(num_frames, dtype=np.float64)

    def wave(amp: float, period: float, phase: float) -> np.ndarray:
        # Zero at t = 0 so the first camera is the world frame up to the sway offsets.
        return amp * (np.sin(2 * math.pi * t / period + phase) - math.sin(phase))

    yaw = wave(a_yaw * deg, per[0], ph[0])
    pitch = wave(a_pitch * deg, per[1], ph[1])
    roll = wave(a_roll * deg, per[2], ph[2])
    speed = k_v * v * (1.0 + 0.15 * np.sin(2 * math.pi * t / p_v + ph[3]))
    # Integrate the forward velocity along the heading (midpoint rule), then add sway and bob.
    heading = np.stack([np.sin(yaw), np.zeros_like(yaw), np.cos(yaw)], axis=-1)
    step = 0.5 * (speed[1:, None] * heading[1:] + speed[:-1, None] * heading[:-1])
    pos = np.concatenate([np.zeros((1, 3)), np.cumsum(step, axis=0)], axis=0)
    pos[:, 0] += wave(a_x, p_x, ph[4])
    pos[:, 1] += wave(a_y, p_y, ph[5])
    poses = np.tile(np.eye(4), (num_frames, 1, 1))
    for i in range(num_frames):  # loop over frames (a handful of 3x3 products)
        poses[i, :3, :3] = _rot_y(yaw[i]) @ _rot_x(pitch[i]) @ _rot_z(roll[i])
        poses[i, :3, 3] = pos[i]
    return poses


# ---------------------------------------------------------------------------------------------------- scenes


@dataclass
class _Box:
    centre: np.ndarray  # (3,)
    rot: np.ndarray  # (3, 3) columns are the box axes in the world
    half: np.ndarray  # (3,) half extents
    inside: bool = False  # True for the enclosing room (seen from within)
    kind: str = "object"  # what it stands for (crate, pillar, building, rail, ...): picks its texture family


class _SceneBuilder:
    """Collects boxes around a trajectory, keeping a clear lane around the camera path."""

    def __init__(self, poses: np.ndarray, preset: RigPreset, rng: np.random.Generator) -> None:
        self.rng = rng
        self.s = preset.scale
        pos = poses[:, :3, 3]
        self.xmin, self.xmax = pos[:, 0].min(), pos[:, 0].max()
        self.ymin, self.ymax = pos[:, 1].min(), pos[:, 1].max()
        self.zmin, self.zmax = pos[:, 2].min(), pos[:, 2].max()
        self.floor = self.ymax + preset.cam_height  # world Y points down
        self.far = preset.far
        self.boxes: list[_Box] = []

    def room(self, half_width: float, height_above: float, back: float) -> None:
        x0, x1 = self.xmin - half_width, self.xmax + half_width
        y0, y1 = self.ymin - height_above, self.floor
        z0, z1 = self.zmin - back, self.zmax + self.far
        self.x0, self.x1, self.y0, self.z0, self.z1 = x0, x1, y0, z0, z1
        self.boxes.append(
            _Box(np.array([(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2]), np.eye(3),
                 np.array([(x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2]), inside=True, kind="room")
        )

    def add(self, centre: tuple[float, float, float], half: tuple[float, float, float], yaw: float = 0.0,
            tilt: float = 0.0, kind: str = "object") -> None:
        rot = _rot_y(yaw) @ _rot_z(tilt)
        self.boxes.append(_Box(np.asarray(centre, dtype=np.float64), rot, np.asarray(half, dtype=np.float64),
                               kind=kind))

    def x_extent(self, half: np.ndarray, yaw: float) -> float:
        """Half extent along world x of a box yawed by ``yaw``."""
        return abs(math.cos(yaw)) * half[0] + abs(math.sin(yaw)) * half[2]

    def side_objects(self, clearance: float, spacing: float, tall: float) -> None:
        """Crates and pillars along both walls, outside the lane ``[xmin - clearance, xmax + clearance]``."""
        rng, s = self.rng, self.s
        for side in (-1.0, 1.0):
            z = self.z0 + rng.uniform(0.3, 1.0) * spacing
            while z < self.z1 - 0.5 * s:
                kind = rng.uniform()
                yaw = rng.uniform(-0.5, 0.5) if kind < 0.5 else 0.0
                if kind < 0.7:  # crate on the floor
                    half = np.array([rng.uniform(0.15, 0.4), rng.uniform(0.2, 0.75), rng.uniform(0.15, 0.45)]) * s
                    yc, name = self.floor - half[1], "crate"
                elif kind < 0.85:  # pillar floor to ceiling
                    w = rng.uniform(0.1, 0.25, 2) * s
                    half = np.array([w[0], (self.floor - self.y0) / 2, w[1]])
                    yc, name = (self.floor + self.y0) / 2, "pillar"
                else:  # box on a shelf, mid-height
                    half = np.array([rng.uniform(0.1, 0.3), rng.uniform(0.1, 0.3), rng.uniform(0.1, 0.3)]) * s
                    yc, name = self.floor - tall * rng.uniform(0.3, 0.6), "shelf"
                ext = self.x_extent(half, yaw)
                lane_edge = (self.xmax + clearance) if side > 0 else (self.xmin - clearance)
                wall = self.x1 if side > 0 else self.x0
                room_for = abs(wall - lane_edge) - 2 * ext
                if room_for > 0:
                    xc = lane_edge + side * (ext + rng.uniform(0.3, 1.0) * room_for)
                    self.add((xc, yc, z), tuple(half), yaw=yaw, kind=name)
                z += spacing * rng.uniform(0.6, 1.4)

    def hanging(self, spacing: float, clearance_above: float) -> None:
        """Boxes hanging from the ceiling across the lane, their bottom above the camera path."""
        rng, s = self.rng, self.s
        z = self.z0 + spacing * rng.uniform(0.5, 1.5)
        while z < self.z1 - s:
            bottom = self.ymin - clearance_above
            top = self.y0
            if bottom - top > 0.1 * s:
                h = (bottom - top) * rng.uniform(0.3, 0.9) / 2
                xc = rng.uniform(self.x0 + 0.3 * s, self.x1 - 0.3 * s)
                self.add((xc, top + h, z), (rng.uniform(0.2, 0.6) * s, h, rng.uniform(0.05, 0.2) * s),
                         yaw=rng.uniform(-0.3, 0.3), kind="hanging")
            z += spacing * rng.uniform(0.6, 1.4)


def _build_scene(scene: str, poses: np.ndarray, preset: RigPreset, rng: np.random.Generator,
                 detail_rng: np.random.Generator | None = None) -> list[_Box]:
    """The boxes of ``scene`` around the trajectory; with ``detail_rng``, thin structures are added after the
    original layout (drawn from their own generator, so the layout itself does not change)."""
    b = _SceneBuilder(poses, preset, rng)
    s = b.s
    if scene == "corridor":
        b.room(half_width=1.5 * s, height_above=1.5 * s, back=3.0 * s)
        b.side_objects(clearance=0.85 * s, spacing=1.2 * s, tall=1.5 * s)
        b.hanging(spacing=3.0 * s, clearance_above=0.55 * s)
        # A few obstacles on the end wall region make the far field less flat.
        for _ in range(3):
            half = np.array([rng.uniform(0.2, 0.5), rng.uniform(0.3, 0.9), rng.uniform(0.2, 0.5)]) * s
            b.add((rng.uniform(b.x0 + half[0], b.x1 - half[0]), b.floor - half[1],
                   b.z1 - rng.uniform(1.0, 3.0) * s), tuple(half), yaw=rng.uniform(-0.6, 0.6), kind="crate")
    elif scene == "hall":
        b.room(half_width=4.0 * s, height_above=2.5 * s, back=4.0 * s)
        b.side_objects(clearance=0.8 * s, spacing=0.7 * s, tall=2.0 * s)
        b.hanging(spacing=3.0 * s, clearance_above=0.6 * s)
        # Slanted panels leaning against the side walls.
        for side in (-1.0, 1.0):
            z = b.z0 + rng.uniform(1.0, 3.0) * s
            while z < b.z1 - s:
                half = (0.03 * s, rng.uniform(0.4, 0.9) * s, rng.uniform(0.3, 0.8) * s)
                xc = (b.x1 if side > 0 else b.x0) - side * 0.5 * s
                b.add((xc, b.floor - half[1] * 0.9, z), half, yaw=rng.uniform(-0.4, 0.4), tilt=side * 0.35,
                      kind="panel")
                z += rng.uniform(3.0, 6.0) * s
    elif scene == "street":
        b.room(half_width=3.5 * s, height_above=6.0 * s, back=4.0 * s)
        # Building blocks along both sides: varying height and setback, with gaps between them.
        for side in (-1.0, 1.0):
            z = b.z0
            while z < b.z1:
                length = rng.uniform(1.0, 2.5) * s
                depth = rng.uniform(0.3, 1.0) * s
                height = rng.uniform(0.8, 5.5) * s
                inner = (b.xmax + rng.uniform(2.0, 2.8) * s) if side > 0 else (b.xmin - rng.uniform(2.0, 2.8) * s)
                xc = inner + side * depth
                b.add((xc, b.floor - height / 2, z + length / 2), (depth, height / 2, length / 2), kind="building")
                z += length + rng.uniform(0.0, 0.6) * s
        # Parked 'cars' (low boxes) and poles at the kerb.
        b.side_objects(clearance=0.9 * s, spacing=1.2 * s, tall=0.6 * s)
    else:  # pragma: no cover - guarded by check_choice
        raise ValueRangeError(f"scene: unknown {scene!r}")
    if detail_rng is not None:
        _thin_structures(b, scene, detail_rng)
    return b.boxes


def _thin_structures(b: _SceneBuilder, scene: str, rng: np.random.Generator) -> None:
    """Rails with posts, pipes and poles: structures a few centimetres thick, outside the camera's lane."""
    s = b.s

    def railing(x: float, z0: float, z1: float, height: float, post_every: float, infill: bool) -> None:
        b.add((x, b.floor - height, (z0 + z1) / 2), (0.02 * s, 0.02 * s, (z1 - z0) / 2), kind="rail")
        z = z0
        while z <= z1:
            b.add((x, b.floor - height / 2, z), (0.015 * s, height / 2, 0.015 * s), kind="rail")
            z += post_every * rng.uniform(0.9, 1.1)
        if infill:  # slats between the posts, as a thin striped panel
            b.add((x, b.floor - 0.5 * height, (z0 + z1) / 2), (0.003 * s, 0.4 * height, (z1 - z0) / 2),
                  kind="railing")

    def poles(x: float, z0: float, z1: float, height: float, every: tuple[float, float]) -> None:
        z = z0 + rng.uniform(0.0, every[1])
        while z < z1:
            b.add((x, b.floor - height / 2, z), (0.02 * s, height / 2, 0.02 * s), kind="pole")
            z += rng.uniform(*every)

    if scene == "corridor":
        for side in (-1.0, 1.0):
            wall = b.x1 if side > 0 else b.x0
            if rng.uniform() < 0.7:  # a handrail along the wall
                railing(wall - side * 0.06 * s, b.z0 + 0.5 * s, b.z1 - 0.5 * s, 0.9 * s, 1.8 * s, infill=False)
            # A pipe under the ceiling.
            b.add((wall - side * rng.uniform(0.1, 0.3) * s, b.y0 + rng.uniform(0.05, 0.15) * s, (b.z0 + b.z1) / 2),
                  (0.025 * s, 0.025 * s, (b.z1 - b.z0) / 2), kind="pipe")
    elif scene == "hall":
        side = rng.choice([-1.0, 1.0])
        x = (b.xmax + 1.3 * s) if side > 0 else (b.xmin - 1.3 * s)
        z0 = b.z0 + rng.uniform(1.0, 3.0) * s
        railing(x, z0, min(z0 + rng.uniform(6.0, 10.0) * s, b.z1 - s), 1.0 * s, 1.2 * s, infill=True)
        for side in (-1.0, 1.0):  # free-standing thin columns
            x = (b.xmax + rng.uniform(1.0, 2.5) * s) if side > 0 else (b.xmin - rng.uniform(1.0, 2.5) * s)
            poles(x, b.z0 + s, b.z1 - s, b.floor - b.y0, (3.0 * s, 6.0 * s))
    elif scene == "street":
        for side in (-1.0, 1.0):  # lamp and sign poles at the kerb
            x = (b.xmax + 1.6 * s) if side > 0 else (b.xmin - 1.6 * s)
            poles(x, b.z0, b.z1, 0.7 * s, (2.5 * s, 4.0 * s))
        side = rng.choice([-1.0, 1.0])
        x = (b.xmax + 1.4 * s) if side > 0 else (b.xmin - 1.4 * s)
        z0 = b.z0 + rng.uniform(2.0, 6.0) * s
        railing(x, z0, min(z0 + 6.0 * s, b.z1 - s), 0.17 * s, 0.5 * s, infill=False)


# Texture families per surface kind, scene by scene: {kind: ((family, weight), ...)}. Room faces have the kinds
# wall (sides), ceiling, floor, back and end; the other kinds are those of _SceneBuilder and _thin_structures.
_FAMILY_TABLE: dict[str, dict[str, tuple[tuple[str, float], ...]]] = {
    "corridor": {
        "wall": (("painted", 0.7), ("brick", 0.3)), "ceiling": (("painted", 1.0),),
        "floor": (("tiles", 0.5), ("grain", 0.5)), "end": (("painted", 0.5), ("print", 0.5)),
        "crate": (("print", 0.5), ("plain", 0.3), ("stripes", 0.2)), "pillar": (("painted", 0.6), ("plain", 0.4)),
        "hanging": (("plain", 0.5), ("print", 0.5)),
    },
    "hall": {
        "wall": (("brick", 0.5), ("painted", 0.5)), "ceiling": (("painted", 1.0),), "floor": (("tiles", 1.0),),
        "end": (("brick", 0.5), ("painted", 0.5)),
        "crate": (("print", 0.5), ("plain", 0.3), ("stripes", 0.2)), "pillar": (("painted", 0.6), ("plain", 0.4)),
        "panel": (("stripes", 0.5), ("print", 0.5)), "hanging": (("plain", 0.5), ("print", 0.5)),
    },
    "street": {
        "wall": (("brick", 0.5), ("painted", 0.5)), "ceiling": (("sky", 1.0),), "floor": (("grain", 1.0),),
        "end": (("painted", 1.0),),
        "building": (("brick", 0.4), ("painted", 0.3), ("tiles", 0.15), ("print", 0.15)),
        "crate": (("plain", 0.6), ("print", 0.4)), "pillar": (("painted", 0.5), ("plain", 0.5)),
    },
}
_FAMILY_DEFAULT: dict[str, tuple[tuple[str, float], ...]] = {
    "back": (("painted", 1.0),), "shelf": (("print", 1.0),), "rail": (("plain", 1.0),), "pipe": (("plain", 1.0),),
    "pole": (("plain", 1.0),), "railing": (("stripes", 1.0),), "object": (("print", 1.0),),
}
_ROOM_KINDS = ("wall", "wall", "ceiling", "floor", "back", "end")  # by face 2 k + (side > 0) of the room box


def _surface_families(scene: str, boxes: list[_Box], rng: np.random.Generator) -> np.ndarray:
    """Texture family (an index into FAMILY_NAMES) of every face, ``(6 * len(boxes),)``, drawn per box (per face
    for the room) from the scene's table."""
    table = {**_FAMILY_DEFAULT, **_FAMILY_TABLE[scene]}
    out = np.zeros(6 * len(boxes), dtype=np.int64)

    def draw(kind: str) -> int:
        names, weights = zip(*table[kind], strict=True)
        w = np.asarray(weights) / sum(weights)
        return FAMILY_NAMES.index(names[int(rng.choice(len(names), p=w))])

    for i, box in enumerate(boxes):  # loop over boxes (tens)
        if box.inside:
            out[6 * i : 6 * i + 6] = [draw(kind) for kind in _ROOM_KINDS]
        else:
            out[6 * i : 6 * i + 6] = draw(box.kind)
    return out


def _lights(scene: str, boxes: list[_Box], poses: np.ndarray, preset: RigPreset) -> np.ndarray:
    """Point lights under the ceiling along the path, ``(L, 3)``; none outdoors (the sun is directional)."""
    if scene == "street":
        return np.zeros((0, 3))
    room = boxes[0]
    y_ceiling = room.centre[1] - room.half[1]
    z0 = room.centre[2] - room.half[2]
    z1 = room.centre[2] + room.half[2]
    s = preset.scale
    zs = np.arange(z0 + 2.0 * s, z1, 6.0 * s)
    pos = poses[:, :3, 3]
    xc = 0.5 * (pos[:, 0].min() + pos[:, 0].max())
    xs = xc + 0.6 * s * np.where(np.arange(len(zs)) % 2 == 0, 1.0, -1.0)
    ys = np.full_like(zs, y_ceiling + 0.15 * s)
    return np.stack([xs, ys, zs], axis=-1)


# ------------------------------------------------------------------------------------------------ ray casting


def _faces(boxes: list[_Box]) -> dict[str, np.ndarray]:
    """Every box face as a rectangle facing its visible side: centre, unit normal, in-plane axes, half sizes.

    Face ``6 b + 2 k + (side > 0)`` is the face of box ``b`` normal to its axis ``k``. Normals point out of solid
    boxes and into the room, so a face can be seen only from the side its normal points to.
    """
    other = ((1, 2), (0, 2), (0, 1))
    centre, normal, eu, ev, half = [], [], [], [], []
    for b in boxes:
        for k in range(3):
            for side in (-1.0, 1.0):
                i, j = other[k]
                centre.append(b.centre + side * b.half[k] * b.rot[:, k])
                normal.append((-side if b.inside else side) * b.rot[:, k])
                eu.append(b.rot[:, i])
                ev.append(b.rot[:, j])
                half.append((b.half[i], b.half[j]))
    return {k: np.asarray(v, dtype=np.float64) for k, v in
            (("centre", centre), ("normal", normal), ("eu", eu), ("ev", ev), ("half", half))}


class _Renderer:
    """Scan-converts box faces with exact per-pixel depth (a w-buffer) and shades them (all on the render device).

    For a planar face, inverse depth ``1 / Z`` and ``u / Z``, ``v / Z`` (in-plane coordinates over depth) are affine
    functions of the pixel coordinates, so intersecting every pixel's ray with a face costs a few multiply-adds
    per pixel, evaluated only inside the face's projected bounding rectangle.
    """

    def __init__(self, boxes: list[_Box], lights: np.ndarray, preset: RigPreset, K: np.ndarray,
                 height: int, width: int, rng: np.random.Generator, texture_seed: int,
                 device: torch.device, dtype: torch.dtype, families: np.ndarray | None = None,
                 family_rng: np.random.Generator | None = None) -> None:
        self.device, self.dtype = device, dtype
        self.h, self.w = height, width
        self.f, self.cx, self.cy = float(K[0, 0]), float(K[0, 2]), float(K[1, 2])
        self.scale = preset.scale
        self.np_faces = _faces(boxes)
        n_faces = len(self.np_faces["centre"])

        def t(x: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.asarray(x), device=device, dtype=dtype)

        self.face_centre = t(self.np_faces["centre"])
        self.face_normal = t(self.np_faces["normal"])
        self.face_eu = t(self.np_faces["eu"])
        self.face_ev = t(self.np_faces["ev"])
        ang = rng.uniform(0, 2 * math.pi, n_faces)
        scl = rng.uniform(0.75, 1.35, n_faces) * preset.texel
        off = rng.uniform(0, 4096, (n_faces, 2))
        gain = rng.uniform(0.9, 1.25, n_faces)
        bias = rng.uniform(-0.05, 0.05, n_faces)
        self.families = None
        if families is not None:
            ang, scl, gain, bias = self._family_layout(families, ang, scl, gain, bias, family_rng)
            self.families = family_textures(str(device), dtype)
            self.face_family = torch.as_tensor(families, device=device)
        # Texel coordinates = A_f @ (u, v) + off_f, A_f a rotation over the face's texel size.
        A = np.stack([np.cos(ang), -np.sin(ang), np.sin(ang), np.cos(ang)], -1).reshape(-1, 2, 2) / scl[:, None, None]
        self.face_A = t(A)
        self.face_off = t(off)
        self.face_texel = t(scl)
        self.face_gain = t(gain)
        self.face_bias = t(bias)
        # A directional light (the sun outdoors, a window indoors): constant over each planar face.
        sun = np.array([0.4, -0.8, 0.45])
        sun_term = np.clip(self.np_faces["normal"] @ (sun / np.linalg.norm(sun)), 0.0, None)
        self.face_sun = t(sun_term)
        self.sun_weight = 0.45 if len(lights) == 0 else 0.15
        self.lights = t(lights)
        self.light_range = 4.0 * preset.scale
        self.texture = make_texture(texture_seed, device=str(device), dtype=dtype)
        self.xs = torch.arange(width, device=device, dtype=dtype)
        self.ys = torch.arange(height, device=device, dtype=dtype)

    def _family_layout(self, families: np.ndarray, ang: np.ndarray, scl: np.ndarray, gain: np.ndarray,
                       bias: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
        """Placement of the texture families: periodic patterns upright at their physical size, a bright sky."""
        ang, scl, gain, bias = ang.copy(), scl.copy(), gain.copy(), bias.copy()
        jitter = rng.uniform(0.9, 1.1, len(families))
        # Rows of a pattern run along the face's more horizontal axis (world y is vertical).
        eu_up = np.abs(self.np_faces["eu"][:, 1]) > np.abs(self.np_faces["ev"][:, 1])
        for k, name in enumerate(FAMILY_NAMES):  # loop over a handful of families
            on = families == k
            if FAMILY_TEXEL[name] is not None:
                ang[on] = np.where(eu_up[on], 0.5 * math.pi, 0.0)
                scl[on] = FAMILY_TEXEL[name] * jitter[on]
            if name == "sky":  # unlit by the lamps and the sun: bright on its own
                gain[on], bias[on] = 1.6, 0.0
        return ang, scl, gain, bias

    # -- per camera: affine coefficients and bounding rectangles of the faces

    def setup(self, world_T_cam: np.ndarray) -> list[tuple[int, tuple, int, int, int, int]]:
        """Visible faces for a camera: ``(face, coefficients, x0, x1, y0, y1)`` with half-open pixel rectangles.

        ``coefficients`` are three affine maps ``(a_x, a_y, c)`` of the pixel coordinates: ``1 / Z``, ``u / Z`` and
        ``v / Z`` along each pixel's ray, and the face's half sizes ``(h_u, h_v)``.
        """
        R, o = world_T_cam[:3, :3], world_T_cam[:3, 3]
        F = self.np_faces
        rel = F["centre"] - o  # (F, 3)
        dist = (rel * F["normal"]).sum(-1)  # < 0 when the camera is on the face's visible side
        near = 1e-3 * self.scale
        f, cx, cy = self.f, self.cx, self.cy
        out = []
        corners_uv = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
        for i in np.nonzero(dist < -1e-9 * self.scale)[0]:  # loop over front-facing faces
            # Clip the face rectangle to the near plane, then bound its projection.
            corners = F["centre"][i] + (corners_uv * F["half"][i]) @ np.stack([F["eu"][i], F["ev"][i]])
            cam = (corners - o) @ R
            poly = []
            for a, b in zip(cam, np.roll(cam, -1, axis=0), strict=True):
                if a[2] >= near:
                    poly.append(a)
                if (a[2] >= near) != (b[2] >= near):
                    poly.append(a + (near - a[2]) / (b[2] - a[2]) * (b - a))
            if not poly:
                continue
            poly = np.asarray(poly)
            x = f * poly[:, 0] / poly[:, 2] + cx
            y = f * poly[:, 1] / poly[:, 2] + cy
            x0, x1 = max(math.floor(x.min()) - 1, 0), min(math.ceil(x.max()) + 2, self.w)
            y0, y1 = max(math.floor(y.min()) - 1, 0), min(math.ceil(y.max()) + 2, self.h)
            if x0 >= x1 or y0 >= y1:
                continue

            def affine(w: np.ndarray) -> np.ndarray:
                # w . d(x, y) with d = R [(x - cx) / f, (y - cy) / f, 1]: affine in (x, y).
                m = R.T @ w
                return np.array([m[0] / f, m[1] / f, m[2] - m[0] * cx / f - m[1] * cy / f])

            inv = affine(F["normal"][i]) / dist[i]  # 1 / t = (n . d) / ((p0 - o) . n)
            u = -(rel[i] @ F["eu"][i]) * inv + affine(F["eu"][i])  # u / t = (o - p0) . e_u / t + e_u . d
            v = -(rel[i] @ F["ev"][i]) * inv + affine(F["ev"][i])
            coef = (*inv.tolist(), *u.tolist(), *v.tolist(), float(F["half"][i][0]), float(F["half"][i][1]))
            out.append((int(i), coef, x0, x1, y0, y1))
        return out

    @staticmethod
    def _inv_depth(coef: tuple, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Inverse depth of the face along the rays through pixels ``(x, y)`` (broadcast); 0 where they miss it."""
        ia, ib, ic, ua, ub, uc, va, vb, vc, hu, hv = coef
        inv = x * ia + (y * ib + ic)
        # Faces are grown by a hair (relative 1e-5) so that rays through shared edges never slip between them.
        hu, hv = hu * (1.0 + 1e-5), hv * (1.0 + 1e-5)
        inside = ((x * ua + (y * ub + uc)).abs() <= inv * hu) & ((x * va + (y * vb + vc)).abs() <= inv * hv)
        return torch.where(inside & (inv > 0), inv, torch.zeros_like(inv))

    def cast_grid(self, faces: list) -> tuple[torch.Tensor, torch.Tensor]:
        """Nearest face for every pixel centre: inverse depth ``(H, W)`` and face index ``(H, W)``."""
        best = torch.zeros((self.h, self.w), device=self.device, dtype=self.dtype)
        ids = torch.zeros((self.h, self.w), device=self.device, dtype=torch.long)
        for i, coef, x0, x1, y0, y1 in faces:  # loop over faces
            inv = self._inv_depth(coef, self.xs[None, x0:x1], self.ys[y0:y1, None])
            cur = best[y0:y1, x0:x1]
            closer = inv > cur
            best[y0:y1, x0:x1] = torch.where(closer, inv, cur)
            ids[y0:y1, x0:x1].masked_fill_(closer, i)
        return best, ids

    def _supersample(self, faces: list, face: torch.Tensor, idx: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Four rotated-grid samples in each pixel ``idx`` ``(n,)`` (flat indices), tested only against the faces
        seen at the centres of the pixel's 3x3 neighbourhood: sample x, y, inverse depth, face, each ``(4 n,)``."""
        n_all = len(self.np_faces["centre"])
        table = torch.zeros((n_all, 11), device=self.device, dtype=self.dtype)
        table[torch.tensor([fc[0] for fc in faces], device=self.device)] = torch.tensor(
            [fc[1] for fc in faces], device=self.device, dtype=self.dtype)
        padded = torch.nn.functional.pad(face[None, None].to(self.dtype), (1, 1, 1, 1), mode="replicate")[0, 0]
        padded = padded.long()
        y, x = idx // self.w, idx % self.w
        cand = torch.stack([padded[y + dy, x + dx] for dy in range(3) for dx in range(3)], -1)  # (n, 9)
        coef = table[cand]  # (n, 9, 11)
        off = torch.tensor([[-0.125, -0.375], [0.375, -0.125], [0.125, 0.375], [-0.375, 0.125]],
                           device=self.device, dtype=self.dtype)
        px = x.to(self.dtype)[:, None] + off[:, 0]  # (n, 4)
        py = y.to(self.dtype)[:, None] + off[:, 1]
        X, Y = px[:, :, None], py[:, :, None]  # (n, 4, 1) against coefficients (n, 1, 9)
        c = coef[:, None]
        inv = X * c[..., 0] + Y * c[..., 1] + c[..., 2]
        inside = ((X * c[..., 3] + Y * c[..., 4] + c[..., 5]).abs() <= inv * c[..., 9]) & (
            (X * c[..., 6] + Y * c[..., 7] + c[..., 8]).abs() <= inv * c[..., 10]) & (inv > 0)
        inv = torch.where(inside, inv, torch.zeros_like(inv))
        best, arg = inv.max(-1)  # (n, 4)
        hit = cand.gather(1, arg)  # (n, 4)
        # A sample that none of the neighbourhood's faces covers (a sliver thinner than a pixel) keeps the centre.
        centre = face.view(-1)[idx][:, None].expand(-1, 4)
        inv_centre = 1.0 / self.depth_flat[idx][:, None].expand(-1, 4)
        miss = best <= 0
        hit = torch.where(miss, centre, hit)
        best = torch.where(miss, inv_centre, best)
        return px.reshape(-1), py.reshape(-1), best.reshape(-1), hit.reshape(-1)

    def blocked(self, faces: list, x: torch.Tensor, inv_point: torch.Tensor) -> torch.Tensor:
        """For rays through ``(x[r, c], r)`` ``(H, W)``: does any face lie nearer than ``1 / inv_point``?"""
        limit = inv_point * (1.0 + 1e-4)
        out = torch.zeros(x.shape, device=self.device, dtype=torch.bool)
        for _, coef, x0, _x1, y0, y1 in faces:  # loop over faces; left x >= right x >= x0
            inv = self._inv_depth(coef, x[y0:y1, x0:], self.ys[y0:y1, None])
            out[y0:y1, x0:] |= inv > limit[y0:y1, x0:]
        return out

    # -- shading

    def shade(self, origin: torch.Tensor, dirs: torch.Tensor, depth: torch.Tensor, face: torch.Tensor,
              supersample: float = 1.0) -> torch.Tensor:
        """Intensity ``(n,)`` of hits ``origin + depth * dirs`` on ``face`` (``dirs`` ``(n, 3)``, camera z = 1)."""
        pts = origin + depth[:, None] * dirs
        rel = pts - self.face_centre[face]
        uv = torch.stack([(rel * self.face_eu[face]).sum(-1), (rel * self.face_ev[face]).sum(-1)], -1)
        tex_uv = (self.face_A[face] @ uv[:, :, None])[:, :, 0] + self.face_off[face]
        normal = self.face_normal[face]
        # Footprint of a pixel on the surface (geometric mean of its two axes) in texels: band-limits the texture.
        cos = (normal * dirs).sum(-1).abs() / dirs.norm(dim=-1)
        footprint = depth / (self.f * supersample * cos.clamp_min(1e-3).sqrt()) / self.face_texel[face]
        if self.families is None:
            albedo = self.texture.sample(tex_uv[:, 0], tex_uv[:, 1], footprint)
        else:
            family = self.face_family[face]
            albedo = torch.empty_like(depth)
            for k, tex in enumerate(self.families):  # loop over a handful of texture families
                idx = (family == k).nonzero().squeeze(1)
                if idx.numel() > 0:
                    albedo[idx] = tex.sample(tex_uv[idx, 0], tex_uv[idx, 1], footprint[idx])
        # Lambertian lighting from fixed point lights (view-independent, so left and right agree).
        irradiance = torch.zeros_like(depth)
        for light in self.lights:  # loop over a handful of lights
            to_light = light - pts
            r2 = (to_light * to_light).sum(-1)
            lam = ((to_light * normal).sum(-1) * r2.rsqrt()).clamp_min(0.0)
            irradiance += lam / (1.0 + r2 / self.light_range**2)
        shading = 0.55 + 0.45 * (1.0 - torch.exp(-1.5 * irradiance)) + self.sun_weight * self.face_sun[face]
        value = albedo * shading.clamp_max(1.0) * self.face_gain[face] + self.face_bias[face]
        return value.clamp(0.02, 0.98)

    def _dirs(self, R: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        cam = torch.stack([(x - self.cx) / self.f, (y - self.cy) / self.f, torch.ones_like(x)], -1)
        return cam @ R.T

    # -- one image

    def render_view(self, cam_T: np.ndarray, antialias: bool) -> tuple[torch.Tensor, torch.Tensor, list]:
        """Image ``(H, W)``, depth ``(H, W)`` and visible-face list seen from camera pose ``cam_T`` (world_T_cam)."""
        R = torch.as_tensor(cam_T[:3, :3], device=self.device, dtype=self.dtype)
        origin = torch.as_tensor(cam_T[:3, 3], device=self.device, dtype=self.dtype)
        faces = self.setup(cam_T)
        inv, face = self.cast_grid(faces)
        depth = 1.0 / inv  # every pixel sees a face of the room at least, so inv > 0
        self.depth_flat = depth.view(-1)
        yy, xx = torch.meshgrid(self.ys, self.xs, indexing="ij")
        dirs = self._dirs(R, xx.reshape(-1), yy.reshape(-1))
        value = self.shade(origin, dirs, depth.view(-1), face.view(-1)).view(self.h, self.w)
        if antialias:
            # Re-render pixels on geometric edges (where the face changes) with 4 rotated-grid samples.
            edge = torch.zeros_like(face, dtype=torch.bool)
            dx = face[:, 1:] != face[:, :-1]
            dy = face[1:, :] != face[:-1, :]
            edge[:, 1:] |= dx
            edge[:, :-1] |= dx
            edge[1:, :] |= dy
            edge[:-1, :] |= dy
            idx = edge.view(-1).nonzero().squeeze(1)
            if idx.numel() > 0:
                px, py, inv_s, face_s = self._supersample(faces, face, idx)
                dirs_s = self._dirs(R, px, py)
                vs = self.shade(origin, dirs_s, 1.0 / inv_s, face_s, supersample=2.0)
                value.view(-1)[idx] = vs.view(-1, 4).mean(-1)
        return value, depth, faces


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
