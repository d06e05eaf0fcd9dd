"""`egorefine run-many`: recordings as Ray tasks on a real local Ray instance; outputs equal `egorefine run`'s; a
failed recording reported and retried; finished ones skipped; bad input in one line with exit status 2."""

from __future__ import annotations

import importlib
import json
import shutil
import socket
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import test_cli

from egorefine.cli import main
from egorefine.data import render_sequence

ray = pytest.importorskip("ray")  # the `ray` extra (the dev extra brings it)

_run_many = importlib.import_module("egorefine.cli._run_many")  # egorefine.cli._run_many is also the function

_code, _one_line_error = test_cli._code, test_cli._one_line_error
H, W, T = test_cli.H, test_cli.W, 5
GOOD = ("alpha", "beta")
# The same `egorefine run` options for every recording and for the reference runs (one thread: float results
# depend on the thread count).
OPTIONS = ["--layout", "folders", "--max-disparity", "8", "--verify-every", "2", "--threads", "1"]


def _write_folders_layout(root: Path, seed: int) -> Path:
    seq = render_sequence(num_frames=T, height=H, width=W, seed=seed)
    for side, images in (("left", seq.left), ("right", seq.right)):
        (root / side).mkdir(parents=True)
        for t, img in enumerate(images):
            cv2.imwrite(str(root / side / f"{t:06d}.png"), (img[0].numpy() * 255).round().astype(np.uint8))
    test_cli._write_calibration(root / "calib.yaml", seq.K, seq.baseline)
    return root


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> Path:
    """Three folders layouts: alpha and beta (two rendered scenes) and broken (alpha's images, a calibration file
    that does not parse; ``calib.good`` beside it is the real one)."""
    root = tmp_path_factory.mktemp("recordings")
    for name, seed in zip(GOOD, (3, 5), strict=True):
        _write_folders_layout(root / name, seed)
    broken = Path(shutil.copytree(root / "alpha", root / "broken"))
    (broken / "calib.yaml").rename(broken / "calib.good")
    (broken / "calib.yaml").write_text("%YAML:1.0\nK1: [this is not, a matrix\n")
    return root


@pytest.fixture(scope="module")
def reference(recordings, tmp_path_factory) -> Path:
    """`egorefine run` of each good recording, in this process: what run-many's tasks must reproduce."""
    out = tmp_path_factory.mktemp("reference")
    for name in GOOD:
        assert main(["run", str(recordings / name), "--out", str(out / name), *OPTIONS, "--quiet"]) == 0
    return out


@pytest.fixture(scope="module")
def ray_instance():
    """One local Ray instance with 2 CPUs for the tests of this file, started the way the command starts it; the
    command then uses it (and leaves it running) instead of starting its own."""
    started = _run_many._start_ray(None, num_cpus=2, quiet=True)
    yield
    if started:
        ray.shutdown()


def _summary(out: Path) -> dict:
    return json.loads((out / "run-many.json").read_text())


def _statuses(out: Path) -> dict[str, str]:
    return {r["name"]: r["status"] for r in _summary(out)["recordings"]}


def _assert_same_maps(got: Path, want: Path) -> None:
    for folder in ("disparity", "valid"):
        names = sorted(p.name for p in (want / folder).iterdir())
        assert names and sorted(p.name for p in (got / folder).iterdir()) == names, folder
        for name in names:
            assert (got / folder / name).read_bytes() == (want / folder / name).read_bytes(), f"{folder}/{name}"


def _list(path: Path, *lines: str) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------------------------------ bad input: exit 2
def test_a_line_that_names_no_recording_gives_its_line_number(recordings, tmp_path, capsys):
    lst = _list(tmp_path / "list.txt", "# header", f"{recordings / 'alpha'} {' '.join(OPTIONS)}",
                f"{recordings / 'gamma'} {' '.join(OPTIONS)}")
    out = tmp_path / "out"
    capsys.readouterr()
    assert _code(["run-many", str(lst), "--out", str(out), "--quiet"]) == 2
    line = _one_line_error(capsys.readouterr().err)
    assert f"{lst}:3:" in line and "names no recording" in line and "gamma" in line
    assert not out.exists()


@pytest.mark.parametrize("bad, expected", [
    ("--layout folders", "starts with the option"),
    ("alpha --layout folders --max-disparity zero", "--max-disparity"),
    ("alpha --layout folders --out elsewhere", "--out is chosen by run-many"),
    ("alpha --max-disparity 8", "no --layout"),
    ("alpha --layout folders 'unclosed", "quotation"),
])
def test_bad_lines_give_one_line_and_their_line_number(recordings, tmp_path, capsys, bad, expected):
    lst = _list(recordings / "bad-list.txt", "", bad)  # relative paths are read from the list's folder
    capsys.readouterr()
    assert _code(["run-many", str(lst), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    line = _one_line_error(capsys.readouterr().err)
    assert f"{lst}:2:" in line and expected in line
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv, expected", [
    (["{root}/nothing-*"], "matches no recording"),
    (["{root}/al*"], "needs --layout"),
    (["{root}/no-such-list.txt"], "no such list file"),
    (["{root}/comments.txt", "--layout", "folders"], "names no recording"),
    (["{root}/al*", "--layout", "folders", "--run-options=--frames 0:x"], "--frames"),
    (["{root}/al*", "--layout", "folders", "--num-cpus", "2", "--ray-address", "10.0.0.5:6379"], "--num-cpus"),
])
def test_bad_patterns_and_options_give_one_line(recordings, tmp_path, capsys, argv, expected):
    _list(recordings / "comments.txt", "# nothing here", "")
    capsys.readouterr()
    argv = [a.format(root=recordings) for a in argv]
    assert _code(["run-many", *argv, "--out", str(tmp_path / "out"), "--quiet"]) == 2
    assert expected in _one_line_error(capsys.readouterr().err)
    assert not (tmp_path / "out").exists()


