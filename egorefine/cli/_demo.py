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


def _verdict(name: str, ours: dict, theirs: dict) -> str:
    """One sentence from two rows of the demo's table: how ``ours`` compares with ``theirs`` (OpenCV SGBM) in error
    (on each one's own pixels and on the pixels every row marks valid), density and time."""

    def word(a: float, b: float, lower: str, higher: str) -> str:
        return f"{a / b:.2f}x" + (f", {lower}" if a < b else f", {higher}" if a > b else "")

    return (f"{name} against OpenCV SGBM: EPE {ours['epe']:.3f} px against {theirs['epe']:.3f} on the pixels each "
            f"marks valid ({word(ours['epe'], theirs['epe'], 'lower', 'higher')}) and {ours['epe common']:.3f} "
            f"against {theirs['epe common']:.3f} on the pixels every row marks valid "
            f"({word(ours['epe common'], theirs['epe common'], 'lower', 'higher')}); density {ours['density']:.3f} "
            f"against {theirs['density']:.3f}; {ours['ms']:.1f} against {theirs['ms']:.1f} ms/frame "
            f"({word(ours['ms'], theirs['ms'], 'faster', 'slower')}).")


def _demo(args: argparse.Namespace) -> int:
    import cv2

    from ..data import render_sequence
    from ..metrics import compose_motions, distinct_levels, evaluate_disparity, evaluate_trajectory
    from ..refine import EgoMotionRefiner, StereoOptions, refine_sequence
    from ..stereo import block_matching, match_opencv, stereo_bm, stereo_sgbm
    from ..viz import save_maps_figure, save_row_figure, save_trajectory_figure

    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
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

    # Warm-up: numba compiles each kernel on its first call in a process; timing starts after it.
    warm = slice(0, min(3, T))
    for subpixel in (False, True):
        block_matching(seq.left[:1], seq.right[:1], args.max_disparity, subpixel=subpixel)
    for fusion, (motion, subpixel) in modes.items():
        refine_sequence(seq.left[warm], seq.right[warm], K, baseline, verify_every=2, fusion=fusion,
                        motion_method=motion, stereo=StereoOptions(subpixel=subpixel), max_disparity=args.max_disparity)

    # name -> (disparity (T, H, W), valid (T, H, W), ms/frame, stereo frames, motions (T, 4, 4))
    runs: dict[str, tuple[torch.Tensor, torch.Tensor, float, int, torch.Tensor]] = {}
    no_motion = torch.eye(4).repeat(T, 1, 1)
    num = -(-args.max_disparity // 16) * 16  # OpenCV searches a multiple of 16 disparities
    for name, matcher in (("OpenCV StereoBM, per frame", stereo_bm(num)), ("OpenCV SGBM, per frame", stereo_sgbm(num))):
        t0 = time.perf_counter()
        outs = [match_opencv(matcher, seq.left[t : t + 1], seq.right[t : t + 1]) for t in range(T)]
        ms = (time.perf_counter() - t0) * 1e3 / T
        runs[name] = (torch.cat([o[0] for o in outs])[:, 0], torch.cat([o[1] for o in outs])[:, 0], ms, T, no_motion)
    for name, subpixel in (("stereo per frame, integer", False), ("stereo per frame, sub-pixel", True)):
        t0 = time.perf_counter()
        outs = [block_matching(seq.left[t : t + 1], seq.right[t : t + 1], args.max_disparity, subpixel=subpixel)
                for t in range(T)]
        ms = (time.perf_counter() - t0) * 1e3 / T
        runs[name] = (torch.cat([o[0] for o in outs])[:, 0], torch.cat([o[1] for o in outs])[:, 0], ms, T, no_motion)
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
        runs[name] = (res.disparity[:, 0, 0], res.valid[:, 0, 0], ms, int(res.stereo_ran.sum()), res.motion[:, 0])

    # Scores over frames 1..T-1: on each row's own valid pixels, and on the pixels every row marks valid (the only
    # comparison of errors that does not favour the row that keeps fewer, easier pixels).
    scored = slice(1, T)
    common = gt_mask[scored, 0].clone()
    for _, valid, *_ in runs.values():
        common &= valid[scored]
    results: dict[str, dict[str, float]] = {}
    for name, (disp, valid, ms, n, _) in runs.items():
        own = evaluate_disparity(disp[scored], seq.disparity[scored, 0], valid[scored], gt_mask[scored, 0])
        on_common = evaluate_disparity(disp[scored], seq.disparity[scored, 0], common, gt_mask[scored, 0])
        results[name] = {**own, "epe common": on_common["epe"], "bad-0.5 common": on_common["bad-0.5"], "ms": ms,
                         "stereo frames": n}
    header = ["method", "EPE px", "bad-0.5", "density", "EPE common", "bad-0.5 common", "stereo frames",
              "ms/frame"]
    rows = [[k, m["epe"], m["bad-0.5"], m["density"], m["epe common"], m["bad-0.5 common"],
             f"{m['stereo frames']}/{T}", m["ms"]] for k, m in results.items()]
    print(_table(rows, header))
    share = float(common.sum()) / max(1, int(gt_mask[scored].sum()))
    print("(frames 1..T-1. EPE, bad-0.5 (share off by over 0.5 px): on the pixels each method marks valid; "
          "'common': on the\n"
          f" {share:.1%} of pixels with truth that every row marks valid; density = share of pixels with truth "
          "it marks valid;\n"
          f" ms/frame on {torch.get_num_threads()} thread(s), in this run, after a warm-up that compiles the "
          "kernels)")
    kalman = next(k for k in results if k.startswith("kalman"))
    print(_verdict("The refined map (kalman mode)", results[kalman], results["OpenCV SGBM, per frame"]))

    last = T - 1
    truth = _nan_where(seq.disparity[last, 0], gt_mask[last, 0])
    maps = {k: _nan_where(disp[last], valid[last]) for k, (disp, valid, *_) in runs.items()}
    est_poses = seq.poses[0].to(torch.float64) @ compose_motions(runs[kalman][4].to(torch.float64))
    traj = evaluate_trajectory(est_poses, seq.poses.to(torch.float64))
    print(f"trajectory ({kalman.split(' (')[0]}): ATE {traj['ate_rmse_m']:.4f} m, frame-to-frame RPE "
          f"{traj['rpe_translation_rmse_m']:.4f} m / {traj['rpe_rotation_mean_deg']:.3f} deg over a "
          f"{traj['path_length_m']:.2f} m path")

    row = H // 2 + H // 8
    curves = {"ground truth": truth}
    for k, m in maps.items():
        if not k.startswith("OpenCV StereoBM"):
            curves[k.split(" (")[0].replace("stereo per frame,", "stereo,").replace(", per frame", "")] = m
    levels = {k: distinct_levels(v[row][torch.isfinite(v[row])]) for k, v in curves.items()}
    print("distinct disparity levels along row", row, ":", ", ".join(f"{k}: {v}" for k, v in levels.items()))
    vmax = float(seq.disparity.max())
    figures = [
        _figure(save_row_figure, out_dir / "demo_row.png", row, curves, max_disparity=vmax,
                title=f"frame {last}: disparity along row {row}"),
        _figure(save_maps_figure, out_dir / "demo_maps.png", seq.left[last, 0],
                {"OpenCV SGBM": maps["OpenCV SGBM, per frame"],
                 "stereo (sub-pixel)": maps["stereo per frame, sub-pixel"], "refined (kalman)": maps[kalman]},
                truth=truth, max_disparity=vmax, title=f"frame {last}; grey: no value"),
        _figure(save_trajectory_figure, out_dir / "demo_trajectory.png",
                {"truth": seq.poses, "estimated (kalman)": est_poses}),
    ]
    for fig in figures:
        if fig is not None:
            print(f"figure: {fig}")
    return 0
