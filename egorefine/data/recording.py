"""Stereo recordings in the folder layouts people have, opened lazily and rectified on the fly.

:func:`open_recording` reads a layout's file lists, calibration, time stamps and poses, and returns a
:class:`StereoRecording`: a sequence of rectified grey ``(left, right)`` pairs read only when indexed, with the
rectified left camera's ``K``, the baseline and (where the layout has them) ``world_T_camera`` poses.

Layouts (:data:`LAYOUTS`):

``folders``
    ``path/left/`` and ``path/right/`` image folders (or ``cam0/cam1``, or KITTI's ``image_0/image_1`` with
    ``camera="grey"`` and ``image_2/image_3`` with ``camera="colour"``: the first pair present, in that order),
    frames paired by sorted file name, and a calibration file (``calib``, or found in ``path``: see
    :func:`egorefine.data.read_calibration` for the formats; ``camera`` also picks a KITTI file's pair). Time
    stamps from ``path/times.txt`` (seconds, one line per frame) where present; no poses.
``kitti-raw``
    A synced and rectified drive, ``.../2011_09_26/2011_09_26_drive_0001_sync/``: ``image_00``/``image_01``
    (grey) or ``image_02``/``image_03`` (colour) with ``data/*.png`` and ``timestamps.txt`` (the left camera's,
    else image_02's or image_00's: the synced cameras share a trigger);
    ``calib_cam_to_cam.txt`` in the drive folder or its parent (the date folder); poses from ``oxts/data/*.txt``
    where present, with ``calib_imu_to_velo.txt`` and ``calib_velo_to_cam.txt`` (drive or date folder; poses
    None without them). The world frame is the first OXTS pose's, as in the KITTI devkit.
``kitti-odometry``
    A sequence folder ``.../sequences/XX/``: ``calib.txt`` (``P0`` .. ``P3``), ``image_0``/``image_1`` (grey) or
    ``image_2``/``image_3`` (colour), ``times.txt``, and ``../../poses/XX.txt`` where present (camera 0's poses,
    moved to the loaded left camera).
``euroc``
    EuRoC MAV's ASL layout (``mav0/cam0``, ``mav0/cam1``, ground truth optional; ``path`` is the folder holding
    ``mav0`` or ``mav0`` itself): see :func:`egorefine.data.load_euroc`. Grey cameras only.
``rosbag``
    A ROS 1 ``.bag`` file or a ROS 2 bag folder (sqlite3 or mcap storage): two image topics (``topics``), paired
    by header stamp, calibrated from their CameraInfo topics or ``calib``; see :func:`egorefine.data.open_rosbag`.
    Needs ``pip install egorefine[rosbag]``.

Every unrectified layout goes through :func:`egorefine.data.rectify_maps`.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from ..core import DataError, MissingDataError, ShapeError, ValueRangeError, check_choice
from .calib import _KITTI_PAIRS, CAMERAS, StereoCalibration, _read_kitti_txt, _remap, read_calibration, rectify_maps
from .euroc import _index_euroc, _rectified_poses
from .folder import read_grey

__all__ = ["LAYOUTS", "StereoRecording", "open_recording", "oxts_to_poses"]

#: The folder layouts :func:`open_recording` reads.
LAYOUTS = ("folders", "kitti-raw", "kitti-odometry", "euroc", "rosbag")
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
_FOLDER_PAIRS = {"grey": (("left", "right"), ("cam0", "cam1"), ("image_0", "image_1")),
                 "colour": (("left", "right"), ("cam0", "cam1"), ("image_2", "image_3"))}
_EARTH_RADIUS_M = 6378137.0  # WGS84 equatorial radius, the KITTI devkit's Mercator projection


class StereoRecording:
    """A stereo recording read lazily: each ``(left, right)`` pair is read and rectified when indexed.

    Build one with :func:`open_recording`, which reads a layout's files into these arguments.

    Args:
        left_files, right_files: one image file per frame and camera.
        K: ``(3, 3)`` intrinsics of the rectified left camera, pixels.
        baseline: metres, > 0.
        image_size: ``(H, W)`` of the images (raw and rectified alike: rectification keeps the size).
        names: one stem per frame.
        timestamps: ``(T,)`` seconds, or None.
        poses: ``(T, 4, 4)`` ``world_T_camera`` of the rectified left camera, or None.
        maps: :func:`egorefine.data.rectify_maps`'s tables for both cameras, or None for rectified input.

    Attributes:
        K: ``(3, 3)`` float64 intrinsics of the rectified left camera, pixels.
        baseline: metres, > 0.
        image_size: ``(H, W)`` of the rectified images.
        names: one file stem per frame (a time stamp or a frame number), for output file names.
        timestamps: ``(T,)`` float64 seconds, or None where the layout has none.
        poses: ``(T, 4, 4)`` float64 ``world_T_camera`` of the rectified left camera, or None.
        rectified_input: the layout's images were rectified already (no remap).
        left_files: the left camera's image files, one per frame.
        right_files: the right camera's image files, one per frame.

    Indexing (``rec[t]``, negative too) and iteration yield ``(left, right)``, each ``(1, 1, H, W)`` float32 grey
    in [0, 1], rectified; colour frames become grey. ``len(rec)`` is the number of frames.

    Raises (on indexing):
        MissingDataError: an image file has gone.
        DataError: a file that does not decode, or a frame whose size differs from the calibration's.

    Example:
        >>> import tempfile, pathlib, cv2
        >>> folder = pathlib.Path(tempfile.mkdtemp())
        >>> files = [folder / "left.png", folder / "right.png"]
        >>> for f in files:
        ...     _ = cv2.imwrite(str(f), np.zeros((24, 32), np.uint8))
        >>> K = torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]])
        >>> rec = StereoRecording(files[:1], files[1:], K, 0.1, (24, 32), ["000000"])  # rectified already
        >>> len(rec), rec.rectified_input, rec[0][0].shape, rec[0][1].shape
        (1, True, torch.Size([1, 1, 24, 32]), torch.Size([1, 1, 24, 32]))
    """

    def __init__(self, left_files: list[Path], right_files: list[Path], K: torch.Tensor, baseline: float,
                 image_size: tuple[int, int], names: list[str], timestamps: np.ndarray | None = None,
                 poses: torch.Tensor | None = None, maps: tuple | None = None) -> None:
        self.left_files, self.right_files = list(left_files), list(right_files)
        self.K = K.to(torch.float64)
        self.baseline = float(baseline)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.names = list(names)
        self.timestamps = timestamps
        self.poses = poses
        self.rectified_input = maps is None
        self._maps = maps
        T = len(self.left_files)
        for name, n in (("right_files", len(self.right_files)), ("names", len(self.names)),
                        ("timestamps", None if timestamps is None else len(timestamps)),
                        ("poses", None if poses is None else len(poses))):
            if n is not None and n != T:
                raise ShapeError(f"{name}: expected one entry per frame ({T}), got {n}")
        if not self.baseline > 0:
            raise ValueRangeError(f"baseline: expected > 0 metres, got {self.baseline}")

    def __len__(self) -> int:
        return len(self.left_files)

    def __repr__(self) -> str:
        H, W = self.image_size
        return (f"StereoRecording(T={len(self)}, H={H}, W={W}, f={float(self.K[0, 0]):.2f}, "
                f"baseline={self.baseline:.4f}, rectified_input={self.rectified_input}, "
                f"poses={self.poses is not None})")

    def _read(self, path: Path, camera: int) -> torch.Tensor:
        return self._rectified(read_grey(path).numpy()[0, 0], path, camera)

    def _rectified(self, img: np.ndarray, where: object, camera: int) -> torch.Tensor:
        """A frame ``(H, W)`` read from ``where`` (named in the error), checked for size and rectified by
        ``camera``'s maps (0: left, 1: right), as a ``(1, 1, H, W)`` tensor."""
        if img.shape != self.image_size:
            raise DataError(f"path: {where} is {img.shape[1]}x{img.shape[0]} (W x H), expected "
                            f"{self.image_size[1]}x{self.image_size[0]} as the calibration and first frame")
        if self._maps is not None:
            img = _remap(img, self._maps[camera])
        return torch.from_numpy(np.ascontiguousarray(img))[None, None]

    def __getitem__(self, t: int) -> tuple[torch.Tensor, torch.Tensor]:
        if not -len(self) <= t < len(self):
            raise IndexError(f"t: frame {t} out of range for {len(self)} frames")
        return self._read(self.left_files[t], 0), self._read(self.right_files[t], 1)

    def __iter__(self) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        for t in range(len(self)):
            yield self[t]


