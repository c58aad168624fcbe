"""`redsim bench accuracy SCENE`: what accuracy costs in time, against a converged full-space reference.

For each seeded scenario of a scene (loads on one handle as the environments apply them: an
action in [-1, 1]^D times the env's ``max_force``, :data:`PLANS`; for any other scene, e.g. a fitted mesh's,
as the reach task of ``redsim.envs.make`` applies them, :func:`reach_plan`), the reference is float64
full-space implicit Euler (:class:`redsim.integrators.ImplicitEuler` over :class:`FullSpace`,
Newton, converged to ``PLANS[scene].reference_tol``) started from the full-space rest
equilibrium (:func:`redsim.integrators.reference.rest_state`). Every configuration runs the same
loads side by side in one process, all of a scenario's stepped in turn, step by step (:func:`lockstep`), so that a
load on the machine that changes during the bench falls on every row's time alike:

- full space, loosened: a looser tolerance, a fixed small number of Newton iterations, a larger
  time step (compared at the reference's times it lands on);
- subspaces of the same d: the shipped neural map, linear modes and modal derivatives (both
  built at the full rest state, σ of the neural fit), each stepped by the runtime
  (:class:`redsim.runtime.LatentStepper`, B = 1, float32 or float64, its Hessian models and
  iteration budgets) and by the converged latent reference (``ImplicitEuler(LatentSpace)``,
  float64 Newton), which separates the subspace's error from the solver's;
- with ``maps`` (neural maps of several d, e.g. fitted with the scene's preset): the three
  subspaces at each of those d, labelled ``KIND d=D`` (the runtime's other options only for the
  map given as ``neural``);
- a neural map with a cubature (``cubatures``): also the runtime with the cubature energy
  (:class:`redsim.cubature.CubatureEnergy`) instead of the map's full energy.

A latent run starts from the subspace's own rest (its unloaded equilibrium z*), so a subspace
whose rest is not a full-space equilibrium does not count its fall as error; the offset between
the two rests is reported on its own (``rest offset``). Errors compare displacements from each
run's own start:

    e(t) = |(q(t) - q(0)) - (q_ref(t) - q_ref(0))|_M / max_s |q_ref(s) - q_ref(0)|_M,

its mean over the steps, and the same for the handle's position in cm (``handle cm``: mean of
|Δp(t) - Δp_ref(t)|). ``projection`` is the floor no latent solver can beat: the mean over every
10th step of min_z |(f(z) - f(z*)) - (q_ref(t) - q_ref(0))|_M, relative as e(t). It bounds a latent run's e(t)
at those steps (``rel_error_at_projection_steps`` in the JSON), not its mean over every step, which takes in the
early steps where e(t) is small and can sit below the floor. The row
:data:`NO_MOTION` scores a run that stays at its start: the error of ignoring the loads.
"""

from __future__ import annotations

import csv
import math
import statistics
import time
from collections.abc import Callable, Generator, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from redsim import scenes
from redsim.cubature import Cubature, CubatureEnergy
from redsim.envs.chain import ChainEnv
from redsim.envs.cloth_ball import ClothBallEnv
from redsim.envs.conditional_bar import ConditionalBarEnv
from redsim.envs.hanging_cloth import HangingClothEnv
from redsim.envs.mini_chain import MiniChainEnv
from redsim.envs.reach import ReachEnv
from redsim.integrators import FullSpace, FullState, ImplicitEuler, LatentSpace, latent_equilibrium
from redsim.integrators.implicit_euler import quiet_steps
from redsim.integrators.reference import rest_or_warn, rest_state
from redsim.metrics.reach import nearest_latent
from redsim.plausibility import MAX_STEP_SIZES, step_failure
from redsim.runtime import LatentStepper
from redsim.runtime.stepper import DEFAULT_HESSIAN, DEFAULT_MAX_ITER
from redsim.scene import Scene
from redsim.subspace import write_atomically

SCENARIOS = ("push", "actions")
"""``push``: a constant unit action along +x (the issue's sideways load); ``actions``: seeded uniform
random actions in [-1, 1]^D, each held for :data:`HOLD_STEPS` steps."""
HOLD_STEPS = 10
"""Steps an action of the ``actions`` scenario is held (dt multiples of the coarse runs divide it)."""
DT = 0.02
"""Time step of the reference and of the envs [s]."""
PROJECTION_EVERY = 10
"""Reference steps between the states the projection floor is measured on."""
REFERENCE_MAX_ITER = 100
"""Newton iterations a full-space reference step may take (the mini chain's push takes up to ~60), also in the
start study's full-space run and the larger-dt rows."""


@dataclass(frozen=True)
class Plan:
    """What the accuracy bench does on one scene.

    Attributes:
        handle: The handle the actions push (the env's).
        max_force: Force [N] of a unit action (the env's ``max_force``).
        reference_tol: Relative gradient tolerance of the full-space reference steps.
        note: Why, in one line.
    """

    handle: str
    max_force: float
    reference_tol: float = 1e-8
    note: str = ""


def _env_plan(scene_name: str, env: type[ReachEnv], why: str = "") -> Plan:
    """The plan of an env's scene: the env's handle and ``max_force``, so bench and env cannot drift apart, and the
    scene's full-space tolerance (:func:`redsim.scenes.full_space_tol`)."""
    note = f"{env.__name__}'s handle and max_force" + (f"; {why}" if why else "")
    tol = scenes.full_space_tol(scene_name)
    return Plan(env.goal_handle, env.default_max_force, reference_tol=tol, note=note)


PLANS: dict[str, Plan] = {
    "mini_chain": _env_plan("mini_chain", MiniChainEnv),
    "chain": _env_plan("chain", ChainEnv),
    "hanging_sheet": _env_plan(
        "hanging_sheet",
        HangingClothEnv,
        why="the sheet's Newton stalls near 3e-5 of its forces (tol 1e-5 and 1e-6 steps end unconverged at "
        "|g| ~ 1e-3 N), so 1e-4 is the converged reference",
    ),
    "cloth_ball": _env_plan("cloth_ball", ClothBallEnv, why="the ball pushed across the pinned cloth"),
    "conditional_bar": _env_plan(
        "conditional_bar",
        ConditionalBarEnv,
        why="at the condition space's default (stiffness ratio 1, pin at 0.65), shared by the full space and maps",
    ),
    "bistable_bar": Plan(
        "middle",
        200.0,
        reference_tol=scenes.full_space_tol("bistable_bar"),
        note="more than BistableBar's 60 N / 40 N: 200 N on the middle column moves it ~1/3 of the bar's height "
        "against the arch",
    ),
}
"""The scenes the bench knows, with their handle and load scale."""


def plan(scene_name: str) -> Plan:
    """The :class:`Plan` of a scene (ValueError listing the known ones)."""
    if scene_name not in PLANS:
        raise ValueError(f"bench accuracy knows scenes {sorted(PLANS)}, not {scene_name!r}")
    return PLANS[scene_name]


