"""Plant known defects in egorefine one at a time and list the tests that catch each (DESIGN.md: a test of a step
must fail when the step is removed; STYLE.md, "Tests that fail when the method breaks").

Each defect is applied in memory by ``tools/mutant_plugin.py`` (a pytest plugin; no library file is edited) and the
tests below run in a pytest subprocess with it. The table gives, per defect, the tests that failed and whether a
test on realistic imaging (the renderer's default camera model) or on real data is among them; a first row runs
the same tests with no defect, where nothing may fail.

    python tools/mutants.py                              # every defect and the baseline
    python tools/mutants.py --only offset-0.10           # one defect (and the baseline)
    python tools/mutants.py --only no-fill --no-baseline --tests tests/refine/test_options.py

Exit status: 0 when the baseline passes and every defect is caught by a realistic-imaging or real-data test, 1
otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TOOLS = Path(__file__).resolve().parent
ROOT = TOOLS.parent
sys.path.insert(0, str(TOOLS))
from mutant_plugin import DEFECTS, ENV  # noqa: E402

REALISTIC, REAL, IDEAL = "realistic", "real", "ideal"

# The tests each defect runs against, and what each test's images are: "realistic" (the renderer's default imaging:
# noise, camera differences, weak texture), "real" (real pairs and video: EuRoC, KITTI, Middlebury) or "ideal"
# (ideal renders and synthetic textured planes, which check a mechanism on clean data). A node id names a test, a
# parametrised case, or every test of a file.
TESTS = {
    "tests/refine/test_refiner.py::test_loop_on_realistic_imaging": REALISTIC,
    "tests/refine/test_refiner_realistic.py": REALISTIC,
    "tests/refine/test_options.py::test_kalman_mode_fills_the_box_matchers_holes_from_sgm": REALISTIC,
    "tests/refine/test_options.py::test_the_filled_loop_is_denser_than_its_box_matcher_and_stays_accurate": REALISTIC,
    "tests/refine/test_still_camera.py": REALISTIC,
    "tests/stereo/test_renderer_accuracy.py::test_subpixel_accuracy_on_a_small_rendered_frame": REALISTIC,
    "tests/refine/test_refiner_euroc.py": REAL,
    "tests/stereo/test_real_kitti.py::test_bad3_and_density_on_lidar_truth": REAL,
    "tests/stereo/test_middlebury.py": REAL,
    "tests/refine/test_refiner.py::test_refined_disparity_against_truth": IDEAL,
    "tests/refine/test_refiner.py::test_motion_follows_the_rig": IDEAL,
    "tests/stereo/test_matching.py::test_subpixel_accuracy_on_textured_plane": IDEAL,
    "tests/test_cli_viz.py::test_folder_command_writes_one_accurate_map_per_frame": IDEAL,
}
# tests whose images differ by parameter: the cases named here override their node's kind
CASE_KINDS = {
    "tests/stereo/test_renderer_accuracy.py::test_subpixel_accuracy_on_a_small_rendered_frame[ideal": IDEAL,
}


def kind_of(nodeid: str, tests: dict[str, str]) -> str:
    """The images of test ``nodeid``: the kind of the longest key of ``CASE_KINDS`` or ``tests`` it starts with."""
    for table in (CASE_KINDS, tests):
        keys = [k for k in table if nodeid.startswith(k)]
        if keys:
            return table[max(keys, key=len)]
    return "?"


def run(defect: str, tests: list[str], verbose: bool) -> tuple[dict[str, str], float, int]:
    """Run ``tests`` with ``defect`` planted ("" = none): ({nodeid: outcome}, seconds, pytest's exit status)."""
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "outcomes.json"
        env = {**os.environ, ENV: defect, ENV + "_REPORT": str(report),
               "PYTHONPATH": os.pathsep.join(p for p in (str(TOOLS), os.environ.get("PYTHONPATH", "")) if p)}
        cmd = [sys.executable, "-m", "pytest", "-p", "mutant_plugin", "-p", "no:cacheprovider", "-q", "-m", "",
               "--no-header", "-rN", *tests]
        start = time.perf_counter()
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=not verbose, text=True)
        seconds = time.perf_counter() - start
        if not report.exists():
            tail = "" if verbose else (proc.stdout + proc.stderr)[-3000:]
            raise SystemExit(f"pytest did not run with defect {defect or 'none'!r} (exit {proc.returncode}):\n{tail}")
        return json.loads(report.read_text()), seconds, proc.returncode


def _short(nodeid: str) -> str:
    return nodeid.removeprefix("tests/")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", action="append", choices=sorted(DEFECTS), help="run this defect (repeatable)")
    parser.add_argument("--tests", nargs="+", help="node ids to run instead of the default list")
    parser.add_argument("--no-baseline", action="store_true", help="skip the run without a defect")
    parser.add_argument("--verbose", action="store_true", help="show pytest's output")
    args = parser.parse_args(argv)

    tests = dict.fromkeys(args.tests, "?") if args.tests else dict(TESTS)
    defects = args.only or list(DEFECTS)
    runs, ok = {}, True
    for defect in ([] if args.no_baseline else [""]) + defects:
        outcomes, seconds, _ = run(defect, list(tests), args.verbose)
        failed = [n for n, o in outcomes.items() if o == "failed"]
        counts = {o: sum(v == o for v in outcomes.values()) for o in ("passed", "failed", "skipped", "xfailed")}
        caught = bool({REALISTIC, REAL} & {kind_of(n, TESTS) for n in failed}) if defect else not failed
        ok &= caught
        runs[defect] = (outcomes, caught, seconds)
        print(f"{defect or 'baseline'}: " + ", ".join(f"{v} {k}" for k, v in counts.items() if v)
              + f" in {seconds:.0f} s", flush=True)

    print("\n| defect | realistic-imaging or real-data tests that failed | ideal-render tests that failed | caught on "
          "realistic/real | time |")
    print("|---|---|---|---|---|")
    for defect, (outcomes, caught, seconds) in runs.items():
        failed = sorted(n for n, o in outcomes.items() if o == "failed")
        users = [f"{_short(n)} ({kind_of(n, TESTS)})" for n in failed if kind_of(n, TESTS) in (REALISTIC, REAL)]
        ideal = [_short(n) for n in failed if kind_of(n, TESTS) not in (REALISTIC, REAL)]
        verdict = ("yes" if caught else "NO") if defect else ("ok: nothing failed" if caught else "FAILURES")
        print(f"| {defect or 'none (baseline)'} | {'<br>'.join(users) or '-'} | {'<br>'.join(ideal) or '-'} | "
              f"{verdict} | {seconds:.0f} s |")

    names = sorted({n for outcomes, _, _ in runs.values() for n in outcomes})
    print("\nPer test (x: failed, i.e. caught the defect; xf: an expected failure, as it should be; s: skipped):\n")
    print("| test | images | " + " | ".join(d or "baseline" for d in runs) + " |")
    print("|---|---|" + "---|" * len(runs))
    marks = {"failed": "x", "xfailed": "xf", "skipped": "s", "passed": ""}
    for n in names:
        cells = [marks.get(outcomes.get(n, ""), "?") if n in outcomes else "-" for outcomes, _, _ in runs.values()]
        print(f"| {_short(n)} | {kind_of(n, TESTS)} | " + " | ".join(cells) + " |")
    print("\nDefects:")
    for name, plant in DEFECTS.items():
        print(f"- {name}: {(plant.__doc__ or '').strip()}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
