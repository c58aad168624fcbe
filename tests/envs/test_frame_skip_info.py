"""An env step of ``frame_skip`` stepper steps reports the solver statistics of all of them in its ``info``.

``iterations`` is the solver's work over the env step (the env bench's ``iterations_per_step`` reads it) and
``energy_gain_tolerance`` the rise the energy-gain flag allowed over it: each the sum over the stepper steps, while
``energy`` and ``residual`` are the last step's. Keeping only the last stepper step's iterations passed
tests/envs/test_envs.py, test_linkage_envs.py, test_vector_api.py and test_env_ab.py, and keeping only its
tolerance their tests named for frame_skip, gain or info (hand mutation audit, helper-276).
MiniChain-v0 in float64 steps alike whether frame_skip steps it or the caller does (its loads are the action's
alone), so a frame_skip 3 step is compared with three single steps.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import redsim  # noqa: F401  (registers the ids)


def test_a_frame_skip_step_sums_the_iterations_and_tolerances_of_its_stepper_steps() -> None:
    skipping = gym.make("RedSim/MiniChain-v0", frame_skip=3, dtype="float64").unwrapped
    single = gym.make("RedSim/MiniChain-v0", dtype="float64").unwrapped
    skipping.reset(seed=0)
    single.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(3):
        action = rng.uniform(-1, 1, skipping.action_space.shape).astype(np.float32)
        obs, _, _, _, info = skipping.step(action)
        steps = [single.step(action) for _ in range(3)]
        parts = [step[4] for step in steps]
        np.testing.assert_allclose(obs, steps[-1][0], rtol=1e-9, atol=1e-9)  # the same three solves
        iterations = [int(p["iterations"]) for p in parts]
        assert min(iterations) > 0 and int(info["iterations"]) == sum(iterations), (info["iterations"], iterations)
        tolerance = sum(float(p["energy_gain_tolerance"]) for p in parts)
        assert float(info["energy_gain_tolerance"]) == pytest.approx(tolerance, rel=1e-9)
        assert float(info["energy_gain_tolerance"]) > float(parts[-1]["energy_gain_tolerance"])
        assert bool(info["converged"]) == all(bool(p["converged"]) for p in parts)
        assert float(info["energy"]) == pytest.approx(float(parts[-1]["energy"]), rel=1e-9)
        assert float(info["residual"]) == pytest.approx(float(parts[-1]["residual"]), rel=1e-6, abs=1e-15)
