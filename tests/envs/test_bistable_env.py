"""`RedSim/BistableBar-v0` and `-v1`: snap the compressed bar from one buckled state to the other.

The registry-wide contract checks (check_env, SB3, soak) run in test_envs.py under ``-m slow``.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import redsim  # noqa: F401  (registers the ids)
from redsim.envs.base import LatentEnv, shipped
from redsim.envs.bistable_bar import SnapThrough

ID = "RedSim/BistableBar-v0"
WEAK = "RedSim/BistableBar-v1"
"""40 N, below what a held push needs to snap the env's bar (48 N snaps, 36 N springs back; docs/envs.md)."""


@pytest.fixture(scope="module")
def env() -> LatentEnv:
    return gym.make(ID).unwrapped


def test_the_two_stable_states_are_the_buckled_arches(env: LatentEnv) -> None:
    """The task's states are latent equilibria arched up and down, about as far as the full-space arches (0.26 m)."""
    up, down = env.task.heights.tolist()
    assert 0.2 < up < 0.32 and -0.32 < down < -0.2, (up, down)
    heights = set()
    for seed in range(6):
        obs, _ = env.reset(seed=seed)
        start, goal = obs[16], obs[16] + obs[17]
        assert {round(float(start), 4), round(float(goal), 4)} == {round(up, 4), round(down, 4)}
        heights.add(round(float(start), 4))
    assert len(heights) == 2  # both starts are drawn


def test_the_scripted_push_snaps_it_and_it_stays(env: LatentEnv) -> None:
    """From either state the bang-bang controller carries the bar over within the episode; it then stays there."""
    for seed in (0, 1, 2):
        env.reset(seed=seed)
        goal = float(env.sim.params["goal_height"][0])
        success = []
        for _ in range(150):
            _, reward, terminated, _, info = env.step(env.task.controller(env.sim)[0])
            assert not terminated
            success.append(info["is_success"])
        assert all(success[-50:]) and np.sign(info["height"]) == np.sign(goal), (seed, info["height"], goal)
        assert info["elastic_inverted"] == 0 and info["elastic_min_det_f"] > 0.2
        terms = sum(info[f"reward_{t}"] for t in ("height", "control", "success"))
        assert reward == pytest.approx(terms, rel=1e-5)


def test_a_weak_push_only_bends_the_arch(env: LatentEnv) -> None:
    """A tenth of the force held for 2 s and released: the bar springs back to where it started."""
    env.reset(seed=0)
    start, goal = (float(env.sim.params[k][0]) for k in ("start_height", "goal_height"))
    push = np.array([0.1 * np.sign(goal - start)], np.float32)
    for _ in range(100):
        _, _, _, _, info = env.step(push)
    assert info["height"] != pytest.approx(start, abs=1e-3)  # it did bend
    for _ in range(100):
        _, _, _, _, info = env.step(np.zeros(1, np.float32))
    assert not info["is_success"] and info["height"] == pytest.approx(start, abs=0.1 * abs(goal - start))


def _pump(obs: np.ndarray) -> np.ndarray:
    """Push along the middle's velocity (towards the goal when at rest) until it is 60% of the way over, then let go.

    obs [B, 19]: h, h* - h and h_dot are its last three entries; the start is the goal's mirror image."""
    h, offset, speed = obs[:, -3], obs[:, -2], obs[:, -1]
    goal = h + offset
    push = np.where(np.abs(speed) > 1e-3, np.sign(speed), np.sign(offset))
    return np.where((h + goal) / (2.0 * goal) > 0.6, 0.0, push)[:, None].astype(np.float32)


def test_v1_force_is_below_the_snap_load_yet_pumping_snaps_it() -> None:
    """v1 (40 N): the scripted push towards the goal fails in some of 8 seeded episodes, swinging the bar by pushing
    along its motion snaps every one of them, so the task is reachable but needs more than a push."""
    venv = gym.make_vec(WEAK, num_envs=8, vectorization_mode="vector_entry_point")
    assert venv.sim.task.max_force == 40.0
    results = {}
    for name in ("push", "pump"):
        obs, _ = venv.reset(seed=0)
        for _ in range(200):
            action = venv.sim.task.controller(venv.sim) if name == "push" else _pump(obs)
            obs, _, terminated, truncated, info = venv.step(np.asarray(action, np.float32))
            assert not terminated.any()
        assert truncated.all()
        results[name] = info["is_success"].copy()
    assert results["pump"].all(), results
    assert not results["push"].all(), results


def test_vector_env_equals_single_envs_and_seeds_repeat() -> None:
    n, steps = 2, 8
    actions = np.random.default_rng(0).uniform(-1, 1, (steps, n, 1)).astype(np.float32)
    tight = {"dtype": "float64", "stepper_options": {"tol": 1e-10, "max_iter": 60}}
    venv = gym.make_vec(ID, num_envs=n, vectorization_mode="vector_entry_point", **tight)
    obs, _ = venv.reset(seed=3)
    vec = [obs] + [venv.step(a)[0] for a in actions]
    for i in range(n):
        single = gym.make(ID, **tight)
        obs, _ = single.reset(seed=3 + i)
        np.testing.assert_allclose(
            np.array(vec)[:, i], np.array([obs] + [single.step(a)[0] for a in actions[:, i]]), rtol=1e-6, atol=1e-7
        )
    again = gym.make(ID)
    runs = []
    for _ in range(2):
        obs, _ = again.reset(seed=5)
        runs.append(np.array([obs] + [again.step(a)[0] for a in actions[:, 0]]))
    assert np.array_equal(runs[0], runs[1])


def test_snap_task_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="max_force"):
        SnapThrough("middle", max_force=0.0)
    with pytest.raises(ValueError, match="release"):
        SnapThrough("middle", max_force=10.0, release=1.5)
    scene, sub = shipped("bistable_bar")
    with pytest.raises(ValueError, match="no handle 'tip'"):
        LatentEnv(scene, sub, SnapThrough("tip", max_force=10.0))
