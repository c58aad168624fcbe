"""What every metric shares: evaluating a map through its latent space, seeded samples, M-norms.

Every metric takes any subspace object (a callable z [..., d] -> q [..., n] with a
``latent_dim``, e.g. :class:`redsim.subspace.SubspaceMap` or a :class:`redsim.subspace.LinearSubspace`;
a conditional map with ``config.condition_dim > 0`` is evaluated at ``cond``) and evaluates it
through :class:`redsim.integrators.LatentSpace`: the map runs in its own dtype, everything after
it (energies, norms, solves) in float64. Latent samples come from a ``torch.Generator`` seeded
with ``seed``, so every number is reproducible.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from redsim.integrators import LatentSpace, map_condition_dim
from redsim.scene import Scene
from redsim.subspace import periodic_latents, sample_latents

DISPLACEMENT_FLOOR = 1e-6
"""Smallest load response, relative to the M-norm size of the scene, that relative errors divide by."""
CHUNK = 256
"""Latent samples mapped and evaluated per batch (bounds memory on large scenes)."""

Subspace = Callable[..., Tensor]
"""What a metric measures: a map z [..., d] -> q [..., n] with a ``latent_dim``."""


def check_count(name: str, value: int, low: int) -> None:
    """Refuse a count that is not an integer >= low (ValueError naming it)."""
    if int(value) != value or value < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")


def latent_space(scene: Scene, subspace: Subspace, cond: Tensor | None) -> LatentSpace:
    """The latent space of the map, at condition ``cond`` if the map is conditional."""
    return LatentSpace(scene, subspace, cond=cond if map_condition_dim(subspace) else None)


def latents(samples: int, space: LatentSpace, seed: int) -> Tensor:
    """Latent samples [samples, d] of the space's map (:func:`redsim.subspace.sample_latents`), float64, seeded."""
    generator = torch.Generator().manual_seed(seed)
    return sample_latents(
        samples, space.latent_dim, periodic_latents(space.subspace), generator=generator, dtype=torch.float64
    )


def configurations(space: LatentSpace, z: Tensor) -> list[Tensor]:
    """f(z) [B, n] (float64) in chunks of at most CHUNK samples."""
    with torch.no_grad():
        return [space.configuration(chunk) for chunk in z.split(CHUNK)]


def m_norm(mass: Any, v: Tensor) -> float:
    """|v|_M [kg^1/2 m] of a vector v [n]."""
    x = v.detach().cpu().numpy()
    return math.sqrt(max(float(x @ (mass @ x)), 0.0))


def scene_size(scene: Scene, mass: Any) -> float:
    """S = sqrt(sum diag M) L [kg^1/2 m], the M-norm size of the scene (L its largest extent)."""
    return math.sqrt(float(mass.diagonal().sum())) * scene.extent()


def summary(values: Tensor, keys: Sequence[str] = ("mean", "median", "max", "min"), suffix: str = "") -> dict[str, Any]:
    """Statistics of values [S] as floats, e.g. ``{"mean_energy": ...}`` for ``suffix="_energy"``."""
    stats = {"mean": values.mean, "median": values.median, "max": values.max, "min": values.min}
    return {key + suffix: float(stats[key]()) for key in keys}
