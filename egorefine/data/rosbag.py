"""Stereo recordings stored in ROS bags (ROS 1 ``.bag`` files, ROS 2 bag folders), read with ``rosbags``.

:func:`open_rosbag` (the ``rosbag`` layout of :func:`egorefine.data.open_recording`) reads two image topics of a
bag and returns a :class:`RosbagRecording`: the same lazily read, rectified grey ``(left, right)`` pairs as the
other layouts give, decoded from the bag's messages when indexed. No ROS installation is needed: the pure-Python
`rosbags <https://gitlab.com/ternaris/rosbags>`_ library (``pip install egorefine[rosbag]``) reads ROS 1 bags
(version 2.0) and ROS 2 bags (a folder with ``metadata.yaml`` and ``sqlite3`` ``.db3`` or ``.mcap`` storage).

What is read and what is assumed:

- **Images**: ``sensor_msgs/msg/Image`` in the encodings of :data:`ROSBAG_ENCODINGS` (grey, BGR, RGB, with or
  without alpha, 8 or 16 bits; big-endian 16-bit data and padded rows too), or ``sensor_msgs/msg/CompressedImage``
  decoded with OpenCV's ``imdecode`` (PNG, JPEG, ...; colour read as BGR, as ``image_transport`` writes it).
  Colour turns grey with OpenCV's luma weights and integers are scaled to [0, 1] by their type's maximum, as
  :func:`egorefine.data.read_grey` does for files.
- **Pairs**: left and right messages are paired by their header stamps: each left frame with the right frame
  nearest in time, where each is the other's nearest and they lie within the tolerance (default: 0.005 s, or half the
  median interval between left frames where that is shorter, so that a dropped frame never pairs with its
  neighbour's partner). Frames without a partner are skipped and counted in :attr:`RosbagRecording.info`.
  The recording's time stamps are the left header stamps, in seconds; frames are named by the left stamp in
  nanoseconds (EuRoC's file names).
- **Calibration**: the first ``sensor_msgs/msg/CameraInfo`` message of each camera's info topic, by default the
  image topic's sibling (``/cam0/image_raw`` -> ``/cam0/camera_info``; ``/cam0/image_raw/compressed`` too). The
  calibration is taken to hold for the whole bag. As in ROS, a camera_info describes the raw images: its ``K`` and
  ``D`` the raw camera, ``R`` the rectifying rotation and ``P`` the rectified projection, the right camera's
  holding ``-fx * baseline`` in ``P[0, 3]``. A pair with no distortion and identity ``R`` is taken as rectified
  (``K`` and the baseline from ``P``, no remap); so are topics named ``image_rect*`` (ROS's ``image_proc``
  output, which ``P`` describes whatever ``D`` says). Otherwise the raw cameras' relative pose is recovered from
  ``R`` and ``P`` (``X_right = R_r^T R_l X_left + R_r^T (t_r - t_l)`` with ``P = K' [I | t]``) and the pair is
  rectified afresh by :func:`egorefine.data.rectify_maps`, as every unrectified layout is (OpenCV's
  ``stereoRectify`` with ``alpha = 0``, so ``K`` and the baseline are the re-rectified ones). Binning and a region
  of interest are not supported. ``calib`` replaces the camera_info topics with a calibration file in any format
  :func:`egorefine.data.read_calibration` reads.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from ..core import DataError, MissingDataError, MissingExtraError, ValueRangeError, require_extra
from .calib import StereoCalibration, _from_ros, read_calibration, rectify_maps
from .folder import _grey
from .recording import StereoRecording, _fit_calibration

__all__ = ["ROSBAG_ENCODINGS", "RosbagNotInstalledError", "RosbagRecording", "open_rosbag"]

_IMAGE = "sensor_msgs/msg/Image"
_COMPRESSED = "sensor_msgs/msg/CompressedImage"
_CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
# encoding -> (channels, dtype, OpenCV conversion to grey or None for one channel)
_ENCODINGS = {
    "mono8": (1, np.uint8, None), "8UC1": (1, np.uint8, None),
    "mono16": (1, np.uint16, None), "16UC1": (1, np.uint16, None),
    "bgr8": (3, np.uint8, cv2.COLOR_BGR2GRAY), "rgb8": (3, np.uint8, cv2.COLOR_RGB2GRAY),
    "bgra8": (4, np.uint8, cv2.COLOR_BGRA2GRAY), "rgba8": (4, np.uint8, cv2.COLOR_RGBA2GRAY),
    "bgr16": (3, np.uint16, cv2.COLOR_BGR2GRAY), "rgb16": (3, np.uint16, cv2.COLOR_RGB2GRAY),
    "bgra16": (4, np.uint16, cv2.COLOR_BGRA2GRAY), "rgba16": (4, np.uint16, cv2.COLOR_RGBA2GRAY),
}
#: The ``sensor_msgs/msg/Image`` encodings :func:`open_rosbag` decodes (CompressedImage: whatever OpenCV decodes).
ROSBAG_ENCODINGS = tuple(_ENCODINGS)
# Default pairing tolerance: stereo cameras triggered together stamp within a few milliseconds of each other.
_DEFAULT_TOLERANCE_S = 0.005
# image_transport's suffixes of a transported topic: /cam0/image_raw/compressed is /cam0/image_raw compressed.
_TRANSPORTS = ("compressed", "compressedDepth", "theora", "zstd")


class RosbagNotInstalledError(MissingExtraError):
    """``rosbags``, the optional dependency that reads ROS bags, is not installed.

    Example:
        >>> issubclass(RosbagNotInstalledError, ImportError)  # ``except ImportError`` still catches it
        True
    """


def _require_rosbags() -> Any:
    """The ``rosbags.highlevel`` module, or a one-line :class:`RosbagNotInstalledError` naming the extra."""
    return require_extra("rosbags.highlevel", "rosbag", "rosbags (which the rosbag layout reads bags with)",
                         RosbagNotInstalledError)


@dataclass(frozen=True)
class _MessageRef:
    """Where one image message sits in a bag: its connection, log time (ns) and rank among the messages of that
    connection at that log time; ``stamp_ns`` is its header stamp."""

    topic: str
    connection: Any
    log_ns: int
    rank: int
    stamp_ns: int

    def __str__(self) -> str:
        return f"the {self.topic} message stamped {self.stamp_ns / 1e9:.9f} s"


def _stamp_ns(msg: Any) -> int:
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _decode(msg: Any, msgtype: str, where: object) -> np.ndarray:
    """An Image or CompressedImage message as ``(H, W)`` float32 grey in [0, 1]."""
    data = np.asarray(msg.data, dtype=np.uint8)
    if msgtype == _COMPRESSED:
        raw = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        if raw is None:
            raise DataError(f"path: {where} (format {msg.format!r}) is not an image OpenCV can decode")
        return _grey(raw, None)
    if msg.encoding not in _ENCODINGS:
        raise DataError(f"path: {where} has encoding {msg.encoding!r}, which egorefine cannot read (readable: "
                        f"{', '.join(ROSBAG_ENCODINGS)})")
    channels, dtype, code = _ENCODINGS[msg.encoding]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * channels * np.dtype(dtype).itemsize
    if h < 1 or w < 1 or step < row or data.size < h * step:
        raise DataError(f"path: {where}: {data.size} bytes with step {step} do not hold a {w}x{h} (W x H) "
                        f"{msg.encoding} image")
    rows = np.ascontiguousarray(data[:h * step].reshape(h, step)[:, :row])  # rows may be padded to `step`
    order = ">" if msg.is_bigendian else "<"
    raw = rows.view(np.dtype(dtype).newbyteorder(order)).reshape(h, w, channels).astype(dtype)
    return _grey(raw[..., 0] if channels == 1 else raw, code)


def _bag_errors() -> tuple[type[Exception], ...]:
    """What ``rosbags`` raises for a bag it cannot read (a damaged chunk, a message that does not deserialise)."""
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as ReaderError1
    from rosbags.rosbag2 import ReaderError as ReaderError2

    return AnyReaderError, ReaderError1, ReaderError2


def _fetch(reader: Any, ref: _MessageRef) -> np.ndarray:
    """One image message, fetched through the bag's index by its log time, decoded to ``(H, W)`` float32 grey."""
    try:
        window = reader.messages(connections=[ref.connection], start=ref.log_ns, stop=ref.log_ns + 1)
        for k, (conn, _, raw) in enumerate(window):
            if k == ref.rank:
                msg = reader.deserialize(raw, conn.msgtype)
                break
        else:
            raise MissingDataError(f"path: {ref} is no longer in the bag")
    except _bag_errors() as err:
        raise DataError(f"path: {ref} does not read ({' '.join(str(err).split())})") from None
    return _decode(msg, conn.msgtype, ref)


