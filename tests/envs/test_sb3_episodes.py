"""The SB3 adapter's ``info["episode"]`` counts each episode's own return and length, the second one too.

SB3 logs ep_rew_mean and ep_len_mean from it. tests/envs/test_vector_api.py checks the first episode only:
carrying the return and length over into the next episode (no zeroing where one ends) passed it and the SB3 tests
of tests/envs/test_envs.py and tests/trainers/test_agents.py (hand mutation audit, helper-276).
"""

from __future__ import annotations

import numpy as np
import pytest

import redsim  # noqa: F401  (registers the ids)
from redsim.envs.sb3 import SB3VecEnv

PUSH = np.full((2, 3), 0.5, np.float32)


def test_every_episode_reports_its_own_return_and_length() -> None:
    venv = SB3VecEnv.make("RedSim/MiniChain-v0", 2, max_episode_steps=3)
    try:
        venv.seed(0)
        venv.reset()
        for episode in range(3):
            total = np.zeros(2)
            for step in range(3):
                _, reward, done, infos = venv.step(PUSH)
                total += reward
                assert done.all() == (step == 2) and ("episode" in infos[0]) == (step == 2), (episode, step)
            for info, expected in zip(infos, total, strict=True):
                assert info["episode"]["l"] == 3, episode
                assert info["episode"]["r"] == pytest.approx(expected, rel=1e-5), episode
    finally:
        venv.close()
