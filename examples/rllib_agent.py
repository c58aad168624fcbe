"""Ray RLlib PPO on a RedSim env, with several env runners on a Ray cluster (needs `pip install "redsim[ray]"`).

Run here (the script starts a local Ray cluster: the runners are processes on this machine):
    python examples/rllib_agent.py --iterations 20 --env-runners 2
On a multi-machine cluster (redsim installed on every node, same versions):
    ray start --head --port=6379                    # on the head node
    ray start --address=HEAD_IP:6379                # on each other node
    python examples/rllib_agent.py --address auto --env-runners 16
(or set RAY_ADDRESS=HEAD_IP:6379; each env runner takes one CPU of whichever node Ray places it on). Without either,
the script starts a local cluster of its own, also where `ray start` left one running on this machine.
Each runner steps --envs-per-runner copies in redsim's native vector env (one batched solve for all of them).
The env config is checked in this process first, as the runners build it, so a bad id or keyword is a clear error
here rather than dead runners. --out DIR saves the algorithm to DIR/rllib_ppo (refused where one is, unless
--overwrite); `--restore DIR/rllib_ppo` trains on from it with its own settings (env, runners, batch), so those
flags are refused beside it; a local cluster then gets every CPU of the machine, and at least one per restored
runner (read from the checkpoint: with fewer, RLlib waited for them without a word).
--seed S seeds the runners' episodes (runs repeat; without it they do not); --evaluate N then runs the saved
policy greedily on N seeded single envs of the env it trained in, its episode length included (policy_returns: the
network alone, no Ray cluster). With --address the cluster must have a free CPU per runner (a restore's too), else
this stops with the count (RLlib would wait without a word).
main()'s defaults are the one-iteration budget the test suite runs.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from redsim.trainers.rllib import check_env_config, checkpoint_config, register
from redsim.trainers.rllib import restore as restore_algorithm

ENV_ID = "RedSim/MiniChain-v0"
SETTINGS = {"env": ENV_ID, "env_runners": 2, "envs_per_runner": 16, "batch": 4000, "episode_steps": None}
"""The command line's defaults of the settings a restored algorithm brings along."""