def test_an_unreachable_ray_address_fails_fast_naming_it(recordings, tmp_path, capsys):
    address = f"127.0.0.1:{_free_port()}"  # nothing listens there
    capsys.readouterr()
    t0 = time.perf_counter()
    assert _code(["run-many", str(recordings / "al*"), "--layout", "folders", "--out", str(tmp_path / "out"),
                  "--ray-address", address, "--quiet"]) == 2
    assert time.perf_counter() - t0 < 2 * _run_many._CONNECT_TIMEOUT_S
    line = _one_line_error(capsys.readouterr().err)
    assert f"--ray-address {address}" in line and "cannot reach" in line
    assert not (tmp_path / "out").exists()


def test_without_ray_one_line_names_the_extra(recordings, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    capsys.readouterr()
    assert _code(["run-many", str(recordings / "al*"), "--layout", "folders", "--out", str(tmp_path / "out"),
                  "--quiet"]) == 2
    assert "pip install egorefine[ray]" in _one_line_error(capsys.readouterr().err)


# --------------------------------------------------------------------------------------- on a local Ray instance
def test_tasks_asking_for_more_cpus_than_a_node_has_are_refused(recordings, ray_instance, tmp_path, capsys):
    capsys.readouterr()
    assert _code(["run-many", str(recordings / "al*"), "--layout", "folders", "--out", str(tmp_path / "out"),
                  "--cpus-per-task", "3", "--quiet"]) == 2
    line = _one_line_error(capsys.readouterr().err)
    assert "--cpus-per-task" in line and "3 CPUs" in line
    assert not (tmp_path / "out").exists()


def test_runs_like_run_reports_the_failure_then_resumes(recordings, reference, ray_instance, tmp_path, capsys):
    options = " ".join(OPTIONS)
    lst = _list(recordings / "list.txt", "# two scenes and a broken calibration", "",
                f"alpha {options}", f"{recordings / 'beta'} {options}  # an absolute path", f"broken {options}")
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["run-many", str(lst), "--out", str(out), "--quiet"]) == 1
    table = capsys.readouterr().out
    assert _statuses(out) == {"alpha": "done", "beta": "done", "broken": "failed"}
    for name in GOOD:
        _assert_same_maps(out / name, reference / name)
    rows = {r["name"]: r for r in _summary(out)["recordings"]}
    assert rows["alpha"]["frames"] == T and rows["alpha"]["frames_per_s"] > 0 and rows["alpha"]["stereo_frames"] >= 1
    error = rows["broken"]["error"]
    assert error.startswith("DataError: ") and "calib.yaml does not parse" in error and "\n" not in error
    assert "Traceback" in rows["broken"]["traceback"]
    assert rows["broken"]["frames"] is None and not (out / "broken" / "run.json").exists()
    assert _summary(out)["counts"] == {"done": 2, "skipped": 0, "failed": 1}
    assert [line.split()[0] for line in table.splitlines()[2:]] == ["alpha", "beta", "broken"]
    assert "failed: " in table.splitlines()[-1]

    # Fix the calibration, leave alpha as an interrupted run leaves it (no run.json, a stray file): the second
    # invocation skips beta, redoes alpha from the start and retries broken.
    (recordings / "broken" / "calib.good").replace(recordings / "broken" / "calib.yaml")
    (out / "alpha" / "run.json").unlink()
    (out / "alpha" / "disparity" / "stray.png").write_bytes(b"")
    beta_written = (out / "beta" / "run.json").stat().st_mtime_ns
    assert main(["run-many", str(lst), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert _statuses(out) == {"alpha": "done", "beta": "skipped", "broken": "done"}
    assert (out / "beta" / "run.json").stat().st_mtime_ns == beta_written
    _assert_same_maps(out / "alpha", reference / "alpha")
    _assert_same_maps(out / "broken", reference / "alpha")  # broken holds alpha's images and calibration
    assert _summary(out)["recordings"][1]["frames"] == T  # a skipped recording's figures, from its run.json
    assert "egorefine run-many" in captured.err and "frame" in captured.err  # the progress bar
    assert "2 done, 1 skipped, 0 failed" in captured.err

    # Everything finished: a third invocation only reads the run.json files.
    assert main(["run-many", str(lst), "--out", str(out), "--quiet"]) == 0
    assert set(_statuses(out).values()) == {"skipped"}


def test_a_glob_pattern_with_shared_options(recordings, reference, ray_instance, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run-many", str(recordings / "[ab]*a"), "--layout", "folders", "--out", str(out), "--quiet",
                 f"--run-options={' '.join(OPTIONS[2:])}", "--cpus-per-task", "1"]) == 0
    assert _statuses(out) == {"alpha": "done", "beta": "done"}
    for name in GOOD:
        _assert_same_maps(out / name, reference / name)
    assert {r["cpus"] for r in _summary(out)["recordings"]} == {1}
