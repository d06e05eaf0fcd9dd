"""``egorefine run-many``: many recordings, one Ray task each, resumable, with one progress bar and a summary.

The driver (this process) reads the list, checks every line before anything runs, connects to Ray (a local
instance it starts, an existing cluster at ``--ray-address``, or the Ray this Python process has already
initialised), skips the recordings whose ``run.json`` says they finished, and submits one task per remaining
recording. Each task runs :func:`egorefine.cli._run._run`, the code of ``egorefine run``, in the Ray worker's
process with ``--quiet`` and ``--overwrite`` (a folder without a finished ``run.json`` holds the remains of an
interrupted or failed run, which are replaced) and reports its frames to a small progress actor, which the driver
reads for its bar. Ray is the ``ray`` extra (``pip install egorefine[ray]``), imported only here.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import glob
import io
import json
import logging
import os
import shlex
import socket
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from .. import __version__
from ..core import MissingExtraError, ValueRangeError, require_extra
from ._shared import _RUN_JSON, _table, _write_json

__all__ = ["RayNotInstalledError", "RecordingJob", "parse_recording_list", "require_ray"]

#: The summary ``egorefine run-many`` writes into its ``--out`` folder.
RUN_MANY_JSON = "run-many.json"
# Seconds the driver waits for a TCP connection to --ray-address before calling it unreachable: ray.init itself
# retries an unreachable address for minutes.
_CONNECT_TIMEOUT_S = 3.0
# The ports Ray listens on when an address gives none: the head's GCS, and the Ray Client server for ray://.
_GCS_PORT, _CLIENT_PORT = 6379, 10001
# How often the driver looks at finished tasks and the frames the running ones have refined.
_POLL_S = 0.25
# CPUs each task reserves (and the run's torch threads) where neither --cpus-per-task nor the line's --threads say:
# two keeps the writer threads and the refiner busy without one recording taking a whole node.
_DEFAULT_TASK_CPUS = 2


class RayNotInstalledError(MissingExtraError):
    """Ray, an optional dependency (the ``ray`` extra), is not installed.

    Example:
        >>> issubclass(RayNotInstalledError, ImportError)  # ``except ImportError`` still catches it
        True
    """


# the module, or a one-line error naming the extra that installs it
require_ray = functools.partial(require_extra, "ray", "ray", "Ray", RayNotInstalledError)


@dataclass
class RecordingJob:
    """One recording of ``egorefine run-many``: where it came from, its ``egorefine run`` options and its output.

    Attributes:
        name: the output folder's name inside ``--out`` (unique within the list).
        input: the recording's path, absolute.
        source: where it was named: ``LIST:LINE`` or the glob pattern.
        run_args: the parsed options of ``egorefine run`` for it, ``--out`` and ``--quiet`` included.
        cpus: CPUs its Ray task reserves.
        result: what became of it: ``status`` (``done``, ``skipped`` or ``failed``), ``frames``, ``frames_per_s``,
            ``stereo_frames``, ``error`` (one line) and ``traceback`` where it failed, ``seconds`` where it ran.
    """

    name: str
    input: str
    source: str
    run_args: argparse.Namespace
    cpus: int
    result: dict = field(default_factory=dict)


def _option_given(tokens: list[str], option: str) -> bool:
    return any(tok == option or tok.startswith(option + "=") for tok in tokens)


def _parse_run_options(tokens: list[str], where: str) -> argparse.Namespace:
    """``tokens`` (``INPUT`` and options) parsed by ``egorefine run``'s own parser; its one-line usage error
    becomes a :class:`ValueRangeError` that starts with ``where``."""
    from . import _build_parser

    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured), contextlib.redirect_stdout(captured):
            return _build_parser().parse_args(["run", *tokens])
    except SystemExit:
        text = " ".join(captured.getvalue().split())
        text = text.removeprefix("egorefine run: error: ").split(" (see 'egorefine run --help')")[0]
        raise ValueRangeError(f"{where}: {text or 'not options of egorefine run'}") from None


def _unique_name(path: str, taken: set[str]) -> str:
    """The last part of ``path`` (``rec``), or ``rec-2``, ``rec-3``, ... where an earlier recording took it."""
    base = Path(path).name or "recording"
    name, k = base, 1
    while name in taken:
        k += 1
        name = f"{base}-{k}"
    taken.add(name)
    return name


def _make_job(path: str, options: list[str], where: str, out: Path, layout: str | None, cpus_per_task: int | None,
              taken: set[str], base: Path) -> RecordingJob:
    """The job of one recording: its path made absolute (against ``base``), options checked by the run parser."""
    if _option_given(options, "--out"):
        raise ValueRangeError(f"{where}: --out is chosen by run-many (each recording goes to its --out DIR/NAME); "
                              "remove it from the line")
    if _option_given(options, "--overwrite"):
        raise ValueRangeError(f"{where}: --overwrite is run-many's to give (it then redoes finished recordings "
                              "too); remove it from the line")
    if path.startswith("-"):
        raise ValueRangeError(f"{where}: names no recording: the line starts with the option {path!r}; put the "
                              "recording's path first")
    absolute = Path(os.path.abspath(base / os.path.expanduser(path)))
    if not absolute.exists():
        raise ValueRangeError(f"{where}: {path!r} names no recording: no such file or folder ({absolute})")
    if layout is not None and not _option_given(options, "--layout"):
        options = ["--layout", layout, *options]
    if not _option_given(options, "--layout"):
        raise ValueRangeError(f"{where}: no --layout for {path!r}; give it on the line or to run-many")
    name = _unique_name(str(absolute), taken)
    args = _parse_run_options([str(absolute), *options, "--out", str(out / name), "--quiet"], where)
    for attr in ("calib", "rerun"):  # relative to the list's folder, like the recording's path
        if getattr(args, attr, None) is not None:
            setattr(args, attr, os.path.abspath(base / os.path.expanduser(getattr(args, attr))))
    cpus = cpus_per_task or args.threads or _DEFAULT_TASK_CPUS
    if args.threads is None:
        args.threads = cpus
    args.argv = ["run", str(absolute), *options, "--out", str(out / name), "--quiet"]
    return RecordingJob(name=name, input=str(absolute), source=where, run_args=args, cpus=cpus)


def parse_recording_list(spec: str, out: str | os.PathLike, layout: str | None = None,
                         run_options: str | None = None, cpus_per_task: int | None = None) -> list[RecordingJob]:
    """The recordings ``egorefine run-many`` refines: from a list file or a glob pattern, every line checked.

    A list file names one recording per line: its path (relative paths are taken from the list's folder), then
    its ``egorefine run`` options, shell-quoted, e.g. ``data/V1_01 --layout euroc --frames 0:100``; ``#`` starts
    a comment, blank lines are skipped. Anything else is read as a glob pattern (``**`` recurses), every match a
    recording. ``layout`` and ``run_options`` apply to every recording; a line's own options come after them and
    win. Each recording goes to ``out/NAME``, NAME the last part of its path, made unique with ``-2``, ``-3``...
    in list order (so a rerun with the same list finds its folders again).

    Args:
        spec: the list file, or a glob pattern of recordings.
        out: the folder the recordings' output folders go into (made absolute: a task may run elsewhere).
        layout: ``--layout`` of every recording that does not give its own; needed with a glob pattern.
        run_options: more ``egorefine run`` options for every recording, shell-quoted in one string.
        cpus_per_task: CPUs each task reserves; default: the recording's ``--threads``, else 2. The run's
            ``--threads`` defaults to it.

    Returns:
        One :class:`RecordingJob` per recording, in list (or sorted glob) order.

    Raises:
        ValueRangeError: a line that names no existing recording, has no ``--layout`` or gives an option ``egorefine
            run`` refuses, ``--out`` or ``--overwrite`` on a line, a pattern that matches nothing, a list with no
            recording; each message names ``LIST:LINE`` or the pattern.

    Example:
        >>> import pathlib, tempfile
        >>> root = pathlib.Path(tempfile.mkdtemp())
        >>> (root / "V1_01").mkdir()
        >>> _ = (root / "list.txt").write_text("# two ranges of one recording\\nV1_01 --frames 0:50\\n"
        ...                                    "V1_01 --frames 50:100 --threads 4\\n")
        >>> jobs = parse_recording_list(str(root / "list.txt"), root / "out", layout="euroc")
        >>> [(job.name, job.source.rsplit(":", 1)[1], job.run_args.frames, job.cpus) for job in jobs]
        [('V1_01', '2', slice(0, 50, None), 2), ('V1_01-2', '3', slice(50, 100, None), 4)]
    """
    out = Path(os.path.abspath(out))  # the tasks' working folder need not be this one (another node's, say)
    try:
        shared = shlex.split(run_options or "")
    except ValueError as err:
        raise ValueRangeError(f"--run-options: {err}: {run_options!r}") from None
    taken: set[str] = set()
    jobs = []
    if Path(spec).is_file():
        for number, line in enumerate(Path(spec).read_text().splitlines(), start=1):
            where = f"{spec}:{number}"
            try:
                tokens = shlex.split(line, comments=True)
            except ValueError as err:
                raise ValueRangeError(f"{where}: {err}: {line.strip()!r}") from None
            if tokens:
                jobs.append(_make_job(tokens[0], [*shared, *tokens[1:]], where, out, layout, cpus_per_task, taken,
                                      Path(spec).parent))
        if not jobs:
            raise ValueRangeError(f"{spec}: the list names no recording (only comments and blank lines)")
        return jobs
    if not glob.has_magic(spec):
        raise ValueRangeError(f"{spec!r}: no such list file (and not a glob pattern of recordings)")
    matches = sorted(glob.glob(os.path.expanduser(spec), recursive=True))
    if not matches:
        raise ValueRangeError(f"{spec!r}: the pattern matches no recording")
    if layout is None:
        raise ValueRangeError(f"{spec!r}: a glob pattern needs --layout (it applies to every recording)")
    return [_make_job(path, shared, spec, out, layout, cpus_per_task, taken, Path.cwd()) for path in matches]


def _finished_report(out: Path) -> dict | None:
    """``out/run.json`` where it is a finished run's (written last, so its presence means the run finished)."""
    try:
        report = json.loads((out / _RUN_JSON).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(report, dict) or not isinstance(report.get("frames"), dict) or "timings" not in report:
        return None
    return report


def _figures(report: dict) -> dict:
    """Frames, frames/s and stereo frames of a finished run's run.json."""
    return {"frames": report["frames"].get("count"), "frames_per_s": report["timings"].get("frames_per_s"),
            "stereo_frames": report["frames"].get("stereo_ran")}


def _one_line(err: BaseException, first_line: bool = False) -> str:
    """``Type: message`` on one line (only the message's first line where ``first_line``: Ray's errors carry the
    remote traceback below it)."""
    text = str(err).strip()
    text = text.splitlines()[0] if first_line and text else text
    return f"{type(err).__name__}: {' '.join(text.split())}".rstrip(": ")


class _Progress:
    """A Ray actor: the frames each running recording has refined and its frame count, for the driver's bar."""

    def __init__(self):
        self.counts: dict[str, tuple[int, int]] = {}

    def report(self, name: str, done: int, total: int) -> None:
        self.counts[name] = (done, total)

    def read(self) -> dict[str, tuple[int, int]]:
        return dict(self.counts)


def _run_recording(name: str, run_args: argparse.Namespace, reporter=None) -> dict:
    """The Ray task: ``egorefine run`` for one recording in this worker's process; never raises for a bad recording.

    Returns:
        ``status`` ``done`` with the run.json's figures, or ``failed`` with the error in one line and its
        ``traceback``; ``seconds``.
    """
    from ._run import _run

    t0 = time.perf_counter()
    on_progress = None if reporter is None else (lambda done, total: reporter.report.remote(name, done, total))
    run_args.overwrite = True  # no finished run.json there (the driver skipped those): remains of an earlier try
    try:
        _run(run_args, on_progress=on_progress)
        result = {"status": "done", **_figures(json.loads((Path(run_args.out) / _RUN_JSON).read_text()))}
    except (Exception, SystemExit) as err:  # noqa: BLE001 - one recording's failure is reported, the rest go on
        result = {"status": "failed", "error": _one_line(err), "traceback": traceback.format_exc()}
    return {**result, "seconds": time.perf_counter() - t0}


def _probe(address: str) -> None:
    """Fail fast where nothing accepts a TCP connection at ``address`` (``HOST[:PORT]`` or ``ray://HOST[:PORT]``;
    ``auto`` is left to Ray, which reads the address of the cluster started on this machine)."""
    if address == "auto":
        return
    client = address.startswith("ray://")
    hostport = address.removeprefix("ray://").rstrip("/")
    host, sep, port = hostport.rpartition(":")
    if not sep or "]" in port:  # no port (or an IPv6 address without one)
        host, port = hostport, str(_CLIENT_PORT if client else _GCS_PORT)
    host = host.strip("[]")
    try:
        port_number = int(port)
    except ValueError:
        raise ValueRangeError(f"--ray-address {address}: expected HOST:PORT, e.g. 10.0.0.5:6379") from None
    try:
        with socket.create_connection((host, port_number), timeout=_CONNECT_TIMEOUT_S):
            pass
    except OSError as err:
        reason = "timed out" if isinstance(err, TimeoutError) else (err.strerror or type(err).__name__)
        raise ValueRangeError(f"--ray-address {address}: cannot reach a Ray head there within "
                              f"{_CONNECT_TIMEOUT_S:g} s ({reason}); start one with 'ray start --head' or check "
                              "the address") from None


def _start_ray(address: str | None, num_cpus: int | None, quiet: bool) -> bool:
    """Connect to Ray: the instance this process already has, the cluster at ``address``, or a new local one with
    ``num_cpus`` CPUs. Returns whether this call connected (so the caller shuts it down again)."""
    ray = require_ray()
    if address is not None:
        _probe(address)
    if ray.is_initialized():
        return False
    level = logging.ERROR if quiet else logging.WARNING
    try:
        if address is None:
            ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False, logging_level=level)
        else:
            ray.init(address=address, log_to_driver=False, logging_level=level)
    except (ConnectionError, RuntimeError, ValueError) as err:
        where = f"--ray-address {address}" if address is not None else "a local Ray instance"
        raise ValueRangeError(f"{where}: Ray did not start or connect: {' '.join(str(err).split())}") from None
    return True


def _check_cpus(ray, jobs: list[RecordingJob]) -> None:
    """Refuse tasks that ask for more CPUs than any node has: Ray would keep them waiting for ever."""
    largest = max((node.get("Resources", {}).get("CPU", 0) for node in ray.nodes() if node.get("Alive")), default=0)
    wanted = max(job.cpus for job in jobs)
    if wanted > largest:
        raise ValueRangeError(f"--cpus-per-task: a task asks for {wanted} CPUs; the largest node of the Ray cluster "
                              f"has {largest:g} (lower --cpus-per-task or the lines' --threads)")


def _run_tasks(ray, jobs: list[RecordingJob], quiet: bool) -> None:
    """Submit one task per job, wait for all of them (the bar showing frames), fill in each job's ``result``."""
    from tqdm import tqdm

    reporter = None if quiet else ray.remote(num_cpus=0)(_Progress).remote()
    task = ray.remote(_run_recording)
    pending = {task.options(num_cpus=job.cpus, max_retries=0, name=f"egorefine run {job.name}")
               .remote(job.name, job.run_args, reporter): job for job in jobs}
    # The bar counts frames of every recording to refine; a recording's count joins the total when its task has
    # opened it (ray schedules them as CPUs free up). Same look as egorefine.core.progress's bars.
    bar = None if quiet else tqdm(total=0, desc="egorefine run-many", unit="frame", leave=False, dynamic_ncols=True)
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=_POLL_S)
            for ref in ready:
                job = pending.pop(ref)
                try:
                    job.result = ray.get(ref)
                except ray.exceptions.RayError as err:  # the worker died (killed, out of memory), not the run
                    job.result = {"status": "failed", "error": _one_line(err, first_line=True),
                                  "traceback": str(err)}
            if bar is not None:
                counts = ray.get(reporter.read.remote())
                failed = {job.name for job in jobs if job.result.get("status") == "failed"}
                bar.total = sum(done if name in failed else total for name, (done, total) in counts.items())
                bar.n = sum(done for done, _ in counts.values())
                bar.set_postfix_str(f"{len(jobs) - len(pending)}/{len(jobs)} recordings", refresh=False)
                bar.refresh()
    except BaseException:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise
    finally:
        if bar is not None:
            bar.close()