def main(
    out: Path | None = None,
    iterations: int = 1,
    env_runners: int = 2,
    address: str | None = None,
    episode_steps: int | None = 20,
    batch: int = 80,
    env_id: str = ENV_ID,
    envs_per_runner: int = 2,
    restore: Path | None = None,
    seed: int | None = None,
) -> dict[str, Any]:
    import ray
    from ray.rllib.algorithms.ppo import PPOConfig

    if restore is not None and not (restore / "rllib_checkpoint.json").is_file():
        raise ValueError(f"{restore} is not an RLlib checkpoint (no rllib_checkpoint.json): give OUT/rllib_ppo")
    env_config = {"id": env_id, "kwargs": {} if episode_steps is None else {"max_episode_steps": episode_steps}}
    if restore is None:
        check_env_config(env_config, num_envs=envs_per_runner)  # before any runner starts, as the runners build it
    if restore is not None:  # the checkpoint's runners, whatever the command line says
        env_runners = int(checkpoint_config(restore)["num_env_runners"])
    address = address or os.environ.get("RAY_ADDRESS") or None  # RAY_ADDRESS as --address, the CPU check included
    if address is not None:
        try:
            ray.init(address=address)
        except ConnectionError as err:  # after about 25 s of retries; Ray's traceback ends in this one line
            ray.shutdown()
            raise RuntimeError(
                f"could not connect to the Ray cluster at {address!r} ({err}): where its head has token "
                "authentication on, set RAY_AUTH_MODE=token and the token (RAY_AUTH_TOKEN, or ~/.ray/auth_token copied "
                "over) here; on the head node, --address auto finds it (the Ray log above names InvalidAuthToken)"
            ) from None
        cpus = ray.available_resources().get("CPU", 0.0)  # free ones: another job's runners hold theirs
        if cpus < env_runners:  # RLlib would wait for them without a word
            ray.shutdown()
            raise RuntimeError(
                f"the cluster at {address!r} has {cpus:g} free CPUs and each of the {env_runners} env runners takes "
                "one: start more nodes or ask for fewer runners (a node that did not join: see its log, e.g. "
                "InvalidAuthToken where the head has token authentication on)"
            )
    else:  # a local cluster of its own: ray.init(num_cpus=...) joined one `ray start` left here and refused num_cpus
        # a restore's: every CPU of the machine, and one per runner plus this driver at least; else the runners + driver
        cpus = max(os.cpu_count() or 1, env_runners + 1) if restore is not None else env_runners + 1
        ray.init(address="local", num_cpus=cpus, include_dashboard=False, object_store_memory=200 * 2**20)
    name = register()  # before from_checkpoint too: the checkpoint names the creator
    if restore is not None:
        algo = restore_algorithm(restore)  # every runner on the checkpoint's weights
    else:
        config = (
            PPOConfig()
            .environment(name, env_config=env_config)
            .env_runners(
                num_env_runners=env_runners,
                num_envs_per_env_runner=envs_per_runner,
                gym_env_vectorize_mode="vector_entry_point",  # the copies of a runner: one batched latent solve
                rollout_fragment_length="auto",
            )
            .training(train_batch_size_per_learner=batch, minibatch_size=min(batch, 128), num_epochs=2, lr=3e-4)
            .debugging(seed=seed)  # runner r's copies draw from it (redsim.trainers.rllib.RunnerSeeds)
        )
        algo = config.build_algo()
    try:
        for _ in range(iterations):
            result = algo.train()
            runners = result.get("env_runners", {})
            if "num_env_steps_sampled_lifetime" not in runners:
                raise RuntimeError(f"iteration {result['training_iteration']} sampled nothing (see the runners' log)")
            mean = runners.get("episode_return_mean", math.nan)
            returns = "no episode ended yet" if math.isnan(mean) else f"episode return {mean:.2f}"
            print(
                f"iteration {result['training_iteration']}: {runners['num_env_steps_sampled_lifetime']} env steps, "
                f"{returns}"
            )
        healthy = algo.env_runner_group.num_healthy_remote_workers()
        if out is not None:
            print(f"saved {algo.save_to_path(str((out / 'rllib_ppo').resolve()))}")
        settings = {"runners": algo.config.num_env_runners, "batch": algo.config.train_batch_size_per_learner}
        env_id, env_kwargs = algo.config.env_config["id"], dict(algo.config.env_config.get("kwargs", {}))
    finally:
        algo.stop()
        ray.shutdown()
    return {
        "iterations": float(result["training_iteration"]),
        "env_steps": float(runners["num_env_steps_sampled_lifetime"]),
        "healthy_runners": float(healthy),
        "requested_runners": float(settings["runners"]),
        "batch": float(settings["batch"]),
        "env_id": env_id,
        "env_kwargs": env_kwargs,
    }


def policy_returns(
    checkpoint: Path, env_id: str = ENV_ID, episodes: int = 5, seed: int = 0, env_kwargs: dict[str, Any] | None = None
) -> np.ndarray:
    """Returns [episodes] of a saved algorithm's policy acting greedily (its Gaussian's mean) in single envs made
    with ``env_kwargs`` (those it trained with: an episode length too) and reset with seeds seed .. seed + episodes - 1:
    the policy network alone, loaded without a Ray cluster."""
    import gymnasium as gym
    import torch
    from ray.rllib.core.columns import Columns
    from ray.rllib.core.rl_module.rl_module import RLModule

    module = RLModule.from_checkpoint(str((checkpoint / "learner_group/learner/rl_module/default_policy").resolve()))
    greedy = module.get_inference_action_dist_cls()
    env = gym.make(env_id, **(env_kwargs or {}))
    returns = np.zeros(episodes)
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i)
        done = False
        while not done:
            with torch.no_grad():
                out = module.forward_inference({Columns.OBS: torch.as_tensor(obs)[None]})
            action = greedy.from_logits(out[Columns.ACTION_DIST_INPUTS]).to_deterministic().sample()[0].numpy()
            obs, reward, terminated, truncated, _ = env.step(action)
            returns[i] += reward
            done = terminated or truncated
    env.close()
    return returns


