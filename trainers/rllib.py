"""Ray RLlib on the RedSim envs (the optional extra ``pip install "redsim[ray]"``).

RLlib builds its envs on every env runner from a registered creator, never from Gymnasium's
registry. :func:`register` registers :func:`env_creator` under a name with
``ray.tune.registry.register_env``; the creator lives in this importable module (not in a script), so
runners on other machines unpickle it by reference: redsim must be installed on every node.

    >>> import ray
    >>> from ray.rllib.algorithms.ppo import PPOConfig
    >>> from redsim.trainers.rllib import register
    >>> ray.init()                                  # a local cluster; ray.init(address="auto") joins one
    >>> config = PPOConfig().environment(register(), env_config={"id": "RedSim/MiniChain-v0"})
    >>> algo = config.env_runners(num_env_runners=2).build_algo()
    >>> algo.train()["env_runners"]["episode_return_mean"]
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym

DEFAULT_NAME = "redsim"
"""The name :func:`register` gives the creator (``PPOConfig().environment(DEFAULT_NAME, ...)``)."""


def env_creator(env_config: Mapping[str, Any]) -> gym.Env:
    """One env for an RLlib env runner: ``env_config["id"]`` made with ``env_config["kwargs"]``.

    Raises:
        ValueError: no ``"id"``, or not a RedSim id.
    """
    import redsim.envs

    env_id = env_config.get("id")
    if env_id not in redsim.envs.ids():
        raise ValueError(f"env_config['id'] must be one of {', '.join(redsim.envs.ids())}, got {env_id!r}")
    return gym.make(env_id, **dict(env_config.get("kwargs", {})))


def register(name: str = DEFAULT_NAME) -> str:
    """Register :func:`env_creator` with Ray Tune under ``name``; returns ``name``.

    Raises:
        ImportError: Ray is not installed (``pip install "redsim[ray]"``).
    """
    try:
        from ray.tune.registry import register_env
    except ImportError as err:
        raise ImportError('Ray RLlib is not installed: pip install "redsim[ray]"') from err
    register_env(name, env_creator)
    return name


__all__ = ["DEFAULT_NAME", "env_creator", "register"]
