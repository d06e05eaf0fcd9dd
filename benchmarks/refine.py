"""Benchmark of the predict-and-correct loop against per-frame stereo, on many rendered sequences with exact truth.

Sequences: per rig (the paper's and the KITTI-like preset, each at its full resolution) three scenes
(corridor, hall, street) with two motions each, one of the two FAST: three times the preset's speed,
rendered as three times the frames of which every third is kept (truth and poses alike; the motions are
recomputed from the kept poses). Twelve sequences of 60 frames, each with its own seed. The imaging is
the renderer's default (realistic once it has one); the JSON records which.

Seeds: seeds 0-99 (``TUNING_SEEDS``) are for tuning and never reported: ``--tune`` runs the same
sequences on them and writes ``results/cache/refine_tune.json`` only. The reported run draws
sequence ``i``'s seed as ``REPORT_SEED_BASE + i`` (1000 + i), and refuses to write the README from
any other seed.

Methods, per sequence, in the same run: per-frame own stereo (the default matcher, sub-pixel), per-frame
OpenCV StereoBM (block 9) and StereoSGBM as OpenCV users run them (benchmarks/_opencv.py: SGBM 3-way, blockSize 5,
P1 = 8*cn*bs^2, P2 = 32*cn*bs^2; both with uniquenessRatio 10, speckleWindowSize 100, speckleRange 2,
disp12MaxDiff 1; runs before 2026-12-02 had StereoBM without that post-processing), and the
refiner at verify_every=5: Kalman mode with default options (the target row: on verification frames the box
matcher, its holes filled from census + SGM, ``StereoOptions.fill``), paper mode (the method as published:
pixel-accurate stereo, the linear motion solve of eq. 3, gate 0.5 px, gain 0.4), Kalman mode with the box
matcher alone (the default of earlier releases), Kalman mode with census + SGM alone (``StereoOptions.dense()``,
unverified predictions kept; chosen on the tuning seeds), Kalman mode with the opt-in +-2 px residual search
and hole measurement, Kalman mode with stereo on every frame (what the prediction frames between verifications
cost), and Kalman mode with ``motion_method="direct"`` (the exact solve refined photometrically).

For each it reports EPE, median error, bad-0.5, bad-1 (on pixels a method marks valid that have truth
and are not occluded), density (share of those pixels a method marks valid), the temporal consistency
of the error, the distinct disparity levels along a row, and ms per frame (every method warmed up
first, so that no numba compile lands in a timing); per rig, the mean and the min-max across
sequences; and per sequence, PASS/FAIL on issue 17's targets for Kalman mode @5 with defaults:
(a) lower EPE and lower bad-0.5 than per-frame SGBM at no lower density; (b) density at least our own
per-frame stereo's; (c) fewer ms per frame than per-frame SGBM. Writes benchmarks/results/refine.json,
the README table and a row figure per sequence.

    python benchmarks/refine.py                  # full run (many minutes on 2 cores)
    python benchmarks/refine.py --quick          # two tiny sequences, a few frames: a smoke run
    python benchmarks/refine.py --only kitti_street_turn_x3   # one (or a comma-separated few), full size
    python benchmarks/refine.py --report-from benchmarks/results/refine.json  # the README from a saved run
    python benchmarks/refine.py --render-only    # render the sequences into the cache (later runs reuse them)
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import inspect
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's egorefine, not an installed one
from _common import RESULTS, markdown_table, set_threads, update_readme, write_json  # noqa: E402
from _opencv import compute, stereo_bm, stereo_sgbm  # noqa: E402
from _timing import run_loop  # noqa: E402

from egorefine.data import StereoSequence, render_sequence  # noqa: E402
from egorefine.metrics import distinct_levels, evaluate_disparity, temporal_consistency  # noqa: E402
from egorefine.refine import CorrectionOptions, EgoMotionRefiner, SearchOptions, StereoOptions  # noqa: E402
from egorefine.stereo import block_matching  # noqa: E402

# Seeds 0-99 are for tuning (tests, experiments, --tune); the reported run uses REPORT_SEED_BASE + i.
TUNING_SEEDS = range(0, 100)
REPORT_SEED_BASE = 1000
FAST = 3  # a fast sequence moves at three times the preset's speed
VERIFY_EVERY = 5
MAX_DISPARITY = {"paper": 64, "kitti": 128}


@dataclasses.dataclass(frozen=True)
class Spec:
    """One benchmark sequence: rig preset, scene, motion, and how many rendered frames make one step."""

    preset: str
    scene: str
    motion: str
    step: int = 1

    @property
    def name(self) -> str:
        return f"{self.preset}_{self.scene}_{self.motion}" + (f"_x{self.step}" if self.step > 1 else "")


# Three scenes x two motions per rig, one of each scene's two motions fast. The index in this list
# fixes a sequence's seed, so append, never reorder.
SEQUENCES = [
    Spec("paper", "corridor", "forward"),
    Spec("paper", "corridor", "turn", FAST),
    Spec("paper", "hall", "turn"),
    Spec("paper", "hall", "forward", FAST),
    Spec("paper", "street", "lateral"),
    Spec("paper", "street", "shaky", FAST),
    Spec("kitti", "street", "forward"),
    Spec("kitti", "street", "turn", FAST),
    Spec("kitti", "hall", "shaky"),
    Spec("kitti", "hall", "forward", FAST),
    Spec("kitti", "corridor", "still"),
    Spec("kitti", "corridor", "shaky", FAST),
]
QUICK = ("paper_corridor_forward", "kitti_street_turn_x3")  # one per rig, one of them fast
QUICK_SIZE = {"paper": (72, 96), "kitti": (64, 208)}
QUICK_FRAMES = 8

OWN = "own stereo, sub-pixel"
OWN_SGM = "own SGM option (census, 4 paths)"
BM = "OpenCV StereoBM"
SGBM = "OpenCV SGBM 3-way"
KALMAN = f"kalman mode, verify every {VERIFY_EVERY}"
PAPER = f"paper mode, verify every {VERIFY_EVERY}"
HOLES = f"kalman + local search 2 + holes, verify every {VERIFY_EVERY}"
EVERY_FRAME = "kalman mode, verify every 1"  # stereo on every frame: what the prediction frames cost (issue 31)
DIRECT = f"kalman, direct motion, verify every {VERIFY_EVERY}"  # motion_method="direct" (issue 31)
BOX = f"kalman, box matcher alone, verify every {VERIFY_EVERY}"
DENSE = f"kalman, census + SGM alone, verify every {VERIFY_EVERY}"


def seed_of(index: int, tune: bool) -> int:
    return TUNING_SEEDS[index] if tune else REPORT_SEED_BASE + index


def imaging_default() -> str:
    """The imaging the renderer uses by default, for the record."""
    param = inspect.signature(render_sequence).parameters.get("imaging")
    return "ideal (the renderer has no imaging option)" if param is None else str(param.default)


def every_nth(seq: StereoSequence, n: int) -> StereoSequence:
    """Every ``n``-th frame of ``seq``: every per-frame field (images, truth, poses, ...) sliced alike, the
    motions recomputed from the kept poses."""
    if n == 1:
        return seq
    keep, T = slice(None, None, n), len(seq)
    fields = {f.name: getattr(seq, f.name) for f in dataclasses.fields(seq) if f.name != "K"}
    kept = {k: v[keep].clone() for k, v in fields.items() if isinstance(v, torch.Tensor) and v.shape[:1] == (T,)}
    p64 = kept["poses"].double()
    motions = torch.eye(4, dtype=torch.float64, device=p64.device).repeat(len(p64), 1, 1)
    if len(p64) > 1:
        motions[1:] = torch.linalg.inv(p64[1:]) @ p64[:-1]  # camera_t_T_camera_{t-1}, as render_sequence
    kept["motions"] = motions.to(seq.motions.dtype)
    return dataclasses.replace(seq, **kept)


def render(spec: Spec, frames: int, size: tuple[int, int] | None, seed: int, imaging: str | None,
           cache: bool = False) -> StereoSequence:
    """The sequence of ``spec``; with ``cache``, read from (or written to) the git-ignored cache folder, keyed by
    every argument and the renderer's source (rendering takes about as long as running every method)."""
    extra = {} if size is None else {"height": size[0], "width": size[1]}
    if imaging is not None:
        extra["imaging"] = imaging
    path = None
    if cache:
        key = hashlib.sha1(repr((spec, frames, size, seed, imaging, _renderer_digest())).encode()).hexdigest()[:16]
        path = RESULTS / "cache" / f"refine_{spec.name}_{key}.pt"
        if path.exists():
            return torch.load(path, weights_only=False)
    seq = render_sequence(num_frames=(frames - 1) * spec.step + 1, preset=spec.preset, scene=spec.scene,
                          motion=spec.motion, seed=seed, **extra)
    seq = every_nth(seq, spec.step)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(seq, path)
    return seq


