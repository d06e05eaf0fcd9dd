"""The deprecated `egorefine folder` command and the figures, on small rendered data."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from egorefine.cli import main
from egorefine.data import read_pfm, render_sequence
from egorefine.viz import (
    colorize_disparity,
    disparity_palette_image,
    save_maps_figure,
    save_row_figure,
    save_trajectory_figure,
)


@pytest.fixture(scope="module")
def seq():
    # Ideal images: this checks the command's wiring (PNG round trip, intrinsics, one map per frame) with a bound
    # that a wrong focal or baseline breaks; the matcher's accuracy on realistic images is measured in tests/stereo.
    return render_sequence(num_frames=3, height=120, width=160, seed=1, imaging="ideal")


def test_folder_command_writes_one_accurate_map_per_frame(seq, tmp_path):
    for side, images in (("left", seq.left), ("right", seq.right)):
        (tmp_path / side).mkdir()
        for t, img in enumerate(images):
            cv2.imwrite(str(tmp_path / side / f"{t:03d}.png"), (img[0].numpy() * 255).round().astype(np.uint8))
    K = seq.K
    argv = ["folder", "--left", str(tmp_path / "left"), "--right", str(tmp_path / "right"),
            "--focal", str(float(K[0, 0])), "--cx", str(float(K[0, 2])), "--cy", str(float(K[1, 2])),
            "--baseline", str(seq.baseline), "--max-disparity", "24", "--verify-every", "2",
            "--out", str(tmp_path / "out")]
    assert main(argv) == 0
    maps = sorted((tmp_path / "out").glob("*.pfm"))
    assert len(maps) == 3
    # Every map (stereo, predicted, verified) against truth, at bounds about 1.3 times what the loop achieves on
    # these frames (density: a few points below): a wrong focal, baseline or frame order breaks them, and so does a
    # loop whose motion or sub-pixel stereo is lost.
    for t, path in enumerate(maps):
        d = read_pfm(path)[None]  # (1, 1, H, W); +inf where the refiner has no value
        ok = torch.isfinite(d) & ~seq.occluded[t : t + 1]
        error = (d - seq.disparity[t : t + 1]).abs()[ok]
        assert ok.float().mean() > 0.92, t
        assert error.mean() < 0.12 and error.median() < 0.07, (t, float(error.mean()), float(error.median()))


def test_row_figure_and_colours(seq, tmp_path):
    rgb = colorize_disparity(seq.disparity[0, 0], 30.0, valid=seq.disparity[0, 0] > 5)
    assert rgb.shape == (120, 160, 3) and rgb.dtype == np.uint8
    assert (rgb[(seq.disparity[0, 0] <= 5).numpy()] == 0).all()
    path = save_row_figure(tmp_path / "row.png", 60, {"truth": seq.disparity[0, 0], "again": seq.disparity[1, 0]})
    image = cv2.imread(str(path))
    assert image is not None and image.shape[0] > 300 and image.shape[1] > 400


def _grey_pixels(path) -> int:
    image = cv2.imread(str(path)).astype(int)
    return int(((image >= 126) & (image <= 129)).all(-1).sum())


def test_maps_figure_draws_missing_values_grey(seq, tmp_path):
    truth = seq.disparity[0, 0]
    holes = truth.clone()
    holes[:, :80] = float("nan")  # no value in the left half
    dark = torch.zeros(120, 160)  # a black left image: grey pixels can only come from the NaN halves
    full = save_maps_figure(tmp_path / "full.png", dark, {"a": truth, "b": truth}, truth=truth)
    half = save_maps_figure(tmp_path / "half.png", dark, {"a": truth, "b": holes}, truth=truth)
    assert cv2.imread(str(full)).shape == cv2.imread(str(half)).shape
    # One map panel and one error panel are half grey: several thousand grey pixels more at this size.
    assert _grey_pixels(half) - _grey_pixels(full) > 5000


def test_trajectory_figure(seq, tmp_path):
    path = save_trajectory_figure(tmp_path / "t.png", {"truth": seq.poses, "estimated": seq.poses.flip(0)})
    image = cv2.imread(str(path))
    assert image is not None and image.shape[0] > 300


def test_disparity_palette_image_matches_the_turbo_map():
    """Index ``floor(255 d / max)`` clipped to 254, invalid (and only invalid) pixels 255; the palette is OpenCV's
    turbo map in RGB with the invalid colour last, and ``colorize_disparity`` is the palette at the indices."""
    max_d = 32.0
    d = torch.tensor([[0.0, 0.12, 0.13, 16.0, 31.8, 31.9, 32.0, 40.0, -3.0, 20.0]])
    valid = torch.ones_like(d, dtype=torch.bool)
    valid[0, -1] = False
    index, palette = disparity_palette_image(d, max_d, valid, (128, 128, 128))
    assert index.tolist() == [[0, 0, 1, 127, 253, 254, 254, 254, 0, 255]]
    turbo = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    assert palette.shape == (256, 3) and np.array_equal(palette[:255], turbo[:255])
    assert palette[255].tolist() == [128, 128, 128]
    assert np.array_equal(colorize_disparity(d, max_d, valid, (128, 128, 128)), palette[index])
    assert disparity_palette_image(d, max_d)[0].max() <= 254  # no mask: nothing invalid