def _images(folder: Path) -> list[Path]:
    """The image files of a folder, sorted by name (other files ignored)."""
    files = sorted(f for f in folder.iterdir() if f.is_file() and f.suffix.lower() in _IMAGE_SUFFIXES)
    if not files:
        raise DataError(f"path: no image files ({', '.join(_IMAGE_SUFFIXES)}) in {folder}")
    return files


def _image_pair(left_dir: Path, right_dir: Path) -> tuple[list[Path], list[Path]]:
    for folder in (left_dir, right_dir):
        if not folder.is_dir():
            raise MissingDataError(f"path: no folder {folder}")
    left, right = _images(left_dir), _images(right_dir)
    if len(left) != len(right):
        raise DataError(f"path: {right_dir} holds {len(right)} images, {left_dir} {len(left)}; expected one right "
                        "frame per left frame")
    return left, right


def _size_of(path: Path) -> tuple[int, int]:
    return tuple(read_grey(path).shape[-2:])


def _pose_matrix(rows: np.ndarray, source: Path | str) -> np.ndarray:
    """``(T, 4, 4)`` from rows of 12 numbers (a 3x4 matrix, row by row)."""
    if rows.ndim != 2 or rows.shape[1] != 12:
        raise DataError(f"path: {source}: expected 12 numbers per line (a 3x4 pose), found shape {rows.shape}")
    out = np.tile(np.eye(4), (len(rows), 1, 1))
    out[:, :3, :] = rows.reshape(-1, 3, 4)
    return out


