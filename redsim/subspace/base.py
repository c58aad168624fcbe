"""What every non-neural subspace map shares: a kind, JSON-able metadata, a checkpoint.

A map of this family (:mod:`redsim.subspace.linear`, :mod:`redsim.subspace.autoencoder`) has the
interface of :class:`redsim.subspace.SubspaceMap` (``latent_dim``, ``metadata``,
``__call__(z [..., d], cond=None) -> q [..., n]``), so integrators, environments and metrics take
it in place of the neural map, and ``.to(dtype)`` casts it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from redsim.subspace.checkpoint import write_checkpoint


class MapModule(nn.Module):
    """Shared metadata, save and shape bookkeeping of the maps built by :mod:`redsim.baselines`.

    Subclasses set ``kind`` (the key stored in their checkpoints) and implement ``latent_dim``,
    :meth:`shapes` and :meth:`from_shapes`.
    """

    kind: ClassVar[str]

    def __init__(self, metadata: dict[str, Any] | None) -> None:
        super().__init__()
        self.metadata: dict[str, Any] = {**dict(metadata or {}), "kind": self.kind}

    @property
    def latent_dim(self) -> int:
        """d, the size of z."""
        raise NotImplementedError

    def shapes(self) -> dict[str, Any]:
        """What :meth:`from_shapes` needs to rebuild an empty module of this shape (JSON-able)."""
        raise NotImplementedError

    @classmethod
    def from_shapes(cls, shapes: dict[str, Any], metadata: dict[str, Any]) -> MapModule:
        """An instance with the given shapes and placeholder values (for loading a state dict)."""
        raise NotImplementedError

    def save(self, stem: str | Path) -> tuple[Path, Path]:
        """Write ``stem.pt`` (state dict) and ``stem.json`` (kind, shapes, metadata); returns both paths."""
        return write_checkpoint(self, stem, self.shapes())


def check_latent(z: Tensor, d: int, cond: Tensor | None) -> None:
    """Refuse latents z [..., d'] with d' != d, and any condition (these maps take none)."""
    if z.shape[-1] != d:
        raise ValueError(f"z must have {d} entries in its last dim, got {tuple(z.shape)}")
    if cond is not None:
        raise ValueError("this subspace takes no condition (it was built at the scene's default condition)")


def dtype_name(dtype: torch.dtype) -> str:
    """The name of a dtype as checkpoints record it ("float64" for torch.float64)."""
    return str(dtype).removeprefix("torch.")
