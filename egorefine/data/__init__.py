"""Data: a synthetic stereo-video renderer with exact ground truth, file formats and sequence loaders."""

from ._families import FAMILIES
from ._imaging import IMAGING, Imaging
from .euroc import EurocSequence, load_euroc, read_euroc_sensor
from .folder import ImageFolderSequence, read_grey
from .io import read_kitti_disparity, read_pfm, write_kitti_disparity, write_pfm
from .synthetic import MOTIONS, PRESETS, SCENES, RigPreset, StereoSequence, render_sequence

__all__ = [
    "FAMILIES",
    "IMAGING",
    "MOTIONS",
    "PRESETS",
    "SCENES",
    "EurocSequence",
    "Imaging",
    "ImageFolderSequence",
    "RigPreset",
    "StereoSequence",
    "load_euroc",
    "read_euroc_sensor",
    "read_grey",
    "read_kitti_disparity",
    "read_pfm",
    "render_sequence",
    "write_kitti_disparity",
    "write_pfm",
]
