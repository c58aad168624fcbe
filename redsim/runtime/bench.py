"""`redsim bench step`: env-steps per second of the latent stepper against today's reference path.

Every row is measured side by side in one process on the same seeded load sequences: the
reference ``ImplicitEuler(LatentSpace(scene, f))`` (one state at a time, so its env-steps/s do
not grow with B), the :class:`~redsim.runtime.LatentStepper` in eager mode and compiled, and the
full-space reference step at B = 1 for scale. With ``mujoco`` installed the same run times a
MuJoCo chain of 24 capsules on ball joints (nv = 72) and prints simulated seconds per wall second.
"""

from __future__ import annotations

import math
import statistics
import time
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from redsim import scenes
from redsim.integrators import FullSpace, FullState, ImplicitEuler, LatentSpace
from redsim.runtime.baseline import run_baseline
from redsim.runtime.solver import HESSIANS
from redsim.runtime.stepper import LatentStepper
from redsim.scene import Scene

LOAD_FRACTION = 0.1
"""Load size: each handle's linear response in the subspace is up to this fraction of the scene size L."""
LOAD_EVERY = 5
"""The loads change every this many steps."""
REFERENCE_WARMUP = 2
"""Untimed steps before a reference path's timed ones (its own and a baseline's), as the stepper's runs have."""
FULL_SPACE_SETTLE = 4
"""Untimed full-space steps from f(z_rest) before the full-space row's timed ones (:func:`run_reference`)."""


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def load_magnitudes(stepper: LatentStepper, fraction: float = LOAD_FRACTION) -> Tensor:
    """Force [N] per handle, shape [H]: the subspace's static response to it is ``fraction`` * L.

    The compliance of handle h at the rest latent z* is the largest eigenvalue of
    G_h J H^-1 J^T G_h^T (J = dq/dz, H the latent energy Hessian made positive definite by absolute
    eigenvalues, G_h the handle's position map), so the loads stay inside the range the map covers.
    """
    z_rest = stepper.rest_latent()[0].to(torch.float64)
    energy = stepper.energy
    cond = stepper._default_cond(1, torch.float64)
    scene64 = stepper.source_scene.to(device=stepper.device, dtype=torch.float64)

    def potential(z: Tensor) -> Tensor:
        e, _ = energy.energy(z.to(stepper.dtype).unsqueeze(0), None if cond is None else cond.to(stepper.dtype))
        return e[0].to(torch.float64)

    hessian = torch.autograd.functional.hessian(potential, z_rest)
    w, v = torch.linalg.eigh(0.5 * (hessian + hessian.T))
    w = w.abs().clamp_min(1e-12 * float(w.abs().max()))
    jac = torch.autograd.functional.jacobian(
        lambda z: energy.positions(z.to(stepper.dtype).unsqueeze(0), cond if cond is None else cond.to(stepper.dtype))[
            0
        ].to(torch.float64),
        z_rest,
    )
    handles = stepper._handle_matrix.to(torch.float64) @ jac  # [H*D, d]
    compliance = handles @ (v / w) @ v.T @ handles.T
    H, D = len(scene64.handles), scene64.dim
    out = []
    for h in range(H):
        block = compliance[h * D : (h + 1) * D, h * D : (h + 1) * D]
        c = float(torch.linalg.eigvalsh(0.5 * (block + block.T)).max())
        out.append(fraction * stepper.length / c if c > 0 else 1.0)
    return torch.tensor(out, dtype=torch.float64)


def load_sequence(
    scene: Scene, magnitudes: Tensor, steps: int, batch: int, *, every: int = LOAD_EVERY, seed: int = 0
) -> Tensor:
    """Loads [steps, B, H, D] [N]: every ``every`` steps each state draws, per handle, a uniformly random
    direction and a magnitude uniform in [0, magnitudes[h]] (seeded)."""
    g = torch.Generator().manual_seed(seed)
    H, D = len(scene.handles), scene.dim
    out = torch.zeros(steps, batch, H, D, dtype=torch.float64)
    for start in range(0, steps, every):
        direction = torch.randn(batch, H, D, generator=g, dtype=torch.float64)
        direction = direction / torch.linalg.vector_norm(direction, dim=-1, keepdim=True)
        size = torch.rand(batch, H, 1, generator=g, dtype=torch.float64) * magnitudes.reshape(1, H, 1)
        out[start : start + every] = direction * size
    return out


