"""Stereo calibration files in the formats people have, and the one rectification every unrectified layout uses.

:func:`read_calibration` reads

- **OpenCV** ``FileStorage`` YAML, XML or JSON as written after ``stereoCalibrate``/``stereoRectify``: ``K1``
  (or ``M1``, ``cameraMatrix1``), ``D1`` (``distCoeffs1``), ``K2``, ``D2``, ``R`` (a 3x3 matrix or a rotation
  vector), ``T``, optionally ``R1``, ``R2``, ``P1``, ``P2`` and the image size (``image_size``, ``imageSize`` or
  ``size`` as ``[width, height]``, or ``image_width`` and ``image_height``). OpenCV's stereo sample writes two
  files, ``intrinsics.yml`` and ``extrinsics.yml``: naming either one (or their folder) reads both. Plain JSON
  with nested lists is read too. ``P1``/``P2`` with no distortion (and ``R1``/``R2`` absent or the identity)
  mean rectified images; otherwise the images are raw and the rectification is computed afresh from ``K``,
  ``D``, ``R``, ``T`` (a file's own ``R1``, ``R2``, ``P1``, ``P2`` are then not used).
- **ROS** ``camera_info`` YAML, one file per camera: name the left camera's file (the right one is found beside
  it, ``left`` replaced by ``right`` or a trailing ``0`` by ``1`` in its name) or their folder. The right
  camera's projection carries ``-fx * B`` in ``P[0, 3]``. As in ROS, the files describe the raw images
  (``image_raw``); a pair with no distortion and identity rectification matrices is taken as rectified.
- **KITTI**: the raw recordings' ``calib_cam_to_cam.txt`` (``K_xx``, ``D_xx``, ``R_xx``, ``T_xx``, ``S_rect_xx``,
  ``R_rect_xx``, ``P_rect_xx``) and the odometry/object benchmarks' ``calib.txt`` (``P0`` .. ``P3``); ``camera``
  picks the grey pair (cameras 0, 1) or the colour pair (2, 3). Both describe rectified images.

:func:`rectify_maps` turns a calibration into the remap tables, the rectified left intrinsics and the baseline:
OpenCV's ``stereoRectify`` (zero-disparity principal points, ``alpha = 0`` so that the rectified image has no
invalid border) and ``initUndistortRectifyMap``. Already-rectified calibrations need no remap.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from ..core import DataError, MissingDataError, check_choice

__all__ = ["CAMERAS", "StereoCalibration", "read_calibration", "rectify_maps"]

#: Which camera pair of a multi-camera rig (KITTI) to use: the grey one or the colour one.
CAMERAS = ("grey", "colour")
_KITTI_PAIRS = {"grey": (0, 1), "colour": (2, 3)}
# File names a calibration folder is searched for, in this order.
_CALIB_NAMES = ("calib.yaml", "calib.yml", "calib.json", "calib.xml", "calib.txt", "calib_cam_to_cam.txt")
_OPENCV_KEYS = {
    "K1": ("K1", "M1", "cameraMatrix1"),
    "D1": ("D1", "distCoeffs1"),
    "K2": ("K2", "M2", "cameraMatrix2"),
    "D2": ("D2", "distCoeffs2"),
    "R": ("R",),
    "T": ("T",),
    "R1": ("R1",),
    "R2": ("R2",),
    "P1": ("P1",),
    "P2": ("P2",),
}
# Below this, a rotation is the identity and a distortion coefficient zero (numbers as printed in text files).
_EXACT = 1e-9


@dataclass(frozen=True)
class StereoCalibration:
    """A stereo pair's calibration: the raw cameras and their relative pose, and/or the rectified projections.

    Attributes:
        K1, K2: ``(3, 3)`` intrinsics of the raw left and right cameras, pixels; None for formats that give only
            rectified projections.
        D1, D2: ``(N,)`` distortion coefficients in OpenCV's order ``(k1, k2, p1, p2[, k3, ...])``; zeros where the
            file gives none.
        R, T: ``(3, 3)`` and ``(3,)`` pose of the right camera relative to the left in OpenCV's convention,
            ``X_right = R @ X_left + T``, ``T`` in metres (``T[0] < 0`` for a right camera on the right).
        image_size: ``(H, W)`` pixels; None where the file does not say (loaders take it from the first frame).
        P1, P2: ``(3, 4)`` projection matrices of the rectified left and right cameras, pixels; None when absent.
        rectified: the images this calibration describes are already rectified: ``P1`` and ``P2`` describe them and
            no remap is done.
        source: the file(s) read, named in error messages.

    Example:
        >>> import numpy as np
        >>> K = np.array([[400.0, 0, 160], [0, 400, 120], [0, 0, 1]])
        >>> c = StereoCalibration(K1=K, K2=K, R=np.eye(3), T=np.array([-0.1, 0, 0]), image_size=(240, 320))
        >>> c.rectified, c.D1.shape
        (False, (5,))
    """

    K1: np.ndarray | None = None
    D1: np.ndarray | None = None
    K2: np.ndarray | None = None
    D2: np.ndarray | None = None
    R: np.ndarray | None = None
    T: np.ndarray | None = None
    image_size: tuple[int, int] | None = None
    P1: np.ndarray | None = None
    P2: np.ndarray | None = None
    rectified: bool = False
    source: str = "calibration"

    def __post_init__(self) -> None:
        shapes = {"K1": (3, 3), "K2": (3, 3), "R": (3, 3), "T": (3,), "P1": (3, 4), "P2": (3, 4)}
        for key, shape in shapes.items():
            value = getattr(self, key)
            if value is not None:
                object.__setattr__(self, key, _matrix(value, shape, key, self.source))
        for key in ("D1", "D2"):
            value = getattr(self, key)
            object.__setattr__(self, key, np.zeros(5) if value is None else _matrix(value, None, key, self.source))
        needed = ("P1", "P2") if self.rectified else ("K1", "K2", "R", "T")
        for key in needed:
            if getattr(self, key) is None:
                what = "rectified" if self.rectified else "raw (unrectified)"
                raise DataError(f"calib: {self.source} lacks {key} (needed for {what} images)")
        if self.image_size is not None:
            h, w = (int(v) for v in self.image_size)
            if h < 1 or w < 1:
                raise DataError(f"calib: {self.source}: image size must be positive, found (H, W) = ({h}, {w})")
            object.__setattr__(self, "image_size", (h, w))


def _matrix(value: object, shape: tuple[int, ...] | None, key: str, source: str) -> np.ndarray:
    """A float64 array of ``shape`` (flat when None) from an array, (nested) lists or a ``{rows, cols, data}`` map."""
    if isinstance(value, dict):
        if "data" not in value:
            raise DataError(f"calib: {key} in {source} is a map without a 'data' list")
        value = value["data"]
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"calib: {key} in {source} is not a list of numbers: {value!r:.60}") from None
    if shape is None:
        return arr.reshape(-1).copy()
    if arr.size != int(np.prod(shape)):
        want = "x".join(str(s) for s in shape)
        raise DataError(f"calib: {key} in {source}: expected {want} numbers, found {arr.size}")
    return arr.reshape(shape).copy()


def _node_to_python(node: cv2.FileNode) -> object:
    """An OpenCV ``FileNode`` as nested dicts, lists, floats and strings; ``!!opencv-matrix`` maps as arrays."""
    if node.isMap():
        keys = node.keys()
        if {"rows", "cols", "dt", "data"} <= set(keys):
            return node.mat()
        return {k: _node_to_python(node.getNode(k)) for k in keys}
    if node.isSeq():
        return [_node_to_python(node.at(i)) for i in range(node.size())]
    if node.isString():
        return node.string()
    if node.isInt() or node.isReal():
        return node.real()
    return None


def _read_tree(path: Path) -> dict:
    """The top-level map of a YAML/XML/JSON calibration file."""
    if path.suffix.lower() == ".json":
        try:
            tree = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise DataError(f"calib: {path} does not parse as JSON ({e})") from None
    else:
        try:
            fs = cv2.FileStorage(os.fspath(path), cv2.FILE_STORAGE_READ)
            opened = fs.isOpened()
        except (cv2.error, SystemError):
            opened = False
        if not opened:
            raise DataError(f"calib: {path} does not parse as an OpenCV YAML/XML file")
        tree = _node_to_python(fs.root())
        fs.release()
    if not isinstance(tree, dict):
        raise DataError(f"calib: {path}: expected a map of named fields at the top level, found {type(tree).__name__}")
    return tree


def _read_kitti_txt(path: Path) -> dict[str, np.ndarray]:
    """The numeric fields of a KITTI calibration text file, ``key: v v v`` per line, as flat float64 arrays."""
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise DataError(f"calib: {path} is not a text file (expected KITTI 'key: numbers' lines)") from None
    out = {}
    for line in text.splitlines():
        key, sep, rest = line.partition(":")
        if not sep:
            continue
        try:
            values = [float(v) for v in rest.split()]
        except ValueError:  # e.g. "calib_time: 09-Jan-2012 13:57:47"
            continue
        if values:
            out[key.strip()] = np.array(values)
    if not out:
        raise DataError(f"calib: {path} holds no 'key: numbers' lines (expected a KITTI calibration text file)")
    return out


def _kitti_field(fields: dict[str, np.ndarray], key: str, shape: tuple[int, ...], source: str) -> np.ndarray:
    if key not in fields:
        raise DataError(f"calib: {source} lacks {key} (found {', '.join(sorted(fields))})")
    return _matrix(fields[key], shape, key, source)


def _from_kitti(fields: dict[str, np.ndarray], camera: str, source: str) -> StereoCalibration:
    """A rectified calibration from KITTI raw ``P_rect_xx`` (with the raw cameras) or odometry ``P0``..``P3``."""
    left, right = _KITTI_PAIRS[camera]
    if not any(k.startswith("P_rect_") for k in fields):
        return StereoCalibration(P1=_kitti_field(fields, f"P{left}", (3, 4), source),
                                 P2=_kitti_field(fields, f"P{right}", (3, 4), source), rectified=True, source=source)
    raw = {}
    keys = [f"{k}_{c:02d}" for c in (left, right) for k in ("K", "D", "R", "T")]
    if all(k in fields for k in keys):
        K1, K2 = (_kitti_field(fields, f"K_{c:02d}", (3, 3), source) for c in (left, right))
        R1, R2 = (_kitti_field(fields, f"R_{c:02d}", (3, 3), source) for c in (left, right))
        T1, T2 = (_kitti_field(fields, f"T_{c:02d}", (3,), source) for c in (left, right))
        # R_xx, T_xx map camera 00 into camera xx; the right camera relative to the left follows.
        R = R2 @ R1.T
        raw = dict(K1=K1, K2=K2, D1=fields[f"D_{left:02d}"], D2=fields[f"D_{right:02d}"], R=R, T=T2 - R @ T1)
    size = None
    if f"S_rect_{left:02d}" in fields:
        w, h = _kitti_field(fields, f"S_rect_{left:02d}", (2,), source)
        size = (int(round(h)), int(round(w)))
    return StereoCalibration(**raw, image_size=size, P1=_kitti_field(fields, f"P_rect_{left:02d}", (3, 4), source),
                             P2=_kitti_field(fields, f"P_rect_{right:02d}", (3, 4), source), rectified=True,
                             source=source)


def _field(tree: dict, key: str, source: str, required: bool = True) -> object:
    """The first of ``key``'s OpenCV spellings present in ``tree``."""
    for name in _OPENCV_KEYS[key]:
        if name in tree and tree[name] is not None:
            return tree[name]
    if required:
        raise DataError(f"calib: {source} lacks {' or '.join(_OPENCV_KEYS[key])} (found {', '.join(sorted(tree))})")
    return None


