"""CUDA-graph replay of fixed-shape inference steps: the motion solve's Levenberg-Marquardt, SGM's scanline
recursion and the prediction's hard splat.

On a GPU these are hundreds to thousands of small kernels whose launches, not their arithmetic,
set the time (each launch costs the host many times what its kernel costs the GPU). A CUDA graph records
the launches of one call once and replays them with a single launch. A graph is recorded per
key (the caller's shapes and settings) on the first call and replayed on the next ones: the
inputs are copied into the recorded ones, and the outputs are copies of the recorded outputs.
Replay runs the recorded kernels, so its results equal an eager call's bit for bit.

Only for CUDA tensors and no autograd: the callers check :func:`usable` and otherwise run eagerly.
A function that cannot be recorded (an operation that synchronises with the host, for one) is
run eagerly from then on for that key.
"""

from __future__ import annotations

import threading
import warnings
from collections.abc import Callable, Sequence

import torch

__all__ = ["ENABLED", "replay", "usable"]

ENABLED = True
_graphs: dict[tuple, tuple | None] = {}
_lock = threading.Lock()
# distinct keys kept (shapes and settings); the oldest is dropped beyond this. A graph keeps the memory of its
# intermediate tensors: a few KB for the motion solve, a few maps for the splat, a few cost volumes for SGM
# (~300 MB at 640x480 / 64)
_MAX_GRAPHS = 16


def usable(*tensors: torch.Tensor) -> bool:
    """Replay applies: enabled, every tensor on a CUDA device and none needs a gradient."""
    return (ENABLED and all(t.is_cuda for t in tensors)
            and not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors)))


def replay(fn: Callable[..., Sequence[torch.Tensor]], key: tuple, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """``fn(*inputs)`` (a tuple of tensors) through a CUDA graph recorded for ``key`` on its first call.

    ``key`` must determine everything about ``fn``'s launches except the values of ``inputs``
    (shapes, dtypes and settings); the device and the input shapes are added to it here.
    """
    full = (key, inputs[0].device, tuple((t.shape, t.dtype) for t in inputs))
    with _lock:
        entry = _graphs.get(full, ())
    if entry is None:  # recording failed before: eager
        return tuple(fn(*inputs))
    if entry == ():
        entry = _record(fn, inputs)
        with _lock:
            if len(_graphs) >= _MAX_GRAPHS:
                _graphs.pop(next(iter(_graphs)))
            _graphs[full] = entry
        if entry is None:
            return tuple(fn(*inputs))
    graph, static_in, static_out = entry
    with torch.no_grad():
        for dst, src in zip(static_in, inputs, strict=True):
            dst.copy_(src)
        graph.replay()
        return tuple(t.clone() for t in static_out)


def _record(fn: Callable[..., Sequence[torch.Tensor]], inputs: Sequence[torch.Tensor]) -> tuple | None:
    """Record ``fn`` on copies of ``inputs``: ``(graph, static inputs, static outputs)``, or None if it cannot be."""
    device = inputs[0].device
    try:
        with torch.no_grad(), torch.cuda.device(device):
            static_in = [t.detach().clone() for t in inputs]
            # warm up on a side stream (lazy initialisations such as solver handles must not be recorded)
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                for _ in range(2):
                    fn(*static_in)
            torch.cuda.current_stream().wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                static_out = tuple(fn(*static_in))
        return graph, static_in, static_out
    except RuntimeError as error:  # e.g. "operation not permitted when stream is capturing"
        warnings.warn(f"egorefine: {getattr(fn, 'func', fn).__name__} cannot be recorded as a CUDA graph and runs "
                      f"eagerly ({error})", RuntimeWarning, stacklevel=3)
        torch.cuda.synchronize(device)
        return None