def run_stepper(
    stepper: LatentStepper, z0: Tensor, loads: Tensor, *, warmup: int = 2, warm: bool = True
) -> dict[str, Any]:
    """Step B states from rest (z = z_prev = z0 [B, d]) through ``loads`` [steps, B, H, D].

    Each step takes E and dE/dz at z_t from the last step's ``stats.carry``, and with ``warm`` starts its solver
    from the last step's model (``stats.model``), as the envs do.

    Returns env_steps_per_s (B * steps / wall time of the timed steps, after ``warmup`` untimed ones
    from the same start), per-step medians (wall and this process's CPU time), iterations per step (mean
    over states and steps), the objective's calls and evaluated rows per step, converged fraction,
    flagged fractions and the trajectory [steps + 1, B, d].
    """
    device = stepper.device
    loads = loads.to(device=device, dtype=stepper.dtype)
    z = z0.to(device=device, dtype=stepper.dtype)
    for i in range(min(warmup, loads.shape[0])):
        stepper.step(z, z, loads[i])
    _sync(device)
    z_prev = z.clone()
    trajectory = [z.clone()]
    times, cpu_times, iterations, converged, out_of_range, diverged = [], [], [], [], [], []
    model = carry = None
    calls, rows = stepper.evaluations.calls, stepper.evaluations.rows
    for i in range(loads.shape[0]):
        start, cpu_start = time.perf_counter(), time.process_time()
        z_next, stats = stepper.step(z, z_prev, loads[i], warm=model, carry=carry)
        model, carry = stats.model if warm else None, stats.carry
        _sync(device)
        times.append(time.perf_counter() - start)
        cpu_times.append(time.process_time() - cpu_start)
        z_prev, z = z, z_next
        trajectory.append(z.clone())
        iterations.append(stats.iterations.to(torch.float64).mean().item())
        converged.append(stats.converged.to(torch.float64).mean().item())
        out_of_range.append(stats.out_of_range.to(torch.float64).mean().item())
        diverged.append(stats.diverged.to(torch.float64).mean().item())
    batch = z0.shape[0]
    return {
        "env_steps_per_s": batch * len(times) / sum(times),
        "median_step_s": statistics.median(times),
        "median_step_cpu_s": statistics.median(cpu_times),
        "iterations_per_step": statistics.fmean(iterations),
        "calls_per_step": (stepper.evaluations.calls - calls) / len(times),
        "rows_per_step": (stepper.evaluations.rows - rows) / len(times),
        "converged_fraction": statistics.fmean(converged),
        "out_of_range_fraction": statistics.fmean(out_of_range),
        "diverged_fraction": statistics.fmean(diverged),
        "trajectory": torch.stack(trajectory).cpu(),
    }


