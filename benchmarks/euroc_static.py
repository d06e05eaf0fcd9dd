"""No-drift check on real stereo video: the EuRoC V1_01 clip (../shared/data), where the vehicle is almost still.

For paper and Kalman fusion (verify every 5, exact motion) it prints the largest per-frame median
|d_t - d_0| over stable pixels (valid on every frame, > 1 px on the first), the same drift measured against
the first map moved to frame t (by the estimated motion, and by the true motion from the ground truth), so
that the vehicle's own sub-degree motion is not counted as drift, the largest per-frame motion error against
the ground truth, and ms per frame. On a still camera the first map is itself a noisy measurement, so a filter
that averages measurements moves away from it while getting better: the benchmark also scores every map against
the per-pixel mean of per-frame stereo over the clip (the best reference a still scene gives) and reports how
much that error grows after frame 0 (negative: the map converges). tests/refine/test_refiner_euroc.py asserts
these quantities.

    python benchmarks/euroc_static.py [--root ../shared/data/euroc_v1_01_micro]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, markdown_table, set_threads, update_readme, write_json  # noqa: E402

from egorefine.data import load_euroc  # noqa: E402
from egorefine.metrics import rotation_error_deg, translation_error  # noqa: E402
from egorefine.refine import EgoMotionRefiner, predict_disparity  # noqa: E402
from egorefine.stereo import match_stereo  # noqa: E402


def compensated_drift(d: torch.Tensor, v: torch.Tensor, moved: torch.Tensor, K: torch.Tensor,
                      b: torch.Tensor) -> torch.Tensor:
    """Median |d_t - W_t(d_0)| per frame, with W_t the first map ``d[0]`` moved to frame t by ``moved[t]``
    (``camera_t_T_camera_0``), over pixels valid in d_t and landed by the warp, > 1 px (``(T,)``)."""
    T = d.shape[0]
    warped = predict_disparity(d[:1].expand(T, -1, -1, -1).contiguous(), moved.to(d.dtype), K.expand(T, 3, 3),
                               b.expand(T), valid=v[:1].expand(T, -1, -1, -1).contiguous(), fill_holes=False)
    ok = warped.valid & v & (warped.disparity > 1.0)
    return torch.stack([(d[t] - warped.disparity[t]).abs()[ok[t]].median() for t in range(T)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", default=str(ROOT.parent / "shared" / "data" / "euroc_v1_01_micro"))
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    set_threads(args.threads)
    seq = load_euroc(args.root)
    K, b = seq.K[None], torch.tensor([seq.baseline])
    gt = torch.linalg.inv(seq.poses[1:]) @ seq.poses[:-1]
    true_moved = torch.linalg.inv(seq.poses) @ seq.poses[:1]  # camera_t_T_camera_0
    stereo = [match_stereo(seq.left[t : t + 1], seq.right[t : t + 1], 64) for t in range(len(seq.left))]
    sd, sv = torch.cat([o.disparity for o in stereo]), torch.cat([o.valid for o in stereo])
    reference = (sd * sv).sum(0) / sv.sum(0).clamp(min=1)
    referenced = sv.float().mean(0) >= 0.5  # measured on at least half of the frames
    rows, results = [], {}
    for fusion in ("paper", "kalman"):
        refiner = EgoMotionRefiner(max_disparity=64, verify_every=5, fusion=fusion)
        state, disparity, valid, motion = None, [], [], []
        t0 = time.perf_counter()
        for t in range(len(seq.left)):
            out, state = refiner(seq.left[t : t + 1], seq.right[t : t + 1], K, b, state)
            disparity.append(out.disparity)
            valid.append(out.valid)
            motion.append(out.motion)
        ms = (time.perf_counter() - t0) * 1e3 / len(seq.left)
        d, v, m = torch.cat(disparity), torch.cat(valid), torch.cat(motion)
        stable = v.all(0) & (d[0] > 1.0)
        drift = torch.stack([(d[t] - d[0]).abs()[stable].median() for t in range(len(d))])
        est_moved = [m[0]]  # camera_t_T_camera_0 from the per-frame motions (m[0] is the identity)
        for step in m[1:]:
            est_moved.append(step @ est_moved[-1])
        est_moved = torch.stack(est_moved)
        drift_est = compensated_drift(d, v, est_moved, K, b)
        drift_true = compensated_drift(d, v, true_moved, K, b)
        ok = stable & referenced
        to_reference = torch.stack([(d[t] - reference).abs()[ok].median() for t in range(len(d))])
        res = {
            "median_error_vs_mean_stereo_first_px": float(to_reference[0]),
            "median_error_vs_mean_stereo_last_px": float(to_reference[-1]),
            "max_growth_vs_mean_stereo_px": float((to_reference - to_reference[0]).max()),
            "max_median_drift_px": float(drift.max()),
            "last_median_drift_px": float(drift[-1]),
            "max_compensated_drift_est_px": float(drift_est.max()),
            "max_compensated_drift_true_px": float(drift_true.max()),
            "stable_fraction": float(stable.float().mean()),
            "max_translation_error_mm": float(translation_error(m[1:], gt).max() * 1e3),
            "max_rotation_error_deg": float(rotation_error_deg(m[1:], gt).max()),
            "ms_per_frame": ms,
        }
        results[fusion] = res
        rows.append([fusion, res["max_median_drift_px"], res["last_median_drift_px"],
                     res["max_compensated_drift_est_px"], res["max_compensated_drift_true_px"],
                     res["median_error_vs_mean_stereo_first_px"], res["median_error_vs_mean_stereo_last_px"],
                     res["max_growth_vs_mean_stereo_px"], res["stable_fraction"],
                     res["max_translation_error_mm"], res["max_rotation_error_deg"], ms])
    header = ["fusion", "max median drift px", "final median drift px", "max drift vs d_0 moved (est.) px",
              "max drift vs d_0 moved (true) px", "vs mean stereo, frame 0 px", "vs mean stereo, last px",
              "max growth vs mean stereo px", "stable share", "max t err mm", "max rot err deg", "ms/frame"]
    table = markdown_table(header, rows)
    H, W = seq.left.shape[-2:]
    print(f"EuRoC V1_01, {len(seq.left)} frames {W}x{H}, verify every 5, exact motion")
    print(table)
    write_json("euroc_static", {"frames": len(seq.left), "results": results})
    update_readme("euroc_static", f"{len(seq.left)} frames, {W}x{H}, verify every 5, exact motion.\n\n{table}")


if __name__ == "__main__":
    main()
