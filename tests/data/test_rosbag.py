"""The rosbag layout on small ROS 1 and ROS 2 bags (sqlite3 and mcap) the tests write with rosbags' writers.

The truth is the rendered sequence itself: its frames are 8-bit (the realistic imaging model quantises them), so a
frame that goes into a bag as mono8, mono16 or a lossless PNG comes back exactly, and the rig's K and baseline are
known. Colour encodings are compared with OpenCV's grey conversion of the BGR image, which is what the folders
layout reads from a colour file.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from egorefine.cli import main
from egorefine.core import DataError, MissingDataError, ValueRangeError
from egorefine.data import (
    LAYOUTS,
    ROSBAG_ENCODINGS,
    RosbagNotInstalledError,
    RosbagRecording,
    open_recording,
    open_rosbag,
    read_disparity,
    render_sequence,
)

rosbags = pytest.importorskip("rosbags")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

T, H, W = 4, 48, 64
T0_NS = 1_700_000_000 * 10**9  # Unix time of the first frame: stamps as a real recording has them
DT_NS = 100_000_000  # 10 fps
LEFT, RIGHT = "/cam0/image_raw", "/cam1/image_raw"
KINDS = ("ros1", "sqlite3", "mcap")
STORE1, STORE2 = get_typestore(Stores.ROS1_NOETIC), get_typestore(Stores.ROS2_HUMBLE)


@pytest.fixture(scope="module")
def seq():
    return render_sequence(num_frames=T, height=H, width=W, seed=5)


def _u8(img: torch.Tensor) -> np.ndarray:
    """A rendered ``(1, H, W)`` frame as the uint8 image it was quantised to."""
    return (img[0].numpy() * 255).round().astype(np.uint8)


def _colour(t: int, seq) -> np.ndarray:
    """A BGR frame whose channels differ (left frame, right frame, left frame upside down): a decoder that swaps
    channels gets another grey image."""
    return np.dstack([_u8(seq.left[t]), _u8(seq.right[t]), _u8(seq.left[t])[::-1]])


class _Bag:
    """Writes a ROS 1 bag (``kind="ros1"``) or a ROS 2 bag with sqlite3 or mcap storage, messages built in the
    right type store and serialisation."""

    def __init__(self, path: Path, kind: str):
        self.kind, self.path = kind, path
        self.store = STORE1 if kind == "ros1" else STORE2
        if kind == "ros1":
            self.writer = Writer1(path)
        else:
            plugin = StoragePlugin.SQLITE3 if kind == "sqlite3" else StoragePlugin.MCAP
            self.writer = Writer2(path, version=9, storage_plugin=plugin)
        self.conns = {}

    def __enter__(self):
        self.writer.open()
        return self

    def __exit__(self, *exc):
        self.writer.close()

    def _header(self, stamp_ns: int):
        types = self.store.types
        stamp = types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        if self.kind == "ros1":
            return types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="cam")
        return types["std_msgs/msg/Header"](stamp=stamp, frame_id="cam")

    def write(self, topic: str, msgtype: str, msg, log_ns: int) -> None:
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        data = (self.store.serialize_ros1 if self.kind == "ros1" else self.store.serialize_cdr)(msg, msgtype)
        self.writer.write(self.conns[topic], log_ns, data)

    def image(self, topic: str, stamp_ns: int, pixels: np.ndarray, encoding: str, log_ns: int | None = None,
              bigendian: bool = False, pad: int = 0) -> None:
        h, w = pixels.shape[:2]
        row = pixels.reshape(h, -1)
        if bigendian:
            row = row.astype(row.dtype.newbyteorder(">"))
        row = np.ascontiguousarray(row).view(np.uint8).reshape(h, -1)
        if pad:  # rows padded to `step` bytes with junk the decoder must skip
            row = np.hstack([row, np.full((h, pad), 77, np.uint8)])
        msg = self.store.types["sensor_msgs/msg/Image"](
            header=self._header(stamp_ns), height=h, width=w, encoding=encoding, is_bigendian=int(bigendian),
            step=row.shape[1], data=row.reshape(-1))
        self.write(topic, "sensor_msgs/msg/Image", msg, stamp_ns if log_ns is None else log_ns)

    def compressed(self, topic: str, stamp_ns: int, pixels: np.ndarray) -> None:
        ok, png = cv2.imencode(".png", pixels)
        assert ok
        msg = self.store.types["sensor_msgs/msg/CompressedImage"](header=self._header(stamp_ns), format="png",
                                                                  data=png.reshape(-1))
        self.write(topic, "sensor_msgs/msg/CompressedImage", msg, stamp_ns)

    def camera_info(self, topic: str, stamp_ns: int, K: np.ndarray, P: np.ndarray, D=None, R=None,
                    size=(H, W)) -> None:
        types = self.store.types
        roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                        do_rectify=False)
        fields = {"d": np.zeros(5) if D is None else np.asarray(D, float), "k": K.reshape(-1),
                  "r": (np.eye(3) if R is None else R).reshape(-1), "p": P.reshape(-1)}
        if self.kind == "ros1":  # ROS 1 spells the matrices in capitals
            fields = {k.upper(): v for k, v in fields.items()}
        msg = types["sensor_msgs/msg/CameraInfo"](header=self._header(stamp_ns), height=size[0], width=size[1],
                                                  distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi,
                                                  **fields)
        self.write(topic, "sensor_msgs/msg/CameraInfo", msg, stamp_ns)


def _K(seq) -> np.ndarray:
    return seq.K.double().numpy()


def _P(seq, right: bool) -> np.ndarray:
    """The rectified projection of a camera of the rig: the right one holds -fx * baseline in P[0, 3]."""
    K = _K(seq)
    return np.hstack([K, [[-K[0, 0] * seq.baseline if right else 0.0], [0.0], [0.0]]])


def _stamp(t: int) -> int:
    return T0_NS + t * DT_NS


def _write_bag(path: Path, kind: str, seq, *, encoding: str = "mono8", info: bool = True, drop_right=(),
               right_delay_ns: int = 0, same_log_time: bool = False) -> Path:
    """A bag of the rendered frames on LEFT/RIGHT and the rig's camera_info beside them."""
    path = path / ("rig.bag" if kind == "ros1" else f"rig_{kind}")
    with _Bag(path, kind) as bag:
        for t in range(T):
            log = T0_NS if same_log_time else None  # every message logged at one instant: only the stamps differ
            for topic, img, delay in ((LEFT, seq.left[t], 0), (RIGHT, seq.right[t], right_delay_ns)):
                if topic == RIGHT and t in drop_right:
                    continue
                bag.image(topic, _stamp(t) + delay, _u8(img), encoding, log_ns=log)
            if info:
                for cam, right in (("cam0", False), ("cam1", True)):
                    bag.camera_info(f"/{cam}/camera_info", _stamp(t), _K(seq), _P(seq, right))
    return path


