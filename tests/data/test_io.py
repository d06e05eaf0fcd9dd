"""PFM and KITTI disparity PNG readers and writers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from egorefine.core import ShapeError, ValueRangeError
from egorefine.data import PNG_ENCODINGS, read_kitti_disparity, read_pfm, write_kitti_disparity, write_pfm, write_png


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


@pytest.mark.parametrize("png", PNG_ENCODINGS)
def test_kitti_png_invalid_values(tmp_path, png: str) -> None:
    inf, nan = float("inf"), float("nan")
    d = torch.tensor([[[0.0, -1.0, nan, 1e6, 1e-4, inf, -inf, 2.5]]])
    valid = torch.tensor([[[True, True, True, True, True, True, True, False]]])
    write_kitti_disparity(tmp_path / "e.png", d, valid, png=png)
    back, ok = read_kitti_disparity(tmp_path / "e.png")
    assert ok.tolist() == [[[False, False, False, True, True, False, False, False]]]
    assert back[0, 0, 3] == pytest.approx(65535 / 256) and back[0, 0, 4] == pytest.approx(1 / 256)
    assert (back[~ok] == 0).all()


@pytest.mark.parametrize("png", PNG_ENCODINGS)
@pytest.mark.parametrize(("dtype", "channels"), [(np.uint8, 1), (np.uint16, 1), (np.uint8, 3), (np.uint16, 3)])
def test_png_encodings_hold_the_same_pixels(tmp_path, png: str, dtype, channels: int) -> None:
    """Every encoding reads back as written, through OpenCV's decoder (which checks the chunks' CRCs); the image is
    large enough that the stored encoding needs several deflate blocks (at most 65535 bytes each)."""
    rng = np.random.default_rng(5)
    shape = (151, 203) if channels == 1 else (151, 203, 3)
    image = rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True)
    image[0, :5] = np.iinfo(dtype).max  # the extremes and a byte order that a swap would show
    image[1, :5] = 0x0102 if dtype == np.uint16 else 0x12
    path = tmp_path / f"{png}.png"
    write_png(path, image, png)
    back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert back.dtype == dtype and back.shape == image.shape
    assert np.array_equal(back if channels == 1 else back[..., ::-1], image)  # RGB in, OpenCV reads BGR
    raw_bytes = image.nbytes + image.shape[0]  # the rows and a filter byte each
    if png == "fast":  # stored: the raw rows plus framing, nothing deflated
        assert raw_bytes < path.stat().st_size < raw_bytes + 200 + 5 * (raw_bytes // 65535 + 1)


def test_png_errors(tmp_path) -> None:
    with pytest.raises(ValueRangeError, match="png"):
        write_png(tmp_path / "a.png", np.zeros((2, 3), np.uint8), "deflated")
    with pytest.raises(ShapeError, match="image"):
        write_png(tmp_path / "a.png", np.zeros((2, 3), np.float32))
    with pytest.raises(ShapeError, match="image"):
        write_png(tmp_path / "a.png", np.zeros((2, 3, 4), np.uint8))
    assert not list(tmp_path.iterdir())


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


@pytest.mark.parametrize("png", PNG_ENCODINGS)
def test_uint16_maps_compiled_and_numpy_paths_write_the_same_bytes(tmp_path, png: str, monkeypatch) -> None:
    """The disparity and confidence files: the compiled scanlines (egorefine.data._png_numba) against numpy's passes,
    file for file, on values that test each step: NaN, infinities, negatives, the clip bounds, halves (rint's ties
    to even) and invalid pixels."""
    from egorefine.core import dispatch
    from egorefine.data import _png_numba
    from egorefine.data.results import write_confidence

    if not _png_numba.AVAILABLE:
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(3)
    d = (rng.random((37, 53)) * 300).astype(np.float32)
    special = [np.nan, np.inf, -np.inf, -1.0, 0.0, 1e-4, 0.5 / 256, 1.5 / 256, 2.5 / 256, 255.99, 256.0, 1e6]
    d[0, : len(special)] = special
    valid = rng.random(d.shape) > 0.2
    valid[0, : len(special)] = True
    c = np.concatenate([d[:, :20] / 300, np.full((37, 5), 0.5 / 65535, np.float32)], axis=1)
    c[1, :4] = [np.nan, -0.5, 1.5, 2.5 / 65535]
    files = {}
    for compiled in (True, False):
        monkeypatch.setattr(dispatch, "ENABLED", compiled)
        write_kitti_disparity(tmp_path / f"d{compiled}.png", d, valid, png=png)
        files[compiled] = [(tmp_path / f"d{compiled}.png").read_bytes(),
                           write_confidence(tmp_path / f"c{compiled}", c, png=png).read_bytes()]
    assert files[True] == files[False]
    back = cv2.imread(str(tmp_path / "dTrue.png"), cv2.IMREAD_UNCHANGED)
    assert back[0, : len(special)].tolist() == [0, 0, 0, 0, 0, 1, 1, 2, 2, 65533, 65535, 65535]
    assert (back[~valid] == 0).all() and (back[valid & (d > 1) & np.isfinite(d)] > 0).all()
