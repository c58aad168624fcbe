"""Golden latent trajectories: a fixed seed and 50 fixed actions per id give the stored z, in float64.

Each ``tests/data/golden/<name>.npz`` holds the actions [T, A] (float32), the latents z [T + 1, d]
and rewards [T] (float64) of one rollout of the unwrapped env in float64 (the stepper's tol
1e-9), and ``solver_spread``: the largest |z| difference [unitless] between that rollout and the
same rollout solved 100x tighter or without the solver's warm start, measured when the file was
written. The test compares z to :data:`Z_TOLERANCE`, far above the solver's spread (any solver
that converges to its tolerance passes) and below what a change of the physics moves (measured
on MiniChain-v0: solver spread 6e-6; a 1% larger action scale moves z by 0.015, a 0.1% one by
0.0012; :func:`test_the_tolerance_catches_a_one_percent_change_of_the_loads`).

Files are written and checked with one torch intra-op thread (``tests/conftest.py``; ``--update`` sets it):
the round-off of another thread count is not in ``solver_spread``, and Stewart-v0's rollout moves by 1.8e-3
between one and two threads (at step 35; measured), above :data:`Z_TOLERANCE`.

The files are never rewritten by the test. After a deliberate change of an env's dynamics
(and a version bump of its id), regenerate them with::

    python tests/envs/test_golden.py --update                     # every id
    python tests/envs/test_golden.py --update RedSim/Klann-v0     # some ids
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch

import redsim

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden"
STEPS = 50
SEED = 7
DTYPE = "float64"
Z_TOLERANCE = 1e-3
"""Largest |z - z_golden| allowed [unitless; z ~ N(0, 1) over the fitted region, motions of order 1]."""
SPREAD_LIMIT = 0.3 * Z_TOLERANCE
"""``--update`` refuses a rollout whose solver spread (default vs 100x tighter tol) is above this."""
ACTION_SCALE = 0.5
"""Half the action range: under full random pushes MiniChain's step objective often has two nearby minima
(3 of 4 rollouts measured), and which one a solve lands in depends on its start, not on the physics."""
SLOW = (
    "RedSim/Chain-v0",
    "RedSim/HangingCloth-v0",
    "RedSim/HangingCloth-v1",
    "RedSim/HangingCloth-v2",
    "RedSim/Stewart-v0",
)
"""Ids whose construction or float64 steps take seconds: checked under ``-m slow`` (ClothBall-v0, on its
cubature and near-point contact, runs its 50 float64 steps in ~5 s under load: default suite)."""


PENDING: dict[str, str] = {}
"""Ids without a golden file yet, and why; ``--update ID`` writes one (then drop the id from here)."""


def golden_path(env_id: str) -> Path:
    return GOLDEN / (env_id.split("/")[-1].removesuffix("-v0").lower() + ".npz")


def golden_actions(env_id: str, action_size: int) -> np.ndarray:
    """The fixed actions [STEPS, A], uniform in [-ACTION_SCALE, ACTION_SCALE] from seed SEED (stored in the file)."""
    rng = np.random.default_rng(SEED)
    return (ACTION_SCALE * rng.uniform(-1.0, 1.0, (STEPS, action_size))).astype(np.float32)


def rollout(env_id: str, actions: np.ndarray, *, cold: bool = False, **kwargs: Any) -> dict[str, np.ndarray]:
    """z [T + 1, d] and rewards [T] of the unwrapped float64 env reset with SEED and driven by ``actions``.

    The episode is not cut at ``terminated`` (the env never resets behind the agent's back);
    ``terminated`` [T] is returned so a golden rollout can be checked to have none. ``cold``
    drops the solver's warm start before every step (each solve builds its own model).
    """
    env = gym.make(env_id, dtype=DTYPE, **kwargs).unwrapped
    env.reset(seed=SEED)
    z, rewards, terminated = [env.get_state()["z"]], [], []
    for action in actions:
        if cold:
            env.set_state({**env.get_state(), "model": None})
        _, reward, done, _, _ = env.step(action)
        z.append(env.get_state()["z"])
        rewards.append(reward)
        terminated.append(done)
    env.close()
    return {"z": np.array(z, np.float64), "rewards": np.array(rewards), "terminated": np.array(terminated)}


def update(env_id: str) -> str:
    """Write ``golden_path(env_id)``.

    Raises:
        ValueError: the rollout terminates, or its solver spread is above SPREAD_LIMIT.
    """
    env = gym.make(env_id).unwrapped
    actions = golden_actions(env_id, env.action_space.shape[0])
    env.close()
    run = rollout(env_id, actions)
    tight = rollout(env_id, actions, stepper_options={"tol": 1e-11, "max_iter": 200})
    cold = rollout(env_id, actions, cold=True)
    spread = max(float(np.abs(run["z"] - other["z"]).max()) for other in (tight, cold))
    if run["terminated"].any():
        raise ValueError(f"{env_id}: the golden rollout terminates at step {int(np.argmax(run['terminated']))}")
    if spread > SPREAD_LIMIT:
        raise ValueError(f"{env_id}: solver spread {spread:.2g} > {SPREAD_LIMIT:.2g}; the rollout is ill-conditioned")
    GOLDEN.mkdir(parents=True, exist_ok=True)
    path = golden_path(env_id)
    np.savez(path, actions=actions, z=run["z"], rewards=run["rewards"], solver_spread=spread, seed=SEED)
    motion = float(np.abs(run["z"] - run["z"][0]).max())
    return f"{env_id}: wrote {path.name} (motion {motion:.3g}, solver spread {spread:.2g})"


def _load(env_id: str) -> dict[str, np.ndarray]:
    with np.load(golden_path(env_id)) as data:
        return {k: data[k] for k in data.files}


IDS = [pytest.param(i, marks=pytest.mark.slow) if i in SLOW else i for i in redsim.envs.ids()]


def test_every_id_has_a_golden_file() -> None:
    missing = [i for i in redsim.envs.ids() if not golden_path(i).exists() and i not in PENDING]
    assert not missing, f"no golden trajectory for {missing}: run `python tests/envs/test_golden.py --update ID`"
    assert not [i for i in PENDING if golden_path(i).exists()], "a pending id has its file now: drop it from PENDING"


@pytest.mark.parametrize("env_id", IDS)
def test_rollout_matches_its_golden_trajectory(env_id: str) -> None:
    if env_id in PENDING:
        pytest.skip(PENDING[env_id])
    gold = _load(env_id)
    assert gold["solver_spread"] <= SPREAD_LIMIT
    run = rollout(env_id, gold["actions"])
    assert run["z"].shape == gold["z"].shape
    assert np.abs(gold["z"] - gold["z"][0]).max() > 100 * Z_TOLERANCE  # it moves: a frozen sim cannot pass
    error = np.abs(run["z"] - gold["z"]).max(axis=1)
    assert error.max() <= Z_TOLERANCE, f"z left the golden trajectory at step {int(np.argmax(error > Z_TOLERANCE))}"
    np.testing.assert_allclose(run["rewards"], gold["rewards"], rtol=1e-2, atol=1e-2)


def test_the_tolerance_catches_a_one_percent_change_of_the_loads() -> None:
    gold = _load("RedSim/MiniChain-v0")
    force = gym.make("RedSim/MiniChain-v0").unwrapped.task.max_force
    run = rollout("RedSim/MiniChain-v0", gold["actions"], max_force=1.01 * force)
    assert np.abs(run["z"] - gold["z"]).max() > 5 * Z_TOLERANCE  # measured 0.015


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Regenerate the golden latent trajectories (tests/data/golden).")
    parser.add_argument("--update", action="store_true", help="write the files (required: nothing is written without)")
    parser.add_argument("ids", nargs="*", help="env ids (default: all)")
    args = parser.parse_args(argv)
    if not args.update:
        parser.error("pass --update to rewrite the golden files")
    torch.set_num_threads(1)  # the tests' setting (module doc)
    ids = args.ids or redsim.envs.ids()
    for env_id in ids:
        if env_id not in redsim.envs.ids():
            parser.error(f"unknown env {env_id!r}; valid: {', '.join(redsim.envs.ids())}")
    failed = 0
    for env_id in ids:
        try:
            sys.stdout.write(update(env_id) + "\n")
        except ValueError as err:  # refused: the old file (if any) stays; the other ids go on
            sys.stderr.write(f"{err}\n")
            failed += 1
        sys.stdout.flush()
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