def _write_folders(root: Path, seq, colour: bool = False) -> Path:
    """The same frames as a folders layout: PNG files named by stamp, times.txt and a KITTI calib.txt of the rig
    (numbers printed exactly)."""
    for side, images in (("left", seq.left), ("right", seq.right)):
        (root / side).mkdir(parents=True)
        for t, img in enumerate(images):
            pixels = _colour(t, seq) if colour and side == "left" else _u8(img)
            cv2.imwrite(str(root / side / f"{_stamp(t)}.png"), pixels)
    (root / "times.txt").write_text("".join(f"{_stamp(t) / 1e9!r}\n" for t in range(T)))
    (root / "calib.txt").write_text("".join(f"P{i}: " + " ".join(repr(float(v)) for v in _P(seq, i).ravel()) + "\n"
                                            for i in (0, 1)))
    return root


# ---------------------------------------------------------------- the bag gives what the folders give


@pytest.mark.parametrize("kind", KINDS)
def test_bag_gives_the_rendered_frames_rig_and_stamps(kind, seq, tmp_path) -> None:
    bag = _write_bag(tmp_path, kind, seq)
    rec = open_recording(bag, "rosbag", topics=(LEFT, RIGHT))
    folders = open_recording(_write_folders(tmp_path / "folders", seq), "folders")
    assert isinstance(rec, RosbagRecording) and "rosbag" in LAYOUTS
    assert len(rec) == T and rec.image_size == (H, W) and rec.rectified_input and rec.poses is None
    # K and baseline come from P exactly as the folders layout reads them from calib.txt, and equal the rig's.
    assert torch.equal(rec.K, folders.K) and rec.baseline == folders.baseline
    torch.testing.assert_close(rec.K, seq.K.double(), rtol=0, atol=1e-12)
    assert rec.baseline == pytest.approx(seq.baseline, rel=1e-12)
    assert rec.names == folders.names == [str(_stamp(t)) for t in range(T)]
    np.testing.assert_array_equal(rec.timestamps, folders.timestamps)
    for t in (2, 0, 3, 1):  # out of order: each frame is fetched from the bag on its own
        (left, right), (fl, fr) = rec[t], folders[t]
        assert torch.equal(left, fl) and torch.equal(right, fr)
        assert torch.equal(left, seq.left[t:t + 1]) and torch.equal(right, seq.right[t:t + 1])
    assert rec.info["pairs"] == T and rec.info["unpaired_left"] == rec.info["unpaired_right"] == 0
    assert rec.notes == ()
    rec.close()
    assert torch.equal(rec[1][0], seq.left[1:2])  # a closed recording reopens the bag


