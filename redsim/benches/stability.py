"""`redsim bench stability`: hard cases stay numerically stable, measured (tests call the same code, small).

Each case drives one scene or env into a regime that breaks simulators and records, per run:
steps run, failures detected (a step the solver reported: not converged or ``diverged``; or ``tunneled``, a
step whose path passed through a contact neither end shows, :mod:`redsim.integrators.tunneling`, also counted
apart; a full-space step whose first solve did and whose solve again within a trust radius ended on the
contact's near side is not a failure, counted as ``tunnels_caught``), failures recovered (a detected failure
followed, later in the same run and copy, by a converged step),
``energy_gains`` (steps flagged ``energy_gain`` by the runtime's StepStats or the reference's
StepInfo: K + E rose by more than the loads' work, :mod:`redsim.integrators.energy_gain`;
information, not a failure), ``nan`` (non-finite states, energies or observations: must be 0),
steps whose energy rose by more than its loads put in without any of those flags (``unreported``:
must be 0), the largest mechanical energy above the start and the largest work the loads did (the
bound the inputs allow). A latent step's rise within its own ``energy_gain`` tolerance (what its inexact
solve can put in, ``StepStats.energy_gain_tolerance``) is not unreported: it is counted as
``within_tolerance``. An env stepping a cubature is judged on the cubature energy it steps (its flag is); the
scene's own energy's unflagged rises beside it are counted as ``cubature_rises`` (the cubature's approximation).

The energy ledger is H_t = K_t + E(q_t) - W_t with K_t = |q_t - q_{t-1}|_M^2 / (2 h^2) and
W_t = sum_{i<t} F_i . (p(q_{i+1}) - p(q_i)) the work of the (per-step constant) handle loads F.
A converged implicit-Euler step of a convex energy never raises H (backward Euler is
dissipative); the scenes are not convex, so a rise of :data:`RISE_SLACK` (float32 runtime) or
:data:`FULL_SLACK` (float64 reference) of the step's own |K + E| (at least 1 J) is allowed without a flag.

Regimes (:data:`REGIMES`): stiffness x1000, time steps 0.1 and 0.5 s, a latent start at |z| = 10,
actions at their bounds held (``bang_bang``) and flipped every step (``alternating``), high-speed
impacts into contact, starts near element inversion, conditions at the edges of their range, and
fuzzed env steps (random actions, many at the bounds, and random resets) over every env, the
step count split in proportion to each env's measured speed. With ``mujoco`` installed,
:func:`mujoco_chain_cases` runs kicked and dropped 24-capsule chains under MuJoCo's integrators at
dt 0.01 beside redsim's chain under the same kicks (:func:`redsim_chain_cases`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from redsim import pretrained, scenes
from redsim.benches.accuracy import PLANS, Plan
from redsim.envs.cloth_ball import ClothBallEnv
from redsim.envs.conditional_bar import ConditionalBarEnv
from redsim.envs.invariants import Invariants
from redsim.integrators import FullSpace, ImplicitEuler
from redsim.integrators.reference import rest_or_warn
from redsim.integrators.tunneling import TunnelTest
from redsim.metrics.reach import nearest_latent
from redsim.runtime import LatentStepper
from redsim.scene import Scene

RISE_SLACK = 1e-3
"""Energy rise per step [fraction of the step's |K + E|, at least 1 J] a float32 latent step may show without a
flag."""
FULL_SLACK = 1e-6
"""The same for converged float64 full-space steps."""
DT = 0.02
"""The envs' time step [s]."""
LOADS: dict[str, Plan] = {
    **PLANS,
    "cloth_ball": Plan(ClothBallEnv.goal_handle, ClothBallEnv.default_max_force),
    "conditional_bar": Plan(ConditionalBarEnv.goal_handle, ConditionalBarEnv.default_max_force),
}
"""Handle and force of a unit action per scene (the envs' ``goal_handle`` and ``default_max_force``)."""
BANG_BANG_HOLD = 50
"""Steps a ``bang_bang`` action is held at one bound before it flips."""
FUZZ_COPIES = {
    "RedSim/ClothBall-v0": 8,
    "RedSim/ClothBall-v1": 8,
    "RedSim/HangingCloth-v0": 8,
    "RedSim/HangingCloth-v1": 8,
    "RedSim/HangingCloth-v2": 8,
}
"""Vector env copies of the fuzzed cloth envs: a 64-copy step takes 0.1-1 s; few copies get deep into episodes."""
DEFAULT_FUZZ_COPIES = 256
"""Vector env copies of the other fuzzed envs (Klann and MiniChain run about 2x the env steps/s of 64 copies)."""


# -- the energy ledger --------------------------------------------------------------------------
def energy_account(
    scene: Scene, q: Tensor, loads: Tensor, dt: float, q_prev: Tensor | None = None, cond: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """(K_t + E(q_t) [T + 1], W_t [T + 1]) [J] of free configurations q [T + 1, n] under loads [T, H, D].

    ``q_prev`` [n] is the state before q[0] (default q[0]: starting at rest); ``cond`` [m] the condition.
    """
    s = scene.to(dtype=torch.float64)
    q = q.to(torch.float64)
    before = q[:1] if q_prev is None else q_prev.reshape(1, -1).to(torch.float64)
    v = torch.diff(torch.cat([before, q]), dim=0)
    kinetic = 0.5 * (v * s.mass_matvec(v)).sum(-1) / dt**2
    c = None if cond is None else cond.to(torch.float64).reshape(1, -1).expand(q.shape[0], -1)
    with torch.no_grad():
        mechanical = kinetic + s.energy(q, None, c)
    if not s.handles:
        return mechanical, torch.zeros_like(mechanical)
    p = s.handle_positions(q)
    power = (loads.reshape(loads.shape[0], -1).to(torch.float64) * (p[1:] - p[:-1])).sum(-1)
    return mechanical, torch.cat([torch.zeros(1, dtype=torch.float64), torch.cumsum(power, 0)])


def ledger(
    scene: Scene, q: Tensor, loads: Tensor, dt: float, q_prev: Tensor | None = None, cond: Tensor | None = None
) -> Tensor:
    """H_t = K_t + E(q_t) - W_t [T + 1] [J] (module doc; arguments as :func:`energy_account`)."""
    mechanical, work = energy_account(scene, q, loads, dt, q_prev, cond)
    return mechanical - work


def unreported_rises(
    h: Tensor, reported: Tensor, slack: float, tolerance: Tensor | None = None, scale: Tensor | None = None
) -> list[int]:
    """Steps t whose H [T + 1] rose by more than ``slack`` times the step's own energy scale, and by more than its
    ``energy_gain`` tolerance [T] [J] where given (what its inexact solve can explain), without being reported ([T]
    bool). The scale of step t is max(|scale_t|, |scale_t+1|, 1 J), ``scale`` [T + 1] the mechanical energy K + E
    (default: H): per step, not the run's largest (H holds the loads' running work: on the stiff bar it let any step
    rise 819 J unflagged where the whole run moved 1.1 kJ), as the fuzz's ledger takes it."""
    rise = h[1:] - h[:-1]
    size = (h if scale is None else scale).abs().nan_to_num(nan=0.0, posinf=0.0)
    limit = slack * torch.maximum(torch.maximum(size[1:], size[:-1]), torch.ones_like(rise))
    bad = ~torch.isfinite(rise) | (rise > limit)
    if tolerance is not None:
        bad &= ~(rise <= tolerance.to(rise.dtype))
    return [int(t) for t in torch.nonzero(bad & ~reported.to(torch.bool)).flatten()]


def topology_counts(scene: Scene, q: Tensor) -> dict[str, int | None]:
    """From the scene's invariants (:class:`redsim.envs.invariants.Invariants`) at every state of q [T + 1, n]
    (float64), what neither NaN nor a flag shows: ``inverted``, the most elements with det F <= 0 (the stable
    neo-Hookean's energy stays finite on one), and ``unlinked``, the most chain pairs that passed through each other
    (``contact_unlinked``: exact, where the ``tunneled`` test is a detector); each None for a scene without it."""
    s = scene.to(dtype=torch.float64)
    values = {key: v.cpu() for key, v in Invariants(s)(s.full_positions(q.to(torch.float64))).items()}
    return {kind: most(values, kind) for kind in ("inverted", "unlinked")}


def most(values: dict[str, Any], kind: str) -> int | None:
    """The largest per-state sum [B] of the invariants ``values`` named ``*_<kind>`` (tensors or arrays); None without
    one."""
    counts = [np.asarray(v) for key, v in values.items() if key.endswith(f"_{kind}") and not key.startswith("_")]
    return None if not counts else int(np.sum(counts, axis=0).max())


def recovered(reported: Sequence[bool], unrecoverable: Sequence[bool] | None = None) -> int:
    """How many reported steps are followed, later in the run, by a step that was not reported.

    A reported step marked ``unrecoverable`` (a step through a contact: the motion after it is another one) is never
    counted, and it does not recover the steps before it either: it is a failure, not a good step.
    """
    never = [False] * len(reported) if unrecoverable is None else list(unrecoverable)
    count, pending = 0, 0
    for bad, lost in zip(reported, never, strict=True):
        if bad:
            pending += not lost
        else:
            count, pending = count + pending, 0
    return count


# -- rollouts -----------------------------------------------------------------------------------
@dataclasses.dataclass
class Rollout:
    """One run of one state: configurations, what each step reported, and what it cost.

    Attributes:
        q: Free configurations [T + 1, n] (float64), q[0] the start.
        q_prev: The state one step before q[0] [n].
        loads: The loads of each step [T, H, D] [N].
        dt: Time step [s].
        reported: [T] bool: the step said it failed (not converged or diverged).
        nonfinite: Non-finite states or energies met (never stepped on).
        flags: Counts of ``unconverged`` and ``tunneled`` steps; latent runs also ``diverged`` and ``out_of_range``,
            full-space runs ``tunnels_caught`` (latent runs also ``idle``: steps
            that took no iteration and ended where they began, their start z_t already within the solver's
            tolerance; a step accepted at a start that moves, extrapolated or predicted, is not idle).
        seconds: Wall time [s].
        cond: The condition [m] of a conditional scene, or None.
        gains: [T] bool: the step was flagged ``energy_gain`` (None: no such flag).
        tolerance: [T] [J]: the rise each step's ``energy_gain`` test allowed (None: the slack alone).
        tunneled: [T] bool: the step passed through a contact (among ``reported``; never counted recovered: the
            motion after it is another one). None: none.
    """

    q: Tensor
    q_prev: Tensor
    loads: Tensor
    dt: float
    reported: Tensor
    nonfinite: int
    flags: dict[str, int]
    seconds: float
    cond: Tensor | None = None
    gains: Tensor | None = None
    tolerance: Tensor | None = None
    tunneled: Tensor | None = None

    def flagged(self) -> Tensor:
        """[T] bool: the step reported a failure or an energy gain."""
        return self.reported if self.gains is None else self.reported | self.gains

    def energy_rises(self, scene: Scene, slack: float) -> list[int]:
        """Steps whose ledger rose by more than ``slack`` without being reported (a failure or an energy gain)."""
        mechanical, work = energy_account(scene, self.q, self.loads, self.dt, self.q_prev, self.cond)
        return unreported_rises(mechanical - work, self.flagged(), slack, self.tolerance, mechanical)

    def row(self, scene: Scene, target: str, regime: str, space: str, slack: float) -> dict[str, Any]:
        """The bench row of this run (module doc)."""
        mechanical, work = energy_account(scene, self.q, self.loads, self.dt, self.q_prev, self.cond)
        h = mechanical - work
        reported = [bool(r) for r in self.reported]
        return {
            "target": target,
            "regime": regime,
            "space": space,
            "steps": len(reported),
            "failures_detected": sum(reported),
            "failures_recovered": recovered(reported, None if self.tunneled is None else self.tunneled.tolist()),
            "energy_gains": 0 if self.gains is None else int(self.gains.sum()),
            "nan": self.nonfinite + int((~torch.isfinite(self.q)).any(-1).sum()),
            "unreported": len(unreported := unreported_rises(h, self.flagged(), slack, self.tolerance, mechanical)),
            "within_tolerance": len(unreported_rises(h, self.flagged(), slack, scale=mechanical)) - len(unreported),
            "start_energy_J": float(mechanical[0]),
            "max_energy_J": float((mechanical - mechanical[0]).max()),
            "input_work_J": float(work.max()),
            # None (printed -) where this space does not count it: out_of_range and idle are latent, tunnels_caught
            # full-space counts (a 0 there read as measured)
            "out_of_range": self.flags.get("out_of_range"),
            "tunneled": self.flags.get("tunneled", 0),
            "tunnels_caught": self.flags.get("tunnels_caught"),
            "idle": self.flags.get("idle"),
            **topology_counts(scene, self.q),
            "seconds": self.seconds,
        }


def runtime_rollouts(
    scene: Scene,
    f: nn.Module,
    loads: Tensor,
    dt: float,
    *,
    z0: Tensor | None = None,
    z_prev: Tensor | None = None,
    cond: Tensor | None = None,
    seconds: float | None = None,
    **options: Any,
) -> list[Rollout]:
    """B latent-runtime runs in one batch under loads [T, B, H, D], all from rest (or z0, z_prev [d]).

    ``cond`` [m] is the condition of every copy; with ``seconds`` [s] the runs stop after the step
    that used up that wall time (each Rollout then holds the steps that ran). ``options`` go to
    :class:`LatentStepper`. Each Rollout's ``seconds`` is the batch's wall time.
    """
    start = time.perf_counter()
    steps, batch = loads.shape[0], loads.shape[1]
    stepper = LatentStepper(scene, f, dt, **options)
    c = None if cond is None else cond.reshape(1, -1).to(stepper.dtype).expand(batch, -1)
    z = stepper.rest_latent(None if c is None else c[:1]) if z0 is None else z0.reshape(1, -1).to(stepper.dtype)
    z = z.expand(batch, -1).clone()
    zp = z.clone() if z_prev is None else z_prev.reshape(1, -1).to(stepper.dtype).expand(batch, -1).clone()
    zs, reported, gains, tolerances, model, carry = [zp, z], [], [], [], None, None
    nonfinite = torch.zeros(batch, dtype=torch.int64)
    flags = {k: torch.zeros(batch, dtype=torch.int64) for k in ("unconverged", "diverged", "out_of_range", "idle")}
    for i in range(steps):
        z_next, stats = stepper.step(z, zp, loads[i], c, warm=model, carry=carry)  # warm and carried as the envs do
        model, carry = stats.model, stats.carry
        bad = ~(torch.isfinite(z_next).all(-1) & torch.isfinite(stats.energy))
        nonfinite += bad.cpu()
        z_next = torch.where(torch.isfinite(z_next), z_next, z)
        flags["unconverged"] += (~stats.converged).cpu()
        flags["diverged"] += stats.diverged.cpu()
        flags["out_of_range"] += stats.out_of_range.cpu()
        flags["idle"] += ((stats.iterations == 0) & (z_next == z).all(-1)).cpu()  # left where it was
        reported.append((stats.diverged | ~stats.converged).cpu())
        gains.append(stats.energy_gain.cpu())
        tolerances.append(stats.energy_gain_tolerance.cpu().to(torch.float64))
        zp, z = z, z_next
        zs.append(z)
        if seconds is not None and time.perf_counter() - start >= seconds:
            break
    ran = len(reported)
    q = stepper.positions(torch.cat(zs), None if c is None else c[:1].expand(len(zs) * batch, -1))
    q = q.to(torch.float64).reshape(len(zs), batch, -1)
    x = scene.to(dtype=torch.float64).full_positions(q.reshape(len(zs) * batch, -1)).reshape(len(zs), batch, -1)
    steps_from, steps_to = x[1:-1].flatten(0, 1), x[2:].flatten(0, 1)  # zs: z_prev, then the start and each step's end
    tunneled = TunnelTest(scene.to(dtype=torch.float64))(steps_from, steps_to).reshape(ran, batch)
    flags["tunneled"] = tunneled.sum(0)
    seconds_used = time.perf_counter() - start
    reported_t, gains_t, tolerance_t = torch.stack(reported) | tunneled, torch.stack(gains), torch.stack(tolerances)
    return [
        Rollout(
            q[1:, b],
            q[0, b],
            loads[:ran, b],
            dt,
            reported_t[:, b],
            int(nonfinite[b]),
            {k: int(v[b]) for k, v in flags.items()},
            seconds_used,
            cond,
            gains_t[:, b],
            tolerance_t[:, b],
            tunneled[:, b],
        )
        for b in range(batch)
    ]


def runtime_rollout(scene: Scene, f: nn.Module, loads: Tensor, dt: float, **options: Any) -> Rollout:
    """One latent-runtime run (B = 1) under loads [T, H, D]; the options of :func:`runtime_rollouts`."""
    return runtime_rollouts(scene, f, loads.unsqueeze(1), dt, **options)[0]


def full_rollout(
    scene: Scene,
    loads: Tensor,
    dt: float,
    *,
    q0: Tensor | None = None,
    velocity: Tensor | None = None,
    max_iter: int = 50,
) -> Rollout:
    """A float64 full-space run from q0 [n] (default the seed) with an initial velocity [n] [m/s]."""
    start = time.perf_counter()
    integrator = ImplicitEuler(FullSpace(scene.to(dtype=torch.float64)), dt, max_iter=max_iter)
    state = integrator.initial_state(q0, velocity)
    qs, reported, gains, nonfinite = [state.q_prev, state.q], [], [], 0
    unconverged, through, caught = 0, [], 0
    for i in range(loads.shape[0]):
        state, info = integrator.step(state, loads[i])
        if not bool(torch.isfinite(state.q).all()):
            nonfinite += 1
        reported.append(not info.converged or info.tunneled)
        gains.append(info.energy_gain)
        unconverged += not info.converged
        through.append(info.tunneled)
        caught += info.tunnel_caught
        qs.append(state.q)
    seconds = time.perf_counter() - start
    flags = {"unconverged": unconverged, "tunneled": int(sum(through)), "tunnels_caught": caught}
    as_mask = lambda values: torch.tensor(values, dtype=torch.bool)  # noqa: E731
    return Rollout(
        torch.stack(qs[1:]),
        qs[0],
        loads,
        dt,
        as_mask(reported),
        nonfinite,
        flags,
        seconds,
        gains=as_mask(gains),
        tunneled=as_mask(through),
    )


def bang_bang(scene: Scene, steps: int, force: float, handle: int = 0, axis: int = 0, hold: int = 1) -> Tensor:
    """Loads [steps, H, D] [N]: +force for ``hold`` steps, then -force, ... on one handle axis."""
    loads = torch.zeros(steps, len(scene.handles), scene.dim, dtype=torch.float64)
    sign = 1.0 - 2.0 * ((torch.arange(steps) // hold) % 2).to(torch.float64)
    loads[:, handle, axis] = force * sign
    return loads


def plan_loads(scene: Scene, steps: int, hold: int, scale: float = 1.0) -> Tensor:
    """:func:`bang_bang` on the scene's :data:`LOADS` handle at ``scale`` x its unit-action force, along x."""
    plan = LOADS[scene.name]
    return bang_bang(scene, steps, scale * plan.max_force, scene.handle_names.index(plan.handle), 0, hold)


def latent_velocity(stepper: LatentStepper, z: Tensor, velocity: Tensor) -> Tensor:
    """The latent velocity [d] whose image J v_z is M-closest to a free-DOF velocity [n] at z [1, d]."""
    f = stepper.energy.positions
    z64 = z.detach().to(stepper.dtype)
    columns = torch.func.jacfwd(lambda u: f(u.unsqueeze(0), None)[0])(z64[0]).to(torch.float64)  # [n, d]
    s = stepper.source_scene.to(dtype=torch.float64)
    mj = s.mass_matvec(columns.T)  # [d, n]
    return torch.linalg.solve(mj @ columns, mj @ velocity.to(torch.float64))


def project_latent(stepper: LatentStepper, q: Tensor, z0: Tensor, iterations: int = 100) -> Tensor:
    """argmin_z |f(z) - q|_M [1, d] from z0 [1, d] (L-BFGS): a configuration [n] as the map can show it."""
    target = q.to(stepper.dtype).reshape(1, -1)
    f = stepper.energy.positions
    return nearest_latent(lambda z: f(z, None), stepper.scene, target, z0.to(stepper.dtype), max_iter=iterations)


# -- rigid motions of the chains ----------------------------------------------------------------
def rotated_chain(scene: Scene, angle: float) -> Tensor:
    """The chain's seed q [n] turned by ``angle`` [rad] about the x axis (its hook's axis: the hook still holds)."""
    c, s = math.cos(angle), math.sin(angle)
    rot = torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=torch.float64)
    x = scene.full_positions(scene.q_seed.to(torch.float64).unsqueeze(0))[0].reshape(-1, 3, 4)
    return scene.dof_map.restrict((rot @ x).reshape(1, -1))[0]


def swing_velocity(scene: Scene, q: Tensor, tip_speed: float) -> Tensor:
    """Free-DOF velocity [n] [m/s] of the chain q [n] turning rigidly about the z axis through the hook.

    The angular speed makes the farthest link centre move at ``tip_speed`` [m/s] (a kick).
    """
    x = scene.full_positions(q.to(torch.float64).unsqueeze(0))[0].reshape(-1, 3, 4)
    reach = float(torch.linalg.vector_norm(x[:, :, 3], dim=-1).max())
    omega = tip_speed / reach
    skew = torch.tensor([[0.0, -omega, 0.0], [omega, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    return scene.dof_map.restrict((skew @ x).reshape(1, -1))[0]


# -- the regimes --------------------------------------------------------------------------------
Case = Callable[[int, float | None, list[dict[str, Any]] | None], list[dict[str, Any]]]
"""A case: run it with a step budget (``long``: the length of the long runs) and a wall-time budget [s] (None: none;
only the long runs of ``action_bounds`` use it) and get its rows; given a list ``rows``, it appends each row to it as
the row finishes and returns it (a Ctrl-C then leaves the rows finished before it there)."""


def _shipped(name: str, **params: Any) -> tuple[Scene, nn.Module]:
    scene = scenes.build(name, **params)
    return scene, pretrained.load(name, scenes.build(name) if params else scene)


def _zero_loads(scene: Scene, steps: int) -> Tensor:
    return torch.zeros(steps, len(scene.handles), scene.dim, dtype=torch.float64)


def stiff_cases(
    long: int, budget: float | None = None, rows: list[dict[str, Any]] | None = None
) -> list[dict[str, Any]]:
    """Stiffness x1000 driven by the soft shipped map: bistable bar (Young's modulus), chain (contact), under
    bang-bang loads of 1000 x the env's largest force (the stiffer scene then moves about as much)."""
    rows = [] if rows is None else rows
    for name, params in (("bistable_bar", {"young": 1e8}), ("chain", {"contact_stiffness": 1e8})):
        stiff, f = _shipped(name, **params)
        loads = plan_loads(stiff, max(2, long // 10), 1, 1000.0)
        run = runtime_rollout(stiff, f, loads, DT)
        rows.append(run.row(stiff, name, "stiff_x1000", "latent", RISE_SLACK))
        full = full_rollout(stiff, loads[:2], DT)
        rows.append(full.row(stiff, name, "stiff_x1000", "full", FULL_SLACK))
    return rows


def big_dt_cases(
    long: int, budget: float | None = None, rows: list[dict[str, Any]] | None = None
) -> list[dict[str, Any]]:
    """Time steps of 0.1 and 0.5 s under actions at their bounds flipping every step."""
    rows = [] if rows is None else rows
    for name in ("mini_chain", "chain", "bistable_bar"):
        scene, f = _shipped(name)
        for dt in (0.1, 0.5):
            loads = plan_loads(scene, max(2, long // 20), 1)
            rows.append(runtime_rollout(scene, f, loads, dt).row(scene, name, f"dt_{dt:g}", "latent", RISE_SLACK))
            full = full_rollout(scene, loads[:3], dt)
            rows.append(full.row(scene, name, f"dt_{dt:g}", "full", FULL_SLACK))
    return rows


def far_latent_cases(
    long: int, budget: float | None = None, rows: list[dict[str, Any]] | None = None
) -> list[dict[str, Any]]:
    """Starts at |z| = 10 (far outside z ~ N(0, I) the maps were fitted on), released unloaded."""
    rows = [] if rows is None else rows
    for name in pretrained.names():
        scene, f = _shipped(name)
        d = int(f.latent_dim)
        z0 = torch.full((d,), 10.0 / math.sqrt(d))
        run = runtime_rollout(scene, f, _zero_loads(scene, max(2, long // 40)), DT, z0=z0)
        rows.append(run.row(scene, name, "far_latent", "latent", RISE_SLACK))
    return rows


def action_bound_cases(
    long: int, budget: float | None = None, rows: list[dict[str, Any]] | None = None
) -> list[dict[str, Any]]:
    """Actions at their bounds for ``long`` steps, held BANG_BANG_HOLD steps (``bang_bang``) or flipped each step.

    Both runs of a scene are one batch of the runtime (B = 2); ``budget`` [s] caps each scene's
    wall time (its rows then report the steps that ran).
    """
    rows = [] if rows is None else rows
    regimes = (("bang_bang", BANG_BANG_HOLD), ("alternating", 1))
    for name in ("mini_chain", "chain", "bistable_bar", "conditional_bar", "cloth_ball", "hanging_sheet"):
        scene, f = _shipped(name)
        loads = torch.stack([plan_loads(scene, long, hold) for _, hold in regimes], 1)
        runs = runtime_rollouts(scene, f, loads, DT, seconds=budget)
        for (regime, _), run in zip(regimes, runs, strict=True):
            rows.append(run.row(scene, name, regime, "latent", RISE_SLACK))
    return rows


def impact_cases(
    long: int, budget: float | None = None, rows: list[dict[str, Any]] | None = None
) -> list[dict[str, Any]]:
    """High-speed impacts into contact: chains thrown up into their hook, the ball thrown down onto the cloth.

    Full space starts from the seed (contact-free), the runtime from its rest z* (a state the
    full-space energy need not be at rest in: its first converged step can drop into contact).
    """
    rows = [] if rows is None else rows
    steps = max(2, long // 100)
    for name in ("mini_chain", "chain", "cloth_ball"):
        scene, f = _shipped(name)
        stepper = LatentStepper(scene, f, DT)
        z = stepper.rest_latent()
        for speed in (10.0, 100.0):
            x_dot = torch.zeros(scene.full_dof_count, dtype=torch.float64)
            if name == "cloth_ball":
                x_dot[-12 + 7] = -speed  # t_y of the ball (the last body's row-major [R | t])
            else:
                x_dot[7::12] = speed  # t_y of every link
            v = scene.dof_map.restrict(x_dot.unsqueeze(0))[0]
            loads = _zero_loads(scene, steps)
            regime = f"impact_{speed:g}"
            full = full_rollout(scene, loads[: 3 if name == "cloth_ball" else steps], DT, velocity=v)
            rows.append(full.row(scene, name, regime, "full", FULL_SLACK))
            kick = DT * latent_velocity(stepper, z, v).to(z)
            run = runtime_rollout(scene, f, loads, DT, z0=z[0], z_prev=z[0] - kick)
            rows.append(run.row(scene, name, regime, "latent", RISE_SLACK))
    return rows


def squashed_column(scene: Scene, column: int = 10, ratio: float = 0.05) -> Tensor:
    """Free q [n]: a 2D bar's seed, vertex column ``column`` pushed to ``ratio`` of its gap to the next (J ~ ratio)."""
    x = scene.full_positions(scene.q_seed.to(torch.float64).unsqueeze(0))[0].reshape(-1, 2).clone()
    xs = x[:, 0].unique()
    chosen = torch.isclose(x[:, 0], xs[column])
    x[chosen, 0] = xs[column + 1] - ratio * (xs[column + 1] - x[chosen, 0])
    return scene.dof_map.restrict(x.reshape(1, -1))[0]


def near_inversion_cases(
    long: int, budget: float | None = None, rows: list[dict[str, Any]] | None = None
) -> list[dict[str, Any]]:
    """FEM bars released from a state with one column of elements squashed to 5% of their width."""
    rows = [] if rows is None else rows
    for name in ("bistable_bar", "conditional_bar"):
        scene = scenes.build(name)
        loads = _zero_loads(scene, max(2, min(5, long // 100)))
        rows.append(
            full_rollout(scene, loads, DT, q0=squashed_column(scene)).row(
                scene, name, "near_inversion", "full", FULL_SLACK
            )
        )
    return rows


def condition_edge_cases(
    long: int, budget: float | None = None, rows: list[dict[str, Any]] | None = None
) -> list[dict[str, Any]]:
    """The conditional bar at the four corners of its condition range (and 20% beyond one), actions at the bounds."""
    scene, f = _shipped("conditional_bar")
    space = scene.condition_space
    low, high = space.low.to(torch.float64), space.high.to(torch.float64)
    corners = [torch.stack([a, b]) for a in (low[0], high[0]) for b in (low[1], high[1])]
    beyond = high + 0.2 * (high - low)
    rows = [] if rows is None else rows
    for cond, label in [*((c, "condition_edge") for c in corners), (beyond, "condition_beyond")]:
        run = runtime_rollout(scene, f, plan_loads(scene, max(2, long // 10), 1), DT, cond=cond)
        values = ", ".join(f"{float(v):.3g}" for v in cond)
        row = run.row(scene, "conditional_bar", f"{label} ({values})", "latent", RISE_SLACK)
        row["condition"] = [float(v) for v in cond]
        rows.append(row)
    return rows


REGIMES: dict[str, Case] = {
    "stiff": stiff_cases,
    "big_dt": big_dt_cases,
    "far_latent": far_latent_cases,
    "action_bounds": action_bound_cases,
    "impact": impact_cases,
    "near_inversion": near_inversion_cases,
    "condition_edges": condition_edge_cases,
}
"""Regime groups of the scene cases, by name (the env fuzz is :func:`fuzz_envs`)."""


# -- fuzzed env steps ---------------------------------------------------------------------------
def fuzz_actions(rng: np.random.Generator, shape: tuple[int, ...], step: int) -> np.ndarray:
    """Actions [N, A]; copy i mod 4: 0 uniform in [-1, 1], 1 at a random bound, 2 +-1 flipping, 3 x3 (clipped)."""
    actions = rng.uniform(-1.0, 1.0, shape)
    kind = np.arange(shape[0]) % 4
    actions[kind == 1] = np.sign(actions[kind == 1])
    actions[kind == 2] = 1.0 if step % 2 == 0 else -1.0
    actions[kind == 3] *= 3.0
    return actions.astype(np.float32)


class _EnvLedger:
    """Per-copy energy bookkeeping of a vector env between resets (module doc's ledger, step by step).

    E is the energy the env steps, in float64: the scene's on a map's every element, or an env's cubature
    (:class:`redsim.cubature.CubatureEnergy`, rebuilt in float64), whose ``energy_gain`` flag judges that energy
    too. Over a cubature the scene's own energy is booked beside it: its rises above the slack that neither a flag
    nor the cubature's ledger shows are the cubature's approximation (``cubature_rises``), not a failure of the step.
    """

    def __init__(self, sim: Any) -> None:
        from redsim.cubature import CubatureEnergy

        self.sim = sim
        self.scene = sim.source_scene.to(dtype=torch.float64)
        self.dt = float(sim.stepper.dt)
        rules = sim.stepper.energy.cubature if isinstance(sim.stepper.energy, CubatureEnergy) else None
        self.cubature = (
            None
            if rules is None
            else CubatureEnergy(sim.source_scene, sim.subspace, rules, dtype=torch.float64, device=sim.device)
        )
        z, q = self.state()
        self.z, self.q_prev, self.q = z, q.clone(), q
        self.start = self.mechanical(z, q, q)
        self.work = torch.zeros_like(self.start)
        self.max_energy = 0.0
        self.max_work = 0.0
        self.max_cubature_rise = 0.0  # [J], the largest of the scene energy's rises counted as cubature_rises

    def state(self) -> tuple[Tensor, Tensor]:
        """The copies' latents z [N, d] and positions q [N, n], float64."""
        return self.sim.z.to(torch.float64), self.sim.positions(self.sim.z).to(torch.float64)

    def mechanical(self, z: Tensor, q: Tensor, q_prev: Tensor, *, scene_energy: bool = False) -> Tensor:
        """K + E [N] [J] at latents z with positions q, q_prev; E the stepped energy (``scene_energy``: the scene's)."""
        v = q - q_prev
        cond = None if self.sim.cond is None else self.sim.cond.to(torch.float64)
        with torch.no_grad():
            kinetic = 0.5 * (v * self.scene.mass_matvec(v)).sum(-1) / self.dt**2
            if self.cubature is None or scene_energy:
                return kinetic + self.scene.energy(q, None, cond)
            return kinetic + self.cubature.energy(z, cond)[0]

    def rise(self, z_next: Tensor, q_next: Tensor, power: Tensor, *, scene_energy: bool = False) -> tuple[Tensor, ...]:
        """Each copy's step: (rise of K + E - W [N] [J], the slack it may rise by (:data:`RISE_SLACK`), K + E after)."""
        before = self.mechanical(self.z, self.q, self.q_prev, scene_energy=scene_energy)
        after = self.mechanical(z_next, q_next, self.q, scene_energy=scene_energy)
        slack = RISE_SLACK * torch.maximum(torch.maximum(before.abs(), after.abs()), torch.ones_like(after))
        return after - before - power, slack, after

    def step(self, reported: Tensor, tolerance: Tensor) -> tuple[int, int, np.ndarray, int]:
        """Account for one step of every copy, whose ``energy_gain`` tests allowed rises of ``tolerance`` [N] [J];
        returns (unreported rises, rises above the slack within that tolerance, the copies [N] (bool) whose state or
        K + E is not finite, unflagged rises of the scene's energy that the cubature's does not show: 0 without a
        cubature)."""
        z_next, q_next = self.state()
        loads = self.sim.loads.to(torch.float64).reshape(q_next.shape[0], -1)
        if self.scene.handles:
            power = (loads * (self.scene.handle_positions(q_next) - self.scene.handle_positions(self.q))).sum(-1)
        else:
            power = torch.zeros(q_next.shape[0], dtype=torch.float64)
        rise, slack, after = self.rise(z_next, q_next, power)
        finite = torch.isfinite(after) & torch.isfinite(q_next).all(-1)
        above = (rise > slack) & ~reported
        excused = above & (rise <= tolerance.to(rise.dtype))
        unreported = int((above & ~excused).sum())
        hidden = 0
        if self.cubature is not None:
            scene_rise, scene_slack, _ = self.rise(z_next, q_next, power, scene_energy=True)
            shown_apart = (scene_rise > scene_slack) & ~reported & ~above
            hidden = int(shown_apart.sum())
            if hidden:
                self.max_cubature_rise = max(self.max_cubature_rise, float(scene_rise[shown_apart].max()))
        self.work = self.work + power
        if bool(finite.any()):
            self.max_energy = max(self.max_energy, float((after - self.start)[finite].max()))
            self.max_work = max(self.max_work, float(self.work[finite].max()))
        self.z, self.q_prev, self.q = z_next, self.q, q_next
        return unreported, int(excused.sum()), (~finite).cpu().numpy(), hidden

    def reset(self, rows: np.ndarray) -> None:
        """Copies ``rows`` restarted at rest."""
        if not rows.any():
            return
        z, q = self.state()
        index = torch.as_tensor(np.nonzero(rows)[0])
        for mine, now in ((self.z, z), (self.q, q), (self.q_prev, q)):
            mine[index] = now[index]
        self.start[index] = self.mechanical(z, q, q)[index]
        self.work[index] = 0.0


def fuzz_copies(env_id: str, copies: int | None = None) -> int:
    """Vector env copies the fuzz runs ``env_id`` with: :data:`FUZZ_COPIES` for the cloths, else ``copies``
    (default :data:`DEFAULT_FUZZ_COPIES`)."""
    return FUZZ_COPIES.get(env_id, copies or DEFAULT_FUZZ_COPIES)


def fuzz_env(
    env_id: str,
    steps: int,
    *,
    num_envs: int | None = None,
    seed: int = 0,
    reset_probability: float = 0.01,
    seconds: float | None = None,
) -> dict[str, Any]:
    """About ``steps`` env steps (copies x vector steps) of one env under :func:`fuzz_actions` and random resets.

    Each copy is also reset when its episode ends (terminated, or the id's ``max_episode_steps``).
    ``num_envs`` copies (default :func:`fuzz_copies`); with ``seconds`` [s] it stops after the vector
    step that used up that wall time. Returns the bench row (module doc); ``steps`` is what actually
    ran, ``steps_asked`` what was asked, ``seconds`` the whole run's wall time [s] and ``stepping_seconds`` its
    steps' (after the env was made and reset).
    """
    import gymnasium as gym

    start = time.perf_counter()
    copies = int(num_envs or fuzz_copies(env_id))
    venv = gym.make_vec(env_id, num_envs=copies, vectorization_mode="vector_entry_point")
    limit = gym.spec(env_id).max_episode_steps or 10**9
    rng = np.random.default_rng(seed)
    venv.reset(seed=seed)
    stepping = time.perf_counter()  # the env made and reset: from here the steps (``stepping_seconds``)
    account = _EnvLedger(venv.unwrapped.sim)
    elapsed = np.zeros(copies, dtype=np.int64)
    pending = np.zeros(copies, dtype=np.int64)
    kinds = "steps failures recovered gains nan unreported excused hidden out_of_range tunneled resets idle"
    counts = dict.fromkeys(kinds.split(), 0)
    worst: dict[str, int | None] = {"inverted": None, "unlinked": None}
    vector_steps = max(1, math.ceil(steps / copies))
    for i in range(vector_steps):
        z_before = venv.unwrapped.sim.z.clone()
        obs, reward, terminated, truncated, info = venv.step(fuzz_actions(rng, venv.action_space.shape, i))
        still = (venv.unwrapped.sim.z == z_before).all(-1).cpu().numpy()  # before any reset below
        counts["idle"] += int((still & (np.asarray(info["iterations"]) == 0)).sum())
        for kind, value in worst.items():  # the envs' invariants (topology_counts), per copy
            step_most = most(info, kind)
            if step_most is not None:
                worst[kind] = max(value or 0, step_most)
        tunneled = np.asarray(info["tunneled"], dtype=bool)
        bad = ~np.asarray(info["converged"], dtype=bool) | np.asarray(info["diverged"], dtype=bool) | tunneled
        counts["tunneled"] += int(tunneled.sum())
        gain = np.asarray(info["energy_gain"], dtype=bool)
        tolerance = torch.as_tensor(np.asarray(info["energy_gain_tolerance"], dtype=np.float64))
        unreported, excused, nonfinite, hidden = account.step(torch.as_tensor(bad | gain), tolerance)
        counts["hidden"] += hidden
        counts["gains"] += int(gain.sum())
        nonfinite |= ~np.isfinite(obs).all(-1) | ~np.isfinite(reward) | ~np.isfinite(info["energy"])
        counts["nan"] += int(nonfinite.sum())  # copies, each once (a NaN state shows in its obs and energy too)
        counts["unreported"] += unreported
        counts["excused"] += excused
        counts["out_of_range"] += int(np.asarray(info["out_of_range"]).sum())
        counts["failures"] += int(bad.sum())
        counts["recovered"] += int(pending[~bad].sum())
        pending[~bad] = 0
        pending[bad & ~tunneled] += 1  # a step through a contact is never recovered: the motion after it is another
        counts["steps"] += copies
        elapsed += 1
        done = terminated | truncated | (elapsed >= limit) | (rng.random(copies) < reset_probability)
        if done.any():
            venv.reset(options={"reset_mask": done})
            account.reset(done)
            elapsed[done] = 0
            counts["resets"] += int(done.sum())
        if seconds is not None and time.perf_counter() - start >= seconds:
            break
    venv.close()
    return {
        "target": env_id,
        "regime": "fuzz",
        "space": "latent",
        "steps": counts["steps"],
        "steps_asked": vector_steps * copies,
        "failures_detected": counts["failures"],
        "failures_recovered": counts["recovered"],
        "energy_gains": counts["gains"],
        "nan": counts["nan"],
        "unreported": counts["unreported"],
        "within_tolerance": counts["excused"],
        "cubature_rises": None if account.cubature is None else counts["hidden"],
        "cubature_rise_max_J": None if account.cubature is None else account.max_cubature_rise,
        "max_energy_J": account.max_energy,
        "input_work_J": account.max_work,
        "out_of_range": counts["out_of_range"],
        "tunneled": counts["tunneled"],
        "idle": counts["idle"],
        **worst,
        "copies": copies,
        "resets": counts["resets"],
        "seconds": time.perf_counter() - start,
        "stepping_seconds": time.perf_counter() - stepping,
    }


def env_speeds(
    env_ids: Sequence[str], *, probe_steps: int = 3, seed: int = 0, copies: int | None = None
) -> dict[str, float]:
    """Env steps/s of each id under :func:`fuzz_env` (a few vector steps after one warm-up run; the steps' time
    only, not the env's construction and reset: ``stepping_seconds``)."""
    speeds = {}
    for env_id in env_ids:
        n = fuzz_copies(env_id, copies)
        fuzz_env(env_id, n, num_envs=n, seed=seed)  # warm-up: construction, first steps
        row = fuzz_env(env_id, probe_steps * n, num_envs=n, seed=seed)
        speeds[env_id] = row["steps"] / row["stepping_seconds"]
    return speeds


def split_steps(total: int, speeds: dict[str, float]) -> dict[str, int]:
    """``total`` env steps split in proportion to each env's speed (equal wall time per env), each >= 1."""
    if int(total) != total or total < 1:
        raise ValueError(f"steps must be an integer >= 1, got {total!r}")
    rate = sum(speeds.values())
    return {k: max(1, round(total * v / rate)) for k, v in speeds.items()}


def fuzz_envs(
    env_ids: Sequence[str],
    total: int,
    *,
    seed: int = 0,
    copies: int | None = None,
    seconds: float | None = None,
    progress: Callable[[str], None] | None = None,
) -> Iterator[dict[str, Any]]:
    """Rows of :func:`fuzz_env` over ``env_ids``, ``total`` env steps split by :func:`split_steps`.

    ``copies``: see :func:`fuzz_copies`; ``seconds`` [s]: the wall-time budget of each env's run.
    """
    if len(env_ids) > 1:
        shares = split_steps(total, env_speeds(env_ids, seed=seed, copies=copies))
    else:
        shares = {env_ids[0]: total}
    for env_id, share in shares.items():
        if progress is not None:
            progress(f"fuzz {env_id}: {share} env steps")
        yield fuzz_env(env_id, share, num_envs=fuzz_copies(env_id, copies), seed=seed, seconds=seconds)


# -- the chain beside MuJoCo --------------------------------------------------------------------
MUJOCO_INTEGRATORS = ("Euler", "implicit", "implicitfast", "RK4")
"""MuJoCo's built-in integrators (Euler is its default)."""
CHAIN_KICKS = (1.0, 3.0, 10.0, 30.0, 100.0)
"""Tip speeds [m/s] of the kicked-chain scenarios (a rigid swing about the hook)."""
CHAIN_DROPS = (90.0, 135.0, 170.0)
"""Angles [deg] the chain is lifted to, about the hook's axis, before the dropped-chain scenarios release it."""
ENERGY_GROWTH = 0.1
"""A chain run blew up when its total energy rose above the start by this fraction of the start's free energy
(its energy above the hanging rest): MuJoCo's stable runs stay within 2% at dt 0.01, its unstable ones gain 100x+."""


def chain_scenarios() -> list[tuple[str, float, float]]:
    """(label, lift angle [rad], tip speed [m/s]) of the kicked and dropped chain scenarios."""
    return [(f"kick_{v:g}", 0.0, v) for v in CHAIN_KICKS] + [(f"drop_{a:g}", math.radians(a), 0.0) for a in CHAIN_DROPS]


def mujoco_lifted_chain(integrator: str, dt: float, angle: float) -> tuple[Any, Any, float]:
    """MuJoCo's chain of :func:`redsim.runtime.bench.mujoco_chain_xml` with its energy computed, lifted rigidly by
    ``angle`` [rad] about the hook's x axis, at rest: (model, data, the hanging rest's total energy [J])."""
    import mujoco

    from redsim.runtime.bench import mujoco_chain_xml

    xml = mujoco_chain_xml(integrator=integrator, timestep=dt)
    xml = xml.replace('-9.81"/>', '-9.81"><flag energy="enable"/></option>', 1)
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    rest = float(data.energy.sum())
    data.qpos[0:4] = [math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0]
    return model, data, rest


def mujoco_chain_run(
    integrator: str, angle: float, tip_speed: float, *, steps: int, dt: float = 0.01
) -> dict[str, Any]:
    """One scenario of :func:`redsim.runtime.bench.mujoco_chain_xml` (24 capsules) under ``integrator``.

    Lifted by ``angle`` about the hook's x axis and swung about z so the tip moves at ``tip_speed``.
    Returns ``blew_up`` and why: NaN states, MuJoCo warnings (bad acceleration, instability, ...) or
    total energy growth past :data:`ENERGY_GROWTH`.
    """
    import mujoco

    from redsim.runtime.bench import MUJOCO_CHAIN_LINKS

    model, data, rest = mujoco_lifted_chain(integrator, dt, angle)
    omega = tip_speed / (0.1 * MUJOCO_CHAIN_LINKS)
    local = np.array([0.0, omega, 0.0])  # about the horizontal y axis (MuJoCo's z is up): the tip moves along x
    rot = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(angle), -math.sin(angle)], [0.0, math.sin(angle), math.cos(angle)]])
    data.qvel[0:3] = rot.T @ local  # a ball joint's velocity is in its child's frame
    mujoco.mj_forward(model, data)
    e0 = float(data.energy.sum())
    allowance = ENERGY_GROWTH * (e0 - rest)
    reason, at = "", steps
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda _text: None)  # counted through data.warning instead of printed
    try:
        reason, at = _mujoco_steps(mujoco, model, data, steps, e0 + allowance)
    finally:
        mujoco.set_mju_user_warning(previous)
    return {
        "integrator": integrator,
        "blew_up": bool(reason),
        "reason": reason or None,
        "at_step": at,
        "free_energy_J": e0 - rest,
    }


def _mujoco_steps(mujoco: Any, model: Any, data: Any, steps: int, ceiling: float) -> tuple[str, int]:
    """Step until NaN, a MuJoCo warning or total energy above ``ceiling`` [J]: (reason or "", steps run)."""
    for i in range(steps):
        mujoco.mj_step(model, data)
        if not (np.isfinite(data.qpos).all() and np.isfinite(data.qvel).all()):
            return "nan", i + 1
        if any(w.number for w in data.warning):
            return "warning", i + 1
        if float(data.energy.sum()) > ceiling:
            return "energy", i + 1
    return "", steps


def mujoco_chain_cases(steps: int = 300, dt: float = 0.01) -> list[dict[str, Any]] | None:
    """Every :func:`chain_scenarios` entry under every MuJoCo integrator (None without mujoco)."""
    try:
        import mujoco  # noqa: F401
    except ImportError:
        return None
    rows = []
    for label, angle, speed in chain_scenarios():
        for integrator in MUJOCO_INTEGRATORS:
            rows.append({"scenario": label, **mujoco_chain_run(integrator, angle, speed, steps=steps, dt=dt)})
    return rows


def redsim_chain_cases(
    steps: int = 300, dt: float = 0.01, *, full_steps: int | None = None, scenarios: Sequence[str] | None = None
) -> list[dict[str, Any]]:
    """The same scenarios on redsim's 24-link chain at ``dt``: the latent runtime and the full-space reference.

    Each space starts from its own rest (kicks: the full-space equilibrium and the latent z*) or
    from the seed lifted by the scenario's angle (drops); latent runs take it as the map can show
    it (:func:`project_latent`, :func:`latent_velocity`). A run ``blew_up`` where it met a NaN or its energy rose
    above the start by more than :data:`ENERGY_GROWTH` of its free energy (MuJoCo's test); an unreported energy gain
    is counted apart (``unreported``: it fails the command too). ``full_steps`` (default ``steps``)
    shortens the full-space runs (0.3-1 s a step).
    """
    scene, f = _shipped("chain")
    stepper = LatentStepper(scene, f, dt)
    z_rest = stepper.rest_latent()
    s64 = scene.to(dtype=torch.float64)
    latent_rest = float(s64.energy(stepper.positions(z_rest).to(torch.float64))[0])
    q_rest = rest_or_warn(scene, "the chain scenarios' full-space start")
    full_rest = float(s64.energy(q_rest.unsqueeze(0))[0])
    rows = []
    for label, angle, speed in chain_scenarios():
        if scenarios is not None and label not in scenarios:
            continue
        q0 = rotated_chain(scene, angle) if angle else q_rest
        z0 = project_latent(stepper, q0, z_rest) if angle else z_rest
        kick = dt * latent_velocity(stepper, z0, swing_velocity(scene, stepper.positions(z0)[0], speed)).to(z0)
        latent = runtime_rollout(scene, f, _zero_loads(scene, steps), dt, z0=z0[0], z_prev=z0[0] - kick)
        velocity = swing_velocity(scene, q0, speed)
        full_count = steps if full_steps is None else full_steps
        full = full_rollout(scene, _zero_loads(scene, full_count), dt, q0=q0, velocity=velocity)
        for space, run, slack, rest in (
            ("latent", latent, RISE_SLACK, latent_rest),
            ("full", full, FULL_SLACK, full_rest),
        ):
            row = run.row(scene, "chain", label, space, slack)
            row["free_energy_J"] = row["start_energy_J"] - rest
            growth = row["max_energy_J"] > ENERGY_GROWTH * row["free_energy_J"]
            row["blew_up"] = bool(row["nan"] or growth)
            rows.append({"scenario": label, **row})
    return rows


# -- output -------------------------------------------------------------------------------------
ROW_COLUMNS = (
    ("target", "scene / env"),
    ("regime", "regime"),
    ("space", "space"),
    ("steps", "steps"),
    ("failures_detected", "failures detected"),
    ("failures_recovered", "recovered"),
    ("energy_gains", "energy gains flagged"),
    ("nan", "nan"),
    ("unreported", "unreported gains"),
    ("max_energy_J", "max energy above start [J]"),
    ("input_work_J", "max load work [J]"),
    ("out_of_range", "out of range"),
    ("tunneled", "tunneled"),
    ("tunnels_caught", "tunnels caught"),
    ("idle", "idle steps"),
    ("inverted", "most inverted elements"),
    ("unlinked", "most unlinked pairs"),
)
"""Columns of :func:`markdown_rows`: (row key, header)."""


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.3g}"
    return str(value)


def markdown_rows(rows: Sequence[dict[str, Any]]) -> list[str]:
    """The rows as a markdown table (:data:`ROW_COLUMNS`)."""
    lines = ["| " + " | ".join(h for _, h in ROW_COLUMNS) + " |", "|" + "---|" * len(ROW_COLUMNS)]
    lines += ["| " + " | ".join(_cell(r.get(k)) for k, _ in ROW_COLUMNS) + " |" for r in rows]
    return lines


UNLIKE_START = 2.0
"""A latent chain run whose free energy at its start is above this many times the full-space run's starts from
another state (the map cannot show the lifted chain): :func:`chain_table` says so."""


def _free_energies(label: str, mujoco: Sequence[Mapping[str, Any]] | None, rows: Mapping[Any, Any]) -> str:
    """A scenario's free energy at the start [J]: MuJoCo's / redsim full space's / redsim latent's."""
    mine = [rows.get((label, space)) for space in ("full", "latent")]
    theirs = next((r["free_energy_J"] for r in mujoco or () if r["scenario"] == label), None)
    values = [theirs, *(None if r is None else r["free_energy_J"] for r in mine)]
    return " / ".join("-" if v is None else f"{v:.3g}" for v in values)


def _unlike_start(label: str, rows: Mapping[Any, Any]) -> bool:
    latent, full = rows.get((label, "latent")), rows.get((label, "full"))
    if latent is None or full is None:
        return False
    return latent["free_energy_J"] > UNLIKE_START * max(full["free_energy_J"], 1e-9)


def chain_table(chain: dict[str, Any]) -> list[str]:
    """Per chain scenario: which MuJoCo integrators blew up (and why), whether redsim's chains survived, and the
    free energy each started with (a latent run that starts far above the full space's is another experiment)."""
    mujoco = chain["mujoco"]
    redsim_rows = {(r["scenario"], r["space"]): r for r in chain["redsim"]}
    labels = [label for label, _, _ in chain_scenarios()]
    integrators = list(MUJOCO_INTEGRATORS) if mujoco is not None else []
    head = [
        "scenario",
        "free energy at start [J]: MuJoCo / full / latent",
        *(f"MuJoCo {i}" for i in integrators),
        "redsim latent",
        "redsim full",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label in labels:
        cells = [label, _free_energies(label, mujoco, redsim_rows)]
        for integrator in integrators:
            m = next(r for r in mujoco if r["scenario"] == label and r["integrator"] == integrator)
            cells.append(f"blew up ({m['reason']}, step {m['at_step']})" if m["blew_up"] else "ok")
        for space in ("latent", "full"):
            r = redsim_rows.get((label, space))
            if r is None:
                cells.append("-")
                continue
            state = "blew up" if r["blew_up"] else "ok"
            cells.append(
                f"{state} ({r['steps']} steps, {r.get('nan', 0)} non-finite, {r['failures_detected']} failures "
                f"detected, {r['unreported']} unreported gains)"
            )
        lines.append("| " + " | ".join(cells) + " |")
    if mujoco is None:
        lines.append("")
        lines.append("mujoco is not installed (pip install 'redsim[bench]'): the MuJoCo columns are skipped")
    else:
        survived = {
            space: sum(
                1
                for label in labels
                if any(r["blew_up"] for r in mujoco if r["scenario"] == label)
                and (label, space) in redsim_rows
                and not redsim_rows[(label, space)]["blew_up"]
            )
            for space in ("latent", "full")
        }
        broken = [label for label in labels if any(r["blew_up"] for r in mujoco if r["scenario"] == label)]
        unlike = [label for label in broken if _unlike_start(label, redsim_rows)]
        lines.append("")
        lines.append(
            f"{len(broken)} of {len(labels)} scenarios blow up at least one MuJoCo integrator at dt {chain['dt']:g}; "
            f"of those, redsim's latent chain survives {survived['latent']} and its full-space chain "
            f"{survived['full']}"
        )
        if unlike:
            lines.append(
                f"not the same experiment in latent space: {', '.join(unlike)} (the latent run starts with more than "
                f"{UNLIKE_START:g}x the full space's free energy: the map cannot show that start, and its projection "
                "is a strained state)"
            )
    return lines


def row_totals(rows: Sequence[Mapping[str, Any]]) -> dict[str, int]:
    """Sums over the table's rows of ``nan`` and ``unreported`` (both must be 0), ``energy_gains``,
    ``within_tolerance``, ``cubature_rises`` and ``steps``."""
    keys = ("nan", "unreported", "energy_gains", "within_tolerance", "cubature_rises", "steps")
    return {k: sum(int(r.get(k) or 0) for r in rows) for k in keys}


def report(result: dict[str, Any]) -> list[str]:
    """Human-readable lines of a :mod:`redsim bench stability <redsim.benches.stability>` result."""
    rows, lines = result["rows"], []
    if rows:  # none when only the MuJoCo chain regime ran
        lines += markdown_rows(rows)
        fuzz = [r for r in rows if r["regime"] == "fuzz"]
        if fuzz:
            lines.append("")
            lines.append(
                f"fuzzed env steps run: {sum(r['steps'] for r in fuzz)} of {sum(r['steps_asked'] for r in fuzz)} "
                f"planned ({result['fuzz_steps']} asked, split by measured env speed, each env's share rounded up to "
                "whole vector steps of its copies)"
            )
        totals = row_totals(rows)
        lines.append(f"total nan: {totals['nan']}, unreported energy gains: {totals['unreported']} (both must be 0)")
        lines.append(f"steps flagged energy_gain: {totals['energy_gains']} of {totals['steps']} (not failures)")
        lines.append(
            f"rises above the slack that the solve's tolerance explains (not flagged, by the flag's rule): "
            f"{totals['within_tolerance']}"
        )
        cubature = [r for r in rows if r.get("cubature_rises") is not None]
        if cubature:
            largest = max(r.get("cubature_rise_max_J") or 0.0 for r in cubature)
            lines.append(
                f"rises of the scene's own energy that the cubature energy the env steps does not show (the cubature's "
                f"approximation, not a failure; {', '.join(r['target'] for r in cubature)}): "
                f"{totals['cubature_rises']}, the largest {largest:.3g} J"
            )
    if result.get("chain") is not None:
        lines += [""] * bool(lines) + chain_table(result["chain"])
    return lines


__all__ = [
    "BANG_BANG_HOLD",
    "DEFAULT_FUZZ_COPIES",
    "FULL_SLACK",
    "LOADS",
    "REGIMES",
    "RISE_SLACK",
    "Rollout",
    "bang_bang",
    "chain_scenarios",
    "chain_table",
    "energy_account",
    "full_rollout",
    "fuzz_copies",
    "fuzz_env",
    "fuzz_envs",
    "ledger",
    "markdown_rows",
    "mujoco_chain_cases",
    "plan_loads",
    "recovered",
    "redsim_chain_cases",
    "report",
    "row_totals",
    "runtime_rollout",
    "runtime_rollouts",
    "split_steps",
    "unreported_rises",
]
