"""Refined depth, images, poses and per-frame statistics as a Rerun recording (``.rrd``): :class:`RerunLogger`,
:func:`log_rerun`.

The Rerun SDK is an optional dependency (the ``rerun`` extra: ``pip install egorefine[rerun]``); it is imported
when a logger is made, never when :mod:`egorefine.viz` is. A logger only writes a file: no viewer is spawned and
nothing is sent over a network. Open the file with the viewer: ``rerun FILE.rrd``.
"""

from __future__ import annotations

import contextlib
import functools
import os
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .core import MissingExtraError, ShapeError, StateError, ValueRangeError, check_shape, require_extra
from .geometry import disparity_to_depth

__all__ = ["RERUN_ENTITIES", "RerunLogger", "RerunNotInstalledError", "log_rerun", "require_rerun"]

#: Entity path -> what :class:`RerunLogger` logs there, once per frame unless said otherwise.
RERUN_ENTITIES = {
    "world": "ViewCoordinates of the world frame (static; only where ``world_xyz`` is given)",
    "world/camera": "Transform3D world_T_camera of the rectified left camera, and its Pinhole (K, image size)",
    "world/camera/image": "Image: the left image, uint8 grey (L) or RGB",
    "world/camera/depth": "DepthImage: refined depth, float32 metres (f B / d where valid, 0 = no value), meter=1",
    "world/camera/valid": "SegmentationImage: uint8, 1 = valid, 0 = no value (class names in a static "
                          "AnnotationContext)",
    "world/camera/confidence": "Image: confidence in [0, 1], float32 grey (L)",
    "world/trajectory": "LineStrips3D: the camera positions of every frame so far",
    "stats/stereo": "Scalars: 1 where stereo matching ran on the frame, else 0",
    "stats/tracks": "Scalars: features tracked into the frame",
    "stats/motion": "Scalars: 1 where the ego-motion was solved, 0 where it failed (identity motion)",
    "stats/status": "Scalars: the frame's Status bits (0 = an ordinary frame)",
    "log/status": "TextLog: the names of the Status flags, on frames with any",
}

# Time stamps from this many seconds on are read as Unix time (2001 and later: recordings such as EuRoC and KITTI
# raw); smaller ones as seconds from the recording's start (KITTI odometry's times.txt), a "duration" timeline.
_UNIX_TIME_FROM_S = 1e9

# Classes of the validity image (Rerun draws class 0 transparent, class 1 in green).
_VALID_CLASSES = [(0, "no value", (0, 0, 0, 0)), (1, "valid", (40, 200, 80, 255))]


class RerunNotInstalledError(MissingExtraError):
    """The Rerun SDK, an optional dependency (the ``rerun`` extra), is not installed.

    Example:
        >>> issubclass(RerunNotInstalledError, ImportError)  # ``except ImportError`` still catches it
        True
    """


# the module, or a one-line error naming the extra that installs it
require_rerun = functools.partial(require_extra, "rerun", "rerun", "the Rerun SDK", RerunNotInstalledError)


def _item(x: torch.Tensor | np.ndarray | float, item: int, name: str, dims: list[str],
          bound: dict[str, int] | None = None) -> torch.Tensor:
    """Item ``item`` of ``x`` of shape ``["B", *dims]`` as a CPU tensor; ``x`` of shape ``dims`` holds for every
    item and is returned as it is. Named sizes must match ``bound`` (not changed here)."""
    x = torch.as_tensor(x).detach()
    bound = dict(bound or {})
    if x.dim() == len(dims):
        check_shape(x, dims, name, bound)
        return x.cpu()
    check_shape(x, ["B", *dims], name, bound)
    if not -x.shape[0] <= item < x.shape[0]:
        raise ShapeError(f"{name}: item {item} asked of a batch of {x.shape[0]}")
    return x[item].cpu()


def _to_uint8(image: torch.Tensor) -> np.ndarray:
    """``(C, H, W)`` float image in [0, 1] -> ``(H, W)`` or ``(H, W, 3)`` uint8 (a new array)."""
    u8 = (image.float().clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)
    return u8[0].numpy().copy() if u8.shape[0] == 1 else u8.permute(1, 2, 0).numpy().copy()