def _summary(jobs: list[RecordingJob]) -> str:
    rows = []
    for job in jobs:
        r = job.result
        fps = r.get("frames_per_s")
        rows.append([job.name, "-" if r.get("frames") is None else r["frames"], "-" if fps is None else float(fps),
                     "-" if r.get("stereo_frames") is None else r["stereo_frames"],
                     r["status"] + (f": {r['error']}" if r.get("error") else "")])
    return _table(rows, ["recording", "frames", "frames/s", "stereo", "status"])


def _run_many(args: argparse.Namespace) -> int:
    """``egorefine run-many``: exit status 0 where every recording is done or skipped, 1 where one failed."""
    ray = require_ray()
    if args.num_cpus is not None and args.ray_address is not None:
        raise ValueRangeError("--num-cpus sizes a local Ray instance; a cluster at --ray-address has its own CPUs")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueRangeError(f"--out: {str(out)!r} exists and is not a folder")
    jobs = parse_recording_list(args.list, out, layout=args.layout, run_options=args.run_options,
                                cpus_per_task=args.cpus_per_task)
    t0 = time.perf_counter()
    todo = []
    for job in jobs:
        report = None if args.overwrite else _finished_report(out / job.name)
        if report is not None:
            job.result = {"status": "skipped", **_figures(report)}
        else:
            todo.append(job)
    started = False
    if todo:
        started = _start_ray(args.ray_address, args.num_cpus, args.quiet)
        try:
            _check_cpus(ray, todo)
            out.mkdir(parents=True, exist_ok=True)
            _run_tasks(ray, todo, args.quiet)
        finally:
            if started:
                ray.shutdown()
    counts = {status: sum(job.result["status"] == status for job in jobs) for status in ("done", "skipped", "failed")}
    out.mkdir(parents=True, exist_ok=True)
    _write_json(out / RUN_MANY_JSON, {
        "egorefine_version": __version__,
        "command": ["egorefine", *(args.argv or [])],
        "list": args.list,
        "ray_address": args.ray_address,
        "total_s": time.perf_counter() - t0,
        "counts": counts,
        "recordings": [{"name": job.name, "input": job.input, "source": job.source, "out": job.run_args.out,
                        "cpus": job.cpus, "run_command": ["egorefine", *job.run_args.argv],
                        "frames": None, "frames_per_s": None, "stereo_frames": None, "error": None, **job.result}
                       for job in jobs],
    })
    print(_summary(jobs))
    if not args.quiet:
        print(f"egorefine run-many: {counts['done']} done, {counts['skipped']} skipped, {counts['failed']} failed "
              f"-> {out / RUN_MANY_JSON}", file=sys.stderr)
    return 1 if counts["failed"] else 0