class RosbagRecording(StereoRecording):
    """A stereo recording in a ROS bag, read lazily: each pair's messages are fetched, decoded and rectified when
    indexed.

    Build one with :func:`open_rosbag` (or :func:`egorefine.data.open_recording` with ``layout="rosbag"``). It
    behaves as :class:`~egorefine.data.StereoRecording` does (indexing, iteration, ``K``, ``baseline``,
    ``image_size``, ``names``, ``timestamps``; ``poses`` is None: a bag's pose topics are not read), with
    ``left_files`` and ``right_files`` holding references to the bag's messages instead of files. The bag stays
    open while the recording is used; :meth:`close` (or a ``with`` block) closes it, and indexing reopens it.

    Attributes:
        path: the bag (a ROS 1 ``.bag`` file or a ROS 2 bag folder).
        topics: ``(left, right)`` image topics.
        info: what the layout read, for a report (``run.json`` keeps it): bag, topics, calibration source,
            pairing tolerance (s), messages per topic, pairs, unpaired left and right frames.
        notes: human-readable remarks for a log, e.g. frames skipped for want of a partner; empty when none.

    Example:
        >>> import tempfile, pathlib
        >>> from egorefine.data import render_sequence
        >>> seq = render_sequence(num_frames=2, height=24, width=32)
        >>> bag = _write_example_bag(pathlib.Path(tempfile.mkdtemp()) / "rig.bag", seq)
        >>> with open_rosbag(bag, "/cam0/image_raw", "/cam1/image_raw") as rec:
        ...     len(rec), rec.image_size, round(rec.baseline, 6), rec.rectified_input, rec[0][0].shape
        (2, (24, 32), 0.08, True, torch.Size([1, 1, 24, 32]))
    """

    def __init__(self, path: Path, reader: Any, topics: tuple[str, str], left: list[_MessageRef],
                 right: list[_MessageRef], K: torch.Tensor, baseline: float, image_size: tuple[int, int],
                 maps: tuple | None, info: dict, notes: tuple[str, ...] = ()) -> None:
        stamps = np.array([m.stamp_ns for m in left], dtype=np.int64)
        names = [str(s) for s in stamps]
        if len(set(names)) != len(names):  # repeated stamps: frame numbers keep the output file names apart
            names = [f"{i:06d}" for i in range(len(left))]
        super().__init__(left, right, K, baseline, image_size, names, timestamps=stamps / 1e9, maps=maps)
        self.path = Path(path)
        self.topics = tuple(topics)
        self.info = info
        self.notes = tuple(notes)
        self._reader = reader
        self._connections: dict | None = None  # a reopened bag's connections by (topic, id)

    def __repr__(self) -> str:
        return super().__repr__().replace("StereoRecording(", f"RosbagRecording({self.path.name}, ", 1)

    def close(self) -> None:
        """Close the bag (indexing opens it again)."""
        reader, self._reader = self._reader, None
        if reader is not None and reader.stack is not None:
            reader.close()

    def __enter__(self) -> RosbagRecording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _image(self, ref: _MessageRef) -> np.ndarray:
        if self._reader is None:
            self._reader = _open_reader(self.path)
            # The reopened bag has new connection objects: each reference's is looked up by topic and id.
            self._connections = {(c.topic, c.id): c for c in self._reader.connections}
        if self._connections is not None:
            ref = replace(ref, connection=self._connections.get((ref.topic, ref.connection.id), ref.connection))
        return _fetch(self._reader, ref)

    def _read(self, ref: _MessageRef, camera: int) -> torch.Tensor:
        return self._rectified(self._image(ref), ref, camera)