@pytest.mark.parametrize("kind", ["ros1", "sqlite3"])
def test_messages_logged_at_one_instant_are_told_apart(kind, seq, tmp_path) -> None:
    """Messages are fetched by log time; where many share it, their rank among them picks the right one."""
    rec = open_rosbag(_write_bag(tmp_path, kind, seq, same_log_time=True), LEFT, RIGHT)
    for t in (3, 0, 2):
        assert torch.equal(rec[t][0], seq.left[t:t + 1]) and torch.equal(rec[t][1], seq.right[t:t + 1])


def _widen(x: np.ndarray) -> np.ndarray:
    """16-bit pixels whose two bytes differ (x * 257 would read the same in either byte order)."""
    return (x.astype(np.uint16) << 8) | (255 - x).astype(np.uint16)


def _encoded(encoding: str, t: int, seq) -> tuple[np.ndarray, np.ndarray]:
    """Pixels to store in ``encoding`` for frame ``t``, and the grey image in [0, 1] the folders layout would read
    from the same picture as a BGR(A) file."""
    bgr = _colour(t, seq)
    wide = "16" in encoding
    scale = 65535.0 if wide else 255.0
    if encoding.startswith("mono") or encoding in ("8UC1", "16UC1"):
        grey = _u8(seq.left[t])
        pixels = _widen(grey) if wide else grey
        return pixels, pixels.astype(np.float32) / scale
    if wide:
        bgr = _widen(bgr)
    expected = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(np.float32) / scale
    order = {"bgr": bgr, "rgb": bgr[..., ::-1]}[encoding[:3]]
    if encoding[3] == "a":
        order = np.dstack([order, np.full_like(order[..., :1], 7)])  # alpha does not count
    return np.ascontiguousarray(order), expected


@pytest.mark.parametrize(("encoding", "bigendian", "pad"), [
    *[(e, False, 0) for e in ROSBAG_ENCODINGS], ("mono16", True, 0), ("rgb16", True, 6), ("bgr8", False, 5)])
def test_image_encodings(encoding, bigendian, pad, seq, tmp_path) -> None:
    """Each readable encoding (byte order, padded rows) gives the grey image OpenCV makes of the BGR picture."""
    bag = tmp_path / "enc"
    with _Bag(bag, "sqlite3") as writer:
        for t in range(2):
            pixels, _ = _encoded(encoding, t, seq)
            for topic in (LEFT, RIGHT):
                writer.image(topic, _stamp(t), pixels, encoding, bigendian=bigendian, pad=pad)
                writer.camera_info(topic.replace("image_raw", "camera_info"), _stamp(t), _K(seq),
                                   _P(seq, topic == RIGHT))
    rec = open_rosbag(bag, LEFT, RIGHT)
    assert rec.info["encodings"][LEFT] == {encoding: 2}
    for t in range(2):
        _, expected = _encoded(encoding, t, seq)
        np.testing.assert_array_equal(rec[t][0][0, 0].numpy(), expected)
    if encoding.startswith(("rgb", "bgr")):  # the channel order matters: swapped, the grey image differs
        swapped = cv2.cvtColor(_colour(0, seq)[..., ::-1].copy(), cv2.COLOR_BGR2GRAY) / 255.0
        assert np.abs(swapped - _encoded("bgr8", 0, seq)[1]).mean() > 0.02


