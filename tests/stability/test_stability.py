"""Hard cases stay numerically stable: stiff materials, big steps, impacts, extreme and NaN actions.

Every regime runs through the latent runtime (:class:`redsim.runtime.LatentStepper`) and the
float64 full-space reference (:class:`redsim.integrators.ImplicitEuler` over
:class:`FullSpace`). Asserted everywhere: every state finite; every step that gained more energy
than its loads put in is reported (runtime: ``diverged`` or not ``converged``; full space:
``SolveInfo.converged`` False); non-finite inputs raise before anything is stepped.

The energy ledger is H_t = K_t + E(q_t) - W_t with K_t = |q_t - q_{t-1}|_M^2 / (2 h^2) and
W_t = sum_{i<t} F_i . (p(q_{i+1}) - p(q_i)) the work of the (per-step constant) handle loads.
A converged implicit-Euler step of a convex energy never raises H (backward Euler is
dissipative); the scenes here are not convex, so a small rise is allowed: RISE_SLACK of the
trajectory's largest |H| (float32 runtime) or ``FULL_SLACK`` (float64 reference, converged at
1e-8 of its force scale).
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from redsim import pretrained, scenes
from redsim.integrators import FullSpace, ImplicitEuler
from redsim.runtime import LatentStepper
from redsim.solvers import ConvergenceError

RISE_SLACK = 1e-3
"""Energy rise per step [fraction of max |H|] a float32 latent step may show without a flag."""
FULL_SLACK = 1e-6
"""The same for converged float64 full-space steps."""


def _handle_positions(scene, q: torch.Tensor) -> torch.Tensor:
    x = scene.full_positions(q)
    return torch.cat([h.position(x) for h in scene.handles], -1)


def ledger(scene, q: torch.Tensor, loads: torch.Tensor, dt: float, q_prev: torch.Tensor | None = None) -> torch.Tensor:
    """H_t [T + 1] [J] of free configurations q [T + 1, n] under loads [T, H, D] (module doc).

    ``q_prev`` [n] is the state before q[0] (default q[0]: starting at rest).
    """
    s = scene.to(dtype=torch.float64)
    q = q.to(torch.float64)
    before = q[:1] if q_prev is None else q_prev.reshape(1, -1).to(torch.float64)
    v = torch.diff(torch.cat([before, q]), dim=0)
    kinetic = 0.5 * (v * s.mass_matvec(v)).sum(-1) / dt**2
    p = _handle_positions(s, q)
    power = (loads.reshape(loads.shape[0], -1).to(torch.float64) * (p[1:] - p[:-1])).sum(-1)
    work = torch.cat([torch.zeros(1, dtype=torch.float64), torch.cumsum(power, 0)])
    return kinetic + s.energy(q) - work


def unreported_rises(h: torch.Tensor, reported: torch.Tensor, slack: float) -> list[int]:
    """Steps t whose H rose by more than ``slack`` max|H| without being reported (reported: [T] bool)."""
    rise = h[1:] - h[:-1]
    limit = slack * float(h.abs().max().clamp_min(1.0))
    return [t for t in range(rise.shape[0]) if float(rise[t]) > limit and not bool(reported[t])]


@dataclasses.dataclass
class Rollout:
    q: torch.Tensor  # [T + 1, n] float64
    q_prev: torch.Tensor  # [n]: the state one step before q[0]
    reported: torch.Tensor  # [T] bool: the step said it failed
    flags: dict[str, int]

    def energy_rises(self, scene, loads: torch.Tensor, dt: float, slack: float) -> list[int]:
        """Steps whose ledger rose by more than ``slack`` without being reported."""
        return unreported_rises(ledger(scene, self.q, loads, dt, self.q_prev), self.reported, slack)


def runtime_rollout(scene, f, loads, dt, *, z0=None, z_prev=None, **options) -> Rollout:
    """B = 1 runtime rollout from rest (or z0, z_prev) under loads [T, H, D]; every state checked finite."""
    stepper = LatentStepper(scene, f, dt, **options)
    z = stepper.rest_latent() if z0 is None else z0.reshape(1, -1).to(stepper.dtype)
    zp = z.clone() if z_prev is None else z_prev.reshape(1, -1).to(stepper.dtype)
    zs, reported = [zp, z], []
    flags = {"unconverged": 0, "diverged": 0, "out_of_range": 0}
    for i in range(loads.shape[0]):
        z_next, stats = stepper.step(z, zp, loads[i : i + 1])
        assert bool(torch.isfinite(z_next).all()), f"non-finite latent at step {i}"
        assert bool(torch.isfinite(stats.energy).all()), f"non-finite energy at step {i}"
        flags["unconverged"] += int((~stats.converged).sum())
        flags["diverged"] += int(stats.diverged.sum())
        flags["out_of_range"] += int(stats.out_of_range.sum())
        reported.append(bool(stats.diverged[0]) or not bool(stats.converged[0]))
        zp, z = z, z_next
        zs.append(z)
    q = stepper.positions(torch.cat(zs)).to(torch.float64)
    assert bool(torch.isfinite(q).all())
    return Rollout(q[1:], q[0], torch.tensor(reported), flags)


def full_rollout(scene, loads, dt, *, q0=None, velocity=None, max_iter=50) -> Rollout:
    """Full-space float64 rollout from q0 (default the seed) with an initial velocity [n] [m/s]."""
    integrator = ImplicitEuler(FullSpace(scene.to(dtype=torch.float64)), dt, max_iter=max_iter)
    state = integrator.initial_state(q0, velocity)
    qs, reported = [state.q_prev, state.q], []
    for i in range(loads.shape[0]):
        state, info = integrator.step(state, loads[i])
        assert bool(torch.isfinite(state.q).all()), f"non-finite state at step {i}"
        if not info.converged:
            assert "not converged" in info.message or "failed" in info.message, info.message
        reported.append(not info.converged)
        qs.append(state.q)
    return Rollout(torch.stack(qs[1:]), qs[0], torch.tensor(reported), {"unconverged": int(sum(reported))})


def bang_bang(scene, steps: int, force: float, handle: int = 0, axis: int = 0) -> torch.Tensor:
    """Loads [steps, H, D]: +force, -force, +force, ... on one handle axis (an action at its bounds)."""
    loads = torch.zeros(steps, len(scene.handles), scene.dim, dtype=torch.float64)
    loads[0::2, handle, axis] = force
    loads[1::2, handle, axis] = -force
    return loads


@pytest.fixture(scope="module")
def mini_chain():
    return scenes.build("mini_chain"), pretrained.load("mini_chain")


# -- big time steps ---------------------------------------------------------------------------
@pytest.mark.parametrize("dt", [0.1, 0.5])
def test_runtime_big_steps_stay_finite_and_report_energy_gains(mini_chain, dt: float) -> None:
    scene, f = mini_chain
    loads = bang_bang(scene, 12, 15.0)
    run = runtime_rollout(scene, f, loads, dt)
    assert run.energy_rises(scene, loads, dt, RISE_SLACK) == []


@pytest.mark.parametrize("dt", [0.1, 0.5])
def test_full_space_big_steps_stay_finite_and_never_gain_energy(mini_chain, dt: float) -> None:
    scene, _ = mini_chain
    loads = bang_bang(scene, 8, 15.0)
    run = full_rollout(scene, loads, dt)
    assert run.energy_rises(scene, loads, dt, FULL_SLACK) == []


# -- stiff materials --------------------------------------------------------------------------
def test_stiff_bar_x1000_stays_finite_in_both_spaces() -> None:
    """The bistable bar at 1000x its Young's modulus, driven by its shipped (soft) map and in full space."""
    soft = scenes.build("bistable_bar")
    stiff = scenes.build("bistable_bar", young=1e8)
    f = pretrained.load("bistable_bar", soft)
    loads = bang_bang(stiff, 6, 2e5)
    run = runtime_rollout(stiff, f, loads, 0.02)
    assert run.energy_rises(stiff, loads, 0.02, RISE_SLACK) == []
    full = full_rollout(stiff, loads[:2], 0.02)
    assert full.energy_rises(stiff, loads[:2], 0.02, FULL_SLACK) == []


