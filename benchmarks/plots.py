"""Figures for the benchmarks that draw none themselves, from the JSON they stored in benchmarks/results/.

refine.py and speed.py draw their own figures as they run; the other benchmarks write only JSON and a table. This
script reads that JSON (it measures nothing, imports neither torch nor egorefine, and takes a few seconds) and draws
one figure per benchmark, ``benchmarks/results/<name>.png``, for the docs' benchmarks page:

- ``real``: bad-2 against density per matcher on each real pair, ours beside OpenCV, with the regions that issue
  17's targets (stored in the JSON) ask ours to reach;
- ``euroc_static``: the drift on a still camera per method, EuRoC V1_01 (with issue 20's tile-drift bound) and the
  long rendered sequence against its truth;
- ``stereo``: bad-2 against density per matcher, per image size and disparity range;
- ``autograd``: the gradient step's time ratios against issue 19's targets (read from autograd.py), and
  ``torch.compile`` against eager;
- ``ego_motion``: translation and rotation error per method, rig and source of disparity;
- ``gpu``: ms per frame of the matchers and the loop on the GPU, and the loop's stages (the run has no CPU
  timings to set beside them);
- ``learning``: the two training stages' loss curves, and EPE per held-back sequence before and after training.

Each figure's title carries the date and machine stored in its JSON. A benchmark whose JSON is missing is skipped
with a note on stderr. ``make bench`` runs this after the benchmarks.

    python benchmarks/plots.py                    # every figure whose JSON is there
    python benchmarks/plots.py real stereo        # only these
    python benchmarks/plots.py --out /tmp/plots   # write the PNGs elsewhere
"""

from __future__ import annotations

import argparse
import ast
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
SIZE = (8.5, 4.2)  # inches; at DPI this keeps each PNG small
DPI = 110
# issue 20's bound on the largest per-tile drift (benchmarks/euroc_static.py's docstring; the test holds each fusion
# to its own, tighter bound)
TILE_DRIFT_BOUND_PX = 0.05
# learning.py's target: the held-back mean EPE at least this share below the untrained defaults'
LEARNING_TARGET_GAIN = 0.10
COLORS = plt.rcParams["axes.prop_cycle"].by_key()["color"]


def script_constant(script: str, name: str) -> float:
    """A module-level constant of a benchmark script, read from its source (no import: no torch here)."""
    tree = ast.parse((HERE / script).read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == name for t in node.targets):
            return ast.literal_eval(node.value)
    raise KeyError(f"{script} has no constant {name}")


def stamp(payload: dict) -> str:
    """The run's date and machine as stored in its JSON, for a title's second line."""
    m = payload.get("machine", {})
    parts = [m.get("date", "undated")]
    if payload.get("device"):
        parts.append(payload["device"])
    elif m.get("cpus"):
        parts.append(f"{m['cpus']} CPUs, {m.get('torch_threads', '?')} threads")
    if m.get("torch"):
        parts.append(f"torch {m['torch']}")
    return ", ".join(parts)


def finish(fig: plt.Figure, title: str, payload: dict, path: Path, bottom: float | None = None) -> None:
    """Title the figure with what it shows and when and where it was measured, lay it out and save it."""
    fig.suptitle(f"{title}\n{stamp(payload)}", fontsize=10)
    fig.tight_layout(rect=(0, bottom or 0, 1, 1))
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def short(method: str) -> str:
    """A method's name without the words every legend entry would repeat."""
    return method.replace(" (census, 4 paths)", " (census)").replace("opencv ", "OpenCV ")


def plain_log(axis: matplotlib.axis.Axis) -> None:
    """Put a log axis's ticks in plain numbers (2, 3, 5, 10 rather than powers of ten); call after plotting."""
    if axis.axis_name == "y":
        axis.axes.set_yscale("log")
    else:
        axis.axes.set_xscale("log")
    axis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
    low, high = axis.get_view_interval()
    digits = "123456789" if high / low < 10 else "235"  # within a decade every minor tick gets its label
    axis.set_minor_formatter(matplotlib.ticker.FuncFormatter(
        lambda v, _: f"{v:g}" if f"{v:g}".lstrip("0.")[:1] in digits else ""))
    axis.axes.tick_params(axis=axis.axis_name, which="both", labelsize=8)


