"""Each episode of the simulated states draws its own loads (hand mutation audit, helper-281: every episode replaying
the first one's loads passed tests/baselines/test_baselines.py, whose seeded-and-finite check compares whole runs)."""

from __future__ import annotations

import torch

from redsim import scenes
from redsim.baselines import simulated_states


def test_episodes_differ_and_the_first_is_that_of_a_one_episode_run() -> None:
    bar = scenes.build("toy_tiny_bar_2d")
    steps = 20
    two = simulated_states(bar, steps=steps, dt=0.02, episodes=2, seed=0, load_scale=5.0)
    one = simulated_states(bar, steps=steps, dt=0.02, episodes=1, seed=0, load_scale=5.0)
    torch.testing.assert_close(two[:steps], one, rtol=0, atol=0)  # the loads are drawn episode by episode
    assert float((two[steps:] - two[:steps]).abs().max()) > 1e-3  # [m]: the second episode moves otherwise
