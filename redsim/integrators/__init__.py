"""Integrators and equilibria over the full space or a subspace, all minimizing one objective.

- :mod:`~redsim.integrators.spaces`: the coordinates solved for, :class:`FullSpace` (q, the
  float64 reference) and :class:`LatentSpace` (the latent z of a subspace map q = f(z)).
- :mod:`~redsim.integrators.objective`: :class:`PotentialObjective`, the inertia term, the
  per-scene constants, and the scales the convergence test reads.
- :mod:`~redsim.integrators.implicit_euler`: :class:`ImplicitEuler`, the two-state implicit
  Euler of the paper, its :class:`FullState` and per-step :class:`StepInfo`;
  :mod:`~redsim.integrators.energy_gain`: the test that a step's K + E rose by more than its loads' work.
- :mod:`~redsim.integrators.equilibrium`: :func:`static_equilibrium` (over q) and
  :func:`latent_equilibrium` (over z).
- :mod:`~redsim.integrators.reference`: the robust full-space equilibria metrics measure
  against (relaxation, saddle escapes), :func:`rest_state`;
  :mod:`~redsim.integrators.cache`: their in-memory and on-disk cache.
"""

from __future__ import annotations

from redsim.integrators.equilibrium import latent_equilibrium, static_equilibrium
from redsim.integrators.implicit_euler import FullState, ImplicitEuler, LoadSchedule, StepInfo
from redsim.integrators.objective import (
    MIN_TIME_STEP,
    Inertia,
    PotentialObjective,
    SceneConstants,
    check_time_step,
    length_scale,
)
from redsim.integrators.spaces import FullSpace, LatentSpace, Space, as_float64, map_condition_dim, map_tensor

__all__ = [
    "MIN_TIME_STEP",
    "FullSpace",
    "FullState",
    "ImplicitEuler",
    "Inertia",
    "LatentSpace",
    "LoadSchedule",
    "PotentialObjective",
    "SceneConstants",
    "Space",
    "StepInfo",
    "as_float64",
    "check_time_step",
    "latent_equilibrium",
    "length_scale",
    "map_condition_dim",
    "map_tensor",
    "static_equilibrium",
]
