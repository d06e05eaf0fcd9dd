"""The detector's quadratic peak fit and smallest image side, shared by the torch path and its compiled twin.

:mod:`egorefine.features.detection` (the torch reference) and :mod:`egorefine.features._detect_numba` (its numba
form) both import from here, so neither imports the other's internals: the detector imports its compiled twin, the
twin imports only this module.
"""

from __future__ import annotations

import torch

from ..core import eps_like

# The corner response's gradient and window filters pad by reflection, which needs more pixels than their radius:
# the smallest height and width either path accepts.
_MIN_SIDE = 4


def _subpixel_offsets(resp: torch.Tensor, ix: torch.Tensor, iy: torch.Tensor) -> torch.Tensor:
    """Quadratic fit of ``resp`` (B, H, W) over the 3x3 neighbourhoods of integer peaks (B, N).

    Fits ``r(u) = r0 + g.u + u^T H u / 2`` by central differences and returns the vertex
    offset ``-H^-1 g`` (B, N, 2), clamped to one pixel. Where the fitted Hessian is not
    negative definite, each axis falls back to its own 1-D parabola (or to no offset).
    """
    b, h, w = resp.shape
    flat = resp.reshape(b, h * w)

    def at(dx: int, dy: int) -> torch.Tensor:
        xx = (ix + dx).clamp(0, w - 1)
        yy = (iy + dy).clamp(0, h - 1)
        return flat.gather(1, yy * w + xx)

    c = at(0, 0)
    gx = 0.5 * (at(1, 0) - at(-1, 0))
    gy = 0.5 * (at(0, 1) - at(0, -1))
    hxx = at(1, 0) - 2 * c + at(-1, 0)
    hyy = at(0, 1) - 2 * c + at(0, -1)
    hxy = 0.25 * (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1))
    eps = eps_like(resp)
    det = hxx * hyy - hxy * hxy
    definite = (hxx < 0) & (det > eps * (hxx * hxx + hyy * hyy + eps))
    det_safe = torch.where(definite, det, torch.ones_like(det))
    ox2 = -(hyy * gx - hxy * gy) / det_safe
    oy2 = -(hxx * gy - hxy * gx) / det_safe
    # 1-D fallbacks: the parabola through three samples along one axis.
    hxx_safe = torch.where(hxx < 0, hxx, -torch.ones_like(hxx))
    hyy_safe = torch.where(hyy < 0, hyy, -torch.ones_like(hyy))
    ox1 = torch.where(hxx < 0, -gx / hxx_safe, torch.zeros_like(gx))
    oy1 = torch.where(hyy < 0, -gy / hyy_safe, torch.zeros_like(gy))
    ox = torch.where(definite, ox2, ox1).clamp(-1.0, 1.0)
    oy = torch.where(definite, oy2, oy1).clamp(-1.0, 1.0)
    return torch.stack([ox, oy], dim=-1)
