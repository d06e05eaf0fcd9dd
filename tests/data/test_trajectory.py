"""TUM and KITTI trajectory files: exact round trips, the formats evo reads, and bad files."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from egorefine.core import ShapeError, ValueRangeError
from egorefine.data import read_trajectory, write_kitti_poses, write_tum
from egorefine.geometry import se3_exp


def _poses() -> torch.Tensor:
    g = torch.Generator().manual_seed(7)
    twists = torch.randn(9, 6, dtype=torch.float64, generator=g) * 2.0
    poses = se3_exp(twists)
    # Turns of exactly and nearly 180 degrees, where a trace-based quaternion formula loses its sign.
    poses[0] = se3_exp(torch.tensor([[1.0, -2.0, 3.0, math.pi, 0.0, 0.0]], dtype=torch.float64))[0]
    poses[1] = se3_exp(torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, math.pi - 1e-7]], dtype=torch.float64))[0]
    poses[2] = torch.eye(4, dtype=torch.float64)
    return poses


def test_tum_round_trip(tmp_path):
    poses = _poses()
    stamps = 1403715273.262142976 + 0.05 * np.arange(len(poses))
    write_tum(tmp_path / "t.txt", poses, stamps)
    read_stamps, back = read_trajectory(tmp_path / "t.txt")
    torch.testing.assert_close(back, poses, atol=1e-9, rtol=0)
    np.testing.assert_allclose(read_stamps, stamps, atol=1e-6, rtol=0)
    # evo's TUM format: 8 numbers a line, a unit quaternion (x, y, z, w) last; '#' lines are comments.
    rows = [line.split() for line in (tmp_path / "t.txt").read_text().splitlines() if not line.startswith("#")]
    assert all(len(r) == 8 for r in rows)
    q = np.array([[float(v) for v in r[4:]] for r in rows])
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    assert (q[:, 3] >= 0).all()
    assert rows[2][1:] == ["0", "0", "0", "0", "0", "0", "1"]


def test_kitti_round_trip_and_format(tmp_path):
    poses = _poses()
    write_kitti_poses(tmp_path / "k.txt", poses)
    stamps, back = read_trajectory(tmp_path / "k.txt")
    assert stamps is None
    assert torch.equal(back, poses)  # 17 significant digits: the same float64 numbers
    first = [float(v) for v in (tmp_path / "k.txt").read_text().splitlines()[0].split()]
    assert len(first) == 12 and first[3] == pytest.approx(float(poses[0, 0, 3]))
    assert first[8:] == pytest.approx(poses[0, 2].tolist())


def test_default_timestamps_and_tabs(tmp_path):
    poses = _poses()[:3]
    write_tum(tmp_path / "t.txt", poses)
    stamps, _ = read_trajectory(tmp_path / "t.txt")
    assert stamps.tolist() == [0.0, 1.0, 2.0]
    (tmp_path / "tab.txt").write_text("# comment\n\n0\t1\t2\t3\t0\t0\t0\t2\n")  # an unnormalised quaternion
    stamps, back = read_trajectory(tmp_path / "tab.txt")
    torch.testing.assert_close(back[0, :3, :3], torch.eye(3, dtype=torch.float64))
    assert back[0, :3, 3].tolist() == [1.0, 2.0, 3.0]


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", "holds no pose"),
        ("0 1 2 3 4 5 6\n", "8 columns .*12"),
        ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0\n", "line 2 has 7 numbers"),
        ("0 0 0 x 0 0 0 1\n", "line 1 is not a row of numbers"),
        ("0 0 0 0 0 0 0 0\n", "zero quaternion"),
    ],
)
def test_bad_files(tmp_path, text, match):
    (tmp_path / "bad.txt").write_text(text)
    with pytest.raises(ValueRangeError, match=match):
        read_trajectory(tmp_path / "bad.txt")


def test_bad_arguments(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_trajectory(tmp_path / "none.txt")
    with pytest.raises(ShapeError, match="poses"):
        write_tum(tmp_path / "t.txt", torch.eye(3)[None])
    with pytest.raises(ShapeError, match="timestamps"):
        write_tum(tmp_path / "t.txt", torch.eye(4)[None].repeat(2, 1, 1), np.zeros(3))