def _renderer_digest() -> str:
    """A digest of the renderer's source files: a cached render is stale once any of them changes."""
    files = sorted((Path(__file__).resolve().parents[1] / "egorefine" / "data").glob("*.py"))
    return hashlib.sha1(b"".join(f.read_bytes() for f in files)).hexdigest()


def _u8(img: torch.Tensor) -> np.ndarray:
    return (img[0, 0].clamp(0, 1) * 255).round().byte().numpy()


def opencv_matchers(max_disparity: int) -> dict[str, Callable]:
    """StereoBM and StereoSGBM as their users run them (benchmarks/_opencv.py), on grey images."""

    def run(matcher):
        def f(left: torch.Tensor, right: torch.Tensor):
            d, valid = compute(matcher, _u8(left), _u8(right))
            return torch.from_numpy(d)[None, None].clamp_min(0), torch.from_numpy(valid)[None, None]

        return f

    return {BM: run(stereo_bm(max_disparity)), SGBM: run(stereo_sgbm(max_disparity))}


# numba compiles a kernel on its first call (or loads it from its cache, which any edit of its module
# invalidates): every method first runs untimed on the sequence's first frames, so that no compile lands in a timing
_WARM_UP_FRAMES = 6


def run_per_frame(fn, seq: StereoSequence) -> tuple[torch.Tensor, torch.Tensor, list[float], int]:
    fn(seq.left[:1], seq.right[:1])  # warm-up
    disp, valid, ms = [], [], []
    for t in range(len(seq)):
        t0 = time.perf_counter()
        d, v = fn(seq.left[t : t + 1], seq.right[t : t + 1])
        ms.append((time.perf_counter() - t0) * 1e3)
        disp.append(d)
        valid.append(v)
    return torch.cat(disp), torch.cat(valid), ms, len(seq)


