"""``egorefine run``: refine a recording and write its maps, trajectory and run.json; the deprecated ``folder``."""

from __future__ import annotations

import argparse
import functools
import os
import queue
import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

from .. import __version__
from ..core import ValueRangeError, progress
from ._shared import _FRAME_DIRS, _RUN_JSON, _TRAJECTORY_FILES, _write_json

# Colour of the preview pixels without a value (mid grey: outside the turbo colour map).
_INVALID_RGB = (128, 128, 128)
# The writer's threads and how many frames may wait for them before the refiner waits in turn.
_WRITER_THREADS = min(2, os.cpu_count() or 1)
_WRITER_DEPTH = 2 * _WRITER_THREADS


def parse_outputs(text: str) -> tuple[str, ...]:
    """The ``--outputs`` type: comma-separated names of per-frame outputs (``none``: trajectory and run.json only).

    Example:
        >>> parse_outputs("preview, disparity"), parse_outputs("none")
        (('disparity', 'preview'), ())
    """
    names = {name.strip() for name in text.split(",")}
    if names == {"none"}:
        return ()
    if not names <= set(_FRAME_DIRS):
        raise argparse.ArgumentTypeError(f"expected a comma-separated list of {', '.join(_FRAME_DIRS)} (or none "
                                         f"alone), got {text!r}")
    return tuple(name for name in _FRAME_DIRS if name in names)


def _read_ahead(rec, count: int) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """``rec[0], rec[1], ...`` up to ``count``, each read (decoded, rectified) on a thread of its own while the
    caller refines the one before: the reading overlaps the refining. One read at a time, in order (a recording's
    reader need not be thread-safe, only used by one thread at a time); a read's error is raised where its frame is
    taken."""
    with ThreadPoolExecutor(1, thread_name_prefix="egorefine-reader") as pool:
        ahead = pool.submit(rec.__getitem__, 0)
        for t in range(count):
            frame = ahead.result()
            if t + 1 < count:
                ahead = pool.submit(rec.__getitem__, t + 1)
            yield frame


class _Writer:
    """Runs jobs (writing one frame's files) on background threads while the caller refines the next frames.

    :meth:`submit` blocks while ``depth`` jobs wait, so at most that many frames are held in memory. The first
    error a job raises is raised again by the next :meth:`submit` or by :meth:`close`; the jobs queued after it
    are dropped. ``ms`` holds each finished job's time on its thread, ``wait_s`` the time the caller spent
    waiting for the threads (a full queue, the final drain).
    """

    def __init__(self, threads: int, depth: int):
        self._jobs: queue.Queue = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._stopped = False
        self.ms: list[float] = []
        self.wait_s = 0.0
        self._threads = [threading.Thread(target=self._work, name=f"egorefine-writer-{i}", daemon=True)
                         for i in range(threads)]
        for thread in self._threads:
            thread.start()

    def _work(self) -> None:
        while (job := self._jobs.get()) is not None:
            if self._error is not None or self._stopped:
                continue
            t0 = time.perf_counter()
            try:
                job()
            except BaseException as err:  # noqa: BLE001 - handed to the caller's thread, raised there
                self._error = self._error or err
            else:
                self.ms.append((time.perf_counter() - t0) * 1e3)

    def _raise(self) -> None:
        if self._error is not None:
            raise self._error

    def submit(self, job: Callable[[], object]) -> None:
        """Queue ``job``, waiting while the queue is full; raises the error of an earlier job."""
        self._raise()
        t0 = time.perf_counter()
        self._jobs.put(job)
        self.wait_s += time.perf_counter() - t0

    def close(self, drop: bool = False) -> None:
        """Wait for the queued jobs (or drop them) and end the threads; raises a job's error unless ``drop``."""
        if self._threads:
            self._stopped = drop
            t0 = time.perf_counter()
            for _ in self._threads:
                self._jobs.put(None)
            for thread in self._threads:
                thread.join()
            self._threads = []
            self.wait_s += time.perf_counter() - t0
        if not drop:
            self._raise()