def run_reference(
    scene: Scene,
    subspace: nn.Module,
    dt: float,
    z0: Tensor,
    loads: Tensor,
    *,
    space: str = "latent",
    warmup: int = REFERENCE_WARMUP,
    settle: int = 0,
) -> dict[str, Any]:
    """Today's path, one state: ``ImplicitEuler(LatentSpace(scene, f), dt)`` (or ``FullSpace`` from f(z0))
    through ``loads`` [steps, H, D]; env-steps/s, iterations, converged fraction, trajectory.

    The first ``warmup`` steps run once untimed from the same start (first-call costs), as in :func:`run_stepper`.
    Then the first ``settle`` steps of ``loads`` run untimed and the timing goes on from the state they reach: for
    a start that is not at rest in this space (f(z0) in the full space, whose first Newton solves take 2-3x the
    iterations of later ones); the trajectory starts there too.
    """
    if space == "latent":
        integrator = ImplicitEuler(LatentSpace(scene, subspace), dt)
        u0 = z0.to(torch.float64)
    else:
        integrator = ImplicitEuler(FullSpace(scene), dt, tol=scenes.full_space_tol(scene.name))
        with torch.no_grad():
            u0 = LatentSpace(scene, subspace).configuration(z0.to(torch.float64).unsqueeze(0))[0]
    state = FullState(u0.clone(), u0.clone(), 0.0)
    for i in range(min(warmup, loads.shape[0])):
        state, _ = integrator.step(state, loads[i])
    state = FullState(u0.clone(), u0.clone(), 0.0)
    for i in range(min(settle, loads.shape[0] - 1)):
        state, _ = integrator.step(state, loads[i])
    times, iterations, converged, trajectory = [], [], [], [state.q.clone()]
    for i in range(min(settle, loads.shape[0] - 1), loads.shape[0]):
        start = time.perf_counter()
        state, info = integrator.step(state, loads[i])
        times.append(time.perf_counter() - start)
        iterations.append(info.iterations)
        converged.append(float(info.converged))
        trajectory.append(state.q.clone())
    return {
        "env_steps_per_s": len(times) / sum(times),
        "median_step_s": statistics.median(times),
        "iterations_per_step": statistics.fmean(iterations),
        "converged_fraction": statistics.fmean(converged),
        "trajectory": torch.stack(trajectory),
    }


MUJOCO_CHAIN_LINKS = 24


def mujoco_chain_xml(links: int = MUJOCO_CHAIN_LINKS, *, integrator: str = "RK4", timestep: float = 0.01) -> str:
    """MJCF of a hanging chain of ``links`` capsules (radius 0.01 m, length 0.1 m, steel) on ball joints."""
    body = ""
    for i in reversed(range(links)):
        pos = "0 0 0" if i == 0 else "0 0 -0.1"
        body = (
            f'<body name="link{i}" pos="{pos}"><joint type="ball"/>'
            f'<geom type="capsule" fromto="0 0 0 0 0 -0.1" size="0.01" density="7800"/>{body}</body>'
        )
    return (
        f'<mujoco><option timestep="{timestep}" integrator="{integrator}" gravity="0 0 -9.81"/>'
        f'<worldbody><body name="hook" pos="0 0 3">{body}</body></worldbody></mujoco>'
    )


def mujoco_chain(*, integrator: str, timestep: float) -> tuple[Any, Any] | None:
    """The MuJoCo chain's ``(MjModel, MjData)``, swinging, after 100 untimed steps (None without mujoco)."""
    try:
        import mujoco
    except ImportError:
        return None
    model = mujoco.MjModel.from_xml_string(mujoco_chain_xml(integrator=integrator, timestep=timestep))
    data = mujoco.MjData(model)
    data.qvel[:] = 0.1  # start swinging
    for _ in range(100):
        mujoco.mj_step(model, data)
    return model, data


def run_mujoco_chain(*, integrator: str, timestep: float, steps: int) -> dict[str, Any] | None:
    """Steps/s and simulated seconds per wall second of the MuJoCo chain, the mean of a bare loop of ``steps``
    steps, as ``redsim bench step`` times its rates (None without mujoco)."""
    built = mujoco_chain(integrator=integrator, timestep=timestep)
    if built is None:
        return None
    import mujoco

    model, data = built
    start = time.perf_counter()
    for _ in range(steps):
        mujoco.mj_step(model, data)
    wall = time.perf_counter() - start
    return {
        "integrator": integrator,
        "timestep": timestep,
        "nv": int(model.nv),
        "steps_per_s": steps / wall,
        "sim_s_per_wall_s": steps * timestep / wall,
    }


def _configurations(stepper: LatentStepper, z: Tensor) -> Tensor:
    """f(z) [K, n] (float64, CPU) of latents z [K, d]."""
    return stepper.positions(z.to(device=stepper.device, dtype=stepper.dtype)).to(torch.float64).cpu()


