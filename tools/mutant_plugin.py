"""A pytest plugin that plants one named defect in egorefine before the tests import it (``tools/mutants.py``).

Loaded with ``-p mutant_plugin`` (``tools/`` on ``PYTHONPATH``); the defect is named by the environment variable
``EGOREFINE_MUTANT`` (unset or empty: no defect, the baseline). The plugin module is imported while pytest starts,
before ``conftest.py`` and the test modules, so every ``from egorefine... import name`` in a test sees the patched
object. Library files are never edited: each defect replaces functions in memory only.

A function is replaced in every ``egorefine`` module that binds it (``from .solve import solve_ego_motion`` makes a
second binding in ``egorefine.motion`` and one in ``egorefine.refine.refiner``): :func:`_replace_everywhere` walks
the imported package and swaps each binding that is the original object. The defects act above the point where a
stage picks its compiled CPU kernel or its torch path (:func:`egorefine.core.use_compiled`), so both paths carry
them: the sub-pixel defect forces the matcher's ``subpixel`` argument, which both its numba kernels and its torch
path read.

Example (what ``tools/mutants.py`` runs):

    EGOREFINE_MUTANT=identity-motion PYTHONPATH=tools python -m pytest -p mutant_plugin tests/refine/test_refiner.py
"""

from __future__ import annotations

import functools
import importlib
import os
import pkgutil
import sys

ENV = "EGOREFINE_MUTANT"


def _import_all() -> None:
    """Import every egorefine module, so that every binding of a function exists before it is replaced."""
    import egorefine

    for info in pkgutil.walk_packages(egorefine.__path__, "egorefine."):
        if info.name.endswith("__main__"):
            continue
        importlib.import_module(info.name)


def _replace_everywhere(original, replacement) -> int:
    """Rebind ``original`` to ``replacement`` in every imported egorefine module; returns how many bindings."""
    count = 0
    for name, module in list(sys.modules.items()):
        if module is None or not (name == "egorefine" or name.startswith("egorefine.")):
            continue
        for attr, value in list(vars(module).items()):
            if value is original:
                setattr(module, attr, replacement)
                count += 1
    if count == 0:
        raise RuntimeError(f"mutant: no binding of {original!r} found")
    return count


def _keep_prediction() -> None:
    """Verification frames keep the prediction: the correction step returns it unchanged."""
    from egorefine.refine.correct import Correction
    from egorefine.refine.refiner import EgoMotionRefiner

    def _correct(self, grey, pred, meas, outlier_count, verification, matched=None):
        return Correction(pred.disparity, pred.variance, pred.valid, outlier_count)

    EgoMotionRefiner._correct = _correct


def _identity_motion() -> None:
    """The ego-motion solve returns the identity (its flags, weights and counts unchanged)."""
    import torch

    from egorefine.motion import solve as solve_module

    original = solve_module.solve_ego_motion

    @functools.wraps(original)
    def solve_ego_motion(*args, **kwargs):
        out = original(*args, **kwargs)
        eye = torch.eye(4, dtype=out.motion.dtype, device=out.motion.device).expand_as(out.motion).clone()
        return out._replace(motion=eye, twist=torch.zeros_like(out.twist))

    _replace_everywhere(original, solve_ego_motion)


def _offset(px: float):
    def plant() -> None:
        """Every refined map comes out ``px`` too large where it is valid."""
        from egorefine.refine.refiner import EgoMotionRefiner

        forward = EgoMotionRefiner.forward

        @functools.wraps(forward)
        def shifted(self, *args, **kwargs):
            out, state = forward(self, *args, **kwargs)
            return out._replace(disparity=out.disparity + px * out.valid.to(out.disparity.dtype)), state

        EgoMotionRefiner.forward = shifted

    plant.__doc__ = f"Every refined map comes out +{px} px where it is valid (the loop's state is not shifted)."
    return plant


def _integer_stereo() -> None:
    """The stereo matchers' sub-pixel fit is off: integer disparities (full maps and the hole windows)."""
    from egorefine.stereo import _sad_numba, matching

    match = matching._match

    @functools.wraps(match)
    def _match(left, right, max_disparity, min_disparity, block_size, cost, aggregation, subpixel, *rest, **kw):
        return match(left, right, max_disparity, min_disparity, block_size, cost, aggregation, False, *rest, **kw)

    matching._match = _match
    windows = _sad_numba.match_sad_windows

    @functools.wraps(windows)
    def match_sad_windows(*args):
        *head, opts = args
        return windows(*head, {**opts, "subpixel": False})

    _sad_numba.match_sad_windows = match_sad_windows


def _no_fill() -> None:
    """The refiner's fill of the box matcher's holes (Kalman mode's default) does nothing."""
    from egorefine.refine import refiner

    refiner.fill_invalid = lambda primary, secondary: primary


DEFECTS = {
    "keep-prediction": _keep_prediction,
    "identity-motion": _identity_motion,
    "offset-0.25": _offset(0.25),
    "offset-0.10": _offset(0.10),
    "integer-stereo": _integer_stereo,
    "no-fill": _no_fill,
}


def plant(name: str) -> None:
    """Apply the defect ``name`` (a key of :data:`DEFECTS`) to the imported library."""
    if name not in DEFECTS:
        raise SystemExit(f"{ENV}={name!r}: not one of {sorted(DEFECTS)}")
    _import_all()
    DEFECTS[name]()


_NAME = os.environ.get(ENV, "")
if _NAME:
    plant(_NAME)


def pytest_report_header(config):
    return f"egorefine mutant: {_NAME or 'none (baseline)'}"


_REPORT = os.environ.get(ENV + "_REPORT", "")
_OUTCOMES: dict[str, str] = {}


def pytest_runtest_logreport(report):
    """Each test's outcome (``failed`` if any of its phases failed), for ``tools/mutants.py``."""
    if report.failed:
        _OUTCOMES[report.nodeid] = "failed"
    elif report.when == "call" or (report.when == "setup" and report.skipped):
        outcome = ("xfailed" if hasattr(report, "wasxfail") else "skipped") if report.skipped else report.outcome
        _OUTCOMES.setdefault(report.nodeid, outcome)


def pytest_sessionfinish(session, exitstatus):
    if _REPORT:
        import json

        with open(_REPORT, "w") as f:
            json.dump(_OUTCOMES, f, indent=1)
