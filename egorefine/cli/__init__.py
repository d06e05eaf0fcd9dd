"""The ``egorefine`` command: refine stereo video with the rig's ego-motion, from the shell.

``egorefine demo`` renders the built-in synthetic sequence (the paper's rig), scores per-frame stereo and the
refiner against its exact ground truth and draws pictures. ``egorefine run`` refines a recorded sequence
(image folders with a calibration file, KITTI raw, KITTI odometry, EuRoC, ROS bags) and writes per-frame disparity,
valid mask, confidence and preview files plus the trajectory in TUM and KITTI formats. ``egorefine eval`` scores
disparity maps and trajectories against truth. ``egorefine run-many`` runs ``run`` on many recordings as Ray
tasks, skipping those that finished (exit status 1 where one failed). ``egorefine info`` prints the processor,
library versions and thread counts (float results differ between CPUs and thread counts: put it beside a bug
report).

Bad input (a missing file, a calibration that does not parse, too few frames, an output folder that already holds
results) ends with one line ``egorefine <command>: error: ...`` on stderr and exit status 2; ``--debug`` shows the
traceback instead.
"""

from __future__ import annotations

import argparse
import sys

from .. import __version__
from ..core import EgorefineError, machine_info
from ..data import PNG_ENCODINGS

# The parser and main() live here, the work of each command in a private module of its own: _demo, _run (with the
# deprecated folder command), _eval; _shared holds what they share.
from ._demo import _demo
from ._eval import _eval
from ._eval import evaluate_disparity_folders as evaluate_disparity_folders
from ._eval import evaluate_trajectory_files as evaluate_trajectory_files
from ._run import _folder, _run, parse_outputs
from ._run_many import _run_many
from ._shared import _FRAME_DIRS

__all__ = ["main", "parse_frame_range"]


# Matcher choices of `egorefine run`: COST or COST+sgm, passed to the refiner as stereo_cost / aggregation.
_MATCHERS = ("sad", "zncc", "census", "sad+sgm", "zncc+sgm", "census+sgm")
_EXAMPLES = """examples:
  egorefine demo --frames 8 --out results/demo
  egorefine run my_rig/ --layout folders --calib my_rig/stereo.yaml --out out/
  egorefine run raw/2011_09_26/2011_09_26_drive_0001_sync --layout kitti-raw --out out/
  egorefine run odometry/dataset/sequences/00 --layout kitti-odometry --frames 0:200 --out out/
  egorefine run V1_01_easy --layout euroc --max-disparity 48 --out out/
  egorefine run rig.bag --layout rosbag --left-topic /cam0/image_raw --right-topic /cam1/image_raw --out out/
  egorefine run-many recordings.txt --out out/ --ray-address 10.0.0.5:6379
  egorefine eval out/ truth/ --traj out/trajectory_tum.txt --gt-traj out/groundtruth_tum.txt --json scores.json
  egorefine info"""


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Help with each option's default appended (where it has one its help does not already state)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if default is None or default is False or default == argparse.SUPPRESS or "default" in text \
                or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)"


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr and exit status 2."""

    def error(self, message: str):  # noqa: D102 - argparse's hook
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _at_least(minimum: int):
    """An argparse type: an int no smaller than ``minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {value}")
        return value

    return parse


