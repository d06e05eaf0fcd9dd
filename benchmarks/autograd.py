"""Gradients and torch.compile: the refiner's cost with autograd on, and under ``torch.compile`` (issue 19).

Data: one realistic render (``render_sequence``, "paper" preset, its default corridor scene and forward
motion, default imaging) with seed ``SEED``, a tuning seed (0-99: these numbers are timings, not accuracy
reported elsewhere), at 320x240 and 640x480; max disparity 64 px at 640 wide, scaled with the width. The
refiner configurations are the named keyword dicts of ``CONFIGS``; a keyword the installed
``EgoMotionRefiner`` does not take (TypeError) skips that row with a printed note.

1. **torch.compile** (both sizes): ms per frame over a short sequence (``--frames``, verify_every=5, no
   grad), as the mean over the frames of one pass, median over ``--compile-repeats`` passes; eager with the compiled
   numba kernels (the default), eager on the torch path (``egorefine.core.dispatch.ENABLED = False``; under
   ``torch.compile`` every stage takes the torch path, so this is the fair baseline) and
   ``torch.compile(refiner, backend=...)``, interleaved pass by pass. The first compiled pass (tracing and
   compiling, recompiles included) is reported on its own as the compile time. Compiled outputs are
   compared with both eager paths frame by frame: max |difference| of disparity on pixels valid in both,
   and whether the validity masks are equal on every frame. Each backend runs in a fresh subprocess with a
   time limit (``--compile-timeout``); ``inductor`` first, and where it fails or runs past the limit the
   ``eager`` (dynamo's capture only) and, at 320x240, ``aot_eager`` (also AOTAutograd) backends too, for the
   first configuration that fails at that size. Where a compile fails, the eager columns hold one pass each.
2. **Gradients** (320x240, float32): one refiner step on a prediction frame (``PREDICTION_FRAME``) and,
   separately, on a verification frame (``VERIFICATION_FRAME``). The state before the step comes from a
   no-grad run of the earlier frames; the previous left image in it (and its tracker pyramid) is rebuilt
   from a leaf with ``requires_grad=True``, as are the step's own left and right images. Timed, interleaved
   repeat by repeat: the no-grad step (default: compiled kernels; and on the torch path), the step with
   gradients, and the backward of the mean refined disparity over valid pixels to all three images. Targets
   (issue 19): forward with gradients at most 5x the no-grad forward (judged against the default no-grad
   step, the one a user switches gradients on from; the torch-path ratio is printed beside it), backward
   at most 3x the forward with gradients. The gradient reaching the previous frame's left image is checked
   finite and reported (its L1 norm).
3. **Profiles**: where a target fails, ``torch.profiler`` over one forward with gradients and one backward:
   the top operators by self CPU time, the top autograd nodes of the backward by total CPU time, and a
   ``cProfile`` of the forward's egorefine functions by cumulative time (the stage to look at).

    python benchmarks/autograd.py                     # full run (long: compiling the refiner takes minutes)
    python benchmarks/autograd.py --backends none     # gradients only, no torch.compile
    python benchmarks/autograd.py --table-only        # rewrite the README table from the last JSON
    python benchmarks/autograd.py --sizes 320x240 --compile-configs "kalman default"   # compile one, at one size

Writes benchmarks/results/autograd.json, autograd.md and the README's ``autograd`` table (with ``--out DIR``:
the JSON and markdown in DIR only).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import logging
import pstats
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's egorefine, not an installed one
from benchmarks._common import (  # noqa: E402
    RESULTS,
    machine_info,
    markdown_table,
    omp_setting,
    set_threads,
    summarize,
    update_readme,
)
from egorefine.core import dispatch, to_grey  # noqa: E402
from egorefine.data import render_sequence  # noqa: E402
from egorefine.features import build_pyramid  # noqa: E402
from egorefine.refine import EgoMotionRefiner  # noqa: E402

# The refiner configurations: a row is one more entry.
CONFIGS = [
    {"name": "kalman default", "kwargs": {"fusion": "kalman"}},
    {"name": "paper default", "kwargs": {"fusion": "paper"}},
    {"name": "kalman differentiable", "kwargs": {"fusion": "kalman", "differentiable": True}},
]
SIZES = [(320, 240), (640, 480)]
GRAD_SIZE = (320, 240)
SEED = 7  # a tuning seed (0-99)
VERIFY_EVERY = 5
PREDICTION_FRAME = 3  # a frame after the first prediction (its search is centred by the previous motion)
VERIFICATION_FRAME = 5
TARGET_FORWARD = 5.0  # forward with gradients / no-grad forward
TARGET_BACKWARD = 3.0  # backward / forward with gradients
FALLBACK_BACKENDS = ["eager", "aot_eager"]
# aot_eager at the small size only: tracing it takes longer than dynamo alone, and the torch path it runs takes
# seconds per frame at 640x480 on 2 cores
AOT_EAGER_MAX_PIXELS = 320 * 240
TOP = 10


def max_disparity_for(width: int) -> int:
    """64 px at 640 wide (the paper rig's range), scaled with the width; at least 16."""
    return max(16, 64 * width // 640)


def make_refiner(config: dict, width: int) -> EgoMotionRefiner | None:
    """The configuration's refiner, or None (with a printed note) where the installed version lacks a keyword."""
    try:
        return EgoMotionRefiner(max_disparity=max_disparity_for(width), verify_every=VERIFY_EVERY,
                                **config["kwargs"])
    except TypeError as err:
        print(f"note: skipping '{config['name']}': this EgoMotionRefiner does not take {config['kwargs']} ({err})",
              flush=True)
        return None


def render(width: int, height: int, frames: int, imaging: str = "realistic"):
    seq = render_sequence(frames, preset="paper", seed=SEED, height=height, width=width, imaging=imaging)
    return seq.left, seq.right, seq.K[None], torch.tensor([seq.baseline], dtype=seq.left.dtype)


class _TorchPath:
    """``with _TorchPath(): ...`` runs every stage on its torch path (the compiled kernels switched off)."""

    def __enter__(self):
        self.previous = dispatch.ENABLED
        dispatch.ENABLED = False

    def __exit__(self, *exc):
        dispatch.ENABLED = self.previous


def _ms_since(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def run_pass(refiner, lefts, rights, K, b) -> tuple[float, list]:
    """One no-grad pass over the sequence: (mean ms per frame, [(disparity, valid)] per frame)."""
    outs, state = [], None
    t0 = time.perf_counter()
    with torch.no_grad():
        for t in range(len(lefts)):
            out, state = refiner(lefts[t : t + 1], rights[t : t + 1], K, b, state)
            outs.append((out.disparity, out.valid))
    return _ms_since(t0) / len(lefts), outs


def compare(outs_a: list, outs_b: list) -> dict:
    """Max |disparity difference| on pixels valid in both, over all frames; whether every frame's mask is equal."""
    diff, equal = 0.0, True
    for (da, va), (db, vb) in zip(outs_a, outs_b, strict=True):
        both = va & vb
        if bool(both.any()):
            diff = max(diff, float((da - db).abs()[both].max()))
        equal = equal and bool(torch.equal(va, vb))
    return {"max_abs_diff_px": diff, "masks_equal": equal}


# --------------------------------------------------------------------------- part 1: torch.compile (subprocess)


class _RecompileLimitCounter(logging.Handler):
    """Counts dynamo's 'hit config.recompile_limit' warnings (the function then runs eagerly)."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.hits = 0

    def emit(self, record):
        if "recompile_limit" in record.getMessage() or "cache_size_limit" in record.getMessage():
            self.hits += 1


def compile_worker(spec: dict) -> None:
    """One (size, configuration, backend) of part 1; writes its result to ``spec["out"]`` after each phase, so a
    run stopped at the time limit still leaves its eager timings."""
    set_threads(spec["threads"])
    data = torch.load(spec["data"])
    lefts, rights, K, b = data["left"], data["right"], data["K"], data["b"]
    width = lefts.shape[-1]
    config = spec["config"]
    refiner = make_refiner(config, width)
    result = {"backend": spec["backend"], "status": "eager only"}
    out_path = Path(spec["out"])

    def save():
        out_path.write_text(json.dumps(result, default=float))

    eager_pass = lambda: run_pass(refiner, lefts, rights, K, b)  # noqa: E731

    def torch_pass():
        with _TorchPath():
            return run_pass(refiner, lefts, rights, K, b)

    eager_pass()  # warm-up (the numba kernels load from their cache)
    ms_eager, eager_out = eager_pass()
    ms_torch, torch_out = torch_pass()
    # one pass each until the interleaved timing below replaces them (they stay where compiling fails)
    result.update(eager=summarize([ms_eager]), torch_path=summarize([ms_torch]),
                  eager_vs_torch_path=compare(eager_out, torch_out))
    save()

    counter = _RecompileLimitCounter()
    logging.getLogger("torch._dynamo").addHandler(counter)
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    compiled = torch.compile(refiner, backend=spec["backend"])
    compiled_pass = lambda: run_pass(compiled, lefts, rights, K, b)  # noqa: E731
    t0 = time.perf_counter()
    try:
        _, compiled_out = compiled_pass()
    except Exception as err:  # noqa: BLE001 - any compiler failure is a result to report
        result.update(status="failed", error=f"{type(err).__name__}: {str(err).splitlines()[0][:300]}",
                      compile_s=time.perf_counter() - t0)
        save()
        return
    result["compile_s"] = time.perf_counter() - t0
    counters = torch._dynamo.utils.counters
    result["unique_graphs"] = int(counters["stats"]["unique_graphs"])
    result["graph_breaks"] = int(sum(counters["graph_break"].values()))
    result["recompile_limit_hits"] = counter.hits
    result["compiled_vs_torch_path"] = compare(compiled_out, torch_out)
    result["compiled_vs_eager"] = compare(compiled_out, eager_out)
    samples = {"eager": [], "torch_path": [], "compiled": []}
    for i in range(spec["repeats"]):  # interleaved: a burst of load hits all three alike
        samples["eager"].append(eager_pass()[0])
        samples["torch_path"].append(torch_pass()[0])
        samples["compiled"].append(compiled_pass()[0])
        result.update({k: summarize(v) for k, v in samples.items()})  # saved round by round (the time limit)
        result["status"] = "ok" if i + 1 == spec["repeats"] else f"ok, {i + 1} of {spec['repeats']} passes"
        save()


def run_compile(config: dict, size: tuple[int, int], backend: str, data_path: Path, args) -> dict:
    """Part 1 for one backend in a fresh subprocess under the time limit."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "result.json"
        spec = {"config": config, "backend": backend, "data": str(data_path), "out": str(out),
                "repeats": args.compile_repeats, "threads": args.threads}
        t0 = time.perf_counter()
        try:
            proc = subprocess.run([sys.executable, __file__, "--compile-worker", json.dumps(spec)],
                                  capture_output=True, text=True, timeout=args.compile_timeout)
            failed = proc.returncode != 0
            tail = (proc.stderr or "").strip().splitlines()[-1:] if failed else []
        except subprocess.TimeoutExpired:
            failed, tail = False, []
            timed_out = True
        else:
            timed_out = False
        wall = time.perf_counter() - t0
        result = json.loads(out.read_text()) if out.exists() else {"backend": backend, "status": "no result"}
    result["wall_s"] = wall
    if timed_out and result.get("status") != "ok":
        result["status"] = f"stopped at the {args.compile_timeout:.0f} s limit ({result.get('status')})"
    elif failed and result.get("status") != "failed":
        result.update(status="failed", error=tail[0][:300] if tail else "worker exited with an error")
    return result


# --------------------------------------------------------------------------- part 2: one step with gradients


def _leaf(x: torch.Tensor) -> torch.Tensor:
    return x.detach().clone().requires_grad_(True)


def grad_case(refiner, lefts, rights, K, b, t: int, repeats: int, profile: bool) -> dict:
    """Step ``t`` with and without gradients, and its backward; see the module docstring."""
    state = None
    with torch.no_grad():
        for i in range(t):
            out, state = refiner(lefts[i : i + 1], rights[i : i + 1], K, b, state)
    levels = len(state.pyramid) if state.pyramid is not None else 3
    left, right = lefts[t : t + 1], rights[t : t + 1]

    def leaves():
        prev = _leaf(lefts[t - 1 : t])
        grey = to_grey(prev)
        step_state = state._replace(image=grey, pyramid=tuple(build_pyramid(grey, levels)))
        return prev, _leaf(left), _leaf(right), step_state

    def nograd(torch_path: bool):
        t0 = time.perf_counter()
        if torch_path:
            with _TorchPath(), torch.no_grad():
                refiner(left, right, K, b, state)
        else:
            with torch.no_grad():
                refiner(left, right, K, b, state)
        return _ms_since(t0)

    def forward(inputs):
        prev, lt, rt, st = inputs
        out, _ = refiner(lt, rt, K, b, st)
        valid = out.valid.to(out.disparity.dtype)
        return out, (out.disparity * valid).sum() / valid.sum().clamp(min=1.0)

    def with_grad():
        inputs = leaves()
        t0 = time.perf_counter()
        out, loss = forward(inputs)
        fwd = _ms_since(t0)
        t0 = time.perf_counter()
        grads = torch.autograd.grad(loss, inputs[:3], allow_unused=True)
        return fwd, _ms_since(t0), out, grads

    # warm-up (and the gradient check)
    nograd(False), nograd(True)
    _, _, out, grads = with_grad()
    g_prev = grads[0]
    samples = {"nograd": [], "nograd_torch_path": [], "forward_grad": [], "backward": []}
    for _ in range(repeats):
        samples["nograd"].append(nograd(False))
        samples["nograd_torch_path"].append(nograd(True))
        fwd, bwd, _, _ = with_grad()
        samples["forward_grad"].append(fwd)
        samples["backward"].append(bwd)
    times = {k: summarize(v) for k, v in samples.items()}
    med = {k: v["median_ms"] for k, v in times.items()}
    fwd_ratio = med["forward_grad"] / med["nograd"]
    bwd_ratio = med["backward"] / med["forward_grad"]
    result = {
        "frame": t,
        "stereo_ran": bool(out.stereo_ran),
        "times": times,
        "forward_ratio": fwd_ratio,
        "forward_ratio_torch_path": med["forward_grad"] / med["nograd_torch_path"],
        "backward_ratio": bwd_ratio,
        "forward_pass": fwd_ratio <= TARGET_FORWARD,
        "backward_pass": bwd_ratio <= TARGET_BACKWARD,
        "grad_prev_left_l1": float(g_prev.abs().sum()) if g_prev is not None else 0.0,
        "grad_prev_left_finite": bool(g_prev is None or torch.isfinite(g_prev).all()),
        "grad_left_l1": float(grads[1].abs().sum()) if grads[1] is not None else 0.0,
        "grads_finite": all(g is None or bool(torch.isfinite(g).all()) for g in grads),
    }
    if profile and not (result["forward_pass"] and result["backward_pass"]):
        result["profile"] = profile_step(forward, leaves)
    return result


def profile_step(forward, leaves) -> dict:
    """Top costs of one forward with gradients and of its backward (see the module docstring, part 3)."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    def top_ops(prof, key, only=None):
        rows = [e for e in prof.key_averages() if only is None or only(e.key)]
        rows.sort(key=lambda e: -getattr(e, key))
        return [{"name": e.key, "ms": getattr(e, key) / 1e3, "calls": e.count} for e in rows[:TOP]]

    inputs = leaves()
    with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
        out, loss = forward(inputs)
    fwd_ops = top_ops(prof, "self_cpu_time_total")
    with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
        torch.autograd.grad(loss, inputs[:3], allow_unused=True)
    bwd_ops = top_ops(prof, "self_cpu_time_total")
    bwd_nodes = top_ops(prof, "cpu_time_total", only=lambda k: k.startswith("autograd::engine::evaluate_function"))
    for row in bwd_nodes:
        row["name"] = row["name"].replace("autograd::engine::evaluate_function: ", "")

    inputs = leaves()
    pr = cProfile.Profile()
    pr.enable()
    forward(inputs)
    pr.disable()
    stats = pstats.Stats(pr)
    stages = []
    for (file, _line, fn), (_, _, _, cum, _) in stats.stats.items():
        if "egorefine" in file and "benchmarks" not in file and fn != "forward":
            stages.append({"name": f"{Path(file).parent.name}/{Path(file).name}:{fn}", "ms": cum * 1e3})
    stages.sort(key=lambda r: -r["ms"])
    return {"forward_ops": fwd_ops, "forward_functions": stages[:TOP], "backward_ops": bwd_ops,
            "backward_nodes": bwd_nodes}


# --------------------------------------------------------------------------- main and the table


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=6,
                        help="frames of the compile part's sequence (6: the first, four predictions, a verification)")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats of the gradient steps")
    parser.add_argument("--compile-repeats", type=int, default=2, help="timed passes of the compile part")
    parser.add_argument("--configs", default=None, help="comma-separated names of CONFIGS to run (default: all)")
    parser.add_argument("--compile-configs", default=None,
                        help="comma-separated names of the configurations the compile part runs (default: --configs)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--sizes", default=",".join(f"{w}x{h}" for w, h in SIZES), help="compile part, WxH,...")
    parser.add_argument("--grad-size", default="x".join(map(str, GRAD_SIZE)))
    parser.add_argument("--backends", default="inductor",
                        help="comma-separated torch.compile backends, or 'none'; the fallbacks "
                             f"({', '.join(FALLBACK_BACKENDS)}) run where the first fails or times out")
    parser.add_argument("--compile-timeout", type=float, default=900.0, help="seconds per compile subprocess")
    parser.add_argument("--imaging", default="realistic", choices=["realistic", "ideal"],
                        help="the renderer's imaging (realistic, its default, for the reported run)")
    parser.add_argument("--no-profile", action="store_true")
    parser.add_argument("--out", type=Path, default=None, help="write JSON and markdown here, not the README")
    parser.add_argument("--table-only", action="store_true", help="rewrite the table from the last JSON")
    parser.add_argument("--compile-worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.compile_worker:
        compile_worker(json.loads(args.compile_worker))
        return {}
    if args.table_only:
        payload = json.loads((RESULTS / "autograd.json").read_text())
        update_readme("autograd", table(payload))
        return payload
    set_threads(args.threads)
    parse = lambda s: tuple(int(v) for v in s.split("x"))  # noqa: E731
    sizes = [parse(s) for s in args.sizes.split(",") if s]
    grad_w, grad_h = parse(args.grad_size)
    backends = [] if args.backends == "none" else args.backends.split(",")
    payload = {"seed": SEED, "preset": "paper", "imaging": args.imaging, "verify_every": VERIFY_EVERY,
               "frames": args.frames, "repeats": args.repeats, "compile_repeats": args.compile_repeats,
               "threads": args.threads,
               "omp": omp_setting(), "skipped": [], "compile": [], "grad": []}
    configs = CONFIGS if args.configs is None else [c for c in CONFIGS if c["name"] in args.configs.split(",")]
    payload["configs"] = configs
    refiners = {}
    for config in configs:
        if make_refiner(config, grad_w) is None:
            payload["skipped"].append(config["name"])
        else:
            refiners[config["name"]] = config

    # part 2 first: it needs no subprocess and is the target
    lefts, rights, K, b = render(grad_w, grad_h, VERIFICATION_FRAME + 1, args.imaging)
    for name, config in refiners.items():
        refiner = make_refiner(config, grad_w)
        for kind, t in (("prediction", PREDICTION_FRAME), ("verification", VERIFICATION_FRAME)):
            row = {"config": name, "size": f"{grad_w}x{grad_h}", "kind": kind,
                   **grad_case(refiner, lefts, rights, K, b, t, args.repeats, not args.no_profile)}
            payload["grad"].append(row)
            tm = row["times"]
            print(f"grad {name:16s} {kind:12s} frame {t}: no-grad {tm['nograd']['median_ms']:.1f} ms "
                  f"(torch path {tm['nograd_torch_path']['median_ms']:.1f}), fwd+grad "
                  f"{tm['forward_grad']['median_ms']:.1f} ms ({row['forward_ratio']:.1f}x), backward "
                  f"{tm['backward']['median_ms']:.1f} ms ({row['backward_ratio']:.2f}x)", flush=True)

    if backends:
        with tempfile.TemporaryDirectory() as tmp:
            for width, height in sizes:
                data_path = Path(tmp) / f"seq_{width}x{height}.pt"
                lefts, rights, K, b = render(width, height, args.frames, args.imaging)
                torch.save({"left": lefts, "right": rights, "K": K, "b": b}, data_path)
                fell_back = False
                for name, config in refiners.items():
                    if args.compile_configs is not None and name not in args.compile_configs.split(","):
                        continue
                    tried = list(backends)
                    for backend in tried:
                        r = run_compile(config, (width, height), backend, data_path, args)
                        row = {"config": name, "size": f"{width}x{height}", **r}
                        payload["compile"].append(row)
                        print(f"compile {name:16s} {width}x{height} {backend:9s}: {row['status']}; "
                              + ", ".join(f"{k} {row[k]['median_ms']:.1f} ms/frame"
                                          for k in ("eager", "torch_path", "compiled") if k in row)
                              + (f"; compile {row['compile_s']:.0f} s" if "compile_s" in row else ""), flush=True)
                        # The fallbacks run for the first configuration whose first backend fails at this size (the
                        # failure seen so far is on frame 0, which every configuration here runs alike).
                        if row["status"] != "ok" and backend == backends[0] and not fell_back:
                            fell_back = True
                            tried += [f for f in FALLBACK_BACKENDS if f not in tried
                                      and (f != "aot_eager" or width * height <= AOT_EAGER_MAX_PIXELS)]

    if args.out is None:
        path = RESULTS / "autograd.json"
        RESULTS.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"machine": machine_info(), **payload}, indent=2, default=float))
        update_readme("autograd", table(payload))
    else:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "autograd.json").write_text(json.dumps({"machine": machine_info(), **payload}, indent=2,
                                                           default=float))
        (args.out / "autograd.md").write_text(table(payload) + "\n")
    return payload


def _ms(t: dict) -> str:
    return f"{t['median_ms']:.1f} [{t['q1_ms']:.1f}-{t['q3_ms']:.1f}]"


def _match(c: dict | None) -> str:
    if c is None:
        return ""
    return f"{c['max_abs_diff_px']:.2g} px, masks {'equal' if c['masks_equal'] else 'differ'}"


def table(payload: dict) -> str:
    parts = []
    grad_rows = []
    for r in payload["grad"]:
        tm = r["times"]
        grad_rows.append([
            r["config"], f"{r['kind']} (frame {r['frame']})", _ms(tm["nograd"]), _ms(tm["nograd_torch_path"]),
            _ms(tm["forward_grad"]), _ms(tm["backward"]),
            f"{r['forward_ratio']:.1f}x ({r['forward_ratio_torch_path']:.1f}x)",
            "PASS" if r["forward_pass"] else "FAIL", f"{r['backward_ratio']:.2f}x",
            "PASS" if r["backward_pass"] else "FAIL",
            f"{r['grad_prev_left_l1']:.3g}" + ("" if r["grads_finite"] else " (not finite)"),
        ])
    if grad_rows:
        size = payload["grad"][0]["size"]
        parts.append(
            f"One refiner step with gradients at {size}, float32, {payload['threads']} threads ({payload['omp']}); "
            f"render seed {payload['seed']} (a tuning seed), {payload['imaging']} imaging, verify every "
            f"{payload['verify_every']}; median [IQR] ms of {payload['repeats']} interleaved repeats. No-grad: "
            "the default (compiled kernels) and the torch path; fwd ratio = forward with gradients / default "
            f"no-grad forward (in brackets: / torch-path no-grad), target <= {TARGET_FORWARD:g}x; bwd ratio = "
            f"backward / forward with gradients, target <= {TARGET_BACKWARD:g}x. Loss: mean refined disparity "
            "over valid pixels; grad L1: the L1 norm of its gradient w.r.t. the previous frame's left image.\n\n"
            + markdown_table(["configuration", "step", "no-grad ms", "no-grad torch path ms", "fwd+grad ms",
                              "backward ms", "fwd ratio", "target", "bwd ratio", "target", "grad L1, prev left"],
                             grad_rows))
    comp_rows = []
    for r in payload["compile"]:
        comp_rows.append([
            r["size"], r["config"], r["backend"], _ms(r["eager"]) if "eager" in r else "",
            _ms(r["torch_path"]) if "torch_path" in r else "", _ms(r["compiled"]) if "compiled" in r else "",
            f"{r['compiled']['median_ms'] / r['torch_path']['median_ms']:.2f}x" if "compiled" in r else "",
            f"{r['compile_s']:.0f}" if "compile_s" in r else "",
            f"{r['unique_graphs']} / {r['graph_breaks']} / {r['recompile_limit_hits']}" if "unique_graphs" in r else "",
            _match(r.get("compiled_vs_torch_path")), _match(r.get("compiled_vs_eager")),
            r["status"] + (f": {r['error']}" if r.get("error") else ""),
        ])
    if comp_rows:
        parts.append(
            f"`torch.compile(refiner)` against eager, no grad: ms per frame over {payload['frames']} frames "
            f"(median [IQR] of {payload['compile_repeats']} interleaved passes). Eager: the default (compiled numba "
            "kernels); torch path: eager with the kernels off (`dispatch.ENABLED = False`), which is what the "
            "compiled refiner runs. Compile s: the first compiled pass (tracing, compiling, recompiles). Graphs: "
            "dynamo's unique graphs / graph breaks / functions that hit the recompile limit (then run eagerly). "
            "Match: max |disparity difference| on pixels valid in both, over all frames, and the validity masks.\n\n"
            + markdown_table(["size", "configuration", "backend", "eager ms/frame", "eager torch path ms/frame",
                              "compiled ms/frame", "compiled / torch path", "compile s", "graphs / breaks / limit",
                              "match vs torch path", "match vs eager", "status"], comp_rows))
    parity, seen = [], set()
    for r in payload["compile"]:
        if "eager_vs_torch_path" in r and (r["size"], r["config"]) not in seen:
            seen.add((r["size"], r["config"]))
            parity.append(f"{r['size']} {r['config']}: {_match(r['eager_vs_torch_path'])}")
    if parity:
        parts.append("Eager with the compiled kernels against eager on the torch path (the two paths' own parity, "
                     "no compiling): " + "; ".join(parity) + ".")
    profiles = []
    for r in payload["grad"]:
        p = r.get("profile")
        if not p:
            continue
        fmt = lambda rows: ", ".join(f"`{x['name']}` {x['ms']:.1f}" for x in rows)  # noqa: E731
        profiles.append(f"- {r['config']}, {r['kind']} step: forward, egorefine functions by cumulative ms: "
                        f"{fmt(p['forward_functions'])}; forward ops by self ms: {fmt(p['forward_ops'])}; "
                        f"backward nodes by total ms: {fmt(p['backward_nodes'])}; backward ops by self ms: "
                        f"{fmt(p['backward_ops'])}.")
    if profiles:
        parts.append(f"Where a target fails, the top {TOP} costs of one profiled step (torch.profiler, cProfile; "
                     "ms, profiler overhead included):\n\n" + "\n".join(profiles))
    if payload["skipped"]:
        parts.append("Skipped (the installed EgoMotionRefiner lacks a keyword): " + ", ".join(payload["skipped"]) + ".")
    return "\n\n".join(parts)


if __name__ == "__main__":
    main()
