"""A noisy reset's start velocity reads the same in the task's speed extras at any frame_skip.

With ``reset_noise_scale`` the start has a latent velocity, and x_prev is put one env step (frame_skip stepper
steps) back along it, so that an extra reading x_prev over the env step's dt (BistableBar-v0's height speed,
Klann-v0's crank speed) sees that velocity as z_dot does. Putting x_prev one stepper step back instead passed the
reset, noise, frame_skip and start tests of tests/envs/test_envs.py, test_linkage_envs.py, test_bistable_env.py and
test_reset_options.py (hand mutation audit, helper-276): at frame_skip 3 the first observation's speed read a third
of the start's (0.022 for 0.065 m/s on BistableBar-v0, seed 3, noise 0.2).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import redsim  # noqa: F401  (registers the ids)


@pytest.mark.parametrize(
    ("env_id", "extra"), [("RedSim/BistableBar-v0", "height_speed"), ("RedSim/Klann-v0", "crank_speed")]
)
def test_the_start_speed_does_not_depend_on_frame_skip(env_id: str, extra: str) -> None:
    speeds, velocities = [], []
    for frame_skip in (1, 3):
        env = gym.make(env_id, reset_noise_scale=0.2, frame_skip=frame_skip, dtype="float64")
        obs, _ = env.reset(seed=3)
        structure = env.unwrapped.observation_structure
        offsets = np.cumsum([0, *structure.values()])
        index = offsets[list(structure).index(extra)]
        speeds.append(float(obs[index]))
        velocities.append(obs[offsets[1] : offsets[2]])  # z_dot
        env.close()
    np.testing.assert_array_equal(velocities[0], velocities[1])  # the same start, drawn from the same seed
    assert abs(speeds[0]) > 1e-2  # the start moves
    assert speeds[1] == pytest.approx(speeds[0], rel=0.02)  # measured 0.4% apart (the map's curvature)
