"""`redsim bench stability --regimes damping`: implicit Euler's numerical damping, measured.

Backward Euler dissipates: an exact step of a convex energy loses |v_{t+1} - v_t|²_M / 2
(:mod:`redsim.integrators.energy_gain`), so an unforced scene slows down although nothing in it is a
damper. How much, per scene, space and time step:

- start: the static equilibrium under the constant load of the accuracy bench's ``push`` scenario
  (:data:`redsim.benches.stability.LOADS`: the env's unit action along +x on its handle), each space its
  own (full space: :func:`redsim.integrators.reference.full_equilibrium` from the rest
  :func:`redsim.integrators.reference.rest_state`; latent: :func:`redsim.integrators.latent_equilibrium`
  of the shipped map from its unloaded rest z*), at zero velocity (q_{-1} = q_0);
- release: the load removed (gravity and the scene's other effects stay), ``seconds`` simulated at dt / k
  for each k of ``divisions`` (dt = 0.02 s, the envs');
- free energy F_t = K_t + E(q_t) - E_rest [J], K_t = |q_t - q_{t-1}|²_M / (2 h²), E_rest the energy of the
  space's own unloaded equilibrium (full: q_rest; latent: f(z*)), all in float64
  (:func:`redsim.benches.stability.energy_account`);
- ``retained``: F_t / F_0 at 0.5 s, 1 s and ``seconds``; ``largest``: its maximum after the start (above
  1: the run gained energy). A run that comes to rest at another equilibrium than E_rest's ends away from 0; one
  whose F_0 is not > 0 (its start not above its rest) has no fraction: NaN, named under the table. cloth_ball's
  full space is one: from its rest (which converges: |g| 8.5e-5 N) the push (8 N along +x on the ball, under its
  9.81 N weight) finds no static equilibrium, the ball leaves the cloth and falls (nothing is below it), so the
  loaded solve stops unconverged (|g| = 12.7 N, the unbalanced load and weight) some 20 m below, 203 J under the
  rest. The static solves that did not converge are named under the table (:attr:`Start.unconverged`).

Runs: the latent runtime (:class:`redsim.runtime.LatentStepper`, B = 1, in float32, what the envs run, and
in float64, which separates the solver's tolerance from the integrator), and the float64 full-space reference
(:func:`redsim.benches.accuracy.run_full`: Newton to the scene's tolerance). ``idle`` counts the runtime steps
that took no iteration (the start was already within its tolerance, which grows as 1/h²: the state then does
not move); it is None (printed -) on the full-space and MuJoCo rows, as ``unconverged`` is on MuJoCo's. With mujoco
installed and the chain among the scenes: MuJoCo's 24-capsule chain of ``redsim bench step`` (ball joints, no joint
damping) lifted rigidly about the hook by the angle of the full-space chain's loaded tip, at rest, under
:data:`MUJOCO_INTEGRATORS` at the same time steps.

Exit status (``redsim bench stability``): a redsim row (not MuJoCo's: its ``implicit`` chain at 0.02 s gains 3x,
a fact about MuJoCo) whose ``largest`` exceeds 1 + :data:`GAIN_TOL` gained free energy unforced, a defect of the
integrator or the solver, and fails the command (exit 4, as an unreported gain in the other regimes; :func:`gains`);
a NaN fails it with 3. A Ctrl-C during :func:`bench_damping` raises :class:`Interrupted`, which holds the rows finished
before it; the command prints them and exits 130.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from redsim import pretrained, scenes
from redsim.benches.accuracy import run_full
from redsim.benches.stability import DT, LOADS, energy_account, mujoco_lifted_chain, runtime_rollout
from redsim.integrators import LatentSpace, latent_equilibrium
from redsim.integrators.reference import full_equilibrium, rest_state
from redsim.scene import Scene

SCENES = ("mini_chain", "chain", "bistable_bar", "conditional_bar")
"""Scenes measured by default (any of :data:`LOADS` with a shipped map can be asked for)."""
DIVISIONS = (1, 4, 16)
"""Time steps dt / k measured by default (dt = :data:`DT`)."""
SECONDS = 1.0
"""Simulated time [s] of each released run by default."""
CHECKPOINTS = (0.5, 1.0)
"""Simulated times [s] the retained fraction is reported at (beside the run's end)."""
RUNTIME_DTYPES = {"latent f32": torch.float32, "latent f64": torch.float64}
"""The latent runtime's rows: label and dtype."""
MUJOCO_INTEGRATORS = ("RK4", "implicit")
"""MuJoCo's integrators measured beside the chain."""
GAIN_TOL = 1e-3
"""Largest rise of F_t / F_0 above 1 a redsim row may show before it counts as a gain (:func:`gains`): 0.1% of the
start's free energy, the float32 ledger's slack (:data:`redsim.benches.stability.RISE_SLACK`).

An unforced backward-Euler run only loses free energy; one that does not move reads 1 to round-off. Measured at
0.5 s (dt 0.02, 0.005 and 0.00125 s; mini_chain, bistable_bar, conditional_bar, chain; AMD EPYC, at 9cf08bf): the
float32 chain idle at 0.00125 s (400 of 400 steps) read 1 + 3.6e-15, the idle mini chain exactly 1, and every moving
row at most 1 - 7.9e-5 (the chain's full space at 0.00125 s; its first step's loss)."""


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (or a SIGTERM made to raise) during :func:`bench_damping`; ``result`` holds the rows finished before it
    (the result's form, ``interrupted`` True). A KeyboardInterrupt, so a caller that does not look stops as before."""

    def __init__(self, result: dict[str, Any]) -> None:
        super().__init__("bench_damping interrupted")
        self.result = result


def check_seconds(seconds: float, divisions: Sequence[int], what: str = "seconds") -> None:
    """Refuse a run length ``seconds`` [s] that is not a whole multiple (>= 1) of every time step dt / k, k in
    ``divisions`` (float round-off aside): its step count and time columns would be rounded.

    Raises:
        ValueError: naming ``what``, the time steps and the step they all divide (dt / gcd(divisions)).
    """
    dts = [DT / k for k in sorted(set(divisions))]
    steps = [seconds / dt for dt in dts]
    if all(round(n) >= 1 and math.isclose(n, round(n), rel_tol=1e-9) for n in steps):
        return
    unit = DT / math.gcd(*(int(k) for k in divisions))
    raise ValueError(
        f"{what} must be a whole multiple of {unit:g} s (each time step {', '.join(f'{dt:g}' for dt in dts)} s "
        f"divides it), got {seconds!r}"
    )


def release_load(scene: Scene) -> Tensor:
    """The load [H, D] [N] (float64) the start is the equilibrium under: :data:`LOADS`' force along +x."""
    plan = LOADS[scene.name]
    load = torch.zeros(len(scene.handles), scene.dim, dtype=torch.float64)
    load[scene.handle_names.index(plan.handle), 0] = plan.max_force
    return load


@dataclasses.dataclass(frozen=True)
class Start:
    """Where the released runs start and what their free energy is measured from (module doc).

    Attributes:
        q0: Full-space start [n] (float64): the equilibrium under :func:`release_load`.
        q_rest: Full-space unloaded equilibrium [n].
        z0: Latent start [d] (float64).
        z_rest: The map's unloaded equilibrium z* [d].
        full_rest_J: E(q_rest) [J].
        latent_rest_J: E(f(z*)) [J].
        unconverged: The static solves that did not converge, of :data:`START_SOLVES`.
    """

    q0: Tensor
    q_rest: Tensor
    z0: Tensor
    z_rest: Tensor
    full_rest_J: float
    latent_rest_J: float
    unconverged: tuple[str, ...] = ()

    @property
    def converged(self) -> bool:
        """All four static solves converged."""
        return not self.unconverged


START_SOLVES = ("full rest", "full loaded", "latent rest", "latent loaded")
"""The static solves of a :class:`Start`: q_rest, q0, z* and z0."""


def release_start(scene: Scene, f: nn.Module) -> Start:
    """The :class:`Start` of a scene and its map f."""
    s64 = scene.to(dtype=torch.float64)
    load = release_load(scene)
    q_rest, rest_ok = rest_state(scene)
    q0, loaded_ok, _ = full_equilibrium(s64, load, start=q_rest)
    space = LatentSpace(s64, f)
    z_rest, z_rest_info = latent_equilibrium(space, None)
    z0, z0_info = latent_equilibrium(space, load, z0=z_rest)
    with torch.no_grad():
        energies = s64.energy(torch.stack([q_rest, space.configuration(z_rest.unsqueeze(0))[0]]))
    oks = (rest_ok, loaded_ok, z_rest_info.converged, z0_info.converged)
    unconverged = tuple(solve for solve, ok in zip(START_SOLVES, oks, strict=True) if not ok)
    return Start(q0, q_rest, z0, z_rest, float(energies[0]), float(energies[1]), unconverged)


def retained(scene: Scene, q: Tensor, q_prev: Tensor, dt: float, rest_energy: float) -> Tensor:
    """F_t / F_0 [T + 1] of an unloaded run q [T + 1, n] (q_prev [n]: the state before q[0]; module doc)."""
    loads = torch.zeros(q.shape[0] - 1, len(scene.handles), scene.dim, dtype=torch.float64)
    mechanical, _ = energy_account(scene, q, loads, dt, q_prev)
    free = mechanical - rest_energy
    return free / free[0]


def _row(
    name: str, space: str, dt: float, fractions: Tensor, free_J: float, seconds: float, **counts: Any
) -> dict[str, Any]:
    """One table row of run ``name``: the retained fraction at each checkpoint and at the end, and its counts.

    A start whose free energy ``free_J`` is not above the rest's has no fraction (NaN): F_t / F_0 then reads as
    energy kept (cloth_ball's full space: its loaded start, unconverged, 203 J below the rest gave "retained 1").
    """
    if not free_J > 0.0:
        fractions = torch.full_like(fractions, math.nan)
    values = {}
    for t in (*(c for c in CHECKPOINTS if c < seconds), seconds):
        index = round(t / dt)
        values[f"{t:g}"] = float(fractions[index]) if index < fractions.shape[0] else math.nan
    after = fractions[1:]
    return {
        "scene": name,
        "space": space,
        "dt": dt,
        "steps": int(fractions.shape[0] - 1),
        "free_energy_J": free_J,
        "retained": values,
        "largest": float(after.max()) if bool(torch.isfinite(after).all()) and after.numel() else math.nan,
        **counts,
    }


def scene_rows(
    scene: Scene,
    f: nn.Module,
    *,
    seconds: float,
    divisions: Sequence[int] = DIVISIONS,
    full_divisions: Sequence[int] = DIVISIONS,
    start: Start | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """The rows of one scene: the runtime (:data:`RUNTIME_DTYPES`) at dt / k for k in ``divisions``, the full
    space at dt / k for k in ``full_divisions``, each released from ``start`` (default :func:`release_start`).

    Raises:
        ValueError: ``seconds`` not a whole multiple of every time step (:func:`check_seconds`).
    """
    check_seconds(seconds, [*divisions, *full_divisions])
    start = release_start(scene, f) if start is None else start
    return list(_scene_rows(scene, f, seconds, divisions, full_divisions, start, progress))


def _scene_rows(
    scene: Scene,
    f: nn.Module,
    seconds: float,
    divisions: Sequence[int],
    full_divisions: Sequence[int],
    start: Start,
    progress: Callable[[str], None] | None,
) -> Iterator[dict[str, Any]]:
    """:func:`scene_rows`, each row as soon as it is measured (an interrupted run keeps those before)."""
    s64 = scene.to(dtype=torch.float64)
    tol = scenes.full_space_tol(scene.name)
    for k in divisions:
        dt = DT / k
        steps = round(seconds / dt)
        loads = torch.zeros(steps, len(scene.handles), scene.dim, dtype=torch.float64)
        for label, dtype in RUNTIME_DTYPES.items():
            begin = time.perf_counter()
            run = runtime_rollout(scene, f, loads, dt, z0=start.z0, z_prev=start.z0, dtype=dtype)
            fractions = retained(s64, run.q, run.q_prev, dt, start.latent_rest_J)
            free = float(s64.energy(run.q[:1])[0]) - start.latent_rest_J
            nan = run.nonfinite + int((~torch.isfinite(run.q)).any(-1).sum())
            yield _row(
                scene.name,
                label,
                dt,
                fractions,
                free,
                seconds,
                unconverged=run.flags["unconverged"],
                idle=run.flags["idle"],
                nan=nan,
                wall_s=time.perf_counter() - begin,
            )
            if progress:
                progress(f"damping {scene.name} {label} dt {dt:g}: {time.perf_counter() - begin:.1f} s")
    for k in full_divisions:
        dt = DT / k
        steps = round(seconds / dt)
        loads = torch.zeros(steps, len(scene.handles), scene.dim, dtype=torch.float64)
        begin = time.perf_counter()
        run = run_full(scene, start.q0, loads, dt=dt, tol=tol, max_iter=100)
        fractions = retained(s64, run.q, run.q[0], dt, start.full_rest_J)
        free = float(s64.energy(run.q[:1])[0]) - start.full_rest_J
        yield _row(
            scene.name,
            "full f64",
            dt,
            fractions,
            free,
            seconds,
            unconverged=run.failed,
            idle=None,  # the runtime's count (a full-space step at its start is not idle: it was solved there)
            nan=run.nonfinite,
            wall_s=time.perf_counter() - begin,
        )
        if progress:
            progress(f"damping {scene.name} full dt {dt:g}: {time.perf_counter() - begin:.1f} s")


def lift_angle(scene: Scene, start: Start) -> float:
    """Angle [rad] about the hook (the origin) between the chain's handle at the start and at rest."""
    s64 = scene.to(dtype=torch.float64)
    p = s64.handle_positions(torch.stack([start.q0, start.q_rest]))
    a, b = p[0], p[1]
    return float(torch.atan2(torch.linalg.vector_norm(torch.linalg.cross(a, b)), (a * b).sum()))


def mujoco_rows(
    angle: float,
    *,
    seconds: float,
    divisions: Sequence[int] = DIVISIONS,
    integrators: Sequence[str] = MUJOCO_INTEGRATORS,
) -> list[dict[str, Any]] | None:
    """MuJoCo's 24-capsule chain lifted by ``angle`` [rad] at rest, released (module doc); None without mujoco.

    Its free energy is MuJoCo's total energy (``data.energy``, evaluated after each step) above the hanging rest.

    Raises:
        ValueError: ``seconds`` not a whole multiple of every time step (:func:`check_seconds`).
    """
    check_seconds(seconds, divisions)
    try:
        import mujoco
    except ImportError:
        return None
    rows = []
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda _text: None)  # a blow-up shows as a NaN or a gain in the row
    try:
        for k in divisions:
            dt = DT / k
            for integrator in integrators:
                model, data, rest = mujoco_lifted_chain(integrator, dt, angle)
                mujoco.mj_forward(model, data)
                energies = [float(data.energy.sum())]
                begin = time.perf_counter()
                for _ in range(round(seconds / dt)):
                    mujoco.mj_step(model, data)
                    mujoco.mj_forward(model, data)  # data.energy of the new state
                    energies.append(float(data.energy.sum()) if np.isfinite(data.qpos).all() else math.nan)
                free = torch.tensor(energies, dtype=torch.float64) - rest
                nan = int((~torch.isfinite(free)).sum())
                wall = time.perf_counter() - begin
                fractions = free / free[0]
                rows.append(
                    _row(
                        "mujoco_chain",
                        f"MuJoCo {integrator}",
                        dt,
                        fractions,
                        float(free[0]),
                        seconds,
                        unconverged=None,  # no solve of redsim's to report on
                        idle=None,
                        nan=nan,
                        wall_s=wall,
                    )
                )
    finally:
        mujoco.set_mju_user_warning(previous)
    return rows


def bench_damping(
    names: Sequence[str] = SCENES,
    *,
    seconds: float = SECONDS,
    divisions: Sequence[int] = DIVISIONS,
    full_divisions: Sequence[int] = DIVISIONS,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Every scene's rows (:func:`scene_rows`), and MuJoCo's chain (:func:`mujoco_rows`) when ``chain`` is one.

    Raises:
        ValueError: a scene without a :data:`LOADS` plan or a shipped map, ``seconds`` not > 0 or not a whole
            multiple of every time step (:func:`check_seconds`), or a division < 1.
        Interrupted: a KeyboardInterrupt (Ctrl-C) while it ran; its ``result`` holds the rows finished before.
    """
    unknown = [n for n in names if n not in LOADS or n not in pretrained.names()]
    if unknown:
        valid = sorted(n for n in LOADS if n in pretrained.names())
        raise ValueError(f"damping runs on {valid}, not {unknown}")
    if not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"seconds must be finite and > 0, got {seconds!r}")
    if any(int(k) != k or k < 1 for k in (*divisions, *full_divisions)):
        raise ValueError(f"divisions must be integers >= 1, got {list(divisions)} and {list(full_divisions)}")
    check_seconds(seconds, [*divisions, *full_divisions])
    rows: list[dict[str, Any]] = []
    mujoco: list[dict[str, Any]] | None = None
    starts: dict[str, list[str]] = {}
    angle = None

    def result(interrupted: bool) -> dict[str, Any]:
        return {
            "dt": DT,
            "seconds": seconds,
            "divisions": list(divisions),
            "full_divisions": list(full_divisions),
            "starts_converged": {name: not failed for name, failed in starts.items()},
            "starts_unconverged": starts,
            "mujoco_lift_deg": None if angle is None else math.degrees(angle),
            "rows": rows,
            "mujoco": mujoco,
            "interrupted": interrupted,
        }

    try:
        for name in names:
            scene = scenes.build(name)
            f = pretrained.load(name, scene)
            start = release_start(scene, f)
            starts[name] = list(start.unconverged)
            for row in _scene_rows(scene, f, seconds, divisions, full_divisions, start, progress):
                rows.append(row)
            if name == "chain":  # the angle with the rows: alone, it would read as "mujoco is not installed"
                lift = lift_angle(scene, start)
                mujoco = mujoco_rows(lift, seconds=seconds, divisions=divisions)
                angle = lift
    except KeyboardInterrupt as stop:
        raise Interrupted(result(True)) from stop
    return result(False)


def gains(result: dict[str, Any]) -> list[str]:
    """The redsim rows of a :func:`bench_damping` result (not MuJoCo's) whose released run gained free energy:
    ``largest`` > 1 + :data:`GAIN_TOL`, each as "scene space dt DT" (a NaN largest, no fraction, is not one)."""
    return [f"{r['scene']} {r['space']} dt {r['dt']:g}" for r in result["rows"] if r["largest"] > 1.0 + GAIN_TOL]


def report(result: dict[str, Any]) -> list[str]:
    """The damping regime's heading and :func:`damping_table`."""
    head = (
        f"numerical damping: free energy K + E - E_rest retained after release, {result['seconds']:g} s unforced "
        "from the equilibrium under the push load, at zero velocity (redsim.benches.damping)"
    )
    return [head, *damping_table(result)]


def damping_table(result: dict[str, Any]) -> list[str]:
    """The result as markdown lines: one row per scene, space and time step (module doc)."""
    seconds = result["seconds"]
    times = [f"{t:g}" for t in (*(c for c in CHECKPOINTS if c < seconds), seconds)]
    head = [
        "scene",
        "space",
        "dt [s]",
        "steps",
        "free energy at start [J]",
        *(f"retained at {t} s" for t in times),
        "largest",
        "unconverged",
        "idle",
        "nan",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in [*result["rows"], *(result["mujoco"] or [])]:
        cells = [row["scene"], row["space"], f"{row['dt']:g}", str(row["steps"]), f"{row['free_energy_J']:.3g}"]
        cells += [f"{row['retained'].get(t, math.nan):.3g}" for t in times]
        counts = (row["unconverged"], row["idle"], row["nan"])
        cells += [f"{row['largest']:.3g}", *("-" if v is None else str(v) for v in counts)]
        lines.append("| " + " | ".join(cells) + " |")
    notes = []
    if result.get("mujoco_lift_deg") is not None:
        if result["mujoco"] is None:
            notes.append("mujoco is not installed (pip install 'redsim[bench]'): no MuJoCo rows")
        else:
            notes.append(
                f"mujoco_chain: MuJoCo's 24-capsule chain lifted rigidly by {result['mujoco_lift_deg']:.3g} deg (the "
                "full-space chain's loaded tip about the hook), released at rest"
            )
    unconverged = [f"{k} ({', '.join(v)})" for k, v in result["starts_unconverged"].items() if v]
    if unconverged:
        notes.append(f"a static solve of the start did not converge: {'; '.join(unconverged)}")
    below = sorted({f"{r['scene']} {r['space']}" for r in result["rows"] if not r["free_energy_J"] > 0.0})
    if below:
        notes.append(
            f"no retained fraction (nan) where the start is not above the rest: {', '.join(below)} (its free energy "
            "at the start is <= 0)"
        )
    gained = gains(result)
    if gained:
        notes.append(
            f"gained free energy unforced (largest > 1 + {GAIN_TOL:g}, a defect of the integrator or the solve): "
            + ", ".join(gained)
        )
    if result.get("interrupted"):
        notes.append("interrupted: the rows finished before it")
    return lines + (["", *notes] if notes else [])


__all__ = [
    "CHECKPOINTS",
    "DIVISIONS",
    "GAIN_TOL",
    "MUJOCO_INTEGRATORS",
    "RUNTIME_DTYPES",
    "SCENES",
    "SECONDS",
    "START_SOLVES",
    "Interrupted",
    "Start",
    "bench_damping",
    "check_seconds",
    "damping_table",
    "gains",
    "lift_angle",
    "mujoco_rows",
    "release_load",
    "release_start",
    "report",
    "retained",
    "scene_rows",
]