def test_colour_bag_matches_colour_folders(seq, tmp_path) -> None:
    """A bgr8 left camera in a ROS 1 bag reads as the same BGR picture saved as a colour PNG does."""
    bag = tmp_path / "colour.bag"
    with _Bag(bag, "ros1") as writer:
        for t in range(T):
            writer.image(LEFT, _stamp(t), _colour(t, seq), "bgr8")
            writer.image(RIGHT, _stamp(t), _u8(seq.right[t]), "mono8")
            for cam, right in (("cam0", False), ("cam1", True)):
                writer.camera_info(f"/{cam}/camera_info", _stamp(t), _K(seq), _P(seq, right))
    rec = open_rosbag(bag, LEFT, RIGHT)
    folders = open_recording(_write_folders(tmp_path / "folders", seq, colour=True), "folders")
    for t in range(T):
        assert torch.equal(rec[t][0], folders[t][0]) and torch.equal(rec[t][1], folders[t][1])


# ---------------------------------------------------------------- compressed images, pairing


def _write_compressed(path: Path, seq, drop_right=(), right_delay_ns: int = 1_000_000) -> Path:
    """PNG CompressedImage topics (image_transport's names) with a right camera 1 ms late."""
    with _Bag(path, "mcap") as bag:
        for t in range(T):
            bag.compressed(LEFT + "/compressed", _stamp(t), _u8(seq.left[t]))
            if t not in drop_right:
                bag.compressed(RIGHT + "/compressed", _stamp(t) + right_delay_ns, _u8(seq.right[t]))
            for cam, right in (("cam0", False), ("cam1", True)):
                bag.camera_info(f"/{cam}/camera_info", _stamp(t), _K(seq), _P(seq, right))
    return path


def test_compressed_png_with_a_dropped_right_frame(seq, tmp_path) -> None:
    bag = _write_compressed(tmp_path / "compressed", seq, drop_right=(2,))
    rec = open_rosbag(bag, LEFT + "/compressed", RIGHT + "/compressed")  # camera_info found at /camX/camera_info
    kept = [0, 1, 3]
    assert len(rec) == len(kept)
    assert rec.info["pairs"] == 3 and rec.info["unpaired_left"] == 1 and rec.info["unpaired_right"] == 0
    assert rec.info["pair_tolerance_s"] == pytest.approx(0.005)  # below half the 0.1 s frame interval
    assert "1 left and 0 right frames" in rec.notes[0]
    np.testing.assert_array_equal(rec.timestamps, [_stamp(t) / 1e9 for t in kept])  # the left stamps
    for i, t in enumerate(kept):  # PNG is lossless: the rendered frames exactly
        assert torch.equal(rec[i][0], seq.left[t:t + 1]) and torch.equal(rec[i][1], seq.right[t:t + 1])
    assert rec.baseline == pytest.approx(seq.baseline, rel=1e-12)
    # frames count among the pairs
    assert open_rosbag(bag, LEFT + "/compressed", RIGHT + "/compressed", frames=slice(1, None)).names == [
        str(_stamp(1)), str(_stamp(3))]


