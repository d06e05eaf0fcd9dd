"""Rerun out: `egorefine run --rerun FILE.rrd` and `egorefine.viz.log_rerun`, read back with Rerun's own reader."""

from __future__ import annotations

import errno
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import test_cli
import torch

rr = pytest.importorskip("rerun")  # the `rerun` extra (the dev extra brings it)
from rerun.chunk import RrdReader  # noqa: E402

import egorefine.data  # noqa: E402
from egorefine.cli import main  # noqa: E402
from egorefine.data import read_disparity, read_trajectory, render_sequence  # noqa: E402
from egorefine.refine import EgoMotionRefiner, RefinerOutput, TrackingOptions, refine_sequence  # noqa: E402
from egorefine.viz import RERUN_ENTITIES, RerunLogger, RerunNotInstalledError, log_rerun  # noqa: E402

FRAMES = 4
PER_FRAME = ["/world/camera", "/world/camera/image", "/world/camera/depth", "/world/camera/valid",
             "/world/camera/confidence", "/world/trajectory", "/stats/stereo", "/stats/tracks", "/stats/motion",
             "/stats/status"]


# ------------------------------------------------------------------------------------------------ reading back
def _rows(path: Path) -> dict[str, list[dict]]:
    """Entity path -> its temporal rows (column name -> pyarrow scalar), in frame order; static rows under
    ``"static:" + path``. Read with Rerun's own reader (``rerun.chunk.RrdReader``)."""
    rows: dict[str, list[dict]] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        names = [n for n in batch.schema.names if n != "rerun.controls.RowId"]
        key = ("static:" if chunk.is_static else "") + chunk.entity_path
        for i in range(batch.num_rows):
            rows[key].append({n: batch.column(n)[i] for n in names})
    for key, entries in rows.items():
        if not key.startswith("static:"):
            entries.sort(key=lambda r: r["frame"].as_py())
    return rows


def _first(row: dict, column: str):
    """The first instance of a component in one row (a pyarrow scalar)."""
    return row[column].values[0]


def _image(row: dict, archetype: str, dtype) -> np.ndarray:
    """The ``(H, W[, C])`` pixels of an image archetype's row."""
    fmt = _first(row, f"{archetype}:format").as_py()
    data = np.frombuffer(_first(row, f"{archetype}:buffer").values.to_numpy(zero_copy_only=False).tobytes(),
                         dtype=dtype)
    channels = data.size // (fmt["width"] * fmt["height"])
    assert data.size == fmt["width"] * fmt["height"] * channels
    return data.reshape(fmt["height"], fmt["width"], *([channels] if channels > 1 else []))


def _scalars(rows: dict, entity: str) -> list[float]:
    return [float(_first(r, "Scalars:scalars").as_py()) for r in rows[entity]]


def _frames(rows: dict, entity: str) -> list[int]:
    return [r["frame"].as_py() for r in rows[entity]]


def _transforms(rows: dict) -> np.ndarray:
    """``(T, 4, 4)`` world_T_camera of the camera entity (Rerun stores 3x3 matrices column-major)."""
    poses = []
    for r in rows["/world/camera"]:
        if r.get("Transform3D:translation") is None or not r["Transform3D:translation"].is_valid:
            continue
        pose = np.eye(4)
        pose[:3, 3] = _first(r, "Transform3D:translation").as_py()
        pose[:3, :3] = np.asarray(_first(r, "Transform3D:mat3x3").as_py()).reshape(3, 3).T
        poses.append(pose)
    return np.stack(poses)


def _depth(disparity: np.ndarray, valid: np.ndarray, fb: float) -> np.ndarray:
    """The depth a recording must hold: f B / d where valid and d > 0, 0 elsewhere (float64)."""
    d = disparity.astype(np.float64)
    ok = valid & (d > 0)
    return np.where(ok, fb / np.where(ok, d, 1.0), 0.0)