def method_styles(methods: list[str]) -> dict[str, dict]:
    """One colour and marker per method, kept across panels: OpenCV's in greys, ours in colour."""
    styles, ours, grey = {}, 0, 0
    for name in methods:
        if name.startswith("opencv"):
            styles[name] = {"color": ("0.1", "0.35", "0.55")[grey % 3], "marker": "sD^v"[grey % 4]}
            grey += 1
        else:
            styles[name] = {"color": COLORS[ours % len(COLORS)], "marker": "o^vPXh"[ours % 6]}
            ours += 1
    return styles


def plot_real(payload: dict, path: Path) -> None:
    """bad-2 against density per matcher on each pair, with the target regions of issue 17."""
    rows = payload["results"]
    pairs = list(dict.fromkeys(r["data"] for r in rows))
    styles = method_styles(list(dict.fromkeys(r["method"] for r in rows)))
    # "pair: OURS bad-2 x % at y % vs OPENCV x % at y % (density allowance N points): met"
    pattern = re.compile(r"^(\S+): (.+?) bad-2 .* vs (.+?) [\d.]+ % at .*allowance ([\d.]+) points\): (.+)$")
    targets = [m.groups() for t in payload.get("targets", []) if (m := pattern.match(t))]
    fig, axes = plt.subplots(1, len(pairs), figsize=(SIZE[0], SIZE[1] + 0.6), squeeze=False)
    for ax, pair in zip(axes[0], pairs, strict=True):
        by_method = {r["method"]: r for r in rows if r["data"] == pair}
        for name, r in by_method.items():
            ax.scatter(100 * r["density"], 100 * r["bad2"], s=40, zorder=3, label=short(name), **styles[name])
        verdicts = []
        for data, ours, ref, allowance, verdict in targets:
            if data != pair or ours not in by_method or ref not in by_method:
                continue
            x0, y0 = 100 * by_method[ref]["density"] - float(allowance), 100 * by_method[ref]["bad2"]
            ax.fill_between([x0, 100], 0, y0, color=styles[ours]["color"], alpha=0.08, zorder=1)
            ax.plot([x0, x0, 100], [0, y0, y0], color=styles[ours]["color"], lw=0.8, ls=":", zorder=2)
            verdicts.append(f"{short(ours).removeprefix('ours ')} {verdict}")
        xs = [100 * r["density"] for r in by_method.values()]
        ys = [100 * r["bad2"] for r in by_method.values()]
        ax.set_xlim(min(xs) - 4, min(100, max(xs) + 4))
        ax.set_ylim(0, max(ys) * 1.15)
        first = next(iter(by_method.values()))
        ax.set_title(f"{pair} ({first['size']}, D = {first['disparities']})"
                     + (f"\ntargets: {', '.join(verdicts)}" if verdicts else ""), fontsize=9)
        ax.set_xlabel("density (% of truth pixels)")
        ax.set_ylabel("bad-2 (% of valid pixels with truth)")
        ax.grid(True, alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=7, frameon=False)
    finish(fig, "Real pairs: error against density per matcher (lower right is better; shaded: the targets)",
           payload, path, bottom=0.13)


