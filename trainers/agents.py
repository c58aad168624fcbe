"""Train and evaluate stable-baselines3 agents on the RedSim envs.

Training runs through the native vector env (:class:`redsim.envs.sb3.SB3VecEnv`: one batched
latent step for all copies), with hyperparameters per env and algorithm in one table
(:data:`HYPERPARAMS`, the rl-zoo layout), SB3's ``EvalCallback`` and ``CheckpointCallback``, a
progress bar, and resumable runs. :func:`train_agent` writes into its output folder:

- ``model.zip``: the final SB3 model (it records the env id and the algorithm it was trained with);
- ``model_vecnormalize.pkl``: the observation (and reward) normalization statistics of SB3's
  ``VecNormalize`` the policy acts through (settings with ``"normalize"``; :func:`load_agent` applies
  them, :func:`normalizer_path` names the file beside any model);
- ``best_model.zip`` (+ ``best_model_vecnormalize.pkl``): the best model by evaluation return (``EvalCallback``, each
  evaluation on the same seeded episodes; PPO's after an update, :func:`_evaluations`);
- ``replay_buffer.pkl`` (SAC, TD3): the replay buffer, so a resumed run goes on with it;
- ``checkpoints/``: periodic models and their statistics (PPO's as a rollout starts: only learnt rollouts). A resumed
  run goes on from whichever of ``model.zip`` and the checkpoints was trained the most env steps (``model.zip`` on
  a tie), from a checkpoint with an empty replay buffer;
- ``curve.csv`` and ``curve.png``: evaluation return vs env steps and vs wall time (a run's final evaluation, on
  other episodes than the periodic ones, is a row marked ``final`` and a separate point: :data:`CURVE_FIELDS`);
- ``evaluations.npz``: ``EvalCallback``'s log of every evaluation (steps, returns, episode lengths);
- ``progress.csv``: SB3's own training log (losses, learning rate, fps, ``eval/mean_reward``; a resumed run
  writes ``progress-from-STEPS.csv`` beside it), where SB3 alone would make an empty ``/tmp/SB3-*`` folder;
- ``policy.gif``: one episode of the trained policy;
- ``agent.json``: what ran (env, algorithm, steps, wall time, hyperparameters, last evaluation).

``her=True`` (SAC, TD3; the reach envs) trains with hindsight experience replay: on the goal-conditioned
env (:class:`redsim.envs.goal.GoalVectorObservation`, dict observations, the reward of the goals alone) with
SB3's ``HerReplayBuffer``. The evaluations still score the env's own reward, and the saved model acts on the
env's flat observations (:class:`Agent` splits them into goals), so it is evaluated, compared and drawn as
any other.

:func:`evaluate` runs seeded episodes of a trained model, a random policy or the task's
scripted controller (:meth:`redsim.envs.base.Task.controller`) the same way, one episode per
copy of a vector env whose copy i is seeded ``seed + i`` (equal to single envs seeded alike).
An episode succeeds when ``info["is_success"]`` holds at its last step.
"""

from __future__ import annotations

import copy
import csv
import inspect
import json
import logging
import os
import pickle
import re
import shutil
import time
import warnings
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from redsim.subspace import map_fingerprint, write_atomically

log = logging.getLogger(__name__)

BUFFER = "replay_buffer.pkl"
"""The off-policy replay buffer beside ``model.zip`` (a resumed run goes on with it)."""
NORMALIZER = "_vecnormalize.pkl"
"""Suffix of the ``VecNormalize`` statistics beside a model (``model.zip`` -> ``model_vecnormalize.pkl``)."""
ALGOS = ("ppo", "sac", "td3")
"""The stable-baselines3 algorithms the table covers."""
FINAL_EVAL_SEED = 20_000
"""The first reset seed of a run's final evaluation past its own seed (``seed + FINAL_EVAL_SEED + i``): seeds no
training copy starts from (:func:`training_seed`; SB3's own envs start at 0, 1, ...)."""

_OFF_POLICY = {
    "learning_starts": 1000,
    "buffer_size": 200_000,
    "batch_size": 256,
    "train_freq": 1,
    "normalize": {"norm_obs": True, "norm_reward": False},
}

_PPO_WIDE = {
    "n_envs": 64,
    "n_steps": 64,
    "batch_size": 512,
    "gamma": 0.99,
    "policy_kwargs": {"net_arch": [64, 64], "log_std_init": 0.0},
}
"""PPO over many copies with a wide initial exploration (std e^0 = 1 of the unit action): what learnt BistableBar-v1."""

_CONDITIONAL_BAR = {
    "sac": {"n_envs": 16, "gradient_steps": 8},
    "td3": {"n_envs": 16, "gradient_steps": 8},
    "ppo": _PPO_WIDE,
}
"""ConditionalBar-v0 and v1 (v0 on its cubature): TD3 is what beat the scripted controller (below)."""

HYPERPARAMS: dict[str, dict[str, dict[str, Any]]] = {
    "default": {
        "sac": {
            "n_envs": 8,
            **_OFF_POLICY,
            "learning_rate": 1e-3,
            "gamma": 0.98,
            "tau": 0.02,
            "gradient_steps": 2,
            "policy_kwargs": {"net_arch": [64, 64]},
        },
        "td3": {
            "n_envs": 8,
            **_OFF_POLICY,
            "learning_rate": 1e-3,
            "gamma": 0.98,
            "gradient_steps": 2,
            "action_noise_std": 0.2,
            "policy_kwargs": {"net_arch": [64, 64]},
        },
        "ppo": {
            "normalize": {"norm_obs": True, "norm_reward": True},
            "n_envs": 16,
            "n_steps": 128,
            "batch_size": 256,
            "n_epochs": 10,
            "learning_rate": 3e-4,
            "gamma": 0.98,
            "gae_lambda": 0.95,
            "policy_kwargs": {"net_arch": [64, 64], "log_std_init": -0.5},
        },
    },
    "RedSim/MiniChain-v0": {"sac": {"n_envs": 16, "gradient_steps": 8}},
    "RedSim/Chain-v0": {"sac": {"n_envs": 16, "gradient_steps": 8}},
    "RedSim/ClothBall-v0": {"sac": {"n_envs": 16, "gradient_steps": 8}},
    "RedSim/ClothBall-v1": {"sac": {"n_envs": 16, "gradient_steps": 8}},
    "RedSim/HangingCloth-v0": {"sac": {"n_envs": 16, "gradient_steps": 8}},
    "RedSim/HangingCloth-v1": {"ppo": _PPO_WIDE},
    "RedSim/HangingCloth-v2": {"ppo": _PPO_WIDE},
    "RedSim/ConditionalBar-v0": _CONDITIONAL_BAR,
    "RedSim/ConditionalBar-v1": _CONDITIONAL_BAR,
    "RedSim/Klann-v0": {"sac": {"n_envs": 16, "gradient_steps": 8}},
    "RedSim/Stewart-v0": {"sac": {"n_envs": 16, "gradient_steps": 8}},
    "RedSim/BistableBar-v0": {"sac": {"n_envs": 16, "gradient_steps": 8}},
    "RedSim/BistableBar-v1": {
        "sac": {"n_envs": 16, "gradient_steps": 8, "gamma": 0.99},
        "ppo": _PPO_WIDE,
    },
}
"""env id -> algorithm -> settings; each env's entries override ``"default"`` key by key.

``n_envs`` is the number of copies of the vector env; ``learning_starts`` (SAC, TD3) holds unless it is more than
half a run's steps, then half (unless given as an override); ``action_noise_std`` (TD3) the std of
Gaussian exploration noise in units of the action bound; ``normalize`` the keyword arguments of
SB3's ``VecNormalize`` around the training env (running mean/std of the observations, and for PPO
of the returns; false: raw observations); every other key is a keyword argument of the SB3 algorithm.

Normalization is what made the reach tasks learnable: their raw observations mix latent velocities
of std ~7 1/s with target offsets of std ~0.04 m (MiniChain), and SAC without it stayed below the
scripted controller after 45k steps; with it, 12k steps beat it (docs/agents.md). ConditionalBar-v0
ships TD3: some of its targets need the full force, where SAC (tanh-squashed actions, an entropy term)
tied the scripted controller and deterministic TD3 beat it.
"""


def hyperparams(env_id: str | None, algo: str) -> dict[str, Any]:
    """The settings of ``algo`` on ``env_id`` (None: a user's env; the defaults).

    Raises:
        ValueError: an unknown algorithm.
    """
    if algo not in ALGOS:
        raise ValueError(f"unknown algorithm {algo!r}; valid: {', '.join(ALGOS)}")
    settings = copy.deepcopy(HYPERPARAMS["default"][algo])
    settings.update(copy.deepcopy(HYPERPARAMS.get(env_id or "", {}).get(algo, {})))
    return settings


def check_env_id(env_id: str) -> None:
    """Raise ValueError naming the valid ids when ``env_id`` is not a RedSim id."""
    import redsim.envs

    if env_id not in redsim.envs.ids():
        raise ValueError(f"unknown env {env_id!r}; valid: {', '.join(redsim.envs.ids())}")


def _algo_class(algo: str) -> Any:
    from stable_baselines3 import PPO, SAC, TD3

    return {"ppo": PPO, "sac": SAC, "td3": TD3}[algo]


KEPT_WRAPPERS = ("TimeLimit", "EpisodeLimit", "OrderEnforcing", "PassiveEnvChecker")
"""Wrappers of a user's env that its vectorized copies stand in for (``gym.make``'s, and :func:`redsim.envs.make`'s
:class:`redsim.envs.factory.EpisodeLimit`): the limit of a TimeLimit is kept; any other wrapper would not act on the
copies and is refused."""


def _base_env(env: gym.Env) -> tuple[Any, int | None]:
    """The :class:`LatentEnv` under ``env`` and its episode limit (the ``TimeLimit``'s, if any).

    Raises:
        ValueError: a wrapper other than :data:`KEPT_WRAPPERS` (the copies are made from the bare env).
    """
    from redsim.envs.factory import NO_LIMIT

    limits = [env.spec.max_episode_steps] if env.spec is not None and env.spec.max_episode_steps is not None else []
    inner: Any = env
    while isinstance(inner, gym.Wrapper):
        if type(inner).__name__ not in KEPT_WRAPPERS:
            raise ValueError(
                f"the env is wrapped in {type(inner).__name__}, which its vectorized copies would not have: pass the "
                "env without it (a TimeLimit's length is kept; normalized observations are train_agent's setting "
                "overrides={'normalize': {...}}, and an Agent trained so normalizes its observations itself)"
            )
        limits.append(getattr(inner, "_max_episode_steps", NO_LIMIT))
        inner = inner.env
    limit = min(limits, default=NO_LIMIT)  # the first TimeLimit to end an episode ends it
    return inner, None if limit == NO_LIMIT else limit


