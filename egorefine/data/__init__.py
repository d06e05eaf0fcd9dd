"""Data: a synthetic stereo-video renderer with exact ground truth, file formats and sequence loaders."""

from .calib import CAMERAS, StereoCalibration, read_calibration, rectify_maps
from .euroc import EurocSequence, load_euroc, read_euroc_sensor
from .folder import ImageFolderSequence, read_grey
from .io import read_kitti_disparity, read_pfm, write_kitti_disparity, write_pfm
from .recording import LAYOUTS, StereoRecording, open_recording, oxts_to_poses
from .synthetic import MOTIONS, PRESETS, SCENES, RigPreset, StereoSequence, render_sequence

__all__ = [
    "CAMERAS",
    "LAYOUTS",
    "MOTIONS",
    "PRESETS",
    "SCENES",
    "EurocSequence",
    "ImageFolderSequence",
    "RigPreset",
    "StereoCalibration",
    "StereoRecording",
    "StereoSequence",
    "load_euroc",
    "open_recording",
    "oxts_to_poses",
    "read_calibration",
    "read_euroc_sensor",
    "read_grey",
    "read_kitti_disparity",
    "read_pfm",
    "rectify_maps",
    "render_sequence",
    "write_kitti_disparity",
    "write_pfm",
]
