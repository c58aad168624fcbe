"""Ray RLlib on the RedSim envs (the optional extra ``pip install "redsim[ray]"``).

RLlib builds its envs on every env runner from a registered creator, never from Gymnasium's registry.
:func:`register` registers :func:`env_creator` under a name with ``ray.tune.registry.register_env``; the creator
lives in this importable module (not in a script), so runners on other machines unpickle it by reference: redsim
must be installed on every node. The creator's name, not a RedSim id, goes to ``PPOConfig().environment(...)``:
a bare ``"RedSim/..."`` id fails on the runners, which never import redsim (``NamespaceNotFound`` in their logs;
``"redsim:RedSim/..."`` makes Gymnasium import it, without the native vector env's seeds of :class:`RunnerSeeds`).
:func:`restore` restores an algorithm from a checkpoint, registering the creator under the checkpoint's name first
(the checkpoint names it, not the function; RLlib's ``from_checkpoint`` also leaves runners on their old weights);
:func:`checkpoint_config` reads a checkpoint's settings (its runners, its env) without a Ray cluster. With
``gym_env_vectorize_mode="vector_entry_point"`` a runner's ``num_envs_per_env_runner`` copies are redsim's native
vector env: one batched latent solve for all of them, seeded by :class:`RunnerSeeds`. With RLlib's default
(``"sync"``) the creator makes one env per copy and RLlib's ``SyncVectorEnv`` seeds copy i with the runner's seed
+ i; :class:`RunnerCopySeed` mixes in the runner's index (``env_config.worker_index``), so that neighbouring
runners do not replay each other's episodes there either.

RLlib drops every runner whose creator raises and then fails with an ``IndexError`` in ``get_spaces``, the
creator's own message only in the workers' logs: :func:`check_env_config` makes the env once in the driver,
so a bad id or keyword is a clear error there.

    >>> import ray
    >>> from ray.rllib.algorithms.ppo import PPOConfig
    >>> from redsim.trainers.rllib import check_env_config, register
    >>> ray.init()                                  # a local cluster; ray.init(address="auto") joins one
    >>> env_config = {"id": "RedSim/MiniChain-v0", "kwargs": {"max_episode_steps": 100}}
    >>> check_env_config(env_config, num_envs=8)     # as the runners build it (8 copies each, below)
    >>> config = PPOConfig().environment(register(), env_config=env_config)
    >>> vector = {"num_envs_per_env_runner": 8, "gym_env_vectorize_mode": "vector_entry_point"}
    >>> config = config.env_runners(num_env_runners=2, **vector)
    >>> algo = config.build_algo()
    >>> algo.train()["env_runners"]["episode_return_mean"]
"""

from __future__ import annotations

import importlib.util
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

DEFAULT_NAME = "redsim"
"""The name :func:`register` gives the creator (``PPOConfig().environment(DEFAULT_NAME, ...)``)."""
ENV_CONFIG_KEYS = ("id", "kwargs")
"""What an ``env_config`` holds: the env id and its keyword arguments (RLlib adds ``num_envs`` itself)."""
RESTORE_TIMEOUT = 60.0
"""Seconds :func:`restore` waits for the env runners to take the checkpoint's weights."""


def env_creator(env_config: Mapping[str, Any]) -> gym.Env | gym.vector.VectorEnv:
    """The env of an RLlib env runner: ``env_config["id"]`` made with ``env_config["kwargs"]``; where RLlib adds
    ``"num_envs"`` (``gym_env_vectorize_mode="vector_entry_point"``), the native vector env of that many copies,
    its seeds spread so that runners do not share episodes (:class:`RunnerSeeds`).

    Raises:
        ValueError: no ``"id"`` or not a RedSim id, ``"kwargs"`` not a dict, or a key other than
            :data:`ENV_CONFIG_KEYS` (an env keyword given beside ``"kwargs"`` instead of in it).
    """
    import redsim.envs

    unknown = sorted(set(env_config) - {*ENV_CONFIG_KEYS, "num_envs"})
    if unknown:
        raise ValueError(
            f"env_config has unknown key(s) {unknown}: it is {{'id': ENV_ID, 'kwargs': {{...}}}}, "
            "the env's keyword arguments go in 'kwargs'"
        )
    env_id = env_config.get("id")
    if env_id not in redsim.envs.ids():
        raise ValueError(f"env_config['id'] must be one of {', '.join(redsim.envs.ids())}, got {env_id!r}")
    kwargs = env_config.get("kwargs", {})
    if not isinstance(kwargs, Mapping):
        raise ValueError(f"env_config['kwargs'] must be a dict of the env's keyword arguments, got {kwargs!r:.80}")
    if "num_envs" in env_config:
        copies = int(env_config["num_envs"])
        return RunnerSeeds(gym.make_vec(env_id, num_envs=copies, vectorization_mode="vector_entry_point", **kwargs))
    env = gym.make(env_id, **kwargs)
    worker_index = getattr(env_config, "worker_index", None)  # an EnvContext: RLlib's runners make one per copy
    return env if worker_index is None else RunnerCopySeed(env, int(worker_index))