# ------------------------------------------------------------------------------------------------ egorefine run
def _euroc_argv(root: Path, out: Path, *extra: str) -> list[str]:
    return ["run", str(root), "--layout", "euroc", "--frames", f"0:{FRAMES}", "--max-disparity", "24",
            "--verify-every", "2", "--threads", "1", "--quiet", "--out", str(out), *extra]


def _one_line_error(err: str) -> str:
    line = test_cli._one_line_error(err)
    assert line.startswith("egorefine run: error: ")
    return line


@pytest.fixture(scope="module")
def euroc_run(euroc_root, tmp_path_factory):
    """One `egorefine run --rerun` of the EuRoC clip's first frames: (output folder, rrd path, rows read back)."""
    out = tmp_path_factory.mktemp("rerun") / "out"
    rrd = out / "run.rrd"  # in --out, which the run makes
    assert main(_euroc_argv(euroc_root, out, "--format", "npy", "--outputs", "disparity,valid", "--rerun",
                            str(rrd))) == 0
    return out, rrd, _rows(rrd)


def test_run_rerun_entities_and_frames(euroc_run):
    out, rrd, rows = euroc_run
    report = json.loads((out / "run.json").read_text())
    assert report["outputs"]["rerun"] == str(rrd.resolve())
    assert report["timings"]["rerun_ms_mean"] > 0
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []  # no temporary file left
    for entity in PER_FRAME:
        assert _frames(rows, entity) == list(range(FRAMES)), entity  # one row per frame, frame = 0 .. T-1
    assert {e for e in rows if not e.startswith("static:")} >= set(PER_FRAME)
    assert {e.lstrip("/") for e in PER_FRAME} <= set(RERUN_ENTITIES)
    assert "static:/world" not in rows  # the EuRoC world frame is the motion capture's: no axes are claimed
    # the timestamp timeline: the recording's stamps (those of the TUM trajectory file)
    stamps, poses = read_trajectory(out / "trajectory_tum.txt")
    depth_rows = rows["/world/camera/depth"]
    ns = np.array([r["time"].value for r in depth_rows], dtype=np.int64)
    np.testing.assert_allclose(ns * 1e-9, stamps, rtol=0, atol=1e-6)
    # the pose of each frame is the trajectory file's (which holds the nearest rotations: float32 level)
    np.testing.assert_allclose(_transforms(rows), poses.numpy(), rtol=0, atol=1e-5)
    # the path so far: frame t's line strip holds the positions of frames 0 .. t
    for t, r in enumerate(rows["/world/trajectory"]):
        strip = np.asarray(_first(r, "LineStrips3D:strips").as_py())
        np.testing.assert_allclose(strip, poses[: t + 1, :3, 3].numpy(), rtol=0, atol=1e-5)
    # statistics: stereo on frames 0 and 2 (--verify-every 2), as run.json counts
    assert _scalars(rows, "/stats/stereo") == [1.0, 0.0, 1.0, 0.0]
    assert sum(_scalars(rows, "/stats/stereo")) == report["frames"]["stereo_ran"]
    assert FRAMES - sum(_scalars(rows, "/stats/motion")) == report["frames"]["motion_failed"]
    assert all(n > 0 for n in _scalars(rows, "/stats/tracks")[1:])


