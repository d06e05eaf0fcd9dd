"""The world of a rendered sequence: the rig (:class:`RigPreset`), its smooth 6-DoF trajectory, the boxes of the
scene around that path, their texture families and the lights.

Poses, boxes and lights are float64 numpy arrays, drawn from the seeded generators that
:func:`egorefine.data.render_sequence` hands in (one per part, so that adding to one part leaves the others as they
were); :mod:`egorefine.data._raycast` renders them. Conventions are those of :mod:`egorefine.data.synthetic`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core import ValueRangeError
from ._families import FAMILY_NAMES

__all__ = ["RigPreset"]


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
        >>> from egorefine.data import PRESETS
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
