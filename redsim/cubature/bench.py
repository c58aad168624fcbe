"""``redsim bench cubature``: a cubature energy against the all-element latent step, side by side in one run.

Per scene: elements kept, held-out reduced-force error, trajectory deviation from the all-element
step over seeded load sequences, contact penetration of both, and step time at each batch size.
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from typing import Any

import torch
from torch import Tensor, nn

from redsim.cubature.energy import Cubature, CubatureEnergy
from redsim.cubature.fit import CubatureConfig, default_load_scale, error_measures, split_states, training_states
from redsim.effects.penalty import SDFContact
from redsim.runtime import Evaluations, LatentStepper
from redsim.scene import Scene

ACCURACY_STATES = 8
"""Rollouts (seeded load sequences) whose median deviation the bench reports by default, whatever its timing
batches."""
WARMUP_STEPS = 30
"""All-element steps under the seeded loads before the timed ones (from rest a cloth's steps take fewer calls than
once it swings: hanging_sheet 12 against 19 at B=64, docs/cubature.md, "Stop 39")."""


def _loads(scene: Scene, steps: int, batch: int, hold: int, scale: float, seed: int) -> Tensor:
    """Seeded piecewise-constant loads [steps, B, H, D]: N(0, scale^2) per component, redrawn every ``hold`` steps."""
    generator = torch.Generator().manual_seed(seed)
    segments = -(-steps // hold)
    draws = scale * torch.randn(
        segments, batch, len(scene.handles), scene.dim, generator=generator, dtype=torch.float32
    )
    return draws.repeat_interleave(hold, 0)[:steps]


def _state_loads(scene: Scene, steps: int, count: int, hold: int, scale: float, seed: int) -> Tensor:
    """The accuracy rollouts' loads [steps, count, H, D], nested: the first :data:`ACCURACY_STATES` are the default
    bench's whatever ``count`` (fewer states take the first ones, more add states drawn from seed + 2)."""
    loads = _loads(scene, steps, ACCURACY_STATES, hold, scale, seed)
    if count <= ACCURACY_STATES:
        return loads[:, :count]
    return torch.cat([loads, _loads(scene, steps, count - ACCURACY_STATES, hold, scale, seed + 2)], 1)


FLAGS = ("diverged", "unconverged", "out_of_range")
"""The step flags the accuracy rollouts count per energy (:class:`redsim.runtime.StepStats`)."""


def _rollout(
    stepper: LatentStepper,
    z0: Tensor,
    loads: Tensor | None,
    steps: int,
    z_prev: Tensor | None = None,
    flags: dict[str, int] | None = None,
) -> tuple[Tensor, list[float]]:
    """Latents [steps + 1, B, d] of a rollout from z0 (at rest, or moving from ``z_prev``) and each step's wall time
    [s]; ``flags`` (:data:`FLAGS`), if given, gets each state-step the stepper flagged added."""
    z, z_prev, out, times, model, carry = z0, z0 if z_prev is None else z_prev, [z0], [], None, None
    for t in range(steps):
        start = time.perf_counter()
        z_next, stats = stepper.step(z, z_prev, None if loads is None else loads[t], warm=model, carry=carry)
        model, carry = stats.model, stats.carry
        times.append(time.perf_counter() - start)
        if flags is not None:
            for key, flagged in zip(FLAGS, (stats.diverged, ~stats.converged, stats.out_of_range), strict=True):
                flags[key] += int(flagged.sum())
        z_prev, z = z, z_next
        out.append(z)
    return torch.stack(out), times


def penetration(scene: Scene, q: Tensor) -> float:
    """Deepest contact penetration [m] (below the margin) over configurations q [S, n] (0 without contact)."""
    x = scene.full_positions(q)
    depth = 0.0
    for effect in scene.effects:
        if isinstance(effect, SDFContact):
            depth = max(depth, float(effect.penetration(x).max()))
    return depth


