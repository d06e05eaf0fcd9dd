"""Stereo matching benchmark: egorefine.stereo against OpenCV StereoBM and StereoSGBM (3-way).

Accuracy (EPE, bad-1, bad-2 on the pixels each method marks valid, and density = valid share of
the pixels with known truth) and time per pair, all methods timed round-robin in the same run
with 2 threads, at 640x480 and 1242x375 with 64 and 128 disparities. Data: the Middlebury
'motorcycle' pair that scikit-image ships, cropped to the target aspect and resized (its truth
scaled alike); with ``--synthetic`` also one frame of the repository's renderer per size
("paper" preset at 640x480, "kitti" at 1242x375). The default matcher runs compiled on CPU
(numba); it is also timed with that switched off, as the eager torch int16 path, which gives the
same outputs. Peak extra memory of the default matcher (both paths) and of SGM at 1242x375 /
128 disparities is the process RSS high-water mark (VmHWM) growth in a fresh subprocess, so
torch's CPU allocations are seen.

    python benchmarks/stereo.py            # full run (a few minutes)
    python benchmarks/stereo.py --quick    # 640x480 / 64 only, fewer repeats
    python benchmarks/stereo.py --quick --torch-compile  # and the torch path under torch.compile

Writes benchmarks/results/stereo.json and the README's ``stereo`` table.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks._common import (  # noqa: E402
    markdown_table,
    omp_setting,
    set_threads,
    time_interleaved,
    update_readme,
    write_json,
)
from egorefine.core import dispatch  # noqa: E402
from egorefine.stereo import match_stereo  # noqa: E402

SIZES = [(640, 480), (1242, 375)]
DISPARITIES = [64, 128]
BM_BLOCK = 9
SGBM_BLOCK = 5

OURS = {
    "ours sad (default)": {},
    "ours zncc": {"cost": "zncc"},
    "ours census": {"cost": "census", "block_size": 7},
    "ours sgm (census, 4 paths)": {"cost": "census", "aggregation": "sgm", "block_size": 5},
    "ours differentiable (sad)": {"differentiable": True},
}
# the default matcher with its compiled CPU form switched off: the eager torch int16 path (same outputs)
TORCH_PATH = "ours sad (default), eager torch path"
COMPILED_TORCH_PATH = "ours sad (default), torch path + torch.compile"


def motorcycle(width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The motorcycle pair (grey uint8) and its truth, centre-cropped to the aspect, resized."""
    from skimage import data

    left, right, gt = data.stereo_motorcycle()
    h, w = gt.shape
    aspect = width / height
    if w / h > aspect:  # too wide: crop columns
        cw, ch = int(round(h * aspect)), h
    else:
        cw, ch = w, int(round(w / aspect))
    x0, y0 = (w - cw) // 2, (h - ch) // 2
    crop = lambda a: a[y0 : y0 + ch, x0 : x0 + cw]  # noqa: E731
    grey = [cv2.cvtColor(crop(a), cv2.COLOR_RGB2GRAY) for a in (left, right)]
    grey = [cv2.resize(g, (width, height), interpolation=cv2.INTER_AREA) for g in grey]
    truth = crop(gt).astype(np.float32)
    truth = cv2.resize(np.where(np.isfinite(truth), truth, -1.0), (width, height), interpolation=cv2.INTER_NEAREST)
    truth = np.where(truth > 0, truth * (width / cw), np.inf).astype(np.float32)
    return grey[0], grey[1], truth


