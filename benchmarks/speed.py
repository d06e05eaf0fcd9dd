"""Speed of the loop, its two kinds of frame and its stages, against OpenCV StereoBM and StereoSGBM in the same run.

The method exists so that stereo need not run on every frame: the loop (Kalman mode, verify every 5, default
options) should cost less per frame than OpenCV's SGBM on every frame. Per case (640x480 at 32 and 64 disparities,
1242x375 at 128; realistic renders, seed 7777, not a tuning seed of the accuracy benchmarks), each timed frame runs,
one after the other on the same pair: OpenCV StereoBM (block 9) and StereoSGBM (3-way, block 5, P1 = 8*25, P2 =
32*25) with the post-processing their users turn on (uniqueness 10, speckle window 100 within 2 px, a 1 px
left-right check; benchmarks/_opencv.py, shared with real.py and the tests), our default box matcher and our census +
SGM alone (``match_stereo`` with the refiner's options and ``StereoOptions.dense()``), and the loop's frame
(benchmarks/_timing.py's timer, with each frame split into stages). Frames 1-20 of each of ``--passes`` passes are
timed (frame 0 starts the state untimed; one untimed pass warms every method up). Medians and inter-quartile ranges
over all timed frames; the loop's ms per frame is the mean over a pass's frames (one verification in five), its
ratio to SGBM taken per pass against that pass's SGBM mean.

Targets (issue 29): loop at most 0.5x SGBM per frame (640x480 D=64 and 1242x375 D=128), our census + SGM at most
1.0x SGBM, our box matcher at most 1.0x StereoBM, a prediction frame at most 0.25x an SGBM frame.

A figure (``results/speed.png``) plots ms per frame against image size (D = 32 at 320x240, 480x360, 640x480) and
against D (16-128 at 640x480) for the loop, its frame kinds and OpenCV (one pass each).

    python benchmarks/speed.py                # full run: JSON, README table, figure (a few minutes on 2 cores)
    python benchmarks/speed.py --passes 1 --no-sweep --out /tmp/speed   # a quick look, README untouched
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's egorefine, not an installed one
from _common import (  # noqa: E402
    RESULTS,
    machine_info,
    markdown_table,
    omp_setting,
    set_threads,
    summarize,
    update_readme,
    write_json,
)
from _opencv import stereo_bm, stereo_sgbm  # noqa: E402
from _timing import BOOKKEEPING, StageProfiler, run_loop, stage_labels  # noqa: E402

from egorefine.data import StereoSequence, render_sequence  # noqa: E402
from egorefine.refine import EgoMotionRefiner, StereoOptions  # noqa: E402
from egorefine.stereo import match_stereo  # noqa: E402

SEED = 7777
VERIFY_EVERY = 5
TIMED = range(1, 21)  # four verification frames (5, 10, 15, 20) in twenty
CASES = [("paper", 640, 480, 32), ("paper", 640, 480, 64), ("kitti", 1242, 375, 128)]
SIZE_SWEEP = [(320, 240), (480, 360), (640, 480)]
D_SWEEP = [16, 32, 64, 128]
SCENE = {"paper": "corridor", "kitti": "street"}
TARGETS = {"loop_vs_sgbm": 0.5, "sgm_vs_sgbm": 1.0, "box_vs_bm": 1.0, "prediction_vs_sgbm": 0.25}


def render(preset: str, width: int, height: int, frames: int) -> StereoSequence:
    """The case's sequence, from the cache when rendered before (rendering is the slow part)."""
    cache = RESULTS / "cache" / f"speed_{preset}_{width}x{height}_{frames}_{SEED}.pt"
    if cache.exists():
        return torch.load(cache, weights_only=False)
    seq = render_sequence(num_frames=frames, preset=preset, scene=SCENE[preset], motion="forward", seed=SEED,
                          width=width, height=height)
    cache.parent.mkdir(parents=True, exist_ok=True)
    torch.save(seq, cache)
    return seq