def vector_env(
    env: str | gym.Env,
    num_envs: int,
    autoreset_mode: Any = None,
    env_kwargs: Mapping[str, Any] | None = None,
    shards: int = 1,
) -> Any:
    """A :class:`LatentVectorEnv` of ``num_envs`` copies of an id (made with ``env_kwargs``) or of a user's env;
    with ``shards`` P > 1 (ids only), a :class:`redsim.envs.sharded.ShardedVectorEnv` of them in P processes."""
    from gymnasium.vector import AutoresetMode

    from redsim.envs.vector import LatentVectorEnv

    mode = AutoresetMode.NEXT_STEP if autoreset_mode is None else autoreset_mode
    if isinstance(env, str):
        check_env_id(env)
        sharding = {"shards": shards} if shards != 1 else {}
        return gym.make_vec(
            env,
            num_envs=num_envs,
            vectorization_mode="vector_entry_point",
            autoreset_mode=mode,
            **sharding,
            **dict(env_kwargs or {}),
        )
    if shards != 1:
        raise ValueError("shards > 1 needs a registered env id (a worker process builds its copies from it)")
    base, limit = _base_env(env)
    return LatentVectorEnv(base, num_envs, max_episode_steps=limit, autoreset_mode=mode)


def _sb3_env(
    env: str | gym.Env,
    num_envs: int,
    seed: int,
    env_kwargs: Mapping[str, Any] | None,
    shards: int = 1,
    goal: Mapping[str, Any] | None = None,
) -> Any:
    """SB3's VecEnv of ``num_envs`` copies (with Monitor's episode statistics); ``goal``: goal-conditioned, with these
    :class:`redsim.envs.goal.GoalVectorObservation` arguments.

    Raises:
        ValueError: ``goal`` with an env that is not a reach env, or with ``shards`` > 1.
    """
    from gymnasium.vector import AutoresetMode

    from redsim.envs.goal import GoalVectorObservation
    from redsim.envs.sb3 import SB3VecEnv

    vector = vector_env(env, num_envs, AutoresetMode.SAME_STEP, env_kwargs, shards)
    if goal is not None:
        try:
            vector = GoalVectorObservation(vector, **goal)
        except TypeError as err:
            vector.close()
            raise ValueError(f"her: {err}") from err
    venv = SB3VecEnv(vector)  # its infos carry Monitor's episode statistics
    venv.seed(seed)
    return venv


def _check_reach(env: str | gym.Env) -> None:
    """Refuse ``her`` on an env whose task is not a reach (checked again, on the built env, by the goal wrapper).

    Raises:
        ValueError: another task, or an id whose entry point is not a :class:`redsim.envs.reach.ReachEnv`.
    """
    from gymnasium.envs.registration import load_env_creator

    from redsim.envs.reach import HandleReach, ReachEnv

    if isinstance(env, str):
        entry = gym.spec(env).entry_point
        creator = load_env_creator(entry) if isinstance(entry, str) else entry
        reach = isinstance(creator, type) and issubclass(creator, ReachEnv)
    else:
        reach = isinstance(_base_env(env)[0].task, HandleReach)
    if not reach:
        raise ValueError(
            f"her needs a reach env (MiniChain, Chain, ClothBall, HangingCloth, ConditionalBar, or one made with "
            f'task="reach"): {_env_label(env)} has no goal to relabel'
        )


def _episode_steps(env: str | gym.Env, env_kwargs: Mapping[str, Any] | None) -> int | None:
    """The episode limit of an id made with ``env_kwargs`` (whose ``max_episode_steps`` None is the id's own and -1
    none, as ``gym.make`` and the vector entry points read it) or of a user's env; None: no limit."""
    if isinstance(env, str):
        steps = dict(env_kwargs or {}).get("max_episode_steps")
        if steps is None:
            return gym.spec(env).max_episode_steps
        return None if steps == -1 else steps
    return _base_env(env)[1]


def _env_defaults(env: str | gym.Env) -> dict[str, Any]:
    """The keyword arguments an id's env is made with where none is given, as a model file records them (JSON): its
    entry point's defaults, the id's registered kwargs and its ``max_episode_steps``; {} for a user's env. A class's
    defaults include those of its base classes that its ``**kwargs`` reach (LatentEnv's ``dtype``, ``device``),
    except where the class replaces one by a class attribute of that name (ConditionalBar's
    ``randomize_condition``): that default is not known here."""
    from gymnasium.envs.registration import load_env_creator

    if not isinstance(env, str):
        return {}
    spec = gym.spec(env)
    creator = load_env_creator(spec.entry_point) if isinstance(spec.entry_point, str) else spec.entry_point

    def own_defaults(function: Any) -> dict[str, Any]:
        parameters = inspect.signature(function).parameters.values()
        return {p.name: p.default for p in parameters if p.default is not inspect.Parameter.empty}

    defaults = own_defaults(creator)
    if inspect.isclass(creator):
        for base in creator.__mro__[1:]:
            if "__init__" in vars(base):
                inherited = own_defaults(base.__init__).items()
                defaults = {k: v for k, v in inherited if not hasattr(creator, k)} | defaults  # the subclass's win
    defaults.update(spec.kwargs, max_episode_steps=spec.max_episode_steps)
    return json.loads(json.dumps(defaults, default=str))


def _env_label(env: str | gym.Env) -> str:
    if isinstance(env, str):
        return env
    return f"custom:{_base_env(env)[0].sim.scene.name}"


def _label_scene(label: str) -> str | None:
    """The scene name behind an env label of :func:`_env_label` (None: an id whose env class names none)."""
    if label.startswith("custom:"):
        return label.removeprefix("custom:")
    from gymnasium.envs.registration import load_env_creator

    try:
        creator = load_env_creator(gym.spec(label).entry_point)
    except gym.error.Error:  # an id not registered here (recorded by another version of redsim)
        return None
    return getattr(creator, "scene_name", None)


def _warn_if_other_env(trained_on: str | None, env: str | gym.Env) -> None:
    """Warn where a model recorded as trained on ``trained_on`` (an :func:`_env_label`) is run on another env: its
    spaces may match (HangingCloth-v1 and v2, a user's scene and a shipped one of the same sizes) while its task does
    not. A user's env of a registered id's scene counts as that id (training on it records ``custom:SCENE``)."""
    label = _env_label(env)
    if trained_on is None or trained_on == label:
        return
    if "custom:" in (trained_on[:7], label[:7]) and _label_scene(trained_on) == _label_scene(label):
        return
    warnings.warn(
        f"this model was trained on {trained_on}, and is evaluated on {label} (load_agent(path, env_id=...) refuses "
        "another env; eval-agent does too)",
        UserWarning,
        stacklevel=3,
    )


def _map_of(vector: Any) -> str | None:
    """The fingerprint (:func:`redsim.subspace.map_fingerprint`) of the subspace map a vector env of redsim steps in
    (through Gymnasium's vector wrappers); None where it has none to reach (a sharded env's lives in its workers)."""
    sim = getattr(getattr(vector, "unwrapped", vector), "sim", None)
    subspace = getattr(sim, "subspace", None)
    return None if subspace is None else map_fingerprint(subspace)


def _warn_if_other_map(trained_on: str | None, venv: Any) -> None:
    """Warn where a model recorded as trained in the map ``trained_on`` (its fingerprint) is run in another: the
    observations keep their shapes, but are another map's latent coordinates (a checkpoint refitted in place, a
    user-cache fit of other options)."""
    now = _map_of(venv)
    if trained_on is None or now is None or trained_on == now:
        return
    warnings.warn(
        f"this model was trained in the subspace map {trained_on}, and is evaluated in {now}: its observations are "
        "another map's latent coordinates, which mean other states than those the policy learnt on",
        UserWarning,
        stacklevel=3,
    )


# -- evaluation -------------------------------------------------------------------------------
@dataclass(frozen=True)
class Evaluation:
    """Returns of seeded episodes, one per seed ``seed .. seed + episodes - 1``.

    Attributes:
        policy: What acted ("agent", "random", "scripted").
        returns: Undiscounted return of each episode, shape [episodes].
        successes: ``info["is_success"]`` at each episode's last step (the task's test: within the success radius
            for the reach tasks, Klann's speed window held), shape [episodes].
        lengths: Steps of each episode, shape [episodes].
        success_steps: Fraction of each episode's steps that met the success test, shape [episodes]
            (what a tracking task, Klann's crank speed, is judged by along the way).
        seed: The first seed.
        saturated_steps: Fraction of each episode's steps with some action component at its bound
            (|a| >= 0.999), shape [episodes].
        final_distance: ``info["distance"]`` at each episode's last step [m] (the reach tasks, Stewart),
            shape [episodes]; None where the env reports no distance.
        sampled: The policy's actions were sampled (``evaluate(deterministic=False)``), not its deterministic ones.
        diverged: ``info["diverged"]`` at each episode's last step: the stepper could not make a step of it finite
            and the episode ended there (``terminated``), its return over fewer steps, shape [episodes]; None where
            the env reports no such flag.
    """

    policy: str
    returns: np.ndarray
    successes: np.ndarray
    lengths: np.ndarray
    seed: int
    success_steps: np.ndarray
    saturated_steps: np.ndarray
    final_distance: np.ndarray | None = None
    sampled: bool = False
    diverged: np.ndarray | None = None

    @property
    def mean(self) -> float:
        """Mean return over the episodes."""
        return float(np.mean(self.returns))

    @property
    def std(self) -> float:
        """Standard deviation of the returns (population, ddof 0)."""
        return float(np.std(self.returns))

    @property
    def success_rate(self) -> float:
        """Fraction of the episodes that ended in success."""
        return float(np.mean(self.successes))

    def above(self, other: Evaluation) -> tuple[float, int]:
        """How clearly these returns lie above ``other``'s on the same episodes (same seed and count).

        Returns:
            The p-value of a paired one-sided t-test (mean of self - other > 0) and the number of episodes
            in which self returned more. The p-value is NaN for a single episode (no spread to test against),
            and 0 or 1 where every episode differs by the same amount (above or below).

        Raises:
            ValueError: ``other`` ran other episodes.
        """
        from scipy import stats

        if other.seed != self.seed or len(other.returns) != len(self.returns):
            raise ValueError(
                f"a paired comparison needs the same episodes: seeds {self.seed} and {other.seed}, "
                f"{len(self.returns)} and {len(other.returns)} episodes"
            )
        if np.array_equal(self.returns, other.returns):
            return 1.0, 0
        better = int(np.sum(self.returns > other.returns))
        difference = self.returns - other.returns
        if len(difference) < 2:  # scipy would warn (divide by zero) and answer NaN
            return float("nan"), better
        if np.all(difference == difference[0]):  # no spread: t is +-inf (scipy warns of precision loss)
            return (0.0 if difference[0] > 0 else 1.0), better
        p_value = float(stats.ttest_rel(self.returns, other.returns, alternative="greater").pvalue)
        return p_value, better

    def as_dict(self) -> dict[str, Any]:
        """JSON-able summary (what ``eval-agent --json`` prints): the means, the rates and the per-episode lists."""
        return {
            "policy": self.policy,
            "episodes": len(self.returns),
            "seed": self.seed,
            "sampled": self.sampled,
            "mean_return": self.mean,
            "std_return": self.std,
            "success_rate": self.success_rate,
            "mean_length": float(np.mean(self.lengths)),
            "success_steps": float(np.mean(self.success_steps)),
            "returns": [float(r) for r in self.returns],
            "successes": [bool(h) for h in self.successes],
            "saturated_steps": [float(f) for f in self.saturated_steps],
            **({} if self.final_distance is None else {"final_distance": [float(d) for d in self.final_distance]}),
            **({} if self.diverged is None else {"diverged_episodes": int(np.sum(self.diverged))}),
            **({} if self.diverged is None else {"diverged": [bool(f) for f in self.diverged]}),
        }