def _numbers(path: Path, ncols: int | None = None) -> np.ndarray:
    """A text file of whitespace-separated numbers as ``(lines, columns)`` float64."""
    try:
        rows = [[float(v) for v in line.split()] for line in path.read_text().splitlines() if line.strip()]
    except (ValueError, UnicodeDecodeError):
        raise DataError(f"path: {path} is not a text file of numbers") from None
    if not rows or len({len(r) for r in rows}) != 1 or (ncols is not None and len(rows[0]) < ncols):
        want = f"at least {ncols}" if ncols is not None else "the same number of"
        raise DataError(f"path: {path}: expected {want} numbers on every line")
    return np.array(rows)


def _check_count(what: str, source: Path, n: int, frames: int) -> None:
    if n != frames:
        raise DataError(f"path: {source} has {n} {what}, expected one per frame ({frames})")


def _times(path: Path, frames: int) -> np.ndarray | None:
    """Seconds from a ``times.txt`` (one number per line, one line per frame); None without the file."""
    if not path.is_file():
        return None
    times = _numbers(path)[:, 0]
    _check_count("time stamps", path, len(times), frames)
    return times


def _rect_offset(P: np.ndarray) -> np.ndarray:
    """``t`` with ``P = K [I | t]``: where a rectified camera sits relative to the rectified reference camera."""
    return np.linalg.solve(P[:, :3], P[:, 3])


