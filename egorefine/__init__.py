"""egorefine: sub-pixel disparity from stereo video, refined with the rig's own ego-motion.

The loop of Skulimowski and Strumillo (docs/method.md): stereo block matching, feature tracking,
ego-motion from the motion-field equation, prediction of the next disparity map by moving
every 3-D point, and correction against fresh stereo every i-th frame.

>>> import egorefine
>>> refiner = egorefine.EgoMotionRefiner(max_disparity=64, verify_every=5, fusion="paper")
"""

from . import core, data, features, geometry, metrics, motion, refine, stereo, viz
from .refine import EgoMotionRefiner, RefinerOutput, RefinerState, SequenceResult, refine_sequence

#: The package version.
__version__ = "0.1.0"

__all__ = [
    "core",
    "data",
    "features",
    "geometry",
    "metrics",
    "motion",
    "refine",
    "stereo",
    "viz",
    "EgoMotionRefiner",
    "RefinerOutput",
    "RefinerState",
    "SequenceResult",
    "refine_sequence",
    "__version__",
]
