"""PPO on the conditional bar: stiffness and support change every episode, and the policy sees them.

Run: python examples/bar_agent.py [--steps 50000] [--episodes 5] [--episode-steps 200] [--out DIR] [--no-progress]
(--out DIR saves DIR/bar_ppo.zip and the observation statistics it acts through, DIR/bar_ppo_vecnormalize.pkl;
`redsim eval-agent DIR/bar_ppo.zip RedSim/ConditionalBar-v0 --algo ppo --baselines` evaluates it again later).
Domain randomization comes from the conditional subspace f(z, c): each episode draws c (the right half's
stiffness factor and the support location), and c is the last two numbers of the observation. After
training, a plain Gymnasium loop runs the policy and prints each episode's condition, return, final distance
and success. Gymnasium warns that ConditionalBar-v0 is out of date: v1 is its cubature version, v0 steps every
element (the exact dynamics; README "Gymnasium environments"). main()'s defaults are the tiny budget the test suite
runs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecNormalize

import redsim  # noqa: F401  (registers the RedSim ids)
from redsim.envs.sb3 import SB3VecEnv
from redsim.trainers.agents import FINAL_EVAL_SEED, hyperparams

ENV_ID = "RedSim/ConditionalBar-v0"


def main(
    out: Path | None = None, steps: int = 128, episodes: int = 2, episode_steps: int = 20, progress: bool = False
) -> dict[str, float]:
    settings = hyperparams(ENV_ID, "ppo")
    n_envs = settings.pop("n_envs")
    if steps < 1000:  # the test budget: one short rollout
        n_envs, settings["n_steps"], settings["batch_size"], settings["n_epochs"] = 4, 32, 64, 2
    venv = SB3VecEnv.make(ENV_ID, num_envs=n_envs, max_episode_steps=episode_steps)
    venv = VecNormalize(venv, gamma=settings["gamma"], **settings.pop("normalize"))  # running obs/return mean, std
    model = PPO("MlpPolicy", venv, seed=0, **settings).learn(total_timesteps=steps, progress_bar=progress)
    venv.training = False
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        model.save(out / "bar_ppo.zip")
        venv.save(str(out / "bar_ppo_vecnormalize.pkl"))  # the policy acts on observations normalized by these

    env = gym.make(ENV_ID, max_episode_steps=episode_steps)
    structure = env.unwrapped.observation_structure  # {"z": 8, "z_dot": 8, ..., "condition": 2}
    conditions, distances, returns = [], [], []
    first = FINAL_EVAL_SEED  # seeds no training copy started from (SB3's are 0, 1, ...)
    for seed in range(first, first + episodes):
        obs, _ = env.reset(seed=seed)
        conditions.append(obs[-2:].copy())
        total, done = 0.0, False
        while not done:
            action = model.predict(venv.normalize_obs(obs), deterministic=True)[0]  # the policy sees normalized obs
            obs, reward, terminated, truncated, info = env.step(action)
            total += float(reward)
            done = terminated or truncated
        distances.append(info["distance"])
        returns.append(total)
        stiffness, support = conditions[-1]
        print(
            f"seed {seed}: stiffness x{stiffness:.2f}, support {support:.2f} m: return {total:.1f}, final distance "
            f"{info['distance']:.3f} m, success {bool(info['is_success'])} (random and scripted baselines: redsim "
            "eval-agent --baselines)"
        )
    env.close()
    return {
        "steps": model.num_timesteps,
        "budget": steps,
        "episodes": episodes,
        "observation_size": sum(structure.values()),
        "distinct_conditions": len({tuple(np.round(c, 6)) for c in conditions}),
        "mean_return": float(np.mean(returns)),
        "finite": float(np.isfinite(distances).all()),
    }


def check(result: dict[str, float]) -> None:
    """What this example must show: PPO ran its budget, each episode drew its own condition, nothing blew up."""
    assert result["steps"] >= result["budget"]
    assert result["observation_size"] == 22
    assert result["distinct_conditions"] == result["episodes"]
    assert result["finite"] == 1.0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="PPO on RedSim/ConditionalBar-v0")
    parser.add_argument("--steps", type=int, default=50_000, help="PPO's env steps (default 50000)")
    parser.add_argument("--episodes", type=int, default=5, help="episodes of the trained policy shown (default 5)")
    parser.add_argument("--episode-steps", type=int, default=200, help="steps per episode (default 200)")
    parser.add_argument("--out", type=Path, help="folder for the policy and its normalizer (default: not saved)")
    parser.add_argument("--no-progress", action="store_true", help="no SB3 progress bar while training")
    args = parser.parse_args()
    for flag, value in (
        ("--steps", args.steps),
        ("--episodes", args.episodes),
        ("--episode-steps", args.episode_steps),
    ):
        if value < 1:  # before training: --episode-steps -1 trained, then evaluated an episode that never ends
            parser.error(f"{flag} must be an integer >= 1, got {value}")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out} is a file, not a folder")
    try:
        check(main(args.out, args.steps, args.episodes, args.episode_steps, progress=not args.no_progress))
    except KeyboardInterrupt:
        print("interrupted; nothing was saved", file=sys.stderr)
        sys.exit(130)
