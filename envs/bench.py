"""What `redsim bench envs` measures: env steps per second, single and vectorized, against the full-space step.

For each env id, in one process, side by side: construction time, then the median wall time of
an env step of the single env (random actions) and of the native vector env at each batch size,
as env steps/s (copies x steps / s) and simulated seconds per wall second (env steps/s x the
env's dt). For scale, the same scene's float64 full-space implicit-Euler step
(:class:`redsim.integrators.ImplicitEuler` over :class:`FullSpace`, Newton, under a random load of
the env's force size) is timed too. With ``mujoco`` installed the MuJoCo anchors RL users know
are added; without it they are reported as not installed.
"""

from __future__ import annotations

import importlib.util
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch

DEFAULT_BATCHES = (16, 64, 256)


def _median_time(call: Callable[[], Any], repeats: int, budget: float) -> tuple[float, int]:
    """Median wall time [s] of ``call`` over up to ``repeats`` calls (fewer once ``budget`` seconds are spent)."""
    times: list[float] = []
    spent = 0.0
    while len(times) < repeats and (not times or spent < budget):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
        spent += times[-1]
    return statistics.median(times), len(times)


def _full_space_step(env: Any, repeats: int, budget: float, rng: np.random.Generator) -> dict[str, Any]:
    """Median wall time of one float64 full-space step of the env's scene from rest, under one random load."""
    from redsim.integrators import FullSpace, ImplicitEuler

    sim = env.sim
    scene = sim.source_scene.to(dtype=torch.float64)
    integrator = ImplicitEuler(FullSpace(scene), sim.dt / sim.frame_skip, minimizer="newton", tol=1e-8, max_iter=50)
    q0 = sim.positions(sim.z[:1])[0].to(torch.float64)
    state = integrator.initial_state(q0)
    action = rng.uniform(-1.0, 1.0, env.action_space.shape).astype(np.float32)
    loads = sim.task.loads(torch.as_tensor(action[None], dtype=sim.torch_dtype), sim.params)[0].to(torch.float64)
    holder = {"state": state, "converged": True}

    def call() -> None:
        holder["state"], info = integrator.step(holder["state"], loads.cpu())
        holder["converged"] = holder["converged"] and info.converged

    seconds, count = _median_time(call, repeats, budget)
    return {"step_s": seconds * sim.frame_skip, "repeats": count, "converged": holder["converged"]}


def bench_env(
    env_id: str,
    *,
    batches: Sequence[int] = DEFAULT_BATCHES,
    steps: int = 20,
    warmup: int = 3,
    budget: float = 20.0,
    full_space: bool = True,
    seed: int = 0,
    **env_kwargs: Any,
) -> dict[str, Any]:
    """Timings of one env id (module doc).

    Args:
        env_id: A registered id.
        batches: Vector env sizes.
        steps: Timed steps per configuration (fewer once ``budget`` seconds are spent).
        warmup: Untimed steps first.
        budget: Seconds of timing per configuration.
        full_space: Also time the scene's full-space step.
        seed: Seeds resets and actions.
        **env_kwargs: Passed to ``gym.make``/``gym.make_vec``.

    Returns:
        ``id``, ``n``, ``d``, ``action_size``, ``observation_size``, ``dt`` [s], ``make_s``,
        ``single`` and ``vector`` (per batch) with ``env_steps_per_s`` and ``sim_s_per_wall_s``,
        ``full_space`` (``step_s``, ``sim_s_per_wall_s``) or None.
    """
    rng = np.random.default_rng(seed)
    start = time.perf_counter()
    env = gym.make(env_id, **env_kwargs).unwrapped
    make_s = time.perf_counter() - start
    env.reset(seed=seed)
    dt = env.dt

    def single_step() -> None:
        _, _, terminated, _, _ = env.step(env.action_space.sample())
        if terminated:
            env.reset()

    env.action_space.seed(seed)
    for _ in range(warmup):
        single_step()
    seconds, count = _median_time(single_step, steps, budget)
    row: dict[str, Any] = {
        "id": env_id,
        "n": env.sim.scene.free_dof_count,
        "d": env.sim.latent_dim,
        "action_size": int(env.action_space.shape[0]),
        "observation_size": int(env.observation_space.shape[0]),
        "dt": dt,
        "make_s": make_s,
        "single": {"env_steps_per_s": 1.0 / seconds, "sim_s_per_wall_s": dt / seconds, "repeats": count},
        "vector": {},
    }
    for batch in batches:
        venv = gym.make_vec(env_id, num_envs=int(batch), vectorization_mode="vector_entry_point", **env_kwargs)
        venv.reset(seed=seed)
        actions = rng.uniform(-1.0, 1.0, (max(steps, 1) + warmup, *venv.action_space.shape)).astype(np.float32)
        cursor = iter(actions)

        def vector_step(venv: Any = venv, cursor: Any = cursor) -> None:
            venv.step(next(cursor))

        for _ in range(warmup):
            vector_step()
        seconds, count = _median_time(vector_step, steps, budget)
        row["vector"][int(batch)] = {
            "env_steps_per_s": batch / seconds,
            "sim_s_per_wall_s": batch * dt / seconds,
            "repeats": count,
        }
        venv.close()
    row["full_space"] = None
    if full_space:
        full = _full_space_step(env, max(2, steps // 5), budget, rng)
        full["sim_s_per_wall_s"] = dt / full["step_s"]
        row["full_space"] = full
    env.close()
    return row


def mujoco_anchors(steps: int = 200) -> dict[str, Any]:
    """Env steps/s of MuJoCo's ``HalfCheetah-v5`` (single env) where ``mujoco`` is installed, else a reason."""
    if importlib.util.find_spec("mujoco") is None:
        return {"available": False, "reason": "mujoco is not installed (pip install mujoco)"}
    env = gym.make("HalfCheetah-v5")
    env.reset(seed=0)
    start = time.perf_counter()
    for _ in range(steps):
        env.step(env.action_space.sample())
    seconds = (time.perf_counter() - start) / steps
    dt = float(env.unwrapped.dt)
    env.close()
    return {
        "available": True,
        "HalfCheetah-v5": {"env_steps_per_s": 1.0 / seconds, "sim_s_per_wall_s": dt / seconds},
    }


__all__ = ["DEFAULT_BATCHES", "bench_env", "mujoco_anchors"]