def _u8(img: torch.Tensor) -> np.ndarray:
    return (img[0, 0].clamp(0, 1) * 255).round().byte().numpy()


def opencv(max_disparity: int) -> dict[str, cv2.StereoMatcher]:
    """StereoBM and StereoSGBM as their users run them (benchmarks/_opencv.py, the tests' and real.py's too)."""
    return {"StereoBM": stereo_bm(max_disparity), "StereoSGBM": stereo_sgbm(max_disparity)}


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return (time.perf_counter() - t0) * 1e3


def measure_case(preset: str, width: int, height: int, max_disparity: int, passes: int,
                 with_matchers: bool = True, frames: range = TIMED) -> dict:
    """Time one case: OpenCV, our matchers alone and the loop, interleaved frame by frame."""
    seq = render(preset, width, height, frames.stop)
    refiner = EgoMotionRefiner(max_disparity=max_disparity, verify_every=VERIFY_EVERY, fusion="kalman")
    cv = opencv(max_disparity)
    box_options = refiner.stereo.matcher_options()
    dense_options = StereoOptions.dense().matcher_options()
    u8 = [(_u8(seq.left[t : t + 1]), _u8(seq.right[t : t + 1])) for t in range(len(seq))]
    methods = {name: (lambda t, m=m: m.compute(*u8[t])) for name, m in cv.items()}
    if with_matchers:
        methods["ours box"] = lambda t: match_stereo(seq.left[t : t + 1], seq.right[t : t + 1], max_disparity,
                                                     **box_options)
        methods["ours census+SGM"] = lambda t: match_stereo(seq.left[t : t + 1], seq.right[t : t + 1],
                                                            max_disparity, **dense_options)
        # at SGBM 3-way's paths (left-right, right-left, top-down): the comparison at the same paths
        methods["ours census+SGM 3 paths"] = lambda t: match_stereo(seq.left[t : t + 1], seq.right[t : t + 1],
                                                                    max_disparity, sgm_paths=3, **dense_options)
    samples: dict[str, list[float]] = {name: [] for name in methods}
    per_pass: list[dict] = []

    def between(t: int) -> None:
        for name, fn in methods.items():
            samples[name].append(_timed(lambda fn=fn: fn(t)))

    run_loop(refiner, seq, frames)  # warm-up pass: compiles, caches and workspaces
    for fn in methods.values():
        fn(frames.start)
    for name in samples:
        samples[name].clear()
    runs = []
    with StageProfiler() as prof:
        for _ in range(passes):
            start = {name: len(v) for name, v in samples.items()}
            run = run_loop(refiner, seq, frames, profiler=prof, between=between)
            runs.append(run)
            sgbm = statistics.fmean(samples["StereoSGBM"][start["StereoSGBM"]:])
            per_pass.append({"loop_ms_per_frame": statistics.fmean(run.ms), "sgbm_ms": sgbm,
                             "loop_vs_sgbm": statistics.fmean(run.ms) / sgbm})
    kinds = {"prediction": [], "verification": []}
    stages = {"prediction": [], "verification": []}
    for run in runs:
        for ms, stereo, booked in zip(run.ms, run.stereo, run.stages, strict=True):
            kind = "verification" if stereo else "prediction"
            kinds[kind].append(ms)
            stages[kind].append(booked)
    labels = stage_labels()
    stage_ms = {kind: {label: statistics.median([b.get(label, 0.0) for b in booked]) for label in labels}
                for kind, booked in stages.items() if booked}
    result = {
        "preset": preset, "size": f"{width}x{height}", "max_disparity": max_disparity, "passes": passes,
        "frames": [frames.start, frames.stop - 1],
        "methods": {name: summarize(v) for name, v in samples.items()},
        "frame_kinds": {kind: summarize(v) for kind, v in kinds.items() if v},
        "stages_median_ms": stage_ms,
        "per_pass": per_pass,
    }
    sgbm = result["methods"]["StereoSGBM"]["median_ms"]
    ratios = [p["loop_vs_sgbm"] for p in per_pass]
    result["ratios"] = {
        "loop_vs_sgbm": statistics.median(ratios), "loop_vs_sgbm_min": min(ratios), "loop_vs_sgbm_max": max(ratios),
        "prediction_vs_sgbm": result["frame_kinds"]["prediction"]["median_ms"] / sgbm,
        "verification_vs_sgbm": result["frame_kinds"]["verification"]["median_ms"] / sgbm,
    }
    if with_matchers:
        result["ratios"]["sgm_vs_sgbm"] = result["methods"]["ours census+SGM"]["median_ms"] / sgbm
        result["ratios"]["sgm3_vs_sgbm"] = result["methods"]["ours census+SGM 3 paths"]["median_ms"] / sgbm
        result["ratios"]["box_vs_bm"] = result["methods"]["ours box"]["median_ms"] / \
            result["methods"]["StereoBM"]["median_ms"]
    return result


