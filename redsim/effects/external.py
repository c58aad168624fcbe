"""Linear potentials: gravity and external loads on handles."""

from __future__ import annotations

import torch
from torch import Tensor

from redsim.effects.base import Effect, per_element
from redsim.points import PointSet


class Gravity(Effect):
    """E = -sum_i m_i g . p_i over particles and rigid-body centres of mass.

    Args:
        name: Term name.
        points: Where the masses sit (vertices, body centroids), P of them.
        masses: Mass [kg] of each point, shape [P].
        acceleration: Gravitational acceleration [m/s^2], shape [D] (e.g. (0, -9.81, 0)), finite.

    Raises:
        ValueError: ``acceleration`` is not D finite numbers, or a mass is negative or not finite.
    """

    kind = "gravity"

    def __init__(self, name: str, points: PointSet, masses: Tensor, acceleration: Tensor) -> None:
        self.name = name
        self.points = points
        self.element_dofs = points.local_dofs()
        masses = torch.as_tensor(masses, dtype=torch.float64).reshape(points.count)
        self.masses = per_element(masses, points.count, f"masses of {name!r}")
        given = torch.as_tensor(acceleration, dtype=torch.float64)
        if given.numel() != points.dim or not bool(torch.isfinite(given).all()):
            raise ValueError(
                f"acceleration of {name!r} must be {points.dim} finite numbers (the scene's dimension), got "
                f"{given.tolist()}"
            )
        self.acceleration = given.reshape(points.dim)
        self._precompute()

    def _precompute(self) -> None:
        """E is linear in x: E = x . coefficients + constant, precomputed for the hot path (:meth:`energy`)."""
        points = self.points
        weight = -self.masses[:, None, None] * self.acceleration[None, :, None] * points.weights[:, None, :]
        size = int(points.dofs.max()) + 1 if points.count else 0
        self.coefficients = weight.new_zeros(size).index_add_(0, points.dofs.reshape(-1), weight.reshape(-1))
        self.constant = -(self.masses[:, None] * self.acceleration * points.offset).sum()

    def subset(self, index: Tensor) -> Gravity:
        """The gravity of the points ``index`` only (its linear form recomputed: :meth:`energy` is theirs)."""
        out: Gravity = super().subset(index)  # type: ignore[assignment]
        out._precompute()
        return out

    def element_energy(self, xe: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        return -self.masses * (self.points.local_positions(xe) * self.acceleration).sum(-1)

    def energy(self, x: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        """The element sum, computed as one dot product (it is linear in x)."""
        size = self.coefficients.shape[0]
        return x[:, :size] @ self.coefficients + self.constant


class ExternalLoad(Effect):
    """E = -sum_i w_i F_h(i) . p_i: a force F_h [N] per handle, spread over the handle's points.

    Loads arrive per step as a tensor [B, H, D] (H handles in scene order); without loads
    the term is zero.

    Args:
        name: Term name.
        points: All handle points, P of them.
        handle_index: Handle of each point, shape [P], int64.
        weights: Share of the handle's force on each point, shape [P] (each handle sums to 1).
        handle_count: Number of handles H.
    """

    kind = "external_load"
    uses_loads = True

    def __init__(self, name: str, points: PointSet, handle_index: Tensor, weights: Tensor, handle_count: int) -> None:
        self.name = name
        self.points = points
        self.element_dofs = points.local_dofs()
        self.handle_index = torch.as_tensor(handle_index, dtype=torch.int64).reshape(points.count)
        self.weights = torch.as_tensor(weights, dtype=torch.float64).reshape(points.count)
        self.handle_count = int(handle_count)

    def element_energy(self, xe: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        if loads is None:
            return xe.new_zeros(xe.shape[:2])
        force = loads[:, self.handle_index]  # [B, P, D]
        return -self.weights * (self.points.local_positions(xe) * force).sum(-1)