def held_out_errors(
    scene: Scene,
    subspace: nn.Module,
    cubature: Cubature,
    config: CubatureConfig | None = None,
    *,
    every_state: bool = False,
    seed: int | None = None,
) -> dict[str, Any]:
    """The cubature's errors on its build's held-out states, in float64, each a relative error
    (:func:`redsim.cubature.fit.error_measures`).

    The states are those its build held out (:func:`~redsim.cubature.fit.training_states` and
    :func:`~redsim.cubature.fit.split_states` of ``cubature.config``, which are seeded; a build made before whole
    rollouts were held out, 2026-12-07, split otherwise), or those ``config`` draws and holds out (another seed: states
    of the same distribution the build never saw), all of them with ``every_state``. ``seed``: every state the
    recorded config draws under that seed instead (``every_state`` implied). F is J^T grad E of the all-element
    energy (every effect but the load term, :class:`redsim.runtime.MapEnergy`), E - E(0) its energy (E(0): z = 0, the
    default condition), the residuals the cubature energy's less those. Returns ``error_measures``' keys against the
    total (``force_error`` is the build's ``held_out_force_error`` on its own states), ``subsampled_force_error``: the
    plain force error against the reduced force of the subsampled effects alone (the exact ones, linear and kept whole,
    left out of F; the residual is theirs alone), ``states`` and ``seed``.

    Raises:
        ValueError: a cubature without a recorded config, and no ``config`` given.
    """
    from redsim.runtime import MapEnergy

    if config is None:
        if not cubature.config:
            raise ValueError("the cubature records no config (built in Python?): give the states' CubatureConfig")
        config = CubatureConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in cubature.config.items()})
    if seed is not None:
        config, every_state = dataclasses.replace(config, seed=seed), True
    z, cond, _, episode = training_states(scene, subspace, config)
    test = torch.arange(z.shape[0]) if every_state else split_states(episode, config)[0]
    z, cond = z[test], None if cond is None else cond[test]
    exact = MapEnergy(scene, subspace, dtype=torch.float64)
    approx = CubatureEnergy(scene, subspace, cubature, dtype=torch.float64)
    z0 = torch.zeros(1, z.shape[1], dtype=torch.float64)
    c0 = None if scene.condition_space is None else scene.condition_space.default.to(torch.float64)[None]
    zs = z.clone().requires_grad_(True)
    with torch.enable_grad():
        q = exact.positions(zs, cond)
        x = exact.scene.full_positions(q)
        energies = {effect.name: effect.energy(x, cond) for effect in exact.effects}
        forces = {name: torch.autograd.grad(e.sum(), zs, retain_graph=True)[0] for name, e in energies.items()}
        cub_energy = approx.energy(zs, cond)[0]
        (cub_force,) = torch.autograd.grad(cub_energy.sum(), zs)
    with torch.no_grad():
        energy = sum(energies.values()).detach() - exact.energy(z0, c0)[0]
        cub_delta = cub_energy.detach() - approx.energy(z0, c0)[0]
    force = sum(forces.values())
    residual = cub_force - force
    out = error_measures(residual, force, cub_delta - energy, energy)
    subsampled = [r.name for r in cubature.rules if r.mode == "cubature"]
    part = sum((forces[name] for name in subsampled), torch.zeros_like(force))
    out["subsampled_force_error"] = float(
        torch.linalg.vector_norm(residual) / torch.linalg.vector_norm(part).clamp_min(1e-300)
    )
    return out | {"states": int(z.shape[0]), "seed": int(config.seed)}


