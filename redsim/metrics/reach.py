"""Reach and winding: does a map contain given states, and does a crank go all the way round?

- :func:`reach_error`: min_z |f(z) - q_t|_M for target states q_t, e.g. the bistable bar's two
  buckled equilibria (:func:`buckled_states`).
- :func:`handle_winding`: how far a handle turns about a pivot as a periodic latent goes round.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from redsim.integrators import LatentSpace, as_float64, static_equilibrium
from redsim.integrators.reference import FULL_TOL
from redsim.metrics.common import (
    DISPLACEMENT_FLOOR,
    Subspace,
    check_count,
    configurations,
    latent_space,
    latents,
    m_norm,
    scene_size,
)
from redsim.scene import Scene
from redsim.subspace import periodic_latents


def reach_error(
    scene: Scene,
    subspace: Subspace,
    targets: Sequence[Tensor],
    *,
    samples: int = 4096,
    refine: int = 4,
    seed: int = 0,
    cond: Tensor | None = None,
) -> dict[str, Any]:
    """How close the subspace comes to given configurations: min_z |f(z) - q_t|_M per target.

    The search samples z ~ N(0, 4 I) (``samples`` of them, wider than the fitting distribution
    so tails count), then refines the ``refine`` nearest by L-BFGS over z. The error is relative
    to the target's distance from the seed, |q_t - q_seed|_M: 0 means the subspace contains
    q_t, 1 is what a subspace that only holds the seed scores.

    Args:
        scene: The scene.
        subspace: The map (module doc).
        targets: Configurations q_t [n] (float64 or castable).
        samples: Latent samples of the coarse search (>= 1).
        refine: Nearest samples refined by L-BFGS (>= 1).
        seed: Seed of the samples.
        cond: Condition of a conditional map; default: the scene's.

    Returns:
        ``errors`` (relative, per target), ``distances`` (|f(z*) - q_t|_M [kg^1/2 m]),
        ``latents`` (z* per target), ``samples``, ``seed``.
    """
    check_count("samples", samples, 1)
    check_count("refine", refine, 1)
    space = latent_space(scene, subspace, cond)
    scene64 = space.scene
    mass = scene64.mass_matrix_scipy()
    z = 2.0 * latents(samples, space, seed)
    states = torch.cat(configurations(space, z))
    rows = []
    for target in targets:
        target = target.detach().to(states)
        gaps = (states - target).numpy()
        coarse = np.einsum("bi,bi->b", gaps, (mass @ gaps.T).T)
        best: tuple[float, Tensor] = (math.inf, z[0])
        for start in z[np.argsort(coarse)[:refine]]:
            best = min(best, _nearest_latent(space, mass, target, start), key=lambda pair: pair[0])
        scale = m_norm(mass, target - scene64.q_seed)
        rows.append((best[0], best[0] / max(scale, DISPLACEMENT_FLOOR * scene_size(scene64, mass)), best[1]))
    return {
        "errors": [r[1] for r in rows],
        "distances": [r[0] for r in rows],
        "latents": [r[2].tolist() for r in rows],
        "samples": samples,
        "seed": seed,
    }


def handle_winding(
    scene: Scene,
    subspace: Subspace,
    handle: str,
    center: Sequence[float],
    *,
    latent: int = 0,
    samples: int = 360,
    cond: Tensor | None = None,
) -> dict[str, Any]:
    """How far a handle turns about a point as one periodic latent goes once round the circle.

    Latent ``latent`` sweeps [-pi, pi] in ``samples`` equal steps (the others stay 0); the
    handle's position, projected on the x-y plane, is followed about ``center`` with its angle
    unwrapped. A crank whose map closes the loop turns 360 degrees (winding +-1); a map that
    swings it back and forth turns less and winds 0.

    Args:
        scene: The scene.
        subspace: A map whose latent ``latent`` is periodic (``config.periodic``).
        handle: Handle name.
        center: Pivot (x, y) [m].
        latent: Index of the periodic latent.
        samples: Steps round the circle (>= 8).
        cond: Condition of a conditional map; default: the scene's.

    Returns:
        ``winding`` (whole turns, signed), ``turn_degrees`` (range of the unwrapped angle),
        ``energy_min``/``energy_max`` [J] along the sweep, ``seed_energy`` [J], ``samples``.

    Raises:
        ValueError: an unknown handle, a latent that is not periodic, or too few samples.
    """
    check_count("samples", samples, 8)
    if latent not in periodic_latents(subspace):
        raise ValueError(f"latent {latent} is not periodic (periodic: {list(periodic_latents(subspace))})")
    if handle not in scene.handle_names:
        raise ValueError(f"scene {scene.name!r} has no handle {handle!r}; valid handles: {list(scene.handle_names)}")
    space = latent_space(scene, subspace, cond)
    scene64 = space.scene
    z = torch.zeros(samples + 1, space.latent_dim, dtype=torch.float64)
    z[:, latent] = torch.linspace(-math.pi, math.pi, samples + 1, dtype=torch.float64)
    q = torch.cat(configurations(space, z))
    with torch.no_grad():
        position = scene64.handles[scene64.handle_names.index(handle)].position(scene64.dof_map.expand(q))
        energy = scene64.energy(q, cond=cond)
    offset = (position[:, :2] - torch.as_tensor(center, dtype=torch.float64)[:2]).numpy()
    angle = np.unwrap(np.arctan2(offset[:, 1], offset[:, 0]))
    return {
        "winding": round(float(angle[-1] - angle[0]) / (2.0 * math.pi)),
        "turn_degrees": float(np.degrees(angle.max() - angle.min())),
        "energy_min": float(energy.min()),
        "energy_max": float(energy.max()),
        "seed_energy": float(scene64.energy(scene64.q_seed.unsqueeze(0), cond=cond)[0]),
        "samples": samples,
    }


def buckled_states(scene: Scene, *, bump: float = 0.01, cond: Tensor | None = None) -> list[Tensor]:
    """The two buckled equilibria of a compressed bar (``bistable_bar``): arched up and down.

    Each is the full-space static equilibrium (tolerance FULL_TOL) reached from the seed with
    every free DOF along the scene's last axis (y) moved by +-bump * extent * sin(pi s), s in
    [0, 1] the particle's position along x between the pins.

    Args:
        scene: A 2D or 3D scene whose seed is a straight compressed bar along x.
        bump: Size of the initial arch, relative to the scene's extent.
        cond: Condition of the energy; default: the scene's.

    Returns:
        [q_up, q_down], each [n] float64.

    Raises:
        RuntimeError: a solve did not converge, or both starts reached the same state.
    """
    scene64 = as_float64(scene)
    positions = scene64.full_positions(scene64.q_seed.unsqueeze(0))[0].reshape(-1, scene64.dim)
    x = positions[:, 0]
    s = (x - x.min()) / (x.max() - x.min())
    shape = torch.zeros_like(positions)
    shape[:, -1] = torch.sin(math.pi * s)
    direction = scene64.dof_map.restrict(shape.reshape(1, -1))[0] * bump * scene64.extent()
    states = []
    for sign in (1.0, -1.0):
        q, info = static_equilibrium(scene64, None, cond, q0=scene64.q_seed + sign * direction, tol=FULL_TOL)
        if not info.converged:
            raise RuntimeError(f"buckled state of {scene.name!r} did not converge: {info.message}")
        states.append(q.detach())
    mass = scene64.mass_matrix_scipy()
    if m_norm(mass, states[0] - states[1]) < m_norm(mass, direction):  # closer than the two starts were
        raise RuntimeError(f"scene {scene.name!r}: both bumps reached the same equilibrium (not bistable)")
    return states


def nearest_latent(
    positions: Callable[[Tensor], Tensor],
    scene: Scene,
    target: Tensor,
    start: Tensor,
    *,
    max_iter: int = 200,
    scale: float = 1.0,
    tolerance_grad: float = 1e-7,
) -> Tensor:
    """A local minimum of |f(z) - target|_M over z [1, d], by L-BFGS (strong Wolfe) from ``start`` [1, d].

    ``positions`` maps z [1, d] to f(z) [1, n] (a :class:`LatentSpace`'s ``configuration`` or a stepper's map),
    ``scene`` gives M in the dtype of f(z); the minimized value is |f(z) - target|^2_M / scale^2, so
    ``tolerance_grad`` (L-BFGS's stop on its gradient) is relative to ``scale`` [kg^1/2 m].
    """
    z = start.detach().clone().requires_grad_(True)
    optimizer = torch.optim.LBFGS([z], max_iter=max_iter, line_search_fn="strong_wolfe", tolerance_grad=tolerance_grad)

    def closure() -> Tensor:
        optimizer.zero_grad()
        gap = positions(z) - target
        value = (gap * scene.mass_matvec(gap)).sum() / scale**2
        value.backward()
        return value

    with torch.enable_grad():
        optimizer.step(closure)
    return z.detach()


def _nearest_latent(space: LatentSpace, mass: Any, target: Tensor, start: Tensor) -> tuple[float, Tensor]:
    """Local minimum of |f(z) - target|_M over z from ``start`` [d]: (distance [kg^1/2 m], z [d])."""
    z = nearest_latent(space.configuration, space.scene, target, start.unsqueeze(0))
    with torch.no_grad():
        q = space.configuration(z)[0]
    return m_norm(mass, q - target), z[0]