def check(result: dict[str, Any]) -> None:
    """What this example must show: every runner stayed up and the iterations sampled env steps."""
    assert result["healthy_runners"] == result["requested_runners"]
    assert result["iterations"] >= 1 and result["env_steps"] >= result["batch"]


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text}")
    return value


def _count(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0 (0: the driver samples), got {text}")
    return value


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="RLlib PPO on a RedSim env")
    parser.add_argument("--env", help=f"a RedSim id (default {ENV_ID})")
    parser.add_argument("--iterations", type=_positive, default=20, help="training iterations (default 20)")
    parser.add_argument("--env-runners", type=_count, help="env runner processes (default 2; 0: the driver samples)")
    parser.add_argument("--envs-per-runner", type=_positive, help="env copies per runner (default 16)")
    parser.add_argument("--batch", type=_positive, help="env steps per iteration (default 4000)")
    parser.add_argument("--episode-steps", type=_positive, help="steps per episode (default: the env's limit)")
    parser.add_argument("--address", help="a running Ray cluster ('auto', or HEAD_IP:6379); default: start one")
    parser.add_argument("--out", type=Path, help="save the algorithm to OUT/rllib_ppo")
    parser.add_argument("--overwrite", action="store_true", help="replace an algorithm saved in OUT/rllib_ppo")
    parser.add_argument("--restore", type=Path, help="train on from OUT/rllib_ppo, with its own settings")
    parser.add_argument("--seed", type=_count, help="seed of the runners' episodes (default: none, not reproducible)")
    parser.add_argument(
        "--evaluate", type=_positive, metavar="EPISODES", help="then run the saved policy greedily (needs --out)"
    )
    args = parser.parse_args()
    if importlib.util.find_spec("ray") is None:
        parser.error('this example needs Ray RLlib: pip install "redsim[ray]"')
    given = {key: getattr(args, key) for key in (*SETTINGS, "seed")}
    if args.restore is not None and any(value is not None for value in given.values()):
        flags = [f"--{key.replace('_', '-')}" for key, value in given.items() if value is not None]
        parser.error(f"--restore trains on with the checkpoint's own settings: drop {' '.join(flags)}")
    if args.evaluate is not None and args.out is None:
        parser.error("--evaluate runs the policy saved in OUT/rllib_ppo: give --out")
    if args.out is not None and (args.out / "rllib_ppo").exists() and not args.overwrite:
        parser.error(f"{args.out / 'rllib_ppo'} holds a saved algorithm: --restore it, or give --overwrite")
    settings = {key: SETTINGS[key] if value is None else value for key, value in given.items() if key in SETTINGS}
    if args.restore is not None and not (args.restore / "rllib_checkpoint.json").is_file():
        parser.error(f"{args.restore} is not an RLlib checkpoint (no rllib_checkpoint.json): give OUT/rllib_ppo")
    if args.restore is None:
        kwargs = {} if settings["episode_steps"] is None else {"max_episode_steps": settings["episode_steps"]}
        try:  # as the runners will build it, before Ray starts
            check_env_config({"id": settings["env"], "kwargs": kwargs}, num_envs=settings["envs_per_runner"])
        except ValueError as err:
            parser.error(str(err))
    try:
        result = main(
            args.out,
            args.iterations,
            settings["env_runners"],
            args.address,
            settings["episode_steps"],
            settings["batch"],
            settings["env"],
            settings["envs_per_runner"],
            args.restore,
            args.seed,
        )
    except KeyboardInterrupt:
        print("interrupted; the algorithm was not saved", file=sys.stderr)
        sys.exit(130)
    except RuntimeError as err:
        sys.exit(f"error: {err}")
    check(result)
    if args.evaluate is not None:
        returns = policy_returns(
            args.out / "rllib_ppo", result["env_id"], args.evaluate, env_kwargs=result["env_kwargs"]
        )
        length = result["env_kwargs"].get("max_episode_steps", "the env's")
        print(
            f"greedy policy, {args.evaluate} episodes of {length} steps as trained (seeds 0-{args.evaluate - 1}): "
            f"return {returns.mean():.2f} ± {returns.std():.2f}"
        )