class SpaceMismatchError(ValueError):
    """A model that acts on observations or actions of other shapes than the env's."""


def _check_spaces(policy: Any, venv: Any) -> None:
    """Refuse a model that acts on other observations or actions than ``venv``'s (an SB3 model would raise deep
    inside its network, or broadcast)."""
    model = getattr(policy, "model", policy)
    if getattr(policy, "goal", None) is not None:  # acts on the flat observations split into its dict (Agent)
        return
    spaces = (("observation", venv.single_observation_space), ("action", venv.single_action_space))
    for name, space in spaces:
        own = getattr(model, f"{name}_space", None)
        if isinstance(own, gym.spaces.Dict) and not isinstance(space, gym.spaces.Dict):
            raise SpaceMismatchError(
                f"the model acts on dict observations ({', '.join(own.spaces)}), the env gives an array of shape "
                f"{space.shape}: a goal-conditioned model (HER) not trained by redsim (train-agent --her records "
                "its goal split), or one of another env?"
            )
        if own is not None and own.shape != space.shape:
            raise SpaceMismatchError(
                f"the model's {name} space has shape {own.shape}, the env's {space.shape}: a model of another env?"
            )


def evaluate(
    env: str | gym.Env,
    policy: Any = "scripted",
    *,
    episodes: int = 20,
    seed: int = 0,
    deterministic: bool = True,
    env_kwargs: Mapping[str, Any] | None = None,
) -> Evaluation:
    """Run ``episodes`` seeded episodes at once (one per copy of a vector env) and collect their returns.

    Args:
        env: A registered id or a user's env (from :func:`redsim.envs.make`).
        policy: An :class:`Agent` or SB3 model (anything with ``predict(obs, deterministic=...)``),
            ``"random"`` (uniform actions drawn from ``seed``) or ``"scripted"`` (the task's controller).
        episodes: Number of episodes (copies).
        seed: Copy i resets with seed ``seed + i``.
        deterministic: Passed to the model's ``predict``. False samples the policy's actions (SB3's stochastic
            ``predict``; TD3's actor has no distribution and acts alike either way) from torch's generator seeded
            with ``seed`` inside the call (the caller's generator state is kept), so a sampled evaluation repeats.
        env_kwargs: Keyword arguments of the id's env (e.g. ``max_episode_steps``).

    Raises:
        ValueError: an unknown id or policy name, or fewer than one episode.
        SpaceMismatchError: a model whose observation or action space has another shape than the env's.
    """
    if int(episodes) != episodes or episodes < 1:
        raise ValueError(f"episodes must be an integer >= 1, got {episodes!r}")
    if isinstance(policy, str) and policy not in ("random", "scripted"):
        raise ValueError(f"policy must be a model, 'random' or 'scripted', got {policy!r}")
    venv = vector_env(env, int(episodes), env_kwargs=env_kwargs)
    try:
        if not isinstance(policy, str):
            _check_spaces(policy, venv)
            _warn_if_other_env(getattr(policy, "env_id", None), env)
            _warn_if_other_map(getattr(policy, "map", None), venv)
        if venv.max_episode_steps is None:
            raise ValueError("evaluation needs an env with an episode limit (max_episode_steps)")
    except ValueError:
        venv.close()  # a sharded env's workers too
        raise
    rngs = [np.random.default_rng([seed, i]) for i in range(venv.num_envs)]  # episode i's actions, whatever the count
    cuda = list(range(torch.cuda.device_count())) if torch.cuda.is_available() else []
    with torch.random.fork_rng(devices=cuda):  # a sampling policy draws from torch's generators: seeded, then restored
        torch.manual_seed(seed)  # (the CUDA ones too: a policy on the GPU samples there)
        return _run_episodes(venv, policy, seed, deterministic, rngs)


def _run_episodes(
    venv: Any, policy: Any, seed: int, deterministic: bool, rngs: list[np.random.Generator]
) -> Evaluation:
    """The episodes of :func:`evaluate` on its vector env ``venv`` (closed at the end), one per copy."""
    obs, _ = venv.reset(seed=seed)
    returns = np.zeros(venv.num_envs)
    lengths = np.zeros(venv.num_envs, dtype=np.int64)
    successes = np.zeros(venv.num_envs, dtype=bool)
    success_steps = np.zeros(venv.num_envs)
    saturated = np.zeros(venv.num_envs)
    distance = diverged = None
    running = np.ones(venv.num_envs, dtype=bool)
    while running.any():
        if policy == "random":
            action = np.stack([g.uniform(-1.0, 1.0, venv.single_action_space.shape) for g in rngs]).astype(np.float32)
        elif policy == "scripted":
            action = np.asarray(venv.sim.task.controller(venv.sim), dtype=np.float32)
        else:
            action = policy.predict(obs, deterministic=deterministic)[0]
        obs, reward, terminated, truncated, info = venv.step(action)
        returns[running] += reward[running]
        saturated[running] += (np.abs(action) >= 0.999).any(axis=1)[running]
        lengths[running] += 1
        done = running & (terminated | truncated)
        if "is_success" in info:
            hit = np.asarray(info["is_success"], dtype=bool)
            successes[done] = hit[done]
            success_steps[running] += hit[running]
        if "distance" in info:
            distance = np.full(venv.num_envs, np.nan) if distance is None else distance
            distance[done] = np.asarray(info["distance"], dtype=float)[done]
        if "diverged" in info:
            diverged = np.zeros(venv.num_envs, dtype=bool) if diverged is None else diverged
            diverged[done] = np.asarray(info["diverged"], dtype=bool)[done]
        running &= ~done
    venv.close()
    name = policy if isinstance(policy, str) else "agent"
    steps = dict(success_steps=success_steps / lengths, saturated_steps=saturated / lengths)
    sampled = not deterministic and not isinstance(policy, str)
    return Evaluation(
        name,
        returns,
        successes,
        lengths,
        int(seed),
        **steps,
        final_distance=distance,
        sampled=sampled,
        diverged=diverged,
    )


# -- model files ------------------------------------------------------------------------------
def _zip_path(path: str | Path) -> Path:
    """``path``, or ``path`` + ``.zip`` where only that file exists: SB3's ``save("NAME")`` writes ``NAME.zip``, and
    its ``load("NAME")`` reads it, so a model is named as SB3 users name it."""
    path = Path(path)
    zipped = path.with_name(path.name + ".zip")
    return zipped if not path.exists() and path.suffix != ".zip" and zipped.is_file() else path


def model_record(path: str | Path, plain_algo: str | None = None) -> dict[str, Any]:
    """The env id and algorithm a model file of :func:`train_agent` was trained with, whether it acts
    through normalized observations, the observation blocks of a goal-conditioned (HER) model (else None), and
    the copies it was trained on, the env's keyword arguments and the fingerprint of its subspace map (``"env_id"``,
    ``"algo"``, ``"normalized"``, ``"goal"``, ``"n_envs"``, ``"env_kwargs"``, ``"map"``: None for a model that does
    not record them).

    ``plain_algo`` (one of :data:`ALGOS`) also takes an SB3 model that redsim did not write (an example's, your own
    script's): its record is that algorithm, env id None, and normalized where the statistics file beside it
    (:func:`normalizer_path`) exists.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not an SB3 model, not one written by :func:`train_agent` (without ``plain_algo``),
            or one written with another algorithm than ``plain_algo``.
    """
    from stable_baselines3.common.save_util import load_from_zip_file

    path = _zip_path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no model file {path}")
    try:
        data, _, _ = load_from_zip_file(path, load_data=True, device="cpu")
    except Exception as err:  # SB3 raises whatever zipfile/json raise on a bad archive
        raise ValueError(f"{path} is not a stable-baselines3 model file: {err}") from err
    if plain_algo is not None and plain_algo not in ALGOS:
        raise ValueError(f"algo must be one of {', '.join(ALGOS)}, got {plain_algo!r}")
    if data is None:  # SB3 reads an archive without its "data" member as no data, without raising
        raise ValueError(f"{path} is not a stable-baselines3 model file: it has no 'data' member")
    if "redsim_env_id" not in data or data.get("redsim_algo") not in ALGOS:
        if plain_algo is None:
            raise ValueError(
                f"{path} is an SB3 model, but not one trained by redsim (no env id recorded): name its algorithm "
                "(eval-agent --algo, load_agent(..., algo=)) to load it as a plain SB3 model"
            )
        if getattr(data.get("replay_buffer_class"), "__name__", "") == "HerReplayBuffer":
            raise ValueError(
                f"{path} is an SB3 model trained with HER on dict observations redsim does not know: only "
                "`redsim train-agent --her` models record how to split the env's flat observations"
            )
        normalized = normalizer_path(path).is_file()
        return {
            "env_id": None,
            "algo": plain_algo,
            "normalized": normalized,
            "goal": None,
            "n_envs": None,
            "env_kwargs": None,
            "map": None,
        }
    if plain_algo is not None and plain_algo != data["redsim_algo"]:
        raise ValueError(f"{path} was trained with {data['redsim_algo']}, not {plain_algo}")
    return {
        "env_id": data["redsim_env_id"],
        "algo": data["redsim_algo"],
        "normalized": bool(data.get("redsim_normalized", False)),
        "goal": data.get("redsim_goal"),
        "n_envs": data.get("n_envs"),
        "env_kwargs": data.get("redsim_env_kwargs"),
        "map": data.get("redsim_map"),
    }