def plot_euroc_static(payload: dict, path: Path) -> None:
    """Drift on a still camera per method: EuRoC V1_01 and, where stored, the long rendered sequence."""
    synthetic = payload.get("synthetic")
    fig, axes = plt.subplots(1, 2 if synthetic else 1, figsize=SIZE, squeeze=False)

    def bars(ax, results: dict, series: list[tuple[str, str]]) -> None:
        methods = list(results)
        width = 0.8 / len(series)
        for i, (key, label) in enumerate(series):
            xs = [j + (i - (len(series) - 1) / 2) * width for j in range(len(methods))]
            ax.bar(xs, [results[m].get(key, float("nan")) for m in methods], width, label=label, color=COLORS[i])
        ax.set_xticks(range(len(methods)), methods, fontsize=8)
        ax.set_ylabel("px")
        ax.set_ylim(0, 1.6 * max(results[m].get(k, 0.0) for m in methods for k, _ in series))
        ax.grid(True, axis="y", alpha=0.3)

    ax = axes[0][0]
    bars(ax, payload["results"], [("max_pixel_drift_est_px", "largest per-pixel drift vs d_0 moved (est. motion)"),
                                  ("max_tile_drift_est_px", "largest 32 px tile drift vs d_0 moved (est. motion)"),
                                  ("max_growth_vs_mean_stereo_px", "largest growth of error vs mean stereo")])
    ax.axhline(TILE_DRIFT_BOUND_PX, color=COLORS[1], ls="--", lw=1, label="bound on tile drift")
    ax.set_title(f"EuRoC V1_01, {payload.get('frames', '?')} frames", fontsize=9)
    ax.legend(fontsize=7, loc="upper right")
    if synthetic:
        ax = axes[0][1]
        bars(ax, synthetic["results"], [("median_error_first_px", "median error vs truth, frame 0"),
                                        ("median_error_last_px", "median error vs truth, last frame"),
                                        ("max_tile_drift_true_px", "largest tile drift vs d_0 moved (true motion)"),
                                        ("max_tile_shift_vs_truth_px", "largest tile shift vs truth")])
        ax.set_title(f"rendered still rig, {synthetic.get('frames', '?')} frames, seed {synthetic.get('seed', '?')}",
                     fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    finish(fig, "A still camera: drift per method (per-frame stereo: the noise floor)", payload, path)


def plot_stereo(payload: dict, path: Path) -> None:
    """bad-2 against density per matcher, one panel per image size, D by marker; duplicate outputs drawn once."""
    rows = payload["results"]
    data = rows[0]["data"]
    others = sorted({r["data"] for r in rows} - {data})
    if others:
        print(f"stereo: drawing {data} only, not {', '.join(others)}", file=sys.stderr)
    rows = [r for r in rows if r["data"] == data]
    sizes = list(dict.fromkeys(r["size"] for r in rows))
    disparities = sorted({r["disparities"] for r in rows})
    seen, dropped, kept = {}, {}, []
    for r in rows:  # a method whose outputs equal another's (the eager torch path) would hide behind it
        key = (r["size"], r["disparities"], r["epe"], r["bad2"], r["density"])
        if key in seen and seen[key] != r["method"]:
            dropped[r["method"]] = seen[key]
            continue
        seen[key] = r["method"]
        kept.append(r)
    methods = list(dict.fromkeys(r["method"] for r in kept))
    styles = method_styles(methods)
    fig, axes = plt.subplots(1, len(sizes), figsize=(SIZE[0], SIZE[1] + 0.7), squeeze=False)
    for ax, size in zip(axes[0], sizes, strict=True):
        for i, m in enumerate(methods):
            points = sorted((r["disparities"], 100 * r["density"], 100 * r["bad2"]) for r in kept
                            if r["size"] == size and r["method"] == m)
            ax.plot([p[1] for p in points], [p[2] for p in points], color=styles[m]["color"], lw=0.7, alpha=0.6)
            for d, x, y in points:
                filled = d != disparities[0]
                ax.scatter(x, y, s=42, marker=styles[m]["marker"], zorder=4 - i / len(methods), linewidths=1.4,
                           facecolors=styles[m]["color"] if filled else "white", edgecolors=styles[m]["color"])
        plain_log(ax.yaxis)
        ax.set_title(size, fontsize=9)
        ax.set_xlabel("density (% of truth pixels)")
        ax.set_ylabel("bad-2 (% of valid pixels, log)")
        ax.grid(True, which="both", alpha=0.3)
    handles = [plt.Line2D([], [], ls="", label=short(m), **styles[m]) for m in methods]
    handles += [plt.Line2D([], [], ls="", marker="o", color="0.3", markerfacecolor="white" if d == disparities[0]
                           else "0.3", label=f"D = {d}") for d in disparities]
    fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=7, frameon=False, bbox_to_anchor=(0.5, 0.03))
    note = "; ".join(f"{short(a)}: same outputs as {short(b)}, not drawn" for a, b in dropped.items())
    if note:
        fig.text(0.5, 0.005, note, ha="center", fontsize=7, color="0.3")
    finish(fig, f"Stereo matchers on {data}: error against density per image size and D (lower right is better)",
           payload, path, bottom=0.16)


