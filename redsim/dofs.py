"""Free and pinned degrees of freedom."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class DofMap:
    """Maps free configurations q (pinned entries removed) to full configurations x and back.

    Attributes:
        free_index: Full index of each free entry, shape [n], int64.
        full_values: Full configuration holding the pinned values [m], shape [N]; the free
            entries hold the seed and are overwritten by :meth:`expand`.
    """

    free_index: Tensor
    full_values: Tensor

    @property
    def free_dof_count(self) -> int:
        return int(self.free_index.shape[0])

    @property
    def full_dof_count(self) -> int:
        return int(self.full_values.shape[0])

    @property
    def pinned_index(self) -> Tensor:
        """Full indices of the pinned entries, shape [N - n], int64."""
        mask = torch.ones(self.full_dof_count, dtype=torch.bool, device=self.free_index.device)
        mask[self.free_index] = False
        return torch.nonzero(mask).reshape(-1)

    def full_to_free(self) -> Tensor:
        """Free index of every full entry, -1 where pinned, shape [N], int64."""
        out = torch.full((self.full_dof_count,), -1, dtype=torch.int64, device=self.free_index.device)
        out[self.free_index] = torch.arange(self.free_dof_count, device=self.free_index.device)
        return out

    def expand(self, q: Tensor) -> Tensor:
        """Full configurations [B, N] from free ones [B, n] (differentiable in q)."""
        base = self.full_values.to(q.dtype).expand(q.shape[0], -1)
        return base.index_copy(1, self.free_index, q)

    def restrict(self, x: Tensor) -> Tensor:
        """Free configurations [B, n] from full ones [B, N]."""
        return x[:, self.free_index]

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> DofMap:
        return DofMap(self.free_index.to(device=device), self.full_values.to(device=device, dtype=dtype))
