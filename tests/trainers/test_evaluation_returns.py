"""An evaluation's return counts each episode's own steps only, however long the others run, and training seeds move
on with the steps a run resumes at (hand mutation audit, helper-281: adding the reward of every copy on every step,
and a training seed of the run's seed alone, each passed tests/trainers/test_agents.py -m 'not slow')."""

from __future__ import annotations

import numpy as np
import torch

import redsim
from redsim.envs.base import Task
from redsim.trainers.agents import evaluate, training_seed


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


def test_each_episodes_return_counts_its_own_steps() -> None:
    env = redsim.envs.make("mini_chain", task=EndAtDrawnStep(), max_episode_steps=20)
    result = evaluate(env, "random", episodes=4, seed=0)
    assert len(set(result.lengths.tolist())) > 1  # the episodes end at different steps
    np.testing.assert_array_equal(result.returns, result.lengths)


def test_a_resumed_runs_training_seed_moves_on_with_its_steps() -> None:
    seeds = {training_seed(7, steps) for steps in (0, 1000, 2000, 5000)}
    assert len(seeds) == 4
    assert training_seed(7, 1000) == training_seed(7, 1000)
