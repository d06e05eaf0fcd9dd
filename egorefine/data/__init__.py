"""Data: a synthetic stereo-video renderer with exact ground truth, file formats and sequence loaders."""

from ._families import FAMILIES
from ._imaging import IMAGING, Imaging
from .calib import CAMERAS, StereoCalibration, read_calibration, rectify_maps
from .euroc import EurocSequence, load_euroc, read_euroc_sensor
from .folder import ImageFolderSequence, read_grey
from .io import PNG_ENCODINGS, read_kitti_disparity, read_pfm, write_kitti_disparity, write_pfm, write_png
from .recording import LAYOUTS, StereoRecording, open_recording, oxts_to_poses
from .results import (
    DISPARITY_FORMATS,
    atomic_path,
    read_disparity,
    write_confidence,
    write_disparity,
    write_mask,
    write_preview,
)
from .rosbag import ROSBAG_ENCODINGS, RosbagNotInstalledError, RosbagRecording, open_rosbag
from .synthetic import MOTIONS, PRESETS, SCENES, RigPreset, StereoSequence, render_sequence
from .trajectory import read_trajectory, write_kitti_poses, write_tum

__all__ = [
    "CAMERAS",
    "LAYOUTS",
    "DISPARITY_FORMATS",
    "FAMILIES",
    "IMAGING",
    "MOTIONS",
    "PNG_ENCODINGS",
    "PRESETS",
    "ROSBAG_ENCODINGS",
    "SCENES",
    "EurocSequence",
    "Imaging",
    "ImageFolderSequence",
    "RigPreset",
    "RosbagNotInstalledError",
    "RosbagRecording",
    "StereoCalibration",
    "StereoRecording",
    "atomic_path",
    "StereoSequence",
    "load_euroc",
    "open_recording",
    "open_rosbag",
    "oxts_to_poses",
    "read_calibration",
    "read_euroc_sensor",
    "read_disparity",
    "read_grey",
    "read_kitti_disparity",
    "read_pfm",
    "rectify_maps",
    "read_trajectory",
    "render_sequence",
    "write_confidence",
    "write_disparity",
    "write_kitti_disparity",
    "write_kitti_poses",
    "write_mask",
    "write_pfm",
    "write_png",
    "write_preview",
    "write_tum",
]