def plot_autograd(payload: dict, path: Path) -> None:
    """The gradient step's time ratios against issue 19's targets, and torch.compile against eager."""
    targets = {"forward_ratio": script_constant("autograd.py", "TARGET_FORWARD"),
               "backward_ratio": script_constant("autograd.py", "TARGET_BACKWARD")}
    labels = {"forward_ratio": "forward with grad / no-grad forward",
              "backward_ratio": "backward / forward with grad"}
    compiled = payload.get("compile") or []
    fig, axes = plt.subplots(1, 2 if compiled else 1, figsize=SIZE, squeeze=False,
                             gridspec_kw={"width_ratios": [2, 1]} if compiled else None)
    ax = axes[0][0]
    grad = payload["grad"]
    for i, key in enumerate(targets):
        xs = [j + (i - 0.5) * 0.38 for j in range(len(grad))]
        ax.bar(xs, [g[key] for g in grad], 0.38, color=COLORS[i], label=labels[key])
        ax.axhline(targets[key], color=COLORS[i], ls="--", lw=1, label=f"target <= {targets[key]:g}x")
    ax.set_xticks(range(len(grad)), [f"{g['config'].replace(' ', chr(10))}\n{g['kind']}" for g in grad], fontsize=7)
    ax.set_ylim(0, 1.4 * max([*targets.values(), *(g[k] for g in grad for k in targets)]))
    ax.set_ylabel("time ratio (x)")
    ax.set_title(f"one refiner step with gradients, {grad[0]['size']}", fontsize=9)
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=7, ncol=2, loc="upper center")
    if compiled:
        ax = axes[0][1]
        series = [("eager", "eager (compiled kernels)"), ("torch_path", "eager, torch path"),
                  ("compiled", "torch.compile")]
        for i, (key, label) in enumerate(series):
            xs = [j + (i - 1) * 0.27 for j in range(len(compiled))]
            ax.bar(xs, [c[key]["median_ms"] if key in c else float("nan") for c in compiled], 0.27,
                   color=COLORS[i + 2], label=label)
        ax.set_xticks(range(len(compiled)), [f"{c['size']}\n{c['backend']} ({c['status']})" for c in compiled],
                      fontsize=7)
        ax.set_ylabel("ms per frame (no grad)")
        ax.set_title(f"torch.compile, {compiled[0]['config']}", fontsize=9)
        ax.grid(True, axis="y", alpha=0.3)
        ax.legend(fontsize=7)
    finish(fig, "Gradients and torch.compile: cost against the no-grad step", payload, path)


SOURCES = {"gt": "true disparity", "matcher": "block matcher's disparity"}


def plot_ego_motion(payload: dict, path: Path) -> None:
    """Median translation (in % of the true step) and rotation error per method, rig and disparity source."""
    results = payload["results"]
    keys = list(dict.fromkeys(k for seq in results.values() for k in seq["errors"]))
    methods = list(dict.fromkeys(k.split(" [")[0] for k in keys))
    sources = list(dict.fromkeys(k.split(" [")[1].rstrip("]") for k in keys))
    series = [(seq, src) for seq in results for src in sources]
    width = 0.8 / len(series)
    rigs = {seq: f"{seq.split('/')[0]} rig ({seq.split('/')[1]}, {r['image'][1]}x{r['image'][0]}, "
                 f"{1000 * r['median_step_m']:.0f} mm/frame)" for seq, r in results.items()}
    fig, axes = plt.subplots(1, 2, figsize=(SIZE[0], SIZE[1] + 0.4))
    for ax, key, ylabel in ((axes[0], "median_t_pct", "translation error (% of true step, median)"),
                            (axes[1], "median_r_deg", "rotation error (deg, median)")):
        for i, (seq, src) in enumerate(series):
            errors = results[seq]["errors"]
            xs = [j + (i - (len(series) - 1) / 2) * width for j in range(len(methods))]
            ys = [errors.get(f"{m} [{src}]", {}).get(key, float("nan")) for m in methods]
            ax.bar(xs, ys, width, color=COLORS[list(results).index(seq)], hatch="//" if src != sources[0] else None,
                   edgecolor="white", label=f"{rigs[seq]}, {SOURCES.get(src, src)}")
        ax.set_xticks(range(len(methods)), methods)
        plain_log(ax.yaxis)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.grid(True, axis="y", which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=7, frameon=False)
    finish(fig, "Ego-motion per frame pair against the true motion: median error per method", payload, path,
           bottom=0.1)


