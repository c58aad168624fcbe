"""Build an env, or a vector env of copies, from any scene, subspace and task (the bodies of
:func:`redsim.envs.make` and :func:`redsim.envs.make_vec`)."""

from __future__ import annotations

import functools
import numbers
import os
import sys
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
from gymnasium.envs.registration import EnvSpec
from gymnasium.vector import AutoresetMode
from gymnasium.wrappers import TimeLimit
from torch import nn

from redsim.effects.external import Gravity
from redsim.envs.base import LatentEnv, Task, checkpoint_subspace
from redsim.envs.reach import HandleReach
from redsim.envs.sharded import ShardedVectorEnv
from redsim.envs.vector import LatentVectorEnv, vector_of
from redsim.scene import Scene

NO_LIMIT = sys.maxsize
""":class:`EpisodeLimit`'s length where Gymnasium's own ``TimeLimit`` around it holds the episode's (or none)."""


class EpisodeLimit(TimeLimit):
    """:func:`redsim.envs.make`'s episode length, which gives way to Gymnasium's where ``gym.make`` made the env:
    an id registered with ``max_episode_steps=N`` and no length in its ``kwargs`` ends its episodes where Gymnasium's
    ``TimeLimit`` ends them (N; M for ``gym.make(id, max_episode_steps=M)``; never for -1), as ``gym.make_vec``
    passes N to :func:`redsim.envs.make_vec`; 200 steps inside Gymnasium's length before. A length in the ``kwargs``
    holds in both, and an id registered with no length at all keeps make's 200, as make_vec does."""

    @property
    def _max_episode_steps(self) -> int:
        if self._resolved is None:
            spec = self.env.unwrapped.spec  # gym.make's, once the entry point has returned: its kwargs, no length
            if spec is None:  # made directly (or gym.make has not returned yet)
                return self._own_steps
            registered = gym.registry.get(spec.id)
            own = "max_episode_steps" in spec.kwargs or (
                registered is not None and registered.max_episode_steps is None
            )
            self._resolved = self._own_steps if own else NO_LIMIT
        return self._resolved

    @_max_episode_steps.setter
    def _max_episode_steps(self, steps: int) -> None:
        self._own_steps, self._resolved = steps, None

    @property
    def spec(self) -> EnvSpec | None:
        """As TimeLimit's, without a length where Gymnasium's ``TimeLimit`` holds it (no wrapper of its own)."""
        return self.env.spec if self._max_episode_steps == NO_LIMIT else super().spec


TASKS: dict[str, type[Task]] = {"reach": HandleReach}
"""Task names accepted by :func:`redsim.envs.make`."""

DEFAULT_FORCE_FRACTION = 0.5
"""A reach task on a user's scene gets max_force = this fraction of the scene's weight [N] (1 N without gravity)."""


def build(
    scene: Scene | str,
    subspace: Any,
    task: Task | str,
    *,
    max_episode_steps: int | None = 200,
    task_options: Mapping[str, Any] | None = None,
    **kwargs: Any,
) -> gym.Env:
    """See :func:`redsim.envs.make`."""
    from redsim import pretrained, scenes

    if max_episode_steps is not None and (
        isinstance(max_episode_steps, bool)
        or not isinstance(max_episode_steps, numbers.Integral)
        or not (max_episode_steps == -1 or max_episode_steps >= 1)
    ):
        raise ValueError(
            f"max_episode_steps must be None or -1 (no limit) or an integer >= 1, got {max_episode_steps!r}"
        )
    if not isinstance(scene, Scene | str):
        raise TypeError(f"scene must be a redsim.Scene or a catalog name, got {type(scene).__name__}")
    if not isinstance(task, Task | str):
        raise TypeError(f"task must be a redsim.envs.base.Task or a task name {sorted(TASKS)}, got {task!r:.60}")
    if isinstance(scene, str):
        name = scene
        scene = scenes.build(name)
        if subspace is None:
            subspace = pretrained.load(name, scene)
    if subspace is None:
        if scene.name not in pretrained.names():
            raise ValueError(f"scene {scene.name!r} has no shipped subspace: give one (a map or a checkpoint path)")
        subspace = pretrained.load(scene.name, scene)  # a catalog scene built with other parameters is refused
    if isinstance(subspace, nn.Module) and not hasattr(subspace, "latent_dim"):
        raise ValueError(
            f"the subspace {type(subspace).__name__} has no latent_dim: a map z [B, d] -> q [B, n] needs one "
            "(redsim's maps have it), or give a checkpoint path"
        )
    if not hasattr(subspace, "latent_dim"):
        if not isinstance(subspace, (str, os.PathLike)):
            fitted = hasattr(getattr(subspace, "subspace", None), "latent_dim")  # fit_subspace's FitResult
            raise TypeError(
                "subspace must be a map (an nn.Module with latent_dim) or a checkpoint path, got "
                + (f"a {type(subspace).__name__}: pass its .subspace" if fitted else f"{subspace!r:.80}")
            )
        subspace = checkpoint_subspace(subspace, scene)
    if isinstance(task, str):
        if task not in TASKS:
            raise ValueError(f"unknown task {task!r}; valid tasks: {sorted(TASKS)}")
        if not scene.handles:
            raise ValueError(f"scene {scene.name!r} has no handles for a {task!r} task")
        options = {"goal_handle": scene.handle_names[0], "max_force": default_force(scene), **dict(task_options or {})}
        task = TASKS[task](**options)
    elif task_options:
        raise ValueError("task_options only apply to a task given by name")
    env: gym.Env = LatentEnv(scene, subspace, task, **kwargs)
    return env if max_episode_steps in (None, -1) else EpisodeLimit(env, int(max_episode_steps))


def _bare(*, scene: Scene | str, subspace: Any, task: Task | str, **kwargs: Any) -> LatentEnv:
    """The env :func:`build` makes, without a TimeLimit (keyword arguments only: :func:`vector_of` may swap the
    subspace)."""
    return build(scene, subspace, task, max_episode_steps=None, **kwargs)


def build_vector(
    scene: Scene | str,
    subspace: Any = None,
    task: Task | str = "reach",
    *,
    num_envs: int = 1,
    max_episode_steps: int | None = 200,
    autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
    shards: int = 1,
    timeout: float | None = None,
    **kwargs: Any,
) -> LatentVectorEnv | ShardedVectorEnv:
    """See :func:`redsim.envs.make_vec`."""
    limit = None if max_episode_steps in (None, -1) else max_episode_steps
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, numbers.Integral) or limit < 1):
        raise ValueError(f"max_episode_steps must be None or -1 (no limit) or an integer >= 1, got {limit!r}")
    create = functools.partial(_bare, scene=scene, subspace=subspace, task=task, **kwargs)
    return vector_of(create, num_envs, None if limit is None else int(limit), autoreset_mode, shards, timeout)


def default_force(scene: Scene) -> float:
    """The reach task's default max force [N]: a fraction of the scene's weight under its gravity effect (found by
    type: a user's effect may be named "gravity"), 1 N without one."""
    gravity = next((e for e in scene.effects if isinstance(e, Gravity)), None)
    if gravity is None:
        return 1.0
    weight = float(gravity.masses.sum()) * float(gravity.acceleration.norm())
    return DEFAULT_FORCE_FRACTION * weight if weight > 0.0 else 1.0


__all__ = ["TASKS", "build"]
