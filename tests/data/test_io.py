"""PFM and KITTI disparity PNG readers and writers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from egorefine.core import ShapeError, ValueRangeError
from egorefine.data import read_kitti_disparity, read_pfm, write_kitti_disparity, write_pfm


@pytest.mark.parametrize("little_endian", [True, False])
@pytest.mark.parametrize("channels", [1, 3])
def test_pfm_round_trip(tmp_path, little_endian: bool, channels: int) -> None:
    gen = torch.Generator().manual_seed(0)
    data = torch.randn(channels, 7, 5, generator=gen) * 100
    path = tmp_path / "x.pfm"
    write_pfm(path, data, little_endian=little_endian)
    back = read_pfm(path)
    assert back.dtype == torch.float32 and back.shape == (channels, 7, 5)
    assert torch.equal(back, data)


def test_pfm_accepts_2d_and_batched(tmp_path) -> None:
    d = np.arange(12, dtype=np.float32).reshape(3, 4)
    write_pfm(tmp_path / "a.pfm", d)
    assert torch.equal(read_pfm(tmp_path / "a.pfm")[0], torch.from_numpy(d))
    write_pfm(tmp_path / "b.pfm", torch.from_numpy(d)[None, None])
    assert read_pfm(tmp_path / "b.pfm").shape == (1, 3, 4)


def test_pfm_rows_bottom_to_top_and_scale_sign(tmp_path) -> None:
    """A file written by hand: big endian (positive scale), rows stored bottom first."""
    rows = np.array([[1.0, 2.0], [3.0, 4.0]], dtype=">f4")  # stored order: bottom row first
    path = tmp_path / "hand.pfm"
    path.write_bytes(b"Pf\n2 2\n1.0\n" + rows.tobytes())
    img = read_pfm(path)
    torch.testing.assert_close(img[0], torch.tensor([[3.0, 4.0], [1.0, 2.0]]))
    little = np.array([[5.0, 6.0]], dtype="<f4")
    path.write_bytes(b"Pf\n2 1\n-1.0\n" + little.tobytes())
    torch.testing.assert_close(read_pfm(path)[0], torch.tensor([[5.0, 6.0]]))


def test_pfm_errors(tmp_path) -> None:
    bad = tmp_path / "bad.pfm"
    bad.write_bytes(b"P6\n2 2\n255\n")
    with pytest.raises(ValueRangeError, match="not a PFM"):
        read_pfm(bad)
    bad.write_bytes(b"Pf\n4 4\n-1.0\n" + b"\0" * 8)
    with pytest.raises(ValueRangeError, match="truncated"):
        read_pfm(bad)
    with pytest.raises(ShapeError, match="data"):
        write_pfm(tmp_path / "x.pfm", torch.zeros(2, 3, 3))


def test_kitti_png_round_trip(tmp_path) -> None:
    gen = torch.Generator().manual_seed(1)
    d = torch.rand(1, 9, 11, generator=gen) * 200 + 0.5
    valid = torch.rand(1, 9, 11, generator=gen) > 0.3
    path = tmp_path / "d.png"
    write_kitti_disparity(path, d, valid)
    back, ok = read_kitti_disparity(path)
    assert back.shape == (1, 9, 11) and ok.dtype == torch.bool
    assert torch.equal(ok, valid)
    assert (back[ok] - d[ok]).abs().max() <= 0.5 / 256 + 1e-6  # quantised to 1/256 px
    assert (back[~ok] == 0).all()
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    assert int(raw[ok[0].numpy()][0]) == int(round(float(d[ok][0]) * 256))


def test_kitti_png_invalid_values(tmp_path) -> None:
    d = torch.tensor([[[0.0, -1.0, float("nan"), 1e6, 1e-4]]])
    write_kitti_disparity(tmp_path / "e.png", d)
    back, ok = read_kitti_disparity(tmp_path / "e.png")
    assert ok.tolist() == [[[False, False, False, True, True]]]
    assert back[0, 0, 3] == pytest.approx(65535 / 256) and back[0, 0, 4] == pytest.approx(1 / 256)


def test_kitti_png_errors(tmp_path) -> None:
    cv2.imwrite(str(tmp_path / "u8.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueRangeError, match="uint16"):
        read_kitti_disparity(tmp_path / "u8.png")
    with pytest.raises(FileNotFoundError):
        read_kitti_disparity(tmp_path / "missing.png")
    with pytest.raises(ShapeError, match="disparity"):
        write_kitti_disparity(tmp_path / "x.png", torch.zeros(3, 4, 4))
    with pytest.raises(ShapeError, match="valid"):
        write_kitti_disparity(tmp_path / "x.png", torch.ones(1, 4, 4), torch.ones(3, 3, dtype=torch.bool))