def _shift(t: np.ndarray) -> np.ndarray:
    """The ``(4, 4)`` translation ``[I | t]``."""
    out = np.eye(4)
    out[:3, 3] = t
    return out


def oxts_to_poses(oxts: np.ndarray) -> np.ndarray:
    """OXTS GPS/IMU records to ``world_T_imu`` poses, as the KITTI raw devkit's ``convertOxtsToPose`` does.

    Latitude and longitude go through a Mercator projection whose scale is the first record's
    ``cos(latitude)``; the rotation is ``Rz(yaw) Ry(pitch) Rx(roll)``; the world frame is the first pose's (so
    ``poses[0]`` is the identity): x forward, y left, z up of the vehicle at the start.

    Args:
        oxts: ``(T, >= 6)`` records ``(lat, lon, alt, roll, pitch, yaw, ...)``, degrees, metres, radians.

    Returns:
        ``(T, 4, 4)`` float64 ``world_T_imu``, metres.

    Example:
        >>> import numpy as np
        >>> rec = np.array([[49.0, 8.4, 110.0, 0.0, 0.0, 0.0], [49.0, 8.4, 111.5, 0.0, 0.0, 0.0]])
        >>> oxts_to_poses(rec)[1, :3, 3].round(6).tolist()
        [0.0, 0.0, 1.5]
    """
    oxts = np.asarray(oxts, dtype=np.float64)
    lat, lon, alt, roll, pitch, yaw = (oxts[:, i] for i in range(6))
    scale = np.cos(lat[0] * np.pi / 180.0)
    x = scale * lon * np.pi * _EARTH_RADIUS_M / 180.0
    y = scale * _EARTH_RADIUS_M * np.log(np.tan((90.0 + lat) * np.pi / 360.0))
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    one, zero = np.ones_like(roll), np.zeros_like(roll)
    Rx = np.stack([one, zero, zero, zero, cr, -sr, zero, sr, cr], -1).reshape(-1, 3, 3)
    Ry = np.stack([cp, zero, sp, zero, one, zero, -sp, zero, cp], -1).reshape(-1, 3, 3)
    Rz = np.stack([cy, -sy, zero, sy, cy, zero, zero, zero, one], -1).reshape(-1, 3, 3)
    poses = np.tile(np.eye(4), (len(oxts), 1, 1))
    poses[:, :3, :3] = Rz @ Ry @ Rx
    t = np.stack([x, y, alt], -1)
    poses[:, :3, 3] = t - t[0]  # relative first: Mercator metres are millions, their difference is what counts
    return np.linalg.inv(poses[0]) @ poses


def _rigid(fields: dict[str, np.ndarray], source: Path) -> np.ndarray:
    """``(4, 4)`` from a KITTI extrinsic file's ``R`` (9 numbers) and ``T`` (3)."""
    out = np.eye(4)
    for key, n in (("R", 9), ("T", 3)):
        if key not in fields or fields[key].size != n:
            raise DataError(f"calib: {source} lacks {key} ({n} numbers)")
    out[:3, :3] = fields["R"].reshape(3, 3)
    out[:3, 3] = fields["T"]
    return out


def _kitti_timestamps(path: Path) -> np.ndarray:
    """Seconds (float64, since 1970, read as UTC) from a KITTI raw ``timestamps.txt``."""
    lines = [line.strip() for line in path.read_text().splitlines() if line.strip()]
    try:
        ns = np.array([np.datetime64(line.replace(" ", "T"), "ns") for line in lines]).astype(np.int64)
    except ValueError:
        raise DataError(f"path: {path}: expected lines 'YYYY-MM-DD hh:mm:ss.fffffffff'") from None
    return ns / 1e9


