"""Moving the tensors inside nested scene data (effects' fields, handles, surfaces) to a device and dtype."""

from __future__ import annotations

import dataclasses
from typing import Any

import torch
from torch import Tensor

from redsim.points import PointSet


def cast_tensors(value: Any, device: torch.device | str | None, dtype: torch.dtype | None) -> Any:
    """``value`` with every tensor moved to ``device`` and floating ones cast to ``dtype`` (None: unchanged).

    Recurses into :class:`redsim.points.PointSet`, dataclasses (rebuilt with ``dataclasses.replace``)
    and tuples; anything else is returned as it is. Inputs are never modified.
    """
    if isinstance(value, Tensor):
        if value.is_floating_point():
            return value.to(device=device, dtype=dtype)
        return value.to(device=device)
    if isinstance(value, PointSet):
        return value.to(device, dtype)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        changes = {f.name: cast_tensors(getattr(value, f.name), device, dtype) for f in dataclasses.fields(value)}
        return dataclasses.replace(value, **changes)
    if isinstance(value, tuple):
        return tuple(cast_tensors(v, device, dtype) for v in value)
    return value
