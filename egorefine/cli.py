"""The ``egorefine`` command: refine stereo video with the rig's ego-motion, from the shell.

``egorefine demo`` renders the built-in synthetic sequence (the paper's rig), scores per-frame stereo and the
refiner against its exact ground truth and draws pictures. ``egorefine run`` refines a recorded sequence
(image folders with a calibration file, KITTI raw, KITTI odometry, EuRoC) and writes per-frame disparity, valid
mask, confidence and preview files plus the trajectory in TUM and KITTI formats. ``egorefine eval`` scores
disparity maps and trajectories against truth.

Bad input (a missing file, a calibration that does not parse, too few frames, an output folder that already holds
results) ends with one line ``egorefine <command>: error: ...`` on stderr and exit status 2; ``--debug`` shows the
traceback instead.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch

from . import __version__
from .core import EgorefineError, ValueRangeError, progress

__all__ = ["main", "parse_frame_range"]

# What `egorefine run` writes into its output folder (run.json last: its presence means the run finished).
_FRAME_DIRS = ("disparity", "valid", "confidence", "preview")
_TRAJECTORY_FILES = ("trajectory_tum.txt", "trajectory_kitti.txt", "groundtruth_tum.txt", "groundtruth_kitti.txt")
_RUN_JSON = "run.json"
# Matcher choices of `egorefine run`: COST or COST+sgm, passed to the refiner as stereo_cost / aggregation.
_MATCHERS = ("sad", "zncc", "census", "sad+sgm", "zncc+sgm", "census+sgm")
_INVALID_RGB = (128, 128, 128)
_EXAMPLES = """examples:
  egorefine demo --frames 8 --out results/demo
  egorefine run my_rig/ --layout folders --calib my_rig/stereo.yaml --out out/
  egorefine run raw/2011_09_26/2011_09_26_drive_0001_sync --layout kitti-raw --out out/
  egorefine run odometry/dataset/sequences/00 --layout kitti-odometry --frames 0:200 --out out/
  egorefine run V1_01_easy --layout euroc --max-disparity 48 --out out/
  egorefine eval out/ truth/ --traj out/trajectory_tum.txt --gt-traj out/groundtruth_tum.txt --json scores.json"""


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Help with each option's default appended (where it has one its help does not already state)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if default is None or default is False or default == argparse.SUPPRESS or "default" in text \
                or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)"


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr and exit status 2."""

    def error(self, message: str):  # noqa: D102 - argparse's hook
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _table(rows: list[list[object]], header: list[str]) -> str:
    cells = [[f"{v:.3f}" if isinstance(v, float) else str(v) for v in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) for i, h in enumerate(header)]
    line = "  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))
    body = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) for r in cells]
    return "\n".join([line, "-" * len(line), *body])