def test_run_rerun_depth_is_f_b_over_the_written_disparity(euroc_run):
    out, _, rows = euroc_run
    calib = json.loads((out / "run.json").read_text())["calibration"]
    K, baseline = np.asarray(calib["K"]), calib["baseline_m"]
    assert "static:/world/camera" not in rows  # the pinhole is logged with each frame's pose
    for r in rows["/world/camera"]:
        np.testing.assert_allclose(np.asarray(_first(r, "Pinhole:image_from_camera").as_py()).reshape(3, 3).T, K,
                                   rtol=1e-6)
        assert _first(r, "Pinhole:resolution").as_py() == [calib["image_size_hw"][1], calib["image_size_hw"][0]]
    files = sorted((out / "disparity").glob("*.npy"))
    assert len(files) == FRAMES
    fb = float(np.float32(K[0, 0]) * np.float32(baseline))
    checked = 0
    for file, depth_row, valid_row, conf_row in zip(files, rows["/world/camera/depth"], rows["/world/camera/valid"],
                                                    rows["/world/camera/confidence"], strict=True):
        disparity, has_value = (x.numpy() for x in read_disparity(file))
        depth = _image(depth_row, "DepthImage", np.float32)
        assert depth.shape == disparity.shape
        assert _first(depth_row, "DepthImage:meter").as_py() == 1.0
        np.testing.assert_allclose(depth, _depth(disparity, has_value, fb), rtol=2e-6, atol=0)
        assert ((depth > 0) == has_value).all() and has_value.mean() > 0.2
        valid = _image(valid_row, "SegmentationImage", np.uint8)
        written = egorefine.data.read_grey(out / "valid" / f"{file.stem}.png").numpy()[0, 0] > 0.5
        assert np.array_equal(valid == 1, written)
        confidence = _image(conf_row, "Image", np.float32)
        assert confidence.shape == depth.shape and 0 <= confidence.min() and confidence.max() <= 1
        checked += 1
    assert checked == FRAMES


def test_run_rerun_left_image_is_the_rectified_left(euroc_run, euroc_root):
    _, _, rows = euroc_run
    rec = egorefine.data.open_recording(euroc_root, "euroc", frames=slice(0, FRAMES))
    for t, r in enumerate(rows["/world/camera/image"]):
        left = (rec[t][0][0, 0].clamp(0, 1) * 255).round().to(torch.uint8).numpy()
        assert np.array_equal(_image(r, "Image", np.uint8), left)


# ------------------------------------------------------------------------------------------------ bad input
def test_rerun_folder_missing_is_one_line_and_nothing_read(euroc_root, tmp_path, capsys):
    out = tmp_path / "out"
    capsys.readouterr()
    assert test_cli._code(_euroc_argv(euroc_root, out, "--rerun", str(tmp_path / "nowhere" / "run.rrd"))) == 2
    line = _one_line_error(capsys.readouterr().err)
    assert "--rerun" in line and "does not exist" in line and "nowhere" in line
    assert not out.exists()  # refused before anything was read or made


def test_rerun_folder_not_writable(euroc_root, tmp_path, capsys):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        if not test_cli.mode_stops_writes(folder):
            pytest.skip("the file mode does not stop this user (root)")
        capsys.readouterr()
        assert test_cli._code(_euroc_argv(euroc_root, tmp_path / "out", "--rerun", str(folder / "run.rrd"))) == 2
        line = _one_line_error(capsys.readouterr().err)
        assert "--rerun" in line and "not writable" in line
    finally:
        folder.chmod(0o755)


def test_rerun_file_is_a_folder_or_exists(euroc_root, tmp_path, capsys):
    capsys.readouterr()
    assert test_cli._code(_euroc_argv(euroc_root, tmp_path / "out", "--rerun", str(tmp_path))) == 2
    assert "is a folder" in _one_line_error(capsys.readouterr().err)
    earlier = tmp_path / "earlier.rrd"
    earlier.write_bytes(b"an earlier recording")
    assert test_cli._code(_euroc_argv(euroc_root, tmp_path / "out", "--rerun", str(earlier))) == 2
    line = _one_line_error(capsys.readouterr().err)
    assert "already exists" in line and "--overwrite" in line
    assert earlier.read_bytes() == b"an earlier recording"