def _depth_from_disparity(disparity: torch.Tensor, valid: torch.Tensor, focal: float | torch.Tensor,
                         baseline: float | torch.Tensor) -> torch.Tensor:
    """Depth ``f B / d`` in metres where ``valid`` and ``d > 0``, 0 elsewhere (a depth image's "no value"); also
    0 where ``f B / d`` overflows the dtype.

    Args:
        disparity: ``(..., H, W)`` px.
        valid: bool of the same shape.
        focal: focal length, px.
        baseline: metres.

    Returns:
        float depth of ``disparity``'s shape and dtype.

    Example:
        >>> _depth_from_disparity(torch.tensor([[4.0, 0.0, 8.0]]), torch.tensor([[True, True, False]]), 400.0, 0.1)
        tensor([[10.,  0.,  0.]])
    """
    d = disparity.float() if not disparity.is_floating_point() else disparity
    as_b = lambda x: torch.as_tensor(x, dtype=d.dtype).reshape(1)  # noqa: E731
    # a valid d however small is divided by (a clamp at the dtype's smallest normal value only keeps d <= 0 finite);
    # pixels without a value, and a depth beyond the dtype's range, become 0 (a depth image's "no value")
    depth = disparity_to_depth(d[None], as_b(focal), as_b(baseline), torch.finfo(d.dtype).tiny)[0]
    return torch.where(valid.bool() & (d > 0) & torch.isfinite(depth), depth, torch.zeros_like(d))


