"""Gymnasium environments over latent subspaces: the ``RedSim/...-v0`` suite, registered lazily.

``import redsim`` registers every id (string entry points: nothing heavy is imported, no
checkpoint is loaded until an env is made), so these all work::

    import gymnasium as gym, redsim
    env = gym.make("RedSim/Chain-v0", render_mode="rgb_array")
    venv = gym.make_vec("RedSim/Chain-v0", num_envs=64, vectorization_mode="vector_entry_point")
    env = gym.make("redsim:RedSim/Chain-v0")      # without importing redsim first

:func:`make` turns any scene + subspace + task into an env (a user's own mesh included).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

ENVS: dict[str, tuple[str, str, int, dict[str, Any]]] = {
    "RedSim/Chain-v0": ("chain", "ChainEnv", 300, {}),
    "RedSim/MiniChain-v0": ("mini_chain", "MiniChainEnv", 200, {}),
    "RedSim/ClothBall-v0": ("cloth_ball", "ClothBallEnv", 200, {}),
    "RedSim/ClothBall-v1": (
        "cloth_ball",
        "ClothBallEnv",
        200,
        {"cubature": "lean"},
    ),
    "RedSim/HangingCloth-v0": ("hanging_cloth", "HangingClothEnv", 200, {}),
    "RedSim/HangingCloth-v1": (
        "hanging_cloth",
        "HangingClothEnv",
        200,
        {"targets": "held", "target_spread": 0.8, "cubature": True},
    ),
    "RedSim/HangingCloth-v2": (
        "hanging_cloth",
        "HangingClothEnv",
        200,
        {"targets": "held", "target_spread": 0.8, "cubature": "lean"},
    ),
    "RedSim/ConditionalBar-v0": ("conditional_bar", "ConditionalBarEnv", 200, {}),
    "RedSim/ConditionalBar-v1": ("conditional_bar", "ConditionalBarEnv", 200, {"cubature": True}),
    "RedSim/Klann-v0": ("klann", "KlannEnv", 300, {}),
    "RedSim/Stewart-v0": ("stewart", "StewartEnv", 200, {}),
    "RedSim/BistableBar-v0": ("bistable_bar", "BistableBarEnv", 200, {}),
    "RedSim/BistableBar-v1": ("bistable_bar", "BistableBarEnv", 200, {"max_force": 40.0}),
}
"""id -> (module in redsim.envs, class, max_episode_steps, the id's keyword arguments of the class)."""


def register_envs() -> None:
    """Register every id of :data:`ENVS` with Gymnasium (idempotent)."""
    for env_id, (module, cls, steps, kwargs) in ENVS.items():
        if env_id in gym.registry:
            continue
        gym.register(
            id=env_id,
            entry_point=f"redsim.envs.{module}:{cls}",
            vector_entry_point=f"redsim.envs.{module}:make_vec",
            max_episode_steps=steps,
            kwargs=dict(kwargs),
        )


def ids() -> list[str]:
    """The registered ``RedSim/...`` ids."""
    return list(ENVS)


def make(
    scene: Any, subspace: Any = None, task: Any = "reach", *, max_episode_steps: int | None = 200, **kwargs: Any
) -> gym.Env:
    """An env from any scene, subspace and task.

    Args:
        scene: A :class:`redsim.Scene`, or a catalog name.
        subspace: Its map (an ``nn.Module``), a checkpoint path, or None for the shipped one
            (catalog scenes at their default parameters only).
        task: A :class:`redsim.envs.base.Task`, or ``"reach"``: push the scene's first handle
            to targets drawn from the subspace (:class:`redsim.envs.reach.HandleReach`);
            give its arguments as ``task_options`` (e.g. ``{"goal_handle": "tip", "targets": "held"}``;
            ``max_force`` [N] defaults to half the scene's weight, or 1 N without gravity). The
            observation's blocks: ``env.unwrapped.observation_structure``.
        max_episode_steps: Wrap in a ``TimeLimit`` of this many steps (None or -1: no limit, no wrapper; -1 as
            ``gym.make`` and the vector envs read it). Registered as an entry point (``gym.register(id,
            entry_point="redsim.envs:make", kwargs={...}, max_episode_steps=N)``), the spec's N replaces this
            default, as ``gym.make_vec`` gives N to :func:`make_vec`; a length in ``kwargs`` holds in both
            (:class:`redsim.envs.factory.EpisodeLimit`).
        **kwargs: :class:`redsim.envs.base.LatentEnv` arguments, plus ``task_options`` (dict).

    Raises:
        ValueError: an unknown task name, scene or handle, a subspace of the wrong size or without ``latent_dim``,
            a catalog scene without a shipped subspace and none given, or a bad ``max_episode_steps``.
        redsim.subspace.CheckpointError: the subspace was fitted to another scene.
        TypeError: a scene or task of another type.
    """
    from redsim.envs.factory import build

    return build(scene, subspace, task, max_episode_steps=max_episode_steps, **kwargs)


def make_vec(
    scene: Any,
    subspace: Any = None,
    task: Any = "reach",
    *,
    num_envs: int = 1,
    max_episode_steps: int | None = 200,
    autoreset_mode: Any = None,
    shards: int = 1,
    timeout: float | None = None,
    **kwargs: Any,
) -> Any:
    """``num_envs`` copies of ``make(scene, subspace, task, **kwargs)`` stepped in one batched solve: a
    :class:`redsim.envs.vector.LatentVectorEnv`, or with ``shards`` P > 1 a
    :class:`redsim.envs.sharded.ShardedVectorEnv` of P worker processes (as a registered id's vector env).

    It is the ``vector_entry_point`` of a user's own id: register both entry points (``gym.register("MyRod-v0",
    entry_point="redsim.envs:make", vector_entry_point="redsim.envs:make_vec", kwargs={"scene": scene, "subspace":
    "subspaces/part.pt"}, max_episode_steps=250)``), then ``gym.make_vec("MyRod-v0", num_envs=N,
    vectorization_mode="vector_entry_point")``: Gymnasium passes the spec's length here, and :func:`make` takes it
    too, so the single env and the copies end their episodes alike (a length in ``kwargs`` holds in both). Give the
    length one way: with ``"max_episode_steps": None`` in ``kwargs`` and N in the spec, ``gym.make`` still wraps
    Gymnasium's ``TimeLimit(N)`` while the copies here have no limit.

    Args:
        scene, subspace, task: As :func:`make`'s (``task_options`` among ``kwargs``).
        num_envs: N.
        max_episode_steps: Each copy's episode length (None or -1: no limit).
        autoreset_mode: Gymnasium's ``AutoresetMode`` (None: ``NEXT_STEP``).
        shards: Worker processes (1: all copies in this process).
        timeout: With ``shards`` > 1, seconds each request waits for the workers' answers before the env closes
            and raises :class:`redsim.envs.sharded.ShardTimeoutError` (None: wait for ever).
        **kwargs: :class:`redsim.envs.base.LatentEnv` arguments, plus ``task_options`` (dict).

    Raises:
        ValueError, TypeError, redsim.subspace.CheckpointError: as :func:`make`, and a bad N, mode, shard count or
            timeout.
    """
    from gymnasium.vector import AutoresetMode

    from redsim.envs.factory import build_vector

    mode = AutoresetMode.NEXT_STEP if autoreset_mode is None else autoreset_mode
    return build_vector(
        scene,
        subspace,
        task,
        num_envs=num_envs,
        max_episode_steps=max_episode_steps,
        autoreset_mode=mode,
        shards=shards,
        timeout=timeout,
        **kwargs,
    )


register_envs()

__all__ = ["ENVS", "ids", "make", "make_vec", "register_envs"]
