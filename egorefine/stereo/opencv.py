"""OpenCV's stereo matchers configured as their users run them: the baselines of the demo, benchmarks and tests.

StereoBM and StereoSGBM (3-way) with the post-processing OpenCV's own samples and users turn on: a uniqueness
ratio of 10, a speckle filter of 100 px within 2 px, and a left-right check of 1 px (``disp12MaxDiff``); SGBM's
smoothness penalties P1 = 8 cn bs^2 and P2 = 32 cn bs^2 for cn-channel input (grey images: cn = 1). A bare
``cv2.StereoBM_create(num, block)`` has none of this post-processing and is a weaker baseline than users meet;
comparisons against it would flatter.

Example:
    >>> import numpy as np
    >>> left = np.random.default_rng(0).integers(0, 256, (48, 96), dtype=np.uint8)
    >>> disparity, valid = compute(stereo_bm(16), left, np.roll(left, -4, axis=1))
    >>> disparity.shape, disparity.dtype, valid.dtype
    ((48, 96), dtype('float32'), dtype('bool'))
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from ..core import check_shape, to_grey

__all__ = ["BM_BLOCK", "SGBM_BLOCK", "stereo_bm", "stereo_sgbm", "compute", "match_opencv"]

# BM's window of our default matcher's size; SGBM's window as OpenCV's stereo_match sample uses it
BM_BLOCK = 9
SGBM_BLOCK = 5


def stereo_bm(num_disparities: int, block_size: int = BM_BLOCK) -> cv2.StereoBM:
    """``cv2.StereoBM`` searching ``[0, num_disparities)`` (a multiple of 16) with an odd ``block_size`` window, with
    uniqueness 10, speckle window 100 within 2 px and a 1 px left-right check."""
    bm = cv2.StereoBM_create(num_disparities, block_size)
    bm.setUniquenessRatio(10)
    bm.setSpeckleWindowSize(100)
    bm.setSpeckleRange(2)
    bm.setDisp12MaxDiff(1)
    return bm


def stereo_sgbm(num_disparities: int, block_size: int = SGBM_BLOCK, channels: int = 1) -> cv2.StereoSGBM:
    """``cv2.StereoSGBM`` 3-way over ``[0, num_disparities)``: P1 = 8 cn bs^2, P2 = 32 cn bs^2 (``channels`` = cn),
    uniqueness 10, speckle window 100 within 2 px, a 1 px left-right check."""
    area = channels * block_size * block_size
    return cv2.StereoSGBM_create(minDisparity=0, numDisparities=num_disparities, blockSize=block_size, P1=8 * area,
                                 P2=32 * area, disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100,
                                 speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)


def compute(matcher, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(disparity, valid)`` of ``matcher`` on a uint8 pair ``(H, W)``: float32 px (OpenCV's fixed point / 16) and
    bool (OpenCV marks a pixel without a match negative)."""
    raw = matcher.compute(left, right)
    return raw.astype(np.float32) / 16.0, raw >= 0


def match_opencv(matcher, left: torch.Tensor, right: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``matcher`` (:func:`stereo_bm`, :func:`stereo_sgbm`) on a batch of egorefine images, item by item.

    The images are turned into what OpenCV users feed it: grey (colour through the luma weights,
    :func:`egorefine.core.to_grey`, as OpenCV's ``cvtColor`` does) as uint8, 255 times the value in ``[0, 1]``,
    rounded.

    Args:
        matcher: an OpenCV stereo matcher (``cv2.StereoBM`` or ``cv2.StereoSGBM``).
        left, right: ``(B, 1, H, W)`` or ``(B, 3, H, W)`` images in ``[0, 1]``.

    Returns:
        ``(disparity, valid)``, each ``(B, 1, H, W)``: float32 px (0 where not valid) and bool.

    Example:
        >>> left = torch.rand(2, 1, 32, 64, generator=torch.Generator().manual_seed(0))
        >>> d, valid = match_opencv(stereo_sgbm(16), left, torch.roll(left, -3, dims=3))
        >>> d.shape, valid.dtype, bool((d[valid] - 3).abs().median() < 0.5)
        (torch.Size([2, 1, 32, 64]), torch.bool, True)
    """
    dims = check_shape(left, ["B", "1|3", "H", "W"], "left")
    check_shape(right, ["B", "1|3", "H", "W"], "right", dims)
    outs = []
    for i in range(left.shape[0]):
        grey = [(to_grey(x[i : i + 1])[0, 0].detach().float().clamp(0, 1) * 255).round().byte().cpu().numpy()
                for x in (left, right)]
        outs.append(compute(matcher, *grey))
    disparity = torch.from_numpy(np.stack([d for d, _ in outs]))[:, None].clamp_min(0)
    valid = torch.from_numpy(np.stack([v for _, v in outs]))[:, None]
    return disparity * valid, valid
