"""The ``egorefine`` command.

``egorefine demo`` renders the built-in synthetic stereo sequence (the paper's rig), runs
per-frame stereo and the ego-motion refiner on it, prints errors against the exact ground
truth and writes a figure. ``egorefine folder`` refines a rectified image-folder sequence and
writes PFM disparity maps.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

__all__ = ["main"]


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


def _demo(args: argparse.Namespace) -> int:
    from .data import render_sequence
    from .metrics import distinct_levels, evaluate_disparity
    from .refine import refine_sequence
    from .stereo import block_matching

    torch.set_num_threads(args.threads)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    seq = render_sequence(num_frames=args.frames, preset=args.preset, seed=args.seed)
    T, _, H, W = seq.left.shape
    print(f"rendered {T} frames of {W}x{H} ({args.preset} preset, f={seq.K[0, 0]:.0f} px, "
          f"baseline={seq.baseline:.3f} m) in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    K, baseline = seq.K[None], torch.tensor([seq.baseline])
    gt_mask = (seq.disparity > 0) & ~seq.occluded

    def score(disp: torch.Tensor, valid: torch.Tensor, skip_first: bool = False) -> dict[str, float]:
        s = slice(1, None) if skip_first else slice(None)
        return evaluate_disparity(disp[s], seq.disparity[s], valid[s], gt_mask[s])

    results: dict[str, tuple[dict[str, float], float, int, torch.Tensor]] = {}
    for name, subpixel in (("stereo per frame, integer", False), ("stereo per frame, sub-pixel", True)):
        t0 = time.perf_counter()
        outs = [block_matching(seq.left[t : t + 1], seq.right[t : t + 1], args.max_disparity, subpixel=subpixel)
                for t in range(T)]
        ms = (time.perf_counter() - t0) * 1e3 / T
        disp = torch.cat([o[0] for o in outs])
        valid = torch.cat([o[1] for o in outs])
        results[name] = (score(disp, valid, True), ms, T, disp)
    for fusion in ("paper", "kalman"):
        # Paper mode as published: pixel-accurate stereo and the linear motion solve (eq. 3).
        motion, subpixel = ("linear", False) if fusion == "paper" else ("exact", True)
        t0 = time.perf_counter()
        res = refine_sequence(seq.left, seq.right, K, baseline, verify_every=args.verify_every, fusion=fusion,
                              motion_method=motion, subpixel=subpixel, max_disparity=args.max_disparity,
                              show_progress=True)
        ms = (time.perf_counter() - t0) * 1e3 / T
        stereo = "integer" if not subpixel else "sub-pixel"
        name = f"{fusion} mode ({stereo} stereo, {motion} motion), verify every {args.verify_every}"
        results[name] = (score(res.disparity[:, 0], res.valid[:, 0], True), ms, int(res.stereo_ran.sum()),
                         res.disparity[:, 0])

    header = ["method", "EPE px", "median px", "bad-0.5", "bad-1", "density", "stereo frames", "ms/frame"]
    rows = [[k, m["epe"], m["median"], m["bad-0.5"], m["bad-1"], m["density"], f"{n}/{T}", ms]
            for k, (m, ms, n, _) in results.items()]
    print(_table(rows, header))
    print("(errors over frames 1..T-1 on pixels each method marks valid; density = share of pixels with truth)")

    row = H // 2 + H // 8
    last = T - 1
    curves = {"ground truth": seq.disparity[last, 0]}
    for k, (_, _, _, disp) in results.items():
        curves[k.split(" (")[0].replace("stereo per frame,", "stereo,")] = disp[last, 0]
    levels = {k: distinct_levels(v[row][gt_mask[last, 0, row]]) for k, v in curves.items()}
    print("distinct disparity levels along row", row, ":", ", ".join(f"{k}: {v}" for k, v in levels.items()))
    try:
        from .viz import save_row_figure

        fig = save_row_figure(out_dir / "demo_row.png", row, curves, max_disparity=float(seq.disparity.max()),
                              title=f"frame {last}: disparity along row {row}")
        print(f"figure: {fig}")
    except ImportError:
        print("figure skipped: matplotlib is not installed (pip install egorefine[viz])", file=sys.stderr)
    return 0


def _folder(args: argparse.Namespace) -> int:
    from .data import ImageFolderSequence, write_pfm
    from .geometry import make_intrinsics
    from .refine import EgoMotionRefiner

    torch.set_num_threads(args.threads)
    frames = ImageFolderSequence(args.left, args.right)
    K = make_intrinsics(args.focal, args.cx, args.cy)
    baseline = torch.tensor([args.baseline])
    refiner = EgoMotionRefiner(max_disparity=args.max_disparity, verify_every=args.verify_every, fusion=args.fusion)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    state = None
    for t, (left, right) in enumerate(frames):
        out, state = refiner(left, right, K, baseline, state)
        disp = torch.where(out.valid, out.disparity, torch.zeros_like(out.disparity))
        write_pfm(out_dir / f"{t:06d}.pfm", disp[0, 0])
        print(f"\rframe {t + 1}/{len(frames)} stereo={out.stereo_ran!s:5}", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``egorefine`` command."""
    parser = argparse.ArgumentParser(prog="egorefine", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="refine the built-in synthetic sequence and score it against ground truth")
    demo.add_argument("--frames", type=_at_least(2), default=30)
    demo.add_argument("--preset", default="paper", choices=["paper", "kitti"])
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--max-disparity", type=int, default=48)
    demo.add_argument("--verify-every", type=int, default=5)
    demo.add_argument("--threads", type=int, default=2)
    demo.add_argument("--out", default="results/demo")
    demo.set_defaults(func=_demo)
    folder = sub.add_parser("folder", help="refine a rectified image-folder stereo sequence, write PFM maps")
    folder.add_argument("--left", required=True)
    folder.add_argument("--right", required=True)
    folder.add_argument("--focal", type=float, required=True)
    folder.add_argument("--cx", type=float, required=True)
    folder.add_argument("--cy", type=float, required=True)
    folder.add_argument("--baseline", type=float, required=True)
    folder.add_argument("--max-disparity", type=int, default=64)
    folder.add_argument("--verify-every", type=int, default=5)
    folder.add_argument("--fusion", default="kalman", choices=["paper", "kalman"])
    folder.add_argument("--threads", type=int, default=2)
    folder.add_argument("--out", default="results/folder")
    folder.set_defaults(func=_folder)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
