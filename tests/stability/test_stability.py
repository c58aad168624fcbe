"""Hard cases stay numerically stable: stiff materials, big steps, impacts, extreme and NaN actions.

The rollouts and the ledger are :mod:`redsim.benches.stability`'s (the code of ``redsim bench
stability``), here at small sizes. Every regime runs through the latent runtime
(:class:`redsim.runtime.LatentStepper`) and the float64 full-space reference
(:class:`redsim.integrators.ImplicitEuler` over :class:`FullSpace`). Asserted everywhere: every
state finite; every step that gained more energy than its loads put in is reported (runtime:
``diverged`` or not ``converged``; full space: ``SolveInfo.converged`` False); non-finite inputs
raise before anything is stepped.

The energy ledger and its slack (RISE_SLACK for the float32 runtime, FULL_SLACK for the float64
reference) are described in :mod:`redsim.benches.stability`.
"""

from __future__ import annotations

import pytest
import torch

from redsim import pretrained, scenes
from redsim.benches.stability import (
    BANG_BANG_HOLD,
    FULL_SLACK,
    RISE_SLACK,
    bang_bang,
    full_rollout,
    plan_loads,
    runtime_rollout,
    squashed_column,
)
from redsim.integrators import FullSpace, ImplicitEuler
from redsim.runtime import LatentStepper
from redsim.solvers import ConvergenceError


def unstable_steps(run, scene, slack: float) -> list[int]:
    """Every state of ``run`` finite (asserted), then the steps that gained energy without a report."""
    assert run.nonfinite == 0 and bool(torch.isfinite(run.q).all())
    return run.energy_rises(scene, slack)


@pytest.fixture(scope="module")
def mini_chain():
    return scenes.build("mini_chain"), pretrained.load("mini_chain")


# -- big time steps ---------------------------------------------------------------------------
@pytest.mark.parametrize("dt", [0.1, 0.5])
def test_runtime_big_steps_stay_finite_and_report_energy_gains(mini_chain, dt: float) -> None:
    scene, f = mini_chain
    loads = bang_bang(scene, 12, 15.0)
    run = runtime_rollout(scene, f, loads, dt)
    assert unstable_steps(run, scene, RISE_SLACK) == []


@pytest.mark.parametrize("dt", [0.1, 0.5])
def test_full_space_big_steps_stay_finite_and_never_gain_energy(mini_chain, dt: float) -> None:
    scene, _ = mini_chain
    loads = bang_bang(scene, 8, 15.0)
    run = full_rollout(scene, loads, dt)
    assert unstable_steps(run, scene, FULL_SLACK) == []


# -- stiff materials --------------------------------------------------------------------------
def test_stiff_bar_x1000_stays_finite_in_both_spaces() -> None:
    """The bistable bar at 1000x its Young's modulus, driven by its shipped (soft) map and in full space."""
    soft = scenes.build("bistable_bar")
    stiff = scenes.build("bistable_bar", young=1e8)
    f = pretrained.load("bistable_bar", soft)
    loads = bang_bang(stiff, 6, 2e5)
    run = runtime_rollout(stiff, f, loads, 0.02)
    assert unstable_steps(run, stiff, RISE_SLACK) == []
    full = full_rollout(stiff, loads[:2], 0.02)
    assert unstable_steps(full, stiff, FULL_SLACK) == []


# -- impacts ------------------------------------------------------------------------------------
@pytest.mark.parametrize("speed", [10.0, 100.0])
def test_high_speed_impact_into_the_hook(mini_chain, speed: float) -> None:
    """The chain thrown upward at ``speed`` [m/s] into its hook (torus contact): finite, no hidden gain."""
    scene, f = mini_chain
    up = torch.zeros(scene.free_dof_count, dtype=torch.float64)
    up[7::12] = speed  # t_y of each body's row-major [R | t] (the mini chain has no pinned entries)
    loads = torch.zeros(5, len(scene.handles), scene.dim, dtype=torch.float64)
    full = full_rollout(scene, loads, 0.02, velocity=up)
    assert unstable_steps(full, scene, FULL_SLACK) == []
    stepper = LatentStepper(scene, f, 0.02)
    z = stepper.rest_latent()[0]
    kick = torch.zeros_like(z)
    kick[0] = speed * 0.02  # a latent velocity of the same order, in z per step
    run = runtime_rollout(scene, f, loads, 0.02, z0=z, z_prev=z - kick)
    assert unstable_steps(run, scene, RISE_SLACK) == []


