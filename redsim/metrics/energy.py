"""Energy and stretch of a map's states: the two terms of the fitting loss, measured.

- :func:`energy_stats`: the energy of subspace states, absolute and relative to the drop from
  the seed to the full-space rest equilibrium (the fitting loss's first term).
- :func:`stretch_stats`: the metric stretch |f(z) - f(z')|_M / (sigma |z - z'|) over all pairs
  (supplement A.1; the fitting loss's second term, :func:`redsim.subspace.pair_log_ratios`).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from redsim.integrators.reference import full_equilibrium
from redsim.metrics.common import Subspace, check_count, configurations, latent_space, latents, summary
from redsim.scene import Scene
from redsim.subspace import pair_log_ratios, periodic_latents

RELATIVE_ENERGY_FLOOR = 1e-9
"""Seed-to-rest energy drop, relative to the energies involved, below which the relative energy is undefined."""


def energy_stats(
    scene: Scene, subspace: Subspace, *, samples: int = 1000, seed: int = 0, cond: Tensor | None = None
) -> dict[str, Any]:
    """Energies E(f(z)) [J] of subspace states, z ~ N(0, I), and how they compare with the seed's.

    Energies carry arbitrary constants (gravity's zero level), so only differences mean
    anything. The reference points are the seed q_seed and the rest equilibrium q_rest, the
    full-space static equilibrium without loads reached from the seed (Newton, with the
    relaxation fallback and saddle escapes of
    :func:`redsim.integrators.reference.full_equilibrium`; cached):

    - ``excess_energy`` = mean E(f(z)) - E(q_rest) [J], >= 0 unless a sample finds a lower basin;
    - ``relative_energy`` = excess_energy / (E(q_seed) - E(q_rest)), unit-free: 0 when the states
      are on average as low as the rest equilibrium, 1 when they are as high as the seed (e.g. a
      cloth held flat), above 1 when higher. It is None (undefined) when the seed already is at
      rest (no gravity or preload: the drop is below ``RELATIVE_ENERGY_FLOOR`` times the seed's and
      the rest's energies); then compare ``excess_energy`` between subspaces of one scene.

    Args:
        scene: The scene (evaluated in float64).
        subspace: The map (module doc).
        samples: Number of latent samples (>= 1).
        seed: Seed of the latent samples.
        cond: Condition [m] of the energy (and of a conditional map); default: the scene's.

    Returns:
        ``mean_energy``, ``median_energy``, ``max_energy``, ``min_energy``, ``seed_energy``,
        ``rest_energy`` [J], ``rest_converged``, ``excess_energy`` [J], ``relative_energy``,
        ``samples``, ``seed``.
    """
    check_count("samples", samples, 1)
    space = latent_space(scene, subspace, cond)
    scene64 = space.scene
    z = latents(samples, space, seed)
    energies = torch.cat([scene64.energy(q, cond=cond) for q in configurations(space, z)])
    seed_energy = float(scene64.energy(scene64.q_seed.unsqueeze(0), cond=cond)[0])
    rest, rest_converged, _ = full_equilibrium(scene64, None, cond)
    rest_energy = float(scene64.energy(rest.unsqueeze(0), cond=cond)[0])
    mean = float(energies.mean())
    drop = seed_energy - rest_energy
    floor = RELATIVE_ENERGY_FLOOR * max(abs(seed_energy), abs(rest_energy))  # not the samples': a map's own cost
    return {
        "samples": samples,
        "seed": seed,
        **summary(energies, suffix="_energy"),
        "seed_energy": seed_energy,
        "rest_energy": rest_energy,
        "rest_converged": rest_converged,
        "excess_energy": mean - rest_energy,
        "relative_energy": (mean - rest_energy) / drop if drop > floor else None,
    }


def stretch_stats(
    scene: Scene, subspace: Subspace, sigma: float, *, samples: int = 256, seed: int = 0, cond: Tensor | None = None
) -> dict[str, Any]:
    """The metric stretch s = |f(z) - f(z')|_M / (sigma |z - z'|) over all pairs of samples.

    Supplement A.1: a good fit keeps the mean near 1 (the map spreads its states by sigma per
    unit z in the mass metric) but not within 1e-3 of it everywhere (then it is forced affine).
    An isometric affine map f(z) = b + sigma A z with A^T M A = I has s = 1 for every pair.

    Args:
        scene: The scene (supplies M, float64).
        subspace: The map (module doc).
        sigma: σ [the unit of |q|_M per unit z], > 0.
        samples: Number of latent samples (>= 2); all samples (samples - 1) / 2 pairs are used.
        seed: Seed of the latent samples.
        cond: Condition of a conditional map; default: the scene's.

    Returns:
        ``mean``, ``std``, ``min``, ``max`` of s, ``mean_log`` (mean of log s) and
        ``rms_log`` (the root of the fitting loss's pair term), ``pairs``, ``sigma``, ``samples``, ``seed``.
    """
    check_count("samples", samples, 2)
    if not (math.isfinite(sigma) and sigma > 0.0):
        raise ValueError(f"sigma must be finite and > 0, got {sigma!r}")
    space = latent_space(scene, subspace, cond)
    z = latents(samples, space, seed)
    y = torch.cat(list(configurations(space, z)))
    log_ratio = pair_log_ratios(y, z, space.scene, sigma, periodic_latents(space.subspace))
    stretch = torch.exp(log_ratio)
    return {
        "samples": samples,
        "seed": seed,
        "sigma": float(sigma),
        "pairs": int(stretch.numel()),
        "mean": float(stretch.mean()),
        "std": float(stretch.std()),
        "min": float(stretch.min()),
        "max": float(stretch.max()),
        "mean_log": float(log_ratio.mean()),
        "rms_log": float(torch.sqrt((log_ratio**2).mean())),
    }
