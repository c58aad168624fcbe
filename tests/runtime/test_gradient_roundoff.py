"""The stepper's measured gradient round-off (LatentStepper.roundoff_tol) and its construction warning.

A float32 stepper whose reduced force rounds by more than its tolerance's bound cannot resolve its solves to tol: on a
fine cantilever under a 5 x 128 MLP (f(0) at rest, as ``redsim bench scaling`` steps it) its steps run many times the
iterations of float64's and end unconverged, while the older construction checks (acceleration resolution, tol
against eps) said nothing. The probe must read that round-off as the float64 gradient at the same z shows it, and
stay far below tol on the shipped envs (whose check_env test allows no warning).
"""

from __future__ import annotations

import warnings

import gymnasium as gym
import pytest
import torch

import redsim  # noqa: F401  (registers the envs)
from redsim import scenes
from redsim.benches.scaling import rest_at_origin
from redsim.cubature.fit import default_load_scale
from redsim.runtime import LatentStepper
from redsim.runtime.stepper import RESOLUTION_WARNING, ROUNDOFF_TOL, _StepObjective
from redsim.subspace import SubspaceConfig, SubspaceMap


@pytest.fixture(scope="module")
def beam() -> tuple:
    """The cantilever at cells_x 30, cells_yz 6 (n = 4410) and a seeded 5 x 128 MLP with f(0) at rest."""
    scene = scenes.build("cantilever", cells_x=30, cells_yz=6)
    torch.manual_seed(0)
    subspace = SubspaceMap(SubspaceConfig(latent_dim=8, output_dim=scene.free_dof_count))
    return scene, rest_at_origin(subspace, scene)


def _gradients(stepper: LatentStepper, z: torch.Tensor) -> torch.Tensor:
    """dPhi/dz [k, d] (float64) at z [k, d] of the step from rest at z = 0 (qbar = f(0), no loads)."""
    z = z.to(stepper.dtype)
    with torch.no_grad():
        qbar = stepper._coords(torch.zeros(1, stepper.latent_dim, dtype=stepper.dtype), None).expand(z.shape[0], -1)
    objective = _StepObjective(stepper, qbar, None, None, z)
    return objective._value_and_grad(z, objective.qbar, None, None)[1].to(torch.float64)


def _iterations(stepper: LatentStepper, load: float) -> tuple[int, int]:
    """Total iterations and unconverged steps of 6 steps from rest under a sideways tip load flipped every step."""
    z = torch.zeros(1, stepper.latent_dim, dtype=stepper.dtype)
    push = torch.zeros(1, 1, 3, dtype=stepper.dtype)
    push[..., 2] = load
    z_prev, model, carry, total, unconverged = z.clone(), None, None, 0, 0
    for step in range(6):
        z_next, stats = stepper.step(z, z_prev, push if step % 2 == 0 else -push, warm=model, carry=carry)
        total += int(stats.iterations.sum())
        unconverged += int((~stats.converged).sum())
        model, carry, z_prev, z = stats.model, stats.carry, z, z_next
    return total, unconverged


def test_a_float32_stepper_whose_force_rounds_above_tol_warns_and_its_steps_show_it(beam: tuple) -> None:
    scene, subspace = beam
    with pytest.warns(UserWarning, match=r"round-off in the reduced force, measured at the map's origin") as caught:
        single = LatentStepper(scene, subspace, 0.02)
    assert len(caught) == 1  # the older checks are silent on it
    assert single.acceleration_resolution < RESOLUTION_WARNING and single.tol >= ROUNDOFF_TOL * single._eps
    assert single.roundoff_tol > single.tol
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        double = LatentStepper(scene, subspace, 0.02, dtype=torch.float64)
    assert double.roundoff_tol < 1e-3 * double.tol
    # the probe reads the float32 gradient's error against float64 at the same z (a factor 3 either way)
    u = torch.randn(8, 8, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    z = (1e-6 * u / u.norm(dim=1, keepdim=True)).to(torch.float32)
    error = (_gradients(single, z) - _gradients(double, z.to(torch.float64))).norm(dim=1).median()
    measured = float(error) / (single.jacobian_norm * single.base_force)
    assert single.roundoff_tol / 3 < measured < 3 * single.roundoff_tol
    # and the steps: float64 converges each in a step or two, float32 hunts in round-off for many times that
    load = default_load_scale(scene)
    its64, unconverged64 = _iterations(double, load)
    its32, _ = _iterations(single, load)
    assert unconverged64 == 0 and its64 <= 12
    assert its32 >= 5 * its64


@pytest.mark.parametrize("env_id", ["RedSim/MiniChain-v0", "RedSim/BistableBar-v1", "RedSim/ConditionalBar-v1"])
def test_shipped_env_steppers_round_far_below_their_tolerance(env_id: str) -> None:
    """BistableBar's is the largest of the thirteen ids (0.037 tol in float32); ConditionalBar-v1 steps a cubature."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.filterwarnings("ignore", category=DeprecationWarning)  # gymnasium's note on an older version
        env = gym.make(env_id)
    stepper = env.unwrapped.sim.stepper
    assert stepper.dtype == torch.float32
    assert 0.0 < stepper.roundoff_tol < 0.1 * stepper.tol
    env.close()