def test_pair_tolerance(seq, tmp_path) -> None:
    bag = _write_compressed(tmp_path / "late", seq, right_delay_ns=3_000_000)
    topics = (LEFT + "/compressed", RIGHT + "/compressed")
    assert len(open_rosbag(bag, *topics)) == T  # 3 ms within the default 5 ms
    with pytest.raises(DataError, match=r"pair within 0\.002 s .*median stamp difference is 0\.003 s"):
        open_rosbag(bag, *topics, pair_tolerance=0.002)
    # A right camera half a frame late pairs only when the tolerance allows it, one to one.
    late = _write_compressed(tmp_path / "half", seq, right_delay_ns=DT_NS // 2 - 1_000_000)
    assert len(open_rosbag(late, *topics, pair_tolerance=0.06)) == T
    with pytest.raises(DataError, match="pair"):
        open_rosbag(late, *topics)
    with pytest.raises(ValueRangeError, match="pair_tolerance"):
        open_rosbag(bag, *topics, pair_tolerance=-1.0)


# ---------------------------------------------------------------- calibration


def _ros_yaml(path: Path, K, D, R, P) -> Path:
    def mat(key, M, rows, cols):
        return f"{key}:\n  rows: {rows}\n  cols: {cols}\n  data: [{', '.join(repr(float(x)) for x in np.ravel(M))}]\n"

    path.write_text(f"image_width: {W}\nimage_height: {H}\ncamera_name: cam\n" + mat("camera_matrix", K, 3, 3)
                    + "distortion_model: plumb_bob\n" + mat("distortion_coefficients", D, 1, 5)
                    + mat("rectification_matrix", R, 3, 3) + mat("projection_matrix", P, 3, 4))
    return path


def test_unrectified_camera_info_is_rectified_as_the_folders_layout_does(seq, tmp_path) -> None:
    """A distorted pair's camera_info: the bag is rectified with the remap the same ROS calibration files give the
    folders layout, and the rectified rig keeps the true baseline."""
    D = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
    bag = tmp_path / "raw"
    with _Bag(bag, "sqlite3") as writer:
        for t in range(T):
            for topic, img, right in ((LEFT, seq.left[t], False), (RIGHT, seq.right[t], True)):
                writer.image(topic, _stamp(t), _u8(img), "mono8")
                writer.camera_info(topic.replace("image_raw", "camera_info"), _stamp(t), _K(seq), _P(seq, right),
                                   D=D)
    rec = open_rosbag(bag, LEFT, RIGHT)
    root = _write_folders(tmp_path / "folders", seq)
    (root / "calib.txt").unlink()
    for name, right in (("left.yaml", False), ("right.yaml", True)):
        _ros_yaml(root / name, _K(seq), D, np.eye(3), _P(seq, right))
    folders = open_recording(root, "folders", calib=root / "left.yaml")
    assert not rec.rectified_input and not folders.rectified_input
    assert torch.equal(rec.K, folders.K) and rec.baseline == folders.baseline
    assert rec.baseline == pytest.approx(seq.baseline, rel=1e-9)
    for t in range(T):
        assert torch.equal(rec[t][0], folders[t][0]) and torch.equal(rec[t][1], folders[t][1])
    assert (rec[0][0] - seq.left[:1]).abs().mean() > 1e-3  # the remap did something


def test_calib_file_instead_of_camera_info(seq, tmp_path) -> None:
    bag = _write_bag(tmp_path, "ros1", seq, info=False)
    with pytest.raises(MissingDataError, match=r"no camera_info topic beside /cam0/image_raw, /cam1/image_raw"):
        open_rosbag(bag, LEFT, RIGHT)
    calib = _write_folders(tmp_path / "folders", seq) / "calib.txt"
    rec = open_recording(bag, "rosbag", calib=calib, topics=(LEFT, RIGHT))
    assert rec.baseline == pytest.approx(seq.baseline, rel=1e-12) and torch.equal(rec[0][0], seq.left[:1])
    assert rec.info["calibration"] == str(calib)


def test_info_topics_named(seq, tmp_path) -> None:
    """Camera_info topics elsewhere are named; a named one that is absent lists those the bag has."""
    bag = tmp_path / "named"
    with _Bag(bag, "sqlite3") as writer:
        for t in range(2):
            for topic, img, right in ((LEFT, seq.left[t], False), (RIGHT, seq.right[t], True)):
                writer.image(topic, _stamp(t), _u8(img), "mono8")
                writer.camera_info(f"/calib/{'right' if right else 'left'}", _stamp(t), _K(seq), _P(seq, right))
    with pytest.raises(MissingDataError, match="CameraInfo topics: /calib/left, /calib/right"):
        open_rosbag(bag, LEFT, RIGHT)
    rec = open_recording(bag, "rosbag", topics=(LEFT, RIGHT), info_topics=("/calib/left", "/calib/right"))
    assert rec.baseline == pytest.approx(seq.baseline, rel=1e-12)
    with pytest.raises(MissingDataError, match="no topic '/calib/middle'"):
        open_rosbag(bag, LEFT, RIGHT, left_info_topic="/calib/middle")
    with pytest.raises(DataError, match="expected sensor_msgs/msg/CameraInfo"):
        open_rosbag(bag, LEFT, RIGHT, left_info_topic=LEFT)


# ---------------------------------------------------------------- bad input


def test_missing_topic_lists_the_image_topics(seq, tmp_path) -> None:
    bag = _write_bag(tmp_path, "mcap", seq)
    with pytest.raises(MissingDataError, match=r"no topic '/cam2/image_raw' .*image topics: /cam0/image_raw, "
                                               r"/cam1/image_raw$"):
        open_rosbag(bag, LEFT, "/cam2/image_raw")
    with pytest.raises(DataError, match="carries sensor_msgs/msg/CameraInfo; expected sensor_msgs/msg/Image"):
        open_rosbag(bag, LEFT, "/cam1/camera_info")
    with pytest.raises(ValueRangeError, match="same topic"):
        open_rosbag(bag, LEFT, LEFT)


def test_unreadable_encoding_is_named(seq, tmp_path) -> None:
    bag = tmp_path / "bayer.bag"
    with _Bag(bag, "ros1") as writer:
        for t in range(2):
            for topic in (LEFT, RIGHT):
                writer.image(topic, _stamp(t), _u8(seq.left[t]), "bayer_rggb8" if t else "mono8")
    with pytest.raises(DataError, match=r"/cam0/image_raw .* encodings egorefine cannot read: bayer_rggb8 "
                                        r"\(readable: mono8"):
        open_rosbag(bag, LEFT, RIGHT)


def test_paths_that_are_not_bags(seq, tmp_path) -> None:
    (tmp_path / "notes.txt").write_text("hello")
    (tmp_path / "broken.bag").write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 64)
    (tmp_path / "folder").mkdir()
    (tmp_path / "cut").mkdir()
    cut = _write_bag(tmp_path / "cut", "ros1", seq)  # a recording cut short: its index at the end is gone
    cut.write_bytes(cut.read_bytes()[:cut.stat().st_size * 6 // 10])
    for name in ("notes.txt", "broken.bag", "folder", "cut/rig.bag"):
        with pytest.raises(DataError, match="is not a ROS bag"):
            open_rosbag(tmp_path / name, LEFT, RIGHT)
    with pytest.raises(MissingDataError, match="no ROS bag at"):
        open_rosbag(tmp_path / "absent.bag", LEFT, RIGHT)


def test_storage_file_opens_its_bag_folder(seq, tmp_path) -> None:
    bag = _write_bag(tmp_path, "sqlite3", seq)
    storage = next(bag.glob("*.db3"))
    assert len(open_rosbag(storage, LEFT, RIGHT)) == T


def test_layout_options_are_checked(seq, tmp_path) -> None:
    with pytest.raises(ValueRangeError, match="topics: the rosbag layout needs"):
        open_recording(tmp_path, "rosbag")
    with pytest.raises(ValueRangeError, match="only the rosbag layout reads topics"):
        open_recording(tmp_path, "folders", topics=(LEFT, RIGHT))
    with pytest.raises(ValueRangeError, match="not both"):
        open_rosbag(tmp_path, LEFT, RIGHT, calib=tmp_path, left_info_topic="/x")


def test_missing_rosbags_names_the_extra(monkeypatch, tmp_path) -> None:
    for name in [m for m in sys.modules if m == "rosbags" or m.startswith("rosbags.")]:
        monkeypatch.setitem(sys.modules, name, None)  # import rosbags... now raises ImportError
    monkeypatch.setitem(sys.modules, "rosbags", None)
    with pytest.raises(RosbagNotInstalledError, match=r"pip install egorefine\[rosbag\]"):
        open_rosbag(tmp_path / "x.bag", LEFT, RIGHT)


# ---------------------------------------------------------------- the command


def _run(input_path: Path, out: Path, *extra: str) -> list[str]:
    return ["run", str(input_path), "--out", str(out), "--max-disparity", "8", "--verify-every", "2",
            "--threads", "1", "--quiet", *extra]


def test_cli_on_a_bag_writes_what_it_writes_on_the_folders(seq, tmp_path) -> None:
    """`egorefine run` on a bag and on the same frames in folders: the same maps, names and trajectory (same
    pixels, K and baseline in, a deterministic single-thread run: equal to the bit)."""
    bag = _write_bag(tmp_path, "ros1", seq)
    folders = _write_folders(tmp_path / "folders", seq)
    out_bag, out_dir = tmp_path / "out_bag", tmp_path / "out_dir"
    assert main(_run(bag, out_bag, "--layout", "rosbag", "--left-topic", LEFT, "--right-topic", RIGHT)) == 0
    assert main(_run(folders, out_dir, "--layout", "folders")) == 0
    files = sorted(p.name for p in (out_dir / "disparity").iterdir())
    assert files == [f"{_stamp(t)}.png" for t in range(T)]
    assert sorted(p.name for p in (out_bag / "disparity").iterdir()) == files
    for name in files:
        d_bag, v_bag = read_disparity(out_bag / "disparity" / name)
        d_dir, v_dir = read_disparity(out_dir / "disparity" / name)
        assert torch.equal(v_bag, v_dir) and torch.equal(d_bag[v_bag], d_dir[v_dir])
        assert v_bag.float().mean() > 0.3  # maps with content, not two empty ones
    assert (out_bag / "trajectory_tum.txt").read_text() == (out_dir / "trajectory_tum.txt").read_text()
    report = json.loads((out_bag / "run.json").read_text())
    assert report["recording"]["pairs"] == T and report["recording"]["left_topic"] == LEFT
    assert report["calibration"]["baseline_m"] == pytest.approx(seq.baseline, rel=1e-12)


def test_cli_notes_unpaired_frames(seq, tmp_path, capsys) -> None:
    bag = _write_compressed(tmp_path / "dropped", seq, drop_right=(1,))
    argv = _run(bag, tmp_path / "out", "--layout", "rosbag", "--left-topic", LEFT + "/compressed",
                "--right-topic", RIGHT + "/compressed", "--outputs", "none")
    argv.remove("--quiet")
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "note: 1 left and 0 right frames of dropped have no partner within 0.005 s" in err
    report = json.loads((tmp_path / "out" / "run.json").read_text())
    assert report["recording"]["unpaired_left"] == 1 and report["frames"]["count"] == T - 1


def test_cli_bad_input_is_one_line_and_status_2(seq, tmp_path, capsys) -> None:
    bag = _write_bag(tmp_path, "ros1", seq)
    (tmp_path / "bare").mkdir()
    bare = _write_bag(tmp_path / "bare", "ros1", seq, info=False)
    topics = ("--left-topic", LEFT, "--right-topic", RIGHT)
    cases = {
        "no topic '/cam9/image_raw'": _run(bag, tmp_path / "o1", "--layout", "rosbag", "--left-topic",
                                           "/cam9/image_raw", "--right-topic", RIGHT),
        "no camera_info topic beside": _run(bare, tmp_path / "o2", "--layout", "rosbag", *topics),
        "is not a ROS bag": _run(tmp_path, tmp_path / "o3", "--layout", "rosbag", *topics),
        "needs --left-topic and --right-topic": _run(bag, tmp_path / "o4", "--layout", "rosbag"),
        "--left-topic, --right-topic: only --layout rosbag": _run(tmp_path, tmp_path / "o5", "--layout", "folders",
                                                                  *topics),
    }
    for expected, argv in cases.items():
        assert main(argv) == 2, expected
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("egorefine run: error: ") and expected in err, err