def normalizer_path(model_path: str | Path) -> Path:
    """The ``VecNormalize`` statistics file beside a model file.

    ``NAME.zip`` -> ``NAME_vecnormalize.pkl``; SB3's checkpoint ``rl_model_N_steps.zip`` ->
    ``rl_model_vecnormalize_N_steps.pkl`` (``CheckpointCallback``'s name).
    """
    path = Path(model_path)
    match = re.fullmatch(r"(.+)_(\d+_steps)", path.stem)
    if match is not None:
        return path.with_name(f"{match[1]}_vecnormalize_{match[2]}.pkl")
    return path.with_name(path.stem + NORMALIZER)


def load_normalizer(path: str | Path) -> Any:
    """A ``VecNormalize`` saved by SB3 (no env attached: only :meth:`normalize_obs` is used), frozen.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file holds something else.
    """
    from stable_baselines3.common.vec_env import VecNormalize

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no normalization statistics {path}")
    with path.open("rb") as handle:
        try:
            normalizer = pickle.load(handle)
        except Exception as err:  # whatever unpickling a damaged file raises
            raise ValueError(f"{path} is not a VecNormalize file: {err}") from err
    if not isinstance(normalizer, VecNormalize):
        raise ValueError(f"{path} is not a VecNormalize file (holds a {type(normalizer).__name__})")
    normalizer.training = False
    return normalizer


@dataclass(frozen=True)
class Agent:
    """A trained SB3 model and the observation normalization it acts through.

    Attributes:
        model: The SB3 model (PPO, SAC or TD3).
        normalizer: The ``VecNormalize`` whose statistics map raw observations to the model's
            inputs (None: the model takes raw observations).
        goal: A goal-conditioned (HER) model's observation blocks: the flat observations it is given are split
            into its dict observation first (:class:`redsim.envs.goal.GoalSplit`); None: the model takes them flat.
        env_id: The env the model records it was trained on (an id, or ``custom:SCENE`` for a user's env; None:
            not recorded): :func:`evaluate` warns on another.
        map: The fingerprint of the subspace map it was trained in (:func:`redsim.subspace.map_fingerprint`; None:
            not recorded, as by the shipped policies): :func:`evaluate` warns on another.
    """

    model: Any
    normalizer: Any = None
    goal: Mapping[str, int] | None = None
    env_id: str | None = None
    map: str | None = None

    @property
    def num_timesteps(self) -> int:
        return int(self.model.num_timesteps)

    def predict(
        self,
        obs: np.ndarray,
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, Any]:
        """Actions [B, A] (or [A]) for raw observations [B, obs] (or [obs]), as SB3's ``predict`` (its signature, so
        that SB3's ``evaluate_policy`` takes an agent; ``state`` and ``episode_start`` are passed on), but
        deterministic by default.

        Raises:
            ValueError: a goal-conditioned model given observations of another size.
        """
        if self.goal is not None:
            from redsim.envs.goal import GoalSplit

            size = sum(self.goal.values())
            if np.shape(obs)[-1] != size:  # the split would cut any width into the right shapes
                raise ValueError(
                    f"the model acts on observations of size {size} ({', '.join(self.goal)}), got {np.shape(obs)}"
                )
            obs = GoalSplit(self.goal)(obs)
        if self.normalizer is not None:
            obs = self.normalizer.normalize_obs(obs)
        return self.model.predict(obs, state, episode_start, deterministic)


def load_agent(path: str | Path, env_id: str | None = None, algo: str | None = None) -> Agent:
    """Load a model of :func:`train_agent` and its normalization statistics (:func:`normalizer_path`).

    With ``env_id``, refuse a model trained on another env. ``algo`` ("ppo", "sac", "td3") also loads a plain SB3
    model that does not record its env (an example's), acting through the ``VecNormalize`` statistics beside it
    where that file exists; :func:`evaluate` then checks its spaces against the env's. ``path`` may leave out
    ``.zip``, as SB3's ``load`` does.

    Raises:
        FileNotFoundError: no such model file, or a model trained with normalization whose
            statistics file is missing.
        ValueError: not a redsim model (without ``algo``), a model of another env or algorithm, or a file that
            does not load as ``algo``.
    """
    path = _zip_path(path)
    record = model_record(path, plain_algo=algo)
    if env_id is not None and record["env_id"] not in (env_id, None):
        raise ValueError(f"the model {path} was trained on {record['env_id']}, not on {env_id}")
    # a HER model's replay buffer needs its env to be built; an agent only acts, so it gets a plain one
    plain = {"replay_buffer_class": _dict_buffer(), "replay_buffer_kwargs": {}} if record["goal"] else None
    try:
        model = _algo_class(record["algo"]).load(path, device="cpu", custom_objects=plain)
    except Exception as err:  # SB3 raises what the policy's constructor raises on another algorithm's parameters
        raise ValueError(f"{path} does not load as a {record['algo'].upper()} model: {err!r}") from err
    normalizer = load_normalizer(normalizer_path(path)) if record["normalized"] else None
    return Agent(model, normalizer, record["goal"], record["env_id"], record["map"])


def _dict_buffer() -> Any:
    from stable_baselines3.common.buffers import DictReplayBuffer

    return DictReplayBuffer


def _policies_folder() -> Path:
    from redsim import pretrained

    return pretrained.FOLDER / "policies"


def shipped_policies() -> dict[str, Path]:
    """Env id -> the model file of the trained policy shipped with redsim for it (see :func:`shipped_policy`)."""
    found = {}
    for record in sorted(_policies_folder().glob("*.json")):
        model = record.with_suffix(".zip")
        if model.is_file():
            found[json.loads(record.read_text())["env_id"]] = model
    return found


def shipped_policy(env_id: str) -> Path:
    """The shipped policy of ``env_id``: ``redsim/pretrained/policies/NAME.zip`` (``RedSim/NAME``).

    Beside it: ``NAME_vecnormalize.pkl`` (its observation statistics) and ``NAME.json`` (the command
    that trained it and its seeded evaluation against the baselines). Load it with :func:`load_agent`.

    Raises:
        KeyError: no policy is shipped for ``env_id`` (the message lists those that are).
    """
    found = shipped_policies()
    if env_id not in found:
        raise KeyError(f"no shipped policy for {env_id!r}; shipped: {', '.join(found) or 'none'}")
    return found[env_id]


# -- training ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrainResult:
    """What :func:`train_agent` did.

    Attributes:
        model_path: The final ``model.zip``.
        steps: Env steps the model has been trained for in all (resumed runs included).
        wall_s: Wall time of all training runs into this folder [s] (evaluations included).
        evaluation: The final seeded evaluation of the model.
        out: The output folder.
        trained: Env steps this call trained (0: a resumed run already at ``steps``, evaluated and saved again).
    """

    model_path: Path
    steps: int
    wall_s: float
    evaluation: Evaluation
    out: Path
    trained: int = 0


class TrainingInterrupted(KeyboardInterrupt):
    """A ``train_agent`` run stopped by Ctrl-C after its model, replay buffer, normalizer, curve and
    ``agent.json`` (``"interrupted": true``) were saved: ``resume=True`` continues it (or, stopped in the final
    evaluation, runs that evaluation).

    Attributes:
        steps: Env steps the saved model was trained for (PPO: up to its last learnt rollout, with the weights,
            optimizer and normalizer statistics of then; a rollout not yet learnt, or its unfinished update, is
            dropped).
        model_path: The saved ``model.zip``.
        saved: False where a second Ctrl-C stopped the save: ``model_path`` (if any) and the checkpoints are then
            those of the last whole save, which ``resume=True`` continues from.
    """

    def __init__(self, steps: int, model_path: Path, saved: bool = True) -> None:
        if saved:
            message = f"interrupted at {steps} env steps; saved {model_path}"
        else:
            message = (
                f"interrupted at {steps} env steps and again while saving them: {model_path} and the checkpoints "
                "beside it hold the last whole save"
            )
        super().__init__(message)
        self.steps, self.model_path, self.saved = steps, model_path, saved


def _save_run(model: Any, venv: Any, model_path: Path) -> None:
    """The model, its replay buffer (off-policy) and its ``VecNormalize`` statistics (where normalized), each
    written in full beside its file before any replaces its file: an interrupt while saving keeps the previous
    three whole and together (not a cut-short zip, nor a new model beside the older model's statistics)."""
    from stable_baselines3.common.vec_env import VecNormalize

    writes: list[tuple[Path, Callable[[Path], Any]]] = [(model_path, model.save)]
    if hasattr(model, "save_replay_buffer"):
        writes.append((model_path.parent / BUFFER, model.save_replay_buffer))
    if isinstance(venv, VecNormalize):
        writes.append((normalizer_path(model_path), lambda tmp: venv.save(str(tmp))))
    partial = [path.with_name(path.name + ".tmp") for path, _ in writes]  # a suffix: SB3 adds none
    try:
        for (_, write), tmp in zip(writes, partial, strict=True):
            write(tmp)
        for (path, _), tmp in zip(writes, partial, strict=True):
            os.replace(tmp, path)
    finally:
        for tmp in partial:
            tmp.unlink(missing_ok=True)


def _save_after_interrupt(model: Any, venv: Any, model_path: Path) -> bool:
    """:func:`_save_run` after a Ctrl-C; False where a second Ctrl-C stopped it (the previous files stand whole)."""
    try:
        _save_run(model, venv, model_path)
    except KeyboardInterrupt:
        return False
    return True


def _load_for_resume(cls: Any, previous: Path, found: dict, venv: Any, eval_env: Any) -> tuple[Any, Any, Any]:
    """The model saved at ``previous`` (its record ``found``, :func:`model_record`) loaded onto the training copies
    ``venv``, with its ``VecNormalize`` statistics where it has them (and an evaluation normalizer): (venv, eval_env,
    model).

    Raises:
        ValueError: the envs step in another subspace map than the one the model was trained in (its record's
            fingerprint): its observations would be another map's latent coordinates.
    """
    from stable_baselines3.common.vec_env import VecNormalize

    now = _map_of(eval_env.venv)  # the evaluation copies (in this process, where sharded training copies are not)
    if found["map"] is not None and now is not None and found["map"] != now:
        raise ValueError(
            f"cannot resume: {previous} was trained in the subspace map {found['map']}, and this env steps in {now} "
            "(a checkpoint refitted in place, or other fit options): its observations would be another map's latent "
            "coordinates (give the subspace it was trained in, or another --out)"
        )
    if found["normalized"]:
        venv = VecNormalize.load(str(normalizer_path(previous)), venv)
        eval_env = VecNormalize(eval_env, training=False, norm_reward=False)
    return venv, eval_env, cls.load(previous, env=venv, device="cpu")


