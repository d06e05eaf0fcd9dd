"""Draw docs/figures/dataflow.png: one frame of the loop, the figure of docs/architecture.md.

Run from the repository root: ``python docs/figures/dataflow.py`` (matplotlib only).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch  # noqa: E402

# name -> (x, y, label, colour): stages in the order one frame runs them
BOXES = {
    "images": (0.9, 2.3, "left$_t$, right$_t$", "#e8e8e8"),
    "prev": (0.9, 0.8, "state of frame $t-1$:\nleft$_{t-1}$, features,\nkeyframe disparity", "#e8e8e8"),
    "track": (3.3, 0.8, "features.track\npatch search on a pyramid,\nfrom predicted positions", "#cfe3f7"),
    "motion": (5.7, 0.8, "motion.solve_ego_motion\neq. 2, 3, then SE(3)", "#cfe3f7"),
    "predict": (8.1, 0.8, "refine.predict_disparity\neq. 1: move every point,\nsplat, close cracks", "#d6efd0"),
    "stereo": (5.7, 2.3, "stereo.match_stereo\nverification frames only;\nholes filled by SGM", "#fbe3c8"),
    "correct": (10.5, 2.3, "refine.correct_disparity\nKalman fusion, or the\npaper's gate and gain", "#f6d0d0"),
    "out": (10.5, 0.8, "disparity$_t$, variance$_t$,\nconfidence, motion$_t$,\nstate for $t+1$", "#e8e8e8"),
}
ARROWS = [
    ("prev", "track", ""), ("track", "motion", "tracks"), ("motion", "predict", "motion"),
    ("images", "stereo", "the pair"), ("stereo", "correct", "measurement $s_t$"),
    ("predict", "correct", "prediction $e_t$"), ("predict", "out", "other frames"), ("correct", "out", ""),
]
W, H = 1.75, 0.85
OUT = Path(__file__).with_name("dataflow.png")


def main(path: Path = OUT) -> Path:
    fig, ax = plt.subplots(figsize=(12.5, 3.4))
    for x, y, label, colour in BOXES.values():
        ax.add_patch(FancyBboxPatch((x - W / 2, y - H / 2), W, H, boxstyle="round,pad=0.04", fc=colour, ec="#444"))
        ax.text(x, y, label, ha="center", va="center", fontsize=8.5)
    for a, b, label in ARROWS:
        (xa, ya), (xb, yb) = BOXES[a][:2], BOXES[b][:2]
        if ya == yb:  # side to side
            start, end = (xa + W / 2 * (1 if xb > xa else -1), ya), (xb - W / 2 * (1 if xb > xa else -1), yb)
        elif xa == xb:  # up or down
            start, end = (xa, ya + H / 2 * (1 if yb > ya else -1)), (xb, yb - H / 2 * (1 if yb > ya else -1))
        else:  # from the right edge up (or down) into the other row's box
            start = (xa + W / 2, ya)
            end = (xb - W / 2 + 0.15, yb - H / 2 if yb > ya else yb + H / 2)
        ax.add_patch(FancyArrowPatch(start, end, arrowstyle="-|>", mutation_scale=12, color="#333", lw=1.1))
        if label:  # above the arrow; below where the arrow to the corrector leaves above it
            below = label == "other frames"
            ax.text((start[0] + end[0]) / 2, (start[1] + end[1]) / 2 + (-0.08 if below else 0.08), label,
                    ha="center", va="top" if below else "bottom", fontsize=7.5, color="#333")
    # left_t also feeds the tracker: a line down the left column's right edge
    ax.add_patch(FancyArrowPatch((BOXES["images"][0] + W / 2, BOXES["images"][1] - H / 4),
                                 (BOXES["track"][0] - W / 4, BOXES["track"][1] + H / 2), arrowstyle="-|>",
                                 connectionstyle="angle,angleA=0,angleB=90", mutation_scale=12, color="#333", lw=1.1))
    ax.text(BOXES["track"][0] - W / 4 + 0.05, BOXES["images"][1] - H / 4 + 0.06, "left$_t$", fontsize=7.5, color="#333")
    ax.set_xlim(-0.1, 11.5)
    ax.set_ylim(0.25, 2.85)
    ax.axis("off")
    ax.set_title("One frame of egorefine's loop", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path


if __name__ == "__main__":
    print(main())
