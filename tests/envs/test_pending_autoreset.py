"""A vector env's state saved while copies wait for their NEXT_STEP autoreset restores that wait.

get_state's doc: "a restored state steps exactly alike, episode ends and autoresets included". The tests of
set_state restored states saved mid-episode only; restoring the ``autoresetting`` flags as all False passed
tests/envs/test_vector_api.py and test_sharded.py (hand mutation audit, helper-276), and the copies that had ended
were stepped on from their last state instead of reset.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import redsim  # noqa: F401  (registers the ids)

PUSH = np.full((2, 3), 0.5, np.float32)


@pytest.mark.parametrize("shards", [1, 2])
def test_a_state_saved_with_an_autoreset_pending_resets_those_copies_on_the_next_step(shards: int) -> None:
    venv = gym.make_vec("RedSim/MiniChain-v0", 2, "vector_entry_point", max_episode_steps=2, shards=shards)
    try:
        venv.reset(seed=0)
        venv.step(PUSH)
        truncated = venv.step(PUSH)[3]
        assert truncated.all()
        saved = venv.get_state()
        assert np.asarray(saved["autoresetting"]).all()
        obs, reward, terminated, truncated, _ = venv.step(PUSH)  # the autoreset step: new episodes, reward 0
        assert not reward.any() and not terminated.any() and not truncated.any()
        after = venv.step(PUSH)[0]
        venv.set_state(saved)
        again, reward, terminated, truncated, _ = venv.step(PUSH)
        assert not reward.any() and not terminated.any() and not truncated.any()
        np.testing.assert_allclose(again, obs, rtol=1e-6, atol=1e-6)  # the same draws (the generators restored)
        np.testing.assert_allclose(venv.step(PUSH)[0], after, rtol=1e-5, atol=1e-5)
    finally:
        venv.close()