def synthetic(width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame of the renderer (occluded pixels have no truth)."""
    from egorefine.data import render_sequence

    preset = "paper" if width == 640 else "kitti"
    seq = render_sequence(1, preset=preset, height=height, width=width, seed=0)
    to_u8 = lambda t: (t[0, 0].clamp(0, 1) * 255).round().to(torch.uint8).numpy()  # noqa: E731
    truth = seq.disparity[0, 0].numpy().copy()
    truth[seq.occluded[0, 0].numpy()] = np.inf
    return to_u8(seq.left), to_u8(seq.right), truth


def score(disp: np.ndarray, valid: np.ndarray, gt: np.ndarray) -> dict:
    known = np.isfinite(gt)
    scored = valid & known
    err = np.abs(disp - gt)[scored]
    if err.size == 0:
        return {"epe": float("nan"), "bad1": float("nan"), "bad2": float("nan"), "density": 0.0}
    return {
        "epe": float(err.mean()),
        "bad1": float((err > 1).mean()),
        "bad2": float((err > 2).mean()),
        "density": float(scored.sum() / known.sum()),
    }


def methods(left: np.ndarray, right: np.ndarray, num: int, torch_compile: bool = False) -> dict:
    """name -> callable returning (disparity float32, valid bool) numpy arrays."""
    bm = cv2.StereoBM_create(num, BM_BLOCK)
    area = SGBM_BLOCK * SGBM_BLOCK
    sgbm = cv2.StereoSGBM_create(0, num, SGBM_BLOCK, P1=8 * area, P2=32 * area, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    tl = torch.from_numpy(left).float()[None, None] / 255.0
    tr = torch.from_numpy(right).float()[None, None] / 255.0

    def opencv(matcher):
        def run():
            raw = matcher.compute(left, right)
            return raw.astype(np.float32) / 16.0, raw >= 0

        return run

    def ours(kw, compiled=True, fn=match_stereo):
        def run():
            previous = dispatch.ENABLED
            dispatch.ENABLED = compiled
            try:
                with torch.no_grad():
                    out = fn(tl, tr, num, **kw)
            finally:
                dispatch.ENABLED = previous
            return out.disparity[0, 0].numpy(), out.valid[0, 0].numpy()

        return run

    fns = {f"opencv bm (block {BM_BLOCK})": opencv(bm), f"opencv sgbm 3way (block {SGBM_BLOCK})": opencv(sgbm)}
    fns.update({name: ours(kw) for name, kw in OURS.items()})
    fns[TORCH_PATH] = ours({}, compiled=False)
    if torch_compile:  # the torch path under torch.compile (its first call, in the accuracy pass, compiles)
        fns[COMPILED_TORCH_PATH] = ours({}, compiled=False, fn=torch.compile(match_stereo))
    return fns


_MEMORY_SNIPPET = """
import json, sys, torch
sys.path.insert(0, {root!r})
torch.set_num_threads(2)
from egorefine.stereo import match_stereo
from egorefine.core import dispatch
dispatch.ENABLED = {compiled!r}
def hwm():
    for line in open('/proc/self/status'):
        if line.startswith('VmHWM'):
            return int(line.split()[1]) * 1024
g = torch.Generator().manual_seed(0)
left = torch.rand(1, 1, 375, 1242, generator=g); right = torch.rand(1, 1, 375, 1242, generator=g)
with torch.no_grad():
    match_stereo(left[..., :64, :256], right[..., :64, :256], 128, **{kw!r})  # warm up code paths
    before = hwm()
    match_stereo(left, right, 128, **{kw!r})
print(json.dumps({{"extra_mb": (hwm() - before) / 2**20}}))
"""


def peak_memory(kw: dict, compiled: bool = True) -> float:
    root = str(Path(__file__).resolve().parents[1])
    snippet = _MEMORY_SNIPPET.format(root=root, kw=kw, compiled=compiled)
    out = subprocess.run([sys.executable, "-c", snippet], capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])["extra_mb"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="640x480 / 64 disparities only, fewer repeats")
    parser.add_argument("--synthetic", action="store_true", help="also score one rendered frame per size")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--torch-compile", action="store_true",
                        help="also time the default matcher's torch path under torch.compile (compiles first)")
    parser.add_argument("--table-only", action="store_true", help="rewrite the table from the last JSON")
    args = parser.parse_args()
    if args.table_only:
        last = json.loads((Path(__file__).resolve().parent / "results" / "stereo.json").read_text())
        update_readme("stereo", table(last["results"], last["peak_extra_memory_mb_1242x375_128"], last["threads"]))
        return
    set_threads(args.threads)

    configs = [(s, n) for s in SIZES for n in DISPARITIES]
    if args.quick:
        configs = configs[:1]
    fast_repeats, slow_repeats = (5, 2) if args.quick else (7, 2)
    results = []
    for (width, height), num in configs:
        datasets = {"motorcycle": motorcycle(width, height)}
        if args.synthetic:
            datasets["synthetic"] = synthetic(width, height)
        for data_name, (left, right, gt) in datasets.items():
            fns = methods(left, right, num, args.torch_compile)
            acc = {name: score(*fn(), gt) for name, fn in fns.items()}
            timing = {}
            if data_name == "motorcycle":  # time once per size (timing does not depend on the content much)
                bm, sgbm, default = list(fns)[:3]
                fast = (bm, sgbm, default, TORCH_PATH, "ours sgm (census, 4 paths)",
                        *[k for k in (COMPILED_TORCH_PATH,) if k in fns])
                timing = time_interleaved({k: fns[k] for k in fast}, repeats=fast_repeats, burst=3)
                # the accuracy pass above already warmed every method up
                slow = time_interleaved({k: fns[k] for k in fns if k not in fast}, repeats=slow_repeats, warmup=0)
                for k, v in slow.items():
                    timing.setdefault(k, v)
            for name in fns:
                row = {"data": data_name, "size": f"{width}x{height}", "disparities": num, "method": name, **acc[name]}
                if name in timing:
                    row["time"] = timing[name]
                results.append(row)
                t = f"{timing[name]['median_ms']:9.1f} ms" if name in timing else ""
                print(f"{data_name:10s} {width}x{height} D={num:3d} {name:38s} epe {acc[name]['epe']:.3f} "
                      f"bad2 {acc[name]['bad2']:.4f} dens {acc[name]['density']:.3f} {t}", flush=True)

    memory = {}
    if not args.quick:
        for name in ("ours sad (default)", TORCH_PATH, "ours sgm (census, 4 paths)"):
            memory[name] = peak_memory(OURS.get(name, {}), compiled=name != TORCH_PATH)
            print(f"peak extra memory 1242x375/128 {name}: {memory[name]:.0f} MB", flush=True)

    # a quick run is a smoke run: its own git-ignored file, and the README keeps the full run's table
    write_json("stereo_quick" if args.quick else "stereo",
               {"threads": args.threads, "omp_wait_policy": omp_setting(),
                "quick": args.quick, "results": results,
                "peak_extra_memory_mb_1242x375_128": memory,
                "memory_method": "growth of the process RSS high-water mark (VmHWM) in a fresh subprocess"})
    if not args.quick:
        update_readme("stereo", table(results, memory, args.threads))


def table(results: list[dict], memory: dict, threads: int) -> str:
    rows = []
    ref = {}
    for r in results:
        if "time" in r and r["method"].startswith("opencv"):
            ref[(r["size"], r["disparities"], r["method"].split(" (")[0])] = r["time"]["median_ms"]
    for r in results:
        key = (r["size"], r["disparities"])
        t = r.get("time")
        time_s = f"{t['median_ms']:.1f} [{t['q1_ms']:.1f}-{t['q3_ms']:.1f}]" if t else ""
        bm, sgbm = ref.get((*key, "opencv bm")), ref.get((*key, "opencv sgbm 3way"))
        vs_bm = f"{t['median_ms'] / bm:.1f}x" if t and bm else ""
        vs_sgbm = f"{t['median_ms'] / sgbm:.1f}x" if t and sgbm else ""
        rows.append([r["data"], r["size"], r["disparities"], r["method"], r["epe"], 100 * r["bad1"],
                     100 * r["bad2"], 100 * r["density"], time_s, vs_bm, vs_sgbm])
    header = ["data", "size", "D", "method", "EPE px", "bad-1 %", "bad-2 %", "density %", "ms/pair median [IQR]",
              "/BM", "/SGBM"]
    text = (f"torch and OpenCV with {threads} thread(s) ({omp_setting()}); bad-x and EPE over the "
            "pixels each method marks valid, "
            "density = their share of the pixels with known truth; /BM and /SGBM are time ratios in the same run.\n\n"
            + markdown_table(header, rows))
    if memory:
        text += "\n\nPeak extra memory at 1242x375, 128 disparities (RSS high-water growth, fresh process): " + \
            ", ".join(f"{k}: {v:.0f} MB" for k, v in memory.items()) + "."
    return text


if __name__ == "__main__":
    main()
