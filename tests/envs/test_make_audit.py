"""``redsim.envs.make`` on a user's scene: what the hand mutation audit (helper-283) found no test holding.

- The reach task on a user's scene gets defaults (the first handle, a max force of half the scene's weight); options
  the user gives must replace them. With the defaults written after the user's options a given max_force was silently
  dropped and every test still passed (they only gave the one handle mini_chain has).
- ``max_episode_steps=0`` is refused (as make_vec refuses it); with the bound lowered to >= 0 make took it.
- An id registered with ``entry_point="redsim.envs:make"`` and no length anywhere keeps make's 200 steps (the
  docstring of :class:`redsim.envs.factory.EpisodeLimit`); with the registry's test inverted such an id's episodes
  never ended.
"""

from __future__ import annotations

import gymnasium as gym
import pytest

import redsim
from redsim.envs.factory import NO_LIMIT, EpisodeLimit, default_force


def test_a_given_max_force_replaces_the_default_one() -> None:
    scene = redsim.scenes.build("mini_chain")
    assert default_force(scene) != pytest.approx(2.5)
    env = redsim.envs.make(scene, task="reach", task_options={"max_force": 2.5}, max_episode_steps=5)
    try:
        assert env.unwrapped.task.max_force == pytest.approx(2.5)
    finally:
        env.close()
    env = redsim.envs.make(scene, task="reach", max_episode_steps=5)
    try:
        assert env.unwrapped.task.max_force == pytest.approx(default_force(scene))
    finally:
        env.close()


def test_an_episode_length_of_zero_is_refused() -> None:
    with pytest.raises(ValueError, match="max_episode_steps must be None or -1"):
        redsim.envs.make("mini_chain", max_episode_steps=0)


def _limit(env: gym.Env) -> int:
    """The episode length of the :class:`EpisodeLimit` in ``env``'s wrappers."""
    while not isinstance(env, EpisodeLimit):
        env = env.env
    return env._max_episode_steps


def test_an_id_registered_without_a_length_keeps_make_s_200_steps() -> None:
    own = "RedSimTest/NoLength-v0"
    gym.register(own, entry_point="redsim.envs:make", kwargs={"scene": "mini_chain"})
    try:
        env = gym.make(own)
        assert _limit(env) == 200 and env.spec.max_episode_steps == 200
        env.close()
        gym.registry[own].max_episode_steps = 7  # a length in the registry: Gymnasium's TimeLimit holds it
        env = gym.make(own)
        assert _limit(env) == NO_LIMIT and env.spec.max_episode_steps == 7
        env.close()
    finally:
        gym.registry.pop(own, None)
