"""The restart solve (a solve that ended above Phi(z_t), solved again from z_t) converges to the same gradient scale
as the first solve of its step (hand mutation audit, helper-281; helper-276 left it open: nothing checked the scale
the restart passes to ``minimize``). Step 5 of tests/runtime/test_restart.py's rollout restarts."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

import redsim  # noqa: F401  (registers the ids)
from redsim.runtime import stepper as stepper_module


@pytest.mark.parametrize("dense", [False, True])
def test_the_restart_solves_to_the_first_solves_scale(dense: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[torch.Tensor, float]] = []
    real = stepper_module.minimize

    def spy(objective, z0, scale, noise, **options):
        calls.append((scale.detach().clone(), options["tol"]))
        result = real(objective, z0, scale, noise, **options)
        calls[-1] = (*calls[-1], result)
        return result

    monkeypatch.setattr(stepper_module, "minimize", spy)
    env = gym.make("RedSim/MiniChain-v0", dtype="float64", stepper_options={"dense": dense}).unwrapped
    actions = np.random.default_rng(0).uniform(-1, 1, (8, 3)).astype(np.float32)
    env.reset(seed=0)
    restarted = 0
    for action in actions:
        calls.clear()
        _, _, _, _, info = env.step(action)
        assert info["converged"]
        if len(calls) == 2:  # the first solve and its restart
            restarted += 1
            (first_scale, first_tol, _), (_, _, retry) = calls
            # the restart stops where the first solve would have: |dPhi/dz| within tol of the step's own scale
            assert bool((retry.grad_norm <= first_tol * first_scale).all()), (retry.grad_norm, first_tol * first_scale)
    assert restarted >= 1
