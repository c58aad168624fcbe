"""Walking the tensors inside nested scene data (effects' fields, handles, surfaces): cast, move, select;
Jacobian-vector products (:func:`jvp`); a user's numbers as a tensor, or a clear error (:func:`as_numbers`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
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


def as_numbers(
    value: Any, what: str, shape: str, dtype: torch.dtype | None = None, device: torch.device | str | None = None
) -> Tensor:
    """``value`` as a real tensor (in ``dtype`` on ``device`` where given); a ValueError naming ``what`` and its
    ``shape`` [str] where it is not an array of real numbers (torch's own errors, e.g. "new(): invalid data type
    'str'", name neither, and a complex value would be cast with its imaginary part dropped)."""
    kind = value.dtype if isinstance(value, (Tensor, np.ndarray, np.generic)) else None
    if kind is not None and (kind.is_complex if isinstance(kind, torch.dtype) else kind.kind == "c"):
        raise ValueError(f"{what} must be an array of real numbers of shape {shape}, got {kind}")
    try:
        out = torch.as_tensor(value, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"{what} must be an array of numbers of shape {shape}, got {value!r:.80}") from None
    if out.is_complex():  # complex numbers in a list (or a Python complex): their tensor is complex
        raise ValueError(f"{what} must be an array of real numbers of shape {shape}, got {out.dtype}")
    return out


def jvp(fn: Callable[..., Tensor], primals: tuple[Tensor, ...], tangents: tuple[Tensor, ...]) -> tuple[Tensor, Tensor]:
    """(fn(*primals), J tangents), as ``torch.func.jvp``, by reverse mode twice: J^T u (a graph linear in a dummy
    u), then its gradient in u along the tangents. ``torch.func.jvp`` and ``torch.autograd.forward_ad`` import
    ``torch._dynamo`` on first use (3-4 s of every process's first env, measured) and raise a
    ``torch.jit.script`` DeprecationWarning; this needs neither. One tensor out, detached (no graph kept); not
    under ``torch.inference_mode`` (it needs autograd)."""
    inputs = tuple(p.detach().requires_grad_(True) for p in primals)
    with torch.enable_grad():
        out = fn(*inputs)
        dummy = torch.zeros_like(out, requires_grad=True)
        # scalar outputs: grad_outputs would import torch.fx's symbolic shapes (sympy, ~2 s) in autograd's checks
        vjps = torch.autograd.grad((out * dummy).sum(), inputs, create_graph=True, allow_unused=True)
        pairs = [(v, t) for v, t in zip(vjps, tangents, strict=True) if v is not None and v.requires_grad]
        if not pairs:  # fn does not depend on its inputs, or only through piecewise-constant ops: J = 0
            return out.detach(), torch.zeros_like(out)
        (column,) = torch.autograd.grad(sum((v * t).sum() for v, t in pairs), dummy, allow_unused=True)
    return out.detach(), torch.zeros_like(out) if column is None else column.detach()