class RerunLogger:
    """Logs the refiner's frames to a Rerun recording file (``.rrd``): images, depth as a 3-D point cloud under the
    rig's pinhole camera, validity, confidence, the camera's pose and path, and per-frame statistics.

    One recording stream that writes only to ``path`` (no viewer, no network). The file is written under a
    temporary name beside ``path`` (``.NAME.partial.rrd``) and renamed to ``path`` by :meth:`close`, so a file at
    ``path`` is always a finished recording; :meth:`discard` (or leaving a ``with`` block on an error) deletes the
    temporary file. Each :meth:`log_frame` copies what it logs, so the caller may reuse its tensors at once; call
    it from one thread at a time, in frame order (the path grows in the order of the calls).

    Entity paths (:data:`RERUN_ENTITIES`): ``world/camera`` carries the pose (``Transform3D``, world_T_camera)
    and the pinhole (K and the image size), so the viewer's 3-D view shows ``world/camera/depth`` as a point cloud
    seen from the camera; ``world/camera/image``, ``world/camera/valid`` and ``world/camera/confidence`` lie in
    the same image space; ``world/trajectory`` is the line through the camera positions so far (frame t logs the
    whole path, 12 (t + 1) bytes: less than its depth image for the first 100 000 frames of a 752x480 video);
    ``stats/stereo``, ``stats/tracks``, ``stats/motion`` and ``stats/status`` are time series; ``log/status`` names
    the Status flags of frames that have any.

    Timelines: the sequence ``frame`` (the ``t`` given to :meth:`log_frame`) and, for frames logged with a
    ``stamp``, ``time``: a timestamp where the stamps are Unix time (1e9 s, 2001, and later), else a duration from
    the recording's start (the kind is fixed by the first stamp).

    Args:
        path: the ``.rrd`` file to write; its folder must exist.
        world_xyz: axes of the world frame as Rerun's ``ViewCoordinates`` name, e.g. ``"RDF"`` (default: right,
            down, forward, the camera frame of docs/method.md, right where the trajectory starts at the identity) or
            ``"RIGHT_HAND_Z_UP"``; None leaves it to the viewer (a world frame of a motion-capture system).
        application_id: the recording's application id in the viewer.

    Raises:
        RerunNotInstalledError: the Rerun SDK is not installed.

    Example:
        >>> import tempfile
        >>> from egorefine.refine import RefinerOutput
        >>> H, W = 24, 32
        >>> out = RefinerOutput(disparity=torch.full((1, 1, H, W), 4.0), valid=torch.ones(1, 1, H, W, dtype=torch.bool),
        ...                     motion=torch.eye(4)[None], stereo_ran=True, variance=torch.ones(1, 1, H, W),
        ...                     confidence=torch.full((1, 1, H, W), 0.5), motion_ok=torch.tensor([True]),
        ...                     num_tracks=torch.tensor([0]), status=torch.tensor([0]))
        >>> K = torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]])
        >>> path = Path(tempfile.mkdtemp()) / "one.rrd"
        >>> with RerunLogger(path) as logger:
        ...     logger.log_frame(0, torch.rand(1, 1, H, W), out, K, 0.1, torch.eye(4), stamp=1403715273.26)
        >>> sorted(p.name for p in path.parent.iterdir())  # renamed into place at the end of the block
        ['one.rrd']
    """

    def __init__(self, path: str | os.PathLike, world_xyz: str | None = "RDF", application_id: str = "egorefine"):
        rr = require_rerun()
        self._rr = rr
        self.path = Path(path)
        if not self.path.parent.is_dir():
            raise FileNotFoundError(f"{str(self.path)!r}: the folder {str(self.path.parent)!r} does not exist")
        self._tmp = self.path.with_name(f".{self.path.stem}.partial{self.path.suffix}")
        view = None
        if world_xyz is not None:
            view = getattr(rr.ViewCoordinates, world_xyz, None)
            if not isinstance(view, rr.components.ViewCoordinates):
                raise ValueRangeError(f"world_xyz: expected a name of rerun.ViewCoordinates such as 'RDF', got "
                                      f"{world_xyz!r}")
        # A fresh recording id: two loggers of one process must not merge into one recording.
        self._rec = rr.RecordingStream(application_id, recording_id=uuid.uuid4())
        self._rec.set_log_time_enabled(False)  # only the timelines said above: no wall clock of the logging
        self._rec.set_log_tick_enabled(False)
        self._rec.save(self._tmp)
        self._closed = False
        self._path: list[list[float]] = []
        self._time_kind: str | None = None
        self._rec.log("world/camera/valid", rr.AnnotationContext(_VALID_CLASSES), static=True)
        if view is not None:
            self._rec.log("world", view, static=True)

    def __enter__(self) -> RerunLogger:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.discard()

    def _check_open(self) -> None:
        if self._closed:
            raise StateError(f"RerunLogger({str(self.path)!r}): already closed")

    def _set_time(self, t: int, stamp: float | None) -> None:
        self._rec.reset_time()  # a frame without a stamp must not inherit the previous frame's
        self._rec.set_time("frame", sequence=int(t))
        if stamp is None:
            return
        stamp = float(stamp)
        if self._time_kind is None:
            self._time_kind = "timestamp" if stamp >= _UNIX_TIME_FROM_S else "duration"
        self._rec.set_time("time", **{self._time_kind: stamp})

    def log_frame(
        self,
        t: int,
        left: torch.Tensor,
        result: Any,
        K: torch.Tensor,
        baseline: torch.Tensor | float,
        world_T_camera: torch.Tensor,
        stamp: float | None = None,
        item: int = 0,
    ) -> None:
        """Log one frame at time ``frame = t`` (and ``time = stamp``): what the class docstring lists.

        Args:
            t: the frame's index on the ``frame`` timeline.
            left: ``(B, C, H, W)`` (or ``(C, H, W)``) left image in [0, 1], C = 1 or 3.
            result: the refiner's :class:`~egorefine.refine.RefinerOutput` of this frame (batched like ``left``).
            K: ``(B, 3, 3)`` or ``(3, 3)`` intrinsics of the rectified left camera, px.
            baseline: ``(B,)`` or a float, metres.
            world_T_camera: ``(B, 4, 4)`` or ``(4, 4)`` pose of the camera in the world.
            stamp: the frame's time in seconds (Unix time or from the start), or None: no ``time`` for this frame.
            item: which item of the batch to log.
        """
        self._check_open()
        rr, rec = self._rr, self._rec
        image = _item(left, item, "left", ["1|3", "H", "W"])
        dims = {"H": image.shape[1], "W": image.shape[2]}
        disparity = _item(result.disparity, item, "result.disparity", ["1", "H", "W"], dims)[0]
        valid = _item(result.valid, item, "result.valid", ["1", "H", "W"], dims)[0]
        confidence = _item(result.confidence, item, "result.confidence", ["1", "H", "W"], dims)[0]
        K_i = _item(K, item, "K", ["3", "3"]).double()
        b = _item(baseline, item, "baseline", [])
        pose = _item(world_T_camera, item, "world_T_camera", ["4", "4"]).double()
        H, W = dims["H"], dims["W"]

        self._set_time(t, stamp)
        position = pose[:3, 3].tolist()
        self._path.append(position)
        rec.log("world/camera", rr.Transform3D(translation=position, mat3x3=pose[:3, :3].numpy()),
                rr.Pinhole(image_from_camera=K_i.numpy(), resolution=[W, H]))
        rec.log("world/camera/image", rr.Image(_to_uint8(image), color_model="L" if image.shape[0] == 1 else "RGB"))
        depth = _depth_from_disparity(disparity.float(), valid, float(K_i[0, 0]), float(b))
        rec.log("world/camera/depth", rr.DepthImage(depth.numpy().copy(), meter=1.0))
        rec.log("world/camera/valid", rr.SegmentationImage(valid.to(torch.uint8).numpy().copy()))
        rec.log("world/camera/confidence", rr.Image(confidence.float().numpy().copy(), color_model="L"))
        rec.log("world/trajectory", rr.LineStrips3D([np.asarray(self._path, dtype=np.float32)]))
        stereo = result.stereo_ran
        stereo = bool(stereo[item] if isinstance(stereo, torch.Tensor) and stereo.dim() else stereo)
        status = int(_item(result.status, item, "result.status", []))
        rec.log("stats/stereo", rr.Scalars(float(stereo)))
        rec.log("stats/tracks", rr.Scalars(float(_item(result.num_tracks, item, "result.num_tracks", []))))
        rec.log("stats/motion", rr.Scalars(float(bool(_item(result.motion_ok, item, "result.motion_ok", [])))))
        rec.log("stats/status", rr.Scalars(float(status)))
        if status:
            from .refine import Status

            rec.log("log/status", rr.TextLog(str(Status(status).name), level="WARN"))

    def close(self) -> Path:
        """Flush the recording, finish the file (its footer) and rename it to the path the logger was made with;
        returns that path. Closing twice does nothing more."""
        if not self._closed:
            self._rec.flush()
            self._rec.disconnect()  # finishes the file sink: the footer is written and the file closed
            os.replace(self._tmp, self.path)
            self._closed = True  # only now: where finishing failed, discard() still deletes the temporary file
        return self.path

    def discard(self) -> None:
        """Stop logging and delete the unfinished file (after :meth:`close`: nothing)."""
        if not self._closed:
            self._closed = True
            self._rec.disconnect()
            with contextlib.suppress(FileNotFoundError):
                self._tmp.unlink()