def _fit_calibration(cal: StereoCalibration, size: tuple[int, int], first: object) -> StereoCalibration:
    """``cal`` for images of ``size`` ``(H, W)``: its size where it names none; a DataError naming ``first`` (the
    first frame) where it names another."""
    if cal.image_size is None:
        return replace(cal, image_size=size)
    if cal.image_size != size:
        raise DataError(f"calib: {cal.source} is for {cal.image_size[1]}x{cal.image_size[0]} images, "
                        f"{first} is {size[1]}x{size[0]} (W x H)")
    return cal


def _open_folders(path: Path, calib: str | os.PathLike | None, camera: str) -> dict:
    for a, b in _FOLDER_PAIRS[camera]:
        if (path / a).is_dir() or (path / b).is_dir():
            left, right = _image_pair(path / a, path / b)
            break
    else:
        raise MissingDataError(f"path: {path} holds none of the folder pairs "
                               f"{', '.join(f'{a}/ + {b}/' for a, b in _FOLDER_PAIRS[camera])} (camera={camera!r})")
    size = _size_of(left[0])
    cal = _fit_calibration(read_calibration(path if calib is None else calib, camera), size, left[0])
    maps, K, baseline = rectify_maps(cal)
    return dict(left_files=left, right_files=right, K=K, baseline=baseline, image_size=size, maps=maps,
                names=[f.stem for f in left], timestamps=_times(path / "times.txt", len(left)))


def _open_euroc(path: Path, calib: str | os.PathLike | None, camera: str) -> dict:
    if camera != "grey":
        raise ValueRangeError(f"camera: EuRoC has grey cameras only, got {camera!r}")
    if not (path / "mav0").is_dir() and path.name == "mav0":
        path = path.parent  # the mav0 folder itself was named
    index = _index_euroc(path)
    maps, K, baseline = rectify_maps(index.calib)
    poses = _rectified_poses(index.world_T_cam0, index.calib)
    return dict(left_files=index.left, right_files=index.right, K=K, baseline=baseline, maps=maps,
                image_size=index.calib.image_size, names=[str(s) for s in index.stamps],
                timestamps=np.array(index.stamps, dtype=np.int64) / 1e9, poses=poses)


def _beside(path: Path, name: str) -> Path | None:
    """``name`` in the drive folder or its parent (KITTI raw keeps calibration in the date folder)."""
    for folder in (path, path.parent):
        if (folder / name).is_file():
            return folder / name
    return None


def _open_kitti_raw(path: Path, calib: str | os.PathLike | None, camera: str) -> dict:
    if path.name.endswith("_extract"):
        raise DataError(f"path: {path} is KITTI's unsynced, unrectified '_extract' download; kitti-raw reads the "
                        "synced and rectified '_sync' one")
    a, b = _KITTI_PAIRS[camera]
    left, right = _image_pair(path / f"image_{a:02d}" / "data", path / f"image_{b:02d}" / "data")
    cam_file = _beside(path, "calib_cam_to_cam.txt")
    if cam_file is None:
        raise MissingDataError(f"path: no calib_cam_to_cam.txt in {path} or {path.parent}")
    cal = read_calibration(cam_file, camera)
    maps, K, baseline = rectify_maps(cal)
    size = cal.image_size or _size_of(left[0])
    out = dict(left_files=left, right_files=right, K=K, baseline=baseline, image_size=size, maps=maps,
               names=[f.stem for f in left])
    # The synced cameras are triggered together: another camera's stamps stand in where the left's are missing.
    stamps = [path / f"image_{c:02d}" / "timestamps.txt" for c in (a, 2, 0)]
    stamps = next((f for f in stamps if f.is_file()), None)
    if stamps is not None:
        out["timestamps"] = _kitti_timestamps(stamps)
        _check_count("time stamps", stamps, len(out["timestamps"]), len(left))
    imu_file, velo_file = _beside(path, "calib_imu_to_velo.txt"), _beside(path, "calib_velo_to_cam.txt")
    oxts_dir = path / "oxts" / "data"
    if oxts_dir.is_dir() and imu_file is not None and velo_file is not None:
        files = sorted(oxts_dir.glob("*.txt"))
        _check_count("OXTS records", oxts_dir, len(files), len(left))
        world_T_imu = oxts_to_poses(np.concatenate([_numbers(f, 6)[:1] for f in files]))
        fields = _read_kitti_txt(cam_file)
        if "R_rect_00" not in fields:
            raise DataError(f"calib: {cam_file} lacks R_rect_00 (needed for the poses)")
        rect0 = np.eye(4)
        rect0[:3, :3] = fields["R_rect_00"].reshape(3, 3)
        # X_rect_j = [I | t_j] R_rect_00 (R|T)_velo_to_cam (R|T)_imu_to_velo X_imu (the devkit's chain).
        cam_T_imu = (_shift(_rect_offset(cal.P1)) @ rect0 @ _rigid(_read_kitti_txt(velo_file), velo_file)
                     @ _rigid(_read_kitti_txt(imu_file), imu_file))
        out["poses"] = world_T_imu @ np.linalg.inv(cam_T_imu)
    return out