# -- extreme and invalid actions ----------------------------------------------------------------
def test_huge_loads_are_flagged_not_hidden(mini_chain) -> None:
    scene, f = mini_chain
    loads = bang_bang(scene, 6, 1e6)
    run = runtime_rollout(scene, f, loads, 0.02)
    assert run.flags["diverged"] + run.flags["out_of_range"] + run.flags["unconverged"] > 0
    assert unstable_steps(run, scene, RISE_SLACK) == []


def test_far_latent_start_stays_finite_and_out_of_range(mini_chain) -> None:
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, 0.02)
    z = torch.full((1, stepper.latent_dim), 10.0 / stepper.latent_dim**0.5)  # |z| = 10
    run = runtime_rollout(scene, f, torch.zeros(10, 1, 3, dtype=torch.float64), 0.02, z0=z)
    assert run.flags["out_of_range"] >= 1
    assert run.nonfinite == 0 and bool(torch.isfinite(run.q).all())  # the "stays finite" of the name


def test_a_latent_the_observation_clips_is_flagged_out_of_range() -> None:
    """Chain-v0 (d = 8): the map's radius is 4 sqrt(8) = 11.3, the observation clips each latent at LATENT_BOUND = 10,
    so a latent at 10.2-10.9 with |z| < 11.3 was clipped silently (out_of_range False); the env flags it now."""
    import gymnasium as gym
    import numpy as np

    from redsim.envs.base import LATENT_BOUND
    from redsim.runtime.flags import out_of_range_states

    env = gym.make("RedSim/Chain-v0")
    env.reset(seed=0)
    sim, state = env.unwrapped.sim, env.unwrapped.get_state()
    low, high = env.observation_space.low, env.observation_space.high
    zero = np.zeros(env.action_space.shape, np.float32)
    for start, before in ((-10.5, -10.5), (-11.0, -10.6)):  # at rest beyond the bound; moving out (lands at -10.2)
        z, z_prev = np.zeros(8), np.zeros(8)
        z[7], z_prev[7] = start, before
        assert not bool(out_of_range_states(torch.tensor(z[None]), (), None, None)[0])  # inside the map's radius
        env.unwrapped.set_state({**state, "z": z, "z_prev": z_prev})
        obs, _, _, _, info = env.step(zero)
        assert info["out_of_range"] and not info["diverged"], (start, info)
        clipped = (obs <= low) | (obs >= high)
        assert not clipped[:16].any() or bool((sim.z.abs() > LATENT_BOUND).any())  # a clip shows a latent beyond
    env.unwrapped.set_state({**state, "z": np.full(8, 3.0), "z_prev": np.full(8, 3.0)})  # |z| = 8.5: in range
    assert not env.step(zero)[4]["out_of_range"]
    # a z_prev set far out (a latent velocity of 5e5/s that no step of the map made) is the step's start too: on
    # MiniChain-v0 the step from it lands in range, and reported nothing (a review's case); now it is flagged, and
    # the step after it, from states in range, is not
    mini = gym.make("RedSim/MiniChain-v0").unwrapped
    mini.reset(seed=0)
    state = mini.get_state()
    mini.set_state({**state, "z_prev": state["z"] - 1e4, "z_before": state["z"] - 1e4})
    assert mini.step(zero)[4]["out_of_range"] and not out_of_range_states(mini.sim.z, (), None, None)[0]
    assert not mini.step(zero)[4]["out_of_range"]


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_actions_are_rejected_with_a_message(mini_chain, bad: float) -> None:
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, 0.02)
    z = stepper.rest_latent()
    loads = torch.zeros(1, 1, 3)
    loads[0, 0, 1] = bad
    with pytest.raises(ValueError, match="loads must be finite"):
        stepper.step(z, z, loads)
    integrator = ImplicitEuler(FullSpace(scene.to(dtype=torch.float64)), 0.02)
    with pytest.raises(ValueError, match="loads must be finite"):
        integrator.step(integrator.initial_state(), loads[0].double())


def test_unconverged_full_step_is_reported_and_strict_raises() -> None:
    """One Newton iteration cannot converge a loaded bistable-bar step: the SolveInfo says so, strict=True raises."""
    scene = scenes.build("bistable_bar").to(dtype=torch.float64)
    loads = torch.zeros(1, 2, dtype=torch.float64)
    loads[0, 1] = 200.0
    lax = ImplicitEuler(FullSpace(scene), 0.02, max_iter=1)
    state, info = lax.step(lax.initial_state(), loads)
    assert not info.converged and "not converged" in info.message
    assert bool(torch.isfinite(state.q).all())
    strict = ImplicitEuler(FullSpace(scene), 0.02, max_iter=1, strict=True)
    with pytest.raises(ConvergenceError):
        strict.step(strict.initial_state(), loads)


