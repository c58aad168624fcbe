"""The ``energy_gain`` flag: steps whose K + E rose by more than the loads' work are reported.

The ledger that judges it is the bench's (:func:`redsim.benches.stability.energy_account`, float64,
the true scene energy); the flag is the stepper's own float32 balance (:mod:`redsim.runtime.flags`).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from redsim import pretrained, scenes
from redsim.benches.stability import RISE_SLACK, energy_account, runtime_rollout
from redsim.runtime import LatentStepper
from redsim.runtime.flags import ENERGY_ROUNDOFF, energy_gain_states


def test_energy_gain_states_compares_the_rise_with_the_work() -> None:
    eps = float(torch.finfo(torch.float32).eps)
    now = torch.tensor([10.0, 10.0, 10.0, 10.0, 10.0])
    after = torch.tensor([10.5, 10.5, 9.0, 10.0 + 10 * eps, float("nan")])
    work = torch.tensor([0.0, 1.0, 0.0, 0.0, 0.0])
    inexact = torch.zeros(5)
    flags = energy_gain_states(now, after, work, inexact, eps)
    assert flags.tolist() == [True, False, False, False, True]  # gained; paid for; lost; round-off; NaN
    assert not bool(energy_gain_states(now[:1], after[:1], work[:1], torch.tensor([0.6]), eps)[0])
    assert ENERGY_ROUNDOFF * eps < RISE_SLACK  # the flag is tighter than the bench's ledger slack


@pytest.fixture(scope="module")
def mini_chain() -> tuple:
    scene = scenes.build("mini_chain")
    return scene, pretrained.load("mini_chain", scene)


def _ledger_rises(scene, stepper, zs, loads) -> torch.Tensor:
    """Per step and copy, K + E - W of the float64 scene rose by more than RISE_SLACK of its size: [T, B]."""
    T, B = loads.shape[0], loads.shape[1]
    q = stepper.positions(torch.cat(zs)).to(torch.float64).reshape(T + 2, B, -1)
    rises = []
    for b in range(B):
        mechanical, work = energy_account(scene, q[1:, b], loads[:, b].double(), stepper.dt, q[0, b])
        h = mechanical - work
        limit = RISE_SLACK * torch.maximum(mechanical[1:].abs(), mechanical[:-1].abs()).clamp_min(1.0)
        rises.append((h[1:] - h[:-1]) > limit)
    return torch.stack(rises, 1)


def test_random_loads_gain_energy_and_every_gain_is_flagged(mini_chain) -> None:
    """64 copies under uniform random tip forces (the MiniChain env's, 15 N): some steps gain, all are flagged."""
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, 0.02)
    batch, steps = 64, 12
    rng = np.random.default_rng(0)
    loads = torch.as_tensor(rng.uniform(-15.0, 15.0, (steps, batch, 1, 3)), dtype=torch.float32)
    z = stepper.rest_latent().expand(batch, -1).clone()
    zs, zp, model, flags = [z, z], z, None, []
    for t in range(steps):
        z_next, stats = stepper.step(z, zp, loads[t], warm=model)
        model = stats.model
        assert bool(stats.converged.all()) and not bool(stats.diverged.any())
        flags.append(stats.energy_gain)
        zp, z = z, z_next
        zs.append(z)
    flagged = torch.stack(flags)
    rises = _ledger_rises(scene, stepper, zs, loads)
    assert int(rises.sum()) > 0, "the scenario no longer gains energy: pick one that does"
    assert not bool((rises & ~flagged).any())  # no unreported gain
    assert int(flagged.sum()) <= 2 * int(rises.sum()) + 2  # and the flag is not raised at random


@pytest.mark.parametrize("name", ["mini_chain", "chain", "bistable_bar"])
def test_an_unloaded_release_flags_no_gain(name: str) -> None:
    """Released from the map's rest with a push and no load: backward Euler only loses energy."""
    scene = scenes.build(name)
    f = pretrained.load(name, scene)
    stepper = LatentStepper(scene, f, 0.02)
    z = stepper.rest_latent()
    kick = torch.zeros_like(z)
    kick[0, 0] = 0.05
    loads = torch.zeros(30, len(scene.handles), scene.dim, dtype=torch.float64)
    run = runtime_rollout(scene, f, loads, 0.02, z0=z[0], z_prev=(z - kick)[0])
    assert int(run.gains.sum()) == 0 and int(run.reported.sum()) == 0
    assert run.energy_rises(scene, RISE_SLACK) == []


def test_env_info_reports_energy_gain_without_ending_the_episode() -> None:
    import gymnasium as gym

    env = gym.make_vec("RedSim/MiniChain-v0", num_envs=16, vectorization_mode="vector_entry_point")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    gains = 0
    for _ in range(10):
        _, _, terminated, _, info = env.step(rng.uniform(-1.0, 1.0, (16, 3)).astype(np.float32))
        assert info["energy_gain"].dtype == bool and info["energy_gain"].shape == (16,)
        gains += int(info["energy_gain"].sum())
        assert not bool(terminated.any())  # the mini chain ends an episode only on a diverged step
    env.close()
    assert gains > 0  # uniform random actions on the mini chain gain energy on ~3% of steps