def _image_size(tree: dict, source: str) -> tuple[int, int] | None:
    """``(H, W)`` from ``[width, height]`` under OpenCV's names, or ``image_width``/``image_height``."""
    for name in ("image_size", "imageSize", "size"):
        if name in tree:
            w, h = _matrix(tree[name], (2,), name, source)
            return int(round(h)), int(round(w))
    if "image_width" in tree and "image_height" in tree:
        return int(tree["image_height"]), int(tree["image_width"])
    return None


def _is_identity(R: np.ndarray | None) -> bool:
    return R is None or bool(np.abs(R - np.eye(3)).max() < _EXACT)


def _is_zero(D: np.ndarray | None) -> bool:
    return D is None or bool(np.abs(D).max(initial=0.0) < _EXACT)


def _from_opencv(tree: dict, source: str) -> StereoCalibration:
    P1, P2 = (_field(tree, k, source, required=False) for k in ("P1", "P2"))
    D1, D2 = (_field(tree, k, source, required=False) for k in ("D1", "D2"))
    R1, R2 = (_field(tree, k, source, required=False) for k in ("R1", "R2"))
    size = _image_size(tree, source)
    has_rectified = P1 is not None and P2 is not None
    no_distortion = _is_zero(None if D1 is None else _matrix(D1, None, "D1", source)) and _is_zero(
        None if D2 is None else _matrix(D2, None, "D2", source))
    no_rotation = all(_is_identity(None if r is None else _matrix(r, (3, 3), k, source))
                      for k, r in (("R1", R1), ("R2", R2)))
    if has_rectified and (_field(tree, "K1", source, required=False) is None or (no_distortion and no_rotation)):
        return StereoCalibration(P1=P1, P2=P2, image_size=size, rectified=True, source=source)
    K1, K2 = _field(tree, "K1", source), _field(tree, "K2", source)
    rot = _matrix(_field(tree, "R", source), None, "R", source)
    if rot.size == 3:  # a rotation vector (Rodrigues)
        rot = cv2.Rodrigues(rot.reshape(3, 1))[0]
    return StereoCalibration(K1=K1, D1=D1, K2=K2, D2=D2, R=rot, T=_field(tree, "T", source), image_size=size, P1=P1,
                             P2=P2, source=source)