def _open_kitti_odometry(path: Path, calib: str | os.PathLike | None, camera: str) -> dict:
    a, b = _KITTI_PAIRS[camera]
    left, right = _image_pair(path / f"image_{a}", path / f"image_{b}")
    if not (path / "calib.txt").is_file():
        raise MissingDataError(f"path: no calib.txt in {path} (expected a KITTI odometry sequence folder)")
    cal = read_calibration(path / "calib.txt", camera)
    maps, K, baseline = rectify_maps(cal)
    out = dict(left_files=left, right_files=right, K=K, baseline=baseline, image_size=_size_of(left[0]),
               maps=maps, names=[f.stem for f in left])
    out["timestamps"] = _times(path / "times.txt", len(left))
    pose_file = path.parent.parent / "poses" / f"{path.name}.txt"
    if pose_file.is_file():
        world_T_cam0 = _pose_matrix(_numbers(pose_file), pose_file)
        _check_count("poses", pose_file, len(world_T_cam0), len(left))
        # Rectified camera j sits at X_j = X_0 + t_j (P_j = K [I | t_j]), so cam0_T_camj = [I | -t_j].
        out["poses"] = world_T_cam0 @ _shift(-_rect_offset(cal.P1))
    return out


_OPENERS = {"folders": _open_folders, "kitti-raw": _open_kitti_raw, "kitti-odometry": _open_kitti_odometry,
            "euroc": _open_euroc}


