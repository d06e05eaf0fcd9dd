import pytest
import torch

from egorefine.core import (
    DeviceError,
    DTypeError,
    EgorefineError,
    ShapeError,
    ValueRangeError,
    check_choice,
    check_finite,
    check_float,
    check_image,
    check_positive,
    check_same_device,
    check_shape,
    eps_like,
    safe_div,
)


def test_errors_are_builtin_subclasses():
    assert issubclass(ShapeError, ValueError) and issubclass(ShapeError, EgorefineError)
    assert issubclass(DTypeError, TypeError)
    assert issubclass(ValueRangeError, ValueError)
    assert issubclass(DeviceError, ValueError)


def test_check_shape_binds_names_and_checks_numbers():
    dims = check_shape(torch.zeros(2, 3, 4, 5), ["B", "1|3", "H", "W"], "img")
    assert dims == {"B": 2, "H": 4, "W": 5}
    check_shape(torch.zeros(2, 4, 5), ["B", "H", "*"], "other", dims)
    with pytest.raises(ShapeError, match=r"img: expected shape \(B, 1\|3, H, W\)"):
        check_shape(torch.zeros(2, 2, 4, 5), ["B", "1|3", "H", "W"], "img")
    with pytest.raises(ShapeError, match=r"mask: expected shape .* \(4 dims\)"):
        check_shape(torch.zeros(2, 4, 5), ["B", "1", "H", "W"], "mask")
    with pytest.raises(ShapeError, match="right: dimension H must be 4"):
        check_shape(torch.zeros(2, 1, 6, 5), ["B", "1", "H", "W"], "right", dims)
    with pytest.raises(DTypeError, match="x: expected a torch.Tensor, got list"):
        check_shape([1, 2], ["N"], "x")


def test_value_checks():
    check_float(torch.zeros(1), "a")
    with pytest.raises(DTypeError, match="a: expected a floating-point tensor, got torch.uint8"):
        check_float(torch.zeros(1, dtype=torch.uint8), "a")
    with pytest.raises(ValueRangeError, match="img: contains NaN or Inf"):
        check_finite(torch.tensor([0.0, float("nan")]), "img")
    with pytest.raises(ValueRangeError, match="baseline: every entry must be finite and > 0"):
        check_positive(torch.tensor([0.1, 0.0]), "baseline")
    with pytest.raises(ValueRangeError, match="fusion: expected one of"):
        check_choice("median", ["paper", "kalman"], "fusion")
    with pytest.raises(ValueRangeError, match="left: contains NaN"):
        check_image(torch.full((1, 1, 2, 2), float("inf")), "left")


def test_same_device_passes_on_cpu_and_meta_differs():
    a = torch.zeros(1)
    check_same_device(a, "a", b=torch.zeros(1), c=None)
    with pytest.raises(DeviceError, match="b: on meta, but a is on cpu"):
        check_same_device(a, "a", b=torch.zeros(1, device="meta"))


def test_safe_div_is_finite_with_gradients():
    den = torch.tensor([0.0, -0.0, 1e-30, -2.0], dtype=torch.float64, requires_grad=True)
    out = safe_div(torch.ones(4, dtype=torch.float64), den)
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(den.grad).all()
    assert out[3] == -0.5
    assert eps_like(torch.zeros(1)) == 1e-6


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64, torch.complex64])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_check_finite_finds_any_non_finite_entry(dtype, bad):
    x = torch.rand(3, 5, 7).to(dtype)
    check_finite(x, "x")  # finite: passes
    x[2, 4, 6] = bad  # the last entry
    with pytest.raises(ValueRangeError, match="x: contains NaN or Inf"):
        check_finite(x, "x")
    for view in (x.transpose(0, 2), x[1:, ::2, 2:]):  # strided views
        with pytest.raises(ValueRangeError, match="x: contains NaN or Inf"):
            check_finite(view, "x")
    x[2, 4, 6] = 0.5
    x[0, 0, 0] = bad  # the first
    with pytest.raises(ValueRangeError, match="x: contains NaN or Inf"):
        check_finite(x, "x")


def test_check_finite_passes_integers_empty_and_grad_tensors():
    check_finite(torch.arange(5), "x")
    check_finite(torch.ones(3, dtype=torch.bool), "x")
    check_finite(torch.empty(0, 4), "x")
    check_finite(torch.rand(4, requires_grad=True), "x")