def _poses_from_motions(motions: torch.Tensor, start: torch.Tensor | None = None) -> torch.Tensor:
    """``(T, 4, 4)`` world_T_camera composed from ``(T, 4, 4)`` camera_t_T_camera_{t-1} (the first ignored),
    starting at ``start`` (default: the identity)."""
    poses = [torch.eye(4, dtype=torch.float64) if start is None else start.double().cpu()]
    for motion in motions[1:]:
        poses.append(poses[-1] @ torch.linalg.inv(motion.double().cpu()))
    return torch.stack(poses)


def log_rerun(
    path: str | os.PathLike,
    lefts: torch.Tensor,
    results: Any,
    K: torch.Tensor,
    baseline: torch.Tensor | float,
    poses: torch.Tensor | None = None,
    stamps: Sequence[float] | np.ndarray | None = None,
    item: int = 0,
    world_xyz: str | None = "RDF",
) -> Path:
    """Write a whole refined sequence to a Rerun recording (``.rrd``) with :class:`RerunLogger`; open it with
    ``rerun FILE.rrd``.

    Entity paths and timelines as :class:`RerunLogger` (and :data:`RERUN_ENTITIES`) describe: per frame the left
    image, the refined depth under the camera's pinhole (a point cloud in the viewer's 3-D view), validity,
    confidence, the pose and the path so far, and the statistics ``stats/stereo``, ``stats/tracks``,
    ``stats/motion``, ``stats/status``.

    Args:
        path: the ``.rrd`` file to write (its folder must exist); replaced if it exists.
        lefts: ``(T, B, C, H, W)`` (or ``(T, C, H, W)``) left images in [0, 1], as given to
            :func:`~egorefine.refine.refine_sequence`.
        results: the :class:`~egorefine.refine.SequenceResult` of :func:`~egorefine.refine.refine_sequence`, or a
            list of T :class:`~egorefine.refine.RefinerOutput`.
        K: ``(B, 3, 3)`` or ``(3, 3)`` intrinsics, px.
        baseline: ``(B,)`` or a float, metres.
        poses: ``(T, 4, 4)`` or ``(T, B, 4, 4)`` world_T_camera; default: composed from the results' motions,
            starting at the identity (the first camera's frame is the world).
        stamps: ``(T,)`` seconds, or None: the ``frame`` timeline only.
        item: which item of the batch to log.
        world_xyz: axes of the world frame (:class:`RerunLogger`); the default ``"RDF"`` fits the default poses.

    Returns:
        ``path``.

    Raises:
        RerunNotInstalledError: the Rerun SDK is not installed.
        ShapeError: ``lefts``, ``results``, ``poses`` or ``stamps`` disagree on T or on a shape.

    Example:
        >>> import tempfile
        >>> from egorefine.data import render_sequence
        >>> from egorefine.refine import TrackingOptions, refine_sequence
        >>> seq = render_sequence(num_frames=3, height=40, width=56)
        >>> res = refine_sequence(seq.left, seq.right, seq.K, seq.baseline, max_disparity=8,
        ...                       tracking=TrackingOptions(max_features=64, min_tracks=16))
        >>> path = log_rerun(Path(tempfile.mkdtemp()) / "seq.rrd", seq.left, res, seq.K, seq.baseline)
        >>> path.name, path.stat().st_size > 0
        ('seq.rrd', True)
    """
    from .refine import RefinerOutput, SequenceResult

    require_rerun()  # before any check: a missing SDK is the first thing to know
    lefts = torch.as_tensor(lefts)
    if lefts.dim() == 4:
        lefts = lefts[:, None]
    check_shape(lefts, ["T", "B", "1|3", "H", "W"], "lefts")
    T = lefts.shape[0]
    if isinstance(results, SequenceResult):
        frames = [RefinerOutput(results.disparity[t], results.valid[t], results.motion[t],
                                bool(results.stereo_ran[t]), results.variance[t], results.confidence[t],
                                results.motion_ok[t], results.num_tracks[t], results.status[t])
                  for t in range(results.disparity.shape[0])]
    else:
        frames = list(results)
    if len(frames) != T:
        raise ShapeError(f"results: expected {T} frames (those of lefts), got {len(frames)}")
    if poses is None:
        motions = torch.stack([_item(f.motion, item, "results.motion", ["4", "4"]) for f in frames])
        poses = _poses_from_motions(motions)
    else:
        poses = torch.as_tensor(poses)
        check_shape(poses, [str(T), "4", "4"] if poses.dim() == 3 else [str(T), "B", "4", "4"], "poses")
    if stamps is not None and len(stamps) != T:
        raise ShapeError(f"stamps: expected {T} time stamps (one per frame of lefts), got {len(stamps)}")
    with RerunLogger(path, world_xyz=world_xyz) as logger:
        for t, frame in enumerate(frames):
            logger.log_frame(t, lefts[t], frame, K, baseline, poses[t], None if stamps is None else float(stamps[t]),
                             item=item)
    return Path(path)