def open_recording(path: str | os.PathLike, layout: str, calib: str | os.PathLike | None = None,
                   frames: slice | None = None, camera: str = "grey", *, topics: tuple[str, str] | None = None,
                   info_topics: tuple[str | None, str | None] | None = None,
                   pair_tolerance: float | None = None) -> StereoRecording:
    """Open a stereo recording stored in one of :data:`LAYOUTS`, rectified where the layout is not.

    The file lists, calibration, time stamps and poses are read now, the first pair too (to catch a bad file
    early); the other images when indexed.

    Args:
        path: the recording's folder (see the module's description for each layout).
        layout: one of :data:`LAYOUTS`.
        calib: ``folders`` and ``rosbag`` only: the calibration file (or its folder); default: found in ``path``
            (``folders``) or read from the bag's CameraInfo topics (``rosbag``). The other layouts read their own
            calibration files.
        frames: which frames to keep, e.g. ``slice(100, 200)`` or ``slice(None, None, 2)``; default all.
        camera: ``"grey"`` or ``"colour"``: which KITTI camera pair to read (the kitti layouts, ``folders`` with
            KITTI folder names or a KITTI calibration file); colour frames are turned grey. EuRoC accepts grey
            only. Default grey, KITTI's reference camera 0.
        topics: ``rosbag`` only, and needed there: the ``(left, right)`` image topics.
        info_topics: ``rosbag`` only: the ``(left, right)`` CameraInfo topics (either may be None); default: each
            image topic's sibling ``camera_info``.
        pair_tolerance: ``rosbag`` only: seconds within which left and right header stamps pair; default: 0.005 s
            or half the median left frame interval, the shorter.

    Returns:
        :class:`StereoRecording` (for ``rosbag`` a :class:`~egorefine.data.RosbagRecording`).

    Raises:
        MissingDataError: ``path``, an image folder or a needed calibration file is absent.
        DataError: left/right frame counts differ, a file does not decode or parse or lacks a field, time stamps
            or poses do not match the frames, ``frames`` selects none.
        ValueRangeError: an unknown ``layout`` or ``camera``, ``calib`` with a layout that reads its own
            calibration, the ``rosbag`` options with another layout or ``rosbag`` without ``topics``.

    Example:
        >>> import tempfile, pathlib, cv2, numpy as np
        >>> root = pathlib.Path(tempfile.mkdtemp())
        >>> for side in ("left", "right"):
        ...     (root / side).mkdir()
        ...     _ = cv2.imwrite(str(root / side / "000000.png"), np.zeros((24, 32), np.uint8))
        >>> _ = (root / "calib.txt").write_text("P0: 40 0 16 0 0 40 12 0 0 0 1 0\\nP1: 40 0 16 -4 0 40 12 0 0 0 1 0\\n")
        >>> rec = open_recording(root, "folders")
        >>> len(rec), rec.image_size, rec.baseline, rec[0][0].shape
        (1, (24, 32), 0.1, torch.Size([1, 1, 24, 32]))
    """
    check_choice(layout, LAYOUTS, "layout")
    check_choice(camera, CAMERAS, "camera")
    if calib is not None and layout not in ("folders", "rosbag"):
        raise ValueRangeError(f"calib: the {layout} layout reads its own calibration files; pass calib only with "
                              "layout='folders' or 'rosbag'")
    if layout == "rosbag":
        if topics is None or len(topics) != 2:
            raise ValueRangeError(f"topics: the rosbag layout needs the (left, right) image topics, got {topics!r}")
        from .rosbag import open_rosbag

        left_info, right_info = info_topics if info_topics is not None else (None, None)
        return open_rosbag(path, topics[0], topics[1], calib=calib, camera=camera, left_info_topic=left_info,
                           right_info_topic=right_info, pair_tolerance=pair_tolerance, frames=frames)
    for name, value in (("topics", topics), ("info_topics", info_topics), ("pair_tolerance", pair_tolerance)):
        if value is not None:
            raise ValueRangeError(f"{name}: only the rosbag layout reads topics; got {value!r} with "
                                  f"layout={layout!r}")
    if frames is not None and not isinstance(frames, slice):
        raise ValueRangeError(f"frames: expected a slice or None, got {type(frames).__name__}")
    path = Path(path)
    if not path.is_dir():
        raise MissingDataError(f"path: no folder {os.fspath(path)!r}")
    parts = _OPENERS[layout](path, calib, camera)
    n = len(parts["left_files"])
    keep = list(range(n))[frames] if frames is not None else list(range(n))
    if not keep:
        raise DataError(f"frames: {frames} selects no frame of the {n} in {path}")
    timestamps, poses = parts.get("timestamps"), parts.get("poses")
    rec = StereoRecording(
        left_files=[parts["left_files"][i] for i in keep], right_files=[parts["right_files"][i] for i in keep],
        K=parts["K"], baseline=parts["baseline"], image_size=parts["image_size"],
        names=[parts["names"][i] for i in keep],
        timestamps=None if timestamps is None else np.asarray(timestamps, dtype=np.float64)[keep],
        poses=None if poses is None else torch.as_tensor(np.asarray(poses)[keep], dtype=torch.float64),
        maps=parts["maps"],
    )
    rec[0]  # read the first pair: an unreadable file or a size that does not fit fails here, not mid-run
    return rec
