"""Per-frame result files: disparity in three formats, mask, confidence, preview, atomic writes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from egorefine.core import ShapeError, ValueRangeError
from egorefine.data import (
    PNG_ENCODINGS,
    atomic_path,
    read_disparity,
    read_kitti_disparity,
    read_pfm,
    write_confidence,
    write_disparity,
    write_mask,
    write_preview,
)
from egorefine.viz import colorize_disparity, disparity_palette_image


@pytest.fixture
def disparity():
    g = torch.Generator().manual_seed(3)
    d = torch.rand(1, 1, 6, 9, generator=g) * 40
    valid = torch.rand(1, 1, 6, 9, generator=g) > 0.3
    d[0, 0, 0, 0], valid[0, 0, 0, 0] = 0.0, True  # a valid 0 cannot be stored: invalid in every format
    d[0, 0, 0, 1], valid[0, 0, 0, 1] = float("nan"), True
    return d, valid


@pytest.mark.parametrize(("fmt", "tolerance"), [("png16", 1 / 512), ("pfm", 0.0), ("npy", 0.0)])
def test_disparity_round_trip_marks_invalid_pixels(tmp_path, disparity, fmt, tolerance):
    d, valid = disparity
    path = write_disparity(tmp_path / "frame", d, valid, fmt)
    assert path.name == "frame" + {"png16": ".png", "pfm": ".pfm", "npy": ".npy"}[fmt]
    back, ok = read_disparity(path)
    expected = valid[0, 0] & torch.isfinite(d[0, 0]) & (d[0, 0] > 0)
    assert torch.equal(ok, expected)
    assert (back[ok] - d[0, 0][ok]).abs().max() <= tolerance + 1e-7
    assert (back[~ok] == 0).all()
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporary file left
    if fmt == "pfm":  # invalid pixels are +inf in the file (Middlebury's "unknown"), not 0
        raw = read_pfm(path)[0]
        assert torch.isinf(raw[~expected]).all()
    if fmt == "npy":
        assert np.isnan(np.load(path)[~expected.numpy()]).all()
    if fmt == "png16":
        assert torch.equal(read_kitti_disparity(path)[1][0], expected)


def test_confidence_mask_preview(tmp_path):
    c = torch.tensor([[0.0, 0.25, 1.0], [0.5, 2.0, -1.0]])
    for png in PNG_ENCODINGS:
        raw = cv2.imread(str(write_confidence(tmp_path / png, c, png=png)), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and raw.tolist() == [[0, 16384, 65535], [32768, 65535, 0]]
    odd = torch.tensor([[float("nan"), float("inf"), -float("inf")]])
    assert cv2.imread(str(write_confidence(tmp_path / "o", odd)), cv2.IMREAD_UNCHANGED).tolist() == [[0, 65535, 0]]
    assert np.load(write_confidence(tmp_path / "c", c, "npy")).tolist() == [[0.0, 0.25, 1.0], [0.5, 1.0, 0.0]]
    mask = cv2.imread(str(write_mask(tmp_path / "m.png", c > 0.3)), cv2.IMREAD_UNCHANGED)
    assert mask.dtype == np.uint8 and mask.tolist() == [[0, 0, 255], [255, 255, 0]]
    rgb = np.zeros((2, 3, 3), np.uint8)
    rgb[..., 0] = 200  # red in RGB: blue-channel-last on disk is OpenCV's business
    for png in PNG_ENCODINGS:
        bgr = cv2.imread(str(write_preview(tmp_path / f"{png}.png", rgb, png)))
        assert (bgr[..., 2] == 200).all() and (bgr[..., 0] == 0).all()
    # an indexed-colour preview decodes to the colour image the palette gives
    d = torch.tensor([[0.0, 3.0, 7.9], [8.0, 50.0, 2.0]])
    valid = torch.tensor([[True, True, True], [True, True, False]])
    index, palette = disparity_palette_image(d, 8.0, valid, (128, 128, 128))
    for png in PNG_ENCODINGS:
        bgr = cv2.imread(str(write_preview(tmp_path / f"i{png}.png", index, png, palette)))
        assert np.array_equal(bgr[..., ::-1], colorize_disparity(d, 8.0, valid, (128, 128, 128)))


def test_atomic_path_keeps_the_old_file_on_error(tmp_path):
    target = tmp_path / "a.png"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("stopped")
    assert target.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["a.png"]


def test_bad_arguments(tmp_path, disparity):
    d, valid = disparity
    with pytest.raises(ValueRangeError, match="fmt"):
        write_disparity(tmp_path / "f", d, valid, "tiff")
    for write in (lambda: write_disparity(tmp_path / "f", d, valid, "npy", "zip"),
                  lambda: write_confidence(tmp_path / "f", d, png="zip"),
                  lambda: write_preview(tmp_path / "p.png", np.zeros((2, 3, 3), np.uint8), "zip")):
        with pytest.raises(ValueRangeError, match="png"):
            write()
    with pytest.raises(ShapeError, match="valid"):
        write_disparity(tmp_path / "f", d, valid[..., :3])
    with pytest.raises(ShapeError, match="rgb"):
        write_preview(tmp_path / "p.png", np.zeros((2, 3), np.uint8))
    with pytest.raises(FileNotFoundError):
        read_disparity(tmp_path / "none.png")
    (tmp_path / "x.tif").write_bytes(b"")
    with pytest.raises(ValueRangeError, match="expected a .png, .pfm or .npy"):
        read_disparity(tmp_path / "x.tif")
    (tmp_path / "bad.npy").write_bytes(b"not numpy")
    with pytest.raises(ValueRangeError, match="not a NumPy array"):
        read_disparity(tmp_path / "bad.npy")
