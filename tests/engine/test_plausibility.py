"""A failed time step is told apart from fast but physical motion."""

from __future__ import annotations

import math

import torch

import redsim
from redsim.plausibility import MAX_STEP_SIZES, step_failure


def test_step_failure_flags_only_what_forces_could_not_do() -> None:
    scene = redsim.scenes.build("toy_two_tets")
    size = scene.extent()
    q = scene.q_seed.clone()
    fast = q + 50.0 * size  # moving fast: far from the previous state, close to the inertial target
    assert step_failure(scene, fast, fast + 9.81 * 0.02**2, 1e-9, -1.0) is None
    assert step_failure(scene, q, q + 0.5 * MAX_STEP_SIZES * size, 1e-9, -1.0) is None
    why = step_failure(scene, q, q + 2.0 * MAX_STEP_SIZES * size, 1e-9, -1.0)
    assert why is not None and "10x the scene's size" in why
    assert "not finite" in step_failure(scene, q, q * math.nan, 1.0, 0.0)
    assert "gradient is not finite" in step_failure(scene, q, q, math.inf, 0.0)
    assert "energy is not finite" in step_failure(scene, q, q, 1.0, -math.inf)
    assert step_failure(scene, q, torch.zeros_like(q) + q, 0.0, 0.0) is None