def replanned(scene: Scene, handle: str | None = None, max_force: float | None = None) -> Plan:
    """The :data:`PLANS` entry of ``scene`` with the ``handle`` and ``max_force`` [N] given (each kept where None).

    Raises:
        ValueError: a scene outside :data:`PLANS`, an unknown handle, or a max_force refused by
            :func:`checked_force`.
    """
    p = plan(scene.name)
    if handle is not None and handle not in scene.handle_names:
        raise ValueError(f"scene {scene.name!r} has no handle {handle!r}; valid: {list(scene.handle_names)}")
    if max_force is not None:
        checked_force(max_force)
    given = [f"{key} {value!r} given" for key, value in (("handle", handle), ("max_force", max_force)) if value]
    return replace(
        p,
        handle=p.handle if handle is None else handle,
        max_force=p.max_force if max_force is None else float(max_force),
        note="; ".join([p.note, *given]) if given else p.note,
    )


MAX_FORCE = float(torch.finfo(torch.float32).max)
"""The largest ``max_force`` [N]: the runtime rows step in float32, where a larger load is not finite (the bench
crashed on it after its reference had run)."""


def checked_force(max_force: float) -> float:
    """``max_force`` [N] as a float, finite, > 0 and at most :data:`MAX_FORCE` (ValueError otherwise)."""
    force = float(max_force)
    if not (math.isfinite(force) and 0.0 < force <= MAX_FORCE):
        raise ValueError(
            f"max_force must be finite and > 0 [N], at most {MAX_FORCE:.3g} (float32's largest: the runtime steps "
            f"in float32), got {max_force!r}"
        )
    return force


def reach_plan(scene: Scene, handle: str | None = None, max_force: float | None = None) -> Plan:
    """The plan of any scene as ``redsim.envs.make(scene, ..., task="reach")`` sets it up: ``handle`` (default
    the first) pushed with ``max_force`` [N] per unit action (default the reach task's: half the scene's weight),
    the reference at the scene's full-space tolerance.

    Raises:
        ValueError: a scene without handles, an unknown handle, or a max_force refused by :func:`checked_force`.
    """
    from redsim.envs.factory import default_force

    if not scene.handles:
        raise ValueError(f"scene {scene.name!r} has no handles to push")
    handle = scene.handle_names[0] if handle is None else handle
    if handle not in scene.handle_names:
        raise ValueError(f"scene {scene.name!r} has no handle {handle!r}; valid: {list(scene.handle_names)}")
    force = default_force(scene) if max_force is None else checked_force(max_force)
    why = "the reach task's default (half the scene's weight; 1 N without gravity)" if max_force is None else "given"
    return Plan(handle, force, reference_tol=scenes.full_space_tol(scene.name), note=f"max_force {why}")


def checkpoint_plan(scene: Scene, handle: str | None = None, max_force: float | None = None) -> Plan:
    """The plan of a checkpoint's scene: its :data:`PLANS` entry where the bench has one whose handle the scene has
    (:func:`replanned`: the loads of the tables, so a user's map of a catalog scene is benched as the shipped one),
    else :func:`reach_plan` (a mesh scene's, any other scene's)."""
    if scene.name in PLANS and PLANS[scene.name].handle in scene.handle_names:
        return replanned(scene, handle, max_force)
    return reach_plan(scene, handle, max_force)


def scenario_loads(scene: Scene, scenario: str, steps: int, *, seed: int = 0, load_plan: Plan | None = None) -> Tensor:
    """Loads [steps, H, D] [N] (float64) of a seeded scenario on the plan's handle (default: the scene's
    :data:`PLANS` entry)."""
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; valid: {list(SCENARIOS)}")
    if int(steps) != steps or steps < 1:
        raise ValueError(f"steps must be an integer >= 1, got {steps!r}")
    p = plan(scene.name) if load_plan is None else load_plan
    if p.handle not in scene.handle_names:
        raise ValueError(f"scene {scene.name!r} has no handle {p.handle!r}; valid: {list(scene.handle_names)}")
    h = scene.handle_names.index(p.handle)
    loads = torch.zeros(steps, len(scene.handles), scene.dim, dtype=torch.float64)
    if scenario == "push":
        loads[:, h, 0] = p.max_force
        return loads
    g = torch.Generator().manual_seed(seed)
    for start in range(0, steps, HOLD_STEPS):
        action = 2.0 * torch.rand(scene.dim, generator=g, dtype=torch.float64) - 1.0
        loads[start : start + HOLD_STEPS, h] = action * p.max_force
    return loads


@dataclass
class Run:
    """One configuration's trajectory and cost.

    Attributes:
        q: Free configurations [T + 1, n] (float64) at the reference's times ``times`` (step indices).
        times: Reference step index of each row of q, int64 [T + 1].
        step_s: Wall time of each step [s].
        stride: Reference steps per step (the dt multiple).
        failed: Steps the solver reported as not converged (None: a run that solves nothing, :data:`NO_MOTION`).
        flagged: Steps the runtime flagged ``diverged`` (None: not a runtime run, which has no such flag).
        out_of_range: Steps flagged ``out_of_range`` (None: not a runtime run).
        nonfinite: Steps whose state was not finite (must be 0).
        idle: Steps under a load that the solver accepted without an iteration where it began (a latent step: at
            z_t, not at a start that moves): the start was already within its tolerance, so a loose ``tol`` can
            leave the scene where it was (the row is then not a faster solve of the same motion). None: not counted
            (the converged latent reference, :data:`NO_MOTION`).
        implausible: Full-space steps that moved a coordinate further than the scene can
            (:func:`redsim.plausibility.step_failure`: loads far beyond what it takes).
        tunneled: Full-space steps that passed through a contact (``StepInfo.tunneled``: the solve again within a
            trust radius did not catch them).
        caught: Full-space steps whose first solve passed through a contact and whose solve again within a trust
            radius ended on its near side (``StepInfo.tunnel_caught``: the mini chain's links at the hook at 5x the
            time step); their times hold both solves.
        error: ``TYPE: message`` of the exception that ended the run (:func:`guarded`); its q and times are then
            empty.
    """

    q: Tensor
    times: Tensor
    step_s: list[float]
    stride: int = 1
    failed: int | None = 0
    flagged: int | None = None
    out_of_range: int | None = None
    nonfinite: int = 0
    idle: int | None = None
    implausible: int = 0
    tunneled: int = 0
    caught: int = 0
    error: str | None = None


Steps = Generator[None, None, "Run"]
"""A configuration's run as a generator: it yields once per reference step (dt of simulated time) it has advanced and
returns its :class:`Run` (:func:`lockstep` steps several in turn)."""


def lockstep(runs: Sequence[Steps]) -> list[Run]:
    """Advance every run one reference step in turn (each run's step i, then each one's step i + 1, ...) until all
    have ended, with the per-step convergence warnings silenced (the rows count them); their :class:`Run` in order.

    Timed this way, a load on the machine that changes during the bench falls on every configuration alike (timed
    one after another, a row's time ratio to the reference moved by up to ~2x: docs/accuracy.md).
    """
    results: list[Run | None] = [None] * len(runs)
    live = list(range(len(runs)))
    with quiet_steps():
        while live:
            for k in list(live):
                try:
                    next(runs[k])
                except StopIteration as stop:
                    results[k] = stop.value
                    live.remove(k)
    return results  # type: ignore[return-value]


