"""Typed errors raised for bad input.

Each error names the argument, what was expected and what came, so that a caller can
catch a precise class (``except ShapeError``) and a reader of the traceback can fix the
call without opening the source.
"""

from __future__ import annotations

__all__ = [
    "EgorefineError",
    "ShapeError",
    "DTypeError",
    "DeviceError",
    "ValueRangeError",
    "StateError",
    "DataError",
    "MissingDataError",
    "MissingExtraError",
    "require_extra",
]


class EgorefineError(Exception):
    """Base class of every error egorefine raises on purpose: ``except EgorefineError`` catches bad input of any
    kind and lets programming errors (a bare ``RuntimeError``) through.

    Example:
        >>> import torch
        >>> from egorefine.stereo import match_stereo
        >>> try:
        ...     match_stereo(torch.rand(1, 1, 8, 8), torch.rand(1, 1, 8, 9), 4)
        ... except EgorefineError as err:
        ...     type(err).__name__
        'ShapeError'
    """


class ShapeError(EgorefineError, ValueError):
    """A tensor has the wrong rank or size, or two tensors disagree on a shared dimension.

    Example:
        >>> import torch
        >>> from egorefine.core import check_shape
        >>> check_shape(torch.zeros(2, 4), ["B", "3"], "points")
        Traceback (most recent call last):
        ...
        egorefine.core.errors.ShapeError: points: expected shape (B, 3), got (2, 4)
    """


class DTypeError(EgorefineError, TypeError):
    """A tensor (or argument) has the wrong type, e.g. an integer image where float is needed.

    Example:
        >>> import torch
        >>> from egorefine.core import check_float
        >>> check_float(torch.zeros(2, dtype=torch.uint8), "left")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        egorefine.core.errors.DTypeError: left: ...
    """


class DeviceError(EgorefineError, ValueError):
    """Tensors that must live together are on different devices.

    Example:
        >>> issubclass(DeviceError, ValueError)  # so ``except ValueError`` still catches it
        True
    """


class ValueRangeError(EgorefineError, ValueError):
    """A value is out of its allowed range: NaN/Inf, a non-positive baseline, a bad option.

    Example:
        >>> from egorefine.core import check_choice
        >>> check_choice("kalmann", ["paper", "kalman"], "fusion")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        egorefine.core.errors.ValueRangeError: fusion: ...
    """


class StateError(EgorefineError, ValueError):
    """A carried state does not fit the current input (other resolution, device or batch): start a new sequence
    with ``state=None``.

    Example:
        >>> issubclass(StateError, EgorefineError)
        True
    """


class DataError(EgorefineError, ValueError):
    """A recording, image or calibration file is malformed: a frame that does not decode, a calibration that does
    not parse or lacks a field, cameras that disagree (frame counts, image sizes).

    Example:
        >>> import pathlib, tempfile
        >>> from egorefine.data import read_euroc_sensor
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "sensor.yaml"
        >>> _ = path.write_text("intrinsics: [458.6, 457.3, 367.2, 248.4]\\n")  # no T_BS block
        >>> read_euroc_sensor(path)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        egorefine.core.errors.DataError: path: no T_BS block in '...sensor.yaml'
    """


class MissingDataError(DataError, FileNotFoundError):
    """A file or folder that a data layout needs is absent.

    Example:
        >>> from egorefine.data import read_grey
        >>> try:
        ...     read_grey("no/such/frame.png")
        ... except FileNotFoundError as err:  # a MissingDataError is a FileNotFoundError too
        ...     type(err).__name__
        'MissingDataError'
    """


class MissingExtraError(EgorefineError, ImportError):
    """An optional dependency that one feature needs is not installed; the message names the extra that brings it
    (``pip install egorefine[NAME]``). An ``ImportError`` too, so ``except ImportError`` still catches it.

    Example:
        >>> issubclass(MissingExtraError, ImportError)
        True
    """


def require_extra(module: str, extra: str, what: str, error: type[MissingExtraError] = MissingExtraError):
    """Import ``module`` for a feature of the optional extra ``extra``, or raise ``error`` in one line naming the
    ``pip install`` that brings it: the one rule every optional feature (ROS bags, Rerun, Ray) imports by.

    Args:
        module: the module to import, e.g. ``"rosbags.highlevel"``.
        extra: the extra of egorefine's ``pyproject.toml`` that installs it, e.g. ``"rosbag"``.
        what: what is missing, in words, e.g. ``"rosbags (which reads ROS bags)"``.
        error: the :class:`MissingExtraError` subclass to raise.

    Returns:
        the imported module.

    Example:
        >>> require_extra("json", "none", "the json module").__name__
        'json'
        >>> try:
        ...     require_extra("no_such_module_here", "demo", "a demo package")
        ... except MissingExtraError as err:
        ...     print(err)
        a demo package is not installed: pip install egorefine[demo]
    """
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise error(f"{what} is not installed: pip install egorefine[{extra}]") from None