def _m_norm(scene: Scene, v: Tensor) -> Tensor:
    return (v * scene.to(dtype=torch.float64).mass_matvec(v)).sum(-1).clamp_min(0.0).sqrt()


def _relative_error(error: Tensor, motion: Tensor) -> float | None:
    """The largest ``error`` over the largest ``motion`` (M-norms); None where the reference did not move (its
    largest motion is 0) and the error is finite: the relative error is undefined. NaN where either is not finite."""
    err, move = float(error.max()), float(motion.max())
    if move == 0.0 and math.isfinite(err):
        return None
    return err / move if move > 0.0 else math.nan


def one_step_error(stepper: LatentStepper, reference: Tensor, loads: Tensor) -> float | None:
    """Largest |f(z_mine) - f(z_ref)|_M over the steps of a reference trajectory, relative to the largest
    step |f(z_ref) - f(z_t)|_M; None where no reference step moved (:func:`_relative_error`).

    Every reference step (z_t, z_{t-1}, loads_t) -> z_{t+1} is taken again by ``stepper`` from the
    same state, all steps as one batch, so the error is one solve's, not an accumulated drift.
    """
    z_t = reference[:-1]
    z_prev = torch.cat([reference[:1], reference[:-2]])
    dtype, device = stepper.dtype, stepper.device
    mine, _ = stepper.step(z_t.to(device, dtype), z_prev.to(device, dtype), loads.to(device, dtype))
    q_mine, q_ref, q_t = (_configurations(stepper, u) for u in (mine, reference[1:], z_t))
    scene = stepper.source_scene
    return _relative_error(_m_norm(scene, q_mine - q_ref), _m_norm(scene, q_ref - q_t))


def _rollout_error(stepper: LatentStepper, reference: Tensor, mine: Tensor) -> float | None:
    """Largest |f(z_mine) - f(z_ref)|_M over a rollout relative to the largest |f(z_ref) - f(z_0)|_M; None where the
    reference did not move (:func:`_relative_error`)."""
    count = reference.shape[0]
    q_mine, q_ref = _configurations(stepper, mine[:count]), _configurations(stepper, reference)
    scene = stepper.source_scene
    return _relative_error(_m_norm(scene, q_mine - q_ref), _m_norm(scene, q_ref - q_ref[:1]))


def compare_hessians(
    scene: Scene,
    subspace: nn.Module,
    *,
    dt: float = 0.02,
    batch: int = 16,
    steps: int = 20,
    hessians: tuple[str, ...] = HESSIANS,
    seed: int = 0,
    device: str = "cpu",
) -> list[dict[str, Any]]:
    """Iterations/step, time/step and converged fraction of each solver Hessian model, same loads, on ``device``."""
    rows = []
    loads = None
    for hessian in hessians:
        stepper = LatentStepper(scene, subspace, dt, hessian=hessian, device=device)
        if loads is None:
            loads = load_sequence(scene, load_magnitudes(stepper), steps, batch, seed=seed)
            z0 = stepper.rest_latent().expand(batch, -1).clone()
        result = run_stepper(stepper, z0, loads)
        result.pop("trajectory")
        rows.append({"scene": scene.name, "hessian": hessian, "batch": batch, **result})
    return rows


