"""The one rule that picks a stage's compiled CPU kernel or its torch reference path.

Several stages keep a compiled numba kernel beside their torch code (docs/architecture.md, "Two paths"): the
torch code is the reference (GPU, autograd, ``torch.compile``), the kernel a faster form of the same steps for
inference on the CPU. A call site never decides for itself; it asks :func:`use_compiled`, which takes the kernel
only when all of these hold:

* the switch ``ENABLED`` is on (tests and benchmarks set it False to run every torch path);
* numba can be imported (:data:`egorefine.core._jit.AVAILABLE`);
* torch is not tracing or compiling the call: ``torch.compile`` / dynamo and ``torch.export``, ``torch.jit``
  tracing or scripting, ``torch.fx`` symbolic tracing, a functorch transform (``vmap``, ``torch.func.grad``), or a
  Python dispatch mode (fake tensors, proxy tracing, operator counters) that would not see a kernel's work;
* every tensor is a plain CPU tensor (no tensor subclass such as a fake tensor or an fx proxy), and every
  floating-point one has the kernel's dtype;
* no tensor needs a gradient: grad mode is off, or none of them requires grad. A kernel works on numpy views and
  gives outputs without a graph, so a caller that wants gradients always gets the torch path.

Limits of one kernel (a cost it does not implement, a size it cannot handle, masks it reads as bool) stay at its
call site as named conditions beside the call; the rule above lives here only.
"""

from __future__ import annotations

import torch

from . import _jit

__all__ = ["ENABLED", "needs_grad", "tracing", "use_compiled"]

# False: every stage runs its torch path (tests compare the two paths; benchmarks time the torch one)
ENABLED = True

if hasattr(torch, "compiler") and hasattr(torch.compiler, "is_compiling"):
    _is_compiling = torch.compiler.is_compiling
else:  # pragma: no cover - torch < 2.3
    _is_compiling = torch._dynamo.is_compiling

try:
    from torch.fx import _symbolic_trace as _fx  # its flag: set while fx traces (symbolic_trace, export)
except ImportError:  # pragma: no cover - older torch
    _fx = None

try:
    from torch.utils._python_dispatch import _get_current_dispatch_mode
except ImportError:  # pragma: no cover - older torch
    def _get_current_dispatch_mode():
        return None

# the functorch transform level (vmap, torch.func.grad, jacrev): None outside every transform
_functorch_level = getattr(getattr(torch._C, "_functorch", None), "maybe_current_level", lambda: None)
_PLAIN = (torch.Tensor, torch.nn.Parameter)


def tracing() -> bool:
    """Whether torch is tracing or compiling the running code, so that only torch operations may run.

    True under ``torch.compile`` (dynamo, also behind ``torch.export``), ``torch.jit.trace`` /
    ``torch.jit.script``, ``torch.fx.symbolic_trace``, a functorch transform (``torch.func.vmap``, ``grad``,
    ``jacrev``: their tensors are wrappers) and any active Python dispatch mode (fake tensors, ``make_fx``'s proxy
    tracing, operator counters).

    Returns:
        True where a compiled kernel would be invisible to the tracer or fail on its tensors.

    Example:
        >>> tracing()
        False
    """
    return bool(_is_compiling() or torch.jit.is_tracing() or torch.jit.is_scripting()
                or getattr(_fx, "_is_fx_tracing_flag", False) or _functorch_level() is not None
                or _get_current_dispatch_mode() is not None)


def needs_grad(*tensors: torch.Tensor | None) -> bool:
    """Whether autograd would record a graph through any of ``tensors``: grad mode on and one requires grad.

    Args:
        tensors: tensors (None entries are skipped).

    Returns:
        True where an output computed from ``tensors`` should carry a graph.

    Example:
        >>> x = torch.ones(2, requires_grad=True)
        >>> needs_grad(x, None), needs_grad(x.detach())
        (True, False)
        >>> with torch.no_grad():
        ...     needs_grad(x)
        False
    """
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)


def use_compiled(*tensors: torch.Tensor | None, dtype: torch.dtype | tuple[torch.dtype, ...] = torch.float32) -> bool:
    """Whether a stage may run its compiled CPU kernel on ``tensors`` instead of its torch path.

    The rule of the module docstring: ``ENABLED``, numba importable, torch not tracing or compiling, every
    tensor a plain CPU tensor, every floating-point tensor of ``dtype``, and no gradient wanted through any of
    them. Integer and bool tensors (masks, counts) are checked for device and gradient only; a kernel that
    needs a particular mask dtype says so at its call site.

    Args:
        tensors: every tensor the kernel reads (None entries are skipped).
        dtype: the kernel's floating-point dtype, or a tuple of the dtypes it accepts.

    Returns:
        True: run the compiled kernel; False: run the torch path.

    Example:
        >>> x = torch.rand(1, 1, 4, 4)
        >>> use_compiled(x) == _jit.AVAILABLE, use_compiled(x.double()), use_compiled(x.to("meta"))
        (True, False, False)
        >>> use_compiled(x.requires_grad_(True))
        False
        >>> with torch.no_grad():
        ...     use_compiled(x) == _jit.AVAILABLE
        True
    """
    if not (ENABLED and _jit.AVAILABLE) or tracing():
        return False
    dtypes = (dtype,) if isinstance(dtype, torch.dtype) else tuple(dtype)
    grad = torch.is_grad_enabled()
    for t in tensors:
        if t is None:
            continue
        if type(t) not in _PLAIN or not t.is_cpu:
            return False
        if (t.is_floating_point() and t.dtype not in dtypes) or (grad and t.requires_grad):
            return False
    return True
