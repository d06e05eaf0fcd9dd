"""What the commands of :mod:`egorefine.cli` share: the files ``run`` writes, the tables they print, JSON files."""

from __future__ import annotations

import json
from pathlib import Path

# What `egorefine run` writes into its output folder (run.json last: its presence means the run finished).
_FRAME_DIRS = ("disparity", "valid", "confidence", "preview")
_TRAJECTORY_FILES = ("trajectory_tum.txt", "trajectory_kitti.txt", "groundtruth_tum.txt", "groundtruth_kitti.txt")
_RUN_JSON = "run.json"


def _table(rows: list[list[object]], header: list[str]) -> str:
    cells = [[f"{v:.3f}" if isinstance(v, float) else str(v) for v in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) for i, h in enumerate(header)]
    line = "  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))
    body = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) for r in cells]
    return "\n".join([line, "-" * len(line), *body])


def _write_json(path: Path, data: dict) -> Path:
    from ..data import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")
    return path
