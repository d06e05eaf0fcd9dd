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
]


class EgorefineError(Exception):
    """Base class of every error egorefine raises on purpose."""


class ShapeError(EgorefineError, ValueError):
    """A tensor has the wrong rank or size, or two tensors disagree on a shared dimension."""


class DTypeError(EgorefineError, TypeError):
    """A tensor (or argument) has the wrong type, e.g. an integer image where float is needed."""


class DeviceError(EgorefineError, ValueError):
    """Tensors that must live together are on different devices."""


class ValueRangeError(EgorefineError, ValueError):
    """A value is out of its allowed range: NaN/Inf, a non-positive baseline, a bad option."""


class StateError(EgorefineError, ValueError):
    """A carried state does not fit the current input (other resolution, device or batch)."""


class DataError(EgorefineError, ValueError):
    """A recording, image or calibration file is malformed: a frame that does not decode, a calibration that does
    not parse or lacks a field, cameras that disagree (frame counts, image sizes)."""


class MissingDataError(DataError, FileNotFoundError):
    """A file or folder that a data layout needs is absent."""