def test_rerun_not_installed(euroc_root, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` raises ImportError
    capsys.readouterr()
    assert test_cli._code(_euroc_argv(euroc_root, tmp_path / "out", "--rerun", str(tmp_path / "run.rrd"))) == 2
    assert "pip install egorefine[rerun]" in _one_line_error(capsys.readouterr().err)
    assert not (tmp_path / "out").exists()
    with pytest.raises(RerunNotInstalledError, match=r"pip install egorefine\[rerun\]"):
        RerunLogger(tmp_path / "x.rrd")
    with pytest.raises(ImportError):  # still an ImportError for those who catch that
        log_rerun(tmp_path / "x.rrd", torch.zeros(2, 1, 8, 8), [], torch.eye(3), 0.1)


@pytest.mark.parametrize("where", ["writer", "rerun"])
def test_failed_run_leaves_no_recording(euroc_root, tmp_path, capsys, monkeypatch, where):
    """A write that fails mid-run (the map writer's disk full, or the Rerun thread's) leaves neither the .rrd nor
    its temporary file; an earlier recording at that path (--overwrite) is gone too, as the folder's results are."""
    out = tmp_path / "out"
    out.mkdir()
    rrd = tmp_path / "run.rrd"
    rrd.write_bytes(b"an earlier recording")

    def fail(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    if where == "writer":
        monkeypatch.setattr(egorefine.data, "write_disparity", fail)
    else:
        real = RerunLogger.log_frame
        monkeypatch.setattr(RerunLogger, "log_frame",
                            lambda self, t, *a, **k: fail() if t == 2 else real(self, t, *a, **k))
    capsys.readouterr()
    assert test_cli._code(_euroc_argv(euroc_root, out, "--overwrite", "--rerun", str(rrd))) == 2
    assert "No space left on device" in _one_line_error(capsys.readouterr().err)
    assert not rrd.exists() and not (out / "run.json").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no .run.partial.rrd


# ------------------------------------------------------------------------------------------------ log_rerun
@pytest.fixture(scope="module")
def synthetic():
    seq = render_sequence(num_frames=FRAMES, height=40, width=56, seed=3)
    refiner = EgoMotionRefiner(max_disparity=12, verify_every=2,
                               tracking=TrackingOptions(max_features=64, min_tracks=16))
    res = refine_sequence(seq.left, seq.right, seq.K, seq.baseline, refiner=refiner)
    return seq, res


def test_log_rerun_sequence_result(synthetic, tmp_path):
    seq, res = synthetic
    stamps = 0.1 * np.arange(FRAMES)  # seconds from the start: a duration timeline
    path = log_rerun(tmp_path / "seq.rrd", seq.left, res, seq.K, seq.baseline, stamps=stamps)
    assert path == tmp_path / "seq.rrd" and sorted(p.name for p in tmp_path.iterdir()) == ["seq.rrd"]
    rows = _rows(path)
    for entity in PER_FRAME:
        assert _frames(rows, entity) == list(range(FRAMES)), entity
    assert "static:/world" in rows  # RDF: the world is the first camera's frame
    assert [r["time"].value for r in rows["/world/camera/depth"]] == [round(s * 1e9) for s in stamps]
    fb = float(seq.K[0, 0]) * seq.baseline
    for t, r in enumerate(rows["/world/camera/depth"]):
        d, v = res.disparity[t, 0, 0].numpy(), res.valid[t, 0, 0].numpy()
        depth = _image(r, "DepthImage", np.float32)
        np.testing.assert_allclose(depth, _depth(d, v, fb), rtol=2e-6, atol=0)
        assert (depth > 0).mean() > 0.5
    for t, r in enumerate(rows["/world/camera/valid"]):
        assert np.array_equal(_image(r, "SegmentationImage", np.uint8), res.valid[t, 0, 0].numpy().astype(np.uint8))
    assert _scalars(rows, "/stats/stereo") == [float(s) for s in res.stereo_ran.tolist()] == [1.0, 0.0, 1.0, 0.0]
    assert _scalars(rows, "/stats/tracks") == [float(n) for n in res.num_tracks[:, 0].tolist()]
    assert _scalars(rows, "/stats/status") == [float(s) for s in res.status[:, 0].tolist()]
    # the poses: composed from the motions, starting at the identity
    poses = _transforms(rows)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)
    expected = np.eye(4)
    for t in range(1, FRAMES):
        expected = expected @ np.linalg.inv(res.motion[t, 0].double().numpy())
        np.testing.assert_allclose(poses[t], expected, atol=1e-6)


def test_true_disparity_logs_the_rendered_depth_and_poses(synthetic, tmp_path):
    """Physical truth: frames holding the renderer's disparity (f B / Z) read back as its depth Z and poses."""
    seq, res = synthetic
    frames = [RefinerOutput(seq.disparity[t: t + 1], torch.ones_like(seq.disparity[t: t + 1], dtype=torch.bool),
                            res.motion[t], True, res.variance[t], res.confidence[t], res.motion_ok[t],
                            res.num_tracks[t], res.status[t]) for t in range(FRAMES)]
    rows = _rows(log_rerun(tmp_path / "truth.rrd", seq.left, frames, seq.K, seq.baseline, poses=seq.poses))
    for t, r in enumerate(rows["/world/camera/depth"]):
        np.testing.assert_allclose(_image(r, "DepthImage", np.float32), seq.depth[t, 0].numpy(), rtol=1e-5, atol=0)
    np.testing.assert_allclose(_transforms(rows), seq.poses.double().numpy(), atol=1e-6)


def test_log_rerun_list_of_outputs_and_given_poses_equal(synthetic, tmp_path):
    """A list of RefinerOutput logs what the SequenceResult does; given poses replace the composed ones."""
    seq, res = synthetic
    refiner = EgoMotionRefiner(max_disparity=12, verify_every=2,
                               tracking=TrackingOptions(max_features=64, min_tracks=16))
    outputs, state = [], None
    for t in range(FRAMES):
        out, state = refiner(seq.left[t: t + 1], seq.right[t: t + 1], seq.K[None], torch.tensor([seq.baseline]),
                             state)
        outputs.append(out)
    a = _rows(log_rerun(tmp_path / "a.rrd", seq.left, res, seq.K, seq.baseline))
    b = _rows(log_rerun(tmp_path / "b.rrd", seq.left, outputs, seq.K, seq.baseline, poses=seq.poses,
                        world_xyz=None))
    for ra, rb in zip(a["/world/camera/depth"], b["/world/camera/depth"], strict=True):
        assert np.array_equal(_image(ra, "DepthImage", np.float32), _image(rb, "DepthImage", np.float32))
    np.testing.assert_allclose(_transforms(b), seq.poses.double().numpy(), atol=1e-6)
    assert "time" not in b["/world/camera/depth"][0]  # no stamps: the frame timeline alone
    assert "static:/world" not in b


def test_logger_rejects_bad_shapes_and_use_after_close(synthetic, tmp_path):
    seq, res = synthetic
    frame = RefinerOutput(res.disparity[0], res.valid[0], res.motion[0], True, res.variance[0], res.confidence[0],
                          res.motion_ok[0], res.num_tracks[0], res.status[0])
    logger = RerunLogger(tmp_path / "bad.rrd")
    with pytest.raises(egorefine.core.ShapeError, match="result.disparity"):
        logger.log_frame(0, seq.left[:1, :, :20], frame, seq.K, seq.baseline, torch.eye(4))
    with pytest.raises(egorefine.core.ShapeError, match="K"):
        logger.log_frame(0, seq.left[:1], frame, seq.K[:2], seq.baseline, torch.eye(4))
    logger.discard()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(egorefine.core.StateError, match="closed"):
        logger.log_frame(0, seq.left[:1], frame, seq.K, seq.baseline, torch.eye(4))
    with pytest.raises(egorefine.core.ShapeError, match="results: expected 4 frames"):
        log_rerun(tmp_path / "short.rrd", seq.left, [frame], seq.K, seq.baseline)


def test_frames_handed_to_the_rerun_thread_are_copies(synthetic):
    """`egorefine run` logs on a thread of its own: what it hands over shares no memory with the refiner's output."""
    run_module = sys.modules["egorefine.cli._run"]
    _, res = synthetic
    out = RefinerOutput(res.disparity[0], res.valid[0], res.motion[0], True, res.variance[0], res.confidence[0],
                        res.motion_ok[0], res.num_tracks[0], res.status[0])
    copy = run_module._copied(out)
    assert type(copy) is RefinerOutput and copy.stereo_ran is True
    for a, b in zip(out, copy, strict=True):
        if isinstance(a, torch.Tensor):
            assert torch.equal(a, b) and a.untyped_storage().data_ptr() != b.untyped_storage().data_ptr()
