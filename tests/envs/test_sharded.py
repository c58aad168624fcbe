"""The sharded vector env (worker processes, each a native vector env of a block of copies) is the native one."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

from redsim.envs.sb3 import SB3VecEnv
from redsim.envs.sharded import ShardedVectorEnv, ShardError, shard_sizes

TIGHT = {"dtype": "float64", "stepper_options": {"tol": 1e-10, "max_iter": 60}}
"""Solved tightly, so that the batch composition does not move a copy's solve (see test_envs.py)."""


def _rollout(venv: gym.vector.VectorEnv, actions: np.ndarray, seed: int) -> tuple[list, list, list, list]:
    obs, _ = venv.reset(seed=seed)
    observations, rewards, dones, finals = [obs], [], [], []
    for a in actions:
        obs, reward, terminated, truncated, info = venv.step(a)
        observations.append(obs)
        rewards.append(reward)
        dones.append(terminated | truncated)
        finals.append(info.get("_final_obs", np.zeros(len(obs), dtype=bool)))
    return observations, rewards, dones, finals


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_sharded_env_equals_the_native_vector_env(mode: AutoresetMode) -> None:
    """Same seeds (copy i: seed + i), same actions, same autoresets, over 3 uneven shards of 5 copies."""
    n, steps = 5, 9
    actions = np.random.default_rng(0).uniform(-1, 1, (steps, n, 3)).astype(np.float32)
    kwargs = {"max_episode_steps": 4, "autoreset_mode": mode, **TIGHT}
    native = gym.make_vec("RedSim/MiniChain-v0", num_envs=n, vectorization_mode="vector_entry_point", **kwargs)
    sharded = gym.make_vec(
        "RedSim/MiniChain-v0", num_envs=n, vectorization_mode="vector_entry_point", shards=3, **kwargs
    )
    try:
        assert isinstance(sharded, ShardedVectorEnv) and sharded.sizes == [2, 2, 1]
        assert sharded.observation_space == native.observation_space and sharded.action_space == native.action_space
        expected, got = _rollout(native, actions, 11), _rollout(sharded, actions, 11)
        for a, b in zip(expected[:2], got[:2], strict=True):
            np.testing.assert_allclose(np.array(b), np.array(a), rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(np.array(got[2]), np.array(expected[2]))
        np.testing.assert_array_equal(np.array(got[3]), np.array(expected[3]))
        assert np.array(got[2])[3].all()  # every copy truncated at max_episode_steps = 4
        _, _, _, _, info = sharded.step(actions[0])
        _, _, _, _, native_info = native.step(actions[0])
        assert set(info) == set(native_info) and all(len(v) == n for v in info.values())
    finally:
        native.close()
        sharded.close()


def test_reset_mask_state_round_trip_render_and_close() -> None:
    venv = gym.make_vec(
        "RedSim/MiniChain-v0", num_envs=3, vectorization_mode="vector_entry_point", shards=2, render_mode="rgb_array"
    )
    processes = list(venv._processes)
    venv.reset(seed=0)
    state = venv.get_state()
    after, *_ = venv.step(np.ones((3, 3), np.float32))
    venv.set_state(state)
    again, *_ = venv.step(np.ones((3, 3), np.float32))
    np.testing.assert_array_equal(again, after)
    kept, _ = venv.reset(options={"reset_mask": np.array([True, False, False])})
    assert not np.array_equal(kept[0], again[0])  # copy 0 reset, copies 1 and 2 untouched
    np.testing.assert_array_equal(kept[1:], again[1:])
    frames = venv.render()
    assert len(frames) == 3 and frames[0].ndim == 3 and frames[0].dtype == np.uint8
    venv.close()
    assert all(not p.is_alive() for p in processes)
    with pytest.raises(RuntimeError, match="closed"):
        venv.step(np.zeros((3, 3), np.float32))


def test_bad_input_is_a_clear_error_and_a_failing_worker_raises_in_the_caller() -> None:
    with pytest.raises(ValueError, match="shards must be an integer in"):
        shard_sizes(2, 3)
    with pytest.raises(ValueError, match="shards must be an integer in"):
        gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point", shards=0)
    with pytest.raises(ValueError, match="unknown hessian"):  # raised here, before any worker starts
        gym.make_vec(
            "RedSim/MiniChain-v0",
            num_envs=2,
            vectorization_mode="vector_entry_point",
            shards=2,
            stepper_options={"hessian": "unknown"},
        )
    venv = gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point", shards=2)
    venv.reset(seed=0)
    with pytest.raises(ShardError, match=r"(?s)shard 0.*state is missing"):  # a worker's own error, with its traceback
        venv.set_state([{}, {}])
    assert venv.closed
    venv = gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point", shards=2)
    try:
        venv.reset(seed=0)
        with pytest.raises(ValueError, match="finite"):
            venv.step(np.full((2, 3), np.nan, np.float32))
        venv._processes[1].kill()
        venv._processes[1].join()
        with pytest.raises(ShardError, match="shard 1"):
            venv.step(np.zeros((2, 3), np.float32))
        assert venv.closed
    finally:
        venv.close()


def test_sb3_adapter_runs_on_shards() -> None:
    venv = SB3VecEnv.make("RedSim/MiniChain-v0", 4, shards=2)
    try:
        obs = venv.reset()
        assert obs.shape == (4, *venv.observation_space.shape)
        obs, reward, _, infos = venv.step(np.zeros((4, 3), np.float32))
        assert reward.shape == (4,) and len(infos) == 4 and np.isfinite(obs).all()
    finally:
        venv.close()
