"""The `egorefine` command: help, version, errors, `run` on small layouts, `eval` against egorefine.metrics."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from egorefine import __version__
from egorefine.cli import _build_parser, main, parse_frame_range
from egorefine.data import read_kitti_disparity, read_trajectory, render_sequence, write_kitti_disparity, write_tum
from egorefine.metrics import evaluate_disparity, evaluate_trajectory

H, W, T = 48, 64, 5
REPO = Path(__file__).resolve().parents[1]


def _code(argv: list[str]) -> int:
    """main's exit status, whether it returns it or argparse raises SystemExit."""
    try:
        return main(argv)
    except SystemExit as stop:
        return int(stop.code or 0)


def mode_stops_writes(folder: Path) -> bool:
    """Whether ``folder``'s file mode (as set by the caller) stops this user writing in it: root ignores it."""
    probe = folder / "probe"
    try:
        probe.touch()
    except PermissionError:
        return True
    probe.unlink()
    return False


def _one_line_error(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err and lines[0].startswith("egorefine")
    assert ": error: " in lines[0]
    return lines[0]


def _write_calibration(path: Path, K: torch.Tensor, baseline: float) -> Path:
    """An OpenCV stereoCalibrate-style YAML file of two identical, aligned, distortion-free cameras."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in (("K1", K), ("D1", np.zeros(5)), ("K2", K), ("D2", np.zeros(5)), ("R", np.eye(3)),
                       ("T", [[-baseline], [0.0], [0.0]]), ("image_size", [W, H])):
        fs.write(key, np.asarray(value, dtype=np.float64))
    fs.release()
    return path


@pytest.fixture(scope="module")
def layout(tmp_path_factory):
    """A folders layout of a rendered sequence, its truth maps (KITTI PNG) and true trajectory (TUM)."""
    seq = render_sequence(num_frames=T, height=H, width=W, seed=3)
    root = tmp_path_factory.mktemp("layout")
    for side, images in (("left", seq.left), ("right", seq.right)):
        (root / side).mkdir()
        for t, img in enumerate(images):
            cv2.imwrite(str(root / side / f"{t:06d}.png"), (img[0].numpy() * 255).round().astype(np.uint8))
    _write_calibration(root / "calib.yaml", seq.K, seq.baseline)
    (root / "gt").mkdir()
    for t in range(T):
        write_kitti_disparity(root / "gt" / f"{t:06d}.png", seq.disparity[t], ~seq.occluded[t])
    write_tum(root / "gt_tum.txt", seq.poses.double())
    return root, seq


def _run_argv(root: Path, out: Path, *extra: str) -> list[str]:
    return ["run", str(root), "--layout", "folders", "--out", str(out), "--max-disparity", "8",
            "--verify-every", "2", "--threads", "1", "--quiet", *extra]


@pytest.fixture(scope="module")
def run_out(layout, tmp_path_factory):
    root, _ = layout
    out = tmp_path_factory.mktemp("run") / "out"
    assert main(_run_argv(root, out)) == 0
    return out


# ---------------------------------------------------------------- help, version, options


def _subparsers():
    parser = _build_parser()
    action = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return action.choices


@pytest.mark.parametrize("command", ["demo", "run", "eval", "folder"])
def test_help_of_each_subcommand_lists_every_option(command, capsys):
    assert _code([command, "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    for action in _subparsers()[command]._actions:
        for flag in action.option_strings:
            assert flag in text
        assert action.help, f"{command}: {action.dest} has no help text"
        if action.option_strings and action.default not in (None, False) and action.dest != "help":
            assert f"(default: {action.default})" in text or "default" in action.help, action.dest


def test_version(capsys):
    assert _code(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"egorefine {__version__}"


def test_frame_range():
    assert parse_frame_range("0:6") == slice(0, 6)
    assert parse_frame_range(":6:2") == slice(None, 6, 2)
    assert parse_frame_range("3:") == slice(3, None)
    for bad in ("6", "a:b", "5:2", "-1:3", "0:4:0", "1:2:3:4"):
        with pytest.raises(Exception, match="expected"):
            parse_frame_range(bad)


# ---------------------------------------------------------------- run


def test_run_writes_every_output(layout, run_out):
    root, seq = layout
    stems = [f"{t:06d}" for t in range(T)]
    for folder in ("disparity", "valid", "confidence", "preview"):
        assert sorted(p.stem for p in (run_out / folder).iterdir()) == stems, folder
    assert not list(run_out.rglob(".*partial*")), "temporary files left behind"
    report = json.loads((run_out / "run.json").read_text())
    assert report["egorefine_version"] == __version__
    assert report["frames"]["count"] == T and report["frames"]["stereo_ran"] >= 3  # frames 0, 2, 4
    assert report["settings"]["max_disparity"] == 8 and report["settings"]["fusion"] == "kalman"
    np.testing.assert_allclose(report["calibration"]["K"], seq.K.double().numpy(), atol=1e-4)
    assert report["calibration"]["baseline_m"] == pytest.approx(seq.baseline, rel=1e-6)
    assert report["calibration"]["image_size_hw"] == [H, W]
    assert report["timings"]["total_s"] > 0
    assert not (run_out / "groundtruth_tum.txt").exists()  # a folders layout has no poses

    # The maps: KITTI PNG16 close to the truth, mask and preview agree with them, confidence in its scale.
    disp, valid = read_kitti_disparity(run_out / "disparity" / f"{T - 1:06d}.png")
    mask = cv2.imread(str(run_out / "valid" / f"{T - 1:06d}.png"), cv2.IMREAD_UNCHANGED)
    assert mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
    # The mask is the refiner's; the PNG cannot store a valid disparity of 0 (a point at infinity) and marks it
    # invalid, so the two agree wherever the disparity is positive.
    refined = mask == 255
    assert np.array_equal(refined & (disp[0].numpy() > 0), valid[0].numpy())
    scored = valid & ~seq.occluded[T - 1]
    assert scored.float().mean() > 0.7
    assert (disp - seq.disparity[T - 1]).abs()[scored].median() < 0.25
    conf = cv2.imread(str(run_out / "confidence" / f"{T - 1:06d}.png"), cv2.IMREAD_UNCHANGED)
    assert conf.dtype == np.uint16 and conf.shape == (H, W)
    assert (conf[~refined] == 0).all() and (conf[refined] > 0).all()
    preview = cv2.imread(str(run_out / "preview" / f"{T - 1:06d}.png"))
    assert preview.shape == (H, W, 3)
    assert (preview[~refined] == 128).all()  # invalid pixels grey

    # The trajectory in both formats, the same poses, close to the truth once aligned.
    stamps, tum = read_trajectory(run_out / "trajectory_tum.txt")
    none, kitti = read_trajectory(run_out / "trajectory_kitti.txt")
    assert none is None and np.array_equal(stamps, np.arange(T, dtype=np.float64))
    torch.testing.assert_close(tum, kitti, atol=1e-9, rtol=0)
    torch.testing.assert_close(tum[0], torch.eye(4, dtype=torch.float64))
    metrics = evaluate_trajectory(tum, seq.poses.double())
    assert metrics["ate_rmse_m"] < 0.1 * metrics["path_length_m"]


def test_run_no_fill_gives_the_box_matchers_sparser_maps(layout, run_out, tmp_path):
    """Kalman mode fills the box matcher's holes from census + SGM unless --no-fill: the default run's valid masks
    hold more pixels, and run.json records the choice."""
    root, _ = layout
    out = tmp_path / "nofill"
    assert main(_run_argv(root, out, "--no-fill")) == 0
    assert json.loads((out / "run.json").read_text())["settings"]["no_fill"] is True
    assert json.loads((run_out / "run.json").read_text())["settings"]["no_fill"] is False
    count = lambda folder: sum(int((cv2.imread(str(p), cv2.IMREAD_UNCHANGED) > 0).sum())  # noqa: E731
                               for p in sorted((folder / "valid").iterdir()))
    assert count(run_out) > count(out)


def test_run_refuses_an_output_folder_with_results(layout, run_out, tmp_path, capsys):
    root, _ = layout
    before = (run_out / "run.json").read_bytes()
    capsys.readouterr()
    assert _code(_run_argv(root, run_out)) == 2
    assert "--overwrite" in _one_line_error(capsys.readouterr().err)
    assert (run_out / "run.json").read_bytes() == before

    # --overwrite replaces the earlier run, stale frames included.
    copy = tmp_path / "copy"
    shutil.copytree(run_out, copy)
    (copy / "disparity" / "999999.png").write_bytes((copy / "disparity" / "000000.png").read_bytes())
    assert main(_run_argv(root, copy, "--overwrite", "--format", "npy")) == 0
    assert sorted(p.name for p in (copy / "disparity").iterdir()) == [f"{t:06d}.npy" for t in range(T)]
    assert json.loads((copy / "run.json").read_text())["settings"]["format"] == "npy"


def test_run_bad_input_with_overwrite_keeps_the_earlier_run(layout, run_out, tmp_path):
    root, _ = layout
    copy = tmp_path / "copy"
    shutil.copytree(run_out, copy)
    assert _code(_run_argv(tmp_path / "nowhere", copy, "--overwrite")) == 2
    assert (copy / "run.json").read_bytes() == (run_out / "run.json").read_bytes()


def _kitti_row(M: torch.Tensor) -> str:
    return " ".join(f"{v:.12e}" for v in M.double().reshape(-1).tolist())


def test_run_kitti_odometry_layout_with_poses(layout, tmp_path):
    """A KITTI odometry sequence (calib.txt, image_0/1, times.txt, poses/XX.txt) written here: every output."""
    root, seq = layout
    sequence = tmp_path / "dataset" / "sequences" / "07"
    for src, dst in (("left", "image_0"), ("right", "image_1")):
        shutil.copytree(root / src, sequence / dst)
    P0 = torch.cat([seq.K.double(), torch.zeros(3, 1, dtype=torch.float64)], dim=1)
    P1 = P0.clone()
    P1[0, 3] = -float(seq.K[0, 0]) * seq.baseline
    (sequence / "calib.txt").write_text("".join(f"P{i}: {_kitti_row(P)}\n" for i, P in enumerate((P0, P1, P0, P1))))
    stamps = 0.1 * np.arange(T)
    (sequence / "times.txt").write_text("".join(f"{s:.6e}\n" for s in stamps))
    (tmp_path / "dataset" / "poses").mkdir()
    (tmp_path / "dataset" / "poses" / "07.txt").write_text("".join(_kitti_row(P[:3]) + "\n" for P in seq.poses))
    out = tmp_path / "out"
    assert main(["run", str(sequence), "--layout", "kitti-odometry", "--out", str(out), "--max-disparity", "8",
                 "--verify-every", "2", "--threads", "1", "--quiet", "--format", "pfm"]) == 0
    for folder in ("disparity", "valid", "confidence", "preview"):
        assert len(list((out / folder).iterdir())) == T, folder
    report = json.loads((out / "run.json").read_text())
    assert report["frames"]["has_groundtruth_poses"] and report["calibration"]["rectified_input"]
    gt_stamps, gt = read_trajectory(out / "groundtruth_tum.txt")
    np.testing.assert_allclose(gt_stamps, stamps, atol=1e-9)
    torch.testing.assert_close(read_trajectory(out / "groundtruth_kitti.txt")[1], seq.poses.double(), atol=1e-9,
                               rtol=0)
    # The rendered poses are float32, orthonormal to ~1e-7; a TUM quaternion is exactly a rotation.
    torch.testing.assert_close(gt, seq.poses.double(), atol=1e-6, rtol=0)
    assert main(["eval", str(out), str(root / "gt"), "--traj", str(out / "trajectory_kitti.txt"),
                 "--gt-traj", str(out / "groundtruth_kitti.txt"), "--json", str(tmp_path / "e.json")]) == 0
    scores = json.loads((tmp_path / "e.json").read_text())
    assert scores["disparity"]["frames"] == T and scores["disparity"]["metrics"]["epe"] < 0.3
    assert scores["trajectory"]["ate_rmse_m"] < 0.1 * scores["trajectory"]["path_length_m"]


def test_run_euroc_clip(euroc_root, tmp_path):
    out = tmp_path / "euroc"
    assert main(["run", str(euroc_root), "--layout", "euroc", "--frames", "0:6", "--max-disparity", "24",
                 "--threads", "1", "--quiet", "--out", str(out)]) == 0
    report = json.loads((out / "run.json").read_text())
    assert report["frames"]["count"] == 6 and report["settings"]["frames"] == "0:6"
    assert report["calibration"]["rectified_input"] is False
    assert len(list((out / "disparity").glob("*.png"))) == 6
    est_t, est = read_trajectory(out / "trajectory_tum.txt")
    gt_t, gt = read_trajectory(out / "groundtruth_tum.txt")
    assert est.shape == gt.shape == (6, 4, 4) and np.array_equal(est_t, gt_t)
    torch.testing.assert_close(est[0], gt[0], atol=1e-9, rtol=0)  # starts at the first true pose
    assert evaluate_trajectory(est, gt)["ate_rmse_m"] < 0.02


# ---------------------------------------------------------------- eval


def test_eval_matches_egorefine_metrics(layout, run_out, tmp_path, capsys):
    root, seq = layout
    capsys.readouterr()
    out_json = tmp_path / "eval.json"
    assert main(["eval", str(run_out), str(root / "gt"), "--traj", str(run_out / "trajectory_tum.txt"),
                 "--gt-traj", str(root / "gt_tum.txt"), "--json", str(out_json)]) == 0
    printed = capsys.readouterr().out
    assert "epe" in printed and "ate_rmse_m" in printed
    report = json.loads(out_json.read_text())

    preds = [read_kitti_disparity(run_out / "disparity" / f"{t:06d}.png") for t in range(T)]
    truths = [read_kitti_disparity(root / "gt" / f"{t:06d}.png") for t in range(T)]
    direct = evaluate_disparity(torch.stack([p[0] for p in preds]), torch.stack([g[0] for g in truths]),
                                torch.stack([p[1] for p in preds]), torch.stack([g[1] for g in truths]))
    assert report["disparity"]["frames"] == T
    for key, value in direct.items():
        assert report["disparity"]["metrics"][key] == pytest.approx(value, rel=1e-6, abs=1e-9), key
    assert direct["epe"] < 0.3 and 0.7 < direct["density"] <= 1.0

    est = read_trajectory(run_out / "trajectory_tum.txt")[1]
    expected = evaluate_trajectory(est, seq.poses.double())
    for key, value in expected.items():
        assert report["trajectory"][key] == pytest.approx(value, rel=1e-6, abs=1e-9), key


def test_eval_pairs_tum_files_by_timestamp(layout, tmp_path):
    _, seq = layout
    poses = seq.poses.double()
    write_tum(tmp_path / "gt.txt", poses, np.arange(T) * 0.1)
    # The estimate lacks the first frame and its clock is 3 ms off: pairing by time, not by line.
    write_tum(tmp_path / "est.txt", poses[1:], np.arange(1, T) * 0.1 + 0.003)
    assert main(["eval", "--traj", str(tmp_path / "est.txt"), "--gt-traj", str(tmp_path / "gt.txt"),
                 "--json", str(tmp_path / "e.json")]) == 0
    report = json.loads((tmp_path / "e.json").read_text())["trajectory"]
    assert report["frames"] == T - 1 and report["ate_rmse_m"] < 1e-9 and report["rpe_translation_rmse_m"] < 1e-9


# ---------------------------------------------------------------- bad input


def _bad_inputs(root: Path, tmp: Path) -> dict[str, list[str]]:
    (tmp / "bad").mkdir(exist_ok=True)
    for side in ("left", "right"):
        shutil.copytree(root / side, tmp / "bad" / side, dirs_exist_ok=True)
    (tmp / "bad" / "calib.yaml").write_text("%YAML:1.0\nK1: [not, a, matrix\n")
    (tmp / "ragged.txt").write_text("0 0 0 0 0 0 0 1\n1 0 0\n")
    return {
        "missing input": _run_argv(tmp / "nowhere", tmp / "o1"),
        "bad layout": ["run", str(root), "--layout", "bogus", "--out", str(tmp / "o2")],
        "calibration that does not parse": _run_argv(tmp / "bad", tmp / "o3"),
        "too few frames": _run_argv(root, tmp / "o4", "--frames", "0:1"),
        "bad frame range": _run_argv(root, tmp / "o5", "--frames", "4:2"),
        "max disparity not below the width": _run_argv(root, tmp / "o6", "--max-disparity", "64"),
        "batch size": _run_argv(root, tmp / "o7", "--batch-size", "4"),
        "eval with nothing": ["eval"],
        "eval missing folder": ["eval", str(tmp / "nowhere"), str(root / "gt")],
        "eval ragged trajectory": ["eval", "--traj", str(tmp / "ragged.txt"), "--gt-traj", str(root / "gt_tum.txt")],
        "demo one frame": ["demo", "--frames", "1"],
    }


def test_bad_input_gives_one_line_and_exit_status_2(layout, tmp_path, capsys):
    root, _ = layout
    for name, argv in _bad_inputs(root, tmp_path).items():
        capsys.readouterr()
        assert _code(argv) == 2, name
        _one_line_error(capsys.readouterr().err)
        assert not (tmp_path / "o1").exists() and not (tmp_path / "o4" / "run.json").exists(), name


def test_console_command_error_and_debug(tmp_path):
    argv = [sys.executable, "-m", "egorefine.cli", "run", str(tmp_path / "nowhere"), "--layout", "folders",
            "--out", str(tmp_path / "o")]
    done = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    line = _one_line_error(done.stderr)
    assert "nowhere" in line
    # --debug lets the error through, traceback and all (in-process: a second interpreter start is slow).
    with pytest.raises(FileNotFoundError, match="nowhere"):
        main([*argv[3:], "--debug"])


# ---------------------------------------------------------------- demo


def test_demo_prints_a_table_and_writes_its_pictures(tmp_path, capsys):
    assert main(["demo", "--frames", "3", "--height", "48", "--width", "64", "--max-disparity", "8",
                 "--verify-every", "2", "--threads", "1", "--quiet", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "kalman mode" in printed and "nan" not in printed and "warm-up" in printed
    # OpenCV's rows, and the sentence under the table computed from the table's own numbers
    rows = {line.split("  ")[0]: line.split() for line in printed.splitlines()
            if line.startswith(("OpenCV", "kalman mode"))}
    sgbm, kalman = rows["OpenCV SGBM, per frame"], next(v for k, v in rows.items() if k.startswith("kalman"))
    assert "OpenCV StereoBM, per frame" in rows
    epe, common = -7, -4  # columns from the right: EPE, bad-0.5, density, EPE common, bad-0.5 common, frames, ms
    sentence = next(line for line in printed.splitlines() if "against OpenCV SGBM" in line)
    assert f"EPE {kalman[epe]} px against {sgbm[epe]}" in sentence
    assert f"{kalman[common]} against {sgbm[common]} on the pixels every row marks valid" in sentence
    for name in ("demo_row.png", "demo_maps.png", "demo_trajectory.png"):
        image = cv2.imread(str(tmp_path / name))
        assert image is not None and image.shape[0] > 200, name


def test_demo_verdict_says_lower_higher_faster_from_the_numbers():
    from egorefine.cli._demo import _verdict

    ours = {"epe": 0.2, "epe common": 0.3, "density": 0.9, "ms": 10.0}
    theirs = {"epe": 0.4, "epe common": 0.25, "density": 0.8, "ms": 20.0}
    text = _verdict("ours", ours, theirs)
    assert "0.200 px against 0.400 on the pixels each marks valid (0.50x, lower)" in text
    assert "0.300 against 0.250 on the pixels every row marks valid (1.20x, higher)" in text
    assert "density 0.900 against 0.800" in text and "10.0 against 20.0 ms/frame (0.50x, faster)" in text