def _ros_camera(tree: dict, source: str) -> dict:
    """K, D, rectifying rotation, projection and size of one ROS ``camera_info`` file."""
    model = tree.get("distortion_model", "plumb_bob")
    if model not in ("plumb_bob", "rational_polynomial", None):
        raise DataError(f"calib: {source}: distortion_model {model!r} is not supported "
                        "(expected plumb_bob or rational_polynomial)")
    for key in ("camera_matrix", "projection_matrix", "image_width", "image_height"):
        if key not in tree:
            raise DataError(f"calib: {source} lacks {key} (expected a ROS camera_info file)")
    return {
        "K": _matrix(tree["camera_matrix"], (3, 3), "camera_matrix", source),
        "D": _matrix(tree.get("distortion_coefficients", [0.0] * 5), None, "distortion_coefficients", source),
        "R": _matrix(tree.get("rectification_matrix", np.eye(3)), (3, 3), "rectification_matrix", source),
        "P": _matrix(tree["projection_matrix"], (3, 4), "projection_matrix", source),
        "size": (int(tree["image_height"]), int(tree["image_width"])),
    }


def _from_ros(left: dict, right: dict, source: str) -> StereoCalibration:
    a, b = _ros_camera(left, source), _ros_camera(right, source)
    if a["size"] != b["size"]:
        raise DataError(f"calib: {source}: the cameras' image sizes differ, (H, W) {a['size']} and {b['size']}")
    if all(_is_zero(c["D"]) and _is_identity(c["R"]) for c in (a, b)):
        return StereoCalibration(P1=a["P"], P2=b["P"], image_size=a["size"], rectified=True, source=source)
    # P_j = K' [I | t_j] in the common rectified frame and X_rect_j = R_j X_j, so
    # X_right = R_r^T R_l X_left + R_r^T (t_r - t_l).
    t_l, t_r = (np.linalg.solve(c["P"][:, :3], c["P"][:, 3]) for c in (a, b))
    return StereoCalibration(K1=a["K"], D1=a["D"], K2=b["K"], D2=b["D"], R=b["R"].T @ a["R"],
                             T=b["R"].T @ (t_r - t_l), image_size=a["size"], source=source)