def _write_frame(out: Path, stem: str, outputs: tuple[str, ...], fmt: str, png: str, max_disparity: int,
                 disparity: np.ndarray, valid: np.ndarray, confidence: np.ndarray | None) -> None:
    """Write the ``outputs`` of one frame (run on a writer thread, from arrays no later frame touches)."""
    from ..data import write_confidence, write_disparity, write_mask, write_preview
    from ..viz import disparity_palette_image

    if "disparity" in outputs:
        write_disparity(out / "disparity" / stem, disparity, valid, fmt, png)
    if "valid" in outputs:
        write_mask(out / "valid" / f"{stem}.png", valid)
    if "confidence" in outputs:
        write_confidence(out / "confidence" / stem, confidence, fmt, png)
    if "preview" in outputs:
        index, palette = disparity_palette_image(torch.from_numpy(disparity), max_disparity, torch.from_numpy(valid),
                                                 invalid_color=_INVALID_RGB)
        write_preview(out / "preview" / f"{stem}.png", index, png, palette)


def _own_copy(x: torch.Tensor) -> np.ndarray:
    """``x`` as a CPU numpy array sharing no memory with it (the refiner may reuse its tensors next frame)."""
    return x.detach().cpu().numpy().copy()


def _copied(result):
    """``result`` (a :class:`~egorefine.refine.RefinerOutput`) with copies of its tensors, for another thread."""
    return type(result)(*(x.detach().clone() if isinstance(x, torch.Tensor) else x for x in result))


