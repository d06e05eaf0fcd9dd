"""Checks, typed errors and numeric helpers shared by every stage."""

from .check import (
    check_choice,
    check_finite,
    check_float,
    check_image,
    check_intrinsics,
    check_positive,
    check_same_device,
    check_same_dtype,
    check_setting,
    check_shape,
    check_variance,
)
from .dispatch import use_compiled
from .errors import (
    DataError,
    DeviceError,
    DTypeError,
    EgorefineError,
    MissingDataError,
    MissingExtraError,
    ShapeError,
    StateError,
    ValueRangeError,
    require_extra,
)
from .image import to_grey
from .machine import cpu_model, machine_info
from .numerics import eps_like, safe_div
from .progress import progress

__all__ = [
    "check_choice",
    "check_finite",
    "check_float",
    "check_image",
    "check_intrinsics",
    "check_positive",
    "check_same_device",
    "check_same_dtype",
    "check_setting",
    "check_shape",
    "check_variance",
    "DataError",
    "DeviceError",
    "DTypeError",
    "EgorefineError",
    "MissingDataError",
    "MissingExtraError",
    "ShapeError",
    "StateError",
    "ValueRangeError",
    "cpu_model",
    "eps_like",
    "machine_info",
    "progress",
    "require_extra",
    "safe_div",
    "to_grey",
    "use_compiled",
]
