"""Tests of egorefine.stereo.sgm against a naive scanline reference."""

from __future__ import annotations

import torch

from egorefine.stereo import sgm_aggregate


def _naive_path(vol, p1, p2, dy, dx):
    """Literal SGM recursion along direction (dy, dx), pixel by pixel."""
    b, num, h, w = vol.shape
    out = torch.zeros_like(vol)
    ys = range(h) if dy >= 0 else range(h - 1, -1, -1)
    xs = range(w) if dx >= 0 else range(w - 1, -1, -1)
    for y in ys:
        for x in xs:
            py, px = y - dy, x - dx
            if not (0 <= py < h and 0 <= px < w) or (dy == 0 and dx == 0):
                out[:, :, y, x] = vol[:, :, y, x]
                continue
            prev = out[:, :, py, px]
            m = prev.min(dim=1, keepdim=True).values
            cands = [prev, m.expand_as(prev) + p2]
            cands.append(torch.cat([prev[:, :1] + 1e9, prev[:, :-1] + p1], dim=1))
            cands.append(torch.cat([prev[:, 1:] + p1, prev[:, -1:] + 1e9], dim=1))
            out[:, :, y, x] = vol[:, :, y, x] + torch.stack(cands).min(dim=0).values - m
    return out


def test_sgm_matches_naive_reference():
    gen = torch.Generator().manual_seed(0)
    vol = torch.rand(2, 5, 6, 7, generator=gen, dtype=torch.float64)
    p1, p2 = 0.1, 0.4
    dirs4 = [(0, 1), (0, -1), (1, 0), (-1, 0)]
    ref4 = sum(_naive_path(vol, p1, p2, dy, dx) for dy, dx in dirs4) / 4
    assert torch.allclose(sgm_aggregate(vol, p1, p2, 4), ref4)
    dirs8 = dirs4 + [(1, 1), (1, -1), (-1, 1), (-1, -1)]
    ref8 = sum(_naive_path(vol, p1, p2, dy, dx) for dy, dx in dirs8) / 8
    assert torch.allclose(sgm_aggregate(vol, p1, p2, 8), ref8)


def test_sgm_smooths_a_noisy_winner():
    # a constant true disparity with one outlier column of costs: SGM restores the winner there
    vol = torch.ones(1, 6, 8, 8)
    vol[:, 2] = 0.0
    vol[:, :, 4, 4] = 1.0
    vol[:, 4, 4, 4] = 0.8  # spurious, weak minimum at one pixel
    assert vol.argmin(1)[0, 4, 4] == 4
    assert sgm_aggregate(vol, 0.1, 0.5, 4).argmin(1)[0, 4, 4] == 2


def test_sgm_gradcheck():
    gen = torch.Generator().manual_seed(1)
    vol = torch.rand(1, 4, 4, 5, generator=gen, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda v: sgm_aggregate(v, 0.05, 0.3, 8), (vol,), fast_mode=True)
