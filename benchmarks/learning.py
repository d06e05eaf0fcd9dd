"""Train the refiner's learnable parts through the loop, and score them on sequences it never saw.

The refiner is Kalman mode at verify every 5 with default options plus ``learnable=True`` (process noise and
measurement-noise scale as parameters; the gain and gate of paper mode are there too but do not act in Kalman
mode), a :class:`~egorefine.refine.ConfidenceNet` and a soft Kalman gate (``gate_softness``: with the hard gate a
pixel reset to the measurement has no gradient, so the network could not learn where a reset hurts). Untrained,
the network's scale is 1 and the parameters hold the default values; "before" is the default refiner itself
(hard gate), and the untrained soft-gate refiner is reported beside it.

Training: clips of ``--clip`` frames (stereo on the first and, at verify every 5, the sixth), rendered with
realistic imaging on tuning seeds (0-99, never reported) from two scenes of each rig's list; the loss is the
mean absolute disparity error over the frames after the first, on pixels the refiner marks valid and that have
truth. Evaluation: whole sequences on seeds 2000 and up (neither tuning seeds nor the refine benchmark's),
including a scene not trained on; EPE and bad-0.5 over valid pixels with truth, before and after.

    python benchmarks/learning.py              # full size of the run in the README (about 20 min on 2 cores)
    python benchmarks/learning.py --quick      # a small run, to check that it works

Writes benchmarks/results/learning.json and .md and the README table between its markers.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, update_readme, write_json  # noqa: E402

from egorefine.data import render_sequence  # noqa: E402
from egorefine.refine import ConfidenceNet, CorrectionOptions, EgoMotionRefiner  # noqa: E402

VERIFY_EVERY = 5
TRAIN_SCENES = [("corridor", "forward"), ("street", "lateral"), ("corridor", "turn"), ("street", "shaky")]
EVAL_SCENES = [("corridor", "forward"), ("street", "lateral"), ("hall", "forward"), ("hall", "turn")]
EVAL_SEED_BASE = 2000


GATE_SOFTNESS = 0.1  # standard deviations: the Kalman gate as a logistic, so that a reset has a gradient


def make_refiner(max_disparity: int, learnable: bool = True) -> EgoMotionRefiner:
    if not learnable:  # the untrained defaults
        return EgoMotionRefiner(max_disparity=max_disparity, verify_every=VERIFY_EVERY, fusion="kalman")
    return EgoMotionRefiner(max_disparity=max_disparity, verify_every=VERIFY_EVERY, fusion="kalman",
                            learnable=True, confidence_net=ConfidenceNet(),
                            correction=CorrectionOptions(gate_softness=GATE_SOFTNESS))


def run(refiner, seq, grad: bool):
    """Refine ``seq``; the outputs per frame (with their graph when ``grad``)."""
    K, b = seq.K[None], torch.tensor([seq.baseline])
    state, outs = None, []
    with torch.set_grad_enabled(grad):
        for t in range(len(seq)):
            out, state = refiner(seq.left[t:t + 1], seq.right[t:t + 1], K, b, state)
            outs.append(out)
    return outs


def clip_loss(outs, seq) -> torch.Tensor:
    """Mean |d - d_true| over the frames after the first, valid pixels with truth."""
    errs, count = [], 0
    for t, out in enumerate(outs[1:], start=1):
        truth = seq.disparity[t:t + 1]
        m = out.valid & (truth > 0) & ~seq.occluded[t:t + 1]
        errs.append((out.disparity - truth).abs()[m].sum())
        count += int(m.sum())
    return torch.stack(errs).sum() / max(count, 1)


def score(outs, seq) -> dict:
    err, bad, n, total = 0.0, 0.0, 0, 0
    for t, out in enumerate(outs):
        truth = seq.disparity[t:t + 1]
        known = (truth > 0) & ~seq.occluded[t:t + 1]
        m = out.valid & known
        e = (out.disparity.detach() - truth).abs()[m]
        err += float(e.sum())
        bad += float((e > 0.5).sum())
        n += int(m.sum())
        total += int(known.sum())
    return {"epe": err / max(n, 1), "bad-0.5": bad / max(n, 1), "density": n / max(total, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a small, short run")
    parser.add_argument("--steps", type=int, default=None, help="training steps (default 60; quick 6)")
    parser.add_argument("--size", type=int, nargs=2, default=None, metavar=("H", "W"),
                        help="render size (default 120 160; quick 48 64)")
    parser.add_argument("--clip", type=int, default=7, help="frames per training clip")
    parser.add_argument("--eval-frames", type=int, default=None, help="frames per evaluation sequence (20)")
    parser.add_argument("--lr", type=float, default=0.02)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None, help="results folder (default benchmarks/results)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    steps = args.steps or (6 if args.quick else 60)
    H, W = args.size or ((48, 64) if args.quick else (120, 160))
    eval_frames = args.eval_frames or (8 if args.quick else 20)
    max_disp = 16 if args.quick else 32

    def render(scene, motion, seed, frames):
        return render_sequence(num_frames=frames, preset="paper", scene=scene, motion=motion, seed=seed,
                               height=H, width=W)

    train = [render(sc, mo, seed, args.clip) for seed in range(8) for sc, mo in TRAIN_SCENES]
    evals = [(f"{sc}_{mo}", EVAL_SEED_BASE + i, render(sc, mo, EVAL_SEED_BASE + i, eval_frames))
             for i, (sc, mo) in enumerate(EVAL_SCENES)]
    defaults = make_refiner(max_disp, learnable=False)
    before = {name: score(run(defaults, seq, grad=False), seq) for name, _, seq in evals}
    refiner = make_refiner(max_disp)
    untrained = {name: score(run(refiner, seq, grad=False), seq) for name, _, seq in evals}
    start = {n: p.detach().clone() for n, p in refiner.named_parameters()}
    opt = torch.optim.Adam(refiner.parameters(), lr=args.lr)
    losses, t0 = [], time.perf_counter()
    for step in range(steps):
        seq = train[step % len(train)]
        opt.zero_grad()
        loss = clip_loss(run(refiner, seq, grad=True), seq)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
        print(f"step {step + 1}/{steps}: loss {losses[-1]:.4f} px "
              f"(q {float(refiner.process_noise):.4f}, noise scale {float(refiner.noise_scale):.3f})",
              file=sys.stderr)
    train_s = time.perf_counter() - t0
    after = {name: score(run(refiner, seq, grad=False), seq) for name, _, seq in evals}

    rows, changes = [], {}
    for name, seed, _ in evals:
        b, u, a = before[name], untrained[name], after[name]
        rows.append([name, seed, f"{b['epe']:.3f}", f"{u['epe']:.3f}", f"{a['epe']:.3f}",
                     f"{100 * (a['epe'] / b['epe'] - 1):+.1f} %", f"{b['bad-0.5']:.3f}", f"{a['bad-0.5']:.3f}",
                     f"{b['density']:.3f}", f"{a['density']:.3f}"])
    mean = {k: {m: sum(r[m] for r in d.values()) / len(d) for m in ("epe", "bad-0.5", "density")}
            for k, d in (("before", before), ("untrained", untrained), ("after", after))}
    gain = 1 - mean["after"]["epe"] / mean["before"]["epe"]
    rows.append(["mean", "", f"{mean['before']['epe']:.3f}", f"{mean['untrained']['epe']:.3f}",
                 f"{mean['after']['epe']:.3f}", f"{-100 * gain:+.1f} %", f"{mean['before']['bad-0.5']:.3f}",
                 f"{mean['after']['bad-0.5']:.3f}", f"{mean['before']['density']:.3f}",
                 f"{mean['after']['density']:.3f}"])
    for n, p in refiner.named_parameters():
        if p.numel() == 1:
            changes[n] = [float(start[n]), float(p)]
    target = "met" if gain >= 0.10 else "not met"
    header = (f"Kalman mode, verify every {VERIFY_EVERY}, defaults + `learnable=True` + `ConfidenceNet()`; paper rig "
              f"at {W}x{H}; trained {steps} steps (Adam, lr {args.lr}) on {len(train)} clips of {args.clip} frames "
              f"(tuning seeds 0-7, scenes {', '.join(f'{s}/{m}' for s, m in TRAIN_SCENES)}), {train_s:.0f} s; "
              f"scored on {eval_frames}-frame sequences with seeds {EVAL_SEED_BASE}+ (hall: a scene not trained on). "
              f"Training loss {losses[0]:.4f} -> {losses[-1]:.4f} px (first and last step). Target (held-back EPE "
              f"at least 10 % below the untrained defaults'): {target} ({100 * gain:.1f} %).")
    table = markdown_table(["sequence", "seed", "EPE defaults", "EPE untrained soft gate", "EPE trained",
                            "change vs defaults", "bad-0.5 before",
                            "bad-0.5 after", "density before", "density after"], rows)
    params = ", ".join(f"{n} {a:.3f} -> {b:.3f}" for n, (a, b) in changes.items())
    text = f"{header}\n\n{table}\n\nScalar parameters, start -> end: {params}."
    print(text)
    payload = {"before": before, "untrained_soft_gate": untrained, "after": after, "losses": losses,
               "parameters": changes, "steps": steps,
               "size": [W, H], "clip": args.clip, "train_seconds": train_s, "relative_epe_gain": gain,
               "target_met": gain >= 0.10, "quick": args.quick}
    if args.out is not None:  # (a test's or a trial's folder: the README stays as the full run left it)
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "learning.json").write_text(json.dumps(payload, indent=2))
        (args.out / "learning.md").write_text(text + "\n")
    elif not args.quick:
        write_json("learning", payload)
        update_readme("learning", text)


if __name__ == "__main__":
    main()
