"""``egorefine eval``: score disparity folders and trajectory files against truth."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from .. import __version__
from ..core import ValueRangeError
from ._shared import _RUN_JSON, _table, _write_json


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
    from ..core import ShapeError
    from ..data import read_disparity
    from ..metrics import evaluate_disparity

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
    from ..data import read_trajectory
    from ..metrics import evaluate_trajectory

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
