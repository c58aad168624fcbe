"""The potential a latent stepper evaluates, as a pluggable object (the :class:`LatentEnergy` protocol).

The stepper minimizes, per state b,

    Phi_b(z) = 1/(2 h^2) |q(z) - qbar_b|_M^2 + E(z; c_b) - F_b . p(q(z)),

where q(z) are the free DOFs the map gives, p(q) the handle positions (linear in q) and F_b the
loads. The stepper owns the inertia and load terms (they only need q); the energy object owns
E(z; c) and the map. :class:`MapEnergy` is today's E: ``scene.energy`` composed with the map,
every effect except the load term. A cubature energy drops in by implementing the same protocol,
plus the optional :class:`ReducedInertia` (its features r with q = r W^T + b) so that the stepper's
inertia and load terms need no pass over all of q either.
"""

from __future__ import annotations

import copy
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor, nn

from redsim.devices import check_device
from redsim.integrators import map_condition_dim
from redsim.scene import Scene
from redsim.subspace import periodic_latents


@runtime_checkable
class LatentEnergy(Protocol):
    """What a latent stepper needs from an energy: E(z; c) [J] and the configurations q = f(z; c).

    Attributes:
        latent_dim: d, the size of z.
        condition_dim: m, the size of the map's condition c (0 for an unconditional map).
        periodic: Indices of latents that are angles (never out of range).
    """

    latent_dim: int
    condition_dim: int
    periodic: tuple[int, ...]

    def energy(self, z: Tensor, cond: Tensor | None) -> tuple[Tensor, Tensor | None]:
        """Potential energy E [J], shape [B], of latents z [B, d] (differentiable in z), and q [B, n] if computed.

        ``cond`` [B, m] is the scene condition (None for a scene without one). Returning q (when it
        was computed on the way) saves the stepper a second pass through the map.
        """
        ...

    def positions(self, z: Tensor, cond: Tensor | None) -> Tensor:
        """Free configurations q [B, n] of latents z [B, d] (differentiable in z)."""
        ...


@runtime_checkable
class ReducedInertia(Protocol):
    """Optional extension of :class:`LatentEnergy`: q(z) = r(z) W^T + b with few features r.

    An energy that also implements this lets the stepper evaluate the inertia term
    1/(2h^2)|q - qbar|_M^2 = 1/(2h^2)(r - rbar)^T (W^T M W)(r - rbar) and the load term in r, exactly
    and at a cost that does not grow with n (W^T M W [w, w] is computed once). Energies without it
    (:class:`MapEnergy`) are stepped over all of q, as before.

    Attributes:
        output_weight: W, shape [n, w].
        output_bias: b, shape [n].
    """

    output_weight: Tensor
    output_bias: Tensor

    def features(self, z: Tensor, cond: Tensor | None) -> Tensor:
        """r [B, w] of latents z [B, d] (differentiable in z)."""
        ...

    def energy_features(self, z: Tensor, cond: Tensor | None) -> tuple[Tensor, Tensor]:
        """E [B] [J] and the features r [B, w] it computed on the way."""
        ...


class MapEnergy:
    """E(z; c) = sum of the scene's effects at q = f(z[, c]), the load term left to the stepper.

    The map and the scene are copied to ``dtype`` and ``device`` (the caller's objects are never
    modified). A conditional map is called as f(z, c) with the scene condition c.

    Args:
        scene: The scene.
        subspace: The map z [..., d] -> q [..., n] (``latent_dim`` attribute; an ``nn.Module`` is copied).
        dtype: Floating dtype of every evaluation.
        device: Where the evaluations run.

    Raises:
        ValueError: a map without an integer ``latent_dim`` or whose output is not [B, n], or a device redsim
            cannot run on.
    """

    def __init__(
        self,
        scene: Scene,
        subspace: nn.Module,
        *,
        dtype: torch.dtype = torch.float32,
        device: str | torch.device = "cpu",
    ) -> None:
        device = check_device(device)
        latent_dim = getattr(subspace, "latent_dim", None)
        if not isinstance(latent_dim, int) or latent_dim < 1:
            raise ValueError(f"the subspace must have an integer latent_dim >= 1, got {latent_dim!r}")
        self.latent_dim = latent_dim
        self.condition_dim = map_condition_dim(subspace)
        self.periodic = periodic_latents(subspace)
        self.scene = scene.to(device=device, dtype=dtype)
        self.map = (
            copy.deepcopy(subspace).to(device=device, dtype=dtype) if isinstance(subspace, nn.Module) else subspace
        )
        if isinstance(self.map, nn.Module):
            self.map.requires_grad_(False)
        self.effects = self.scene.load_free_effects("the latent runtime")
        with torch.no_grad():
            cond = self.scene.pack_condition(None, 1, self.scene.q_seed) if self.condition_dim else None
            q = self.positions(torch.zeros(1, latent_dim, dtype=dtype, device=device), cond)
        if q.shape != (1, scene.free_dof_count):
            raise ValueError(
                f"the subspace maps z [1, {latent_dim}] to {tuple(q.shape)}; "
                f"scene {scene.name!r} needs [1, {scene.free_dof_count}]"
            )

    def positions(self, z: Tensor, cond: Tensor | None) -> Tensor:
        """q = f(z[, c]) [B, n]."""
        return self.map(z, cond) if self.condition_dim else self.map(z)

    def q_energy(self, q: Tensor, cond: Tensor | None) -> Tensor:
        """E(q; c) [B] of free configurations q [B, n]: every effect but the load term."""
        x = self.scene.full_positions(q)
        total = self.effects[0].energy(x, cond) if self.effects else q.new_zeros(q.shape[0])
        for effect in self.effects[1:]:
            total = total + effect.energy(x, cond)
        return total

    def energy(self, z: Tensor, cond: Tensor | None) -> tuple[Tensor, Tensor]:
        """E(f(z); c) [B] (all effects but the load term) and q [B, n]."""
        q = self.positions(z, cond)
        return self.q_energy(q, cond), q


__all__ = ["LatentEnergy", "MapEnergy", "ReducedInertia"]
