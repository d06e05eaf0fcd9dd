"""Progress bars for long loops (renders, sequence runs, the command line)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import TypeVar

from tqdm import tqdm

__all__ = ["progress"]

T = TypeVar("T")


def progress(iterable: Iterable[T], total: int | None = None, desc: str = "", enabled: bool = True) -> Iterator[T]:
    """Iterate over ``iterable`` with a tqdm bar on stderr when ``enabled``.

    One place decides how progress looks, so the renderer, :func:`~egorefine.refine.refine_sequence` and the
    ``egorefine`` command show the same bar. With ``enabled=False`` the iterable is returned as it is.

    Args:
        iterable: what to loop over.
        total: its length, where ``len()`` does not give it.
        desc: the bar's label.
        enabled: show the bar (default ``True``); the library's functions pass their ``show_progress`` here.

    Example:
        >>> list(progress(range(3), enabled=False))
        [0, 1, 2]
    """
    if not enabled:
        return iter(iterable)
    return iter(tqdm(iterable, total=total, desc=desc, unit="frame", leave=False, dynamic_ncols=True))