def _ms(s: dict) -> str:
    return f"{s['median_ms']:.1f} [{s['q1_ms']:.1f}-{s['q3_ms']:.1f}]"


def _pass(value: float, target: float) -> str:
    return f"{value:.2f}x {'PASS' if value <= target else 'FAIL'}"


def report(cases: list[dict], threads: int, passes: int) -> str:
    head = (f"Realistic renders (seed {SEED}), {threads} threads ({omp_setting()}), OpenCV in the same run; frames "
            f"{TIMED.start}-{TIMED.stop - 1} of {passes} passes, each frame's methods interleaved on the same pair; "
            "median [IQR] ms. Loop: Kalman mode, verify every 5, default options; its ms/frame is a pass's mean "
            "(min-max over passes in brackets for the ratio). Targets: loop <= 0.5x SGBM, census+SGM <= 1.0x SGBM "
            "at the same paths (SGBM 3-way's three: our `sgm_paths=3`; our default, 4 paths, beside it), box <= "
            "1.0x BM, prediction frame <= 0.25x SGBM.")
    rows = []
    for c in cases:
        m, r, k = c["methods"], c["ratios"], c["frame_kinds"]
        loop = statistics.median([p["loop_ms_per_frame"] for p in c["per_pass"]])
        rows.append([
            f"{c['preset']} {c['size']}", c["max_disparity"], _ms(m["StereoBM"]), _ms(m["StereoSGBM"]),
            _ms(m["ours box"]), _pass(r["box_vs_bm"], TARGETS["box_vs_bm"]), _ms(m["ours census+SGM 3 paths"]),
            _pass(r["sgm3_vs_sgbm"], TARGETS["sgm_vs_sgbm"]), _ms(m["ours census+SGM"]),
            f"{r['sgm_vs_sgbm']:.2f}x", f"{loop:.1f}",
            f"{_pass(r['loop_vs_sgbm'], TARGETS['loop_vs_sgbm'])} [{r['loop_vs_sgbm_min']:.2f}-"
            f"{r['loop_vs_sgbm_max']:.2f}]",
            _ms(k["prediction"]), _pass(r["prediction_vs_sgbm"], TARGETS["prediction_vs_sgbm"]),
            _ms(k["verification"]), f"{r['verification_vs_sgbm']:.2f}x",
        ])
    table = markdown_table(["case", "D", "StereoBM", "SGBM", "ours box", "box / BM", "ours census+SGM, 3 paths",
                            "SGM 3 / SGBM", "ours census+SGM, 4 paths", "SGM 4 / SGBM", "loop ms/frame",
                            "loop / SGBM", "prediction frame", "pred / SGBM",
                            "verification frame", "verif / SGBM"], rows)
    labels = stage_labels()
    stage_rows = []
    for label in labels:
        row = [label]
        for c in cases:
            for kind in ("prediction", "verification"):
                row.append(f"{c['stages_median_ms'][kind].get(label, 0.0):.2f}")
        stage_rows.append(row)
    header = ["stage"] + [f"{c['preset']} {c['size']} D={c['max_disparity']} {kind[:5]}." for c in cases
                          for kind in ("prediction", "verification")]
    stage_text = ("Per stage, median ms over the frames of each kind (exclusive time: a stage's own, not that of the "
                  f"stages it calls; {BOOKKEEPING} = the frame's time no stage holds; medians need not add up to "
                  "the frame's median; the compiled splat closes the cracks as it goes: their time is the splat's).")
    return "\n\n".join([head, table, stage_text, markdown_table(header, stage_rows)])


