"""``egorefine demo``: render the built-in sequence, score stereo and the refiner against its truth, draw it."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from ._shared import _table


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


def _demo(args: argparse.Namespace) -> int:
    from ..data import render_sequence
    from ..metrics import compose_motions, distinct_levels, evaluate_disparity, evaluate_trajectory
    from ..refine import EgoMotionRefiner, StereoOptions, refine_sequence
    from ..stereo import block_matching
    from ..viz import save_maps_figure, save_row_figure, save_trajectory_figure

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
        stereo = ("integer" if not subpixel else "sub-pixel") + " stereo"
        if EgoMotionRefiner(fusion=fusion, stereo=StereoOptions(subpixel=subpixel)).stereo.fill:
            stereo += " + SGM in its holes"
        name = f"{fusion} mode ({stereo}, {motion} motion), verify every {args.verify_every}"
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
