"""Benchmark of the predict-and-correct loop against per-frame stereo, on rendered sequences with exact truth.

For each sequence (the paper's rig and the KITTI-like preset, more than one scene and
motion, 60+ frames each) and each method, in the same run:

* per-frame own stereo (integer and sub-pixel), per-frame OpenCV StereoBM and StereoSGBM (3-way);
* the refiner in paper mode (the method as published: pixel-accurate stereo, the linear motion
  solve of eq. 3, gate 0.5 px, gain 0.4) and in Kalman mode (sub-pixel stereo, exact SE(3)
  motion, per-pixel variance), at verify_every 1, 5 and 10; Kalman mode with the +-2 px
  residual search between verifications (at 5 and 10), and with it plus the hole measurement (at 5);

it reports EPE, median error, bad-0.5, bad-1 (on pixels each method marks valid and that
have truth, not occluded), density (share of those pixels a method marks valid), the
temporal consistency of the error, the number of distinct disparity levels along a row, and
ms per frame. Writes benchmarks/results/refine.json, the README table and a row figure.

    python benchmarks/refine.py            # full run (several minutes on 2 cores)
    python benchmarks/refine.py --quick    # small images, few frames: a smoke run
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import RESULTS, markdown_table, set_threads, update_readme, write_json  # noqa: E402

from egorefine.data import render_sequence  # noqa: E402
from egorefine.metrics import distinct_levels, evaluate_disparity, temporal_consistency  # noqa: E402
from egorefine.refine import EgoMotionRefiner  # noqa: E402
from egorefine.stereo import block_matching  # noqa: E402

# (preset, scene, motion, max_disparity): two scenes/motions per rig.
SEQUENCES = [
    ("paper", "corridor", "forward", 64),
    ("paper", "hall", "turn", 64),
    ("kitti", "street", "forward", 128),
    ("kitti", "hall", "shaky", 128),
]


def _u8(img: torch.Tensor) -> np.ndarray:
    return (img[0, 0].clamp(0, 1) * 255).round().byte().numpy()


def opencv_matchers(max_disparity: int, block: int = 9) -> dict:
    bm = cv2.StereoBM_create(numDisparities=max_disparity, blockSize=block)
    sgbm = cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=max_disparity, blockSize=5, P1=8 * 25, P2=32 * 25,
        uniquenessRatio=10, disp12MaxDiff=1, speckleWindowSize=0, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )

    def run(matcher):
        def f(left: torch.Tensor, right: torch.Tensor):
            d = matcher.compute(_u8(left), _u8(right)).astype(np.float32) / 16.0
            d = torch.from_numpy(d)[None, None]
            return d.clamp_min(0), d > 0

        return f

    return {"OpenCV StereoBM": run(bm), "OpenCV SGBM 3-way": run(sgbm)}


# numba compiles a kernel on its first call (or loads it from its cache, which any edit of its module
# invalidates): every method first runs untimed on the sequence's first frames, so that no compile lands in a timing
_WARM_UP_FRAMES = 6


def run_per_frame(fn, seq) -> tuple[torch.Tensor, torch.Tensor, list[float]]:
    fn(seq.left[:1], seq.right[:1])  # warm-up
    disp, valid, ms = [], [], []
    for t in range(len(seq.left)):
        t0 = time.perf_counter()
        d, v = fn(seq.left[t : t + 1], seq.right[t : t + 1])
        ms.append((time.perf_counter() - t0) * 1e3)
        disp.append(d)
        valid.append(v)
    return torch.cat(disp), torch.cat(valid), ms


def warm_up(refiner: EgoMotionRefiner, seq) -> None:
    """The refiner on the first frames (with and without stereo), untimed."""
    K, b = seq.K[None], torch.tensor([seq.baseline])
    state = None
    for t in range(min(_WARM_UP_FRAMES, len(seq.left))):
        _, state = refiner(seq.left[t : t + 1], seq.right[t : t + 1], K, b, state)


def run_refiner(refiner: EgoMotionRefiner, seq, warm: bool = True
                ) -> tuple[torch.Tensor, torch.Tensor, list[float], int]:
    if warm:
        warm_up(refiner, seq)
    K, b = seq.K[None], torch.tensor([seq.baseline])
    state, disp, valid, ms, stereo = None, [], [], [], 0
    for t in range(len(seq.left)):
        t0 = time.perf_counter()
        out, state = refiner(seq.left[t : t + 1], seq.right[t : t + 1], K, b, state)
        ms.append((time.perf_counter() - t0) * 1e3)
        disp.append(out.disparity)
        valid.append(out.valid)
        stereo += int(out.stereo_ran)
    return torch.cat(disp), torch.cat(valid), ms, stereo


class TrackingClock:
    """Time the refiner spends tracking (pyramid building and ``track``), per frame.

    A per-frame-stereo pipeline needs the same tracking for its ego-motion, so this is the tracking
    term of the time target; it is measured inside a refiner run (constant-velocity prediction and
    pyramid reuse, as the loop tracks) by wrapping the two functions the refiner calls.
    """

    def __init__(self) -> None:
        import egorefine.refine.refiner as refiner_module

        self.module, self.total_ms, self.originals = refiner_module, 0.0, {}

    def __enter__(self) -> TrackingClock:
        for name in ("track", "build_pyramid"):
            original = getattr(self.module, name)
            self.originals[name] = original

            def timed(*args, _f=original, **kwargs):
                t0 = time.perf_counter()
                out = _f(*args, **kwargs)
                self.total_ms += (time.perf_counter() - t0) * 1e3
                return out

            setattr(self.module, name, timed)
        return self

    def __exit__(self, *exc) -> None:
        for name, original in self.originals.items():
            setattr(self.module, name, original)


def benchmark_sequence(preset, scene, motion, max_disp, frames, size, seed, figure_dir) -> dict:
    extra = {} if size is None else {"height": size[0], "width": size[1]}
    t0 = time.perf_counter()
    seq = render_sequence(num_frames=frames, preset=preset, scene=scene, motion=motion, seed=seed, **extra)
    render_s = time.perf_counter() - t0
    T, _, H, W = seq.left.shape
    max_disp = min(max_disp, (W // 16) * 16 - 16)
    gt = seq.disparity
    mask = (gt > 0) & ~seq.occluded
    print(f"[{preset}/{scene}/{motion}] {T} frames {W}x{H}, rendered in {render_s:.1f} s", file=sys.stderr)

    methods: dict[str, dict] = {}

    def record(name, disp, valid, ms, stereo_frames):
        m = evaluate_disparity(disp, gt, valid, mask)
        m["temporal"] = float(temporal_consistency(torch.where(valid, disp, gt), gt, mask & valid))
        m["ms_mean"] = statistics.fmean(ms)
        m["ms_median"] = statistics.median(ms)
        m["stereo_frames"] = stereo_frames
        methods[name] = m
        print(f"  {name:34s} EPE {m['epe']:.3f}  median {m['median']:.3f}  bad-0.5 {m['bad-0.5']:.3f}  "
              f"density {m['density']:.3f}  {m['ms_mean']:.1f} ms/frame", file=sys.stderr)
        return disp

    maps = {}
    for name, sub in (("own stereo, integer", False), ("own stereo, sub-pixel", True)):
        d, v, ms = run_per_frame(lambda a, b, s=sub: block_matching(a, b, max_disp, subpixel=s), seq)
        maps[name] = torch.where(v, d, torch.full_like(d, float("nan")))
        record(name, d, v, ms, T)
    for name, fn in opencv_matchers(max_disp).items():
        d, v, ms = run_per_frame(fn, seq)
        maps[name] = torch.where(v, d, torch.full_like(d, float("nan")))
        record(name, d, v, ms, T)
    # Paper mode is the method as published: pixel-accurate block matching, eq. (3), gate 0.5 px, gain 0.4.
    for fusion, motion_method, subpixel in (("paper", "linear", False), ("kalman", "exact", True)):
        for every in (1, 5, 10):
            refiner = EgoMotionRefiner(max_disparity=max_disp, verify_every=every, fusion=fusion,
                                       motion_method=motion_method, subpixel=subpixel)
            if fusion == "kalman" and every == 5:
                warm_up(refiner, seq)  # (outside the clock: it times the timed run's tracking)
                with TrackingClock() as clock:
                    d, v, ms, n = run_refiner(refiner, seq, warm=False)
                track_ms = clock.total_ms / T
            else:
                d, v, ms, n = run_refiner(refiner, seq)
            name = f"{fusion} mode, verify every {every}"
            maps[name] = torch.where(v, d, torch.full_like(d, float("nan")))
            record(name, d, v, ms, n)
    # Kalman mode with the residual search of +-2 px around the prediction on the frames without stereo.
    for every in (5, 10):
        refiner = EgoMotionRefiner(max_disparity=max_disp, verify_every=every, fusion="kalman", local_search=2)
        d, v, ms, n = run_refiner(refiner, seq)
        name = f"kalman + local search 2, verify every {every}"
        maps[name] = torch.where(v, d, torch.full_like(d, float("nan")))
        record(name, d, v, ms, n)
    # ... and the prediction's holes measured on the regions where they are dense (EgoMotionRefiner.measure_holes).
    refiner = EgoMotionRefiner(max_disparity=max_disp, verify_every=5, fusion="kalman", local_search=2,
                               measure_holes=True)
    d, v, ms, n = run_refiner(refiner, seq)
    name = "kalman + local search 2 + holes, verify every 5"
    maps[name] = torch.where(v, d, torch.full_like(d, float("nan")))
    record(name, d, v, ms, n)

    # Depth layers along one row of a frame that is not a verification frame at i = 5.
    frame = T - 2 if (T - 2) % 5 else T - 3
    row = int(H * 0.6)
    row_mask = mask[frame, 0, row]
    for name, m in methods.items():
        vals = maps[name][frame, 0, row][row_mask]
        m["levels_row"] = distinct_levels(vals[torch.isfinite(vals)])
    methods_gt_levels = distinct_levels(gt[frame, 0, row][row_mask])

    if figure_dir is not None:
        try:
            from egorefine.viz import save_row_figure

            curves = {"ground truth": gt[frame, 0]}
            for name in ("own stereo, integer", "OpenCV SGBM 3-way", "paper mode, verify every 5",
                         "kalman mode, verify every 5"):
                curves[name] = maps[name][frame, 0]
            save_row_figure(figure_dir / f"refine_row_{preset}_{scene}_{motion}.png", row, curves,
                            max_disparity=float(gt[frame].max()),
                            title=f"{preset}/{scene}/{motion}, frame {frame}, row {row}")
        except ImportError:
            pass
    return {"preset": preset, "scene": scene, "motion": motion, "frames": T, "size": [W, H],
            "max_disparity": max_disp, "render_s": render_s, "gt_levels_row": methods_gt_levels,
            "tracking_ms": track_ms, "methods": methods}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="10 frames at a quarter of the size; no README update")
    args = parser.parse_args()
    set_threads(args.threads)
    torch.manual_seed(args.seed)
    frames = 10 if args.quick else args.frames
    results = []
    for preset, scene, motion, max_disp in SEQUENCES:
        size = None
        if args.quick:
            size = (120, 160) if preset == "paper" else (96, 320)
        results.append(benchmark_sequence(preset, scene, motion, max_disp, frames, size, args.seed,
                                          None if args.quick else RESULTS))

    # Averages over the sequences of each rig, per method.
    header = ["rig", "method", "EPE", "median", "bad-0.5", "bad-1", "density", "temporal", "levels/row",
              "stereo frames", "ms/frame"]
    rows = []
    summary = {}
    for preset in ("paper", "kitti"):
        seqs = [r for r in results if r["preset"] == preset]
        for name in seqs[0]["methods"]:
            vals = {k: statistics.fmean(s["methods"][name][k] for s in seqs)
                    for k in ("epe", "median", "bad-0.5", "bad-1", "density", "temporal", "ms_mean", "levels_row")}
            n = sum(s["methods"][name]["stereo_frames"] for s in seqs)
            total = sum(s["frames"] for s in seqs)
            summary[f"{preset}/{name}"] = vals
            rows.append([preset, name, vals["epe"], vals["median"], vals["bad-0.5"], vals["bad-1"], vals["density"],
                         vals["temporal"], f"{vals['levels_row']:.0f}", f"{n}/{total}", vals["ms_mean"]])
    rigs = ("paper", "kitti")
    gt_levels = {p: statistics.fmean(r["gt_levels_row"] for r in results if r["preset"] == p) for p in rigs}
    track = {p: statistics.fmean(r["tracking_ms"] for r in results if r["preset"] == p) for p in rigs}
    notes = []
    for p in ("paper", "kitti"):
        own = summary[f"{p}/own stereo, sub-pixel"]["ms_mean"]
        k5 = summary[f"{p}/kalman mode, verify every 5"]["ms_mean"]
        p5 = summary[f"{p}/paper mode, verify every 5"]["ms_mean"]
        sg = summary[f"{p}/OpenCV SGBM 3-way"]["ms_mean"]
        ls5 = summary[f"{p}/kalman + local search 2, verify every 5"]["ms_mean"]
        h5 = summary[f"{p}/kalman + local search 2 + holes, verify every 5"]["ms_mean"]
        base = own + track[p]
        notes.append(f"{p}: verify every 5 costs {k5:.0f} ms/frame (Kalman), {ls5:.0f} (Kalman + local search), "
                     f"{h5:.0f} (+ holes) and {p5:.0f} ms/frame (paper) = {100 * k5 / base:.0f} % / "
                     f"{100 * ls5 / base:.0f} % / {100 * h5 / base:.0f} % / {100 * p5 / base:.0f} % of per-frame own "
                     f"stereo + tracking ({own:.0f} + {track[p]:.0f} ms); OpenCV SGBM: {sg:.0f} ms/frame. "
                     f"Ground truth has {gt_levels[p]:.0f} distinct levels along the row.")
    table = markdown_table(header, rows)
    table += "\n\n" + "\n".join(f"- {n}" for n in notes)
    seq_list = ", ".join(f"{r['preset']}/{r['scene']}/{r['motion']} ({r['size'][0]}x{r['size'][1]}, {r['frames']} "
                         f"frames)" for r in results)
    table += f"\n\nSequences (averaged per rig): {seq_list}. Errors in px on valid pixels with truth."
    print(table)
    write_json("refine_quick" if args.quick else "refine", {"sequences": results, "summary": summary,
                                                            "notes": notes})
    if not args.quick:
        update_readme("refine", table)


if __name__ == "__main__":
    main()
