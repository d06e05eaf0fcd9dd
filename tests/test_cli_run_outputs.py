"""`egorefine run`: --outputs, the writer threads (same files as writing in order, errors), frames/s in run.json."""

from __future__ import annotations

import errno
import importlib
import json
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
import test_cli
import torch

from egorefine.cli import _build_parser, main
from egorefine.data import open_recording, read_disparity, write_confidence, write_disparity, write_mask, write_preview
from egorefine.viz import colorize_disparity

_run_module = importlib.import_module("egorefine.cli._run")  # egorefine.cli._run is also the command's function

layout = test_cli.layout  # the small rendered folders layout (module scope: rendered once for this file)
_run_argv, _code, _one_line_error = test_cli._run_argv, test_cli._code, test_cli._one_line_error
T = test_cli.T
ALL = ("disparity", "valid", "confidence", "preview")


def _report(out: Path) -> dict:
    return json.loads((out / "run.json").read_text())


def _writer_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("egorefine-writer")]


def test_outputs_subset_writes_exactly_those_folders(layout, tmp_path):
    root, _ = layout
    out = tmp_path / "subset"
    assert main(_run_argv(root, out, "--outputs", "preview,valid")) == 0
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["preview", "valid"]
    for folder in ("preview", "valid"):
        assert sorted(p.name for p in (out / folder).iterdir()) == [f"{t:06d}.png" for t in range(T)]
    report = _report(out)
    assert report["settings"]["outputs"] == ["valid", "preview"]
    assert set(report["outputs"]) == {"valid", "preview", "trajectory", "trajectory_frame"}
    assert report["frames"]["count"] == T

    none = tmp_path / "none"
    assert main(_run_argv(root, none, "--outputs", "none")) == 0
    assert sorted(p.name for p in none.iterdir()) == ["run.json", "trajectory_kitti.txt", "trajectory_tum.txt"]
    assert not _writer_threads()


def test_frames_per_second_in_run_json_and_printed(layout, tmp_path, capsys):
    root, _ = layout
    out = tmp_path / "fps"
    argv = [a for a in _run_argv(root, out) if a != "--quiet"]
    capsys.readouterr()
    assert main(argv) == 0
    timings = _report(out)["timings"]
    assert timings["frames_per_s"] > 0 and timings["loop_s"] > 0
    assert timings["frames_per_s"] == pytest.approx(T / timings["loop_s"])
    assert 0 < timings["loop_s"] <= timings["total_s"]
    assert timings["write_ms_mean"] > 0 and timings["writer_threads"] >= 1
    assert f"{timings['frames_per_s']:.2f} frames/s" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["disparity,bogus", "valid;preview", "none,valid", ""])
def test_unknown_output_name_gives_one_line_with_the_valid_names(layout, tmp_path, capsys, value):
    root, _ = layout
    capsys.readouterr()
    assert _code(_run_argv(root, tmp_path / "o", "--outputs", value)) == 2
    line = _one_line_error(capsys.readouterr().err)
    assert "--outputs" in line and "disparity, valid, confidence, preview" in line and repr(value) in line
    assert not (tmp_path / "o").exists()


def _failing_writes(monkeypatch, after: int, error: OSError):
    """The PNG writer's files: the first ``after`` are written, every later one raises ``error`` on its first write
    (as a full disk does)."""
    calls, lock = [0], threading.Lock()
    io_module = importlib.import_module("egorefine.data.io")

    class _FullDisk:
        def __init__(self, f):
            self._f = f

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self._f.close()

        def write(self, data):
            raise error

    def open_(path, mode="r", *args, **kwargs):
        f = open(path, mode, *args, **kwargs)
        with lock:
            calls[0] += "w" in mode
            fail = calls[0] > after
        return _FullDisk(f) if fail else f

    monkeypatch.setattr(io_module, "open", open_, raising=False)


@pytest.mark.parametrize("png", ["fast", "small"])
def test_writer_failure_stops_the_run_with_one_line_and_no_run_json(layout, tmp_path, capsys, monkeypatch, png):
    root, _ = layout
    finished = tmp_path / "finished"
    assert main(_run_argv(root, finished)) == 0
    _failing_writes(monkeypatch, after=5, error=OSError(errno.ENOSPC, "No space left on device"))  # frame 2 of 4 PNGs
    capsys.readouterr()
    assert _code(_run_argv(root, finished, "--overwrite", "--png", png)) == 2
    assert "No space left on device" in _one_line_error(capsys.readouterr().err)
    # The earlier run's run.json was removed before refining and none was written: the folder is unfinished.
    assert not (finished / "run.json").exists()
    assert not list(finished.glob("trajectory_*.txt"))
    assert not list(finished.rglob(".*partial*")), "temporary files left behind"
    assert not _writer_threads()


