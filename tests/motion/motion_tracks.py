"""Synthetic feature tracks with known depth and ego-motion for the motion tests."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from egorefine.geometry import make_intrinsics, project, transform_points, twist_to_motion, unproject


class Tracks(NamedTuple):
    points_prev: torch.Tensor  # (B,N,2)
    points_next: torch.Tensor  # (B,N,2)
    disparity: torch.Tensor  # (B,N) exact disparity of frame t-1
    K: torch.Tensor  # (B,3,3)
    baseline: torch.Tensor  # (B,)
    motion: torch.Tensor  # (B,4,4) true camera_t_T_camera_{t-1}
    twist: torch.Tensor  # (B,6) true twist
    inlier: torch.Tensor  # (B,N) bool, False for the outlier tracks


def make_tracks(
    twist: torch.Tensor,
    num: int = 200,
    noise: float = 0.0,
    outliers: float = 0.0,
    seed: int = 0,
    focal: float = 400.0,
    size: tuple[int, int] = (480, 640),
    baseline: float = 0.1,
    depth_range: tuple[float, float] = (2.0, 15.0),
) -> Tracks:
    """Random static points (depth 2-15 m) seen in frame t-1, moved by ``twist_to_motion(twist)`` and projected.

    ``noise``: Gaussian pixel noise (std, px) on the tracked positions; ``outliers``: fraction of
    tracks replaced by a random displacement of 5-40 px (a bad track or a moving object).
    """
    dtype = twist.dtype
    B = twist.shape[0]
    gen = torch.Generator().manual_seed(seed)
    H, W = size
    K = make_intrinsics(focal, (W - 1) / 2, (H - 1) / 2, B, dtype=dtype)
    margin = 20.0
    px = torch.rand(B, num, generator=gen, dtype=dtype) * (W - 2 * margin) + margin
    py = torch.rand(B, num, generator=gen, dtype=dtype) * (H - 2 * margin) + margin
    pts = torch.stack([px, py], -1)
    lo, hi = depth_range
    Z = torch.rand(B, num, generator=gen, dtype=dtype) * (hi - lo) + lo
    motion = twist_to_motion(twist)
    nxt = project(transform_points(motion, unproject(pts, Z, K)), K)
    nxt = nxt + noise * torch.randn(B, num, 2, generator=gen, dtype=dtype)
    n_out = int(round(outliers * num))
    inlier = torch.ones(B, num, dtype=torch.bool)
    if n_out:
        idx = torch.rand(B, num, generator=gen).argsort(1)[:, :n_out]
        inlier.scatter_(1, idx, False)
        ang = torch.rand(B, num, generator=gen, dtype=dtype) * 2 * math.pi
        mag = torch.rand(B, num, generator=gen, dtype=dtype) * 35 + 5
        off = torch.stack([ang.cos(), ang.sin()], -1) * mag[..., None]
        nxt = torch.where(inlier[..., None], nxt, nxt + off)
    bl = torch.full((B,), baseline, dtype=dtype)
    disp = focal * baseline / Z
    return Tracks(pts, nxt, disp, K, bl, motion, twist, inlier)
