"""Episodes of a vector env that end at different steps (a task ending at a step drawn per episode, one reward a
step): an evaluation's return counts each episode's own steps, and the pixel wrapper's same-step autoreset restarts
only the copies that ended (hand mutation audit, helper-281: adding every copy's reward on every step in
trainers/agents.py _run_episodes passed tests/trainers/test_agents.py -m 'not slow'; resetting every copy when one
ends in envs/pixels.py passed tests/envs/test_pixels.py, whose copies all end at their time limit together)."""

from __future__ import annotations

import numpy as np
import torch
from gymnasium.vector import AutoresetMode

import redsim
from redsim.envs.base import Task
from redsim.envs.pixels import PixelVectorObservation
from redsim.trainers.agents import evaluate, vector_env


class EndAtDrawnStep(Task):
    """One reward per step on the mini chain; the episode ends at a step drawn per episode (2 to 7)."""

    name = "end_at_drawn_step"
    action_size = 3
    reward_terms = ("step",)

    def bind(self, sim) -> None:
        self.shape = (len(sim.scene.handles), sim.scene.dim)

    def extras_bounds(self):
        return np.full(1, -100.0), np.full(1, 100.0)

    def observation_structure(self):
        return {"clock": 1}

    def sample(self, rng, sim, z_rest, cond):
        return {"limit": torch.tensor(int(rng.integers(2, 8))), "clock": torch.tensor(0)}

    def loads(self, action, params):
        params["clock"] += 1
        loads = torch.zeros(action.shape[0], *self.shape, dtype=action.dtype)
        loads[:, 0] = 5.0 * action
        return loads

    def extras(self, x, x_prev, params):
        return params["clock"].to(x.dtype)[:, None]

    def reward(self, x, action, params):
        step = torch.ones(x.shape[0], dtype=x.dtype)
        return step, {"step": step}

    def terminated(self, x, params):
        return params["clock"] >= params["limit"]

    def metrics(self, x, params):
        return {"is_success": params["clock"] % 2 == 0}  # every second step


def _env(**kwargs):
    return redsim.envs.make("mini_chain", task=EndAtDrawnStep(), max_episode_steps=20, **kwargs)


def test_each_episodes_return_counts_its_own_steps() -> None:
    result = evaluate(_env(), "random", episodes=4, seed=0)
    assert len(set(result.lengths.tolist())) > 1  # the episodes end at different steps
    np.testing.assert_array_equal(result.returns, result.lengths)
    # the fraction of each episode's own steps in success: steps 2, 4, ... of its 1..L
    np.testing.assert_allclose(result.success_steps, (result.lengths // 2) / result.lengths)
    np.testing.assert_array_equal(result.successes, result.lengths % 2 == 0)  # at its last step


def test_same_step_pixels_restart_only_the_copies_that_ended() -> None:
    pictures = {"render_mode": "rgb_array", "width": 32, "height": 32}
    same = PixelVectorObservation(vector_env(_env(**pictures), 3, AutoresetMode.DISABLED), autoreset_mode="SameStep")
    native = vector_env(_env(**pictures), 3, AutoresetMode.SAME_STEP)
    same.reset(seed=0)
    native.reset(seed=0)
    ends = np.zeros(3, dtype=int)
    for action in np.random.default_rng(0).uniform(-1, 1, (12, 3, 3)).astype(np.float32):
        obs, reward, terminated, truncated, _ = same.step(action)
        _, native_reward, native_terminated, native_truncated, _ = native.step(action)
        np.testing.assert_array_equal(terminated, native_terminated)
        np.testing.assert_array_equal(truncated, native_truncated)
        np.testing.assert_array_equal(reward, native_reward)
        np.testing.assert_array_equal(obs, np.stack(native.render()))
        ends += terminated
    assert len(set(ends.tolist())) > 1  # the copies' episodes ended at different steps
    same.close()
    native.close()
