"""SAC with hindsight experience replay on a reach env, against SAC alone with the same budget and settings.

Run: python examples/her_agent.py [--env RedSim/MiniChain-v0] [--steps 10000] [--episodes 20] [--seed 0]
[--num-envs 1] [--episode-steps N] [--out DIR] [--no-progress] (main()'s defaults are the tiny budget the test suite
runs).
Both agents see the goal-conditioned env
(:class:`redsim.envs.goal.GoalObservation`: dict observations, a reward from the goals alone); the only
difference is the replay buffer. ``--num-envs N`` > 1 collects from N copies in the native vector env
(:class:`redsim.envs.goal.GoalVectorObservation` through :class:`redsim.envs.sb3.SB3VecEnv`: one batched
solve for all N) with N gradient steps per vector step, so that the updates per transition stay those of one
env. Each is then evaluated on the same seeded episodes, seeds ``seed + FINAL_EVAL_SEED + i`` (that no training copy
started from, as ``redsim train-agent``'s final evaluation): mean return (the wrapper's reward) and the success rate
(``info["is_success"]`` at the last step).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3 import SAC, HerReplayBuffer
from stable_baselines3.common.env_util import make_vec_env

import redsim  # noqa: F401  (registers the ids)
from redsim.envs.goal import GoalObservation
from redsim.envs.sb3 import SB3VecEnv
from redsim.trainers.agents import FINAL_EVAL_SEED, her_wait

SETTINGS: dict[str, Any] = {
    "learning_rate": 1e-3,
    "gamma": 0.98,
    "batch_size": 256,
    "policy_kwargs": {"net_arch": [64, 64]},
}
"""SAC's settings for both agents (those of redsim's SAC table, one env)."""


def train(
    env_id: str,
    steps: int,
    her: bool,
    env_kwargs: dict[str, Any],
    seed: int = 0,
    num_envs: int = 1,
    progress: bool = False,
) -> tuple[SAC, float]:
    """SAC (with HER, or with SB3's plain replay buffer) trained ``steps`` env steps over ``num_envs`` copies
    (module doc); and its wall time [s]."""
    if num_envs == 1:
        # a function making the goal env, so SB3's Monitor goes outside it and logs the goal reward SAC trains on
        venv = make_vec_env(lambda: GoalObservation(gym.make(env_id, **env_kwargs)), n_envs=1, seed=seed)
    else:
        venv = SB3VecEnv.make(env_id, num_envs, goal=True, **env_kwargs)
    replay = {"replay_buffer_class": HerReplayBuffer, "replay_buffer_kwargs": {"n_sampled_goal": 4}} if her else {}
    ended = episodes_ended(env_id, steps, env_kwargs, num_envs)
    starts = max(min(max(1000, ended), steps // 2), ended)
    model = SAC(
        "MultiInputPolicy",
        venv,
        learning_starts=starts,
        gradient_steps=num_envs,
        seed=seed,
        **SETTINGS,
        **replay,
    )
    start = time.perf_counter()
    model.learn(total_timesteps=steps, progress_bar=progress)
    return model, time.perf_counter() - start


def episodes_ended(env_id: str, steps: int, env_kwargs: dict[str, Any], num_envs: int) -> int:
    """SAC's ``learning_starts`` for its first update to come once every copy has ended an episode (HER samples
    only ended episodes; :func:`redsim.trainers.agents.her_wait`), refusing a budget that does not reach it."""
    episode = env_kwargs.get("max_episode_steps", gym.spec(env_id).max_episode_steps)
    if episode is None or episode < 1:  # -1 (no limit) trained, then evaluated an episode that never ends
        raise ValueError(f"HER needs episodes that end: --episode-steps must be >= 1, got {episode}")
    if num_envs < 1:
        raise ValueError(f"--num-envs must be >= 1, got {num_envs}")
    wait = her_wait(num_envs, episode)
    if steps <= wait:
        raise ValueError(
            f"{steps} steps are not enough: every one of the {num_envs} copies has ended an episode at {wait + 1} "
            f"steps, where learning starts (give {wait + 1} or more)"
        )
    return wait


def evaluate(model: SAC, env_id: str, seeds: range, env_kwargs: dict[str, Any]) -> dict[str, float]:
    """Mean and std of the return and the success rate over the episodes reset with ``seeds`` (deterministic)."""
    env = GoalObservation(gym.make(env_id, **env_kwargs))
    returns, successes = [], []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, info = env.step(action)
            total += reward
            done = terminated or truncated
        returns.append(total)
        successes.append(bool(info["is_success"]))
    return {"mean": float(np.mean(returns)), "std": float(np.std(returns)), "success": float(np.mean(successes))}


def main(
    out: Path | None = None,
    env_id: str = "RedSim/MiniChain-v0",
    steps: int = 50,
    episodes: int = 2,
    episode_steps: int | None = 20,
    seed: int = 0,
    num_envs: int = 1,
    progress: bool = False,
) -> dict[str, Any]:
    env_kwargs = {} if episode_steps is None else {"max_episode_steps": episode_steps}
    seeds = range(seed + FINAL_EVAL_SEED, seed + FINAL_EVAL_SEED + episodes)  # no training copy started from these
    result: dict[str, Any] = {"env": env_id, "steps": steps, "seed": seed, "num_envs": num_envs}
    episodes_ended(env_id, steps, env_kwargs, num_envs)  # before the plain agent trains, not after
    for name, her in (("sac", False), ("sac_her", True)):
        model, wall = train(env_id, steps, her, env_kwargs, seed, num_envs, progress)
        scores = evaluate(model, env_id, seeds, env_kwargs)
        result[name] = {**scores, "wall_s": wall, "timesteps": model.num_timesteps}
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
            model.save(out / f"{name}.zip")
        print(
            f"{name:<8} {steps} steps in {wall:6.0f} s: return {scores['mean']:8.2f} ± {scores['std']:6.2f}   "
            f"success {100 * scores['success']:.0f}% over {episodes} episodes (seeds {seeds.start}-{seeds.stop - 1})"
        )
    return result


def check(result: dict[str, Any]) -> None:
    """What this example must show: both agents trained their budget and scored finite returns."""
    for name in ("sac", "sac_her"):
        assert result[name]["timesteps"] >= result["steps"]
        assert np.isfinite(result[name]["mean"]) and 0.0 <= result[name]["success"] <= 1.0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="SAC with and without HER on a goal-conditioned reach env")
    parser.add_argument("--env", default="RedSim/MiniChain-v0", help="a reach env id (default RedSim/MiniChain-v0)")
    parser.add_argument("--steps", type=int, default=10_000, help="env steps per agent (default 10000)")
    parser.add_argument("--episodes", type=int, default=20, help="evaluation episodes per agent (default 20)")
    parser.add_argument(
        "--seed", type=int, default=0, help="seeds both agents' networks, exploration and envs (default 0)"
    )
    parser.add_argument(
        "--num-envs", type=int, default=1, help="copies in the native vector env (default 1; module doc)"
    )
    parser.add_argument("--episode-steps", type=int, help="steps per episode (default: the env's limit)")
    parser.add_argument("--out", type=Path, help="folder for sac.zip and sac_her.zip (default: not saved)")
    parser.add_argument("--no-progress", action="store_true", help="no SB3 progress bar while training")
    args = parser.parse_args()
    limit = {} if args.episode_steps is None else {"max_episode_steps": args.episode_steps}
    try:  # a budget that ends no episode, an env without a goal, nothing to evaluate
        episodes_ended(args.env, args.steps, limit, args.num_envs)
        GoalObservation(gym.make(args.env, **limit)).close()
        if args.episodes < 1:
            raise ValueError(f"--episodes must be >= 1, got {args.episodes}")
    except (ValueError, TypeError, gym.error.Error) as err:
        parser.error(str(err))
    try:
        main(
            args.out,
            args.env,
            args.steps,
            args.episodes,
            args.episode_steps,
            seed=args.seed,
            num_envs=args.num_envs,
            progress=not args.no_progress,
        )
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