def bench_cubature(
    scene: Scene,
    subspace: nn.Module,
    cubature: Cubature,
    *,
    dt: float = 0.02,
    steps: int = 100,
    batches: tuple[int, ...] = (1, 64),
    timed_steps: int = 10,
    warmup: int = WARMUP_STEPS,
    hold: int = 10,
    load_scale: float | None = None,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
    compiled: bool = False,
    states: int = ACCURACY_STATES,
    held_out: bool = False,
    held_out_seed: int | None = None,
) -> dict[str, Any]:
    """Compare the cubature energy with the all-element step (``dtype``, CPU, the stepper's defaults).

    Accuracy: ``states`` states (:func:`_state_loads`: a larger count keeps the default's first ones and adds others;
    the median of 8 can move by a point when one state moves) from the rest latent under the same seeded loads,
    ``steps`` steps
    with each energy; the deviation of a state is max_t |q_cub(t) - q_all(t)|_M / max_t |q_all(t) - q_all(0)|_M
    (the median over states is reported; each state's, its largest motion max_t |q_all(t) - q_all(0)|_M and the largest
    |z| of the all-element rollouts too), the penetration the deepest contact over all states and steps.
    Time: the median step [s] over ``timed_steps`` steps per batch size, the two energies interleaved, from the
    state ``warmup`` all-element steps under seeded loads reach (a moving shape: steps from rest take fewer
    iterations), with each energy's value-and-gradient calls per step of its timed rollouts (their untimed first
    steps included). ``compiled``: the cubature step with ``compile="dynamic"`` timed beside them
    (``cubature_compiled_s``; a few steps at each batch size before, which compile its graphs, untimed).
    ``flags``: per energy (``all``, ``cubature``), the accuracy rollouts' state-steps flagged diverged (rejected: the
    state stays where it was), unconverged and out of the map's range (:data:`FLAGS`), of ``states * steps``.
    ``held_out_force_error`` and ``held_out_plain_force_error`` are the build's (None where its summary has none);
    ``held_out``: :func:`held_out_errors` of the states its recorded config holds out, recomputed (``held_out_errors``;
    it replays the build's rollouts); ``held_out_seed``: instead every state its recorded config draws under that seed
    (states no build saw; the builds before 2026-12-07 trained on some of the states their config holds out).
    """
    if isinstance(warmup, bool) or not isinstance(warmup, int) or warmup < 0:
        raise ValueError(f"warmup must be an integer >= 0, got {warmup!r}")
    if isinstance(timed_steps, bool) or not isinstance(timed_steps, int) or timed_steps < 1:
        raise ValueError(f"timed_steps must be an integer >= 1, got {timed_steps!r}")
    if isinstance(states, bool) or not isinstance(states, int) or states < 1:
        raise ValueError(f"states must be an integer >= 1, got {states!r}")
    scale = default_load_scale(scene) if load_scale is None else load_scale
    all_elements = LatentStepper(scene, subspace, dt, dtype=dtype)
    energy = CubatureEnergy(scene, subspace, cubature, dtype=dtype)
    reduced = LatentStepper(scene, subspace, dt, dtype=dtype, energy=energy)
    timed_steppers = {"all": all_elements, "cubature": reduced}
    if compiled:
        timed_steppers["cubature_compiled"] = LatentStepper(
            scene, subspace, dt, dtype=dtype, energy=energy, compile="dynamic"
        )
    rest = all_elements.rest_latent()
    count = states
    loads = _state_loads(scene, steps, count, hold, scale, seed) if scene.handles else None
    flags = {"all": dict.fromkeys(FLAGS, 0), "cubature": dict.fromkeys(FLAGS, 0)}
    z_all, _ = _rollout(all_elements, rest.expand(count, -1), loads, steps, flags=flags["all"])
    z_cub, _ = _rollout(reduced, rest.expand(count, -1), loads, steps, flags=flags["cubature"])
    with torch.no_grad():
        q_all = all_elements.positions(z_all.reshape(-1, z_all.shape[-1])).reshape(steps + 1, count, -1)
        q_cub = all_elements.positions(z_cub.reshape(-1, z_cub.shape[-1])).reshape(steps + 1, count, -1)
        mass = all_elements.scene.mass_norm_sq
        gap = mass((q_cub - q_all).reshape(-1, q_all.shape[-1])).reshape(steps + 1, count).sqrt().amax(0)
        motion = mass((q_all - q_all[:1]).reshape(-1, q_all.shape[-1])).reshape(steps + 1, count).sqrt().amax(0)
        deviations = gap / motion.clamp_min(1e-30)
        deviation = deviations.median()
        scene32 = all_elements.scene
        pen_all = penetration(scene32, q_all.reshape(-1, q_all.shape[-1]))
        pen_cub = penetration(scene32, q_cub.reshape(-1, q_cub.shape[-1]))
    timing = {}
    for batch in batches:
        halves = ((timed_steps + 1) // 2 + 1, timed_steps // 2 + 1)  # each rollout's first step untimed
        batch_loads = _loads(scene, warmup + halves[0], batch, hold, scale, seed + 1) if scene.handles else None
        z0 = rest.expand(batch, -1)
        z_prev = None
        if warmup:  # both energies are timed from the same moving state
            path, _ = _rollout(all_elements, z0, None if batch_loads is None else batch_loads[:warmup], warmup)
            z0, z_prev = path[-1], path[-2]
        timed_loads = None if batch_loads is None else batch_loads[warmup:]
        if compiled:  # its graphs compile in these steps (one row, several), not in the timed ones
            _rollout(timed_steppers["cubature_compiled"], z0, timed_loads, min(halves[0], 3), z_prev)
        times = {key: [] for key in timed_steppers}
        calls = dict.fromkeys(timed_steppers, 0)
        for half in halves:  # interleaved halves, so other load on the machine hits all alike
            for key, stepper in timed_steppers.items():
                stepper.evaluations = Evaluations()
                _, t = _rollout(stepper, z0, timed_loads, half, z_prev)
                times[key].extend(t[1:])
                calls[key] += stepper.evaluations.calls
        timing[batch] = {f"{key}_s": statistics.median(t) for key, t in times.items()} | {
            f"{key}_calls_per_step": count / sum(halves) for key, count in calls.items()
        }
    return {
        "scene": scene.name,
        "dtype": str(dtype).removeprefix("torch."),
        "n": scene.free_dof_count,
        "elements": {r.name: int(r.indices.numel()) for r in cubature.rules},
        "element_counts": {r.name: r.element_count for r in cubature.rules},
        "modes": {r.name: r.mode for r in cubature.rules},
        "kept_dofs": int(energy.kept_dofs.numel()),
        "held_out_error": cubature.summary.get("held_out_error"),
        "held_out_force_error": cubature.summary.get("held_out_force_error"),
        "held_out_plain_force_error": cubature.summary.get("held_out_plain_force_error"),
        "held_out_errors": (
            held_out_errors(scene, subspace, cubature, seed=held_out_seed)
            if held_out or held_out_seed is not None
            else None
        ),
        "trajectory_deviation": float(deviation),
        "deviation_per_state": [float(v) for v in deviations],
        "motion_per_state": [float(v) for v in motion],
        "max_latent_norm": float(torch.linalg.vector_norm(z_all, dim=-1).max()),
        "steps": steps,
        "warmup_steps": warmup,
        "load_scale": scale,
        "flags": flags,
        "penetration_all_m": pen_all,
        "penetration_cubature_m": pen_cub,
        "timing": timing,
    }


def mesh_sweep(
    cells: tuple[int, ...],
    *,
    elements: int = 200,
    batches: tuple[int, ...] = (1,),
    timed_steps: int = 4,
    dt: float = 0.02,
    seed: int = 0,
    batch_max_n: int | None = None,
) -> list[dict[str, Any]]:
    """Step time of the same sheet meshed ever finer: all-element latent step vs cubature.

    For each c in ``cells``: ``hanging_sheet`` with c x c cells, a d = 8 neural map of the shipped
    architecture made near the seed state (output bias = the seed, small random output weights: not
    fitted, it measures cost, not accuracy), a cubature of ``elements`` elements per effect on 64
    sampled states, and the median step [s] of both steppers from the seed latent under a constant
    load, per batch size. The all-element step at a batch > 1 runs only up to ``batch_max_n`` free
    DOFs (None: always; past it its ``all_s`` is None): at B = 64 its first step takes minutes and
    ~6 GB at n = 50k, and it is what kept the 100k-DOF sweep from finishing.
    """
    from redsim import scenes
    from redsim.cubature.energy import build_cubature
    from redsim.subspace import SubspaceConfig, SubspaceMap

    rows = []
    for c in cells:
        scene = scenes.build("hanging_sheet", cells_x=int(c), cells_y=int(c))
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            f = SubspaceMap(SubspaceConfig(latent_dim=8, output_dim=scene.free_dof_count))
        with torch.no_grad():
            f.mlp[-1].weight.mul_(0.01)
            f.mlp[-1].bias.copy_(scene.q_seed.to(torch.float32))
        cub = build_cubature(scene, f, CubatureConfig(elements=elements, samples=64, episodes=0, seed=seed))
        all_elements = LatentStepper(scene, f, dt)
        reduced = LatentStepper(scene, f, dt, energy=CubatureEnergy(scene, f, cub))
        row: dict[str, Any] = {"cells": int(c), "n": scene.free_dof_count, "kept": cub.kept, "timing": {}}
        for batch in batches:
            z0 = torch.zeros(batch, 8)
            loads = 0.1 * torch.ones(timed_steps + 1, batch, len(scene.handles), scene.dim)
            _, t_cub = _rollout(reduced, z0, loads, timed_steps + 1)
            row["timing"][batch] = {"all_s": None, "cubature_s": statistics.median(t_cub[1:])}
            if batch == 1 or batch_max_n is None or scene.free_dof_count <= batch_max_n:
                _, t_all = _rollout(all_elements, z0, loads, timed_steps + 1)
                row["timing"][batch]["all_s"] = statistics.median(t_all[1:])
        rows.append(row)
    return rows


__all__ = ["FLAGS", "bench_cubature", "held_out_errors", "mesh_sweep", "penetration"]