def run_refiner(refiner: EgoMotionRefiner, seq: StereoSequence) -> tuple[torch.Tensor, torch.Tensor, list[float], int]:
    K, b = seq.K[None], torch.tensor([seq.baseline])
    state = None
    for t in range(min(_WARM_UP_FRAMES, len(seq))):  # warm-up, with and without stereo, untimed
        _, state = refiner(seq.left[t : t + 1], seq.right[t : t + 1], K, b, state)
    run = run_loop(refiner, seq)  # the timer benchmarks/speed.py uses too
    return run.disparity, run.valid, run.ms, sum(run.stereo)


def methods_for(max_disp: int, holes: bool) -> dict[str, Callable[[StereoSequence], tuple]]:
    def refiner(every: int = VERIFY_EVERY, **options):
        return lambda seq: run_refiner(EgoMotionRefiner(max_disparity=max_disp, verify_every=every, **options), seq)

    methods = {OWN: lambda seq: run_per_frame(lambda a, b: block_matching(a, b, max_disp), seq),
               OWN_SGM: lambda seq: run_per_frame(lambda a, b: block_matching(a, b, max_disp, cost="census",
                                                                              aggregation="sgm"), seq)}
    for name, fn in opencv_matchers(max_disp).items():
        methods[name] = lambda seq, fn=fn: run_per_frame(fn, seq)
    methods[KALMAN] = refiner(fusion="kalman")  # every other option at its default: the target row
    methods[EVERY_FRAME] = refiner(1, fusion="kalman")
    methods[DIRECT] = refiner(fusion="kalman", motion_method="direct")
    methods[PAPER] = refiner(fusion="paper", motion_method="linear", stereo=StereoOptions(subpixel=False))
    methods[BOX] = refiner(fusion="kalman", stereo=StereoOptions(fill=False))
    methods[DENSE] = refiner(fusion="kalman", stereo=StereoOptions.dense(),
                             correction=CorrectionOptions(max_unverified_variance=None))
    if holes:
        methods[HOLES] = refiner(fusion="kalman", search=SearchOptions(local_search=2, measure_holes=True))
    return methods