def plot_gpu(payload: dict, path: Path) -> None:
    """ms per frame of each matcher and loop on the GPU, per rig, and the loop's time per stage."""
    rigs = list(dict.fromkeys([r["rig"] for r in payload["matchers"]] + [r["rig"] for r in payload["loops"]]))
    rows = [(f"stereo: {r['matcher']}", r["rig"], r["ms"]) for r in payload["matchers"]]
    rows += [(f"loop: {r['fusion']}, verify {r['verify_every']}, B = {r['batch']}" + (" (per item)"
              if r["batch"] > 1 else ""), r["rig"], r["ms_per_item"]) for r in payload["loops"]]
    names = list(dict.fromkeys(name for name, _, _ in rows))
    stages = payload.get("stages") or {}
    fig, axes = plt.subplots(1, 2 if stages else 1, figsize=(SIZE[0] + 0.5, SIZE[1]), squeeze=False)
    height = 0.8 / len(rigs)
    ax = axes[0][0]
    for i, rig in enumerate(rigs):
        ms = {name: v for name, r, v in rows if r == rig}
        ys = [j + (i - (len(rigs) - 1) / 2) * height for j in range(len(names))]
        ax.barh(ys, [ms.get(n, float("nan")) for n in names], height, color=COLORS[i], label=f"{rig} rig")
    ax.set_yticks(range(len(names)), names, fontsize=7)
    ax.invert_yaxis()
    plain_log(ax.xaxis)
    ax.set_xlabel("ms per frame (median, log)")
    ax.set_title("matchers and the loop", fontsize=9)
    ax.grid(True, axis="x", which="both", alpha=0.3)
    ax.legend(fontsize=7)
    if stages:
        ax = axes[0][1]
        names = [s for s in next(iter(stages.values())) if s != "total"]
        for i, rig in enumerate(stages):
            ys = [j + (i - (len(stages) - 1) / 2) * height for j in range(len(names))]
            ax.barh(ys, [stages[rig].get(n, float("nan")) for n in names], height, color=COLORS[i],
                    label=f"{rig} (total {stages[rig].get('total', float('nan')):.1f} ms)")
        ax.set_yticks(range(len(names)), names, fontsize=7)
        ax.invert_yaxis()
        ax.set_xlabel("ms per frame")
        ax.set_title("loop stages, each synchronised\n(kalman, verify every 5, B = 1)", fontsize=9)
        ax.grid(True, axis="x", alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    finish(fig, f"On a GPU: torch paths, {payload.get('frames', '?')} rendered frames per rig (no CPU timings in "
           "this run)", payload, path)


def running_mean(values: list[float], window: int) -> list[float]:
    """The mean of each value and the ``window - 1`` before it (fewer at the start)."""
    out, total = [], 0.0
    for i, v in enumerate(values):
        total += v
        if i >= window:
            total -= values[i - window]
        out.append(total / min(i + 1, window))
    return out


def loss_curve(ax, values: list[float], parts: int, color: str, alpha: float, label: str, xlabel: str) -> None:
    """``values`` per step, faint, with their running mean over a ``parts``-th of the steps on top."""
    window = max(1, len(values) // parts)
    steps = range(1, len(values) + 1)
    ax.plot(steps, values, color=color, alpha=alpha, lw=0.7)
    ax.plot(steps, running_mean(values, window), color=color, label=f"{label} (mean of {window})")
    ax.set_xlabel(xlabel, color=color)
    ax.tick_params(axis="x", colors=color)


def plot_learning(payload: dict, path: Path) -> None:
    """The two training stages' loss per step, and EPE per held-back sequence before and after training."""
    fig, axes = plt.subplots(1, 2, figsize=SIZE)
    ax = axes[0]
    fit = payload.get("fit_losses") or []
    top = ax
    if fit:
        loss_curve(ax, fit, 20, COLORS[0], 0.25, "stage 1: correction net, L1 to truth", "stage 1 step")
        top = ax.twiny()
    loss_curve(top, payload["losses"], 10, COLORS[1], 0.35, "stage 2: loss through the loop", "stage 2 step")
    ax.set_ylabel("loss (px)")
    ax.grid(True, alpha=0.3)
    handles = [h for a in dict.fromkeys([ax, top]) for h in a.get_legend_handles_labels()[0]]
    ax.legend(handles=handles, fontsize=7, loc="lower left")
    ax = axes[1]
    runs = [("before", "defaults"), ("untrained_soft_gate", "untrained, soft gate"), ("after", "trained")]
    runs = [(k, label) for k, label in runs if k in payload]
    seqs = list(payload["before"])
    width = 0.8 / len(runs)
    for i, (key, label) in enumerate(runs):
        xs = [j + (i - (len(runs) - 1) / 2) * width for j in range(len(seqs) + 1)]
        epes = [payload[key][s]["epe"] for s in seqs]
        ax.bar(xs, epes + [sum(epes) / len(epes)], width, color=COLORS[i + 2], label=label)
    mean_before = sum(payload["before"][s]["epe"] for s in seqs) / len(seqs)
    ax.hlines((1 - LEARNING_TARGET_GAIN) * mean_before, len(seqs) - 0.45, len(seqs) + 0.45, colors="k",
              linestyles="--", lw=1, label=f"target: mean {100 * LEARNING_TARGET_GAIN:g} % below defaults")
    ax.set_xticks(range(len(seqs) + 1), [s.replace("_", "\n") for s in seqs] + ["mean"], fontsize=7)
    ax.set_ylabel("EPE (px)")
    ax.set_title("held-back sequences (hall: a scene not trained on)", fontsize=9)
    ax.set_ylim(0, 1.35 * max(payload[k][q]["epe"] for k, _ in runs for q in seqs))
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", ncol=2)
    w, h = payload.get("size", ["?", "?"])
    finish(fig, f"Learning the refiner's parts: Kalman mode, paper rig at {w}x{h}, {payload.get('steps', '?')} loop "
           "steps", payload, path)


PLOTS: dict[str, Callable[[dict, Path], None]] = {
    "real": plot_real,
    "euroc_static": plot_euroc_static,
    "stereo": plot_stereo,
    "autograd": plot_autograd,
    "ego_motion": plot_ego_motion,
    "gpu": plot_gpu,
    "learning": plot_learning,
}


def main(argv: list[str] | None = None) -> list[Path]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", metavar="NAME",
                        help=f"benchmarks to draw (default: all of {', '.join(PLOTS)})")
    parser.add_argument("--results", type=Path, default=RESULTS, help="where the JSON lies")
    parser.add_argument("--out", type=Path, default=None, help="where the PNGs go (default: beside the JSON)")
    args = parser.parse_args(argv)
    unknown = [n for n in args.names if n not in PLOTS]
    if unknown:
        parser.error(f"no figure for {', '.join(unknown)}; choose from {', '.join(PLOTS)}")
    out_dir = args.out or args.results
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name in args.names or PLOTS:
        source = args.results / f"{name}.json"
        if not source.exists():
            print(f"{name}: skipped, {source} is missing", file=sys.stderr)
            continue
        path = out_dir / f"{name}.png"
        PLOTS[name](json.loads(source.read_text()), path)
        written.append(path)
        print(f"{name}: {path} ({path.stat().st_size // 1024} kB)", file=sys.stderr)
    return written


if __name__ == "__main__":
    main()