def _seconds(text: str) -> float:
    """The ``--pair-tolerance`` type: a finite number of seconds, >= 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not 0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}")
    return value


def _only_one(text: str) -> int:
    """The ``--batch-size`` type: 1 is the only batch size a single sequence can have."""
    if text.strip() != "1":
        raise argparse.ArgumentTypeError(f"only 1 is possible, got {text!r}: the frames of a sequence are refined "
                                         "in order, each from the state the previous one left")
    return 1


def parse_frame_range(text: str) -> slice:
    """``START:STOP`` or ``START:STOP:STEP`` (each part optional, non-negative) as a :class:`slice` of frames.

    Args:
        text: e.g. ``"0:6"`` (frames 0 to 5), ``"100:"`` (from frame 100 on), ``":50:2"`` (every other frame
            of the first 50).

    Returns:
        The slice, ``None`` for parts left out.

    Raises:
        argparse.ArgumentTypeError: not of that form, a negative number, a step below 1 or STOP <= START.

    Example:
        >>> parse_frame_range("0:6"), parse_frame_range("10:")
        (slice(0, 6, None), slice(10, None, None))
    """
    parts = text.split(":")
    if len(parts) not in (2, 3):
        raise argparse.ArgumentTypeError(f"expected START:STOP or START:STOP:STEP, got {text!r}")
    try:
        values = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected integers in START:STOP[:STEP], got {text!r}") from None
    start, stop, step = (values + [None])[:3]
    if any(v is not None and v < 0 for v in (start, stop)) or (step is not None and step < 1):
        raise argparse.ArgumentTypeError(f"expected START, STOP >= 0 and STEP >= 1, got {text!r}")
    if start is not None and stop is not None and stop <= start:
        raise argparse.ArgumentTypeError(f"expected STOP > START, got {text!r}")
    return slice(start, stop, step)


def _info(args: argparse.Namespace) -> int:
    """``egorefine info``: one ``name: value`` line per entry of :func:`egorefine.core.machine_info`."""
    info = machine_info()
    env = info.pop("env")
    for name, value in info.items():
        print(f"{name}: {value}")
    print("env: " + (" ".join(f"{k}={v}" for k, v in env.items()) or "(no thread variables set)"))
    return 0


def _common() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quiet", action="store_true", help="no progress bars or notes on stderr")
    common.add_argument("--debug", action="store_true", help="show the full traceback of an error")
    return common


def _refiner_options(p: argparse.ArgumentParser, max_disparity: int, fusion: str | None = None) -> None:
    p.add_argument("--max-disparity", type=_at_least(2), default=max_disparity, metavar="PX",
                   help="stereo search range in pixels: candidates 0 <= d < PX (must be below the image width)")
    p.add_argument("--verify-every", type=_at_least(1), default=5, metavar="N",
                   help="run stereo matching on every N-th frame (the paper's i; 1 = every frame), predict the rest")
    if fusion is not None:
        p.add_argument("--fusion", default=fusion, choices=["paper", "kalman"],
                       help="how stereo corrects the prediction: the paper's 0.5 px gate and 0.4 gain, or per-pixel "
                            "Kalman fusion of variances")


def _command(sub, common: argparse.ArgumentParser, name: str, summary: str, description: str, func):
    """A subcommand with the common options, the help formatter and its function."""
    p = sub.add_parser(name, parents=[common], formatter_class=_Formatter, help=summary, description=description)
    p.set_defaults(func=func)
    return p


def _build_parser() -> argparse.ArgumentParser:
    from ..data import CAMERAS, LAYOUTS

    parser = _Parser(prog="egorefine", description=__doc__.replace("``", "'"), epilog=_EXAMPLES,
                     formatter_class=_Formatter)
    parser.add_argument("--version", action="version", version=f"egorefine {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    common = _common()

    demo = _command(
        sub, common, "demo", "refine the built-in synthetic sequence and score it against ground truth",
        "Render the built-in stereo sequence (exact ground truth), run per-frame stereo and the refiner "
        "in paper and Kalman mode, print a table of errors and write figures (maps with colour bars, a "
        "disparity row, the trajectory) to --out.",
        _demo,
    )
    demo.add_argument("--frames", type=_at_least(2), default=30, metavar="T",
                      help="number of frames to render (>= 2: the first one has nothing to refine)")
    demo.add_argument("--preset", default="paper", choices=["paper", "kitti"],
                      help="rig: 'paper' (640x480, f = 398 px, B = 0.08 m) or 'kitti' (1242x375, f = 721.5 px, "
                           "B = 0.537 m)")
    demo.add_argument("--height", type=_at_least(16), default=None, metavar="PX",
                      help="image height in pixels (default: the preset's)")
    demo.add_argument("--width", type=_at_least(16), default=None, metavar="PX",
                      help="image width in pixels; the focal length scales with it (default: the preset's)")
    demo.add_argument("--noise", type=float, default=0.01, metavar="STD",
                      help="standard deviation of the rendered sensor noise, in grey units of [0, 1] (0 = ideal "
                           "images; 0.01 is about 2.5 grey levels of 255)")
    demo.add_argument("--seed", type=int, default=0, help="seed of the scene, trajectory and noise")
    _refiner_options(demo, 48)
    demo.add_argument("--threads", type=_at_least(1), default=2, metavar="N", help="CPU threads for torch and kernels")
    demo.add_argument("--out", default="results/demo", metavar="DIR", help="folder for the figures")

    run = _command(
        sub, common, "run", "refine a recorded stereo sequence; write maps, trajectory and run.json",
        "Read a stereo sequence and its calibration (rectifying it where the layout is unrectified), "
        "refine it frame by frame and write to --out: disparity/, valid/ (255 = valid), confidence/ (1 / "
        "(1 + variance), PNG16 stores it as value / 65535), preview/ (colour, grey = invalid), "
        "trajectory_tum.txt and trajectory_kitti.txt (world_T_camera, the formats evo reads; "
        "groundtruth_*.txt too where the recording has poses) and run.json (settings, version, "
        "calibration, timings, frames/s), written last. --outputs chooses the per-frame folders; they are "
        "written on background threads while the next frames are refined.",
        _run,
    )
    run.add_argument("input", metavar="INPUT", help="the sequence: a folder (or, for some layouts, a file) "
                                                    "in --layout")
    run.add_argument("--layout", required=True, choices=LAYOUTS,
                     help="how INPUT is organised: left/right image folders with a calibration file, a KITTI raw "
                          "drive, a KITTI odometry sequence, an EuRoC ASL folder or a ROS bag (a ROS 1 .bag file or "
                          "a ROS 2 bag folder; with --left-topic and --right-topic)")
    run.add_argument("--out", required=True, metavar="DIR", help="output folder (refused if it holds results)")
    run.add_argument("--calib", default=None, metavar="FILE",
                     help="calibration file (OpenCV YAML/JSON, ROS camera_info YAML, KITTI calib); default: the "
                          "one the layout keeps in INPUT (rosbag: the CameraInfo topics)")
    run.add_argument("--camera", default="grey", choices=CAMERAS,
                     help="which camera pair to read where the layout has both (KITTI: grey image_00/01 or image_0/1, "
                          "colour image_02/03 or image_2/3; read as grey either way)")
    run.add_argument("--frames", type=parse_frame_range, default=None, metavar="START:STOP[:STEP]",
                     help="frame range, 0-based, STOP excluded (default: all frames)")
    rosbag = run.add_argument_group("rosbag layout", "the topics of a ROS bag (--layout rosbag only); needs pip "
                                                     "install egorefine[rosbag]")
    rosbag.add_argument("--left-topic", default=None, metavar="TOPIC",
                        help="the left camera's sensor_msgs/Image or CompressedImage topic, e.g. /cam0/image_raw")
    rosbag.add_argument("--right-topic", default=None, metavar="TOPIC", help="the right camera's image topic")
    rosbag.add_argument("--left-info-topic", default=None, metavar="TOPIC",
                        help="the left camera's CameraInfo topic (default: the image topic's sibling camera_info, "
                             "e.g. /cam0/camera_info)")
    rosbag.add_argument("--right-info-topic", default=None, metavar="TOPIC",
                        help="the right camera's CameraInfo topic (default: the sibling camera_info)")
    rosbag.add_argument("--pair-tolerance", type=_seconds, default=None, metavar="S",
                        help="seconds within which left and right header stamps pair; frames without a partner are "
                             "skipped and counted (default: 0.005, or half the median left frame interval where "
                             "that is shorter)")
    _refiner_options(run, 64, fusion="kalman")
    run.add_argument("--matcher", default="sad", choices=_MATCHERS,
                     help="stereo cost (SAD on x-Sobel, ZNCC or census) and aggregation (box window, or +sgm for "
                          "semi-global)")
    run.add_argument("--no-fill", action="store_true",
                     help="Kalman mode with a box matcher: do not fill its holes from census + SGM on verification "
                          "frames (faster, sparser; the filled pixels are less accurate than the box matcher's)")
    run.add_argument("--motion", default="exact", choices=["linear", "robust", "exact"],
                     help="ego-motion solve: the paper's linear eq. 3, robust-weighted, or exact SE(3) reprojection")
    run.add_argument("--format", default="png16", choices=["png16", "npy", "pfm"],
                     help="disparity and confidence files: KITTI 16-bit PNG (1/256 px steps, 0 = invalid), float32 "
                          "npy (NaN = invalid) or PFM (+inf = invalid)")
    run.add_argument("--png", default="fast", choices=sorted(PNG_ENCODINGS),
                     help="PNG encoding of the disparity, confidence and preview files: fast (stored, not deflated: "
                          "larger files, several times cheaper to write) or small (filtered and deflated: smaller, "
                          "slower); the pixels are the same")
    run.add_argument("--outputs", type=parse_outputs, default=",".join(_FRAME_DIRS), metavar="NAME[,NAME...]",
                     help="per-frame files to write, comma-separated: disparity, valid, confidence, preview; 'none' "
                          "writes only the trajectory and run.json")
    run.add_argument("--batch-size", type=_only_one, default=1, metavar="1",
                     help="frames per refiner call; only 1: each frame is predicted from the previous one's "
                          "state, so the frames of one sequence cannot be batched (the library's API batches "
                          "independent sequences)")
    run.add_argument("--device", default="cpu", metavar="DEV", help="torch device: cpu, cuda or cuda:N")
    run.add_argument("--threads", type=_at_least(1), default=None, metavar="N",
                     help="CPU threads for torch and the compiled kernels (default: torch's, the machine's cores)")
    run.add_argument("--overwrite", action="store_true",
                     help="replace the results of an earlier run in --out (its files are deleted first)")
    run.add_argument("--rerun", default=None, metavar="FILE.rrd",
                     help="also write a Rerun recording of every frame (left image, refined depth as a point cloud "
                          "under the camera, validity, confidence, pose and path, statistics); open it with "
                          "'rerun FILE.rrd'. Its folder must exist (or be --out); needs pip install egorefine[rerun]")

    ev = _command(
        sub, common, "eval", "score disparity maps and/or a trajectory against truth",
        "Disparity metrics of the maps in PRED against those in GT, matched by file stem (KITTI PNG16 "
        "with 0 = invalid, PFM or npy; an 'egorefine run' output folder is read from its disparity/), and "
        "RPE / aligned ATE of --traj against --gt-traj (TUM or KITTI format, told by the column count). "
        "Prints tables; --json writes them.",
        _eval,
    )
    ev.add_argument("pred", nargs="?", default=None, metavar="PRED", help="folder of predicted disparity maps")
    ev.add_argument("gt", nargs="?", default=None, metavar="GT", help="folder of true disparity maps")
    ev.add_argument("--traj", default=None, metavar="FILE", help="estimated trajectory (world_T_camera)")
    ev.add_argument("--gt-traj", default=None, metavar="FILE", help="true trajectory of the same frames")
    ev.add_argument("--max-time-difference", type=float, default=0.01, metavar="S",
                    help="seconds: TUM poses are paired by nearest timestamp within this (KITTI files by line)")
    ev.add_argument("--json", default=None, metavar="FILE", help="also write the metrics to this JSON file")

    many = _command(
        sub, common, "run-many", "refine many recordings, one Ray task each; resumable; a summary table",
        "Run 'egorefine run' on every recording of LIST, each as a Ray task (on a local Ray instance, or on "
        "the cluster at --ray-address), each into DIR/NAME (NAME: the last part of its path, made unique). "
        "LIST is a text file, one recording per line: its path (relative to the list's folder), then its "
        "'egorefine run' options, e.g. 'data/V1_01 --layout euroc --frames 0:100' ('#' comments and blank "
        "lines are ignored); or a glob pattern of recordings (quote it), with --layout. A recording whose "
        "DIR/NAME/run.json says it finished is skipped, one without is redone from the start. Prints a table "
        "(frames, frames/s, stereo frames, status) and writes it as DIR/run-many.json. Exit status: 0 when "
        "every recording is done or skipped, 1 when one failed (the others still run), 2 for bad input. "
        "Needs pip install egorefine[ray].",
        _run_many,
    )
    many.add_argument("list", metavar="LIST", help="a list file of recordings, or a glob pattern of recordings")
    many.add_argument("--out", required=True, metavar="DIR", help="folder of the recordings' output folders")
    many.add_argument("--layout", default=None, choices=LAYOUTS,
                      help="--layout of every recording whose line gives none (needed with a glob pattern)")
    many.add_argument("--run-options", default=None, metavar="'OPTIONS'",
                      help="'egorefine run' options for every recording, in one quoted string written with '=', "
                           "e.g. --run-options='--frames 0:100 --max-disparity 48'; a line's own options win")
    many.add_argument("--cpus-per-task", type=_at_least(1), default=None, metavar="N",
                      help="CPUs each recording's task reserves; the run's --threads defaults to it (default: the "
                           "line's --threads, else 2)")
    many.add_argument("--num-cpus", type=_at_least(1), default=None, metavar="N",
                      help="CPUs of the local Ray instance (default: the machine's); not with --ray-address")
    many.add_argument("--ray-address", default=None, metavar="HOST:PORT",
                      help="run on the Ray cluster whose head is there (what 'ray start --head' prints; 'auto': "
                           "the one started on this machine); outputs then go to DIR as the workers see it")
    many.add_argument("--overwrite", action="store_true", help="redo the recordings that finished too")

    _command(sub, common, "info", "print the processor, library versions and thread counts",
             "Print the processor model, the versions of Python, torch, numpy, numba and OpenCV, their thread "
             "counts and the thread-related environment variables in force, one 'name: value' line each.", _info)

    folder = _command(
        sub, common, "folder", "deprecated: use 'run --layout folders'; refine rectified image folders to PFM maps",
        "Deprecated: 'egorefine run INPUT --layout folders --calib FILE' does this and writes every "
        "output. Refines a rectified left/right image-folder sequence with the intrinsics given here and "
        "writes one PFM map per frame (+inf = invalid).",
        _folder,
    )
    folder.add_argument("--left", required=True, metavar="DIR", help="folder of left images (sorted by name)")
    folder.add_argument("--right", required=True, metavar="DIR", help="folder of right images")
    folder.add_argument("--focal", type=float, required=True, metavar="PX", help="focal length of the rectified "
                                                                                 "pair in pixels")
    folder.add_argument("--cx", type=float, required=True, metavar="PX", help="principal point x, pixels")
    folder.add_argument("--cy", type=float, required=True, metavar="PX", help="principal point y, pixels")
    folder.add_argument("--baseline", type=float, required=True, metavar="M", help="baseline in metres (> 0)")
    _refiner_options(folder, 64, fusion="kalman")
    folder.add_argument("--threads", type=_at_least(1), default=2, metavar="N", help="CPU threads")
    folder.add_argument("--out", default="results/folder", metavar="DIR", help="folder for the PFM maps")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``egorefine`` command; returns the exit status (2 for bad input).

    Args:
        argv: the arguments (default: ``sys.argv[1:]``).

    Example:
        >>> main(["eval"])  # nothing to evaluate: one line on stderr, exit status 2
        2
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    args = _build_parser().parse_args(argv)
    args.argv = argv
    try:
        return args.func(args)
    except (EgorefineError, OSError) as err:
        if args.debug:
            raise
        message = " ".join(str(err).split()) or type(err).__name__
        print(f"egorefine {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"egorefine {args.command}: interrupted", file=sys.stderr)
        return 130