def _ros_partner(path: Path) -> Path:
    """The right camera's ``camera_info`` file beside the left one's."""
    name = path.name
    tries = [name.replace(a, b) for a, b in (("left", "right"), ("Left", "Right"), ("LEFT", "RIGHT")) if a in name]
    stem = path.stem
    if stem.endswith("0"):
        tries.append(stem[:-1] + "1" + path.suffix)
    for t in tries:
        if t != name and (path.parent / t).is_file():
            return path.parent / t
    raise MissingDataError(f"calib: {path} is one camera's ROS camera_info; expected the right camera's beside it "
                           f"(tried {', '.join(tries) or 'a name with left -> right or 0 -> 1'})")


def _opencv_partner(path: Path) -> Path | None:
    """OpenCV's stereo sample writes ``intrinsics.yml`` and ``extrinsics.yml``: the other one of the two."""
    other = {"intrinsics": "extrinsics", "extrinsics": "intrinsics"}.get(path.stem.lower())
    if other is None:
        return None
    for suffix in (path.suffix, ".yml", ".yaml", ".xml", ".json"):
        if (path.parent / (other + suffix)).is_file():
            return path.parent / (other + suffix)
    return None


def _find_in_folder(folder: Path) -> Path:
    """The calibration file of a folder: calib.*, a ROS left camera_info, or OpenCV's intrinsics.yml."""
    for name in _CALIB_NAMES:
        if (folder / name).is_file():
            return folder / name
    for f in sorted(folder.glob("*")):
        if f.suffix.lower() in (".yaml", ".yml") and "left" in f.stem.lower():
            return f
    for f in sorted(folder.glob("intrinsics.*")):
        return f
    raise MissingDataError(f"calib: no calibration file in {folder} (looked for {', '.join(_CALIB_NAMES)}, a ROS "
                           "left/right camera_info pair, OpenCV's intrinsics.yml + extrinsics.yml)")