def _bag_path(path: Path) -> Path:
    """The bag a path names: a ``.bag`` file, a ROS 2 bag folder, or a ROS 2 bag's storage file (its folder)."""
    if not path.exists():
        raise MissingDataError(f"path: no ROS bag at {os.fspath(path)!r}")
    if path.is_file() and path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    if path.is_file() and path.name == "metadata.yaml":
        return path.parent
    return path


def _open_reader(path: Path) -> Any:
    """An open ``rosbags`` ``AnyReader`` on ``path``; a one-line :class:`DataError` when it is not a bag."""
    highlevel = _require_rosbags()
    from rosbags.typesys import Stores, get_typestore

    expected = "expected a ROS 1 .bag file or a ROS 2 bag folder with metadata.yaml"
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise DataError(f"path: {path} is not a ROS bag: a folder without metadata.yaml ({expected})")
    if path.is_file() and path.suffix != ".bag":
        raise DataError(f"path: {path} is not a ROS bag ({expected})")
    try:
        # Bags written without message definitions (early ROS 2) fall back to the latest ROS 2 types.
        reader = highlevel.AnyReader([path], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except (highlevel.AnyReaderError, ValueError, KeyError, OSError) as err:
        reason = " ".join(str(err).split()) or type(err).__name__
        raise DataError(f"path: {path} is not a ROS bag that rosbags can read ({reason}); {expected}") from None
    return reader


def _image_topics(reader: Any) -> dict[str, Any]:
    return {name: info for name, info in reader.topics.items() if info.msgtype in (_IMAGE, _COMPRESSED)}


def _check_topic(reader: Any, topic: str, arg: str, path: Path) -> None:
    topics = reader.topics
    if topic not in topics:
        images = sorted(_image_topics(reader))
        raise MissingDataError(f"{arg}: no topic {topic!r} in {path}; its image topics: "
                               f"{', '.join(images) if images else 'none'}")
    if topics[topic].msgtype not in (_IMAGE, _COMPRESSED):
        raise DataError(f"{arg}: {topic} in {path} carries {topics[topic].msgtype}; expected {_IMAGE} or "
                        f"{_COMPRESSED}")


def _index(reader: Any, topics: tuple[str, ...]) -> list[tuple[list[_MessageRef], dict[str, int]]]:
    """Every message of each image topic as a :class:`_MessageRef`, sorted by header stamp, with the count of each
    encoding (Image) or format (CompressedImage) seen. One pass over the topics; no image data is kept."""
    out = {topic: ([], {}) for topic in topics}
    ranks: dict[tuple[str, int, int], int] = {}
    conns = [c for topic in topics for c in reader.topics[topic].connections]
    messages = reader.messages(connections=conns)
    while True:
        try:
            conn, log_ns, raw = next(messages)
            msg = reader.deserialize(raw, conn.msgtype)
        except StopIteration:
            break
        except _bag_errors() as err:
            raise DataError(f"path: {', '.join(topics)} do not read ({' '.join(str(err).split())})") from None
        key = (conn.topic, conn.id, log_ns)
        ranks[key] = ranks.get(key, -1) + 1
        refs, kinds = out[conn.topic]
        refs.append(_MessageRef(conn.topic, conn, int(log_ns), ranks[key], _stamp_ns(msg)))
        kind = msg.format if conn.msgtype == _COMPRESSED else msg.encoding
        kinds[kind] = kinds.get(kind, 0) + 1
    for refs, _ in out.values():
        refs.sort(key=lambda r: r.stamp_ns)
    return [out[topic] for topic in topics]


def _pair(left: np.ndarray, right: np.ndarray, tolerance_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(i, j)`` of sorted stamps ``left[i]``, ``right[j]`` that are each other's nearest and lie within
    ``tolerance_ns`` (mutual nearest neighbours: one-to-one, and a dropped frame leaves its partner unpaired)."""

    def nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # index of b nearest each a; b sorted, not empty
        j = np.searchsorted(b, a)
        lo, hi = np.clip(j - 1, 0, len(b) - 1), np.clip(j, 0, len(b) - 1)
        return np.where(np.abs(b[lo] - a) <= np.abs(b[hi] - a), lo, hi)

    if not len(left) or not len(right):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    j = nearest(left, right)
    i = nearest(right, left)
    ok = (i[j] == np.arange(len(left))) & (np.abs(right[j] - left) <= tolerance_ns)
    return np.nonzero(ok)[0], j[ok]


def _info_topic(reader: Any, image_topic: str, given: str | None, arg: str, path: Path) -> str | None:
    """The camera_info topic of an image topic: ``given``, else the sibling ``camera_info`` (None if absent)."""
    topics = reader.topics
    if given is not None:
        if given not in topics:
            infos = sorted(n for n, i in topics.items() if i.msgtype == _CAMERA_INFO)
            raise MissingDataError(f"{arg}: no topic {given!r} in {path}; its CameraInfo topics: "
                                   f"{', '.join(infos) if infos else 'none'}")
        if topics[given].msgtype != _CAMERA_INFO:
            raise DataError(f"{arg}: {given} in {path} carries {topics[given].msgtype}; expected {_CAMERA_INFO}")
        return given
    parts = image_topic.rstrip("/").split("/")
    candidates = ["/".join(parts[:-1] + ["camera_info"])]
    if len(parts) > 2 and parts[-1] in _TRANSPORTS:  # /cam0/image_raw/compressed -> /cam0/camera_info
        candidates.append("/".join(parts[:-2] + ["camera_info"]))
    for name in candidates:
        if name in topics and topics[name].msgtype == _CAMERA_INFO:
            return name
    return None


def _field(msg: Any, name: str) -> np.ndarray:
    """A CameraInfo matrix field: lower case in ROS 2 (``k``), upper case in ROS 1 (``K``)."""
    return np.asarray(getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper()), np.float64)


def _first_camera_info(reader: Any, topic: str, path: Path) -> dict:
    """The first CameraInfo message of ``topic`` as a ROS camera_info YAML tree (what calib.py reads)."""
    for conn, _, raw in reader.messages(connections=reader.topics[topic].connections):
        msg = reader.deserialize(raw, conn.msgtype)
        break
    else:
        raise MissingDataError(f"calib: {topic} in {path} holds no message")
    K = _field(msg, "k")
    if K.size != 9 or not np.abs(K).max(initial=0.0) > 0:
        raise DataError(f"calib: {topic} in {path} is not calibrated (K is all zeros); pass --calib FILE")
    if max(int(msg.binning_x), int(msg.binning_y)) > 1 or int(msg.roi.width) or int(msg.roi.height):
        raise DataError(f"calib: {topic} in {path} sets binning or a region of interest, which egorefine does not "
                        "apply; pass --calib FILE for the images as recorded")
    D = _field(msg, "d")
    return {"camera_matrix": K, "distortion_coefficients": D if D.size else np.zeros(5),
            "rectification_matrix": _field(msg, "r"), "projection_matrix": _field(msg, "p"),
            "image_width": int(msg.width), "image_height": int(msg.height),
            "distortion_model": msg.distortion_model or "plumb_bob"}


def _topic_calibration(reader: Any, path: Path, topics: tuple[str, str], info_topics: tuple[str | None, str | None]
                       ) -> tuple[StereoCalibration, str]:
    found = [_info_topic(reader, t, g, a, path)
             for t, g, a in zip(topics, info_topics, ("left_info_topic", "right_info_topic"), strict=True)]
    if None in found:
        missing = [t for t, f in zip(topics, found, strict=True) if f is None]
        infos = sorted(n for n, i in reader.topics.items() if i.msgtype == _CAMERA_INFO)
        raise MissingDataError(f"calib: no camera_info topic beside {', '.join(missing)} in {path} (its CameraInfo "
                               f"topics: {', '.join(infos) if infos else 'none'}); name them with "
                               "--left-info-topic/--right-info-topic or pass --calib FILE")
    trees = [_first_camera_info(reader, t, path) for t in found]
    source = f"{path} {found[0]} + {found[1]}"
    if all(t.rstrip("/").split("/")[-1].startswith("image_rect") or
           t.rstrip("/").split("/")[-2:-1] == ["image_rect"] for t in topics):
        # image_proc's rectified output: P describes it, D and R the raw images it came from.
        size = (trees[0]["image_height"], trees[0]["image_width"])
        return StereoCalibration(P1=trees[0]["projection_matrix"], P2=trees[1]["projection_matrix"],
                                 image_size=size, rectified=True, source=source), " + ".join(found)
    return _from_ros(trees[0], trees[1], source), " + ".join(found)


def open_rosbag(path: str | os.PathLike, left_topic: str, right_topic: str, *,
                calib: str | os.PathLike | None = None, camera: str = "grey", left_info_topic: str | None = None,
                right_info_topic: str | None = None, pair_tolerance: float | None = None,
                frames: slice | None = None) -> RosbagRecording:
    """Open the stereo pair of two image topics of a ROS 1 or ROS 2 bag, rectified where it is not.

    The bag is read once now to index both topics (header stamps and where each message sits, no image data
    kept), pair the frames and read the calibration; the first pair is decoded too (to catch a bad message early),
    the others when indexed. See the module's description for the message types, the pairing and the calibration.

    Args:
        path: a ROS 1 ``.bag`` file, or a ROS 2 bag folder (``metadata.yaml`` with ``.db3`` or ``.mcap`` storage;
            naming its storage file or ``metadata.yaml`` opens the folder).
        left_topic, right_topic: the cameras' ``sensor_msgs/msg/Image`` or ``CompressedImage`` topics, e.g.
            ``"/cam0/image_raw"`` and ``"/cam1/image_raw"``.
        calib: a calibration file (or folder) in a format :func:`egorefine.data.read_calibration` reads, used
            instead of the bag's CameraInfo topics; default None: the CameraInfo topics.
        camera: ``"grey"`` or ``"colour"``: the pair of a KITTI ``calib`` file; others ignore it. Default grey.
        left_info_topic, right_info_topic: the cameras' ``sensor_msgs/msg/CameraInfo`` topics; default None: the
            image topic's sibling ``camera_info``.
        pair_tolerance: seconds, >= 0: the largest header-stamp difference of a left and a right frame that pair;
            default None: 0.005 s, or half the median interval between left frames where that is shorter.
        frames: which of the paired frames to keep, e.g. ``slice(100, 200)``; default all.

    Returns:
        :class:`RosbagRecording`, open on the bag.

    Raises:
        RosbagNotInstalledError: ``rosbags`` is not installed (``pip install egorefine[rosbag]``).
        MissingDataError: no bag at ``path``; a topic that is not in the bag (the message lists its image topics);
            no CameraInfo topics and no ``calib``.
        DataError: ``path`` is not a bag; a topic of another message type; image encodings egorefine cannot read
            (named); no frame pairs within the tolerance; an uncalibrated camera_info; a calibration whose image
            size differs from the frames'; ``frames`` selects none.
        ValueRangeError: a negative ``pair_tolerance``, the same topic twice, ``calib`` with info topics.

    Example:
        >>> import tempfile, pathlib
        >>> from egorefine.data import render_sequence
        >>> seq = render_sequence(num_frames=3, height=24, width=32)
        >>> bag = _write_example_bag(pathlib.Path(tempfile.mkdtemp()) / "rig.bag", seq)
        >>> rec = open_rosbag(bag, "/cam0/image_raw", "/cam1/image_raw")
        >>> len(rec), rec.timestamps.tolist(), rec.info["unpaired_left"]
        (3, [0.0, 0.1, 0.2], 0)
        >>> bool(torch.equal(rec[1][0], seq.left[1:2]))  # the rendered 8-bit frame, back from the bag
        True
        >>> rec.close()
    """
    if pair_tolerance is not None and not pair_tolerance >= 0:
        raise ValueRangeError(f"pair_tolerance: expected >= 0 seconds, got {pair_tolerance}")
    if left_topic == right_topic:
        raise ValueRangeError(f"right_topic: the same topic as left_topic ({left_topic!r}); expected the other "
                              "camera's")
    if calib is not None and (left_info_topic is not None or right_info_topic is not None):
        raise ValueRangeError("calib: pass a calibration file or camera_info topics, not both")
    if frames is not None and not isinstance(frames, slice):
        raise ValueRangeError(f"frames: expected a slice or None, got {type(frames).__name__}")
    _require_rosbags()
    path = _bag_path(Path(path))
    reader = _open_reader(path)
    try:
        topics = (left_topic, right_topic)
        for topic, arg in zip(topics, ("left_topic", "right_topic"), strict=True):
            _check_topic(reader, topic, arg, path)
        (left, left_kinds), (right, right_kinds) = _index(reader, topics)
        for topic, refs, kinds in ((left_topic, left, left_kinds), (right_topic, right, right_kinds)):
            if not refs:
                raise DataError(f"path: {topic} in {path} holds no message")
            if reader.topics[topic].msgtype == _IMAGE and set(kinds) - set(_ENCODINGS):
                bad = sorted(set(kinds) - set(_ENCODINGS))
                raise DataError(f"path: {topic} in {path} has image encodings egorefine cannot read: "
                                f"{', '.join(bad)} (readable: {', '.join(ROSBAG_ENCODINGS)})")
        if calib is not None:
            cal = read_calibration(calib, camera)
            cal_source = os.fspath(calib)
        else:
            cal, cal_source = _topic_calibration(reader, path, topics, (left_info_topic, right_info_topic))

        left_ns = np.array([r.stamp_ns for r in left], dtype=np.int64)
        right_ns = np.array([r.stamp_ns for r in right], dtype=np.int64)
        if pair_tolerance is None:
            tolerance = _DEFAULT_TOLERANCE_S
            if len(left_ns) > 1 and np.median(np.diff(left_ns)) > 0:
                tolerance = min(tolerance, 0.5 * float(np.median(np.diff(left_ns))) / 1e9)
        else:
            tolerance = float(pair_tolerance)
        li, ri = _pair(left_ns, right_ns, int(round(tolerance * 1e9)))
        if not len(li):
            gap = np.abs(right_ns[np.clip(np.searchsorted(right_ns, left_ns), 0, len(right_ns) - 1)] - left_ns)
            raise DataError(f"path: no left/right frames of {path} pair within {tolerance:.6g} s (the median stamp "
                            f"difference is {np.median(gap) / 1e9:.6g} s); a larger pair_tolerance "
                            "(--pair-tolerance) may pair them")
        n = len(li)
        keep = list(range(n))[frames] if frames is not None else list(range(n))
        if not keep:
            raise DataError(f"frames: {frames} selects no frame of the {n} pairs in {path}")
        unpaired = (len(left) - n, len(right) - n)
        notes = ()
        if any(unpaired):
            notes = (f"{unpaired[0]} left and {unpaired[1]} right frames of {path.name} have no partner within "
                     f"{tolerance:.6g} s and are skipped ({n} pairs)",)

        first = left[li[keep[0]]]
        size = _fetch(reader, first).shape
        cal = _fit_calibration(cal, size, first)
        maps, K, baseline = rectify_maps(cal)
        info = {"layout": "rosbag", "bag": os.fspath(path), "left_topic": left_topic, "right_topic": right_topic,
                "calibration": cal_source, "pair_tolerance_s": tolerance,
                "messages": {left_topic: len(left), right_topic: len(right)},
                "encodings": {left_topic: left_kinds, right_topic: right_kinds},
                "pairs": n, "unpaired_left": unpaired[0], "unpaired_right": unpaired[1]}
        rec = RosbagRecording(path, reader, topics, [left[li[k]] for k in keep], [right[ri[k]] for k in keep], K,
                              baseline, size, maps, info, notes)
        rec[0]  # decode the first pair: a message that does not decode fails here, not mid-run
    except BaseException:
        if reader.stack is not None:
            reader.close()
        raise
    return rec


def _write_example_bag(path: Path, seq: Any, dt: float = 0.1) -> Path:
    """A ROS 1 bag of a rendered sequence (mono8 images, camera_info with the rig), for the docstrings' examples."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    types = store.types
    H, W = seq.left.shape[-2:]
    K = seq.K.double().numpy()
    with Writer(path) as writer:
        conns = {name: writer.add_connection(name, t, typestore=store) for name, t in (
            ("/cam0/image_raw", _IMAGE), ("/cam1/image_raw", _IMAGE), ("/cam0/camera_info", _CAMERA_INFO),
            ("/cam1/camera_info", _CAMERA_INFO))}
        for t in range(len(seq.left)):
            ns = int(round(t * dt * 1e9))
            header = types["std_msgs/msg/Header"](seq=t, stamp=types["builtin_interfaces/msg/Time"](
                sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id="cam")
            for cam, img in ((0, seq.left[t]), (1, seq.right[t])):
                pixels = (img[0].numpy() * 255).round().astype(np.uint8)
                msg = types[_IMAGE](header=header, height=H, width=W, encoding="mono8", is_bigendian=0, step=W,
                                    data=pixels.reshape(-1))
                writer.write(conns[f"/cam{cam}/image_raw"], ns, store.serialize_ros1(msg, _IMAGE))
                P = np.hstack([K, [[-K[0, 0] * seq.baseline * cam], [0.0], [0.0]]])
                roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                                do_rectify=False)
                info = types[_CAMERA_INFO](header=header, height=H, width=W, distortion_model="plumb_bob",
                                           D=np.zeros(5), K=K.reshape(-1), R=np.eye(3).reshape(-1),
                                           P=P.reshape(-1), binning_x=0, binning_y=0, roi=roi)
                writer.write(conns[f"/cam{cam}/camera_info"], ns, store.serialize_ros1(info, _CAMERA_INFO))
    return path
