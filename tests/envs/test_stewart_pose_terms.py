"""Stewart-v0's pose terms by hand (hand mutation audit, helper-281): success needs the position AND the orientation
within their radii, and the observation's turn is the rotation still to make (target times current^T), not its
inverse. Either mutation passed tests/envs/test_linkage_envs.py and tests/envs/test_golden.py."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import torch

import redsim  # noqa: F401  (registers the ids)
from redsim.envs.stewart import SUCCESS_FRACTION


def _about_y(angle: float, dtype: torch.dtype) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=dtype)


def test_a_target_at_the_plates_place_but_turned_is_no_success_and_its_turn_is_observed() -> None:
    env = gym.make("RedSim/Stewart-v0")
    try:
        env.reset(seed=0)
        sim = env.unwrapped.sim
        task = sim.task
        p, r = task.pose(sim.x)
        angle = min(1.0, 5.0 * SUCCESS_FRACTION * task.angle_scale)  # five success radii, below 1 rad
        turn = _about_y(angle, r.dtype)
        sim.params["target_position"][:] = p
        sim.params["target_rotation"][:] = turn @ r
        m = task.metrics(sim.x, sim.params)
        assert float(m["distance"][0]) < 1e-6 and abs(float(m["angle"][0]) - angle) < 1e-3 * angle
        assert not bool(m["is_success"][0])
        _, terms = task.reward(sim.x, torch.zeros(1, task.action_size, dtype=r.dtype), sim.params)
        assert float(terms["success"][0]) == 0.0
        extras = task.extras(sim.x, sim.x_prev, sim.params)[0, -3:]
        np.testing.assert_allclose(extras.numpy(), [0.0, math.sin(angle), 0.0], atol=1e-2 * angle)  # r: affine, near R
        sim.params["target_rotation"][:] = r  # the same pose: success
        assert bool(task.metrics(sim.x, sim.params)["is_success"][0])
    finally:
        env.close()
