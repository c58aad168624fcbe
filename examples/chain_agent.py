"""Train SAC to push the end of a chain to random targets; compare it with a random policy and the PI controller.

Run: python examples/chain_agent.py [--env RedSim/Chain-v0] [--steps 30000] [--episodes 20] [--episode-steps N]
[--out DIR] [--no-progress] (main()'s defaults are the tiny budget the test suite runs; MiniChain-v0 is the fast
two-link chain; SB3's progress bar shows unless --no-progress;
--out DIR saves DIR/chain_sac.zip and the observation statistics it acts through, DIR/chain_sac_vecnormalize.pkl;
`redsim eval-agent DIR/chain_sac.zip ENV_ID --algo sac --baselines` evaluates it again later).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from stable_baselines3 import SAC
from stable_baselines3.common.vec_env import VecNormalize

from redsim.envs.sb3 import SB3VecEnv
from redsim.trainers.agents import FINAL_EVAL_SEED, Agent, evaluate, hyperparams


def main(
    out: Path | None = None,
    env_id: str = "RedSim/MiniChain-v0",
    steps: int = 200,
    episodes: int = 4,
    episode_steps: int | None = 30,
    progress: bool = False,
) -> dict[str, float]:
    settings = hyperparams(env_id, "sac")  # the rl-zoo style table of redsim.trainers.agents
    venv = SB3VecEnv.make(env_id, num_envs=settings.pop("n_envs"))  # one batched latent step for all copies
    venv = VecNormalize(venv, gamma=settings["gamma"], **settings.pop("normalize"))  # running obs mean/std
    settings["learning_starts"] = min(settings["learning_starts"], steps // 2)
    model = SAC("MlpPolicy", venv, seed=0, **settings)
    model.learn(total_timesteps=steps, progress_bar=progress)  # SB3's bar (rich): the default 30k steps take long
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        model.save(out / "chain_sac.zip")
        venv.save(str(out / "chain_sac_vecnormalize.pkl"))  # the policy acts on observations normalized by these

    limit = {} if episode_steps is None else {"max_episode_steps": episode_steps}
    venv.training = False
    policies = {"agent": Agent(model, venv), "random": "random", "scripted": "scripted"}  # Agent: obs normalized
    # seeds no training copy started from (SB3 seeds copy i with i), as train_agent's final evaluation takes them
    seed = FINAL_EVAL_SEED
    results = {
        name: evaluate(env_id, p, episodes=episodes, seed=seed, env_kwargs=limit) for name, p in policies.items()
    }
    for name, r in results.items():
        print(f"{name:<9} return {r.mean:8.2f} ± {r.std:6.2f}   success {100 * r.success_rate:.0f}%")
    return {
        "steps": model.num_timesteps,
        "budget": steps,
        "random_std": results["random"].std,
        **{k: r.mean for k, r in results.items()},
    }


def check(result: dict[str, float]) -> None:
    """What this example must show: it trained its budget, and the scripted controller beats random forces."""
    assert result["steps"] >= result["budget"]
    assert result["scripted"] > result["random"] + result["random_std"]
    assert result["agent"] == result["agent"]  # not NaN


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="Train SAC on a chain env")
    parser.add_argument("--env", default="RedSim/MiniChain-v0", help="a reach env id (default RedSim/MiniChain-v0)")
    parser.add_argument("--steps", type=int, default=30_000, help="SAC's env steps (default 30000)")
    parser.add_argument("--episodes", type=int, default=20, help="evaluation episodes per policy (default 20)")
    parser.add_argument("--episode-steps", type=int, help="steps per evaluation episode (default: the env's limit)")
    parser.add_argument("--out", type=Path, help="folder for the policy and its normalizer (default: not saved)")
    parser.add_argument("--no-progress", action="store_true", help="no SB3 progress bar while training")
    args = parser.parse_args()
    counts = (("--steps", args.steps), ("--episodes", args.episodes), ("--episode-steps", args.episode_steps))
    for flag, value in counts:
        if value is not None and value < 1:  # before training, not in the evaluation after it (0 was a traceback)
            parser.error(f"{flag} must be an integer >= 1, got {value}")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out} is a file, not a folder")
    try:  # (check() is the test budget's claim: at any other budget the numbers speak for themselves)
        main(args.out, args.env, args.steps, args.episodes, args.episode_steps, progress=not args.no_progress)
    except KeyboardInterrupt:
        print("interrupted; nothing was saved", file=sys.stderr)
        sys.exit(130)