def guarded(steps: Steps) -> Steps:
    """``steps``, whose Exception (a solve that raised) ends it with a :class:`Run` that holds it in ``error``, so
    that one configuration that fails does not take the other rows of its scenario with it."""
    try:
        return (yield from steps)
    except Exception as err:
        return Run(torch.empty(0), torch.empty(0, dtype=torch.int64), [], error=f"{type(err).__name__}: {err}")


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (or a SIGTERM made to raise) during :func:`bench_accuracy`'s scenarios; ``result`` holds the rows
    finished before it (the result's form, ``interrupted`` True). A KeyboardInterrupt, so a caller that does not
    look stops as before."""

    def __init__(self, result: dict[str, Any]) -> None:
        super().__init__("bench_accuracy interrupted")
        self.result = result


def _counted(steps: Steps, total: int, progress: Callable[[str], None], scenario: str) -> Steps:
    """``steps``, saying ``SCENARIO: step i of TOTAL`` after its step i every tenth of ``total`` (a long bench's
    progress: the rows come when every configuration has ended)."""
    every, done = max(1, total // 10), 0
    while True:
        try:
            next(steps)
        except StopIteration as stop:
            return stop.value
        done += 1
        if done % every == 0 and done < total:
            progress(f"{scenario}: step {done} of {total}")
        yield


def run_full(scene: Scene, q0: Tensor, loads: Tensor, **options: Any) -> Run:
    """:func:`full_steps` (``options``: its ``dt``, ``stride``, ``substeps``, ``tol``, ``max_iter``), run alone."""
    return lockstep([full_steps(scene, q0, loads, **options)])[0]


def full_steps(
    scene: Scene,
    q0: Tensor,
    loads: Tensor,
    *,
    dt: float = DT,
    stride: int = 1,
    substeps: int = 1,
    tol: float = 1e-8,
    max_iter: int = 50,
) -> Steps:
    """Full-space float64 implicit Euler from rest q0 [n] through loads [T, H, D] every ``stride`` steps, each
    step of ``dt * stride`` made of ``substeps`` steps of ``dt * stride / substeps`` (timed together), as
    :data:`Steps` (a step of ``stride`` reference steps yields ``stride`` times)."""
    scene64 = scene.to(dtype=torch.float64)
    integrator = ImplicitEuler(FullSpace(scene64), dt * stride / substeps, tol=tol, max_iter=max_iter)
    state = FullState(q0.clone(), q0.clone(), 0.0)
    qs, times, failed, nonfinite, idle, implausible = [q0.clone()], [], 0, 0, 0, 0
    tunneled = caught = 0
    for i in range(0, loads.shape[0] - stride + 1, stride):
        start = time.perf_counter()
        infos, failures = [], []
        for _ in range(substeps):
            inertial = 2.0 * state.q - state.q_prev
            state, info = integrator.step(state, loads[i])
            infos.append(info)
            failures.append(step_failure(scene64, inertial, state.q, info.grad_norm, info.energy))
        times.append(time.perf_counter() - start)
        failed += not all(info.converged for info in infos)  # per load step, as the other rows count
        idle += all(info.iterations == 0 for info in infos) and bool(loads[i].any())
        nonfinite += not bool(torch.isfinite(state.q).all())
        implausible += any(failures)
        tunneled += any(info.tunneled for info in infos)
        caught += any(info.tunnel_caught for info in infos)
        qs.append(state.q.clone())
        for _ in range(stride):
            yield
    index = torch.arange(len(qs), dtype=torch.int64) * stride
    return Run(
        torch.stack(qs),
        index,
        times,
        stride,
        failed,
        nonfinite=nonfinite,
        idle=idle,
        implausible=implausible,
        tunneled=tunneled,
        caught=caught,
    )


def run_latent_reference(scene: Scene, subspace: nn.Module, z0: Tensor, loads: Tensor, *, dt: float = DT) -> Run:
    """The converged latent solve: ``ImplicitEuler(LatentSpace(scene, f))`` (float64 Newton, tol 1e-8) from z0 [d]."""
    return lockstep([latent_reference_steps(scene, subspace, z0, loads, dt=dt)])[0]


def latent_reference_steps(scene: Scene, subspace: nn.Module, z0: Tensor, loads: Tensor, *, dt: float = DT) -> Steps:
    """:func:`run_latent_reference` as :data:`Steps`."""
    space = LatentSpace(scene.to(dtype=torch.float64), subspace)
    integrator = ImplicitEuler(space, dt)
    state = FullState(z0.clone(), z0.clone(), 0.0)
    zs, times, failed = [z0.clone()], [], 0
    for i in range(loads.shape[0]):
        start = time.perf_counter()
        state, info = integrator.step(state, loads[i])
        times.append(time.perf_counter() - start)
        failed += not info.converged
        zs.append(state.q.clone())
        yield
    with torch.no_grad():
        q = space.configuration(torch.stack(zs))
    nonfinite = int((~torch.isfinite(q).all(-1)).sum())
    return Run(q, torch.arange(q.shape[0]), times, 1, failed, nonfinite=nonfinite)


def run_runtime(stepper: LatentStepper, z0: Tensor, loads: Tensor) -> Run:
    """The runtime (B = 1) from rest z0 [d] through loads [T, H, D]; q = f(z) in float64 afterwards."""
    return lockstep([runtime_steps(stepper, z0, loads)])[0]


def runtime_steps(stepper: LatentStepper | Callable[[], LatentStepper], z0: Tensor, loads: Tensor) -> Steps:
    """:func:`run_runtime` as :data:`Steps` (``stepper`` may be a function that makes it, at the first step)."""
    if not isinstance(stepper, LatentStepper):
        stepper = stepper()
    z = z0.to(stepper.dtype).reshape(1, -1)
    stepper.step(z, z, loads[0:1].to(stepper.dtype))  # warm-up: first-call allocations stay out of the times
    z_prev = z.clone()
    zs, times = [z.clone()], []
    failed = flagged = out_of_range = idle = 0
    model = carry = None
    for i in range(loads.shape[0]):
        start = time.perf_counter()
        z_next, stats = stepper.step(z, z_prev, loads[i : i + 1], warm=model, carry=carry)
        model, carry = stats.model, stats.carry
        times.append(time.perf_counter() - start)
        failed += int((~stats.converged).sum())
        idle += int(((stats.iterations == 0) & (z_next == z).all(-1) & bool(loads[i].any())).sum())
        flagged += int(stats.diverged.sum())
        out_of_range += int(stats.out_of_range.sum())
        z_prev, z = z, z_next
        zs.append(z.clone())
        yield
    space = LatentSpace(stepper.source_scene.to(dtype=torch.float64), stepper.subspace)
    with torch.no_grad():
        q = space.configuration(torch.cat(zs).to(torch.float64))
    nonfinite = int((~torch.isfinite(q).all(-1)).sum())
    return Run(q, torch.arange(q.shape[0]), times, 1, failed, flagged, out_of_range, nonfinite, idle)


def _m_norm(scene64: Scene, v: Tensor) -> Tensor:
    """|v|_M [kg^1/2 m] of rows v [T, n]."""
    return (v * scene64.mass_matvec(v)).sum(-1).clamp_min(0.0).sqrt()


def handle_positions(scene64: Scene, q: Tensor, handle: str) -> Tensor:
    """Position [T, D] [m] of a handle at free configurations q [T, n]."""
    h = scene64.handles[scene64.handle_names.index(handle)]
    return h.position(scene64.full_positions(q))


def trajectory_errors(scene64: Scene, run: Run, reference: Run, handle: str) -> dict[str, float]:
    """Errors of a run against the reference (module doc): rel. M error (mean, final), handle cm, rest offset."""
    ref_q = reference.q[run.times]
    ref_d = ref_q - reference.q[0]
    scale = float(_m_norm(scene64, reference.q - reference.q[0]).max()) or 1.0
    d = run.q - run.q[0]
    rel = _m_norm(scene64, d - ref_d) / scale
    p, p_ref = handle_positions(scene64, run.q, handle), handle_positions(scene64, ref_q, handle)
    cm = 100.0 * torch.linalg.vector_norm((p - p[0]) - (p_ref - p_ref[0]), dim=-1)
    raw = _m_norm(scene64, run.q - ref_q) / scale
    sampled = rel[(run.times > 0) & (run.times % PROJECTION_EVERY == 0)]  # the projection floor's steps
    return {
        "rel_error_mean": float(rel[1:].mean()),
        "rel_error_at_projection_steps": float(sampled.mean()) if sampled.numel() else math.nan,
        "rel_error_final": float(rel[-1]),
        "handle_cm_mean": float(cm[1:].mean()),
        "handle_cm_max": float(cm.max()),
        "raw_error_final": float(raw[-1]),
        "rest_offset": float(raw[0]),
        "rest_offset_cm": 100.0 * float(torch.linalg.vector_norm(p[0] - p_ref[0])),
        "motion_scale": scale,
        "handle_motion_cm": 100.0 * float(torch.linalg.vector_norm(p_ref - p_ref[0], dim=-1).max()),
    }


def project(
    scene64: Scene, subspace: nn.Module, z_rest: Tensor, displacement: Tensor, z_start: Tensor
) -> tuple[float, Tensor]:
    """min_z |(f(z) - f(z*)) - displacement|_M [kg^1/2 m] over z by L-BFGS (strong Wolfe, float64) from z_start [d].

    Returns:
        The smallest M-norm found and its z [d].
    """
    space = LatentSpace(scene64, subspace)
    with torch.no_grad():
        target = space.configuration(z_rest.reshape(1, -1))[0] + displacement
    size = float(_m_norm(scene64, displacement.unsqueeze(0))[0]) or 1.0
    # |r|^2_M / (2 size^2): the objective this bench minimized before nearest_latent (equal to round-off)
    z = nearest_latent(
        space.configuration, scene64, target, z_start.reshape(1, -1), scale=size * math.sqrt(2.0), tolerance_grad=1e-12
    )
    with torch.no_grad():
        r = space.configuration(z) - target
    return float(_m_norm(scene64, r)[0]), z.detach()[0]


def projection_floor(
    scene64: Scene, subspace: nn.Module, z_rest: Tensor, reference: Run, *, every: int = PROJECTION_EVERY
) -> float:
    """Mean over every ``every``-th reference step of :func:`project` of Δq_ref(t), relative as e(t) (module doc).

    Each minimization is warm-started from the last one's z.
    """
    scale = float(_m_norm(scene64, reference.q - reference.q[0]).max()) or 1.0
    z, errors = z_rest.clone(), []
    for t in range(every, reference.q.shape[0], every):
        error, z = project(scene64, subspace, z_rest, reference.q[t] - reference.q[0], z)
        errors.append(error / scale)
    return statistics.fmean(errors) if errors else math.nan


FULL_VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {
    "tol": ("full tol 1e-3", {"tol": 1e-3}),
    "newton1": ("full 1 Newton iteration", {"max_iter": 1}),
    "newton3": ("full 3 Newton iterations", {"max_iter": 3}),
    "dt2": ("full dt x2", {"stride": 2}),
    "dt5": ("full dt x5", {"stride": 5}),
    "dt4th": ("full dt /4", {"substeps": 4}),
}
"""The loosened full-space configurations, and one finer: key -> (label, :func:`run_full` options). ``dt4th`` (dt / 4,
4 substeps per load step) is the reference's own time-step error: the rows are measured against implicit Euler at
dt, which differs from a finer solve by about as much as the mini chain's d = 4 map does (README)."""


@dataclass(frozen=True)
class Config:
    """One row of the bench: a label, its family (for the plot), how to run it (loads [T, H, D] -> :data:`Steps`,
    stepped in turn with the others by :func:`lockstep`), and its subspace's key and d."""

    label: str
    family: str
    run: Callable[[Tensor], Steps]
    subspace: str | None = None
    dim: int | None = None


KINDS = ("neural", "modes", "modal_derivatives")
"""The subspace families, in table order."""


def _subspaces(scene: Scene, maps: Mapping[int, nn.Module], *, with_dims: bool) -> dict[str, nn.Module]:
    """Per neural map of ``maps`` (by d): it, linear modes and modal derivatives of its d and σ at the full rest
    (the two baselines only where d <= n: a scene has n modes, and a neural map may have more latents than DOFs).

    Keys are the kinds of :data:`KINDS` (``"KIND d=D"`` when ``with_dims``), grouped by kind, d ascending.
    """
    from redsim.baselines import modal_analysis, modal_derivatives

    rest = rest_or_warn(scene, "the linear-mode and modal-derivative baselines")
    built: dict[str, dict[int, nn.Module]] = {kind: {} for kind in KINDS}
    for dim in sorted(maps):
        neural = maps[dim]
        built["neural"][dim] = neural
        if dim > scene.free_dof_count:
            continue
        sigma = float(neural.metadata["fit"]["sigma"]) if hasattr(neural, "metadata") else 1.0
        modes = modal_analysis(scene, dim, sigma=sigma, rest=rest)
        built["modes"][dim] = modes
        built["modal_derivatives"][dim] = modal_derivatives(scene, dim, sigma=sigma, rest=modes.offset)
    return {_key(kind, dim, with_dims): m for kind, by_dim in built.items() for dim, m in by_dim.items()}


def _key(kind: str, dim: int, with_dims: bool) -> str:
    return f"{kind} d={dim}" if with_dims else kind


def configurations(
    scene: Scene,
    subspaces: dict[str, nn.Module],
    rests: dict[str, Tensor],
    *,
    dt: float = DT,
    reference_tol: float = 1e-8,
    full: tuple[str, ...] = tuple(FULL_VARIANTS),
    variants: str = "neural",
    cubatures: Mapping[str, Cubature] | None = None,
) -> list[Config]:
    """The configurations of the bench (module doc), in table order; ``rests`` holds each map's z*.

    ``full`` picks keys of :data:`FULL_VARIANTS`; the larger-dt runs keep the reference's tolerance,
    so only the time step differs. The subspace keyed ``variants`` gets every runtime option, the
    others the runtime's default; each neural map keyed in ``cubatures`` also runs with its cubature.
    """
    q_rest, _ = rest_state(scene)
    configs: list[Config] = []
    for key in full:
        if key not in FULL_VARIANTS:
            raise ValueError(f"unknown full-space variant {key!r}; valid: {list(FULL_VARIANTS)}")
    for key in full:
        label, options = FULL_VARIANTS[key]
        if "stride" in options or "substeps" in options:
            options = {**options, "tol": reference_tol, "max_iter": REFERENCE_MAX_ITER}
        configs.append(
            Config(label, "full space", lambda loads, o=options: full_steps(scene, q_rest, loads, dt=dt, **o))
        )
    base = f"runtime f32 {DEFAULT_HESSIAN} {DEFAULT_MAX_ITER} it"
    default = f"{base} (default)"
    all_options: list[tuple[str, dict[str, Any]]] = [
        (default, {}),
        (f"runtime f64 {DEFAULT_HESSIAN} {DEFAULT_MAX_ITER} it", {"dtype": torch.float64}),
        ("runtime f32 bfgs", {"hessian": "bfgs"}),
        ("runtime f32 exact Hessian", {"hessian": "exact"}),
        ("runtime f32 3 it", {"max_iter": 3}),
        ("runtime f32 1 it", {"max_iter": 1}),
    ]
    for key, subspace in subspaces.items():
        z0, family, dim = rests[key], key.split(" ")[0], int(subspace.latent_dim)
        options = all_options if key == variants else all_options[:1]
        cubature = (cubatures or {}).get(key)
        if cubature is not None:
            options = [*options, (f"{base} + cubature ({cubature.kept} elements)", {"cubature": cubature})]
        configs.append(
            Config(
                f"{key}: latent reference f64 Newton",
                family,
                lambda loads, s=subspace, z=z0: latent_reference_steps(scene, s, z, loads, dt=dt),
                key,
                dim,
            )
        )
        for label, o in options:
            configs.append(
                Config(
                    f"{key}: {label}",
                    family,
                    lambda loads, s=subspace, z=z0, o=o: runtime_steps(lambda: _stepper(scene, s, dt, **o), z, loads),
                    key,
                    dim,
                )
            )
    return configs


def _stepper(scene: Scene, subspace: nn.Module, dt: float, *, cubature: Cubature | None = None, **options: Any):
    """A :class:`LatentStepper` with ``options``, on the cubature's energy when one is given."""
    if cubature is None:
        return LatentStepper(scene, subspace, dt, **options)

    def energy(scene: Scene, subspace: nn.Module, *, dtype: torch.dtype, device: torch.device) -> CubatureEnergy:
        return CubatureEnergy(scene, subspace, cubature, dtype=dtype, device=device)

    return LatentStepper(scene, subspace, dt, energy=energy, **options)


def start_study(
    scene: Scene,
    neural: nn.Module,
    z_rest: Tensor,
    loads: Tensor,
    reference: Run,
    *,
    dt: float = DT,
    reference_tol: float = 1e-8,
) -> dict[str, float]:
    """The issue's comparison, taken apart, at the last step of ``loads`` (the ``push`` scenario). The full-space run
    from f(z*) is solved as the reference is (``reference_tol``, :data:`REFERENCE_MAX_ITER`).

    - ``same_start``: runtime latent run and full-space run both from f(z*) (not a full-space
      equilibrium): |q_lat(T) - q_full'(T)|_M / |q_full'(T) - q_full'(0)|_M (the measured 0.99);
    - ``own_rests``: the runtime run from z* against the reference from the full rest, displacements
      compared: |Δq_lat(T) - Δq_ref(T)|_M / |Δq_ref(T)|_M;
    - ``own_rests_converged``: the same with the converged latent solve;
    - ``projection``: min_z |(f(z) - f(z*)) - Δq_ref(T)|_M / |Δq_ref(T)|_M, the subspace's floor;
    - ``full_fall``: how far the full-space run from f(z*) moves without any load being needed
      (|q_full'(T) - q_full'(0)|_M against the reference's |Δq_ref(T)|_M).
    """
    scene64 = scene.to(dtype=torch.float64)
    space = LatentSpace(scene64, neural)
    with torch.no_grad():
        q_start = space.configuration(z_rest.reshape(1, -1))[0]
    fallen = run_full(scene, q_start, loads, dt=dt, tol=reference_tol, max_iter=REFERENCE_MAX_ITER)
    latent = run_runtime(LatentStepper(scene, neural, dt), z_rest, loads)
    converged = run_latent_reference(scene, neural, z_rest, loads, dt=dt)
    ref_d = reference.q[-1] - reference.q[0]
    size = float(_m_norm(scene64, ref_d.unsqueeze(0))[0]) or 1.0

    def norm(v: Tensor) -> float:
        return float(_m_norm(scene64, v.unsqueeze(0))[0])

    fall = norm(fallen.q[-1] - fallen.q[0])
    floor, _ = project(scene64, neural, z_rest, ref_d, z_rest)
    return {
        "steps": int(loads.shape[0]),
        "same_start": norm(latent.q[-1] - fallen.q[-1]) / (fall or 1.0),
        "own_rests": norm((latent.q[-1] - latent.q[0]) - ref_d) / size,
        "own_rests_converged": norm((converged.q[-1] - converged.q[0]) - ref_d) / size,
        "projection": floor / size,
        "full_fall": fall / size,
        "latent_motion": norm(latent.q[-1] - latent.q[0]) / size,
    }


def bench_accuracy(
    scene: Scene,
    neural: nn.Module,
    *,
    steps: int = 100,
    scenarios: tuple[str, ...] = SCENARIOS,
    seed: int = 0,
    dt: float = DT,
    full: tuple[str, ...] = tuple(FULL_VARIANTS),
    study: bool = True,
    study_steps: int = 50,
    maps: Mapping[int, nn.Module] | None = None,
    cubatures: Mapping[int, Cubature] | None = None,
    progress: Callable[[str], None] | None = None,
    load_plan: Plan | None = None,
) -> dict[str, Any]:
    """All rows of one scene (module doc).

    Args:
        scene: A scene of :data:`PLANS`, or any scene with ``load_plan`` (:func:`reach_plan`).
        neural: Its fitted neural map (the shipped one in the CLI); it alone gets every runtime option.
        steps: Steps per scenario (>= 10).
        scenarios: Names from :data:`SCENARIOS`.
        seed: Seed of the ``actions`` scenario.
        dt: Reference time step [s].
        full: Keys of the loosened full-space configurations to run (:data:`FULL_VARIANTS`).
        study: Run :func:`start_study` on the ``push`` loads (``study_steps`` steps).
        maps: Neural maps by d to compare (``neural`` is added at its d); with it, linear modes and
            modal derivatives are built at each of these d and every subspace label carries its d.
        cubatures: Cubatures by d of the neural maps that have one (each checked against its map).
        progress: Called with one line per finished configuration.
        load_plan: The handle, load scale and reference tolerance (default: the scene's :data:`PLANS` entry).

    Returns:
        ``scene``, ``n``, ``d``, ``dims``, ``maps`` (per neural map: d, fit steps, fit seconds, cubature
        elements), ``plan``, ``rows`` (one dict per scenario and configuration, the reference included; a
        row's ``error`` is None, or what its run raised), ``study`` and ``interrupted`` (False).

    Raises:
        ValueError: an unknown scene, scenario or a bad count; ``maps`` holding another map at
            ``neural``'s d; a cubature for a d without a map, or for another map.
        Interrupted: a KeyboardInterrupt (Ctrl-C) during the scenarios; its ``result`` holds the rows finished
            before it. A configuration whose run raises an Exception gets a row with ``error`` set instead.
    """
    p = plan(scene.name) if load_plan is None else load_plan
    if int(steps) != steps or steps < 10:
        raise ValueError(f"steps must be an integer >= 10, got {steps!r}")
    for name in scenarios:
        if name not in SCENARIOS:
            raise ValueError(f"unknown scenario {name!r}; valid: {list(SCENARIOS)}")
    dim = int(neural.latent_dim)
    with_dims = maps is not None
    all_maps = dict(maps or {})
    if all_maps.setdefault(dim, neural) is not neural:
        raise ValueError(f"maps holds another map at d={dim}, the d of the neural map given")
    for d, subspace in all_maps.items():
        if int(subspace.latent_dim) != d:
            raise ValueError(f"maps[{d}] has d={int(subspace.latent_dim)}")
    for d, cubature in (cubatures or {}).items():
        if d not in all_maps:
            raise ValueError(f"a cubature for d={d}, but no neural map of that d; maps: {sorted(all_maps)}")
        cubature.check(scene, all_maps[d], f"cubature of d={d}")
    scene64 = scene.to(dtype=torch.float64)
    q_rest, rest_converged = rest_state(scene)
    subspaces = _subspaces(scene, all_maps, with_dims=with_dims)
    rests, unsettled = {}, []
    for key, subspace in subspaces.items():
        z, info = latent_equilibrium(LatentSpace(scene64, subspace), None)
        rests[key] = z
        if not info.converged:  # its rows start where the solve stopped: reported, not hidden
            unsettled.append(key)
    configs = configurations(
        scene,
        subspaces,
        rests,
        dt=dt,
        reference_tol=p.reference_tol,
        full=full,
        variants=_key("neural", dim, with_dims),
        cubatures={_key("neural", d, with_dims): c for d, c in (cubatures or {}).items()},
    )
    rows: list[dict[str, Any]] = []
    out: dict[str, Any] = {
        "scene": scene.name,
        "n": scene.free_dof_count,
        "d": dim,
        "dims": sorted(all_maps),
        "maps": [_map_info(d, all_maps[d], (cubatures or {}).get(d)) for d in sorted(all_maps)],
        "dt": dt,
        "steps": steps,
        "plan": {"handle": p.handle, "max_force": p.max_force, "reference_tol": p.reference_tol, "note": p.note},
        "rest_converged": bool(rest_converged),
        "latent_rests_unconverged": unsettled,
        "rows": rows,
        "interrupted": False,
    }

    def run_scenario(scenario: str) -> None:
        loads = scenario_loads(scene, scenario, steps, seed=seed, load_plan=p)
        reference_steps = full_steps(scene, q_rest, loads, dt=dt, tol=p.reference_tol, max_iter=REFERENCE_MAX_ITER)
        if progress:
            progress(f"{scenario}: {len(configs) + 1} configurations stepped in turn, {steps} steps")
            reference_steps = _counted(reference_steps, steps, progress, scenario)
        reference, *runs = lockstep([guarded(reference_steps), *(guarded(config.run(loads)) for config in configs)])
        if reference.error is not None:  # nothing to measure the other rows against: its row says why
            rows.append(_failed_row(scenario, "full reference", "reference", None, reference.error))
            return
        ref_median = statistics.median(reference.step_s)
        rows.append(_row(scenario, "full reference", "reference", reference, reference, scene64, p.handle, ref_median))
        rows.append(_row(scenario, NO_MOTION, "reference", _still(reference), reference, scene64, p.handle, ref_median))
        if progress:
            progress(_progress_line(rows[-2]))
        for config, run in zip(configs, runs, strict=True):
            if run.error is not None:
                rows.append(_failed_row(scenario, config.label, config.family, config.dim, run.error))
                continue
            row = _row(scenario, config.label, config.family, run, reference, scene64, p.handle, ref_median)
            row["d"] = config.dim
            key = config.subspace
            if key is not None and config.label.endswith("latent reference f64 Newton"):
                row["projection"] = projection_floor(scene64, subspaces[key], rests[key], reference)
            rows.append(row)
            if progress:
                progress(_progress_line(row))
        if study and scenario == "push":
            head = _prefix(reference, study_steps)
            key = _key("neural", dim, with_dims)
            out["study"] = start_study(
                scene, neural, rests[key], loads[:study_steps], head, dt=dt, reference_tol=p.reference_tol
            )

    try:
        for scenario in scenarios:
            run_scenario(scenario)
    except KeyboardInterrupt as stop:  # the rows finished before it are kept
        raise Interrupted({**out, "interrupted": True}) from stop
    return out


def _map_info(dim: int, neural: nn.Module, cubature: Cubature | None) -> dict[str, Any]:
    """What the report says of one neural map: its d, fit steps and seconds, and its cubature's size."""
    metadata = getattr(neural, "metadata", {})
    return {
        "d": dim,
        "fit_steps": metadata.get("fit", {}).get("steps"),
        "fit_seconds": metadata.get("fit_seconds"),
        "cubature_elements": None if cubature is None else cubature.kept,
    }


NO_MOTION = "no motion (stays at its start)"
"""The row of a run that never moves: the error of ignoring the loads (time per step: none, printed –)."""


def _still(reference: Run) -> Run:
    """A run that stays at the reference's start, at its times (no time per step: NaN)."""
    q = reference.q[:1].expand_as(reference.q).clone()
    return Run(q, reference.times, [math.nan] * len(reference.step_s), reference.stride, failed=None)


def _prefix(run: Run, steps: int) -> Run:
    return Run(run.q[: steps + 1], run.times[: steps + 1], run.step_s[:steps], run.stride)


def _row(
    scenario: str, label: str, family: str, run: Run, reference: Run, scene64: Scene, handle: str, ref_median: float
) -> dict[str, Any]:
    median = statistics.median(run.step_s) / run.stride  # per reference step (per dt of simulated time)
    return {
        "scenario": scenario,
        "config": label,
        "family": family,
        "d": None,
        "ms_per_step": 1e3 * median,
        "speedup": ref_median / median if median > 0 else math.nan,
        **trajectory_errors(scene64, run, reference, handle),
        "projection": math.nan,
        "steps_run": len(run.step_s),
        "failed": run.failed,
        "flagged_diverged": run.flagged,
        "out_of_range": run.out_of_range,
        "nonfinite": run.nonfinite,
        "idle": run.idle,
        "implausible": run.implausible,
        "tunneled": run.tunneled,
        "tunnels_caught": run.caught,
        "error": None,
    }


def _failed_row(scenario: str, label: str, family: str, dim: int | None, error: str) -> dict[str, Any]:
    """The row of a configuration whose run raised ``error``: every number NaN (nothing was measured)."""
    row = dict.fromkeys(_ROW_NUMBERS, math.nan)
    return {"scenario": scenario, "config": label, "family": family, "d": dim, **row, "error": error}


_ROW_NUMBERS = (
    *("ms_per_step", "speedup", "rel_error_mean", "rel_error_at_projection_steps", "rel_error_final"),
    *("handle_cm_mean", "handle_cm_max", "raw_error_final", "rest_offset", "rest_offset_cm", "motion_scale"),
    *("handle_motion_cm", "projection", "steps_run", "failed", "flagged_diverged", "out_of_range", "nonfinite"),
    *("idle", "implausible", "tunneled", "tunnels_caught"),
)
"""The numeric keys of a row (:func:`_row`)."""


def _progress_line(row: dict[str, Any]) -> str:
    return (
        f"{row['scenario']:8s} {row['config']:48s} {row['ms_per_step']:9.3g} ms  rel {row['rel_error_mean']:8.3g}  "
        f"{row['handle_cm_mean']:8.3g} cm"
    )


COLUMNS = (
    ("config", "configuration", "{}"),
    ("ms_per_step", "ms/step", "{:.3g}"),
    ("speedup", "x ref", "{:.3g}"),
    ("rel_error_mean", "rel. M error", "{:.3g}"),
    ("rel_error_final", "final", "{:.3g}"),
    ("handle_cm_mean", "handle cm", "{:.3g}"),
    ("rest_offset", "rest offset", "{:.3g}"),
    ("rest_offset_cm", "offset cm", "{:.3g}"),
    ("projection", "projection", "{:.3g}"),
    ("failed", "unconverged", "{}"),
    ("flagged_diverged", "diverged", "{}"),
    ("out_of_range", "out of range", "{}"),
    ("nonfinite", "non-finite", "{}"),
    ("idle", "idle", "{}"),
)
"""Markdown table columns: key, header, format."""


NOT_APPLICABLE = ("ms_per_step", "speedup", "projection")
"""Columns whose NaN means "does not apply" (a run that never steps; a configuration without a subspace): printed –.
A NaN anywhere else is a measured value that is not finite (a run that diverged), printed nan."""


def markdown_table(result: dict[str, Any], scenario: str) -> str:
    """The rows of one scenario as a markdown table (:data:`NOT_APPLICABLE` NaN cells and counts the run does not make,
    None, print as –; other NaN as nan)."""
    lines = ["| " + " | ".join(h for _k, h, _f in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for row in result["rows"]:
        if row["scenario"] != scenario:
            continue
        cells = []
        for key, _header, fmt in COLUMNS:
            value = row[key]
            if value is None:  # a runtime flag of a run that is not the runtime's, a solve count of no motion
                cells.append("–")
            elif isinstance(value, float) and math.isnan(value):
                cells.append("–" if key in NOT_APPLICABLE else "nan")
            else:
                cells.append(fmt.format(value))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_csv(result: dict[str, Any], path: Path) -> None:
    """All rows to a CSV file (one row per scenario and configuration), written whole or not at all."""
    rows = result["rows"]

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=["scene", *rows[0].keys()])
            writer.writeheader()
            for row in rows:
                writer.writerow({"scene": result["scene"], **row})

    write_atomically(Path(path), write)


FAMILY_STYLE = {
    "reference": ("black", "*"),
    "full space": ("tab:gray", "s"),
    "neural": ("tab:red", "o"),
    "modes": ("tab:blue", "^"),
    "modal_derivatives": ("tab:green", "v"),
}


def undrawn_configs(rows: list[dict[str, Any]], scenario: str) -> list[str]:
    """The configs of ``scenario``'s rows that the Pareto plot cannot place: a non-finite mean error (a run that
    diverged) or no positive time; not the :data:`NO_MOTION` row, which is no run and never has a time."""
    return [
        row["config"]
        for row in rows
        if row["scenario"] == scenario
        and row["config"] != NO_MOTION
        and not (math.isfinite(row.get("rel_error_mean", math.nan)) and row.get("ms_per_step", 0) > 0)
    ]


def pareto_png(result: dict[str, Any], path: Path, machine: str) -> None:
    """Log-log plot of ms/step against the mean relative M error, one panel per scenario."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    scenarios = list(dict.fromkeys(r["scenario"] for r in result["rows"]))
    fig = Figure(figsize=(6.5 * len(scenarios), 5.5))
    FigureCanvasAgg(fig)
    floor = 1e-6  # the reference's own error (0) is drawn at this level
    for i, scenario in enumerate(scenarios):
        ax = fig.add_subplot(1, len(scenarios), i + 1)
        seen = set()
        undrawn = undrawn_configs(result["rows"], scenario)
        if undrawn:  # a point a log-log plot cannot place is named, never silently left out
            ax.text(
                0.01,
                0.01,
                "not drawn (no finite error or time): " + ", ".join(undrawn),
                fontsize=6,
                transform=ax.transAxes,
                wrap=True,
            )
        for row in result["rows"]:
            if row["scenario"] != scenario or row["config"] in undrawn or row["config"] == NO_MOTION:
                continue
            color, marker = FAMILY_STYLE.get(row["family"], ("tab:purple", "x"))
            label = row["family"] if row["family"] not in seen else None
            seen.add(row["family"])
            ax.scatter(max(row["rel_error_mean"], floor), row["ms_per_step"], c=color, marker=marker, label=label)
            short = row["config"].split(": ")[-1].replace("runtime ", "")
            short = short if row.get("d") is None or len(result["dims"]) < 2 else f"d={row['d']} {short}"
            ax.annotate(short, (max(row["rel_error_mean"], floor), row["ms_per_step"]), fontsize=6, alpha=0.8)
        for family in KINDS:  # the runtime's default across d, one line per family
            line = sorted(
                (r["d"], max(r["rel_error_mean"], floor), r["ms_per_step"])
                for r in result["rows"]
                if r["scenario"] == scenario and r["family"] == family and r["config"].endswith("(default)")
            )
            if len(line) > 1:
                ax.plot([x for _d, x, _y in line], [y for _d, _x, y in line], c=FAMILY_STYLE[family][0], alpha=0.4)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("mean relative M-norm trajectory error (reference drawn at 1e-6)")
        ax.set_ylabel("median wall time per 0.02 s step [ms]")
        ax.set_title(f"{result['scene']} (n={result['n']}, d={_dims(result)}), {scenario}", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(machine, fontsize=7)
    fig.tight_layout()
    write_atomically(Path(path), lambda tmp: fig.savefig(tmp, format="png", dpi=120))  # Ctrl-C: no half a PNG


def report(result: dict[str, Any], machine: str) -> str:
    """The human-readable output: the machine line, per scenario its markdown table, and the start study."""
    p = result["plan"]
    lines = [
        f"bench accuracy {result['scene']}  n={result['n']}  d={_dims(result)}  dt={result['dt']} s  "
        f"{result['steps']} steps per scenario  handle {p['handle']}, unit action = {p['max_force']:g} N  "
        f"reference: float64 full-space Newton, tol {p['reference_tol']:g}",
        machine,
    ]
    if result.get("maps"):  # which file each neural row ran (a user's checkpoint, or the shipped map)
        lines.append("neural maps: " + "; ".join(_map_line(m) for m in result["maps"]))
    if any(d > result["n"] for d in result.get("dims", ())):
        lines.append(f"note: no modes or modal derivatives for d > n = {result['n']} (a scene has n modes)")
    if not result.get("rest_converged", True):
        lines.append(
            "note: the full-space rest solve did not converge: the reference starts from the state it stopped at, "
            "and the rest offsets are measured from it"
        )
    if result.get("latent_rests_unconverged"):
        lines.append(
            f"note: the latent rest solve did not converge for {', '.join(result['latent_rests_unconverged'])}: "
            "those rows start where it stopped"
        )
    for scenario in dict.fromkeys(r["scenario"] for r in result["rows"]):
        ref = next(r for r in result["rows"] if r["scenario"] == scenario)
        if ref.get("error"):  # its only row: nothing was measured against it
            lines += [
                "",
                f"scenario {scenario}: the reference raised {ref['error']}: no row is measured",
                "",
                markdown_table(result, scenario),
            ]
            continue
        lines += [
            "",
            f"scenario {scenario}: the reference's handle moves up to {ref['handle_motion_cm']:.3g} cm; "
            f"errors relative to its largest displacement {ref['motion_scale']:.3g} kg^1/2 m",
        ]
        if ref.get("implausible"):  # every row is measured against it: said, not hidden (and the command fails)
            lines.append(
                f"note: the reference is not a trustworthy motion: {ref['implausible']} of its "
                f"{ref['steps_run']} steps moved a coordinate more than {MAX_STEP_SIZES:g}x the scene's size and "
                f"{ref['failed']} ended unconverged (the load, max_force {p['max_force']:g} N, may be far beyond "
                "what the scene can take: a smaller --max-force)"
            )
        if ref.get("tunneled"):  # a motion through a contact: every row is measured against it (the command fails)
            lines.append(
                f"note: the reference is not a trustworthy motion: {ref['tunneled']} of its {ref['steps_run']} steps "
                "passed through a contact (StepInfo.tunneled: a move longer than the contact is thick; a smaller dt)"
            )
        measured = [r for r in result["rows"] if r["scenario"] == scenario and not r.get("error")]
        for row in result["rows"]:  # a configuration whose solve raised: the others ran
            if row["scenario"] == scenario and row.get("error"):
                lines.append(f"note: {row['config']} raised {row['error']}: its row reads nan (the command fails)")
        wild = [r for r in measured if r is not ref and r.get("implausible")]
        for row in wild:  # a loosened full-space run that left the scene (its table row has no column for it)
            lines.append(
                f"note: {row['config']} made {row['implausible']} of its {row['steps_run']} steps that moved a "
                f"coordinate more than {MAX_STEP_SIZES:g}x the scene's size (redsim.plausibility.step_failure): its "
                "errors are those of a motion the scene cannot make"
            )
        through = [r for r in measured if r is not ref and r.get("tunneled")]
        for row in through:  # a loosened full-space run (dt x5 through the mini chain's hook): not the scene's motion
            lines.append(
                f"note: {row['config']} passed through a contact in {row['tunneled']} of its {row['steps_run']} "
                "steps (StepInfo.tunneled): its errors are those of another motion"
            )
        caught = [r for r in measured if r.get("tunnels_caught")]
        for row in caught:  # solved twice: its time is not that of one solve per step
            lines.append(
                f"note: {row['config']} moved through a contact in the first solve of {row['tunnels_caught']} of its "
                f"{row['steps_run']} steps, each solved again within a trust radius to the contact's near side "
                "(StepInfo.tunnel_caught): its times hold both solves"
            )
        if not ref.get("implausible") and ref["failed"]:  # Newton stopped short of its tolerance (the bistable bar's)
            lines.append(
                f"note: {ref['failed']} of the reference's {ref['steps_run']} steps ended unconverged (Newton stopped "
                f"short of tol {p['reference_tol']:g} within {REFERENCE_MAX_ITER} iterations): the rows are measured "
                "against where those steps stopped"
            )
        lines += ["", markdown_table(result, scenario)]
    if result.get("interrupted"):
        lines += ["", "interrupted: the rows finished before it"]
    study = result.get("study")
    if study:
        lines += [
            "",
            f"start study (push, {study['steps']} steps, neural map, runtime default unless said): "
            f"same start f(z*) {study['same_start']:.3g} | own rests {study['own_rests']:.3g} | "
            f"own rests, converged latent solve {study['own_rests_converged']:.3g} | "
            f"projection floor {study['projection']:.3g} | full run from f(z*) moves {study['full_fall']:.3g} "
            f"(latent run {study['latent_motion']:.3g}) of the reference's displacement",
        ]
    return "\n".join(lines)


def failures(result: dict[str, Any]) -> tuple[list[str], list[str]]:
    """What makes the command fail (its exit status), each as a line: the scenarios whose reference made steps the
    scene cannot (:func:`redsim.plausibility.step_failure`, a non-finite state among them, or a step through a
    contact, ``StepInfo.tunneled``: every row is measured against that motion), and the rows whose state was not
    finite (the column that must be 0). A loosened full-space row through a contact gets a note, not a failure.

    Unconverged reference steps are not among them: the report's note says so (the bistable bar's reference stops
    near its tolerance in most steps, docs/accuracy.md).
    """
    references = [
        f"scenario {row['scenario']}: the reference made "
        + " and ".join(
            f"{row[key]} of its {row['steps_run']} steps {what}"
            for key, what in (("implausible", "that the scene cannot"), ("tunneled", "through a contact"))
            if row.get(key)
        )
        + " (its note)"
        for row in result["rows"]
        if row["family"] == "reference"
        and row["config"] != NO_MOTION
        and not row.get("error")
        and (row.get("implausible") or row.get("tunneled"))
    ]
    nonfinite = [
        f"scenario {row['scenario']}, {row['config']}: {row['nonfinite']} non-finite states"
        for row in result["rows"]
        if row.get("nonfinite") and not row.get("error")
    ]
    return references, nonfinite


def raised(result: dict[str, Any]) -> list[str]:
    """The rows whose run raised (:func:`guarded`), each as ``scenario S, CONFIG: ERROR`` (they fail the command)."""
    return [f"scenario {r['scenario']}, {r['config']}: {r['error']}" for r in result["rows"] if r.get("error")]


def _dims(result: dict[str, Any]) -> str:
    return ",".join(str(d) for d in result.get("dims", [result["d"]]))


def _map_line(info: dict[str, Any]) -> str:
    """``d=D: N fit steps (S s), SOURCE, cubature K elements`` of one entry of ``result["maps"]``."""
    text = f"d={info['d']}: {info['fit_steps']} fit steps"
    if info.get("fit_seconds") is not None:
        text += f" ({info['fit_seconds']:.0f} s)"
    if info.get("source"):
        text += f", {info['source']}"
    if info["cubature_elements"]:
        text += f", cubature {info['cubature_elements']} elements"
    return text


def write_outputs(result: dict[str, Any], folder: Path, machine: str) -> list[Path]:
    """``accuracy_SCENE.md`` (the :func:`report`), ``.csv`` and ``.png`` (:func:`pareto_png`) in ``folder``, each
    written whole or not at all (a Ctrl-C while writing leaves the file there before, not half of one)."""
    folder.mkdir(parents=True, exist_ok=True)
    stem = folder / f"accuracy_{result['scene']}"
    paths = [stem.with_suffix(".md"), stem.with_suffix(".csv"), stem.with_suffix(".png")]
    text = report(result, machine) + "\n"
    write_atomically(paths[0], lambda tmp: tmp.write_text(text))
    write_csv(result, paths[1])
    pareto_png(result, paths[2], machine)
    return paths


__all__ = [
    "DT",
    "FULL_VARIANTS",
    "KINDS",
    "MAX_FORCE",
    "NO_MOTION",
    "PLANS",
    "REFERENCE_MAX_ITER",
    "SCENARIOS",
    "Interrupted",
    "Plan",
    "Run",
    "Steps",
    "bench_accuracy",
    "checked_force",
    "checkpoint_plan",
    "failures",
    "full_steps",
    "guarded",
    "handle_positions",
    "latent_reference_steps",
    "lockstep",
    "markdown_table",
    "pareto_png",
    "plan",
    "project",
    "projection_floor",
    "raised",
    "report",
    "run_full",
    "run_latent_reference",
    "run_runtime",
    "runtime_steps",
    "scenario_loads",
    "start_study",
    "trajectory_errors",
    "undrawn_configs",
    "write_csv",
    "write_outputs",
]