def bench_step(
    scene: Scene,
    subspace: nn.Module,
    *,
    dt: float = 0.02,
    batches: tuple[int, ...] = (1, 16, 64, 256),
    steps: int = 20,
    reference_steps: int = 10,
    compiled: bool = True,
    device: str = "cpu",
    seed: int = 0,
    rounds: int = 1,
    dense: bool = False,
    baseline: Path | None = None,
) -> dict[str, Any]:
    """One scene's row of `redsim bench step` (module doc).

    With ``baseline`` (a source tree of another redsim version) each round also times that version's
    reference path on the same loads and start (:func:`redsim.runtime.baseline.run_baseline`), right
    after this version's: ``baseline`` in the row, and ``speedup_baseline`` of every path and B over it.

    With ``dense`` the eager, cold and compiled steppers use the row-selected solver iteration and the
    same run adds ``dense`` and ``dense-cmp`` (compiled): the dense masked iteration (else all use the
    stepper's default, dense exactly on CUDA).

    With ``rounds`` > 1 the reference and every (path, B) run again on the same loads in each round (in
    reverse order every other round, so that a change of the machine's load hits all alike): a rate is
    the median over the rounds (each round's list under ``rounds_env_steps_per_s``), as is a median
    step's CPU time (``rounds_median_step_cpu_s``), and a speedup the median of the per-round ratios to
    that round's reference.

    Returns:
        ``scene``, ``n``, ``d``, ``reference`` and ``full_space`` (B = 1), ``eager``, ``cold`` (eager
        without the warm start from the last step's solver model), ``compiled`` (and with ``dense``,
        ``dense`` and ``dense-cmp``) (per B:
        env_steps_per_s, iterations_per_step, converged_fraction, ...), ``speedup`` of each over the
        reference per B, and ``trajectory_error``: the largest |f(z) - f(z_ref)|_M over the B = 1 eager run's
        first ``reference_steps`` steps relative to the largest motion |f(z_ref) - f(z0)|_M (z_ref: the
        latent float64 reference, not the full space); ``step_error`` (:func:`one_step_error`). Either error
        is None where the reference did not move (e.g. loads too small to be felt at this dt): it is undefined.
    """
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    rows_option = False if dense else None  # dense= of the eager, cold and compiled steppers
    stepper = LatentStepper(scene, subspace, dt, device=device, dense=rows_option)
    magnitudes = load_magnitudes(stepper)
    z_rest = stepper.rest_latent().cpu()
    loads = load_sequence(scene, magnitudes, steps, max(batches), seed=seed)
    reference = run_reference(scene, subspace, dt, z_rest[0], loads[:reference_steps, 0])
    reference_rates = [reference["env_steps_per_s"]]

    def time_baseline() -> dict[str, Any]:
        assert baseline is not None
        return run_baseline(
            baseline, scene.name, subspace, dt, z_rest[0], loads[:reference_steps, 0], warmup=REFERENCE_WARMUP
        )

    baselines = [time_baseline()] if baseline is not None else []
    settle = FULL_SPACE_SETTLE
    full_loads = loads[: settle + min(3, reference_steps), 0]
    full = run_reference(scene, subspace, dt, z_rest[0], full_loads, space="full", warmup=0, settle=settle)
    row: dict[str, Any] = {
        "scene": scene.name,
        "n": scene.free_dof_count,
        "d": stepper.latent_dim,
        "load_magnitudes": magnitudes.tolist(),
        "reference": {k: v for k, v in reference.items() if k != "trajectory"},
        "full_space": {k: v for k, v in full.items() if k != "trajectory"},
        "eager": {},
        "cold": {},
        "compiled": {},
        **({"dense": {}, "dense-cmp": {}} if dense else {}),
    }
    row["step_error"] = one_step_error(stepper, reference["trajectory"], loads[:reference_steps, 0])
    variants = [("eager", stepper, True), ("cold", stepper, False)]
    if dense:
        variants.append(("dense", LatentStepper(scene, subspace, dt, device=device, dense=True), True))
    if compiled:
        for label, option in [("compiled", rows_option)] + [("dense-cmp", True)] * dense:
            runner = LatentStepper(scene, subspace, dt, device=device, compile=True, dense=option)
            variants.append((label, runner, True))
    runs = [(label, runner, warm, b) for label, runner, warm in variants for b in batches]
    rates: dict[tuple[str, int], list[float]] = {}
    cpu: dict[tuple[str, int], list[float]] = {}
    for r in range(rounds):
        if r:
            reference_rates.append(
                run_reference(scene, subspace, dt, z_rest[0], loads[:reference_steps, 0])["env_steps_per_s"]
            )
            if baseline is not None:
                baselines.append(time_baseline())
        for label, runner, warm, b in runs if r % 2 == 0 else runs[::-1]:
            result = run_stepper(runner, z_rest.expand(b, -1).clone(), loads[:, :b], warm=warm)
            trajectory = result.pop("trajectory")
            rates.setdefault((label, b), []).append(result["env_steps_per_s"])
            cpu.setdefault((label, b), []).append(result["median_step_cpu_s"])
            if r == 0:
                if b == 1 and label == "eager":
                    row["trajectory_error"] = _rollout_error(runner, reference["trajectory"], trajectory[:, 0])
                row[label][str(b)] = result
    row["rounds"] = rounds
    row["reference"]["rounds_env_steps_per_s"] = reference_rates
    row["reference"]["env_steps_per_s"] = statistics.median(reference_rates)
    row["speedup"] = {}
    for (label, b), per_round in rates.items():
        result = row[label][str(b)]
        result["rounds_env_steps_per_s"] = per_round
        result["env_steps_per_s"] = statistics.median(per_round)
        result["rounds_median_step_cpu_s"] = cpu[label, b]
        result["median_step_cpu_s"] = statistics.median(cpu[label, b])
        ratios = [mine / ref for mine, ref in zip(per_round, reference_rates, strict=True)]
        row["speedup"].setdefault(label, {})[str(b)] = statistics.median(ratios)
        if baselines:
            ratios = [mine / base["env_steps_per_s"] for mine, base in zip(per_round, baselines, strict=True)]
            row.setdefault("speedup_baseline", {}).setdefault(label, {})[str(b)] = statistics.median(ratios)
    if baselines:
        row["baseline"] = {
            **baselines[0],
            "rounds_env_steps_per_s": [base["env_steps_per_s"] for base in baselines],
            "env_steps_per_s": statistics.median(base["env_steps_per_s"] for base in baselines),
            "same_weights": all(base["same_weights"] for base in baselines),
        }
    return row