def test_writer_failure_in_a_read_only_folder(layout, tmp_path, capsys):
    """A folder the writer may not write to (as a user without root rights sees it: npy files are opened by
    Python, so the error is the OSError of the file system)."""
    root, _ = layout
    out = tmp_path / "ro"
    (out / "disparity").mkdir(parents=True)
    (out / "disparity").chmod(0o555)
    if not test_cli.mode_stops_writes(out / "disparity"):
        (out / "disparity").chmod(0o755)
        pytest.skip("the file mode does not stop this user (root)")
    try:
        capsys.readouterr()
        assert _code(_run_argv(root, out, "--format", "npy", "--outputs", "disparity")) == 2
        assert "Permission denied" in _one_line_error(capsys.readouterr().err)
        assert not (out / "run.json").exists()
    finally:
        (out / "disparity").chmod(0o755)


def _decoded(path: Path) -> np.ndarray:
    return np.load(path) if path.suffix == ".npy" else cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


@pytest.mark.parametrize("fmt", ["png16", "npy"])
def test_threaded_files_equal_the_library_writers_in_order(layout, tmp_path, fmt):
    """Each file the writer threads wrote decodes to the same array as the library's writers give for the same
    frame, refined again here one frame after the other and written before the next frame is refined."""
    root, _ = layout
    out = tmp_path / "threaded"
    argv = _run_argv(root, out, "--format", fmt)
    assert main(argv) == 0
    args = _build_parser().parse_args(argv)
    rec = open_recording(root, "folders")
    refiner = _run_module._refiner(args)
    K, baseline = rec.K.float()[None], torch.tensor([float(rec.baseline)])
    ref = tmp_path / "serial"
    for name in ALL:
        (ref / name).mkdir(parents=True)
    state = None
    with torch.no_grad():
        for t in range(T):
            result, state = refiner(*rec[t], K, baseline, state)
            stem, disp, valid = rec.names[t], result.disparity[0, 0], result.valid[0, 0]
            write_disparity(ref / "disparity" / stem, disp, valid, fmt)
            write_mask(ref / "valid" / f"{stem}.png", valid)
            write_confidence(ref / "confidence" / stem, result.confidence[0, 0], fmt)
            write_preview(ref / "preview" / f"{stem}.png",
                          colorize_disparity(disp, args.max_disparity, valid, invalid_color=_run_module._INVALID_RGB))
            # (the run writes the same colours as an indexed-colour PNG; decoded, the pixels are equal)
    for name in ALL:
        files = sorted(p.name for p in (ref / name).iterdir())
        assert sorted(p.name for p in (out / name).iterdir()) == files and len(files) == T
        for file in files:
            a, b = _decoded(out / name / file), _decoded(ref / name / file)
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), (name, file)
    # the last refined map, as read back, is the one written (not a later frame's)
    _, v = read_disparity(out / "disparity" / f"{rec.names[-1]}{'.png' if fmt == 'png16' else '.npy'}")
    assert (v == (result.valid[0, 0] & (result.disparity[0, 0] > 0))).all()


def test_frames_handed_to_the_writer_are_copies():
    x = torch.arange(6, dtype=torch.float32).reshape(2, 3)
    copy = _run_module._own_copy(x)
    x.add_(100)
    assert copy.tolist() == [[0, 1, 2], [3, 4, 5]] and not np.shares_memory(copy, x.numpy())


def test_writer_raises_a_jobs_error_and_drops_the_rest():
    writer = _run_module._Writer(threads=1, depth=1)  # one thread: the jobs run in the order they came
    done = []

    def fail():
        raise OSError(errno.EACCES, "Permission denied")

    writer.submit(fail)
    with pytest.raises(OSError, match="Permission denied"):
        for i in range(100):  # the error comes back at a later submit, or at close
            writer.submit(lambda i=i: done.append(i))
        writer.close()
    writer.close(drop=True)
    assert done == [] and not _writer_threads()


class _Frames:
    """A recording stand-in: frame ``t`` is ``(t, -t)``; reading ``bad`` raises; records which thread read what."""

    def __init__(self, bad: int | None = None):
        self.bad, self.read, self.threads = bad, [], set()

    def __getitem__(self, t: int):
        self.threads.add(threading.get_ident())
        self.read.append(t)
        if t == self.bad:
            raise OSError(f"frame {t}: cannot decode")
        return t, -t


def test_frames_are_read_ahead_in_order_on_another_thread():
    rec = _Frames()
    frames = _run_module._read_ahead(rec, 5)
    first = next(frames)
    assert first == (0, 0)
    got = [first, *frames]
    assert got == [(t, -t) for t in range(5)] and rec.read == list(range(5))
    assert threading.get_ident() not in rec.threads  # (the reads ran beside the caller)


def test_a_read_error_is_raised_at_its_frame_and_nothing_is_read_after_close():
    rec = _Frames(bad=2)
    frames = _run_module._read_ahead(rec, 6)
    assert next(frames) == (0, 0) and next(frames) == (1, -1)
    with pytest.raises(OSError, match="frame 2: cannot decode"):
        next(frames)
    frames.close()
    assert rec.read == [0, 1, 2]  # frame 3 is requested only once frame 2 is taken
    stopped = _Frames()
    frames = _run_module._read_ahead(stopped, 6)
    next(frames)
    frames.close()  # (a run that stops early: the read under way finishes, no other starts)
    assert stopped.read == [0, 1]
