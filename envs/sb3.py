"""A stable-baselines3 ``VecEnv`` over the native vector env (one batched step for all copies).

    >>> from stable_baselines3 import PPO
    >>> from redsim.envs.sb3 import SB3VecEnv
    >>> venv = SB3VecEnv.make("RedSim/MiniChain-v0", num_envs=16)
    >>> PPO("MlpPolicy", venv).learn(10_000)

SB3 resets a finished copy in the same step and expects its last observation in
``infos[i]["terminal_observation"]``, and ``infos[i]["TimeLimit.truncated"]`` on every step (as its
``DummyVecEnv`` gives them); the adapter runs the
vector env with ``AutoresetMode.SAME_STEP`` and translates. ``SB3VecEnv.make(id, num_envs=64, shards=2)``
steps the copies in 2 worker processes (:mod:`redsim.envs.sharded`). ``SB3VecEnv.make(id, num_envs=8, goal=True)``
gives the goal-conditioned env (:class:`redsim.envs.goal.GoalVectorObservation`) that SB3's ``HerReplayBuffer``
relabels through ``env_method("compute_reward", ...)``, and ``SB3VecEnv.make(id, num_envs=8, pixels=True)`` observes
each copy's picture (:class:`redsim.envs.pixels.PixelVectorObservation`, for ``CnnPolicy``).
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env import VecEnv

from redsim.envs.goal import GoalVectorObservation
from redsim.envs.pixels import PixelVectorObservation
from redsim.envs.sharded import ShardedVectorEnv
from redsim.envs.vector import LatentVectorEnv
from redsim.envs.vector_api import PER_COPY_CALLS, SHARED_METHODS

PIXEL_SIDE = 84
"""Default width and height [px] of ``SB3VecEnv.make(..., pixels=True)``'s observations (Atari's 84 x 84, SB3's
``CnnPolicy`` default input): at the envs' own 480 x 480 a PPO rollout buffer of 2048 steps x 8 copies holds
2048 * 8 * 480 * 480 * 3 float32 values, 42 GiB."""


class SB3VecEnv(VecEnv):
    """SB3's VecEnv interface over a :class:`LatentVectorEnv` or :class:`ShardedVectorEnv`, or a Gymnasium vector
    wrapper of one (e.g. :class:`GoalVectorObservation`), in ``AutoresetMode.SAME_STEP``.

    The copies share one simulation: ``get_attr`` reads the env's (the same for every copy), ``set_attr`` is
    refused, and ``env_method`` answers the per-copy methods of the vector env's ``call``
    (:data:`~redsim.envs.vector_api.PER_COPY_CALLS`: ``get_state``, ``configuration``, ``render``, ``trimeshes``)
    and the :data:`SHARED_METHODS` the vector env defines.
    An ended copy's info carries SB3 ``Monitor``'s ``"episode"`` (``r`` return, ``l`` length, ``t`` seconds since
    this env was made), so SB3 logs ``rollout/ep_rew_mean`` and its evaluations read returns as from a Monitor
    (``env_is_wrapped(Monitor)`` is True); an ``"episode"`` from a wrapper inside is kept.

    Args:
        venv: The vector env.

    Raises:
        ValueError: a vector env in another autoreset mode.
    """

    def __init__(self, venv: LatentVectorEnv | ShardedVectorEnv | gym.vector.VectorWrapper) -> None:
        if venv.metadata["autoreset_mode"] != AutoresetMode.SAME_STEP:
            raise ValueError("SB3VecEnv needs a LatentVectorEnv with autoreset_mode=AutoresetMode.SAME_STEP")
        self.venv = venv
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)
        self.render_mode = venv.render_mode
        # the env's frame rate, as DummyVecEnv forwards it (SB3's VecVideoRecorder reads it, else 30 fps)
        self.metadata = {**self.metadata, "render_fps": venv.metadata["render_fps"]}
        self._actions: np.ndarray | None = None
        self._returns = np.zeros(self.num_envs)
        self._lengths = np.zeros(self.num_envs, dtype=np.int64)
        self._start = time.time()

    @classmethod
    def make(
        cls,
        env_id: str,
        num_envs: int,
        *,
        goal: bool | Mapping[str, Any] = False,
        pixels: bool | Mapping[str, Any] = False,
        **kwargs: Any,
    ) -> SB3VecEnv:
        """``gymnasium.make_vec(env_id, num_envs, vectorization_mode="vector_entry_point", SAME_STEP)`` wrapped.

        Args:
            env_id: A registered id (``"RedSim/Chain-v0"``).
            num_envs: N, the copies stepped in one batched solve.
            goal: Wrap the vector env in :class:`GoalVectorObservation` (a reach env's dict observations, for HER);
                a mapping ({} included): with those arguments (``goal={"control_cost": True}``).
            pixels: Observe each copy's picture (:class:`redsim.envs.pixels.PixelVectorObservation`, uint8
                [H, W, 3], ``render_mode="rgb_array"`` is set; ``width=``/``height=`` size it, :data:`PIXEL_SIDE`
                each by default, not the env's 480); a mapping (``{}`` included): with those arguments
                (``pixels={"grayscale": True}``: [H, W, 1], for SB3's ``VecFrameStack`` and ``CnnPolicy``).
            **kwargs: Passed to ``gymnasium.make_vec``: the env's arguments, ``max_episode_steps``, ``shards``
                (worker processes, :class:`redsim.envs.sharded.ShardedVectorEnv`) and their ``timeout`` [s].

        Raises:
            TypeError: ``goal`` with an env that is not a reach env, or with ``shards`` > 1 (the vector env is
                closed first, workers included); ``goal`` or ``pixels`` neither a bool nor a mapping (nothing is
                built).
            ValueError: ``goal`` and ``pixels`` together, or ``pixels`` with a ``render_mode`` other than "rgb_array".
        """
        for name, value, wrapper, example in (
            ("goal", goal, "GoalVectorObservation", "{'control_cost': True}"),
            ("pixels", pixels, "PixelVectorObservation", "{'grayscale': True}"),
        ):
            if not isinstance(value, bool | np.bool_ | Mapping):
                raise TypeError(
                    f"SB3VecEnv.make: {name} must be True, False or a mapping of {wrapper}'s arguments "
                    f"({name}={example}), got {value!r}"
                )
        # a mapping, {} included, asks for the wrapper (with those arguments)
        goal = goal if isinstance(goal, Mapping) else bool(goal)
        pixels = pixels if isinstance(pixels, Mapping) else bool(pixels)
        if pixels is not False:
            if goal is not False:
                raise ValueError("SB3VecEnv.make: goal observations are vectors; pixels=True makes them pictures")
            if kwargs.setdefault("render_mode", "rgb_array") != "rgb_array":
                raise ValueError(f"pixels=True draws render_mode='rgb_array' frames, got {kwargs['render_mode']!r}")
            kwargs.setdefault("width", PIXEL_SIDE)
            kwargs.setdefault("height", PIXEL_SIDE)
        venv = gym.make_vec(
            env_id,
            num_envs=num_envs,
            vectorization_mode="vector_entry_point",
            # pixels: the wrapper autoresets, after drawing an ended copy's last picture
            autoreset_mode=AutoresetMode.DISABLED if pixels is not False else AutoresetMode.SAME_STEP,
            **kwargs,
        )
        if pixels is not False:
            try:
                options = pixels if isinstance(pixels, Mapping) else {}
                return cls(PixelVectorObservation(venv, **options, autoreset_mode=AutoresetMode.SAME_STEP))
            except (TypeError, ValueError):
                venv.close()
                raise
        if goal is not False:
            try:
                venv = GoalVectorObservation(venv, **(goal if isinstance(goal, Mapping) else {}))
            except TypeError:
                venv.close()
                raise
        return cls(venv)  # type: ignore[arg-type]

    def reset(self) -> np.ndarray:
        """Reset every copy with the seed and options given by ``seed()`` / ``set_options()`` (one for all: the
        copies are reset together; per-copy options that differ are refused)."""
        seed = self._seeds[0] if all(s is not None for s in self._seeds) else None
        options = [dict(o or {}) for o in self._options]
        if any(o != options[0] for o in options):
            raise ValueError("SB3VecEnv resets its copies together: give every copy the same options (set_options)")
        obs, info = self.venv.reset(seed=seed, options=options[0] or None)
        restarted = options[0].get("reset_mask", slice(None))  # the copies that start a new episode
        self._returns[restarted], self._lengths[restarted] = 0.0, 0
        self.reset_infos = [_info_row(info, i) for i in range(self.num_envs)]
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        obs, reward, terminated, truncated, info = self.venv.step(self._actions)
        done = terminated | truncated
        self._returns += reward
        self._lengths += 1
        infos: list[dict[str, Any]] = []
        for i in range(self.num_envs):
            row = _info_row(info, i)
            if done[i]:  # the step's own info (final_info), and what outer wrappers added (e.g. "episode")
                final = _info_row(info["final_info"], i)
                # the top-level values of a key the ended step also reports are the new episode's reset info
                self.reset_infos[i] = {k: row.pop(k) for k in list(row) if k in final}
                row = {**final, **row}
                row["terminal_observation"] = info["final_obs"][i]
                episode = {"r": float(self._returns[i]), "l": int(self._lengths[i]), "t": time.time() - self._start}
                row.setdefault("episode", episode)
                self._returns[i], self._lengths[i] = 0.0, 0
            # on every step, as SB3's DummyVecEnv and SubprocVecEnv put it (a callback reads it without a KeyError)
            row["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
            infos.append(row)
        return obs, reward.astype(np.float32), done, infos

    def close(self) -> None:
        self.venv.close()

    def get_images(self) -> Sequence[np.ndarray | None]:
        frames = self.venv.render()
        return [None] * self.num_envs if frames is None else list(frames)

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        """A copy's ``observation_space`` / ``action_space`` (the vector env's single ones), a shared method
        (:data:`SHARED_METHODS`), or else the setting of the env every copy runs, as the vector env's ``get_attr``
        answers it (an attribute holding a copy's state, e.g. ``np_random``, is an AttributeError)."""
        if attr_name in ("observation_space", "action_space"):
            value = getattr(self.venv, f"single_{attr_name}")
        elif attr_name in SHARED_METHODS:
            value = self._shared(attr_name)
        else:
            value = self.venv.unwrapped.get_attr(attr_name)[0]
        return [value for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        raise AttributeError(
            f"cannot set {attr_name!r} per copy: the copies of a SB3VecEnv share one simulation and its settings; "
            "make it with the setting instead (SB3VecEnv.make(ENV_ID, num_envs=N, KEY=VALUE))"
        )

    def env_method(self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any) -> list[Any]:
        """Each listed copy's answer to ``method_name``: a per-copy method of the vector env's ``call``
        (:data:`~redsim.envs.vector_api.PER_COPY_CALLS`, e.g. ``env_method("get_state")``; it answers every copy
        and the listed ones are kept; asked of the outermost layer with a ``call``, :meth:`_layers`), or a method
        of :data:`SHARED_METHODS`, called once for all.

        Raises:
            AttributeError: another name, a shared method the vector env does not define (the copies share one
                simulation and have no other methods), or a per-copy method where no layer has a ``call``.
            TypeError: arguments to a per-copy method (they take none).
        """
        if method_name in PER_COPY_CALLS:
            layers = list(self._layers())
            call = next((layer.call for layer in layers if hasattr(layer, "call")), None)
            if call is None:  # a user's own vector env inside, without Gymnasium's SyncVectorEnv.call
                chain = " around ".join(type(layer).__name__ for layer in layers)
                raise AttributeError(
                    f"SB3VecEnv.env_method({method_name!r}) asks the vector env's call(name), and no layer of "
                    f"{chain} defines call"
                )
            answers = call(method_name, *method_args, **method_kwargs)
            return [answers[i] for i in self._get_indices(indices)]
        result = self._shared(method_name)(*method_args, **method_kwargs)
        return [result for _ in self._get_indices(indices)]

    def _layers(self) -> Iterator[Any]:
        """The vector wrappers around the vector env, outermost first, then the vector env. Gymnasium's
        ``VectorWrapper`` passes on neither ``call`` nor a goal env's ``compute_reward``: ``env_method`` asks the
        outermost layer that defines the method, so a user's own wrapper outside works and an override in it wins."""
        layer = self.venv
        yield layer
        while isinstance(layer, gym.vector.VectorWrapper):
            layer = layer.env
            yield layer

    def _shared(self, name: str) -> Any:
        """The shared method ``name`` of the vector env or of a vector wrapper around it (the outermost).

        Raises:
            AttributeError: not one of :data:`SHARED_METHODS`, or none defines it.
        """
        if name in SHARED_METHODS:
            for layer in self._layers():
                method = getattr(layer, name, None)
                if method is not None:
                    return method
        raise AttributeError(
            f"SB3VecEnv.env_method answers {', '.join(PER_COPY_CALLS)} copy by copy and {', '.join(SHARED_METHODS)} "
            f"where the vector env or a wrapper in it defines them (the copies share one simulation and have no other "
            f"methods), not {name!r}"
        )

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: Any = None) -> list[bool]:
        """True for SB3's ``Monitor`` (the episode statistics come with the infos), else False."""
        from stable_baselines3.common.monitor import Monitor

        return [wrapper_class is Monitor for _ in self._get_indices(indices)]


def _info_row(info: Mapping[str, Any], i: int) -> dict[str, Any]:
    """Copy i's entries of a Gymnasium vector info (the keys whose ``_key`` mask, if any, holds it; nested dicts,
    such as a vector ``RecordEpisodeStatistics``'s ``"episode"``, row by row), without ``final_obs``/``final_info``."""
    row: dict[str, Any] = {}
    for key, value in info.items():
        if key.startswith("_") or key in ("final_obs", "final_info"):
            continue
        mask = info.get(f"_{key}")
        if mask is not None and not mask[i]:
            continue
        row[key] = _info_row(value, i) if isinstance(value, Mapping) else value[i]
    return row


__all__ = ["PIXEL_SIDE", "SHARED_METHODS", "SB3VecEnv"]