class RunnerSeeds(gym.vector.VectorWrapper):
    """A vector env whose reset with one seed s seeds copy i with ``b + i``, b a 32-bit number drawn from
    ``SeedSequence([s])``, not Gymnasium's ``s + i``.

    RLlib resets env runner w (``worker_index``, 1 for the first remote one) with ``config.seed + w``
    (``config.debugging(seed=...)``; evaluation runners 10^6 further up, Ray 2.60): with ``s + i``, copy i of runner
    w would replay copy i + 1 of runner w - 1, episode for episode, and the low seeds are ``eval-agent``'s episodes
    (0-19). A sequence of seeds, or None, passes through.
    """

    def reset(self, *, seed: Any = None, options: dict[str, Any] | None = None) -> Any:
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            base = int(np.random.SeedSequence([int(seed)]).generate_state(1)[0])
            seed = [base + i for i in range(self.num_envs)]
        return self.env.reset(seed=seed, options=options)


class RunnerCopySeed(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """One env copy of RLlib env runner ``worker_index`` in RLlib's own vector env (``gym_env_vectorize_mode``
    ``"sync"``, its default, or ``"async"``): a reset with one seed s seeds it with a 32-bit number drawn from
    ``SeedSequence([s, worker_index])``.

    RLlib resets the ``SyncVectorEnv`` of the runner with ``worker_index`` w (1 for the first remote one) with
    ``config.seed + w`` (Ray 2.60), which seeds copy i with ``config.seed + w + i``, and gives every copy the same
    ``EnvContext`` (``vector_index`` 0): alone, copy i of runner w would replay copy i + 1 of runner w - 1, episode
    for episode. A seed that is not an integer, or None, passes through.
    """

    def __init__(self, env: gym.Env, worker_index: int) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, worker_index=worker_index)
        gym.Wrapper.__init__(self, env)
        self.worker_index = worker_index

    def reset(self, *, seed: Any = None, options: dict[str, Any] | None = None) -> Any:
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            seed = int(np.random.SeedSequence([int(seed), self.worker_index]).generate_state(1)[0])
        return self.env.reset(seed=seed, options=options)


def check_env_config(env_config: Mapping[str, Any], num_envs: int | None = None) -> None:
    """Make (and close) the env of ``env_config`` here as a runner would, so that a bad one fails in the driver
    (module doc): ``num_envs`` copies in the native vector env (``gym_env_vectorize_mode="vector_entry_point"``,
    which passes every keyword to the env), or the single env (None).

    Raises:
        ValueError: what :func:`env_creator` or the env refuses (an unknown keyword is the env's TypeError, a bad
            ``max_episode_steps`` Gymnasium's AssertionError).
    """
    if not isinstance(env_config, Mapping):
        raise ValueError(f"env_config must be a dict {{'id': ENV_ID, 'kwargs': {{...}}}}, got {env_config!r:.80}")
    config = dict(env_config) if num_envs is None else {**env_config, "num_envs": int(num_envs)}
    try:
        env_creator(config).close()
    except (TypeError, AssertionError) as err:
        raise ValueError(f"env_config['kwargs'] {dict(env_config.get('kwargs', {}))}: {err}") from None