STEP_SCENES = ("mini_chain", "chain", "klann", "bistable_bar", "hanging_sheet", "cloth_ball")
"""The scenes of `redsim bench step` by default."""


def mujoco_rows(*, steps: int = 5000) -> list[dict[str, Any]] | None:
    """The MuJoCo chain with RK4 at dt 0.01 and Euler at dt 0.002 (None without mujoco)."""
    rows = [
        run_mujoco_chain(integrator="RK4", timestep=0.01, steps=steps),
        run_mujoco_chain(integrator="Euler", timestep=0.002, steps=steps),
    ]
    return None if rows[0] is None else [r for r in rows if r is not None]


def _error_text(row: dict[str, Any]) -> str:
    """The ``error`` line's text of a :func:`bench_step` row: its one-step and rollout errors (None: undefined)."""
    errors = [row["step_error"], row.get("trajectory_error", math.inf)]  # inf: the rollout did not run
    step, rollout = ("undefined" if e is None else f"{e:.2g}" for e in errors)
    if "trajectory_error" not in row:
        rollout = "not run (B = 1 not in --batches)"
    idle = "; undefined: the reference did not move" if None in errors else ""
    return (
        "eager (B = 1) against the reference row (the latent float64 solve, not full space): "
        f"one step {step}, rollout {rollout} of the motion (M-norm of f(z)){idle}"
    )