def read_calibration(path: str | os.PathLike, camera: str = "grey") -> StereoCalibration:
    """Read a stereo calibration file (OpenCV YAML/XML/JSON, ROS ``camera_info`` pair, KITTI text).

    Args:
        path: the file, or a folder holding one (``calib.yaml|yml|json|xml|txt``, ``calib_cam_to_cam.txt``, a ROS
            ``left*.yaml`` with its right partner, or OpenCV's ``intrinsics.yml``/``extrinsics.yml``).
        camera: ``"grey"`` or ``"colour"``: which pair of a KITTI calibration to take (cameras 0/1 or 2/3); other
            formats describe one pair and ignore it. Default grey, KITTI's reference cameras.

    Returns:
        :class:`StereoCalibration`, ``rectified`` where the file describes rectified images.

    Raises:
        MissingDataError: no file at ``path``, none in the folder, or a ROS file without its partner.
        DataError: the file does not parse, or lacks a field the format needs.
        ValueRangeError: ``camera`` is not one of :data:`CAMERAS`.

    Example:
        >>> import tempfile, pathlib
        >>> f = pathlib.Path(tempfile.mkdtemp()) / "calib.txt"
        >>> _ = f.write_text("P0: 700 0 600 0 0 700 180 0 0 0 1 0\\nP1: 700 0 600 -378 0 700 180 0 0 0 1 0\\n")
        >>> c = read_calibration(f)
        >>> c.rectified, float(c.P2[0, 3])
        (True, -378.0)
    """
    check_choice(camera, CAMERAS, "camera")
    path = Path(path)
    if path.is_dir():
        path = _find_in_folder(path)
    if not path.is_file():
        raise MissingDataError(f"calib: no calibration file at {os.fspath(path)!r}")
    if path.suffix.lower() == ".txt":
        return _from_kitti(_read_kitti_txt(path), camera, os.fspath(path))
    tree = _read_tree(path)
    if "camera_matrix" in tree or "projection_matrix" in tree:
        partner = _ros_partner(path)
        return _from_ros(tree, _read_tree(partner), f"{path} + {partner.name}")
    partner = _opencv_partner(path)
    if partner is not None:
        return _from_opencv({**_read_tree(partner), **tree}, f"{path} + {partner.name}")
    return _from_opencv(tree, os.fspath(path))


