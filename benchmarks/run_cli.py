"""`egorefine run` end to end: frames/s with the per-frame files written, against refining alone.

The command a user runs on a recording (``egorefine run --layout euroc``, default options) is timed on the real
EuRoC clip, once with ``--outputs none`` (refining alone: the trajectory and run.json only) and once per output set,
round-robin so that a burst of machine load hits every configuration alike. Each run's frames/s leave out the first
frame (it loads numba's cache); they come from the run's own run.json (the same timer a user sees). The ratio of a
configuration is taken against the ``none`` run of the same round, and its median and range over the rounds are
reported. A second table times the library's writers alone on one thread, per file, in both PNG encodings, on the
maps of the clip's last frame (read back from a run's files: the values the run wrote).

    python benchmarks/run_cli.py [--root tests/data/real/euroc_v1_01_micro] [--rounds 5] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, markdown_table, set_threads, update_readme, write_json  # noqa: E402

from egorefine.cli import main  # noqa: E402
from egorefine.data import (  # noqa: E402
    PNG_ENCODINGS,
    read_disparity,
    write_confidence,
    write_disparity,
    write_mask,
    write_preview,
)
from egorefine.viz import disparity_palette_image  # noqa: E402

# name -> the options that differ from the defaults (the first is the reference: refining alone)
CONFIGS = {
    "refining alone (--outputs none)": ["--outputs", "none"],
    "all four outputs (default)": [],
    "all four, --png small": ["--png", "small"],
    "disparity,valid,confidence": ["--outputs", "disparity,valid,confidence"],
    "disparity,valid": ["--outputs", "disparity,valid"],
}


def run_once(root: Path, extra: list[str], threads: int, keep: Path | None = None) -> dict:
    """One ``egorefine run`` into a fresh folder (``keep``, or a temporary one); returns its run.json timings."""
    with tempfile.TemporaryDirectory() as tmp:
        out = keep or Path(tmp) / "out"
        code = main(["run", "--layout", "euroc", "--quiet", "--threads", str(threads), "--out", str(out),
                     *extra, str(root)])
        if code not in (0, None):
            raise SystemExit(f"egorefine run failed with exit status {code}")
        report = json.loads((out / "run.json").read_text())
    timings = report["timings"]
    frames = report["frames"]["count"]
    steady_s = timings["loop_s"] - timings["refine_ms_first_frame"] / 1e3
    return {"frames": frames, "fps": (frames - 1) / steady_s, "write_ms_mean": timings["write_ms_mean"],
            "refine_ms_mean_after_first": timings["refine_ms_mean_after_first"]}


def writer_table(root: Path, repeats: int = 9) -> tuple[str, dict]:
    """Each writer's ms (median of ``repeats``, one thread, encodings interleaved) and file size per encoding."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        run_once(root, ["--outputs", "disparity,confidence"], 1, keep=tmp / "run")
        stem = sorted((tmp / "run" / "disparity").iterdir())[-1].stem
        disparity, valid = read_disparity(tmp / "run" / "disparity" / f"{stem}.png")
        confidence = cv2.imread(str(tmp / "run" / "confidence" / f"{stem}.png"), cv2.IMREAD_UNCHANGED) / 65535.0
        max_disparity = 64  # egorefine run's default --max-disparity

        def preview(path: Path, png: str) -> Path:  # as egorefine run writes it
            index, palette = disparity_palette_image(disparity, max_disparity, valid, (128, 128, 128))
            return write_preview(path, index, png, palette)

        writers = {
            "disparity (uint16)": lambda d, png: write_disparity(d / "d", disparity, valid, "png16", png),
            "valid (uint8 mask; always small)": lambda d, png: write_mask(d / "v.png", valid),
            "confidence (uint16)": lambda d, png: write_confidence(d / "c", confidence, "png16", png),
            "preview (indexed colour, colour map included)": lambda d, png: preview(d / "p.png", png),
        }
        ms = {(w, png): [] for w in writers for png in PNG_ENCODINGS}
        size = {}
        for i in range(repeats):
            for (w, png), times in ms.items():
                folder = tmp / f"{png}{i}"  # a new file each time, as a run writes them
                folder.mkdir(exist_ok=True)
                t0 = time.perf_counter()
                path = writers[w](folder, png)
                times.append((time.perf_counter() - t0) * 1e3)
                size[w, png] = path.stat().st_size / 1024
    rows = [[w, *(x for png in PNG_ENCODINGS for x in (statistics.median(ms[w, png]), size[w, png]))]
            for w in writers]
    rows.append(["all four", *(x for png in PNG_ENCODINGS
                               for x in (sum(statistics.median(ms[w, png]) for w in writers),
                                         sum(size[w, png] for w in writers)))])
    header = ["file", *(f"{png}: {what}" for png in PNG_ENCODINGS for what in ("ms", "KiB"))]
    text = (f"The writers alone, one thread, the clip's last frame ({disparity.shape[-1]}x{disparity.shape[-2]}), "
            f"median of {repeats}, `--png` encodings interleaved:\n\n" + markdown_table(header, rows))
    return text, {"ms": {f"{w} | {png}": v for (w, png), v in ms.items()},
                  "kib": {f"{w} | {png}": v for (w, png), v in size.items()}}


def main_(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, default=ROOT / "tests" / "data" / "real" / "euroc_v1_01_micro")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    set_threads(args.threads)
    names = list(CONFIGS)
    run_once(args.root, CONFIGS[names[0]], args.threads)  # warm-up: numba's cache, OpenCV's and torch's pools
    runs: dict[str, list[dict]] = {name: [] for name in names}
    for r in range(args.rounds):
        for name in names:
            runs[name].append(run_once(args.root, CONFIGS[name], args.threads))
        print(f"round {r + 1}/{args.rounds}: " + ", ".join(f"{n.split(' (')[0]} {runs[n][-1]['fps']:.1f}"
                                                             for n in names), flush=True)
    ref = names[0]
    rows, summary = [], {}
    for name in names:
        fps = [x["fps"] for x in runs[name]]
        ratio = [x["fps"] / y["fps"] for x, y in zip(runs[name], runs[ref], strict=True)]
        summary[name] = {"options": CONFIGS[name], "fps": fps, "ratio_to_refining_alone": ratio,
                         "write_ms_mean": [x["write_ms_mean"] for x in runs[name]]}
        options = f"`{' '.join(CONFIGS[name])}`" if CONFIGS[name] else "-"
        rows.append([name, options, statistics.median(fps), f"{min(fps):.1f}-{max(fps):.1f}",
                     statistics.median(ratio), f"{min(ratio):.2f}-{max(ratio):.2f}",
                     statistics.median(summary[name]["write_ms_mean"])])
    frames = runs[ref][0]["frames"]
    where = args.root.relative_to(ROOT) if args.root.is_relative_to(ROOT) else args.root
    text = (f"`egorefine run --layout euroc` on `{where}` ({frames} frames), {args.threads} threads, "
            f"{args.rounds} rounds round-robin; frames/s after the "
            "first frame, from each run's run.json; ratio to the same round's run with `--outputs none`. Target "
            "(issue 29): the default at least 0.8x.\n\n"
            + markdown_table(["configuration", "options", "frames/s", "range", "ratio", "ratio range",
                              "write ms/frame (writer thread)"], rows))
    table, files = writer_table(args.root)
    text += "\n\n" + table
    print(text)
    write_json("run_cli", {"root": str(args.root), "threads": args.threads, "rounds": args.rounds, "runs": summary,
                           "writers": files})
    update_readme("run_cli", text)


if __name__ == "__main__":
    main_()