# -- starts near element inversion ---------------------------------------------------------------
def test_start_near_inversion_recovers() -> None:
    """A bistable-bar state with one column of vertices pushed almost onto its neighbour (J ~ 0.05)."""
    scene = scenes.build("bistable_bar")
    q0 = squashed_column(scene)
    loads = torch.zeros(2, 1, 2, dtype=torch.float64)
    run = full_rollout(scene, loads, 0.02, q0=q0)
    assert unstable_steps(run, scene, FULL_SLACK) == []


# -- long runs (slow) ---------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("name", ["mini_chain", "chain", "bistable_bar"])
def test_bang_bang_for_thousands_of_steps(name: str) -> None:
    """Actions at their bounds, alternating every step, for 2000 steps of the runtime."""
    scene = scenes.build(name)
    f = pretrained.load(name, scene)
    force = {"mini_chain": 15.0, "chain": 40.0, "bistable_bar": 200.0}[name]
    loads = bang_bang(scene, 2000, force)
    run = runtime_rollout(scene, f, loads, 0.02)
    assert unstable_steps(run, scene, RISE_SLACK) == []


@pytest.mark.slow
@pytest.mark.parametrize("dt", [0.1, 0.5])
def test_chain_big_steps_full_and_latent(dt: float) -> None:
    scene = scenes.build("chain")
    f = pretrained.load("chain", scene)
    loads = bang_bang(scene, 10, 40.0)
    run = runtime_rollout(scene, f, loads, dt)
    assert unstable_steps(run, scene, RISE_SLACK) == []
    full = full_rollout(scene, loads, dt)
    assert unstable_steps(full, scene, FULL_SLACK) == []


# -- stiff contact and actions at their bounds, fast (the bench's slow regimes run them longer) ---------------------
def test_stiff_contact_x1000_stays_finite_and_its_failures_are_counted() -> None:
    """The mini chain's contact 1000x stiffer than its shipped (soft) map was fitted for, under bang-bang loads of
    1000x the env's force: finite in both spaces, no unreported gain, and every step the solver or the tunnel test
    reported is in the row's ``failures detected``."""
    stiff = scenes.build("mini_chain", contact_stiffness=1e8)
    f = pretrained.load("mini_chain", scenes.build("mini_chain"))
    loads = plan_loads(stiff, 6, 1, 1000.0)
    for run, space, slack in (
        (runtime_rollout(stiff, f, loads, 0.02), "latent", RISE_SLACK),
        (full_rollout(stiff, loads[:2], 0.02), "full", FULL_SLACK),
    ):
        assert unstable_steps(run, stiff, slack) == []
        row = run.row(stiff, "mini_chain", "stiff_x1000", space, slack)
        assert row["nan"] == 0 and row["unreported"] == 0
        assert row["failures_detected"] == int(run.reported.sum()) >= run.flags["unconverged"]


@pytest.mark.parametrize("hold", [BANG_BANG_HOLD, 1])
def test_actions_at_their_bounds_held_or_flipped_stay_finite(mini_chain, hold: int) -> None:
    """Actions at +-1 (the env's force) held ``hold`` steps then flipped (bang-bang), or flipped every step, for 120
    steps of the runtime: finite, every energy rise reported."""
    scene, f = mini_chain
    run = runtime_rollout(scene, f, plan_loads(scene, 120, hold), 0.02)
    assert unstable_steps(run, scene, RISE_SLACK) == []
    assert run.row(scene, "mini_chain", "bounds", "latent", RISE_SLACK)["unreported"] == 0


def test_a_full_space_step_through_a_link_is_caught() -> None:
    """The stiff mini chain's first full-space step under 15 kN (1000x the env's force) throws link 1 8.8 m through
    link 0's wire: its tunnel test flags it and the step is solved again, so the chain stays linked (the exact
    topology count ``unlinked`` reads 0) and the catch is counted. Before the tunnel test sampled only the part of a
    path near the shape, that step converged unflagged with the chain torn apart (``unlinked`` 2, the bench's stiff
    regime ``failures detected`` 0 beside ``most unlinked pairs`` 2)."""
    from redsim.benches.stability import topology_counts

    stiff = scenes.build("mini_chain", contact_stiffness=1e8)
    run = full_rollout(stiff, plan_loads(stiff, 1, 1, 1000.0), 0.02)
    unlinked = topology_counts(stiff, run.q[1:])["unlinked"]
    assert unlinked == 0 and run.flags["tunnels_caught"] == 1
