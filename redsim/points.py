"""Points that move linearly with the configuration vector.

Every place where an effect, a handle or a drawing needs a position is a :class:`PointSet`:
a particle (one entry of x per coordinate), a point fixed in a rigid body (the affine 3x4
``[R | t]`` of the body times ``[v; 1]``), a direction fixed in a body (``R v``) or a fixed
world point. All of them are

    p[i, a] = sum_c x[dofs[i, a, c]] * weights[i, c] + offset[i, a],

so one gather serves them all and mixed sets vectorize.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class PointSet:
    """A set of P points in D dimensions, linear in the full configuration x.

    Attributes:
        dofs: Indices into the full configuration, shape [P, D, K], int64.
        weights: Coefficients of those entries, shape [P, K], float.
        offset: Constant part [m], shape [P, D], float.
    """

    dofs: Tensor
    weights: Tensor
    offset: Tensor

    def __post_init__(self) -> None:
        P, D, K = self.dofs.shape
        if self.weights.shape != (P, K) or self.offset.shape != (P, D):
            raise ValueError(
                f"PointSet shapes disagree: dofs {tuple(self.dofs.shape)}, weights "
                f"{tuple(self.weights.shape)}, offset {tuple(self.offset.shape)}"
            )

    @property
    def count(self) -> int:
        return int(self.dofs.shape[0])

    @property
    def dim(self) -> int:
        return int(self.dofs.shape[1])

    @property
    def local_size(self) -> int:
        """Number of x entries one point reads (D * K)."""
        return int(self.dofs.shape[1] * self.dofs.shape[2])

    def local_dofs(self) -> Tensor:
        """Full-configuration indices each point reads, shape [P, D*K]."""
        return self.dofs.reshape(self.count, -1)

    def positions(self, x: Tensor) -> Tensor:
        """Positions [m], shape [B, P, D], from full configurations x of shape [B, N]."""
        return self.local_positions(x[:, self.local_dofs()])

    def local_positions(self, xe: Tensor) -> Tensor:
        """Positions [B, P, D] from the gathered entries xe = x[:, local_dofs()], shape [B, P, D*K]."""
        B = xe.shape[0]
        P, D, K = self.dofs.shape
        return (xe.reshape(B, P, D, K) * self.weights[:, None, :]).sum(-1) + self.offset

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> PointSet:
        return PointSet(
            self.dofs.to(device=device),
            self.weights.to(device=device, dtype=dtype),
            self.offset.to(device=device, dtype=dtype),
        )

    def __getitem__(self, index: Tensor | slice) -> PointSet:
        return PointSet(self.dofs[index], self.weights[index], self.offset[index])

    @staticmethod
    def particles(vertex_dofs: Tensor, *, dtype: torch.dtype = torch.float64) -> PointSet:
        """Particles whose coordinates are x[vertex_dofs[i, a]]; vertex_dofs has shape [P, D]."""
        vertex_dofs = torch.as_tensor(vertex_dofs, dtype=torch.int64)
        P, D = vertex_dofs.shape
        return PointSet(
            vertex_dofs[:, :, None],
            torch.ones(P, 1, dtype=dtype),
            torch.zeros(P, D, dtype=dtype),
        )

    @staticmethod
    def body_points(body_dofs: Tensor, local: Tensor, *, direction: bool = False) -> PointSet:
        """Points (or, with ``direction=True``, directions) fixed in one rigid body.

        Args:
            body_dofs: The body's 12 entries of x, row-major ``[R | t]``, shape [12], int64.
            local: Body-frame coordinates [m], shape [P, 3].
            direction: Directions transform by R only (weight 0 on t).
        """
        local = torch.as_tensor(local, dtype=torch.float64)
        P = local.shape[0]
        dofs = torch.as_tensor(body_dofs, dtype=torch.int64).reshape(1, 3, 4).expand(P, 3, 4).clone()
        homogeneous = torch.zeros(P, 1, dtype=local.dtype) if direction else torch.ones(P, 1, dtype=local.dtype)
        weights = torch.cat([local, homogeneous], dim=1)
        return PointSet(dofs, weights, torch.zeros(P, 3, dtype=local.dtype))

    @staticmethod
    def world(points: Tensor, *, k: int = 1) -> PointSet:
        """Fixed world points [m], shape [P, D]; they read x[0] with weight 0 (k entries per coordinate)."""
        points = torch.as_tensor(points, dtype=torch.float64)
        P, D = points.shape
        return PointSet(
            torch.zeros(P, D, k, dtype=torch.int64),
            torch.zeros(P, k, dtype=points.dtype),
            points.clone(),
        )

    @staticmethod
    def cat(sets: list[PointSet] | tuple[PointSet, ...]) -> PointSet:
        """Concatenate point sets of one dimension, padding K with zero weights."""
        if not sets:
            raise ValueError("PointSet.cat needs at least one set")
        K = max(s.dofs.shape[2] for s in sets)
        dofs, weights = [], []
        for s in sets:
            pad = K - s.dofs.shape[2]
            dofs.append(torch.nn.functional.pad(s.dofs, (0, pad), value=int(s.dofs.reshape(-1)[0]) if s.count else 0))
            weights.append(torch.nn.functional.pad(s.weights, (0, pad)))
        return PointSet(torch.cat(dofs), torch.cat(weights), torch.cat([s.offset for s in sets]))
