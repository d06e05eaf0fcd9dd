"""Ego-motion of the stereo rig from tracked features: motion field (eq. 2) and its solvers (eq. 3, RANSAC, SE(3)),
and its direct photometric refinement."""

from .direct import DIRECT_STATUS, DirectMotion, refine_motion_direct
from .field import motion_field, motion_field_jacobian
from .robust import robust_loss, robust_weight
from .solve import METHODS, EgoMotion, EgoMotionSolver, solve_ego_motion

__all__ = [
    "motion_field",
    "motion_field_jacobian",
    "robust_loss",
    "robust_weight",
    "METHODS",
    "EgoMotion",
    "EgoMotionSolver",
    "solve_ego_motion",
    "refine_motion_direct",
    "DirectMotion",
    "DIRECT_STATUS",
]