def sweep(passes: int) -> dict:
    """One pass per point: ms per frame against image size (D = 32) and against D (640x480)."""
    frames = range(1, 11)
    out = {"size": [], "disparity": []}
    for width, height in SIZE_SWEEP:
        out["size"].append(measure_case("paper", width, height, 32, passes, with_matchers=False, frames=frames))
    for d in D_SWEEP:
        out["disparity"].append(measure_case("paper", 640, 480, d, passes, with_matchers=False, frames=frames))
    return out


def figure(points: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, key, xlabel in ((axes[0], "size", "pixels (millions)"), (axes[1], "disparity", "disparities D")):
        cases = points[key]
        x = [int(c["size"].split("x")[0]) * int(c["size"].split("x")[1]) / 1e6 if key == "size"
             else c["max_disparity"] for c in cases]
        series = {
            "loop (ms/frame)": [statistics.median([p["loop_ms_per_frame"] for p in c["per_pass"]]) for c in cases],
            "prediction frame": [c["frame_kinds"]["prediction"]["median_ms"] for c in cases],
            "verification frame": [c["frame_kinds"]["verification"]["median_ms"] for c in cases],
            "OpenCV SGBM": [c["methods"]["StereoSGBM"]["median_ms"] for c in cases],
            "OpenCV StereoBM": [c["methods"]["StereoBM"]["median_ms"] for c in cases],
        }
        for name, ys in series.items():
            ax.plot(x, ys, marker="o", label=name, linestyle="--" if "OpenCV" in name else "-")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("ms")
        ax.set_yscale("log")
        ax.grid(True, alpha=0.3)
        if key == "disparity":
            ax.set_xscale("log", base=2)
    axes[0].set_title("against image size (D = 32)")
    axes[1].set_title("against D (640x480)")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--passes", type=int, default=3, help="timed passes of frames 1-20 per case")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-sweep", action="store_true", help="skip the size and D sweep (and the figure)")
    parser.add_argument("--out", type=Path, default=None, help="write JSON, table and figure here, not the README")
    args = parser.parse_args(argv)
    set_threads(args.threads)
    torch.manual_seed(0)
    cases = []
    for preset, width, height, d in CASES:
        cases.append(measure_case(preset, width, height, d, args.passes))
        c = cases[-1]
        print(f"{preset} {width}x{height} D={d}: loop {c['ratios']['loop_vs_sgbm']:.2f}x SGBM, prediction "
              f"{c['ratios']['prediction_vs_sgbm']:.2f}x, census+SGM {c['ratios']['sgm3_vs_sgbm']:.2f}x (3 paths) "
              f"{c['ratios']['sgm_vs_sgbm']:.2f}x (4) SGBM, box "
              f"{c['ratios']['box_vs_bm']:.2f}x BM", file=sys.stderr)
    text = report(cases, args.threads, args.passes)
    print(text)
    payload = {"seed": SEED, "verify_every": VERIFY_EVERY, "threads": args.threads, "cases": cases,
               "targets": TARGETS}
    out_dir = args.out or RESULTS
    out_dir.mkdir(parents=True, exist_ok=True)
    if not args.no_sweep:
        payload["sweep"] = sweep(1)
        figure(payload["sweep"], out_dir / "speed.png")
    if args.out is None:
        write_json("speed", payload)
        update_readme("speed", text)
    else:
        (out_dir / "speed.json").write_text(json.dumps({"machine": machine_info(), **payload}, indent=2))
        (out_dir / "speed.md").write_text(text + "\n")
    return payload


if __name__ == "__main__":
    main()