# -- impacts ------------------------------------------------------------------------------------
@pytest.mark.parametrize("speed", [10.0, 100.0])
def test_high_speed_impact_into_the_hook(mini_chain, speed: float) -> None:
    """The chain thrown upward at ``speed`` [m/s] into its hook (torus contact): finite, no hidden gain."""
    scene, f = mini_chain
    up = torch.zeros(scene.free_dof_count, dtype=torch.float64)
    up[7::12] = speed  # t_y of each body's row-major [R | t] (the mini chain has no pinned entries)
    loads = torch.zeros(5, len(scene.handles), scene.dim, dtype=torch.float64)
    full = full_rollout(scene, loads, 0.02, velocity=up)
    assert full.energy_rises(scene, loads, 0.02, FULL_SLACK) == []
    stepper = LatentStepper(scene, f, 0.02)
    z = stepper.rest_latent()[0]
    kick = torch.zeros_like(z)
    kick[0] = speed * 0.02  # a latent velocity of the same order, in z per step
    run = runtime_rollout(scene, f, loads, 0.02, z0=z, z_prev=z - kick)
    assert run.energy_rises(scene, loads, 0.02, RISE_SLACK) == []


# -- extreme and invalid actions ----------------------------------------------------------------
def test_huge_loads_are_flagged_not_hidden(mini_chain) -> None:
    scene, f = mini_chain
    loads = bang_bang(scene, 6, 1e6)
    run = runtime_rollout(scene, f, loads, 0.02)
    assert run.flags["diverged"] + run.flags["out_of_range"] + run.flags["unconverged"] > 0
    assert run.energy_rises(scene, loads, 0.02, RISE_SLACK) == []