def _device(name: str) -> torch.device:
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueRangeError(f"--device: expected cpu, cuda or cuda:N, got {name!r}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueRangeError(f"--device {name}: CUDA is not available on this machine (use --device cpu)")
    return device


def _check_rerun(text: str | None, out: Path, overwrite: bool) -> Path | None:
    """The ``--rerun`` file, checked before anything is read (None without the flag): the Rerun SDK is installed,
    the file's folder exists (or is ``out``, made by the run) and may be written, and no file is there already
    (unless ``overwrite``)."""
    if text is None:
        return None
    from .._rerun import require_rerun

    require_rerun()
    path = Path(text)
    folder = path.parent
    if path.is_dir():
        raise ValueRangeError(f"--rerun: {text!r} is a folder; expected a file name such as run.rrd")
    if folder.resolve() != out.resolve():
        if not folder.is_dir():
            raise ValueRangeError(f"--rerun: the folder {str(folder)!r} of {text!r} does not exist")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise ValueRangeError(f"--rerun: the folder {str(folder)!r} of {text!r} is not writable")
    if path.exists() and not overwrite:
        raise ValueRangeError(f"--rerun: {text!r} already exists; pass --overwrite to replace it or choose another "
                              "file")
    return path


def _check_output(out: Path, overwrite: bool) -> None:
    """Refuse an output folder that holds results of a run, finished or not (unless ``overwrite``)."""
    if out.exists() and not out.is_dir():
        raise ValueRangeError(f"--out: {str(out)!r} exists and is not a folder")
    found = [name for name in (_RUN_JSON, *_TRAJECTORY_FILES) if (out / name).exists()]
    found += [name + "/" for name in _FRAME_DIRS if (out / name).is_dir() and any((out / name).iterdir())]
    if found and not overwrite:
        raise ValueRangeError(f"--out: {str(out)!r} already holds results ({', '.join(found)}); "
                              "pass --overwrite to replace them or choose another folder")


def _clear_output(out: Path) -> None:
    """Delete what an earlier run wrote to ``out``; run.json first, so the folder stops looking finished."""
    for name in (_RUN_JSON, *_TRAJECTORY_FILES):
        (out / name).unlink(missing_ok=True)
    for name in _FRAME_DIRS:
        if (out / name).is_dir():
            shutil.rmtree(out / name)


def _nearest_rigid(poses: torch.Tensor) -> torch.Tensor:
    """Poses ``(T, 4, 4)`` with each rotation block replaced by the nearest rotation (SVD).

    Motions estimated in float32 compose to blocks that are orthonormal only to float32 precision; a TUM file
    stores a unit quaternion, so without this its poses and the KITTI file's would differ at that level.
    """
    U, _, Vh = torch.linalg.svd(poses[:, :3, :3])
    flip = torch.ones_like(poses[:, :3, 0])
    flip[:, 2] = torch.sign(torch.linalg.det(U @ Vh))
    out = poses.clone()
    out[:, :3, :3] = U @ torch.diag_embed(flip) @ Vh
    return out


def _write_trajectories(out: Path, prefix: str, poses: torch.Tensor, stamps: np.ndarray | None) -> list[str]:
    from ..data import atomic_path, write_kitti_poses, write_tum

    names = []
    for fmt in ("tum", "kitti"):
        name = f"{prefix}_{fmt}.txt"
        with atomic_path(out / name) as tmp:
            if fmt == "tum":
                write_tum(tmp, poses, stamps)
            else:
                write_kitti_poses(tmp, poses)
        names.append(name)
    return names


def _run_report(args: argparse.Namespace, rec, device: torch.device, frames: dict, files: list[str],
                timings: dict) -> dict:
    """What run.json holds: version, settings, calibration, frame counts, the meaning of each output written,
    timings."""
    H, W = rec.image_size
    suffix = _format_suffix(args.format)
    settings = {k: v for k, v in vars(args).items() if k not in ("func", "argv")}
    if args.frames is not None:
        start, stop, step = (("" if v is None else str(v)) for v in (args.frames.start, args.frames.stop,
                                                                     args.frames.step))
        settings["frames"] = f"{start}:{stop}" + (f":{step}" if step else "")
    per_frame = {
        "disparity": f"disparity/<frame>{suffix}: "
                     + {"png16": "uint16 PNG, disparity = value / 256 px, 0 = invalid",
                        "pfm": "float32 PFM, px, +inf = invalid",
                        "npy": "float32 npy, px, NaN = invalid"}[args.format],
        "valid": "valid/<frame>.png: uint8, 255 = valid",
        "confidence": f"confidence/<frame>{suffix}: 1 / (1 + variance px^2) in [0, 1]"
                      + (", stored as value / 65535" if args.format == "png16" else ""),
        "preview": f"preview/<frame>.png: turbo colour map, 0 to {args.max_disparity} px, grey = invalid "
                   "(indexed colour)",
    }
    return {
        "egorefine_version": __version__,
        "torch_version": torch.__version__,
        "command": ["egorefine", *(args.argv or [])],
        "settings": settings,
        "device": str(device),
        "threads": torch.get_num_threads(),
        "calibration": {
            "K": rec.K.double().cpu().tolist(),
            "baseline_m": float(rec.baseline),
            "image_size_hw": [int(H), int(W)],
            "rectified_input": bool(rec.rectified_input),
        },
        "frames": frames,
        **({"recording": rec.info} if getattr(rec, "info", None) else {}),
        "outputs": {
            **{name: text for name, text in per_frame.items() if name in args.outputs},
            "trajectory": files,
            "trajectory_frame": "world_T_camera of the rectified left camera; starts at the recording's first "
                                "true pose where it has one, else at the identity",
            **({"rerun": str(Path(args.rerun).resolve())} if getattr(args, "rerun", None) else {}),
        },
        "timings": timings,
    }


_ROSBAG_FLAGS = ("left_topic", "right_topic", "left_info_topic", "right_info_topic", "pair_tolerance")


def _layout_options(args: argparse.Namespace) -> dict:
    """:func:`egorefine.data.open_recording`'s keyword arguments for the layout's own flags (the rosbag topics);
    a flag given with a layout it does not belong to is an error."""
    flag = {name: getattr(args, name, None) for name in _ROSBAG_FLAGS}  # absent from a namespace built elsewhere
    if args.layout != "rosbag":
        given = [name for name, value in flag.items() if value is not None]
        if given:
            flags = ", ".join("--" + name.replace("_", "-") for name in given)
            raise ValueRangeError(f"{flags}: only --layout rosbag reads topics, got --layout {args.layout}")
        return {}
    if flag["left_topic"] is None or flag["right_topic"] is None:
        raise ValueRangeError("--layout rosbag: needs --left-topic and --right-topic (the cameras' image topics)")
    return dict(topics=(flag["left_topic"], flag["right_topic"]),
                info_topics=(flag["left_info_topic"], flag["right_info_topic"]), pair_tolerance=flag["pair_tolerance"])


def _refiner(args: argparse.Namespace):
    """The refiner the options of ``egorefine run`` ask for."""
    from ..refine import EgoMotionRefiner, StereoOptions

    cost, _, aggregation = args.matcher.partition("+")
    return EgoMotionRefiner(max_disparity=args.max_disparity, verify_every=args.verify_every, fusion=args.fusion,
                            motion_method=args.motion,
                            stereo=StereoOptions(cost=cost, aggregation=aggregation or "box",
                                                 fill=False if args.no_fill else None))


def _run(args: argparse.Namespace, on_progress: Callable[[int, int], object] | None = None) -> int:
    """``egorefine run`` from its parsed options; ``on_progress(done, total)``, where given, is called with
    ``(0, T)`` once the recording is open and ``(t + 1, T)`` after each frame (``egorefine run-many`` reports to
    its progress bar through it)."""
    from ..data import open_recording

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    device = _device(args.device)
    out = Path(args.out)
    _check_output(out, args.overwrite)  # before reading: a refusal costs nothing
    rerun_path = _check_rerun(getattr(args, "rerun", None), out, args.overwrite)
    t_start = time.perf_counter()
    rec = open_recording(args.input, args.layout, calib=args.calib, frames=args.frames, camera=args.camera,
                         **_layout_options(args))
    if not args.quiet:
        for note in getattr(rec, "notes", ()):  # e.g. a bag's frames left without a partner
            print(f"egorefine run: note: {note}", file=sys.stderr)
    T = len(rec)
    if T < 2:
        raise ValueRangeError(f"{args.input}: {T} frame(s) in the chosen range; refining needs at least 2 "
                              "(one to start from, one to predict)")
    H, W = rec.image_size
    if not args.max_disparity < W:
        raise ValueRangeError(f"--max-disparity: expected less than the image width {W}, got {args.max_disparity}")
    refiner = _refiner(args)
    K = rec.K.to(device=device, dtype=torch.float32)[None]
    baseline = torch.tensor([float(rec.baseline)], device=device)
    t_open = time.perf_counter() - t_start
    _clear_output(out)  # only once the input is known to be good: bad input leaves an earlier run as it was
    out.mkdir(parents=True, exist_ok=True)
    for name in args.outputs:
        (out / name).mkdir(exist_ok=True)
    if rerun_path is not None:
        rerun_path.unlink(missing_ok=True)  # an earlier run's (--overwrite): deleted with its other results

    world_T_camera = [torch.eye(4, dtype=torch.float64) if rec.poses is None else rec.poses[0].double().cpu()]
    refine_ms, stereo_frames, motion_failed = [], 0, 0
    state = None
    write = functools.partial(_write_frame, out, outputs=args.outputs, fmt=args.format, png=args.png,
                              max_disparity=args.max_disparity)
    writer = _Writer(_WRITER_THREADS, _WRITER_DEPTH)
    # The Rerun recording is logged on a thread of its own, one frame after the other (the trajectory grows in
    # order), from copies of the frame's tensors (the refiner may reuse them). Where the trajectory starts at the
    # identity, the world is the first camera's frame (right, down, forward); a true first pose puts it in the
    # recording's world, whose axes the viewer chooses.
    rerun = rerun_writer = None
    if rerun_path is not None:
        from .._rerun import RerunLogger

        rerun = RerunLogger(rerun_path, world_xyz="RDF" if rec.poses is None else None)
        rerun_writer = _Writer(1, _WRITER_DEPTH)
    t_loop = time.perf_counter()
    if on_progress is not None:
        on_progress(0, T)
    frames = _read_ahead(rec, T)
    try:
        with torch.no_grad():
            for t in progress(range(T), total=T, desc="egorefine run", enabled=not args.quiet):
                left, right = next(frames)
                left, right = left.to(device), right.to(device)
                t0 = time.perf_counter()
                result, state = refiner(left, right, K, baseline, state)
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                refine_ms.append((time.perf_counter() - t0) * 1e3)
                if t > 0:  # compose camera_t_T_camera_{t-1} into world_T_camera_t
                    world_T_camera.append(world_T_camera[-1] @ torch.linalg.inv(result.motion[0].double().cpu()))
                stereo_frames += bool(result.stereo_ran)
                motion_failed += int(not bool(result.motion_ok[0]))
                if rerun is not None:
                    rerun_writer.submit(functools.partial(
                        rerun.log_frame, t, left.clone(), _copied(result), K, baseline, world_T_camera[-1],
                        stamp=None if rec.timestamps is None else float(rec.timestamps[t])))
                if args.outputs:
                    confidence = _own_copy(result.confidence[0, 0]) if "confidence" in args.outputs else None
                    writer.submit(functools.partial(write, rec.names[t], disparity=_own_copy(result.disparity[0, 0]),
                                                    valid=_own_copy(result.valid[0, 0]), confidence=confidence))
                if on_progress is not None:
                    on_progress(t + 1, T)
        writer.close()  # the frames still queued are written (or their error raised) before anything else
        if rerun is not None:
            rerun_writer.close()
            rerun.close()  # flushed, finished and renamed into place
    finally:
        frames.close()  # (after an error: the read under way finishes, no other starts)
        writer.close(drop=True)
        if rerun is not None:
            rerun_writer.close(drop=True)
            rerun.discard()  # on an error: the unfinished recording is deleted (after close: nothing)
    loop_s = time.perf_counter() - t_loop

    poses = _nearest_rigid(torch.stack(world_T_camera))
    files = _write_trajectories(out, "trajectory", poses, rec.timestamps)
    if rec.poses is not None:
        files += _write_trajectories(out, "groundtruth", rec.poses.double().cpu(), rec.timestamps)
    timings = {
        "open_s": t_open,
        "total_s": time.perf_counter() - t_start,
        "loop_s": loop_s,
        "frames_per_s": T / loop_s,
        "refine_ms_first_frame": refine_ms[0],
        "refine_ms_median": float(np.median(refine_ms)),
        "refine_ms_mean_after_first": float(np.mean(refine_ms[1:])),
        "write_ms_mean": float(np.mean(writer.ms)) if writer.ms else 0.0,
        "writer_threads": _WRITER_THREADS,
        "writer_wait_s": writer.wait_s,
        "note": "loop_s: reading, refining and writing every frame, the wait for the last files included; "
                "frames_per_s = frames / loop_s; write_ms_mean: one frame's files on a writer thread, in parallel "
                "with refining; writer_wait_s: time refining waited for the writer; the first frame includes "
                "numba's compilation of the kernels",
    }
    if rerun_writer is not None:  # logging one frame to --rerun on its thread; the refining's wait for that thread
        timings["rerun_ms_mean"] = float(np.mean(rerun_writer.ms)) if rerun_writer.ms else 0.0
        timings["rerun_wait_s"] = rerun_writer.wait_s
    frames = {"count": T, "first": rec.names[0], "last": rec.names[-1], "stereo_ran": stereo_frames,
              "motion_failed": motion_failed, "has_groundtruth_poses": rec.poses is not None}
    report = _run_report(args, rec, device, frames, files, timings)
    _write_json(out / _RUN_JSON, report)
    if not args.quiet:
        print(f"egorefine run: {T} frames ({W}x{H}) -> {out}/ at {T / loop_s:.2f} frames/s (stereo on "
              f"{stereo_frames}, refining {float(np.median(refine_ms)):.1f} ms/frame median); trajectory: "
              f"{', '.join(files)}", file=sys.stderr)
    return 0


def _format_suffix(fmt: str) -> str:
    from ..data import DISPARITY_FORMATS

    return DISPARITY_FORMATS[fmt]


# -- folder (deprecated: run --layout folders does what it did) ---------------------------------------------------
def _folder(args: argparse.Namespace) -> int:
    from ..data import ImageFolderSequence, write_disparity
    from ..geometry import make_intrinsics
    from ..refine import EgoMotionRefiner

    print("egorefine folder: deprecated; use 'egorefine run INPUT --layout folders --calib FILE'", file=sys.stderr)
    torch.set_num_threads(args.threads)
    frames = ImageFolderSequence(args.left, args.right)
    if len(frames) < 2:
        raise ValueRangeError(f"--left: {len(frames)} frame(s); refining needs at least 2")
    K = make_intrinsics(args.focal, args.cx, args.cy)
    baseline = torch.tensor([args.baseline])
    refiner = EgoMotionRefiner(max_disparity=args.max_disparity, verify_every=args.verify_every, fusion=args.fusion)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    state = None
    with torch.no_grad():
        for t in progress(range(len(frames)), desc="egorefine folder", enabled=not args.quiet):
            left, right = frames[t]
            out, state = refiner(left, right, K, baseline, state)
            write_disparity(out_dir / f"{t:06d}", out.disparity[0, 0], out.valid[0, 0], "pfm")
    return 0
