"""Walking the tensors inside nested scene data (effects' fields, handles, surfaces): cast, move, select; and
forward-mode derivatives (:func:`jvp`)."""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor


def map_tensors(value: Any, fn: Callable[[Tensor], Tensor]) -> Any:
    """``value`` with ``fn`` applied to every tensor inside it.

    Recurses into dataclasses (rebuilt with ``dataclasses.replace``, e.g. a
    :class:`redsim.points.PointSet`) and tuples; anything else is returned as it is. Inputs are never modified.
    """
    if isinstance(value, Tensor):
        return fn(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        changes = {f.name: map_tensors(getattr(value, f.name), fn) for f in dataclasses.fields(value)}
        return dataclasses.replace(value, **changes)
    if isinstance(value, tuple):
        return tuple(map_tensors(v, fn) for v in value)
    return value


def cast_tensors(value: Any, device: torch.device | str | None, dtype: torch.dtype | None) -> Any:
    """``value`` with every tensor moved to ``device`` and floating ones cast to ``dtype`` (None: unchanged).

    Recurses like :func:`map_tensors`; inputs are never modified.
    """

    def cast(t: Tensor) -> Tensor:
        return t.to(device=device, dtype=dtype) if t.is_floating_point() else t.to(device=device)

    return map_tensors(value, cast)


_JVP_QUIET: list[bool] = []
"""Non-empty once a :func:`jvp` call has run: torch scripts its forward-mode decompositions once per process."""


def jvp(fn: Callable[..., Tensor], primals: tuple[Tensor, ...], tangents: tuple[Tensor, ...]) -> tuple[Tensor, Tensor]:
    """``torch.func.jvp`` without the ``torch.jit.script`` DeprecationWarning that torch's own forward-mode
    decompositions raise on first use: a warning about torch's internals, which under ``python -W error`` would
    stop a user's first env step. Only the first call is wrapped (``warnings.catch_warnings`` resets Python's
    once-per-location warning registry and is not thread-safe)."""
    if _JVP_QUIET:
        return torch.func.jvp(fn, primals, tangents)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="`torch.jit.script` is deprecated", category=DeprecationWarning)
        result = torch.func.jvp(fn, primals, tangents)
    _JVP_QUIET.append(True)
    return result