def test_far_latent_start_stays_finite_and_out_of_range(mini_chain) -> None:
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, 0.02)
    z = torch.full((1, stepper.latent_dim), 10.0 / stepper.latent_dim**0.5)  # |z| = 10
    run = runtime_rollout(scene, f, torch.zeros(10, 1, 3, dtype=torch.float64), 0.02, z0=z)
    assert run.flags["out_of_range"] >= 1


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
    x = scene.full_positions(scene.q_seed.unsqueeze(0))[0].reshape(-1, 2).clone()
    column = torch.isclose(x[:, 0], x[:, 0].unique()[10])
    right = x[:, 0].unique()[11]
    x[column, 0] = right - 0.05 * (right - x[column, 0])
    q0 = scene.dof_map.restrict(x.reshape(1, -1))[0]
    loads = torch.zeros(2, 1, 2, dtype=torch.float64)
    run = full_rollout(scene, loads, 0.02, q0=q0)
    assert run.energy_rises(scene, loads, 0.02, FULL_SLACK) == []


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
    assert run.energy_rises(scene, loads, 0.02, RISE_SLACK) == []


@pytest.mark.slow
@pytest.mark.parametrize("dt", [0.1, 0.5])
def test_chain_big_steps_full_and_latent(dt: float) -> None:
    scene = scenes.build("chain")
    f = pretrained.load("chain", scene)
    loads = bang_bang(scene, 10, 40.0)
    run = runtime_rollout(scene, f, loads, dt)
    assert run.energy_rises(scene, loads, dt, RISE_SLACK) == []
    full = full_rollout(scene, loads, dt)
    assert full.energy_rises(scene, loads, dt, FULL_SLACK) == []
