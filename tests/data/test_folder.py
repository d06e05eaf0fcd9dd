"""Image-folder stereo sequences."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from egorefine.core import DataError, MissingDataError, ValueRangeError
from egorefine.data import ImageFolderSequence, read_grey


def _write_pairs(root, n: int, colour: bool = False) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    (root / "L").mkdir()
    (root / "R").mkdir()
    frames = []
    for i in range(n):
        img = rng.integers(0, 256, (6, 8), dtype=np.uint8)
        frames.append(img)
        left = cv2.merge([img, img, img]) if colour else img
        cv2.imwrite(str(root / "L" / f"{i:06d}.png"), left)
        cv2.imwrite(str(root / "R" / f"{i:06d}.png"), 255 - img)
    (root / "L" / "notes.txt").write_text("ignored by the pattern")
    return frames


def test_sorted_indexable_iterable(tmp_path) -> None:
    frames = _write_pairs(tmp_path, 3)
    seq = ImageFolderSequence(tmp_path / "L", tmp_path / "R")
    assert len(seq) == 3
    left, right = seq[1]
    assert left.shape == (1, 1, 6, 8) and right.shape == (1, 1, 6, 8) and left.dtype == torch.float32
    torch.testing.assert_close(left[0, 0], torch.from_numpy(frames[1]).float() / 255)
    torch.testing.assert_close(right[0, 0], 1 - torch.from_numpy(frames[1]).float() / 255)
    assert torch.equal(seq[-1][0], seq[2][0])
    pairs = list(seq)
    assert len(pairs) == 3 and torch.equal(pairs[0][0], seq[0][0])
    with pytest.raises(IndexError):
        seq[3]


def test_colour_and_16_bit_become_grey(tmp_path) -> None:
    frames = _write_pairs(tmp_path, 1, colour=True)
    left, _ = ImageFolderSequence(tmp_path / "L", tmp_path / "R", dtype=torch.float64)[0]
    assert left.dtype == torch.float64 and left.shape == (1, 1, 6, 8)
    torch.testing.assert_close(left[0, 0], torch.from_numpy(frames[0]).double() / 255, atol=1 / 255, rtol=0)
    d16 = tmp_path / "d16"
    d16.mkdir()
    cv2.imwrite(str(d16 / "a.png"), np.full((2, 3), 65535, np.uint16))
    left16, _ = ImageFolderSequence(d16, d16)[0]
    assert torch.allclose(left16, torch.ones(1, 1, 2, 3))


def test_errors(tmp_path) -> None:
    _write_pairs(tmp_path, 2)
    (tmp_path / "L" / "000009.png").write_bytes((tmp_path / "L" / "000000.png").read_bytes())
    with pytest.raises(ValueRangeError, match="right_dir"):
        ImageFolderSequence(tmp_path / "L", tmp_path / "R")
    with pytest.raises(ValueRangeError, match="no files"):
        ImageFolderSequence(tmp_path / "L", tmp_path / "R", pattern="*.jpg")
    with pytest.raises(FileNotFoundError, match="left_dir"):
        ImageFolderSequence(tmp_path / "nope", tmp_path / "R")


def test_read_grey_errors(tmp_path) -> None:
    with pytest.raises(MissingDataError, match="no image file at .*gone.png"):
        read_grey(tmp_path / "gone.png")
    (tmp_path / "text.png").write_text("not a PNG")
    with pytest.raises(DataError, match="text.png' is not an image file OpenCV can decode"):
        read_grey(tmp_path / "text.png")
