"""Whether a solved time step can be trusted: finite, and physically possible for its scene.

A minimizer's convergence test is relative to the forces acting (:mod:`redsim.solvers`), so a
load far beyond anything the scene models (10^30 N on a 1 kg chain) still "converges": the
gradient is small next to the load. :func:`step_failure` catches what such a step leaves behind.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from redsim.scene import Scene

MAX_STEP_SIZES = 10.0
"""A step whose forces move any DOF more than this many scene sizes (``Scene.extent()``) away from
where inertia alone takes it has failed: at dt = 0.01 s and a 1 m scene that is an acceleration of
10^5 m/s^2. Free fall moves g dt^2 (1 mm at dt = 0.01 s), so fast but physical motion passes."""


def step_failure(scene: Scene, q_inertial: Tensor, q_after: Tensor, grad_norm: float, energy: float) -> str | None:
    """Why a time step that ended at ``q_after`` failed, or None.

    Args:
        scene: The scene stepped.
        q_inertial: Where inertia alone takes the state, 2 q_t - q_{t-1}, shape [n].
        q_after: Configuration after the step, shape [n].
        grad_norm: The minimizer's final gradient norm.
        energy: Potential energy [J] at ``q_after`` (loads included).
    """
    if not bool(torch.isfinite(q_after).all()):
        return "the state is not finite (NaN or inf)"
    if not math.isfinite(grad_norm):
        return f"the gradient is not finite (|grad| {grad_norm})"
    if not math.isfinite(energy):
        return f"the energy is not finite (E {energy} J)"
    moved = float((q_after - q_inertial).abs().max()) if q_after.numel() else 0.0
    size = scene.extent()
    if moved > MAX_STEP_SIZES * size:
        return (
            f"the forces moved a coordinate {moved:.3g} m in one step, more than {MAX_STEP_SIZES:g}x the scene's size "
            f"({size:.3g} m), with E {energy:.3g} J and |grad| {grad_norm:.3g}: the loads or dt are far beyond "
            "what this scene can take"
        )
    return None
