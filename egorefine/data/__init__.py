"""Data: a synthetic stereo-video renderer with exact ground truth, file formats and sequence loaders."""

from .synthetic import MOTIONS, PRESETS, SCENES, RigPreset, StereoSequence, render_sequence

__all__ = [
    "MOTIONS",
    "PRESETS",
    "SCENES",
    "RigPreset",
    "StereoSequence",
    "render_sequence",
]