def _close_quietly(venv: Any) -> None:
    """Close an env after an interrupt (its workers may have been interrupted too)."""
    try:
        venv.close()
    except Exception as error:  # the run is saved; a worker that died with the interrupt must not hide that
        log.warning("closing %s after the interrupt failed: %r", type(venv).__name__, error)


def _rollout_keeper(venv: Any) -> Any:
    """A PPO callback that copies, as each rollout starts, the point the run has learnt up to: the model's step and
    update counts, its policy and optimizer state and ``venv``'s ``VecNormalize`` statistics; its ``restore()`` puts
    them back. An interrupted PPO run is saved at that point. SB3 counts a rollout's steps (and its observations
    into the statistics) as it collects them and updates the weights in place over ``n_epochs`` only after the
    rollout, so an interrupt inside the rollout, in a callback at its last step or inside the update would otherwise
    save steps, statistics or partly updated weights that were never learnt together. (An interrupt after an update
    but before the next rollout starts drops that update as well: the saved run is older, never inconsistent.)"""
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import VecNormalize

    class RolloutKeeper(BaseCallback):
        kept: tuple[int, int, Any, Any, Any] | None = None

        def _on_rollout_start(self) -> None:
            model = self.model
            statistics = (venv.obs_rms, venv.ret_rms, venv.returns) if isinstance(venv, VecNormalize) else None
            weights = (model.policy.state_dict(), model.policy.optimizer.state_dict(), statistics)
            # one assignment: an interrupt while copying keeps the previous rollout's point whole
            self.kept = (int(model.num_timesteps), int(model._n_updates), *copy.deepcopy(weights))

        def _on_step(self) -> bool:
            return True

        def restore(self) -> None:
            if self.kept is None:  # no rollout started: nothing has moved
                return
            model = self.model
            model.num_timesteps, model._n_updates, policy, optimizer, statistics = self.kept
            model.policy.load_state_dict(policy)
            model.policy.optimizer.load_state_dict(optimizer)
            if statistics is not None:
                venv.obs_rms, venv.ret_rms, venv.returns = copy.deepcopy(statistics)

    return RolloutKeeper()


def _rollout_checkpoints(every: int, folder: Path) -> Any:
    """PPO's checkpoints, in the files of SB3's ``CheckpointCallback`` (``folder/rl_model_N_steps.zip`` and its
    statistics, :func:`normalizer_path`), saved as the first rollout at or past each multiple of ``every`` env steps
    starts, and as training ends: points where the steps, weights and statistics were learnt together. (SB3's saves
    at any vector step, counting the steps of a rollout PPO has not learnt yet, with its observations in the
    statistics; at a rollout's last step even the weights are those from before its update. A resume takes the
    file trained the most steps, so such a checkpoint would skip the rollout, or run past ``steps``.)"""
    from stable_baselines3.common.callbacks import BaseCallback

    class RolloutCheckpoint(BaseCallback):
        saved = 0
        """Grid points (multiples of ``every``) passed at the last save, or at training start."""

        def _init_callback(self) -> None:
            folder.mkdir(parents=True, exist_ok=True)
            self.saved = int(self.model.num_timesteps) // every

        def _on_rollout_start(self) -> None:
            self._save()

        def _on_step(self) -> bool:
            return True

        def _on_training_end(self) -> None:
            self._save()

        def _save(self) -> None:
            steps = int(self.model.num_timesteps)
            if steps // every <= self.saved:
                return
            self.saved = steps // every
            path = folder / f"rl_model_{steps}_steps.zip"
            normalizer = self.model.get_vec_normalize_env()
            if normalizer is not None:  # first: a checkpoint's model is never without its statistics
                normalizer.save(str(normalizer_path(path)))
            self.model.save(path)

    return RolloutCheckpoint()


def _evaluations(eval_env: Any, eval_seed: int, on_rollouts: bool, **options: Any) -> Any:
    """SB3's ``EvalCallback`` (``options``: its arguments) whose every evaluation plays the same episodes: the eval
    env is reseeded with ``eval_seed`` first, so the curve's points compare policies and a resumed run evaluates as
    an uninterrupted one (the env's stream went on from evaluation to evaluation, and restarted on a resume).
    ``on_rollouts`` (PPO): it evaluates as the first rollout at or past each multiple of ``eval_freq`` vector steps
    starts, and as training ends: the policy learnt from every step counted (at a rollout's last step, where SB3's
    own evaluates, the update has not happened yet: the point labelled N scored the policy of N minus a rollout).
    ``evaluate_now()`` makes one evaluation at once (a resumed run's missed one)."""
    from stable_baselines3.common.callbacks import EvalCallback

    class SeededEvaluation(EvalCallback):
        evaluated = 0
        """Grid points (multiples of ``eval_freq`` vector steps) evaluated, or passed at training start."""

        def _init_callback(self) -> None:
            super()._init_callback()
            self.evaluated = self.n_calls // self.eval_freq

        def _on_step(self) -> bool:
            if on_rollouts:
                return True
            if self.n_calls % self.eval_freq == 0:
                self.evaluated = self.n_calls // self.eval_freq
                self.eval_env.seed(eval_seed)
            return super()._on_step()

        def _on_rollout_start(self) -> None:
            if on_rollouts and self.n_calls // self.eval_freq > self.evaluated:
                self.evaluate_now()

        def _on_training_end(self) -> None:
            self._on_rollout_start()

        def evaluate_now(self) -> bool:
            self.evaluated = self.n_calls // self.eval_freq
            self.num_timesteps = self.model.num_timesteps
            self.eval_env.seed(eval_seed)
            freq, self.eval_freq = self.eval_freq, 1  # EvalCallback evaluates where n_calls % eval_freq == 0
            try:
                return super()._on_step()
            finally:
                self.eval_freq = freq

    return SeededEvaluation(eval_env, **options)


def _curve_callback(curve: list[dict[str, float]], wall_offset: float, start: float, path: Path) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    class CurveRecorder(BaseCallback):
        """After each evaluation: one row (env steps, wall s, mean/std return, success rate) of the curve, written
        to ``path`` at once (a run killed later keeps its rows)."""

        def _on_step(self) -> bool:
            parent = self.parent
            results = np.asarray(parent.evaluations_results[-1])
            success = parent.evaluations_successes[-1] if parent.evaluations_successes else []
            curve.append(
                {
                    "env_steps": int(parent.num_timesteps),
                    "wall_s": wall_offset + time.perf_counter() - start,
                    "mean_return": float(results.mean()),
                    "std_return": float(results.std()),
                    "success_rate": float(np.mean(success)) if len(success) else float("nan"),
                }
            )
            _write_curve(path, curve)
            return True

    return CurveRecorder()


def _normalizer_saver(path: Path) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    class NormalizerSaver(BaseCallback):
        """On a new best model: its ``VecNormalize`` statistics beside it (none without normalization)."""

        def _on_step(self) -> bool:
            normalizer = self.model.get_vec_normalize_env()
            if normalizer is not None:
                normalizer.save(str(path))
            return True

    return NormalizerSaver()


RUN_FILES = (
    "model.zip",
    "best_model.zip",
    "replay_buffer.pkl",
    "evaluations.npz",
    "curve.csv",
    "curve.png",
    "progress.csv",
    "policy.gif",
    "agent.json",
)
"""The files of a run in its folder (module doc), with the normalizers beside the models and ``checkpoints/``."""


def check_run_folder(out: Path, resume: bool, overwrite: bool) -> None:
    """Refuse to start a run in ``out`` where one is (unless ``overwrite``), or to resume and overwrite at once: what
    :func:`train_agent` checks first, for a script to check before its own slow work (a fit, say).

    Raises:
        ValueError: as said, naming --resume / --overwrite.
    """
    if resume and overwrite:
        raise ValueError("resume and overwrite exclude each other (--resume continues a run, --overwrite replaces it)")
    if resume or overwrite:
        return
    found = sorted(p.name for p in map(out.joinpath, RUN_FILES) if p.is_file())
    if found or any((out / "checkpoints").glob("rl_model_*")):
        raise ValueError(
            f"{out} holds a run ({', '.join(found) or 'checkpoints/'}): continue it with --resume (resume=True) or "
            "replace it with --overwrite (overwrite=True), or give another --out"
        )


def _remove_run(out: Path) -> None:
    """Delete a run's files from ``out`` (RUN_FILES, their normalizers, ``checkpoints/``); nothing else there."""
    for name in RUN_FILES:
        (out / name).unlink(missing_ok=True)
        if name.endswith(".zip"):
            normalizer_path(out / name).unlink(missing_ok=True)
    for resumed in out.glob("progress-from-*.csv"):
        resumed.unlink()
    shutil.rmtree(out / "checkpoints", ignore_errors=True)


def training_seed(seed: int, steps: int) -> int:
    """The reset seed s of the training copies (copy i: s + i) of a run with ``seed``, started or resumed at
    ``steps``: a 32-bit number from ``SeedSequence([seed, steps])``, so runs of neighbouring seeds share no episode
    (seeds ``seed + i`` would give run 1's copy i run 0's copy i + 1), nor do they replay the evaluations'
    (``seed + 10_000 + i``, ``seed + 20_000 + i``) or ``eval-agent``'s (0-19)."""
    return int(np.random.SeedSequence([int(seed), int(steps)]).generate_state(1)[0])


def _resume_from(out: Path) -> Path | None:
    """Of ``out/model.zip`` and the checkpoints, the one trained the most env steps (``model.zip`` on a tie: it keeps
    the replay buffer); None: nothing to resume from. Steps, not file times: a copy that resets times must not make
    an older checkpoint replace newer work. A checkpoint whose ``VecNormalize`` statistics are missing or damaged
    (:func:`_whole`) is passed over, with a warning, for the next one."""
    found = [p for p in [out / "model.zip", *(out / "checkpoints").glob("rl_model_*_steps.zip")] if p.is_file()]
    ranked = sorted(found, key=lambda p: (_saved_steps(p), p.name == "model.zip"), reverse=True)
    for path in ranked:
        if path.name == "model.zip" or _whole(path):  # model.zip's own statistics missing: the caller refuses
            return path
        log.warning(
            "not resuming from %s: its observation statistics %s are missing or damaged", path, normalizer_path(path)
        )
    return ranked[0] if ranked else None  # none whole: the newest, which the caller refuses (never a new run)


