"""Features: corner detection (gradient response, grid NMS, sub-pixel) and batched block-matching tracking."""

from .detection import Detector, corner_response, detect, replenish
from .tracking import Tracker, TrackOutput, build_pyramid, track

__all__ = [
    "Detector",
    "TrackOutput",
    "Tracker",
    "build_pyramid",
    "corner_response",
    "detect",
    "replenish",
    "track",
]
