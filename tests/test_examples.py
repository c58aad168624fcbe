"""Every example runs and passes its own check() (with the tiny budget of its main()'s defaults)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = sorted((Path(__file__).parent.parent / "examples").glob("*.py"))
if not EXAMPLES:  # the tests copied beside an installed wheel
    pytest.skip("needs the source checkout (examples/)", allow_module_level=True)
OPTIONAL = {"rllib_agent": ("ray", 'Ray RLlib is not installed (pip install "redsim[ray]")')}
"""Examples that need an optional extra: example -> (module, why it is skipped without it)."""


def _example(stem: str):
    """The example module examples/STEM.py, loaded (its __main__ block not run)."""
    path = next(p for p in EXAMPLES if p.stem == stem)
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_example_runs_and_checks(path: Path, tmp_path: Path) -> None:
    if path.stem in OPTIONAL:
        module_name, reason = OPTIONAL[path.stem]
        pytest.importorskip(module_name, reason=reason)
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.check(module.main(tmp_path))


def test_her_example_evaluates_on_seeds_no_training_copy_started_from(monkeypatch: pytest.MonkeyPatch) -> None:
    """It evaluated on seeds 0 .. episodes - 1, and at ``--seed 0`` its first training episode was seed 0's; now
    ``seed + FINAL_EVAL_SEED + i``, as the other examples and ``redsim train-agent``."""
    import numpy as np

    from redsim.trainers.agents import FINAL_EVAL_SEED

    module = _example("her_agent")
    seeds: list[int | None] = []

    class RecordingGoalObservation(module.GoalObservation):
        def reset(self, *, seed=None, options=None):
            seeds.append(seed)
            return super().reset(seed=seed, options=options)

    class StillModel:  # training is not what this checks
        num_timesteps = 50

        def predict(self, obs, deterministic=False):
            return np.zeros(3, np.float32), None

    monkeypatch.setattr(module, "GoalObservation", RecordingGoalObservation)
    monkeypatch.setattr(module, "train", lambda *args, **kwargs: (StillModel(), 0.0))
    module.main(seed=3, episodes=2)
    assert seeds == [3 + FINAL_EVAL_SEED, 4 + FINAL_EVAL_SEED] * 2  # each agent, the same episodes


def test_her_example_monitors_the_goal_reward_it_trains_on(monkeypatch: pytest.MonkeyPatch) -> None:
    """Its single-copy env is SB3's Monitor around the goal env, so the logged episode rewards (``ep_rew_mean``) are
    the goal rewards SAC trains on; ``wrapper_class=GoalObservation`` had put the Monitor inside, logging the env's own
    reward (control cost included)."""
    from stable_baselines3.common.monitor import Monitor

    module = _example("her_agent")
    made = []

    class Stop(Exception):
        pass

    def sac(policy, venv, **kwargs):
        made.append(venv)
        raise Stop

    monkeypatch.setattr(module, "SAC", sac)
    with pytest.raises(Stop):
        module.train("RedSim/MiniChain-v0", 200, True, {"max_episode_steps": 50})
    (env,) = made[0].envs
    assert isinstance(env, Monitor) and isinstance(env.env, module.GoalObservation)
    made[0].close()


def test_her_example_refuses_a_budget_or_episodes_it_cannot_train_on() -> None:
    """--episode-steps -1 (no limit) trained and then evaluated an episode that never ends; 0 was a traceback."""
    path = next(p for p in EXAMPLES if p.stem == "her_agent")
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    env_id = "RedSim/MiniChain-v0"
    for episode in (-1, 0):
        with pytest.raises(
            ValueError, match=f"HER needs episodes that end: --episode-steps must be >= 1, got {episode}"
        ):
            module.episodes_ended(env_id, 100, {"max_episode_steps": episode}, 1)
    with pytest.raises(ValueError, match="--num-envs must be >= 1, got 0"):
        module.episodes_ended(env_id, 100, {"max_episode_steps": 20}, 0)
    # every copy has ended an episode at copies x episode steps: learning starts there, and that budget is enough
    assert module.episodes_ended(env_id, 40, {"max_episode_steps": 20}, 2) == 39
    with pytest.raises(
        ValueError, match="39 steps are not enough: every one of the 2 copies has ended an episode at 40"
    ):
        module.episodes_ended(env_id, 39, {"max_episode_steps": 20}, 2)


def test_rllib_example_starts_its_own_local_cluster_or_joins_ray_address(tmp_path: Path, monkeypatch) -> None:
    """Without --address it called ray.init(num_cpus=...), which joined a cluster `ray start` left on the machine (or
    RAY_ADDRESS's) and failed: "When connecting to an existing cluster, num_cpus and num_gpus must not be provided"."""
    ray = pytest.importorskip("ray", reason=OPTIONAL["rllib_agent"][1])
    module = _example("rllib_agent")
    addresses = []

    class Joined(Exception):
        pass

    def init(*args, **kwargs):
        addresses.append(kwargs.get("address"))
        raise Joined

    monkeypatch.setattr(ray, "init", init)
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    with pytest.raises(Joined):
        module.main(tmp_path)
    monkeypatch.setenv("RAY_ADDRESS", "10.0.0.1:6379")  # the docstring's alternative to --address
    with pytest.raises(Joined):
        module.main(tmp_path)
    assert addresses == ["local", "10.0.0.1:6379"]


def test_rllib_example_names_token_authentication_where_it_cannot_connect(tmp_path: Path, monkeypatch) -> None:
    """A driver with an explicit address on a cluster with token authentication on (Ray 2.60: even on the head)
    failed after about 25 s with Ray's traceback ending in "ConnectionError: Failed to connect to Ray cluster"."""
    ray = pytest.importorskip("ray", reason=OPTIONAL["rllib_agent"][1])
    module = _example("rllib_agent")

    def init(*args, **kwargs):
        raise ConnectionError("Failed to connect to Ray cluster at 10.0.0.1:6379")

    monkeypatch.setattr(ray, "init", init)
    with pytest.raises(RuntimeError, match=r"'10\.0\.0\.1:6379' \(Failed to connect.*RAY_AUTH_MODE=token"):
        module.main(tmp_path, address="10.0.0.1:6379")


def test_chain_example_refuses_episode_steps_0_before_training(tmp_path: Path) -> None:
    """`--episode-steps 0` passed its check (`0 or 1`), trained, then died in the evaluation with a traceback."""
    path = next(p for p in EXAMPLES if p.stem == "chain_agent")
    run = subprocess.run(
        [sys.executable, str(path), "--steps", "2", "--episodes", "1", "--episode-steps", "0", "--no-progress"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
    )
    assert run.returncode == 2 and "--episode-steps must be an integer >= 1, got 0" in run.stderr, run.stderr