def _at_least(minimum: int):
    """An argparse type: an int no smaller than ``minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {value}")
        return value

    return parse


def _only_one(text: str) -> int:
    """The ``--batch-size`` type: 1 is the only batch size a single sequence can have."""
    if text.strip() != "1":
        raise argparse.ArgumentTypeError(f"only 1 is possible, got {text!r}: the frames of a sequence are refined "
                                         "in order, each from the state the previous one left")
    return 1


def parse_frame_range(text: str) -> slice:
    """``START:STOP`` or ``START:STOP:STEP`` (each part optional, non-negative) as a :class:`slice` of frames.

    Args:
        text: e.g. ``"0:6"`` (frames 0 to 5), ``"100:"`` (from frame 100 on), ``":50:2"`` (every other frame
            of the first 50).

    Returns:
        The slice, ``None`` for parts left out.

    Raises:
        argparse.ArgumentTypeError: not of that form, a negative number, a step below 1 or STOP <= START.

    Example:
        >>> parse_frame_range("0:6"), parse_frame_range("10:")
        (slice(0, 6, None), slice(10, None, None))
    """
    parts = text.split(":")
    if len(parts) not in (2, 3):
        raise argparse.ArgumentTypeError(f"expected START:STOP or START:STOP:STEP, got {text!r}")
    try:
        values = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected integers in START:STOP[:STEP], got {text!r}") from None
    start, stop, step = (values + [None])[:3]
    if any(v is not None and v < 0 for v in (start, stop)) or (step is not None and step < 1):
        raise argparse.ArgumentTypeError(f"expected START, STOP >= 0 and STEP >= 1, got {text!r}")
    if start is not None and stop is not None and stop <= start:
        raise argparse.ArgumentTypeError(f"expected STOP > START, got {text!r}")
    return slice(start, stop, step)


def _device(name: str) -> torch.device:
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueRangeError(f"--device: expected cpu, cuda or cuda:N, got {name!r}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueRangeError(f"--device {name}: CUDA is not available on this machine (use --device cpu)")
    return device


def _nan_where(disparity: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """A map with NaN where ``valid`` is False: how figures tell "no value" from disparity 0."""
    return torch.where(valid.bool(), disparity, torch.full_like(disparity, float("nan")))


def _figure(save, *args, **kwargs) -> Path | None:
    """Call a figure writer of :mod:`egorefine.viz`; None (and a note) where matplotlib is missing."""
    try:
        return save(*args, **kwargs)
    except ImportError:
        print("figure skipped: matplotlib is not installed", file=sys.stderr)
        return None


# -- demo ---------------------------------------------------------------------------------------------------------
def _demo(args: argparse.Namespace) -> int:
    from .data import render_sequence
    from .metrics import compose_motions, distinct_levels, evaluate_disparity, evaluate_trajectory
    from .refine import StereoOptions, refine_sequence
    from .stereo import block_matching
    from .viz import save_maps_figure, save_row_figure, save_trajectory_figure

    torch.set_num_threads(args.threads)
    out_dir = Path(args.out)
    t0 = time.perf_counter()
    seq = render_sequence(num_frames=args.frames, preset=args.preset, seed=args.seed, height=args.height,
                          width=args.width, noise_std=args.noise, show_progress=not args.quiet)
    T, _, H, W = seq.left.shape
    if not args.quiet:
        print(f"rendered {T} frames of {W}x{H} ({args.preset} preset, f={seq.K[0, 0]:.0f} px, "
              f"baseline={seq.baseline:.3f} m, noise {args.noise:g}) in {time.perf_counter() - t0:.1f} s",
              file=sys.stderr)
    K, baseline = seq.K[None], torch.tensor([seq.baseline])
    gt_mask = (seq.disparity > 0) & ~seq.occluded
    modes = {"paper": ("linear", False), "kalman": ("exact", True)}  # motion solve, sub-pixel stereo

    def score(disp: torch.Tensor, valid: torch.Tensor) -> dict[str, float]:
        return evaluate_disparity(disp[1:], seq.disparity[1:], valid[1:], gt_mask[1:])

    # Warm-up: numba compiles each kernel on its first call in a process; timing starts after it.
    warm = slice(0, min(3, T))
    for subpixel in (False, True):
        block_matching(seq.left[:1], seq.right[:1], args.max_disparity, subpixel=subpixel)
    for fusion, (motion, subpixel) in modes.items():
        refine_sequence(seq.left[warm], seq.right[warm], K, baseline, verify_every=2, fusion=fusion,
                        motion_method=motion, stereo=StereoOptions(subpixel=subpixel), max_disparity=args.max_disparity)

    results: dict[str, tuple[dict[str, float], float, int, torch.Tensor, torch.Tensor]] = {}
    for name, subpixel in (("stereo per frame, integer", False), ("stereo per frame, sub-pixel", True)):
        t0 = time.perf_counter()
        outs = [block_matching(seq.left[t : t + 1], seq.right[t : t + 1], args.max_disparity, subpixel=subpixel)
                for t in range(T)]
        ms = (time.perf_counter() - t0) * 1e3 / T
        disp, valid = torch.cat([o[0] for o in outs]), torch.cat([o[1] for o in outs])
        results[name] = (score(disp, valid), ms, T, _nan_where(disp[:, 0], valid[:, 0]), torch.eye(4).repeat(T, 1, 1))
    for fusion, (motion, subpixel) in modes.items():
        # Paper mode as published: pixel-accurate stereo and the linear motion solve (eq. 3).
        t0 = time.perf_counter()
        res = refine_sequence(seq.left, seq.right, K, baseline, verify_every=args.verify_every, fusion=fusion,
                              motion_method=motion, stereo=StereoOptions(subpixel=subpixel),
                              max_disparity=args.max_disparity,
                              show_progress=not args.quiet)
        ms = (time.perf_counter() - t0) * 1e3 / T
        stereo = "integer" if not subpixel else "sub-pixel"
        name = f"{fusion} mode ({stereo} stereo, {motion} motion), verify every {args.verify_every}"
        results[name] = (score(res.disparity[:, 0], res.valid[:, 0]), ms, int(res.stereo_ran.sum()),
                         _nan_where(res.disparity[:, 0, 0], res.valid[:, 0, 0]), res.motion[:, 0])

    header = ["method", "EPE px", "median px", "bad-0.5", "bad-1", "density", "stereo frames", "ms/frame"]
    rows = [[k, m["epe"], m["median"], m["bad-0.5"], m["bad-1"], m["density"], f"{n}/{T}", ms]
            for k, (m, ms, n, _, _) in results.items()]
    print(_table(rows, header))
    print("(errors over frames 1..T-1 on pixels each method marks valid; density = share of pixels with truth;\n"
          f" ms/frame on {torch.get_num_threads()} thread(s), timed after a warm-up run that compiles the kernels)")

    last = T - 1
    truth = _nan_where(seq.disparity[last, 0], gt_mask[last, 0])
    kalman = next(k for k in results if k.startswith("kalman"))
    est_poses = seq.poses[0].to(torch.float64) @ compose_motions(results[kalman][4].to(torch.float64))
    traj = evaluate_trajectory(est_poses, seq.poses.to(torch.float64))
    print(f"trajectory ({kalman.split(' (')[0]}): ATE {traj['ate_rmse_m']:.4f} m, frame-to-frame RPE "
          f"{traj['rpe_translation_rmse_m']:.4f} m / {traj['rpe_rotation_mean_deg']:.3f} deg over a "
          f"{traj['path_length_m']:.2f} m path")

    row = H // 2 + H // 8
    curves = {"ground truth": truth}
    for k, (_, _, _, disp, _) in results.items():
        curves[k.split(" (")[0].replace("stereo per frame,", "stereo,")] = disp[last]
    levels = {k: distinct_levels(v[row][torch.isfinite(v[row])]) for k, v in curves.items()}
    print("distinct disparity levels along row", row, ":", ", ".join(f"{k}: {v}" for k, v in levels.items()))
    vmax = float(seq.disparity.max())
    figures = [
        _figure(save_row_figure, out_dir / "demo_row.png", row, curves, max_disparity=vmax,
                title=f"frame {last}: disparity along row {row}"),
        _figure(save_maps_figure, out_dir / "demo_maps.png", seq.left[last, 0],
                {"stereo (sub-pixel)": results["stereo per frame, sub-pixel"][3][last],
                 "refined (kalman)": results[kalman][3][last]},
                truth=truth, max_disparity=vmax, title=f"frame {last}; grey: no value"),
        _figure(save_trajectory_figure, out_dir / "demo_trajectory.png",
                {"truth": seq.poses, "estimated (kalman)": est_poses}),
    ]
    for fig in figures:
        if fig is not None:
            print(f"figure: {fig}")
    return 0


# -- run ----------------------------------------------------------------------------------------------------------
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


def _write_json(path: Path, data: dict) -> Path:
    from .data import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")
    return path


def _write_trajectories(out: Path, prefix: str, poses: torch.Tensor, stamps: np.ndarray | None) -> list[str]:
    from .data import atomic_path, write_kitti_poses, write_tum

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
    """What run.json holds: version, settings, calibration, frame counts, the meaning of each output, timings."""
    H, W = rec.image_size
    suffix = _format_suffix(args.format)
    settings = {k: v for k, v in vars(args).items() if k not in ("func", "argv")}
    if args.frames is not None:
        start, stop, step = (("" if v is None else str(v)) for v in (args.frames.start, args.frames.stop,
                                                                     args.frames.step))
        settings["frames"] = f"{start}:{stop}" + (f":{step}" if step else "")
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
        "outputs": {
            "disparity": f"disparity/<frame>{suffix}: "
                         + {"png16": "uint16 PNG, disparity = value / 256 px, 0 = invalid",
                            "pfm": "float32 PFM, px, +inf = invalid",
                            "npy": "float32 npy, px, NaN = invalid"}[args.format],
            "valid": "valid/<frame>.png: uint8, 255 = valid",
            "confidence": f"confidence/<frame>{suffix}: 1 / (1 + variance px^2) in [0, 1]"
                          + (", stored as value / 65535" if args.format == "png16" else ""),
            "preview": f"preview/<frame>.png: turbo colour map, 0 to {args.max_disparity} px, grey = invalid",
            "trajectory": files,
            "trajectory_frame": "world_T_camera of the rectified left camera; starts at the recording's first "
                                "true pose where it has one, else at the identity",
        },
        "timings": timings,
    }


def _run(args: argparse.Namespace) -> int:
    from .data import open_recording, write_confidence, write_disparity, write_mask, write_preview
    from .refine import EgoMotionRefiner, StereoOptions
    from .viz import colorize_disparity

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    device = _device(args.device)
    out = Path(args.out)
    _check_output(out, args.overwrite)  # before reading: a refusal costs nothing
    t_start = time.perf_counter()
    rec = open_recording(args.input, args.layout, calib=args.calib, frames=args.frames, camera=args.camera)
    T = len(rec)
    if T < 2:
        raise ValueRangeError(f"{args.input}: {T} frame(s) in the chosen range; refining needs at least 2 "
                              "(one to start from, one to predict)")
    H, W = rec.image_size
    if not args.max_disparity < W:
        raise ValueRangeError(f"--max-disparity: expected less than the image width {W}, got {args.max_disparity}")
    cost, _, aggregation = args.matcher.partition("+")
    refiner = EgoMotionRefiner(max_disparity=args.max_disparity, verify_every=args.verify_every, fusion=args.fusion,
                               motion_method=args.motion,
                               stereo=StereoOptions(cost=cost, aggregation=aggregation or "box"))
    K = rec.K.to(device=device, dtype=torch.float32)[None]
    baseline = torch.tensor([float(rec.baseline)], device=device)
    t_open = time.perf_counter() - t_start
    _clear_output(out)  # only once the input is known to be good: bad input leaves an earlier run as it was
    for name in _FRAME_DIRS:
        (out / name).mkdir(parents=True, exist_ok=True)

    world_T_camera = [torch.eye(4, dtype=torch.float64) if rec.poses is None else rec.poses[0].double().cpu()]
    refine_ms, write_ms, stereo_frames, motion_failed = [], [], 0, 0
    state = None
    with torch.no_grad():
        for t in progress(range(T), total=T, desc="egorefine run", enabled=not args.quiet):
            left, right = rec[t]
            left, right = left.to(device), right.to(device)
            t0 = time.perf_counter()
            result, state = refiner(left, right, K, baseline, state)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            refine_ms.append((time.perf_counter() - t0) * 1e3)
            t0 = time.perf_counter()
            if t > 0:  # compose camera_t_T_camera_{t-1} into world_T_camera_t
                world_T_camera.append(world_T_camera[-1] @ torch.linalg.inv(result.motion[0].double().cpu()))
            stereo_frames += bool(result.stereo_ran)
            motion_failed += int(not bool(result.motion_ok[0]))
            disp, valid = result.disparity[0, 0].cpu(), result.valid[0, 0].cpu()
            stem = rec.names[t]
            write_disparity(out / "disparity" / stem, disp, valid, args.format)
            write_mask(out / "valid" / f"{stem}.png", valid)
            write_confidence(out / "confidence" / stem, result.confidence[0, 0].cpu(), args.format)
            write_preview(out / "preview" / f"{stem}.png",
                          colorize_disparity(disp, args.max_disparity, valid, invalid_color=_INVALID_RGB))
            write_ms.append((time.perf_counter() - t0) * 1e3)

    poses = _nearest_rigid(torch.stack(world_T_camera))
    files = _write_trajectories(out, "trajectory", poses, rec.timestamps)
    if rec.poses is not None:
        files += _write_trajectories(out, "groundtruth", rec.poses.double().cpu(), rec.timestamps)
    timings = {
        "open_s": t_open,
        "total_s": time.perf_counter() - t_start,
        "refine_ms_first_frame": refine_ms[0],
        "refine_ms_median": float(np.median(refine_ms)),
        "refine_ms_mean_after_first": float(np.mean(refine_ms[1:])),
        "write_ms_mean": float(np.mean(write_ms)),
        "note": "the first frame includes numba's compilation of the kernels",
    }
    frames = {"count": T, "first": rec.names[0], "last": rec.names[-1], "stereo_ran": stereo_frames,
              "motion_failed": motion_failed, "has_groundtruth_poses": rec.poses is not None}
    report = _run_report(args, rec, device, frames, files, timings)
    _write_json(out / _RUN_JSON, report)
    if not args.quiet:
        print(f"egorefine run: {T} frames ({W}x{H}) -> {out}/ (stereo on {stereo_frames}, "
              f"{float(np.median(refine_ms)):.1f} ms/frame median); trajectory: {', '.join(files)}", file=sys.stderr)
    return 0


def _format_suffix(fmt: str) -> str:
    from .data import DISPARITY_FORMATS

    return DISPARITY_FORMATS[fmt]


# -- eval ---------------------------------------------------------------------------------------------------------
def _disparity_files(folder: Path, name: str) -> dict[str, Path]:
    """Disparity maps in ``folder`` by stem; a ``run`` output folder is read from its ``disparity/``."""
    if not folder.is_dir():
        raise FileNotFoundError(f"{name}: no folder at {str(folder)!r}")
    if (folder / "disparity").is_dir() and (folder / _RUN_JSON).is_file():
        folder = folder / "disparity"
    files: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() in (".png", ".pfm", ".npy") and p.is_file() and not p.name.startswith("."):
            if p.stem in files:
                raise ValueRangeError(f"{name}: two maps for frame {p.stem!r} ({files[p.stem].name}, {p.name})")
            files[p.stem] = p
    if not files:
        raise ValueRangeError(f"{name}: no .png, .pfm or .npy disparity map in {str(folder)!r}")
    return files


def evaluate_disparity_folders(pred_dir: str | Path, gt_dir: str | Path) -> dict:
    """Score the disparity maps of ``pred_dir`` against those of ``gt_dir``, matched by file stem.

    All matched frames are pooled (every scored pixel counts once).

    Args:
        pred_dir: a folder of maps (KITTI PNG16, PFM or npy), or an ``egorefine run`` output folder.
        gt_dir: a folder of true maps; invalid pixels are 0 (PNG) or non-finite / non-positive (PFM, npy).

    Returns:
        ``{"frames", "unmatched_truth", "metrics": {...}, "per_frame": {stem: {"epe", "d1", "density"}}}`` with
        the metrics of :func:`egorefine.metrics.evaluate_disparity` (``epe``, ``bad-1``, ``bad-2``, ``bad-3``,
        ``d1`` ...; ``density`` = share of true pixels the prediction has a value for).
    """
    from .core import ShapeError
    from .data import read_disparity
    from .metrics import evaluate_disparity

    pred, gt = _disparity_files(Path(pred_dir), "PRED"), _disparity_files(Path(gt_dir), "GT")
    stems = sorted(set(pred) & set(gt))
    if not stems:
        raise ValueRangeError(f"PRED: none of its {len(pred)} maps has a file stem found in GT "
                              f"(e.g. {next(iter(pred))!r} against {next(iter(gt))!r})")
    ds, vs, gs, ms, per_frame = [], [], [], [], {}
    for stem in stems:
        d, v = read_disparity(pred[stem])
        g, m = read_disparity(gt[stem])
        if d.shape != g.shape:
            raise ShapeError(f"{pred[stem]}: {tuple(d.shape)} pixels, its truth {gt[stem]} {tuple(g.shape)}")
        frame = evaluate_disparity(d, g, v, m, thresholds=(1.0, 2.0, 3.0))
        per_frame[stem] = {k: frame[k] for k in ("epe", "d1", "density")}
        ds.append(d.flatten())
        vs.append(v.flatten())
        gs.append(g.flatten())
        ms.append(m.flatten())
    metrics = evaluate_disparity(torch.cat(ds), torch.cat(gs), torch.cat(vs), torch.cat(ms),
                                 thresholds=(0.5, 1.0, 2.0, 3.0))
    return {"frames": len(stems), "unmatched_truth": len(set(gt) - set(pred)), "metrics": metrics,
            "per_frame": per_frame}


def _associate(est: tuple, gt: tuple, max_dt: float, names: tuple[str, str]) -> tuple[torch.Tensor, torch.Tensor]:
    """Pair the poses of two trajectories: by timestamp (nearest within ``max_dt``) when both have them, else by
    line, which needs the same number of poses."""
    (est_t, est_p), (gt_t, gt_p) = est, gt
    if est_t is None or gt_t is None:
        if est_p.shape[0] != gt_p.shape[0]:
            raise ValueRangeError(f"{names[0]}: {est_p.shape[0]} poses, {names[1]}: {gt_p.shape[0]}; without "
                                  "timestamps on both (TUM format) the poses are paired line by line")
        return est_p, gt_p
    order = np.argsort(gt_t)
    sorted_t = gt_t[order]
    idx = np.clip(np.searchsorted(sorted_t, est_t), 1, len(sorted_t) - 1) if len(sorted_t) > 1 else np.zeros(
        len(est_t), dtype=int)
    if len(sorted_t) > 1:
        idx = np.where(np.abs(sorted_t[idx - 1] - est_t) <= np.abs(sorted_t[idx] - est_t), idx - 1, idx)
    keep = np.abs(sorted_t[idx] - est_t) <= max_dt
    return est_p[torch.from_numpy(keep)], gt_p[torch.from_numpy(order[idx[keep]])]


def evaluate_trajectory_files(pred: str | Path, gt: str | Path, max_time_difference: float = 0.01) -> dict:
    """RPE and aligned ATE of a trajectory file against a true one (TUM or KITTI, told by the column count).

    Args:
        pred, gt: trajectory files of ``world_T_camera`` poses.
        max_time_difference: seconds; two TUM files are paired by nearest timestamp within it (default 0.01 s,
            the association tolerance ``evo`` uses by default). Files without timestamps are paired line by line.

    Returns:
        :func:`egorefine.metrics.evaluate_trajectory`'s dict.
    """
    from .data import read_trajectory
    from .metrics import evaluate_trajectory

    est_p, gt_p = _associate(read_trajectory(pred), read_trajectory(gt), max_time_difference, ("--traj", "--gt-traj"))
    if est_p.shape[0] < 2:
        raise ValueRangeError(f"--traj: {est_p.shape[0]} pose(s) pair with --gt-traj (within "
                              f"{max_time_difference:g} s); at least 2 are needed")
    return evaluate_trajectory(est_p, gt_p)


def _eval(args: argparse.Namespace) -> int:
    if (args.pred is None) != (args.gt is None):
        raise ValueRangeError("PRED and GT: give both folders of disparity maps, or neither")
    if (args.traj is None) != (args.gt_traj is None):
        raise ValueRangeError("--traj and --gt-traj: give both trajectory files, or neither")
    if args.pred is None and args.traj is None:
        raise ValueRangeError("nothing to evaluate: give PRED GT (disparity folders) and/or --traj --gt-traj")
    report: dict = {"egorefine_version": __version__}
    if args.pred is not None:
        disp = evaluate_disparity_folders(args.pred, args.gt)
        report["disparity"] = disp
        m = disp["metrics"]
        units = {"epe": "px", "median": "px", "rmse": "px"}
        rows = [[k, f"{m[k]:.5g}", units.get(k, "share")]
                for k in ("epe", "median", "rmse", "bad-0.5", "bad-1", "bad-2", "bad-3", "d1", "density")]
        print(f"disparity: {disp['frames']} frames ({disp['unmatched_truth']} truth maps without a prediction)")
        print(_table(rows, ["metric", "value", "unit"]))
    if args.traj is not None:
        traj = evaluate_trajectory_files(args.traj, args.gt_traj, args.max_time_difference)
        report["trajectory"] = traj
        rows = [[k, f"{v:.5g}", "m" if k.endswith("_m") else "deg" if k.endswith("_deg") else ""]
                for k, v in traj.items() if k != "frames"]
        print(f"trajectory: {int(traj['frames'])} paired poses")
        print(_table(rows, ["metric", "value", "unit"]))
    if args.json is not None:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        _write_json(path, report)
    return 0


# -- folder (deprecated) ------------------------------------------------------------------------------------------
def _folder(args: argparse.Namespace) -> int:
    from .data import ImageFolderSequence, write_disparity
    from .geometry import make_intrinsics
    from .refine import EgoMotionRefiner

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


# -- parser -------------------------------------------------------------------------------------------------------
def _common() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quiet", action="store_true", help="no progress bars or notes on stderr")
    common.add_argument("--debug", action="store_true", help="show the full traceback of an error")
    return common


def _refiner_options(p: argparse.ArgumentParser, max_disparity: int, fusion: str | None = None) -> None:
    p.add_argument("--max-disparity", type=_at_least(2), default=max_disparity, metavar="PX",
                   help="stereo search range in pixels: candidates 0 <= d < PX (must be below the image width)")
    p.add_argument("--verify-every", type=_at_least(1), default=5, metavar="N",
                   help="run stereo matching on every N-th frame (the paper's i; 1 = every frame), predict the rest")
    if fusion is not None:
        p.add_argument("--fusion", default=fusion, choices=["paper", "kalman"],
                       help="how stereo corrects the prediction: the paper's 0.5 px gate and 0.4 gain, or per-pixel "
                            "Kalman fusion of variances")


def _command(sub, common: argparse.ArgumentParser, name: str, summary: str, description: str, func):
    """A subcommand with the common options, the help formatter and its function."""
    p = sub.add_parser(name, parents=[common], formatter_class=_Formatter, help=summary, description=description)
    p.set_defaults(func=func)
    return p


def _build_parser() -> argparse.ArgumentParser:
    from .data import CAMERAS, LAYOUTS

    parser = _Parser(prog="egorefine", description=__doc__.replace("``", "'"), epilog=_EXAMPLES,
                     formatter_class=_Formatter)
    parser.add_argument("--version", action="version", version=f"egorefine {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    common = _common()

    demo = _command(
        sub, common, "demo", "refine the built-in synthetic sequence and score it against ground truth",
        "Render the built-in stereo sequence (exact ground truth), run per-frame stereo and the refiner "
        "in paper and Kalman mode, print a table of errors and write figures (maps with colour bars, a "
        "disparity row, the trajectory) to --out.",
        _demo,
    )
    demo.add_argument("--frames", type=_at_least(2), default=30, metavar="T",
                      help="number of frames to render (>= 2: the first one has nothing to refine)")
    demo.add_argument("--preset", default="paper", choices=["paper", "kitti"],
                      help="rig: 'paper' (640x480, f = 398 px, B = 0.08 m) or 'kitti' (1242x375, f = 721.5 px, "
                           "B = 0.537 m)")
    demo.add_argument("--height", type=_at_least(16), default=None, metavar="PX",
                      help="image height in pixels (default: the preset's)")
    demo.add_argument("--width", type=_at_least(16), default=None, metavar="PX",
                      help="image width in pixels; the focal length scales with it (default: the preset's)")
    demo.add_argument("--noise", type=float, default=0.01, metavar="STD",
                      help="standard deviation of the rendered sensor noise, in grey units of [0, 1] (0 = ideal "
                           "images; 0.01 is about 2.5 grey levels of 255)")
    demo.add_argument("--seed", type=int, default=0, help="seed of the scene, trajectory and noise")
    _refiner_options(demo, 48)
    demo.add_argument("--threads", type=_at_least(1), default=2, metavar="N", help="CPU threads for torch and kernels")
    demo.add_argument("--out", default="results/demo", metavar="DIR", help="folder for the figures")

    run = _command(
        sub, common, "run", "refine a recorded stereo sequence; write maps, trajectory and run.json",
        "Read a stereo sequence and its calibration (rectifying it where the layout is unrectified), "
        "refine it frame by frame and write to --out: disparity/, valid/ (255 = valid), confidence/ (1 / "
        "(1 + variance), PNG16 stores it as value / 65535), preview/ (colour, grey = invalid), "
        "trajectory_tum.txt and trajectory_kitti.txt (world_T_camera, the formats evo reads; "
        "groundtruth_*.txt too where the recording has poses) and run.json (settings, version, "
        "calibration, timings), written last.",
        _run,
    )
    run.add_argument("input", metavar="INPUT", help="the sequence: a folder (or, for some layouts, a file) "
                                                    "in --layout")
    run.add_argument("--layout", required=True, choices=LAYOUTS,
                     help="how INPUT is organised: left/right image folders with a calibration file, a KITTI raw "
                          "drive, a KITTI odometry sequence or an EuRoC ASL folder")
    run.add_argument("--out", required=True, metavar="DIR", help="output folder (refused if it holds results)")
    run.add_argument("--calib", default=None, metavar="FILE",
                     help="calibration file (OpenCV YAML/JSON, ROS camera_info YAML, KITTI calib); default: the "
                          "one the layout keeps in INPUT")
    run.add_argument("--camera", default="grey", choices=CAMERAS,
                     help="which camera pair to read where the layout has both (KITTI: grey image_00/01 or image_0/1, "
                          "colour image_02/03 or image_2/3; read as grey either way)")
    run.add_argument("--frames", type=parse_frame_range, default=None, metavar="START:STOP[:STEP]",
                     help="frame range, 0-based, STOP excluded (default: all frames)")
    _refiner_options(run, 64, fusion="kalman")
    run.add_argument("--matcher", default="sad", choices=_MATCHERS,
                     help="stereo cost (SAD on x-Sobel, ZNCC or census) and aggregation (box window, or +sgm for "
                          "semi-global)")
    run.add_argument("--motion", default="exact", choices=["linear", "robust", "exact"],
                     help="ego-motion solve: the paper's linear eq. 3, robust-weighted, or exact SE(3) reprojection")
    run.add_argument("--format", default="png16", choices=["png16", "npy", "pfm"],
                     help="disparity and confidence files: KITTI 16-bit PNG (1/256 px steps, 0 = invalid), float32 "
                          "npy (NaN = invalid) or PFM (+inf = invalid)")
    run.add_argument("--batch-size", type=_only_one, default=1, metavar="1",
                     help="frames per refiner call; only 1: each frame is predicted from the previous one's "
                          "state, so the frames of one sequence cannot be batched (the library's API batches "
                          "independent sequences)")
    run.add_argument("--device", default="cpu", metavar="DEV", help="torch device: cpu, cuda or cuda:N")
    run.add_argument("--threads", type=_at_least(1), default=None, metavar="N",
                     help="CPU threads for torch and the compiled kernels (default: torch's, the machine's cores)")
    run.add_argument("--overwrite", action="store_true",
                     help="replace the results of an earlier run in --out (its files are deleted first)")

    ev = _command(
        sub, common, "eval", "score disparity maps and/or a trajectory against truth",
        "Disparity metrics of the maps in PRED against those in GT, matched by file stem (KITTI PNG16 "
        "with 0 = invalid, PFM or npy; an 'egorefine run' output folder is read from its disparity/), and "
        "RPE / aligned ATE of --traj against --gt-traj (TUM or KITTI format, told by the column count). "
        "Prints tables; --json writes them.",
        _eval,
    )
    ev.add_argument("pred", nargs="?", default=None, metavar="PRED", help="folder of predicted disparity maps")
    ev.add_argument("gt", nargs="?", default=None, metavar="GT", help="folder of true disparity maps")
    ev.add_argument("--traj", default=None, metavar="FILE", help="estimated trajectory (world_T_camera)")
    ev.add_argument("--gt-traj", default=None, metavar="FILE", help="true trajectory of the same frames")
    ev.add_argument("--max-time-difference", type=float, default=0.01, metavar="S",
                    help="seconds: TUM poses are paired by nearest timestamp within this (KITTI files by line)")
    ev.add_argument("--json", default=None, metavar="FILE", help="also write the metrics to this JSON file")

    folder = _command(
        sub, common, "folder", "deprecated: use 'run --layout folders'; refine rectified image folders to PFM maps",
        "Deprecated: 'egorefine run INPUT --layout folders --calib FILE' does this and writes every "
        "output. Refines a rectified left/right image-folder sequence with the intrinsics given here and "
        "writes one PFM map per frame (+inf = invalid).",
        _folder,
    )
    folder.add_argument("--left", required=True, metavar="DIR", help="folder of left images (sorted by name)")
    folder.add_argument("--right", required=True, metavar="DIR", help="folder of right images")
    folder.add_argument("--focal", type=float, required=True, metavar="PX", help="focal length of the rectified "
                                                                                 "pair in pixels")
    folder.add_argument("--cx", type=float, required=True, metavar="PX", help="principal point x, pixels")
    folder.add_argument("--cy", type=float, required=True, metavar="PX", help="principal point y, pixels")
    folder.add_argument("--baseline", type=float, required=True, metavar="M", help="baseline in metres (> 0)")
    _refiner_options(folder, 64, fusion="kalman")
    folder.add_argument("--threads", type=_at_least(1), default=2, metavar="N", help="CPU threads")
    folder.add_argument("--out", default="results/folder", metavar="DIR", help="folder for the PFM maps")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``egorefine`` command; returns the exit status (2 for bad input).

    Args:
        argv: the arguments (default: ``sys.argv[1:]``).

    Example:
        >>> main(["eval"])  # nothing to evaluate: one line on stderr, exit status 2
        2
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    args = _build_parser().parse_args(argv)
    args.argv = argv
    try:
        return args.func(args)
    except (EgorefineError, OSError) as err:
        if args.debug:
            raise
        message = " ".join(str(err).split()) or type(err).__name__
        print(f"egorefine {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"egorefine {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
