"""Ray RLlib PPO on a RedSim env, with several env runners on a Ray cluster (needs `pip install "redsim[ray]"`).

Run here (the script starts a local Ray cluster: the runners are processes on this machine):
    python examples/rllib_agent.py --iterations 20 --env-runners 2
On a multi-machine cluster (redsim installed on every node, same versions):
    ray start --head --port=6379                    # on the head node
    ray start --address=HEAD_IP:6379                # on each other node
    python examples/rllib_agent.py --address auto --env-runners 16
(or set RAY_ADDRESS=HEAD_IP:6379; each env runner takes one CPU of whichever node Ray places it on).
main()'s defaults are the one-iteration budget the test suite runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import ray
from ray.rllib.algorithms.ppo import PPOConfig

from redsim.trainers.rllib import register

ENV_ID = "RedSim/MiniChain-v0"


def main(
    out: Path | None = None,
    iterations: int = 1,
    env_runners: int = 2,
    address: str | None = None,
    episode_steps: int | None = 20,
    batch: int = 80,
) -> dict[str, float]:
    if address is None:  # a local cluster, sized to the runners plus this driver (which also learns)
        ray.init(num_cpus=env_runners + 1, include_dashboard=False, object_store_memory=200 * 2**20)
    else:
        ray.init(address=address)
    kwargs = {} if episode_steps is None else {"max_episode_steps": episode_steps}
    config = (
        PPOConfig()
        .environment(register(), env_config={"id": ENV_ID, "kwargs": kwargs})
        .env_runners(num_env_runners=env_runners, num_envs_per_env_runner=1, rollout_fragment_length="auto")
        .training(train_batch_size_per_learner=batch, minibatch_size=min(batch, 128), num_epochs=2, lr=3e-4)
    )
    algo = config.build_algo()
    try:
        for i in range(iterations):
            result = algo.train()
            runners = result["env_runners"]
            print(
                f"iteration {i + 1}: {runners['num_env_steps_sampled_lifetime']} env steps, "
                f"episode return {runners.get('episode_return_mean', float('nan')):.2f}"
            )
        healthy = algo.env_runner_group.num_healthy_remote_workers()
        if out is not None:
            algo.save_to_path(str((out / "rllib_ppo").resolve()))
    finally:
        algo.stop()
        ray.shutdown()
    return {
        "iterations": float(result["training_iteration"]),
        "env_steps": float(runners["num_env_steps_sampled_lifetime"]),
        "healthy_runners": float(healthy),
        "requested_runners": float(env_runners),
    }


def check(result: dict[str, float]) -> None:
    """What this example must show: every runner stayed up and the iterations sampled env steps."""
    assert result["healthy_runners"] == result["requested_runners"]
    assert result["iterations"] >= 1 and result["env_steps"] >= 80


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="RLlib PPO on a RedSim env")
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--env-runners", type=int, default=2)
    parser.add_argument("--address", help="a running Ray cluster ('auto', or HEAD_IP:6379); default: start one")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    check(main(args.out, args.iterations, args.env_runners, args.address, episode_steps=None, batch=4000))