def _check_kept_settings(overrides: Mapping[str, Any] | None, recorded: Mapping[str, Any] | None, out: Path) -> None:
    """Refuse ``overrides`` that a resumed model would not take: its settings are the saved ones (``recorded``, the
    run's ``agent.json``), so another value would be written to the record but not used. ``learning_starts`` is
    derived again on a resume (module doc) and passes."""
    if not overrides or recorded is None:
        return
    changed = {
        k: v
        for k, v in overrides.items()
        if k != "learning_starts"
        and k in recorded
        and _plain(v)
        and not _within(json.loads(json.dumps(v)), recorded[k])
    }
    if changed:
        kept = {k: recorded.get(k) for k in changed}
        raise ValueError(
            f"cannot resume with overrides {changed}: the run in {out} was made with {kept}, and a resumed model "
            "keeps its settings (give the same overrides, or none, or another --out)"
        )


def _plain(value: Any) -> bool:
    """A value JSON holds as it is (numbers, strings, bools, None, lists and dicts of them): one a record can be
    compared with; a function or class (a schedule, a policy class) is recorded by a name that changes per process."""
    if isinstance(value, Mapping):
        return all(isinstance(k, str) and _plain(v) for k, v in value.items())
    if isinstance(value, list | tuple):
        return all(_plain(v) for v in value)
    return value is None or isinstance(value, bool | int | float | str)


def _within(given: Any, recorded: Any) -> bool:
    """``given`` equals ``recorded``, a dict's keys compared only where given (the run may have added its own, as
    HER's ``goal_selection_strategy`` in ``replay_buffer_kwargs``)."""
    if isinstance(given, dict) and isinstance(recorded, dict):
        return all(k in recorded and _within(v, recorded[k]) for k, v in given.items())
    return given == recorded


def _whole(path: Path) -> bool:
    """False for a saved model trained on normalized observations whose ``VecNormalize`` statistics are missing or do
    not load (a checkpoint's are written after its model: a hard stop between the two leaves them out); a model
    file that cannot be read counts as whole here (its load reports it; :func:`_saved_steps` ranks it last)."""
    try:
        normalized = model_record(path)["normalized"]
    except (FileNotFoundError, ValueError):
        return True
    try:
        if normalized:
            load_normalizer(normalizer_path(path))
    except (FileNotFoundError, ValueError):
        return False
    return True


def _saved_steps(path: Path) -> int:
    """The env steps an SB3 zip was trained for (its ``data``'s ``num_timesteps``; -1 if it cannot be read)."""
    try:
        with zipfile.ZipFile(path) as saved:
            return int(json.loads(saved.read("data"))["num_timesteps"])
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return -1


def _training_log(model: Any, out: Path, resumed_at: int | None) -> Any:
    """SB3's logger writing ``out/progress.csv`` (``progress-from-STEPS.csv`` for a run resumed at STEPS), and, where
    the settings ask for them (``tensorboard_log``, ``verbose``), SB3's own TensorBoard and stdout outputs."""
    from stable_baselines3.common.logger import CSVOutputFormat, Logger
    from stable_baselines3.common.utils import configure_logger

    out.mkdir(parents=True, exist_ok=True)
    name = "progress.csv" if resumed_at is None else f"progress-from-{resumed_at}.csv"
    progress = CSVOutputFormat(str(out / name))
    if model.tensorboard_log is None and not model.verbose:
        return Logger(folder=str(out), output_formats=[progress])
    logger = configure_logger(model.verbose, model.tensorboard_log, type(model).__name__, resumed_at is None)
    logger.output_formats.append(progress)
    return logger


def _wall_at(curve: list[dict[str, Any]], record: Mapping[str, Any], steps: int) -> float:
    """The run's wall time [s] when it had trained ``steps`` env steps: the record's (``agent.json``) where the run
    stopped there, else linear between the curve's evaluations and the record's end (a resume from an older
    checkpoint does not count the time of the work it drops; a record without its steps is taken as the resumed
    step's)."""
    points = {0: 0.0, **{int(row["env_steps"]): float(row["wall_s"]) for row in curve}}
    points[int(record.get("steps", steps))] = float(record.get("wall_s", 0.0))
    xs, ys = zip(*sorted(points.items()), strict=True)
    return float(np.interp(steps, xs, ys))


CURVE_FIELDS = ("env_steps", "wall_s", "mean_return", "std_return", "success_rate", "final")
"""``curve.csv``'s columns. ``final`` is 1 on the row of a run's final evaluation (``final_episodes`` episodes from
SEED + ``FINAL_EVAL_SEED``, made where no periodic evaluation fell on the run's last step) and 0 on the periodic
evaluations' rows (the same ``eval_episodes`` episodes each, so only they compare policies)."""


def _read_curve(path: Path) -> list[dict[str, Any]]:
    """The rows of ``curve.csv`` (a file written before the ``final`` column reads 0 there)."""
    if not path.is_file():
        return []
    with path.open() as handle:
        rows = [{k: int(v) if k == "env_steps" else float(v) for k, v in row.items()} for row in csv.DictReader(handle)]
    return [{"final": 0.0} | row for row in rows]


def _write_curve(path: Path, curve: list[dict[str, float]]) -> None:
    """``curve.csv``, replaced whole (an interrupt in the write leaves the previous file, so a resume can read it)."""

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=CURVE_FIELDS, restval=0.0)
            writer.writeheader()
            writer.writerows(curve)

    write_atomically(path, write)


def _read_record(path: Path) -> dict[str, Any]:
    """A run's ``agent.json`` that a resume checks its seed and settings against.

    Raises:
        ValueError: the file is not a record (damaged, or edited), naming it and what to do.
    """
    try:
        record = json.loads(path.read_text())
    except ValueError as err:
        record = err
    if not isinstance(record, dict):
        raise ValueError(
            f"cannot resume: the run's record {path} is damaged ({record}); restore it, move it away to resume "
            "without its checks (the run's seed, intervals and settings), or start again with --overwrite"
        )
    return record


def _write_record(out: Path, summary: Mapping[str, Any]) -> None:
    """``agent.json``, replaced whole (as :func:`_write_curve`)."""
    text = json.dumps(summary, indent=2, default=str)
    write_atomically(out / "agent.json", lambda tmp: tmp.write_text(text))