def check_targets(m: dict[str, dict], row: str = KALMAN) -> dict[str, bool]:
    """Issue 17's targets for one refiner row (default: Kalman mode @5 with defaults) on one sequence."""
    k, s, own = m[row], m[SGBM], m[OWN]
    return {
        "a": k["epe"] < s["epe"] and k["bad-0.5"] < s["bad-0.5"] and k["density"] >= s["density"],
        "b": k["density"] >= own["density"],
        "c": k["ms_mean"] < s["ms_mean"],
    }


def check_matchers(m: dict[str, dict]) -> dict[str, bool]:
    """Issue 17's matcher targets (item 3) on one sequence, per frame: the default matcher below StereoBM's bad-2 at
    no lower density; the SGM option below SGBM's bad-2 at a density at most 3 points below SGBM's."""
    own, bm, sgm, sgbm = m[OWN], m[BM], m[OWN_SGM], m[SGBM]
    return {"default": own["bad-2"] < bm["bad-2"] and own["density"] >= bm["density"],
            "sgm": sgm["bad-2"] < sgbm["bad-2"] and sgm["density"] >= sgbm["density"] - 0.03}


def benchmark_sequence(spec: Spec, frames: int, size, seed: int, imaging: str | None, holes: bool,
                       figure_dir: Path | None, cache: bool = False) -> dict:
    t0 = time.perf_counter()
    seq = render(spec, frames, size, seed, imaging, cache)
    render_s = time.perf_counter() - t0
    T, _, H, W = seq.left.shape
    max_disp = min(MAX_DISPARITY[spec.preset], (W // 16) * 16 - 16)
    gt = seq.disparity
    mask = (gt > 0) & ~seq.occluded
    print(f"[{spec.name}, seed {seed}] {T} frames {W}x{H}, rendered in {render_s:.1f} s", file=sys.stderr)

    methods: dict[str, dict] = {}
    maps: dict[str, torch.Tensor] = {}
    run_s = time.perf_counter()
    for name, run in methods_for(max_disp, holes).items():
        d, v, ms, stereo_frames = run(seq)
        m = evaluate_disparity(d, gt, v, mask)
        m["temporal"] = float(temporal_consistency(torch.where(v, d, gt), gt, mask & v))
        m["ms_mean"] = statistics.fmean(ms)
        m["ms_median"] = statistics.median(ms)
        m["stereo_frames"] = stereo_frames
        methods[name] = m
        maps[name] = torch.where(v, d, torch.full_like(d, float("nan")))
        print(f"  {name:48s} EPE {m['epe']:.3f}  bad-0.5 {m['bad-0.5']:.3f}  density {m['density']:.3f}  "
              f"{m['ms_mean']:.1f} ms/frame", file=sys.stderr)
    run_s = time.perf_counter() - run_s

    # Depth layers along one row of a frame that is not a verification frame.
    frame = T - 2 if (T - 2) % VERIFY_EVERY else T - 3
    row = int(H * 0.6)
    row_mask = mask[frame, 0, row]
    for name, m in methods.items():
        vals = maps[name][frame, 0, row][row_mask]
        m["levels_row"] = distinct_levels(vals[torch.isfinite(vals)])
    gt_levels = distinct_levels(gt[frame, 0, row][row_mask])

    if figure_dir is not None:
        try:
            from egorefine.viz import save_row_figure

            curves = {"ground truth": gt[frame, 0]}
            curves.update({name: maps[name][frame, 0] for name in (OWN, SGBM, PAPER, KALMAN)})
            save_row_figure(figure_dir / f"refine_row_{spec.name}.png", row, curves,
                            max_disparity=float(gt[frame].max()), title=f"{spec.name}, frame {frame}, row {row}")
        except ImportError:
            pass
    targets = check_targets(methods)
    print("  targets: " + "  ".join(f"({k}) {'PASS' if v else 'FAIL'}" for k, v in targets.items())
          + f"; methods ran in {run_s:.1f} s", file=sys.stderr)
    return {"name": spec.name, "preset": spec.preset, "scene": spec.scene, "motion": spec.motion,
            "speed": spec.step, "seed": seed, "frames": T, "size": [W, H], "max_disparity": max_disp,
            "render_s": render_s, "methods_s": run_s, "gt_levels_row": gt_levels, "targets": targets,
            "methods": methods}


def _spread(vals: list[float]) -> dict[str, float]:
    return {"mean": statistics.fmean(vals), "min": min(vals), "max": max(vals),
            "std": statistics.pstdev(vals) if len(vals) > 1 else 0.0}


def _fmt(s: dict[str, float], digits: int = 3) -> str:
    def f(v: float) -> str:
        return f"{v:.{digits}f}"

    return f"{f(s['mean'])} ({f(s['min'])}-{f(s['max'])})"


def _ok(flag: bool) -> str:
    return "PASS" if flag else "FAIL"


def report(results: list[dict]) -> tuple[str, str, dict]:
    """(summary and targets for the README, the per-sequence table, the summary as data)."""
    keys = ("epe", "median", "bad-0.5", "bad-1", "density", "temporal", "ms_mean")
    summary: dict[str, dict] = {}
    rows = []
    for preset in dict.fromkeys(r["preset"] for r in results):
        seqs = [r for r in results if r["preset"] == preset]
        for name in seqs[0]["methods"]:
            stats = {k: _spread([s["methods"][name][k] for s in seqs]) for k in keys}
            summary[f"{preset}/{name}"] = stats
            rows.append([preset, len(seqs), name, _fmt(stats["epe"]), _fmt(stats["bad-0.5"]),
                         _fmt(stats["density"]), _fmt(stats["ms_mean"], 1)])
    table = markdown_table(["rig", "sequences", "method", "EPE", "bad-0.5", "density", "ms/frame"], rows)

    def target_table(row: str) -> tuple[str, dict[str, int]]:
        t_rows, counts = [], {"a": 0, "b": 0, "c": 0}
        for r in results:
            k, s, own = r["methods"][row], r["methods"][SGBM], r["methods"][OWN]
            t = check_targets(r["methods"], row)
            counts = {key: counts[key] + int(t[key]) for key in counts}
            t_rows.append([r["name"], r["seed"], f"{k['epe']:.3f} / {s['epe']:.3f}",
                           f"{k['bad-0.5']:.3f} / {s['bad-0.5']:.3f}",
                           f"{k['density']:.3f} / {s['density']:.3f} / {own['density']:.3f}",
                           f"{k['ms_mean']:.1f} / {s['ms_mean']:.1f}", _ok(t["a"]), _ok(t["b"]), _ok(t["c"])])
        return markdown_table(["sequence", "seed", "EPE K / SGBM", "bad-0.5 K / SGBM", "density K / SGBM / own",
                               "ms/frame K / SGBM", "(a)", "(b)", "(c)"], t_rows), counts

    n = len(results)
    targets, counts = target_table(KALMAN)
    m_rows, m_counts = [], {"default": 0, "sgm": 0}
    for r in results:
        ms = r["methods"]
        if OWN_SGM not in ms:  # (a run saved before the row existed)
            continue
        t = check_matchers(ms)
        m_counts = {key: m_counts[key] + int(t[key]) for key in m_counts}
        m_rows.append([r["name"], r["seed"], f"{ms[OWN]['bad-2']:.4f} / {ms[BM]['bad-2']:.4f}",
                       f"{ms[OWN]['density']:.3f} / {ms[BM]['density']:.3f}", _ok(t["default"]),
                       f"{ms[OWN_SGM]['bad-2']:.4f} / {ms[SGBM]['bad-2']:.4f}",
                       f"{ms[OWN_SGM]['density']:.3f} / {ms[SGBM]['density']:.3f}", _ok(t["sgm"])])
    matchers = ""
    if m_rows:
        matchers = (f"Per-frame matchers (issue 17, item 3, on these renders): the default matcher below StereoBM's "
                    f"bad-2 at no lower density: {m_counts['default']}/{len(m_rows)}; the SGM option below SGBM's "
                    f"bad-2 at a density at most 3 points below SGBM's: {m_counts['sgm']}/{len(m_rows)}.\n\n"
                    + markdown_table(["sequence", "seed", "bad-2 default / BM", "density default / BM", "",
                                      "bad-2 SGM / SGBM", "density SGM / SGBM", ""], m_rows) + "\n\n")
    seq_rows = []
    for r in results:
        for name, m in r["methods"].items():
            seq_rows.append([r["name"], r["seed"], name, m["epe"], m["median"], m["bad-0.5"], m["bad-1"],
                             m["density"], m["temporal"], m["levels_row"], f"{m['stereo_frames']}/{r['frames']}",
                             m["ms_mean"]])
    per_seq = markdown_table(["sequence", "seed", "method", "EPE", "median", "bad-0.5", "bad-1", "density",
                              "temporal", "levels/row", "stereo frames", "ms/frame"], seq_rows)

    first = results[0]
    sizes = ", ".join(sorted({f"{r['size'][0]}x{r['size'][1]}" for r in results}))
    text = (
        f"Mean (min-max) across sequences, per rig. {n} sequences of {first['frames']} frames "
        f"({sizes}), imaging: "
        f"{first['imaging']}; seeds {min(r['seed'] for r in results)}-{max(r['seed'] for r in results)} "
        f"(seeds {TUNING_SEEDS.start}-{TUNING_SEEDS.stop - 1} are for tuning, never reported); `_x{FAST}`: "
        f"{FAST} times the preset's speed. Errors in px on valid pixels with truth, not occluded.\n\n"
        f"{table}\n\n"
        f"Targets for Kalman mode at verify every {VERIFY_EVERY} with default options (K), per sequence: "
        f"(a) lower EPE and lower bad-0.5 than per-frame OpenCV SGBM at no lower density; (b) density at least "
        f"our own per-frame stereo's; (c) fewer ms per frame than SGBM. "
        f"Passed: (a) {counts['a']}/{n}, (b) {counts['b']}/{n}, (c) {counts['c']}/{n}.\n\n"
        f"{targets}\n\n{matchers}"
        f"<details><summary>Every sequence and method</summary>\n\n{per_seq}\n\n</details>"
    )
    return text, per_seq, {"methods": summary, "target_passes": counts, "sequences": n}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=60, help="frames per sequence, after keeping every third "
                        "of a fast one")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--quick", action="store_true",
                        help=f"{len(QUICK)} sequences, {QUICK_FRAMES} frames of tiny images; no README update")
    parser.add_argument("--only", default=None, help="comma-separated sequence names (e.g. paper_hall_turn); "
                        "writes results/cache/refine_partial.json, no README")
    parser.add_argument("--tune", action="store_true",
                        help="run on the tuning seeds; writes results/cache/refine_tune.json only")
    parser.add_argument("--imaging", default=None, help="passed to render_sequence (default: its own default)")
    parser.add_argument("--no-holes", action="store_true", help="skip the opt-in local search + holes row")
    parser.add_argument("--render-only", action="store_true",
                        help="render the chosen sequences into results/cache (reused by later runs) and stop")
    parser.add_argument("--report-from", default=None, metavar="JSON",
                        help="re-render the tables (and the README, for a reported run) from a saved run's JSON")
    args = parser.parse_args()
    if args.report_from:
        saved = json.loads(Path(args.report_from).read_text())
        text, _, _ = report(saved["sequences"])
        print(text.split("<details>")[0].rstrip())
        if not any(r["seed"] in TUNING_SEEDS for r in saved["sequences"]):
            update_readme("refine", text)
        return
    set_threads(args.threads)
    torch.manual_seed(0)
    names = [s.name for s in SEQUENCES]
    wanted = list(QUICK) if args.quick else names
    if args.only:
        wanted = [w.strip() for w in args.only.split(",") if w.strip()]
        unknown = [w for w in wanted if w not in names]
        if unknown:
            parser.error(f"--only: unknown sequence(s) {', '.join(unknown)}; choose from {', '.join(names)}")
    frames = QUICK_FRAMES if args.quick else args.frames
    imaging = args.imaging if args.imaging is not None else imaging_default()
    partial = args.quick or args.only or args.tune
    t0 = time.perf_counter()
    results = []
    for index, spec in enumerate(SEQUENCES):
        if spec.name not in wanted:
            continue
        seed = seed_of(index, args.tune)
        size = QUICK_SIZE[spec.preset] if args.quick else None
        if args.render_only:
            t1 = time.perf_counter()
            render(spec, frames, size, seed, args.imaging, cache=True)
            print(f"[{spec.name}, seed {seed}] rendered or found in {time.perf_counter() - t1:.1f} s", file=sys.stderr)
            continue
        r = benchmark_sequence(spec, frames, size, seed, args.imaging, not args.no_holes,
                               None if partial else RESULTS, cache=not args.quick)
        r["imaging"] = imaging
        results.append(r)
    total_s = time.perf_counter() - t0
    if args.render_only:
        return
    if not args.tune and any(r["seed"] in TUNING_SEEDS for r in results):
        raise RuntimeError("a reported sequence drew a tuning seed")  # SEQUENCES grew past the seed layout

    text, per_seq, summary = report(results)
    print(text.split("<details>")[0].rstrip())
    print("\n" + per_seq)
    print(f"\n{len(results)} sequences in {total_s:.0f} s", file=sys.stderr)
    # Partial and tuning runs go to the (git-ignored) cache folder, never beside the reported result.
    name = "refine_quick" if args.quick else "cache/refine_tune" if args.tune else "cache/refine_partial" \
        if args.only else "refine"
    (RESULTS / "cache").mkdir(parents=True, exist_ok=True)
    write_json(name, {"imaging": imaging, "verify_every": VERIFY_EVERY, "tuning_seeds": [TUNING_SEEDS.start,
                      TUNING_SEEDS.stop - 1], "total_s": total_s, "sequences": results, "summary": summary})
    if not partial:
        update_readme("refine", text)


if __name__ == "__main__":
    main()