def register(name: str = DEFAULT_NAME) -> str:
    """Register :func:`env_creator` with Ray Tune under ``name``; returns ``name``.

    Raises:
        ImportError: Ray is not installed (``pip install "redsim[ray]"``).
    """
    _require_ray()
    from ray.tune.registry import register_env

    register_env(name, env_creator)
    return name


def _require_ray() -> None:
    """Raise an ImportError naming the extra where Ray is not installed (a bare "No module named 'ray'" does not)."""
    if importlib.util.find_spec("ray") is None:
        raise ImportError('Ray RLlib is not installed: pip install "redsim[ray]"')


def checkpoint_config(path: str | Path) -> dict[str, Any]:
    """The algorithm config an RLlib checkpoint (``algo.save_to_path(path)``) was saved with, as a dict
    (``num_env_runners``, ``env``, ``env_config``, ...), read from its ``class_and_ctor_args.pkl`` without a Ray
    cluster: how many CPUs its runners need before ``ray.init``, which env its policy acts in.

    Raises:
        ValueError: ``path`` is not an RLlib checkpoint (no ``rllib_checkpoint.json``).
    """
    import pickle

    path = Path(path)
    if not (path / "rllib_checkpoint.json").is_file():
        raise ValueError(f"{path} is not an RLlib checkpoint (no rllib_checkpoint.json)")
    with open(path / "class_and_ctor_args.pkl", "rb") as file:  # RLlib's own file, unpickled as from_checkpoint does
        config = pickle.load(file)["ctor_args_and_kwargs"][0][0]
    return dict(config) if isinstance(config, Mapping) else config.to_dict()


def _is_redsim(env_config: Mapping[str, Any]) -> bool:
    """Whether ``env_config`` names a RedSim id (the creator's config, not another env's)."""
    import redsim.envs

    return env_config.get("id") in redsim.envs.ids()


def restore(path: str | Path) -> Any:
    """``Algorithm.from_checkpoint(path)`` with every env runner holding the checkpoint's weights, :func:`env_creator`
    registered first under the checkpoint's env name where its ``env_config`` is the creator's (``id``, a RedSim id,
    and ``kwargs``; another env's checkpoint is left to its own registration).

    RLlib sends the restored weights to the remote runners without waiting, and a runner still busy with its build's
    own weights keeps those: the first restored iteration then sampled with the untrained policy on some runners
    (which ones changed from run to run). This waits for every runner.

    Raises:
        ImportError: Ray is not installed (``pip install "redsim[ray]"``).
        RuntimeError: a runner did not answer within :data:`RESTORE_TIMEOUT` seconds (the algorithm is stopped).
    """
    _require_ray()
    from ray.rllib.algorithms.algorithm import Algorithm

    config = checkpoint_config(path)
    env_config = config.get("env_config") or {}
    if isinstance(config.get("env"), str) and set(env_config) <= {*ENV_CONFIG_KEYS} and _is_redsim(env_config):
        register(config["env"])  # without it, RLlib's runners died on make_vec(..., id=...): an IndexError here
    algo = Algorithm.from_checkpoint(str(Path(path).resolve()))
    runners = algo.env_runner_group
    runners.sync_weights(
        from_worker_or_learner_group=algo.learner_group, inference_only=True, timeout_seconds=RESTORE_TIMEOUT
    )
    # sync_weights waits for the calls in flight, then sends the weights without waiting; a runner serves its calls
    # in order, so one answered call after them means each holds the checkpoint's weights
    answered = runners.foreach_env_runner(lambda runner: None, local_env_runner=False, timeout_seconds=RESTORE_TIMEOUT)
    if len(answered) < runners.num_healthy_remote_workers():
        algo.stop()
        raise RuntimeError(
            f"{runners.num_healthy_remote_workers() - len(answered)} env runner(s) did not take the checkpoint's "
            f"weights within {RESTORE_TIMEOUT:g} s"
        )
    return algo


__all__ = [
    "DEFAULT_NAME",
    "ENV_CONFIG_KEYS",
    "RunnerCopySeed",
    "RunnerSeeds",
    "check_env_config",
    "checkpoint_config",
    "env_creator",
    "register",
    "restore",
]