def plot_curve(curve: list[dict[str, float]], path: Path, title: str) -> None:
    """Evaluation return (mean ± std) vs env steps and vs wall time, side by side, as a PNG: the periodic
    evaluations as a line, the final evaluations (``final`` rows: other episodes) as separate points."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), sharey=True)
    periodic = [r for r in curve if not r.get("final")]
    finals = [r for r in curve if r.get("final")]
    for ax, key, label in ((axes[0], "env_steps", "env steps"), (axes[1], "wall_s", "wall time [s]")):
        if periodic:
            x, mean, std = (np.array([r[k] for r in periodic]) for k in (key, "mean_return", "std_return"))
            ax.plot(x, mean, marker="o", ms=3, label="evaluations (the same episodes each)")
            ax.fill_between(x, mean - std, mean + std, alpha=0.25)
        if finals:
            x, mean, std = (np.array([r[k] for r in finals]) for k in (key, "mean_return", "std_return"))
            ax.errorbar(x, mean, yerr=std, fmt="D", ms=4, color="k", capsize=3, label="final (other episodes)")
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    if finals:
        axes[0].legend(fontsize=7, loc="lower right")
    axes[0].set_ylabel("evaluation return")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def record_gif(
    env: str | gym.Env,
    model: Any,
    path: Path,
    *,
    seed: int = 0,
    size: int = 240,
    every: int = 2,
    env_kwargs: Mapping[str, Any] | None = None,
) -> int:
    """One deterministic episode of ``model`` drawn every ``every`` steps into a GIF; returns the frame count."""
    from PIL import Image

    if isinstance(env, str):
        # the env's own width and height win over ``size``
        single = gym.make(env, **{"width": size, "height": size, **dict(env_kwargs or {}), "render_mode": "rgb_array"})
    elif env.render_mode == "rgb_array":
        single = env
    else:
        raise ValueError("record_gif needs a registered id or an env made with render_mode='rgb_array'")
    obs, _ = single.reset(seed=seed)
    frames = [single.render()]
    for step in range(1, 100_000):
        obs, _, terminated, truncated, _ = single.step(model.predict(obs, deterministic=True)[0])
        if step % every == 0:
            frames.append(single.render())
        if terminated or truncated:
            break
    dt = float(single.unwrapped.dt)
    if single is not env:
        single.close()
    images = [Image.fromarray(f) for f in frames]
    duration = round(1000 * dt * every)
    # to a temporary, then renamed: a Ctrl-C while writing leaves no cut-short GIF (nor a resumed run's old one so)
    write_atomically(
        Path(path),
        lambda tmp: images[0].save(
            tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0
        ),
    )
    return len(images)


def _continue_evaluations(callback: Any, path: Path, until: int, episodes: int) -> None:
    """A resumed run's ``EvalCallback`` starts from the run's earlier evaluations (``evaluations.npz``, those up
    to ``until`` steps), which it rewrites after each evaluation, and replaces ``best_model.zip`` only with a better
    mean return than any earlier evaluation's (those past ``until`` included: a run resumed from a checkpoint may
    have saved its best model later). Earlier evaluations of another episode count are not carried (one file, one
    shape). A damaged file (SB3 writes it in place: a hard stop mid-write truncates it) is warned about and taken as
    none, as a missing one is."""
    if not path.is_file():
        return
    try:
        with np.load(path) as data:
            old = {name: data[name] for name in data.files}
        timesteps, results, lengths = old["timesteps"], old["results"], old["ep_lengths"]
        means = results.reshape(len(timesteps), -1).mean(axis=1) if results.size else None
    except Exception as err:  # whatever a truncated or foreign file raises (BadZipFile, KeyError, ValueError...)
        log.warning(
            "ignoring %s (%s: %s): this run's evaluations.npz starts anew, and its next evaluation's model replaces "
            "best_model.zip",
            path,
            type(err).__name__,
            err,
        )
        return
    if means is not None:
        callback.best_mean_reward = float(means.max())
    keep = timesteps <= until
    results = results[keep]
    if results.ndim != 2 or results.shape[1] != episodes:
        return
    callback.evaluations_timesteps = [int(t) for t in timesteps[keep]]
    callback.evaluations_results = [list(row) for row in results]
    callback.evaluations_length = [list(row) for row in lengths[keep]]
    if "successes" in old and len(old["successes"]) == len(keep):
        callback.evaluations_successes = [list(row) for row in old["successes"][keep]]


def _her_settings(
    settings: dict[str, Any], algo: str, copies: int, episode: int | None, steps: int, shards: int = 1
) -> None:
    """Add SB3's ``HerReplayBuffer`` to an off-policy algorithm's ``settings`` (in place), with ``learning_starts``
    such that learning waits for an ended episode of every copy (HER samples only ended episodes): SB3 learns once
    its step count exceeds ``learning_starts``, so at least copies x episode - 1 (:func:`her_wait`).

    Raises:
        ValueError: PPO, ``shards`` > 1, an env without an episode limit, or ``steps`` below copies x episode (no
            step would learn).
    """
    from stable_baselines3 import HerReplayBuffer

    if algo == "ppo":
        raise ValueError("her needs an off-policy algorithm (sac or td3): HER relabels a replay buffer")
    if shards != 1:  # refused before any worker process starts
        raise ValueError(
            f"her needs the native vector env in one process (shards=1, no --shards), got shards={shards}: the "
            "goal env relabels with the copies' targets, which a sharded env's workers hold"
        )
    if episode is None:
        raise ValueError("her needs an episode limit (max_episode_steps): HER relabels with the episode's goals")
    ended = copies * episode
    if steps < ended:
        raise ValueError(
            f"her: {steps} steps are not enough: HER's relabelling needs an ended episode of every copy, so learning "
            f"starts at {ended} steps ({copies} copies x {episode}-step episodes): give {ended} or more, or fewer "
            "copies or shorter episodes (--steps, --n-envs, --episode-steps)"
        )
    settings["replay_buffer_class"] = HerReplayBuffer
    settings["replay_buffer_kwargs"] = {
        "n_sampled_goal": 4,
        "goal_selection_strategy": "future",
        **settings.get("replay_buffer_kwargs", {}),
    }
    settings["learning_starts"] = max(int(settings.get("learning_starts", 100)), her_wait(copies, episode))


def her_wait(copies: int, episode: int) -> int:
    """The ``learning_starts`` at which SB3 (learning once its step count exceeds it) first learns with an ended
    episode of every copy of a vector env whose copies start together: copies x episode steps, less one."""
    return copies * episode - 1


def train_agent(
    env: str | gym.Env,
    out: str | Path,
    *,
    algo: str = "sac",
    steps: int = 20_000,
    seed: int = 0,
    n_envs: int | None = None,
    eval_every: int | None = None,
    eval_episodes: int = 10,
    final_episodes: int = 20,
    checkpoint_every: int | None = None,
    resume: bool = False,
    overwrite: bool = False,
    progress_bar: bool = False,
    video: bool = True,
    overrides: Mapping[str, Any] | None = None,
    env_kwargs: Mapping[str, Any] | None = None,
    shards: int = 1,
    her: bool = False,
) -> TrainResult:
    """Train ``algo`` on ``env`` for ``steps`` env steps in all, writing the files of the module doc to ``out``.

    Args:
        env: A registered id (``"RedSim/MiniChain-v0"``) or a user's env (:func:`redsim.envs.make`).
        out: Output folder (created).
        algo: "sac", "td3" or "ppo".
        steps: Total env steps (over all copies); with ``resume``, the run continues up to this many.
        seed: Seed of the algorithm and of the env copies.
        n_envs: Vector env copies (default: the table's).
        eval_every: Env steps between evaluations (default: ``steps / 10``).
        eval_episodes: Episodes per evaluation during training.
        final_episodes: Seeded episodes of the final evaluation (in ``agent.json``).
        checkpoint_every: Env steps between checkpoints (default: ``steps / 4``; PPO saves as the first rollout at
            or past each multiple starts, when the steps before it are learnt).
        resume: Continue from the one of ``out/model.zip`` and ``out/checkpoints/*.zip`` trained the most env steps
            (``model.zip`` on a tie), with the same ``env_kwargs`` (a default given again is the same) and seed.
        overwrite: Replace a run already in ``out`` (its files of the module doc); without it (or ``resume``) a
            run there is refused, so that nothing is mixed or lost.
        progress_bar: Show SB3's progress bar (needs ``rich``).
        video: Write ``policy.gif`` (a user's env only when made with ``render_mode="rgb_array"``).
        overrides: Settings that replace the table's (e.g. ``{"learning_rate": 3e-4}``).
        env_kwargs: Keyword arguments of the id's env (e.g. ``{"max_episode_steps": 50}``).
        shards: Worker processes of the training env (:mod:`redsim.envs.sharded`; ids only; the same env, its
            copies stepped on P cores). The evaluation env stays one process.
        her: Hindsight experience replay (module doc; SAC or TD3, a reach env, one process). ``learning_starts``
            is raised to the transitions until every copy has ended an episode, where HER starts to sample.

    Raises:
        ValueError: an unknown id or algorithm, bad counts, a seed outside [0, 2**32 - 1], ``her`` with PPO,
            another task or shards, a budget that ends no episode of every copy, a run already in ``out`` (neither
            ``resume`` nor ``overwrite``), ``resume`` with ``overwrite``, or (resume) a model of another env,
            algorithm, replay, ``env_kwargs`` or subspace map, a run started with another ``seed``, or other
            ``n_envs`` than its replay buffer holds, or a damaged replay buffer.
        FileNotFoundError: (resume) a model trained on normalized observations whose ``VecNormalize`` statistics
            (:func:`normalizer_path`) are missing.
        TrainingInterrupted: a KeyboardInterrupt in training or the final evaluation, raised once the run is saved
            (``resume=True`` continues it).
    """
    from stable_baselines3.common.callbacks import CallbackList, CheckpointCallback
    from stable_baselines3.common.noise import NormalActionNoise
    from stable_baselines3.common.vec_env import VecNormalize

    for name, value in (("steps", steps), ("eval_episodes", eval_episodes), ("final_episodes", final_episodes)):
        if isinstance(value, bool) or int(value) != value or value < 1:  # before training, not after it
            raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    if isinstance(seed, bool) or int(seed) != seed or not 0 <= seed < 2**32:
        raise ValueError(
            f"seed must be an integer in [0, 2**32 - 1] (stable-baselines3 seeds NumPy with it), got {seed!r}"
        )
    if eval_every is not None and (isinstance(eval_every, bool) or int(eval_every) != eval_every or eval_every < 1):
        raise ValueError(f"eval_every must be an integer >= 1 (env steps), got {eval_every!r}")
    env_id = env if isinstance(env, str) else None
    if env_id is not None:
        check_env_id(env_id)
    label = _env_label(env)
    settings = hyperparams(env_id, algo)
    settings.update(overrides or {})
    copies = int(n_envs or settings.pop("n_envs"))
    settings.pop("n_envs", None)
    if copies < 1:
        raise ValueError(f"n_envs must be >= 1, got {copies}")
    normalize = settings.pop("normalize", None)
    if algo != "ppo" and "learning_starts" not in (overrides or {}):
        # the table's start would leave a short run untrained, silently: at most half the budget
        settings["learning_starts"] = min(int(settings["learning_starts"]), int(steps) // 2)
    if _episode_steps(env, env_kwargs) is None:  # before any env is made: an evaluation would never end
        raise ValueError(
            f"train_agent needs an episode limit (max_episode_steps): {label}'s evaluations run whole episodes, "
            "and without a limit its episodes need not end"
        )
    if her:
        _check_reach(env)
        _her_settings(settings, algo, copies, _episode_steps(env, env_kwargs), int(steps), shards)
    out = Path(out)
    cls = _algo_class(algo)
    check_run_folder(out, resume, overwrite)
    previous = _resume_from(out) if resume else None
    buffer = previous is not None and previous == out / "model.zip" and algo != "ppo" and (out / BUFFER).is_file()
    if previous is not None:
        found = model_record(previous)
        if (found["env_id"], found["algo"], found["goal"] is not None) != (label, algo, her):
            replay = {True: " with HER", False: ""}
            raise ValueError(
                f"cannot resume: {previous} is {found['algo']}{replay[found['goal'] is not None]} on "
                f"{found['env_id']}, not {algo}{replay[her]} on {label}"
            )
        if found["normalized"] and not normalizer_path(previous).is_file():
            raise FileNotFoundError(
                f"cannot resume from {previous}: it was trained on normalized observations and its statistics "
                f"{normalizer_path(previous)} are missing (restore the file, or start again with --overwrite)"
            )
        if buffer and found["n_envs"] not in (None, copies):
            raise ValueError(
                f"cannot resume with {copies} copies: the run's replay buffer {out / BUFFER} holds "
                f"{found['n_envs']} (give n_envs={found['n_envs']}, --n-envs {found['n_envs']})"
            )
        if found["normalized"]:
            try:
                load_normalizer(normalizer_path(previous))
            except ValueError as err:
                raise ValueError(
                    f"cannot resume from {previous}: its statistics are damaged ({err}; restore the file, or start "
                    "again with --overwrite)"
                ) from None
    kwargs_now = json.loads(json.dumps(dict(env_kwargs or {}), default=str))  # as the model file records them
    limit_now = None if isinstance(env, str) else _base_env(env)[1]
    if not isinstance(env, str):  # a user's env: no kwargs make it, but its episode limit changes the task
        kwargs_now["max_episode_steps"] = limit_now
        if previous is not None and found["env_kwargs"] == {}:  # a run saved before the limit was recorded
            found["env_kwargs"] = None
    if previous is not None and found["env_kwargs"] not in (None, kwargs_now):
        defaults = _env_defaults(env)  # a default given again (--env-arg max_episode_steps=200) makes the same env
        if {**defaults, **found["env_kwargs"]} != {**defaults, **kwargs_now}:
            same = (
                "the same --env-arg and --episode-steps" if isinstance(env, str) else "the env the same episode limit"
            )
            raise ValueError(
                f"cannot resume with env_kwargs {kwargs_now}: {previous} was trained with {found['env_kwargs']} "
                f"(give {same}, or another --out)"
            )
    has_record = previous is not None and (out / "agent.json").is_file()
    record = _read_record(out / "agent.json") if has_record else {}
    started_with = record.get("seed", seed)
    if started_with != seed:  # the copies' and the evaluations' episodes follow the seed
        raise ValueError(
            f"cannot resume with seed {seed}: the run in {out} was started with seed {started_with} (give "
            f"--seed {started_with}, or another --out)"
        )
    if previous is not None:
        _check_kept_settings(overrides, record.get("hyperparams"), out)
        # the run's own evaluation and checkpoint intervals where this call names none: its step grid stays
        eval_every = eval_every or record.get("eval_every")
        checkpoint_every = checkpoint_every or record.get("checkpoint_every")
    venv = _sb3_env(env, copies, training_seed(seed, 0), env_kwargs, shards, goal={} if her else None)
    # evaluations score the env's own reward (the goal env with its control cost passes it through)
    eval_env = _sb3_env(
        env, min(eval_episodes, 10), seed + 10_000, env_kwargs, goal={"control_cost": True} if her else None
    )
    goal = dict(venv.get_attr("observation_structure")[0]) if her else None
    noise_std = settings.pop("action_noise_std", None)
    if noise_std is not None:
        shape = venv.action_space.shape
        settings["action_noise"] = NormalActionNoise(np.zeros(shape), noise_std * np.ones(shape))

    if previous is not None:
        try:
            venv, eval_env, model = _load_for_resume(cls, previous, found, venv, eval_env)
        except BaseException:
            for env_ in (venv, eval_env):
                _close_quietly(env_)
            raise
        # new episodes, not a replay of the first run's, nor of the evaluations' (seed + 10_000, seed + 20_000)
        venv.seed(training_seed(seed, int(model.num_timesteps)))
        if "action_noise" in settings:  # TD3: the saved noise is vectorized over the saved run's copies
            model.action_noise = settings["action_noise"]
        if buffer:
            try:
                model.load_replay_buffer(out / BUFFER)
            except Exception as err:  # whatever unpickling a damaged file raises (a raw traceback in the CLI)
                for env_ in (venv, eval_env):
                    _close_quietly(env_)
                raise ValueError(
                    f"cannot resume: the replay buffer {out / BUFFER} is damaged ({type(err).__name__}: {err}); delete "
                    f"it to resume from {previous} without one (it acts at random for a while to refill it), or "
                    "start again with --overwrite"
                ) from None
        elif algo != "ppo":  # from a checkpoint (only model.zip keeps a replay buffer): refill before learning
            # HER samples only once every copy has ended an episode again; plain replay after the table's start
            ended = her_wait(copies, int(_episode_steps(env, env_kwargs) or 0))
            left = int(steps) - int(model.num_timesteps)
            wait = ended if her else min(int(settings["learning_starts"]), left // 2)  # as a new run: half at most
            model.learning_starts = max(int(model.learning_starts), int(model.num_timesteps) + wait)
            log.warning(
                "resuming %s from %s without a replay buffer (only model.zip keeps one): it acts at random for "
                "%d new env steps, then learns again%s",
                label,
                previous,
                wait,
                "" if wait < left else f" (past this run's {left} steps: it will not learn)",
            )
        log.info("resuming %s from %s at %d steps", label, previous, model.num_timesteps)
    else:
        if resume:
            log.warning("nothing to resume in %s (no model.zip, no checkpoint): starting a new run", out)
        if normalize:
            options = {"norm_reward": False, "gamma": settings.get("gamma", 0.99), **dict(normalize)}
            venv = VecNormalize(venv, **options)
            eval_env = VecNormalize(eval_env, training=False, norm_reward=False)
        policy = "MultiInputPolicy" if her else "MlpPolicy"
        model = cls(policy, venv, seed=seed, device="cpu", verbose=0, **settings)
        venv.seed(training_seed(seed, 0))  # SB3 seeded the copies seed + i: another run's and the evaluations'
    model.redsim_env_id = label
    model.redsim_algo = algo
    model.redsim_normalized = isinstance(venv, VecNormalize)
    model.redsim_goal = goal
    model.redsim_env_kwargs = kwargs_now
    model.redsim_map = _map_of((eval_env.venv if isinstance(eval_env, VecNormalize) else eval_env).venv)

    curve = _read_curve(out / "curve.csv") if previous is not None else []
    wall_offset = _wall_at(curve, record, int(model.num_timesteps)) if previous is not None else 0.0
    curve = [row for row in curve if row["env_steps"] <= model.num_timesteps]
    start = time.perf_counter()
    eval_every, checkpoint_every = int(eval_every or steps // 10), int(checkpoint_every or steps // 4)  # env steps
    every = max(eval_every // copies, 1)
    if algo == "ppo":  # the policy changes once per rollout of n_steps vector steps: evaluate no more often
        rollout = int(model.n_steps)
        every = max(every, rollout)
        left = int(steps) - int(model.num_timesteps)
        taken = -(-left // (rollout * copies)) * rollout * copies  # SB3 finishes the rollout it is in
        if left > 0 and taken != left:
            log.warning(
                "PPO learns from whole rollouts (n_steps %d x %d copies = %d env steps): this run takes %d, not %d",
                rollout,
                copies,
                rollout * copies,
                taken,
                left,
            )
    if overwrite:  # only now, with the envs and the model built: a refused run neither writes nor removes anything
        _remove_run(out)
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    evaluation_cb = _evaluations(
        eval_env,
        seed + 10_000,
        algo == "ppo",
        n_eval_episodes=eval_episodes,
        eval_freq=every,
        best_model_save_path=str(out),
        log_path=str(out),
        callback_after_eval=_curve_callback(curve, wall_offset, start, out / "curve.csv"),
        callback_on_new_best=_normalizer_saver(normalizer_path(out / "best_model.zip")),
        verbose=0,
    )
    if previous is not None:
        _continue_evaluations(evaluation_cb, out / "evaluations.npz", int(model.num_timesteps), eval_episodes)
    save_freq = max(checkpoint_every // copies, 1)  # vector steps
    if algo == "ppo":  # at learnt rollouts only
        checkpoint_cb = _rollout_checkpoints(save_freq * copies, out / "checkpoints")
    else:
        checkpoint_cb = CheckpointCallback(
            save_freq=save_freq, save_path=str(out / "checkpoints"), save_vecnormalize=True
        )
    if previous is not None:  # SB3's callbacks count their calls from 0 again: keep the run's step grid
        for callback in (evaluation_cb, checkpoint_cb):
            callback.n_calls = int(model.num_timesteps) // copies
    remaining = int(steps) - int(model.num_timesteps)
    summary = {
        "env_id": label,
        "algo": algo,
        "steps": int(model.num_timesteps),
        "wall_s": wall_offset,
        "n_envs": copies,
        "seed": seed,
        "her": her,
        "eval_every": eval_every,
        "checkpoint_every": checkpoint_every,
        "env_kwargs": dict(env_kwargs or {}) | ({} if isinstance(env, str) else {"max_episode_steps": limit_now}),
        # a resumed model keeps the settings it was made with (the record's), whatever this call's table gives
        "hyperparams": (
            record.get("hyperparams")
            or {k: v for k, v in settings.items() if k != "action_noise"}
            | {"action_noise_std": noise_std, "normalize": normalize}
        )
        | ({"learning_starts": int(model.learning_starts)} if hasattr(model, "learning_starts") else {}),
    }
    model_path = out / "model.zip"
    started = int(model.num_timesteps)
    keeper = [_rollout_keeper(venv)] if algo == "ppo" else []  # first: a rollout's point is kept before its checkpoint

    def interrupted(wall: float, saved: bool) -> TrainingInterrupted:
        """Record the run as interrupted (``agent.json``; the curve so far) for the caller to raise; ``saved``: its
        model was saved at this step (else a second Ctrl-C stopped the save)."""
        _write_curve(out / "curve.csv", curve)
        summary.update(steps=int(model.num_timesteps), wall_s=wall, interrupted=True, saved=saved)
        _write_record(out, summary)
        return TrainingInterrupted(int(model.num_timesteps), model_path, saved)

    try:
        if remaining > 0:
            model.set_logger(_training_log(model, out, None if previous is None else started))
            try:
                # the curve has a row of every evaluation made, whatever its episode count (evaluations.npz keeps
                # only those of this run's count), and of the final one
                last = max((row["env_steps"] for row in curve), default=0)  # the last evaluation before it
                missed = evaluation_cb.n_calls // every > last // copies // every  # a grid point since, not evaluated
                if previous is not None and started > 0 and missed:  # interrupted in its evaluation: made now
                    evaluation_cb.init_callback(model)
                    evaluation_cb.evaluate_now()
                model.learn(
                    remaining,
                    callback=CallbackList([*keeper, evaluation_cb, checkpoint_cb]),
                    reset_num_timesteps=previous is None,
                    progress_bar=progress_bar,
                )
            finally:
                model.logger.close()
    except KeyboardInterrupt:
        # as a fit: keep what was learnt (model, replay buffer, normalizer, curve), so --resume goes on from here
        for kept in keeper:  # PPO: back to its last learnt rollout (steps, weights, normalizer statistics)
            kept.restore()
        saved = _save_after_interrupt(model, venv, model_path)
        for env_ in (venv, eval_env):
            _close_quietly(env_)
        raise interrupted(wall_offset + time.perf_counter() - start, saved) from None
    wall = wall_offset + time.perf_counter() - start
    saved = False
    try:  # trained: an interrupt from here on (the saves, the final evaluation, the files) leaves a run that
        # --resume finishes (its final evaluation and files)
        _save_run(model, venv, model_path)
        saved = True
        agent = Agent(model, goal=goal)
        if isinstance(venv, VecNormalize):
            agent = Agent(model, load_normalizer(normalizer_path(model_path)), goal)
        venv.close()
        eval_env.close()

        final = evaluate(env, agent, episodes=final_episodes, seed=seed + FINAL_EVAL_SEED, env_kwargs=env_kwargs)
        if not curve or curve[-1]["env_steps"] < model.num_timesteps:
            curve.append(
                {
                    "env_steps": int(model.num_timesteps),
                    "wall_s": wall,
                    "mean_return": final.mean,
                    "std_return": final.std,
                    "success_rate": final.success_rate,
                    "final": 1.0,  # other episodes than the periodic evaluations': not a point of their line
                }
            )
        _write_curve(out / "curve.csv", curve)
        plot_curve(curve, out / "curve.png", f"{label}: {algo.upper()}")
        if video and (isinstance(env, str) or env.render_mode == "rgb_array"):
            record_gif(env, agent, out / "policy.gif", seed=seed, env_kwargs=env_kwargs)
        summary |= {"steps": int(model.num_timesteps), "wall_s": wall, "final_evaluation": final.as_dict()}
        _write_record(out, summary)
    except KeyboardInterrupt:
        if not saved:  # stopped in the save: once more, so the trained model is kept
            saved = _save_after_interrupt(model, venv, model_path)
        for env_ in (venv, eval_env):  # stopped before they were closed: a sharded env's workers too
            _close_quietly(env_)
        raise interrupted(wall, saved) from None
    return TrainResult(model_path, int(model.num_timesteps), wall, final, out, int(model.num_timesteps) - started)


__all__ = [
    "ALGOS",
    "CURVE_FIELDS",
    "FINAL_EVAL_SEED",
    "HYPERPARAMS",
    "Agent",
    "Evaluation",
    "SpaceMismatchError",
    "TrainResult",
    "TrainingInterrupted",
    "check_env_id",
    "check_run_folder",
    "evaluate",
    "her_wait",
    "hyperparams",
    "load_agent",
    "load_normalizer",
    "model_record",
    "normalizer_path",
    "plot_curve",
    "record_gif",
    "shipped_policies",
    "shipped_policy",
    "train_agent",
    "training_seed",
    "vector_env",
]