def step_table(rows: list[dict[str, Any]], mujoco: list[dict[str, Any]] | None, dt: float) -> list[str]:
    """The human-readable lines of `redsim bench step` for ``rows`` of :func:`bench_step`."""
    lines = []
    batches = list(rows[0]["eager"]) if rows else []
    head = f"{'scene':<14} {'n':>6} {'d':>2} {'path':<9} " + " ".join(f"{'B=' + b:>9}" for b in batches)
    lines.append("env-steps/s (iterations/step, converged %) per batch size B; reference and full space at B = 1")
    lines.append("env-steps/s: B x steps / the steps' total wall time (`bench envs`: B / its median step)")
    rounds = max((row.get("rounds", 1) for row in rows), default=1)
    if rounds > 1:  # say what the cells are, as `bench envs` does: not one run's rates
        lines.append(
            f"each rate the median over {rounds} rounds (the reference and every path in turn, reversed every other "
            "round) of B x steps / their wall time; speedup: the median of the per-round ratios to that round's "
            "reference; its, conv% and the full row: the first round's"
        )
    lines.append(head + "   its  conv%")
    lines.append("-" * (len(head) + 13))
    for row in rows:
        ref, full = row["reference"], row["full_space"]
        lead = f"{row['scene']:<14} {row['n']:>6} {row['d']:>2}"
        cells = " ".join(f"{ref['env_steps_per_s']:>9.3g}" for _ in batches)
        its, conv = ref["iterations_per_step"], 100 * ref["converged_fraction"]
        lines.append(f"{lead} {'reference':<9} {cells}  {its:>4.1f} {conv:>6.1f}")
        base = row.get("baseline")
        if base is not None:
            cells = " ".join(f"{base['env_steps_per_s']:>9.3g}" for _ in batches)
            same = "same map" if base["same_weights"] else "its OWN shipped map, not this one"
            lines.append(f"{'':<23} {'baseline':<9} {cells}  {base['iterations_per_step']:>4.1f}  ({same})")
        for label in ("eager", "cold", "compiled", "dense", "dense-cmp"):
            if not row.get(label):
                continue
            results = row[label]
            cells = " ".join(f"{results[b]['env_steps_per_s']:>9.3g}" for b in batches)
            its = statistics.fmean(r["iterations_per_step"] for r in results.values())
            conv = min(r["converged_fraction"] for r in results.values())
            lines.append(f"{'':<23} {label:<9} {cells}  {its:>4.1f} {100 * conv:>6.1f}")
            speed = " ".join(f"{row['speedup'][label][b]:>8.3g}x" for b in batches)
            lines.append(f"{'':<23} {'speedup':<9} {speed}")
            if base is not None:
                speed = " ".join(f"{row['speedup_baseline'][label][b]:>8.3g}x" for b in batches)
                lines.append(f"{'':<23} {'vs base':<9} {speed}")
        lines.append(
            f"{'':<23} {'full':<9} {full['env_steps_per_s']:>9.3g} (B = 1, {full['iterations_per_step']:.1f} its, "
            f"{100 * full['converged_fraction']:.0f}% converged; float64 full-space implicit Euler)"
        )
        lines.append(f"{'':<23} {'error':<9} {_error_text(row)}")
    sources = sorted({row["baseline"]["redsim_file"] for row in rows if "baseline" in row})
    lines.extend(f"baseline: the reference path (B = 1) of {source}; vs base: speedup over it" for source in sources)
    if mujoco is None:
        lines.append("mujoco is not installed (pip install 'redsim[bench]'): MuJoCo chain skipped")
    else:
        chain = next((r for r in rows if r["scene"] == "chain"), None)
        for m in mujoco:
            lines.append(
                f"MuJoCo chain nv={m['nv']} {m['integrator']} dt={m['timestep']}: {m['steps_per_s']:.3g} steps/s, "
                f"{m['sim_s_per_wall_s']:.3g} sim-s/s"
            )
            if chain is not None:
                for label in ("eager", "compiled"):
                    for b, r in chain[label].items():
                        ratio = r["env_steps_per_s"] * dt / m["sim_s_per_wall_s"]
                        lines.append(f"    latent chain {label} B={b}: {ratio:.3g}x MuJoCo's sim-s/s")
    return lines


__all__ = [
    "LOAD_EVERY",
    "LOAD_FRACTION",
    "STEP_SCENES",
    "bench_step",
    "compare_hessians",
    "load_magnitudes",
    "load_sequence",
    "mujoco_chain_xml",
    "mujoco_rows",
    "one_step_error",
    "run_mujoco_chain",
    "run_reference",
    "run_stepper",
    "step_table",
]
