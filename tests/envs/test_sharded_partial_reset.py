"""With autoreset DISABLED, a partial reset leaves the other ended copies ended: the next step is refused, in the
sharded env as in the native one (hand mutation audit, helper-281: clearing every copy's ended flag at any reset in
envs/sharded.py passed tests/envs/test_sharded.py, and the sharded env then stepped an ended episode on)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import redsim  # noqa: F401  (registers the ids)


@pytest.mark.parametrize("shards", [1, 2])
def test_a_copy_left_ended_by_a_partial_reset_is_not_stepped(shards: int) -> None:
    options = {"shards": shards} if shards > 1 else {}
    venv = gym.make_vec(
        "RedSim/MiniChain-v0",
        num_envs=2,
        vectorization_mode="vector_entry_point",
        max_episode_steps=2,
        autoreset_mode=AutoresetMode.DISABLED,
        **options,
    )
    try:
        venv.reset(seed=0)
        action = np.zeros((2, 3), np.float32)
        for _ in range(2):
            *_, truncated, _ = venv.step(action)
        assert truncated.all()
        venv.reset(options={"reset_mask": np.array([True, False])})
        with pytest.raises(RuntimeError, match=r"copies \[1\] ended"):
            venv.step(action)
        venv.reset(options={"reset_mask": np.array([False, True])})
        venv.step(action)  # both reset now
    finally:
        venv.close()
