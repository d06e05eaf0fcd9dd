"""match_stereo_regions / mask_boxes: the boxes cover the dense parts of a mask, and inside them the output is the
full-frame matcher's (exactly, where the left-right check sees far enough)."""

from __future__ import annotations

import pytest
import torch

import egorefine.stereo.matching as matching
from egorefine.core import ShapeError, ValueRangeError, dispatch
from egorefine.data import render_sequence
from egorefine.stereo import mask_boxes, match_stereo, match_stereo_regions

MAX_D = 48


@pytest.fixture(scope="module")
def scene():
    # a rendered pair with boxes in front of walls: depth edges, occlusions (the left-right check matters)
    seq = render_sequence(num_frames=2, height=120, width=320, seed=3)
    return seq.left[:2], seq.right[:2], seq.disparity[:2]


def _mask(batch: int, height: int, width: int) -> torch.Tensor:
    """Two dense blocks (one at the left edge, inside the search range), a band at the bottom, sparse noise."""
    mask = torch.rand(batch, 1, height, width, generator=torch.Generator().manual_seed(0)) > 0.995
    mask[0, :, 20:70, 5:30] = True
    mask[0, :, 40:100, 200:230] = True
    mask[-1, :, 104:, :] = True
    return mask


def _in_boxes(mask: torch.Tensor, **kwargs) -> torch.Tensor:
    inside = torch.zeros_like(mask)
    for b in range(mask.shape[0]):
        for y0, y1, x0, x1 in mask_boxes(mask[b, 0], **kwargs):
            inside[b, :, y0:y1, x0:x1] = True
    return inside


def test_boxes_cover_dense_parts_and_skip_sparse_pixels():
    mask = torch.zeros(128, 256, dtype=torch.bool)
    mask[24:60, 100:110] = True
    lone = [(5, 5), (120, 250), (70, 20)]
    for y, x in lone:
        mask[y, x] = True
    boxes = mask_boxes(mask)
    assert len(boxes) == 1
    y0, y1, x0, x1 = boxes[0]
    assert (y0, y1, x0, x1) == (16, 64, 96, 112)  # the 16 px tiles the block touches
    assert all(not (y0 <= y < y1 and x0 <= x < x1) for y, x in lone)
    assert mask_boxes(torch.zeros(40, 40, dtype=torch.bool)) == []


def test_boxes_merge_when_one_window_is_cheaper():
    mask = torch.zeros(64, 1024, dtype=torch.bool)
    mask[16:48, 100:116] = True
    mask[16:48, 140:156] = True  # 24 px apart: their 32 px margins overlap, one window is cheaper
    mask[16:48, 900:916] = True  # far away: a second window
    assert mask_boxes(mask, margin=32) == [(16, 48, 96, 160), (16, 48, 896, 928)]


def test_wide_margin_equals_the_full_frame(scene):
    left, right, _ = scene
    mask = _mask(2, *left.shape[-2:])
    full = match_stereo(left, right, MAX_D, speckle_size=0)  # the regions matcher leaves the filter off
    out = match_stereo_regions(left, right, mask, MAX_D, margin=MAX_D)
    inside = _in_boxes(mask, margin=MAX_D, extra_rows=8)
    assert inside.float().mean() > 0.1
    # the left-right check sees every competitor: equal to the full frame, bit for bit, inside the boxes
    assert torch.equal(out.valid, full.valid & inside)
    assert torch.equal(out.disparity, torch.where(inside, full.disparity, torch.zeros_like(full.disparity)))
    assert torch.equal(out.variance[inside], full.variance[inside])
    assert (out.variance[~inside] == matching.INVALID_VARIANCE).all()


def test_narrow_margin_differs_only_in_the_left_right_check(scene):
    left, right, truth = scene
    mask = _mask(2, *left.shape[-2:])
    full = match_stereo(left, right, MAX_D, speckle_size=0)  # the regions matcher leaves the filter off
    out = match_stereo_regions(left, right, mask, MAX_D, margin=8)
    inside = _in_boxes(mask, margin=8, extra_rows=8)
    both = out.valid & full.valid
    assert torch.equal(out.disparity[both], full.disparity[both])  # costs, winners, fits: equal
    assert (full.valid & inside & ~out.valid).sum() == 0  # a check that sees less never rejects more
    extra = (out.valid & ~full.valid).sum() / (full.valid & inside).sum()
    assert extra < 0.005  # a few pixels whose competitor lies beyond the window pass (7 of 12558 here)


@pytest.mark.parametrize("path", ["torch", "whole frame"])
def test_other_paths_match_the_whole_frame(scene, path, monkeypatch):
    left, right, _ = scene
    mask = _mask(2, *left.shape[-2:])
    if path == "torch":
        monkeypatch.setattr(dispatch, "ENABLED", False)
        kwargs = {}
    else:
        kwargs = {"full_fraction": 0.0}  # any window is too much: each item is matched whole
    full = match_stereo(left, right, MAX_D, speckle_size=0)  # the regions matcher leaves the filter off
    out = match_stereo_regions(left, right, mask, MAX_D, **kwargs)
    inside = _in_boxes(mask, margin=32, extra_rows=8)
    assert torch.equal(out.valid, full.valid & inside)
    assert torch.equal(out.disparity[inside], full.disparity[inside])


def test_batch_items_are_independent(scene):
    left, right, _ = scene
    mask = _mask(2, *left.shape[-2:])
    both = match_stereo_regions(left, right, mask, MAX_D, margin=8)
    for b in range(2):
        alone = match_stereo_regions(left[b:b + 1], right[b:b + 1], mask[b:b + 1], MAX_D, margin=8)
        for x, y in zip(both, alone, strict=True):
            assert torch.equal(x[b:b + 1], y)


def test_accuracy_inside_the_boxes(scene):
    left, right, truth = scene
    mask = _mask(2, *left.shape[-2:])
    out = match_stereo_regions(left, right, mask, MAX_D)
    err = (out.disparity - truth).abs()[out.valid]
    # Bounds for realistic imaging (noise, weak texture), set from renders with other seeds.
    assert out.valid.sum() > 4500
    assert err.median() < 0.22 and (err > 1).float().mean() < 0.15


def test_bad_input_is_named(scene):
    left, right, _ = scene
    mask = _mask(2, *left.shape[-2:])
    with pytest.raises(ShapeError, match="mask"):
        match_stereo_regions(left, right, mask[:, :, :-1], MAX_D)
    with pytest.raises(ValueRangeError, match="not arguments of match_stereo"):
        match_stereo_regions(left, right, mask, MAX_D, block=9)
    with pytest.raises(ValueRangeError, match="tile"):
        match_stereo_regions(left, right, mask, MAX_D, tile=0)
    with pytest.raises(ValueRangeError, match="min_fraction"):
        match_stereo_regions(left, right, mask, MAX_D, min_fraction=0.0)
    with pytest.raises(ValueRangeError, match="max_disparity"):
        match_stereo_regions(left, right, mask, 1000)


def test_gradients_flow_through_the_whole_frame_path(scene):
    left, right, _ = scene
    mask = _mask(2, *left.shape[-2:])
    right = right.clone().requires_grad_(True)  # only the right image needs a gradient: not the compiled path
    out = match_stereo_regions(left, right, mask, MAX_D)
    out.disparity.sum().backward()
    assert right.grad is not None and torch.isfinite(right.grad).all() and right.grad.abs().sum() > 0
