"""Checks, typed errors and numeric helpers shared by every stage."""

from .check import (
    check_choice,
    check_finite,
    check_float,
    check_image,
    check_positive,
    check_same_device,
    check_shape,
)
from .dispatch import use_compiled
from .errors import DeviceError, DTypeError, EgorefineError, ShapeError, StateError, ValueRangeError
from .image import to_grey
from .numerics import eps_like, safe_div
from .progress import progress

__all__ = [
    "check_choice",
    "check_finite",
    "check_float",
    "check_image",
    "check_positive",
    "check_same_device",
    "check_shape",
    "DeviceError",
    "DTypeError",
    "EgorefineError",
    "ShapeError",
    "StateError",
    "ValueRangeError",
    "eps_like",
    "progress",
    "safe_div",
    "to_grey",
    "use_compiled",
]