def _stereo_rectify(calib: StereoCalibration) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rectifying rotations ``R1, R2`` (``X_rect = R_i X_cam_i``) and projections ``P1, P2`` of a calibration."""
    if calib.rectified:
        return np.eye(3), np.eye(3), calib.P1, calib.P2
    if calib.image_size is None:
        raise DataError(f"calib: {calib.source} gives no image size, which rectification needs")
    h, w = calib.image_size
    R1, R2, P1, P2, *_ = cv2.stereoRectify(calib.K1, calib.D1, calib.K2, calib.D2, (w, h), calib.R,
                                           calib.T.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
    if abs(P2[1, 3]) > abs(P2[0, 3]):
        raise DataError(f"calib: {calib.source}: the cameras are stacked vertically (T = {calib.T.tolist()}); "
                        "expected a horizontal pair")
    return R1, R2, P1, P2


def rectify_maps(calib: StereoCalibration) -> tuple[
        tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None, torch.Tensor, float]:
    """Remap tables that rectify both cameras, with the rectified left intrinsics and the baseline.

    Unrectified calibrations go through ``cv2.stereoRectify`` (``CALIB_ZERO_DISPARITY``: both principal points
    equal, so disparity is ``x_left - x_right``; ``alpha = 0``: the output shows valid pixels only, no black
    border for the matcher to trip on) and ``cv2.initUndistortRectifyMap``. Rectified ones need no remap:
    ``K`` and the baseline come from ``P1``, ``P2``.

    Args:
        calib: the pair's calibration; unrectified ones need ``image_size``.

    Returns:
        ``(maps, K, baseline)``: ``maps`` is ``((map_x, map_y) of the left camera, (map_x, map_y) of the right)``,
        float32 ``(H, W)`` arrays for ``cv2.remap``, or None for rectified input; ``K`` the ``(3, 3)`` float64
        intrinsics of the rectified left camera, pixels; ``baseline`` metres, ``(P1[0, 3] - P2[0, 3]) / fx``.

    Raises:
        DataError: no image size, a vertical or left-right swapped pair (baseline not positive), or rectified
            projections whose intrinsics differ.

    Example:
        >>> import numpy as np
        >>> K = np.array([[400.0, 0, 160], [0, 400, 120], [0, 0, 1]])
        >>> c = StereoCalibration(K1=K, K2=K, R=np.eye(3), T=np.array([-0.1, 0, 0]), image_size=(240, 320))
        >>> maps, K_rect, baseline = rectify_maps(c)
        >>> maps[0][0].shape, K_rect.shape, round(baseline, 6)
        ((240, 320), torch.Size([3, 3]), 0.1)
    """
    R1, R2, P1, P2 = _stereo_rectify(calib)
    if calib.rectified and np.abs(P1[:, :3] - P2[:, :3]).max() > 1e-6 * np.abs(P1[:, :3]).max():
        raise DataError(f"calib: {calib.source}: the rectified projections P1 and P2 have different intrinsics")
    fx = float(P1[0, 0])
    baseline = (float(P1[0, 3]) - float(P2[0, 3])) / fx
    if not baseline > 0:
        raise DataError(f"calib: {calib.source}: the right camera is not right of the left (baseline "
                        f"{baseline:.6g} m); expected P2[0, 3] < P1[0, 3] or T[0] < 0 - are left and right swapped?")
    K = torch.as_tensor(np.ascontiguousarray(P1[:, :3]), dtype=torch.float64)
    if calib.rectified:
        return None, K, baseline
    h, w = calib.image_size
    maps = tuple(cv2.initUndistortRectifyMap(Kc, Dc, Rc, Pc, (w, h), cv2.CV_32FC1)
                 for Kc, Dc, Rc, Pc in ((calib.K1, calib.D1, R1, P1), (calib.K2, calib.D2, R2, P2)))
    return maps, K, baseline


def _remap(image: np.ndarray, map_xy: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """One camera's image through its rectification table (bilinear, edge pixels repeated), kept in [0, 1]."""
    out = cv2.remap(image, map_xy[0], map_xy[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.clip(out, 0.0, 1.0, out=out)
