"""Writers of the small calibration files the data tests build their layouts from."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def write_filestorage(path: Path, **mats) -> Path:
    """An OpenCV FileStorage file (YAML, XML or JSON by suffix) with each keyword as a float64 matrix."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in mats.items():
        fs.write(key, np.asarray(value, dtype=np.float64))
    fs.release()
    return path


def kitti_numbers(M) -> str:
    """A matrix as one line of KITTI calibration numbers, row by row."""
    return " ".join(f"{v:.12e}" for v in np.ravel(M))
