"""The CUDA path: matcher and predict-and-correct loop timed on a GPU, with their error against the truth.

On a GPU every stage takes its torch path (the compiled numba kernels are CPU-only). Times are
wall-clock per frame with the device synchronised, medians over the frames after the first few;
the lower of two runs through the sequence (the host's launch times vary between runs); the
per-stage split wraps each stage in synchronised timers (which adds a little to each). Needs
a CUDA device; the test suite checks the same path for correctness (tests/test_cuda.py).

    python benchmarks/gpu.py                # on a machine with a GPU
    python benchmarks/gpu.py --table-only   # rewrite the README table from the last JSON

Writes benchmarks/results/gpu.json and the README's ``gpu`` table.
"""

from __future__ import annotations

import argparse
import collections
import json
import statistics
import sys
import time
from functools import partial
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import egorefine.refine.refiner as refiner_module  # noqa: E402
from benchmarks._common import markdown_table, update_readme, write_json  # noqa: E402
from egorefine.data import render_sequence  # noqa: E402
from egorefine.metrics import epe  # noqa: E402
from egorefine.stereo import match_stereo  # noqa: E402

RIGS = {"paper": 64, "kitti": 128}
MATCHERS = {
    "default (SAD)": {},
    "census + SGM (4 paths)": {"cost": "census", "aggregation": "sgm", "block_size": 5},
    "ZNCC": {"cost": "zncc"},
}
LOOPS = [("kalman", 1, 1), ("kalman", 5, 1), ("paper", 5, 1), ("kalman", 5, 4)]
STAGES = ["track", "solve_ego_motion", "predict_finished", "match_stereo", "correct_disparity",
          "replenish", "_expected_positions", "build_pyramid"]
SKIP = 5  # frames left out of the timing (first frame, warm-up)


def _timed(fn, *args):
    """``(ms, fn(*args))`` with the device synchronised before and after."""
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    result = fn(*args)
    torch.cuda.synchronize()
    return (time.perf_counter() - t0) * 1e3, result


def _run_loop(seq, max_d: int, fusion: str, every: int, batch: int, runs: int = 2) -> dict:
    """The loop over the whole sequence ``runs`` times: the lower of the runs' median ms per frame (the host's
    launch times vary by ~25 % between runs), the first run's errors."""
    dev = seq.left.device
    model = refiner_module.EgoMotionRefiner(max_disparity=max_d, verify_every=every, fusion=fusion)
    K, b = seq.K[None].expand(batch, 3, 3), torch.full((batch,), seq.baseline, device=dev)
    medians, errors = [], []
    for run in range(runs):
        state, times = None, []
        for t in range(len(seq.left)):
            left = seq.left[t : t + 1].expand(batch, -1, -1, -1)
            right = seq.right[t : t + 1].expand(batch, -1, -1, -1)
            ms, (out, state) = _timed(model, left, right, K, b, state)
            times.append(ms)
            if run == 0:
                errors.append(float(epe(out.disparity[:1], seq.disparity[t : t + 1], out.valid[:1])))
        medians.append(statistics.median(times[SKIP:]))
    ms = min(medians)
    return {"fusion": fusion, "verify_every": every, "batch": batch, "ms_per_frame": ms, "ms_per_item": ms / batch,
            "epe_mean": statistics.fmean(errors)}


