"""Tuning of the matchers' options on rendered frames with tuning seeds only, against OpenCV in the same run.

Frames: for each sequence spec of ``benchmarks/refine.py`` (``SEQUENCES``: three scenes x two motions per rig,
the paper rig at 640x480 and the KITTI-like rig at 1242x375, realistic imaging) the first frame rendered with
``--seeds-per-spec`` seeds drawn from ``TUNING_SEEDS`` (0-99): spec ``i``'s ``k``-th seed is
``TUNING_SEEDS[i + len(SEQUENCES) * k]``. Seeds 1000+ and the real pairs (motorcycle, KITTI LiDAR frame) are
scored elsewhere (``benchmarks/refine.py``, ``benchmarks/real.py``) and never used here. Rendered frames are
cached in ``benchmarks/results/cache/tune_frames`` (git-ignored).

Per frame, on the pixels with truth that are not occluded (as ``benchmarks/refine.py`` scores): EPE, bad-0.5,
bad-2 over the pixels a method marks valid, density = valid share of the scored pixels; per rig the mean over
frames, and the time per frame (median over frames; 2 threads for torch and OpenCV). OpenCV StereoBM (block 9)
and StereoSGBM 3-way (block 5) run as ``benchmarks/real.py`` runs them (as their users do: P1 = 8 cn bs^2,
P2 = 32 cn bs^2, uniquenessRatio 10, speckleWindowSize 100, speckleRange 2, disp12MaxDiff 1).

    python benchmarks/tune_stereo.py --only "default (before),sgm (before),default,sgm"   # before / after
    python benchmarks/tune_stereo.py --seeds-per-spec 1         # every named configuration, seeds 0-11
    python benchmarks/tune_stereo.py --extra '{"try": {"cost": "census", "aggregation": "sgm"}}'
    python benchmarks/tune_stereo.py --loop --frames 15   # the loop (Kalman @5) with each verification matcher

``--loop``: per rig, the first sequence spec of ``SEQUENCES`` (``--loop-specs``) rendered with its tuning seed
(``TUNING_SEEDS[index]``, as ``benchmarks/refine.py --tune``), ``--frames`` frames; the refiner in Kalman mode at
verify every 5 with its default matcher and with the SGM option on its verification frames, against per-frame SGBM,
in the same run (EPE, bad-0.5, density over the non-occluded pixels with truth; ms per frame after a warm-up).

Writes ``benchmarks/results/cache/tune_stereo.json`` (the table and every per-frame row).
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
from _common import RESULTS, machine_info, markdown_table, set_threads  # noqa: E402
from refine import (  # noqa: E402
    MAX_DISPARITY,
    SEQUENCES,
    TUNING_SEEDS,
    VERIFY_EVERY,
    opencv_matchers,
    render,
    run_per_frame,
    run_refiner,
)

from egorefine.data import render_sequence  # noqa: E402
from egorefine.metrics import evaluate_disparity  # noqa: E402
from egorefine.refine import EgoMotionRefiner  # noqa: E402
from egorefine.stereo import match_stereo  # noqa: E402

CACHE = RESULTS / "cache" / "tune_frames"
BM = "opencv bm (block 9)"
SGBM = "opencv sgbm 3way (block 5)"
SGM = {"cost": "census", "aggregation": "sgm", "block_size": 5}
# name -> match_stereo keyword arguments. The first rows are the defaults as they stood before the tuning of
# issue 17 (2026-12-01), spelt out so that the table keeps them whatever the defaults become.
BEFORE_DEFAULT = {"uniqueness_ratio": 0.15, "texture_threshold": 0.004, "lr_threshold": 1, "speckle_size": 100,
                  "speckle_range": 1.0}
BEFORE_SGM = {**SGM, **BEFORE_DEFAULT, "census_window": 5, "sgm_p1": 0.5, "sgm_p2": 3.0}
CW7 = {**SGM, "census_window": 7}
CONFIGS: dict[str, dict] = {
    "default (before)": BEFORE_DEFAULT,
    "sgm (before)": BEFORE_SGM,
    "default": {},
    "sgm": SGM,
    # the SGM sweep of 2026-12-01 (docs/decisions.md), the checks and speckle filter of then unless named
    "sgm P 4/24": {**BEFORE_SGM, "sgm_p1": 4, "sgm_p2": 24},
    "sgm P 8/48": {**BEFORE_SGM, "sgm_p1": 8, "sgm_p2": 48},
    "sgm P 8/48 u 0.05": {**BEFORE_SGM, "sgm_p1": 8, "sgm_p2": 48, "uniqueness_ratio": 0.05},
    "sgm P 8/48 8 paths": {**BEFORE_SGM, "sgm_p1": 8, "sgm_p2": 48, "sgm_paths": 8},
    "sgm P 24/96": {**BEFORE_SGM, "sgm_p1": 24, "sgm_p2": 96},
    "sgm census 7 P 24/96": {**BEFORE_SGM, **CW7, "sgm_p1": 24, "sgm_p2": 96},
    "sgm census 7 P 32/128": {**BEFORE_SGM, **CW7, "sgm_p1": 32, "sgm_p2": 128},
    "sgm census 7 P 48/192": {**BEFORE_SGM, **CW7, "sgm_p1": 48, "sgm_p2": 192},
    "sgm census 7 P 32/128 u 0.1": {**BEFORE_SGM, **CW7, "sgm_p1": 32, "sgm_p2": 128, "uniqueness_ratio": 0.1},
    "sgm, raw-cost check 0.45": {**SGM, "census_max_distance": 0.45},
    # the default matcher's sweep
    "default speckle 300": {"speckle_size": 300},
    "default speckle 200 u 0.1": {"speckle_size": 200, "uniqueness_ratio": 0.1},
    "default u 0.25": {"uniqueness_ratio": 0.25},
    "default block 7": {"block_size": 7},
    "default speckle range 0.25": {"speckle_range": 0.25},
}


def tuning_frames(seeds_per_spec: int, presets: tuple[str, ...]) -> list[dict]:
    """The tuning frames (rendered once, then read from the cache): dicts of name, preset, seed and tensors."""
    CACHE.mkdir(parents=True, exist_ok=True)
    frames = []
    for k in range(seeds_per_spec):
        for index, spec in enumerate(SEQUENCES):
            if spec.preset not in presets:
                continue
            seed = TUNING_SEEDS[index + len(SEQUENCES) * k]
            path = CACHE / f"{spec.name}_seed{seed}.pt"
            if path.exists():
                data = torch.load(path)
            else:
                t0 = time.perf_counter()
                seq = render_sequence(num_frames=1, preset=spec.preset, scene=spec.scene, motion=spec.motion,
                                      seed=seed)
                data = {"left": seq.left[:1].clone(), "right": seq.right[:1].clone(),
                        "disparity": seq.disparity[:1].clone(), "occluded": seq.occluded[:1].clone()}
                torch.save(data, path)
                print(f"rendered {spec.name} seed {seed} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
            frames.append({"name": spec.name, "preset": spec.preset, "seed": seed, **data})
    return frames


def _u8(img: torch.Tensor) -> np.ndarray:
    return (img[0, 0].clamp(0, 1) * 255).round().byte().numpy()


def opencv(num: int) -> dict:
    """BM and SGBM configured as benchmarks/real.py configures them: name -> fn(frame) -> (disparity, valid)."""
    bm = cv2.StereoBM_create(num, 9)
    bm.setUniquenessRatio(10)
    bm.setSpeckleWindowSize(100)
    bm.setSpeckleRange(2)
    bm.setDisp12MaxDiff(1)
    bs = 5
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=num, blockSize=bs, P1=8 * bs * bs, P2=32 * bs * bs,
                                 disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)

    def run(matcher):
        def fn(frame):
            raw = matcher.compute(_u8(frame["left"]), _u8(frame["right"]))
            return torch.from_numpy(raw.astype(np.float32) / 16.0)[None, None], torch.from_numpy(raw >= 0)[None, None]

        return fn

    return {BM: run(bm), SGBM: run(sgbm)}


def ours(num: int, kw: dict):
    def fn(frame):
        with torch.no_grad():
            out = match_stereo(frame["left"], frame["right"], num, **kw)
        return out.disparity, out.valid

    return fn


def score(disparity: torch.Tensor, valid: torch.Tensor, frame: dict) -> dict:
    gt = frame["disparity"]
    scored = (gt > 0) & ~frame["occluded"] & torch.isfinite(gt)
    both = valid & scored
    err = (disparity - gt).abs()[both]
    n = max(1, int(both.sum()))
    return {"epe": float(err.sum()) / n, "bad05": float((err > 0.5).sum()) / n, "bad1": float((err > 1).sum()) / n,
            "bad2": float((err > 2).sum()) / n, "density": float(both.sum()) / max(1, int(scored.sum()))}


# the refiner's verification matchers compared by --loop (EgoMotionRefiner keyword arguments)
LOOP_MATCHERS = {"kalman @5, default matcher": {},
                 "kalman @5, sgm on verification frames": {"stereo_cost": "census", "aggregation": "sgm",
                                                           "block_size": 5}}


def loop(frames: int, specs: list[str]) -> None:
    """The refiner with each verification matcher against per-frame SGBM on tuning-seed sequences."""
    rows, table = [], []
    for index, spec in enumerate(SEQUENCES):
        if spec.name not in specs:
            continue
        seed = TUNING_SEEDS[index]
        seq = render(spec, frames, None, seed, None)
        max_disp = MAX_DISPARITY[spec.preset]
        gt, mask = seq.disparity, (seq.disparity > 0) & ~seq.occluded
        sgbm = opencv_matchers(max_disp)["OpenCV SGBM 3-way"]
        methods = {SGBM: lambda s, fn=sgbm: run_per_frame(fn, s)}
        for name, kw in LOOP_MATCHERS.items():
            methods[name] = lambda s, kw=kw, md=max_disp: run_refiner(
                EgoMotionRefiner(max_disparity=md, verify_every=VERIFY_EVERY, fusion="kalman", **kw), s)
        for name, run in methods.items():
            d, v, ms, _ = run(seq)
            m = evaluate_disparity(d, gt, v, mask)
            row = {"sequence": spec.name, "seed": seed, "method": name, "epe": m["epe"], "bad05": m["bad-0.5"],
                   "density": m["density"], "ms": statistics.fmean(ms)}
            rows.append(row)
            table.append([spec.name, seed, name, row["epe"], 100 * row["bad05"], 100 * row["density"],
                          f"{row['ms']:.0f}"])
            print(table[-1], file=sys.stderr)
    text = markdown_table(["sequence", "seed", "method", "EPE px", "bad-0.5 %", "density %", "ms/frame"], table)
    print(text)
    out = RESULTS / "cache" / "tune_stereo_loop.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": machine_info(), "frames": frames, "matchers": LOOP_MATCHERS,
                               "rows": rows, "table": text}, indent=2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds-per-spec", type=int, default=2, help="frames per sequence spec (seeds each)")
    parser.add_argument("--presets", default="paper,kitti")
    parser.add_argument("--only", default=None, help="comma-separated configuration names (OpenCV always runs)")
    parser.add_argument("--extra", default=None, help="JSON object name -> match_stereo keyword arguments")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", default="tune_stereo", help="name of the JSON in results/cache")
    parser.add_argument("--loop", action="store_true", help="the refiner's verification matchers (see above)")
    parser.add_argument("--frames", type=int, default=15, help="--loop: frames per sequence")
    parser.add_argument("--loop-specs", default="paper_corridor_forward,kitti_street_forward")
    args = parser.parse_args()
    set_threads(args.threads)
    if args.loop:
        loop(args.frames, [n.strip() for n in args.loop_specs.split(",")])
        return
    configs = dict(CONFIGS)
    if args.only:
        wanted = [w.strip() for w in args.only.split(",") if w.strip()]
        unknown = [w for w in wanted if w not in configs]
        if unknown:
            parser.error(f"--only: unknown configuration(s) {unknown}; choose from {list(configs)}")
        configs = {k: configs[k] for k in wanted}
    if args.extra:
        configs.update(json.loads(args.extra))
    presets = tuple(p.strip() for p in args.presets.split(","))
    frames = tuning_frames(args.seeds_per_spec, presets)
    rows = []
    warm: set[tuple[str, str]] = set()
    for frame in frames:
        num = MAX_DISPARITY[frame["preset"]]
        fns = opencv(num)
        fns.update({name: ours(num, kw) for name, kw in configs.items()})
        for name, fn in fns.items():
            if (name, frame["preset"]) not in warm:  # numba compiles (or loads its cache) on a first call
                fn(frame)
                warm.add((name, frame["preset"]))
            t0 = time.perf_counter()
            d, v = fn(frame)
            ms = (time.perf_counter() - t0) * 1e3
            rows.append({"frame": frame["name"], "seed": frame["seed"], "preset": frame["preset"], "method": name,
                         "ms": ms, **score(d, v, frame)})
        print(f"{frame['name']} seed {frame['seed']}: "
              + "  ".join(f"{r['method']}: {r['bad2']:.3f}@{r['density']:.2f}" for r in rows[-len(fns):]),
              file=sys.stderr)
    table_rows = []
    summary = {}
    for preset in presets:
        sgbm_ms = statistics.median(r["ms"] for r in rows if r["preset"] == preset and r["method"] == SGBM)
        for name in dict.fromkeys(r["method"] for r in rows):
            sel = [r for r in rows if r["preset"] == preset and r["method"] == name]
            if not sel:
                continue
            mean = {k: statistics.fmean(r[k] for r in sel) for k in ("epe", "bad05", "bad1", "bad2", "density")}
            ms = statistics.median(r["ms"] for r in sel)
            summary[f"{preset}/{name}"] = {**mean, "ms": ms, "frames": len(sel)}
            table_rows.append([preset, len(sel), name, mean["epe"], 100 * mean["bad05"], 100 * mean["bad1"],
                               100 * mean["bad2"], 100 * mean["density"], f"{ms:.0f}", f"{ms / sgbm_ms:.2f}x"])
    text = markdown_table(["rig", "frames", "method", "EPE px", "bad-0.5 %", "bad-1 %", "bad-2 %", "density %",
                           "ms/frame", "/SGBM"], table_rows)
    print(text)
    out = RESULTS / "cache" / f"{args.out}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": machine_info(), "seeds_per_spec": args.seeds_per_spec,
                               "configs": configs, "summary": summary, "rows": rows, "table": text}, indent=2))


if __name__ == "__main__":
    main()
