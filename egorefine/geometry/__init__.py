"""Stereo-rig geometry: intrinsics, disparity <-> depth, projection and SE(3) motions."""

from .camera import (
    depth_to_disparity,
    disparity_to_depth,
    make_intrinsics,
    pixel_grid,
    project,
    unproject,
    unproject_disparity,
)
from .se3 import motion_to_twist, se3_exp, se3_inverse, se3_log, transform_points, twist_to_motion

__all__ = [
    "depth_to_disparity",
    "disparity_to_depth",
    "make_intrinsics",
    "pixel_grid",
    "project",
    "unproject",
    "unproject_disparity",
    "motion_to_twist",
    "se3_exp",
    "se3_inverse",
    "se3_log",
    "transform_points",
    "twist_to_motion",
]