def _stage_split(seq, max_d: int) -> dict:
    """Per-stage ms per frame of Kalman at verify every 5 (B = 1), each stage in synchronised timers."""
    totals: dict[str, float] = collections.defaultdict(float)
    originals = {name: getattr(refiner_module, name) for name in STAGES}

    def wrap(name, fn):
        def timed(*args, **kwargs):
            torch.cuda.synchronize()
            t0 = time.perf_counter()
            result = fn(*args, **kwargs)
            torch.cuda.synchronize()
            totals[name] += (time.perf_counter() - t0) * 1e3
            return result

        return timed

    model = refiner_module.EgoMotionRefiner(max_disparity=max_d, verify_every=5, fusion="kalman")
    K, b = seq.K[None], torch.tensor([seq.baseline], device=seq.left.device)
    state, whole = None, 0.0
    try:
        for name, fn in originals.items():
            setattr(refiner_module, name, wrap(name, fn))
        for t in range(len(seq.left)):
            if t == SKIP:
                totals.clear()
            ms, (_, state) = _timed(model, seq.left[t : t + 1], seq.right[t : t + 1], K, b, state)
            whole += ms if t >= SKIP else 0.0
    finally:
        for name, fn in originals.items():
            setattr(refiner_module, name, fn)
    n = len(seq.left) - SKIP
    return {"total": whole / n, **{k: v / n for k, v in sorted(totals.items(), key=lambda kv: -kv[1])}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--table-only", action="store_true", help="rewrite the table from the last JSON")
    args = parser.parse_args()
    path = Path(__file__).resolve().parent / "results" / "gpu.json"
    if args.table_only:
        update_readme("gpu", table(json.loads(path.read_text())))
        return
    if not torch.cuda.is_available():
        sys.exit("benchmarks/gpu.py needs a CUDA device")
    dev = torch.device("cuda")
    payload = {"device": torch.cuda.get_device_name(), "torch": torch.__version__, "frames": args.frames,
               "matchers": [], "loops": [], "stages": {}}
    for rig, max_d in RIGS.items():
        seq = render_sequence(num_frames=args.frames, preset=rig, seed=0, device=dev)
        for name, kw in MATCHERS.items():
            times, errors = [], []
            for t in range(args.frames):
                ms, out = _timed(partial(match_stereo, **kw), seq.left[t : t + 1], seq.right[t : t + 1], max_d)
                times.append(ms)
                errors.append(float(epe(out.disparity, seq.disparity[t : t + 1], out.valid)))
            row = {"rig": rig, "matcher": name, "ms": statistics.median(times[SKIP:]),
                   "epe_mean": statistics.fmean(errors)}
            payload["matchers"].append(row)
            print(f"{rig:6s} stereo {name:24s} {row['ms']:7.1f} ms  EPE {row['epe_mean']:.3f}", flush=True)
        for fusion, every, batch in LOOPS:
            row = {"rig": rig, **_run_loop(seq, max_d, fusion, every, batch)}
            payload["loops"].append(row)
            print(f"{rig:6s} {fusion:6s} every {every} B={batch} {row['ms_per_frame']:7.1f} ms/frame "
                  f"({row['ms_per_item']:.1f} per item)  EPE {row['epe_mean']:.3f}", flush=True)
        payload["stages"][rig] = _stage_split(seq, max_d)
        print(rig, "stages (kalman, every 5, B=1):",
              ", ".join(f"{k} {v:.1f}" for k, v in payload["stages"][rig].items()), flush=True)
    write_json("gpu", payload)
    update_readme("gpu", table(payload))


def table(payload: dict) -> str:
    rows = [[r["rig"], f"stereo: {r['matcher']}", "", r["ms"], "", r["epe_mean"]] for r in payload["matchers"]]
    rows += [[r["rig"], f"{r['fusion']} mode, verify every {r['verify_every']}", r["batch"], r["ms_per_frame"],
              r["ms_per_item"], r["epe_mean"]] for r in payload["loops"]]
    text = (f"{payload['device']}, torch {payload['torch']}; {payload['frames']} rendered frames per rig, median ms "
            f"per frame after the first {SKIP} (loops: lower of two runs), EPE in px over each frame's valid pixels "
            "(mean over frames; the batch's first item).\n\n"
            + markdown_table(["rig", "what", "B", "ms/frame", "ms per item", "EPE"], rows))
    bullets = []
    for rig, stages in payload["stages"].items():
        split = ", ".join(f"{k} {v:.1f}" for k, v in stages.items() if k != "total")
        bullets.append(f"- {rig}: Kalman, verify every 5, B = 1, with each stage synchronised: "
                       f"{stages['total']:.1f} ms per frame; {split} ms.")
    return text + "\n\n" + "\n".join(bullets)


if __name__ == "__main__":
    main()
