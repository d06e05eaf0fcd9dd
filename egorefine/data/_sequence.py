"""What every stereo-sequence dataclass of egorefine.data shares: its length and ``to``."""

from __future__ import annotations

from dataclasses import fields, replace
from typing import TypeVar

import torch

__all__ = ["SequenceMixin"]

S = TypeVar("S", bound="SequenceMixin")


class SequenceMixin:
    """For dataclasses whose ``left`` field is ``(T, C, H, W)``: ``len()`` and a device/dtype ``to``."""

    left: torch.Tensor

    def __len__(self) -> int:
        return self.left.shape[0]

    def to(self: S, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> S:
        """A copy on ``device``; floating tensors also cast to ``dtype`` when given."""
        out = {}
        for f in fields(self):  # type: ignore[arg-type]
            v = getattr(self, f.name)
            if isinstance(v, torch.Tensor):
                v = v.to(device=device, dtype=dtype if (dtype is not None and v.is_floating_point()) else None)
            out[f.name] = v
        return replace(self, **out)  # type: ignore[type-var]
