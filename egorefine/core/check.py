"""Checks at the door: named-dimension shapes, dtypes, devices and values.

Shapes are given as lists of dimension names, as in kornia's ``KORNIA_CHECK_SHAPE``:
a name (``"B"``, ``"H"``) binds to whatever size comes first and must then agree
everywhere it appears again in the same ``dims`` dictionary; a number (``"1"``) must match
exactly; alternatives are written with ``|`` (``"1|3"``); ``"*"`` accepts any size.

>>> import torch
>>> dims = check_shape(torch.zeros(2, 1, 4, 5), ["B", "1", "H", "W"], "left")
>>> dims
{'B': 2, 'H': 4, 'W': 5}
>>> _ = check_shape(torch.zeros(2, 1, 4, 5), ["B", "1", "H", "W"], "right", dims)
>>> check_shape(torch.zeros(2, 1, 4, 6), ["B", "1", "H", "W"], "right", dims)
Traceback (most recent call last):
...
egorefine.core.errors.ShapeError: right: dimension W must be 5 (as bound earlier), got shape (2, 1, 4, 6)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from .errors import DeviceError, DTypeError, ShapeError, ValueRangeError

__all__ = [
    "check_shape",
    "check_float",
    "check_same_device",
    "check_same_dtype",
    "check_finite",
    "check_positive",
    "check_image",
    "check_choice",
    "check_intrinsics",
    "check_variance",
    "check_setting",
    "IMAGE_RANGE_TOLERANCE",
]

# Images are floats in [0, 1]; a little beyond is allowed for noise or augmentation added by the caller, while an
# image left in 0..255 (the likeliest mistake) is far beyond it.
IMAGE_RANGE_TOLERANCE = 0.1

# Half-precision types the stages do not compute in (their sums and sub-pixel fits need float32's mantissa).
_HALF_TYPES = (torch.float16, torch.bfloat16)


def _fmt(shape: Sequence[int]) -> str:
    return "(" + ", ".join(str(int(s)) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def check_shape(
    x: torch.Tensor,
    dims: Sequence[str],
    name: str,
    bound: dict[str, int] | None = None,
) -> dict[str, int]:
    """Check that ``x`` has the named shape ``dims`` and return the name -> size bindings.

    A name binds on its first appearance and must match everywhere it appears again, in this call or in later calls
    that pass the same ``bound``: that is how ``left`` and ``right`` are held to one ``(B, H, W)``.

    Args:
        x: the tensor to check.
        dims: one entry per dimension: a name (``"B"``), a number (``"1"``), alternatives (``"1|3"``) or ``"*"``.
        name: the argument's name, used in the error message.
        bound: sizes bound by earlier checks; updated in place with new names. Default: a fresh dictionary.

    Returns:
        ``bound`` with the names of ``dims`` bound to their sizes.

    Raises:
        DTypeError: ``x`` is not a tensor.
        ShapeError: the rank or a size does not match.

    Example:
        >>> dims = check_shape(torch.zeros(2, 1, 4, 5), ["B", "1", "H", "W"], "left")
        >>> dims
        {'B': 2, 'H': 4, 'W': 5}
        >>> check_shape(torch.zeros(2, 3, 3), ["B", "3", "3"], "K", dims)
        {'B': 2, 'H': 4, 'W': 5}
    """
    if not isinstance(x, torch.Tensor):
        raise DTypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    bound = {} if bound is None else bound
    spec = _parsed_dims(tuple(dims))
    shape = x.shape
    if len(shape) != len(spec):
        raise ShapeError(f"{name}: expected shape ({', '.join(dims)}) ({len(dims)} dims), got {_fmt(shape)}")
    for size, (dim, sizes) in zip(shape, spec, strict=True):
        if sizes is not None:
            if size not in sizes:
                raise ShapeError(f"{name}: expected shape ({', '.join(dims)}), got {_fmt(shape)}")
        elif dim is None:  # "*"
            continue
        elif dim in bound:
            if bound[dim] != size:
                raise ShapeError(
                    f"{name}: dimension {dim} must be {bound[dim]} (as bound earlier), got shape {_fmt(shape)}"
                )
        else:
            bound[dim] = int(size)
    return bound


_PARSED_DIMS: dict[tuple[str, ...], tuple[tuple[str | None, frozenset[int] | None], ...]] = {}


def _parsed_dims(dims: tuple[str, ...]) -> tuple[tuple[str | None, frozenset[int] | None], ...]:
    """``check_shape``'s ``dims`` read once: per entry ``(name, None)``, ``(None, allowed sizes)`` or ``(None, None)``
    for ``"*"`` (the checks run on every frame; parsing the same strings each time cost more than the check). A plain
    dictionary, not ``functools.lru_cache``, which torch.compile warns about when it traces a check."""
    parsed = _PARSED_DIMS.get(dims)
    if parsed is not None:
        return parsed
    out = []
    for dim in dims:
        options = dim.split("|")
        if dim == "*":
            out.append((None, None))
        elif all(o.isdigit() for o in options):
            out.append((None, frozenset(int(o) for o in options)))
        else:
            out.append((dim, None))
    parsed = _PARSED_DIMS[dims] = tuple(out)
    return parsed


def check_float(x: torch.Tensor, name: str) -> None:
    """Raise :class:`DTypeError` unless ``x`` is a float32 or float64 tensor.

    float16 and bfloat16 are refused with a hint: the stages' sums, solves and sub-pixel fits need float32's mantissa,
    and several CPU kernels have no half-precision version.

    Args:
        x: the value to check.
        name: the argument's name, used in the error message.

    Raises:
        DTypeError: not a tensor, not floating point, or half precision.

    Example:
        >>> check_float(torch.zeros(2), "disparity")
        >>> check_float(torch.zeros(2, dtype=torch.int64), "disparity")
        Traceback (most recent call last):
        ...
        egorefine.core.errors.DTypeError: disparity: expected a floating-point tensor, got torch.int64
    """
    if not isinstance(x, torch.Tensor):
        raise DTypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise DTypeError(f"{name}: expected a floating-point tensor, got {x.dtype}")
    if x.dtype in _HALF_TYPES:
        raise DTypeError(f"{name}: expected float32 or float64, got {x.dtype}; convert with .float()")


def check_same_device(reference: torch.Tensor, ref_name: str, **others: torch.Tensor | None) -> None:
    """Raise :class:`DeviceError` if any tensor in ``others`` is on another device than ``reference``.

    Args:
        reference: the tensor whose device the others must share.
        ref_name: its argument name, used in the error message.
        **others: argument name -> tensor; None entries (optional arguments not given) are skipped.

    Raises:
        DeviceError: a tensor of ``others`` is on another device.

    Example:
        >>> check_same_device(torch.zeros(2), "left", right=torch.zeros(2), predicted=None)
    """
    for other_name, t in others.items():
        if t is not None and t.device != reference.device:
            raise DeviceError(f"{other_name}: on {t.device}, but {ref_name} is on {reference.device}")


def _host_array(x: torch.Tensor) -> np.ndarray | None:
    """A numpy view of a CPU float32/float64 tensor (no copy), or None for other devices and dtypes.

    Checks of small tensors (K, the baseline) and of full maps take numpy on the CPU: each torch op costs tens of
    microseconds in dispatch on a 3x3 matrix, and a torch reduction over a full map wakes torch's OpenMP threads,
    which then spin beside whatever compiled kernel runs next."""
    if x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64):
        return x.detach().numpy()
    return None


def _extremes(x: torch.Tensor) -> tuple[float, float] | None:
    """The minimum and maximum of a float tensor (NaN if it holds one), with one synchronisation; None if empty.

    On the CPU, float32/float64 tensors take numpy's single-threaded minimum and maximum: a torch reduction over
    a full map wakes torch's OpenMP threads, which then spin beside whatever compiled kernel runs next.
    """
    if x.numel() == 0:
        return None
    values = _host_array(x)
    if values is not None:
        return float(values.min()), float(values.max())  # numpy's min and max propagate NaN
    low, high = torch.aminmax(x.detach())
    return float(low), float(high)


def check_same_dtype(reference: torch.Tensor, ref_name: str, **others: torch.Tensor | None) -> None:
    """Raise :class:`DTypeError` if any tensor in ``others`` has another dtype than ``reference``.

    Args:
        reference: the tensor whose dtype the others must share.
        ref_name: its argument name, used in the error message.
        **others: argument name -> tensor; None entries are skipped.

    Raises:
        DTypeError: a tensor of ``others`` has another dtype.

    Example:
        >>> check_same_dtype(torch.zeros(2), "prev", next=torch.zeros(2, dtype=torch.float64))
        Traceback (most recent call last):
        ...
        egorefine.core.errors.DTypeError: next: torch.float64, but prev is torch.float32; pass both in one dtype
    """
    for other_name, t in others.items():
        if t is not None and t.dtype != reference.dtype:
            raise DTypeError(f"{other_name}: {t.dtype}, but {ref_name} is {reference.dtype}; pass both in one dtype")


def check_finite(x: torch.Tensor, name: str) -> None:
    """Raise :class:`ValueRangeError` if ``x`` holds NaN or Inf.

    This synchronises with the device once; it guards public entry points, not inner loops. The test is the extremes'
    finiteness (the minimum and maximum propagate NaN; an Inf is an extreme): one reduction without a mask tensor,
    much cheaper than ``isfinite(x).all()``. Integer and bool tensors always pass.

    Args:
        x: the tensor to check.
        name: the argument's name, used in the error message.

    Raises:
        ValueRangeError: a NaN or an Inf.

    Example:
        >>> check_finite(torch.tensor([1.0, float("nan")]), "keypoints")
        Traceback (most recent call last):
        ...
        egorefine.core.errors.ValueRangeError: keypoints: contains NaN or Inf
    """
    if not (x.is_floating_point() or x.is_complex()):
        return  # integers and booleans are always finite
    if x.is_complex():
        x = torch.view_as_real(x)
    extremes = _extremes(x)
    if extremes is not None and not all(np.isfinite(extremes)):
        raise ValueRangeError(f"{name}: contains NaN or Inf")


def check_positive(x: torch.Tensor, name: str) -> None:
    """Raise :class:`ValueRangeError` unless every entry of ``x`` is finite and > 0 (a baseline, a focal length).

    Args:
        x: the tensor to check.
        name: the argument's name, used in the error message (with the first entries of ``x``).

    Raises:
        ValueRangeError: an entry is not finite or not > 0.

    Example:
        >>> check_positive(torch.tensor([0.5, 0.0]), "baseline")
        Traceback (most recent call last):
        ...
        egorefine.core.errors.ValueRangeError: baseline: every entry must be finite and > 0, got [0.5, 0.0]
    """
    values = _host_array(x)
    if values is not None:
        ok = bool((np.isfinite(values) & (values > 0)).all())
    else:
        ok = bool((torch.isfinite(x) & (x > 0)).all())
    if not ok:
        raise ValueRangeError(f"{name}: every entry must be finite and > 0, got {x.detach().flatten()[:8].tolist()}")


def check_image(
    x: torch.Tensor, name: str, bound: dict[str, int] | None = None, min_size: int = 1, values: bool = True
) -> dict[str, int]:
    """Check a float image batch ``(B, C, H, W)``: C in {1, 3}, B >= 1, values in [0, 1] and no NaN/Inf.

    Values may stray beyond [0, 1] by ``IMAGE_RANGE_TOLERANCE`` (noise or augmentation); an image in 0..255 is refused
    with a message saying how to scale it.

    Args:
        x: the image batch.
        name: the argument's name, used in the error message.
        bound: sizes bound by earlier checks (see :func:`check_shape`); updated in place.
        min_size: the smallest height and width the caller's filters work on; default 1 (any image).
        values: also check the values (a pass over the image); False for an image that a caller reads only on
            some calls, and checks there.

    Returns:
        the bindings ``{"B", "H", "W"}`` (and those of ``bound``).

    Raises:
        ShapeError: wrong rank, channels, an empty batch or a side below ``min_size``.
        DTypeError: not a float32/float64 tensor (see :func:`check_float`).
        ValueRangeError: NaN/Inf, or values outside [0, 1] beyond the tolerance.

    Example:
        >>> check_image(torch.rand(2, 1, 4, 5), "left")
        {'B': 2, 'H': 4, 'W': 5}
        >>> check_image(torch.full((1, 1, 4, 5), 9.0), "img")
        Traceback (most recent call last):
        ...
        egorefine.core.errors.ValueRangeError: img: expected values in [0, 1], got [9, 9]; scale 8-bit images by 1/255
    """
    dims = check_shape(x, ["B", "1|3", "H", "W"], name, bound)
    check_float(x, name)
    if x.shape[0] == 0:
        raise ShapeError(f"{name}: expected a batch of at least one image, got shape {_fmt(x.shape)}")
    if min(x.shape[-2:]) < min_size:
        raise ShapeError(f"{name}: expected at least {min_size} px per side, got shape {_fmt(x.shape)}")
    if x.numel() == 0:
        raise ShapeError(f"{name}: expected a non-empty image, got shape {_fmt(x.shape)}")
    if not values:
        return dims
    low, high = _extremes(x)
    if not (np.isfinite(low) and np.isfinite(high)):
        raise ValueRangeError(f"{name}: contains NaN or Inf")
    if low < -IMAGE_RANGE_TOLERANCE or high > 1.0 + IMAGE_RANGE_TOLERANCE:
        hint = "; scale 8-bit images by 1/255" if high > 2.0 else ""
        raise ValueRangeError(f"{name}: expected values in [0, 1], got [{low:.3g}, {high:.3g}]{hint}")
    return dims


def check_intrinsics(K: torch.Tensor, name: str = "K", bound: dict[str, int] | None = None) -> dict[str, int]:
    """Check pinhole intrinsics ``(B, 3, 3)``: float, finite, fx and fy > 0, last row ``(0, 0, 1)``.

    A K with a positive focal length and that last row is invertible, so a singular K is caught here too.

    Args:
        K: the intrinsics.
        name: the argument's name, used in the error message; default ``"K"``.
        bound: sizes bound by earlier checks (see :func:`check_shape`); updated in place.

    Returns:
        the bindings (``{"B"}`` and those of ``bound``).

    Raises:
        ShapeError, DTypeError, ValueRangeError: as the other checks.

    Example:
        >>> check_intrinsics(torch.tensor([[[400.0, 0, 320], [0, 400, 240], [0, 0, 1]]]))
        {'B': 1}
        >>> check_intrinsics(torch.zeros(1, 3, 3))
        Traceback (most recent call last):
        ...
        egorefine.core.errors.ValueRangeError: K: expected fx, fy > 0 and the last row (0, 0, 1), got fx=[0.0], fy=[0.0]
    """
    dims = check_shape(K, ["B", "3", "3"], name, bound)
    check_float(K, name)
    # (Python floats of one host copy: a dozen numpy or torch operations on a 3 x 3 matrix cost far more)
    host = _host_array(K)
    values = (host if host is not None else K.detach().cpu()).tolist()
    if not all(math.isfinite(v) for k in values for row in k for v in row):
        raise ValueRangeError(f"{name}: contains NaN or Inf")
    if not all(k[0][0] > 0 and k[1][1] > 0 and abs(k[2][0]) <= 1e-6 and abs(k[2][1]) <= 1e-6
               and abs(k[2][2] - 1.0) <= 1e-6 for k in values):
        raise ValueRangeError(f"{name}: expected fx, fy > 0 and the last row (0, 0, 1), "
                              f"got fx={[k[0][0] for k in values[:4]]}, fy={[k[1][1] for k in values[:4]]}")
    return dims


def check_variance(x: torch.Tensor, name: str) -> None:
    """Raise :class:`ValueRangeError` unless every entry of ``x`` is finite and >= 0 (a variance map).

    Args:
        x: the tensor to check, float.
        name: the argument's name, used in the error message.

    Raises:
        DTypeError: not a float32/float64 tensor.
        ValueRangeError: a negative or non-finite entry.

    Example:
        >>> check_variance(torch.tensor([0.0, 0.25]), "variance")
        >>> check_variance(torch.tensor([-1.0]), "variance")
        Traceback (most recent call last):
        ...
        egorefine.core.errors.ValueRangeError: variance: expected finite values >= 0, got [-1, -1]
    """
    check_float(x, name)
    extremes = _extremes(x)
    if extremes is None:
        return
    low, high = extremes
    if not (np.isfinite(low) and np.isfinite(high)) or low < 0:
        raise ValueRangeError(f"{name}: expected finite values >= 0, got [{low:.3g}, {high:.3g}]")


def check_choice(value: str, options: Sequence[str], name: str) -> None:
    """Raise :class:`ValueRangeError` unless ``value`` is one of ``options`` (a string setting such as ``cost``).

    Args:
        value: the setting given.
        options: the settings accepted.
        name: the argument's name, used in the error message.

    Raises:
        ValueRangeError: ``value`` is not among ``options``.

    Example:
        >>> check_choice("census", ("sad", "zncc"), "cost")
        Traceback (most recent call last):
        ...
        egorefine.core.errors.ValueRangeError: cost: expected one of ['sad', 'zncc'], got 'census'
    """
    if value not in options:
        raise ValueRangeError(f"{name}: expected one of {list(options)}, got {value!r}")


def check_setting(value: float | torch.Tensor, name: str) -> float | torch.Tensor:
    """A scalar setting that may be learnable: a Python number, or a 0-d tensor that gradients should reach.

    Stages whose settings can be :class:`torch.nn.Parameter` s (a gain, a noise level, a temperature) call this
    once at the door: a tensor that needs no gradient becomes a float (so the compiled kernels and CUDA-graph
    keys see a plain number), a tensor that does stays a tensor (the stage's torch path then carries its graph).
    Range checks stay with the caller, which compares the returned value as it would a number.

    Args:
        value: a number, or a 0-d floating-point tensor.
        name: the argument's name, for the error.

    Returns:
        ``float(value)`` where no gradient is wanted through it, else ``value`` itself.

    Raises:
        ValueRangeError: a tensor that is not 0-d or not finite, or a number that is not finite.

    Example:
        >>> check_setting(torch.tensor(0.4), "gain")
        0.4000000059604645
        >>> check_setting(torch.tensor(0.4, requires_grad=True), "gain")
        tensor(0.4000, requires_grad=True)
    """
    if isinstance(value, torch.Tensor):
        if value.dim() != 0 or not value.is_floating_point():
            raise ValueRangeError(f"{name}: expected a number or a 0-d float tensor, got shape "
                                  f"{tuple(value.shape)} {value.dtype}")
        if not bool(torch.isfinite(value.detach())):
            raise ValueRangeError(f"{name}: expected a finite value, got {value.item()}")
        return value if (torch.is_grad_enabled() and value.requires_grad) else float(value)
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueRangeError(f"{name}: expected a number, got {type(value).__name__}") from None
    if not np.isfinite(number):
        raise ValueRangeError(f"{name}: expected a finite value, got {number}")
    return number
