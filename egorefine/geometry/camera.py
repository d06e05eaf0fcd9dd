"""Pinhole camera of a rectified stereo rig: disparity <-> depth, project and unproject.

Conventions (docs/method.md): camera frame X right, Y down, Z forward; rectified, non-verged
pair; disparity ``d = x_left - x_right > 0`` in pixels; depth ``Z = f * B / d``. ``K`` is the
intrinsic matrix of the rectified left camera in pixels, ``(B, 3, 3)``; ``baseline`` is in
metres, ``(B,)``.
"""

from __future__ import annotations

import torch
from kornia.geometry import create_meshgrid
from kornia.geometry.camera import project_points, unproject_points

from ..core import check_float, check_positive, check_shape, eps_like

__all__ = [
    "make_intrinsics",
    "disparity_to_depth",
    "depth_to_disparity",
    "project",
    "unproject",
    "pixel_grid",
    "unproject_disparity",
]


def make_intrinsics(
    focal: float,
    cx: float,
    cy: float,
    batch_size: int = 1,
    focal_y: float | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Build a batch of pinhole intrinsic matrices ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, in pixels.

    Args:
        focal: focal length ``fx`` in pixels.
        cx: principal point x in pixels.
        cy: principal point y in pixels.
        batch_size: ``B``, the number of copies; default 1.
        focal_y: ``fy`` in pixels; default ``focal`` (square pixels, as rectified stereo rigs have).
        device: device of the result; default torch's default device.
        dtype: dtype of the result; default float32, the library's working type.

    Returns:
        ``(B, 3, 3)`` intrinsics.

    Example:
        >>> make_intrinsics(398.0, 320.0, 240.0, batch_size=2).shape
        torch.Size([2, 3, 3])
    """
    fy = focal if focal_y is None else focal_y
    K = torch.tensor([[focal, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], device=device, dtype=dtype)
    return K.expand(batch_size, 3, 3).clone()


def _per_batch(value: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Reshape a ``(B,)`` tensor to broadcast against ``like`` of shape ``(B, ...)``."""
    return value.reshape(-1, *([1] * (like.dim() - 1)))


def disparity_to_depth(
    disparity: torch.Tensor, focal: torch.Tensor, baseline: torch.Tensor, min_disparity: float | None = None
) -> torch.Tensor:
    """Depth ``Z = f * B / d`` of a disparity map or of disparities at points (docs/method.md, conventions).

    Disparity is clamped to ``min_disparity`` (default: the dtype's epsilon) before dividing, so zero disparity (a
    point at infinity) gives a large finite depth and a finite (zero) gradient instead of Inf/NaN.

    Args:
        disparity: ``(B, ...)`` in pixels, e.g. ``(B, 1, H, W)`` or ``(B, N)``.
        focal: ``(B,)`` focal length in pixels.
        baseline: ``(B,)`` baseline in metres.
        min_disparity: clamp for the divisor in pixels; default the dtype's epsilon, the smallest clamp that keeps
            the division finite.

    Returns:
        depth of ``disparity``'s shape, in metres.

    Example:
        >>> d = torch.tensor([[4.0, 8.0]])
        >>> disparity_to_depth(d, torch.tensor([398.0]), torch.tensor([0.08]))
        tensor([[7.9600, 3.9800]])
    """
    check_float(disparity, "disparity")
    check_shape(focal, ["B"], "focal", {"B": disparity.shape[0]})
    check_shape(baseline, ["B"], "baseline", {"B": disparity.shape[0]})
    eps = eps_like(disparity) if min_disparity is None else min_disparity
    fb = _per_batch(focal * baseline, disparity)
    return fb / disparity.clamp_min(eps)


def depth_to_disparity(
    depth: torch.Tensor, focal: torch.Tensor, baseline: torch.Tensor, min_depth: float | None = None
) -> torch.Tensor:
    """Disparity ``d = f * B / Z`` of a depth map or of depths at points; the inverse of :func:`disparity_to_depth`.

    Depth is clamped to ``min_depth`` before dividing, as disparity is there.

    Args:
        depth: ``(B, ...)`` in metres, e.g. ``(B, 1, H, W)`` or ``(B, N)``.
        focal: ``(B,)`` focal length in pixels.
        baseline: ``(B,)`` baseline in metres.
        min_depth: clamp for the divisor in metres; default the dtype's epsilon.

    Returns:
        disparity of ``depth``'s shape, in pixels.

    Example:
        >>> depth_to_disparity(torch.tensor([[7.96]]), torch.tensor([398.0]), torch.tensor([0.08]))
        tensor([[4.]])
    """
    check_float(depth, "depth")
    check_shape(focal, ["B"], "focal", {"B": depth.shape[0]})
    check_shape(baseline, ["B"], "baseline", {"B": depth.shape[0]})
    eps = eps_like(depth) if min_depth is None else min_depth
    fb = _per_batch(focal * baseline, depth)
    return fb / depth.clamp_min(eps)


def project(points: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Project 3-D points in the camera frame to pixels.

    Args:
        points: ``(B, N, 3)`` camera-frame points.
        K: ``(B, 3, 3)`` intrinsics.

    Returns:
        ``(B, N, 2)`` pixel coordinates ``(x, y)``. Points with ``Z`` near zero are divided
        by a clamped ``Z`` (kornia's homogeneous conversion) and stay finite.

    >>> K = make_intrinsics(100.0, 50.0, 40.0)
    >>> project(torch.tensor([[[0.1, -0.2, 2.0]]]), K)
    tensor([[[55., 30.]]])
    """
    dims = check_shape(points, ["B", "N", "3"], "points")
    check_shape(K, ["B", "3", "3"], "K", dims)
    return project_points(points, K[:, None])


def unproject(pixels: torch.Tensor, depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Lift pixels with known depth to 3-D camera-frame points (inverse of :func:`project`).

    Args:
        pixels: ``(B, N, 2)`` pixel coordinates ``(x, y)``.
        depth: ``(B, N)`` depth ``Z`` in metres.
        K: ``(B, 3, 3)`` intrinsics.

    Returns:
        ``(B, N, 3)`` points.

    >>> K = make_intrinsics(100.0, 50.0, 40.0)
    >>> unproject(torch.tensor([[[55.0, 30.0]]]), torch.tensor([[2.0]]), K)
    tensor([[[ 0.1000, -0.2000,  2.0000]]])
    """
    dims = check_shape(pixels, ["B", "N", "2"], "pixels")
    check_shape(depth, ["B", "N"], "depth", dims)
    check_shape(K, ["B", "3", "3"], "K", dims)
    return unproject_points(pixels, depth[..., None], K[:, None])


def pixel_grid(
    height: int, width: int, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """Pixel coordinates of an image, ``(x, y)`` per pixel, with integer coordinates at pixel centres.

    Args:
        height: ``H`` in pixels.
        width: ``W`` in pixels.
        device: device of the result; default torch's default device.
        dtype: dtype of the result; default float32.

    Returns:
        ``(H, W, 2)``: ``grid[y, x] = (x, y)``.

    Example:
        >>> pixel_grid(2, 3)[1, 2]
        tensor([2., 1.])
    """
    return create_meshgrid(height, width, normalized_coordinates=False, device=device, dtype=dtype)[0]


def unproject_disparity(disparity: torch.Tensor, K: torch.Tensor, baseline: torch.Tensor) -> torch.Tensor:
    """3-D point, in the left camera's frame, of every pixel of a disparity map.

    Each pixel ``(x, y)`` with disparity ``d`` lies at depth ``Z = f B / d`` (``f = fx``) and at
    ``X = (x - cx) Z / fx``, ``Y = (y - cy) Z / fy``: the points the paper moves by the ego-motion
    (docs/method.md, step 3).

    Args:
        disparity: ``(B, 1, H, W)`` in pixels (clamped as in :func:`disparity_to_depth`).
        K: ``(B, 3, 3)`` intrinsics of the rectified left camera.
        baseline: ``(B,)`` in metres, > 0.

    Returns:
        ``(B, H, W, 3)`` points ``(X, Y, Z)`` in metres.

    Example:
        >>> K = make_intrinsics(100.0, 1.0, 1.0)
        >>> points = unproject_disparity(torch.full((1, 1, 3, 3), 4.0), K, torch.tensor([0.08]))
        >>> points.shape, points[0, 1, 1]
        (torch.Size([1, 3, 3, 3]), tensor([0., 0., 2.]))
    """
    dims = check_shape(disparity, ["B", "1", "H", "W"], "disparity")
    check_shape(K, ["B", "3", "3"], "K", dims)
    check_positive(baseline, "baseline")
    B, _, H, W = disparity.shape
    depth = disparity_to_depth(disparity, K[:, 0, 0], baseline)[:, 0]  # (B,H,W)
    grid = pixel_grid(H, W, disparity.device, disparity.dtype)  # (H,W,2)
    fx, fy = K[:, 0, 0].view(B, 1, 1), K[:, 1, 1].view(B, 1, 1)
    cx, cy = K[:, 0, 2].view(B, 1, 1), K[:, 1, 2].view(B, 1, 1)
    X = (grid[..., 0] - cx) / fx * depth
    Y = (grid[..., 1] - cy) / fy * depth
    return torch.stack([X, Y, depth], dim=-1)
