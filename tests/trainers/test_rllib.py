"""The RLlib env creator (the one-iteration run on a local Ray cluster is examples/rllib_agent.py's test)."""

from __future__ import annotations

import importlib.util

import pytest

from redsim.trainers.rllib import env_creator, register


def test_env_creator_makes_the_id_with_its_kwargs() -> None:
    env = env_creator({"id": "RedSim/MiniChain-v0", "kwargs": {"max_episode_steps": 7}})
    assert env.spec.max_episode_steps == 7 and env.action_space.shape == (3,)
    env.close()
    with pytest.raises(ValueError, match="env_config\\['id'\\] must be one of RedSim/Chain-v0"):
        env_creator({"id": "CartPole-v1"})


@pytest.mark.skipif(importlib.util.find_spec("ray") is not None, reason="Ray is installed here")
def test_register_without_ray_names_the_extra() -> None:
    with pytest.raises(ImportError, match='pip install "redsim\\[ray\\]"'):
        register()
