"""egorefine: sub-pixel disparity from stereo video, refined with the rig's own ego-motion."""

from . import core, geometry, metrics

__version__ = "0.1.0"

__all__ = ["core", "geometry", "metrics", "__version__"]
