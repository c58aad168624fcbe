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
"""A step that moves any DOF by more than this many scene sizes (``Scene.extent()``) has failed:
at dt = 0.01 s and a 1 m scene that is 1 km/s."""


def step_failure(scene: Scene, q_before: Tensor, q_after: Tensor, grad_norm: float, energy: float) -> str | None:
    """Why the step from ``q_before`` to ``q_after`` (free configurations [n]) failed, or None.

    Args:
        scene: The scene stepped.
        q_before: Configuration before the step, shape [n].
        q_after: Configuration after it, shape [n].
        grad_norm: The minimizer's final gradient norm.
        energy: Potential energy [J] at ``q_after`` (loads included).
    """
    if not bool(torch.isfinite(q_after).all()):
        return "the state is not finite (NaN or inf)"
    if not math.isfinite(grad_norm):
        return f"the gradient is not finite (|grad| {grad_norm})"
    if not math.isfinite(energy):
        return f"the energy is not finite (E {energy} J)"
    moved = float((q_after - q_before).abs().max()) if q_after.numel() else 0.0
    size = scene.extent()
    if moved > MAX_STEP_SIZES * size:
        return (
            f"the step moved a coordinate by {moved:.3g} m, more than {MAX_STEP_SIZES:g}x the scene's size "
            f"({size:.3g} m), with E {energy:.3g} J and |grad| {grad_norm:.3g}: the loads or dt are far beyond "
            "what this scene can take"
        )
    return None
