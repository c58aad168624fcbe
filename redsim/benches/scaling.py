"""`redsim bench scaling`: how cost grows with the mesh (the paper's supplement B.3).

One elastic shape, the ``cantilever`` beam (neo-Hookean, clamped at one end, under gravity),
meshed with ``cells_x = 5 k`` and ``cells_yz = k`` cells for each k of :data:`SIZES`, and the same
5 x 128 MLP (the cantilever preset's d and σ, λ; the MLP alone, not its anchored map, but with f(0) at rest as
the anchored map has it: :func:`rest_at_origin`). Per size,
each in its own process (so peak memory is that size's):

- fit time per 1000 steps: the median of ``fit_steps`` timed steps of the real fit loop (after
  ``warmup``) times 1000;
- forward pass: f(z) for B = 1 and B = 32 (float32, no grad), median of 20;
- cubature: a :class:`redsim.cubature.Cubature` of the briefly fitted map with at most
  ``cubature_elements`` elastic elements, from ``cubature_samples`` states z ~ N(0, I) (no rollouts:
  they would need the all-element step); its build time and held-out force error;
- latent energy: one evaluation of E(z) and dE/dz at B = 1 (the work of a solver iteration), with
  all elements (the runtime's map energy) and with the cubature, in ``dtype``, median of 20;
- latent step: the runtime (:class:`redsim.runtime.LatentStepper` in ``dtype``, float64 by default, at its default
  tolerance, 1e-9 in float64) on that map from z = 0 under gravity and a sideways tip load of ± the beam's weight,
  its sign flipped every step, with all elements and with the cubature, median of ``latent_steps`` steps, the mean
  solver iterations per step and (the JSON only: ``latent_calls``, ``cubature_calls``) the mean value-and-gradient
  calls, at B = 1 and at B = ``batch`` (the all-element step at B = ``batch`` only up to ``batch_max_n`` free DOFs:
  past that one such step takes minutes). The map is stepped with f(0) at the seed (:func:`rest_at_origin`), so the
  stepper's force scale is the inertia term's at every size and the steps feel the loads
  (``acceleration_resolution`` in the row [m/s^2]). The briefly fitted map is stiff along z: a step's response is
  small and near-linear, and its predicted start (a Newton step of the carried gradient and model, as in the envs)
  mostly meets the tolerance, so the iterations after it read 0-1 in float64. In float32 the tolerance is below what
  round-off lets the cubature step reach on this map: at k = 6 and 8 most of its steps run to ``max_iter``
  (``unconverged``);
- full-space step: float64 Newton implicit Euler (tol 1e-6) from the seed under gravity, median of
  ``full_steps`` steps, up to ``full_max_n`` free DOFs;
- peak resident memory of the process [MiB];
- ``unconverged``: per step curve measured, [timed steps (states at B = ``batch``) that did not converge, timed
  steps (states)]: their times are in the medians, so a curve with any is shown beside them, not dropped.

A value that was not measured (above its size limit) is None, shown as "not run"; a measured one that is not finite
reads nan (or inf). Each curve's growth exponent is the least-squares slope of log(value) against log(n) over the
sizes where it was measured and finite (–: fewer than 2).
"""

from __future__ import annotations

import math
import resource
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from redsim import processes
from redsim.devices import DTYPES
from redsim.subspace import write_atomically

SIZES = (4, 6, 8, 11)
"""Cross-section cells k of the measured meshes (n = 1500, 4410, 9720, 23760)."""
CURVES = (
    "fit_s_per_1000",
    "forward_b1_ms",
    "forward_b32_ms",
    "latent_eval_ms",
    "cubature_eval_ms",
    "latent_step_ms",
    "cubature_step_ms",
    "latent_batch_ms",
    "cubature_batch_ms",
    "full_step_ms",
    "cubature_build_s",
    "peak_mib",
)
"""The measured columns whose growth exponents are fitted."""
DT = 0.02
DTYPE = "float64"
"""The latent steps' default dtype: float32's tolerance is below what its round-off lets the cubature step reach on
the briefly fitted map (k = 8: all 6 timed steps at max_iter 50), so it would time max_iter, not a solve."""


def _step_times(stepper: Any, batch: int, steps: int, load: float) -> tuple[float, float, int, float]:
    """Median wall time [ms] of ``steps`` steps (after one untimed) from z = 0, the mean solver iterations per step,
    the states of the timed steps that did not converge (of ``steps * batch``) and the mean value-and-gradient calls
    per timed step (:attr:`redsim.runtime.LatentStepper.evaluations`).

    The tip is pushed sideways (+z) by ``load`` [N] and pulled back by it on alternate steps. The warm model and the
    carried energy are passed on as the envs pass them, so a step starts from the model's Newton step from z_t and
    its first energy evaluation is there; the iterations are those after it (0: that start met the tolerance).
    """
    z = torch.zeros(batch, stepper.latent_dim, dtype=stepper.dtype)
    push = torch.zeros(batch, 1, 3, dtype=stepper.dtype)
    push[..., 2] = load
    z_prev, model, carry, times, iterations, unconverged = z.clone(), None, None, [], [], 0
    calls = 0
    for step in range(steps + 1):
        calls -= stepper.evaluations.calls if step else 0
        start = time.perf_counter()
        z_next, stats = stepper.step(z, z_prev, push if step % 2 == 0 else -push, warm=model, carry=carry)
        times.append(time.perf_counter() - start)
        iterations.append(float(stats.iterations.float().mean()))
        unconverged += int((~stats.converged).sum()) if step else 0
        calls += stepper.evaluations.calls if step else 0
        model, carry, z_prev, z = stats.model, stats.carry, z, z_next
    return 1e3 * statistics.median(times[1:]), statistics.fmean(iterations[1:]), unconverged, calls / steps


def rest_at_origin(subspace: torch.nn.Module, scene: Any) -> torch.nn.Module:
    """``subspace`` (a :class:`redsim.subspace.SubspaceMap`, changed in place and returned) with its output bias shifted
    so that f(0) is the scene's seed, as the preset's anchored map has it (its b is the rest state).

    The briefly fitted MLP's f(0) is far from rest: its elastic forces there set the runtime's force scale F_b, and
    with it a float32 tolerance (:attr:`redsim.runtime.LatentStepper.acceleration_resolution`) of 3.8 m/s^2 at
    n = 1500 up to 2.7e4 m/s^2 at n = 82620 (float64, whose tolerance is 1000 times smaller: 27 m/s^2 there), so that
    the timed steps did not feel the tip load (0 iterations at all but one size). At rest, F_b is the inertia term's
    and gravity's: 2.8e-3 m/s^2 in float32 at k = 1, 2 and 6 alike (float64: 2.8e-6). An evaluation costs the same
    (one bias changed).
    """
    with torch.no_grad():
        zero = torch.zeros(1, subspace.latent_dim, dtype=subspace.mlp[-1].bias.dtype)
        subspace.mlp[-1].bias -= subspace(zero)[0] - scene.q_seed.to(zero.dtype)
    return subspace


def _eval_ms(energy: Any, latent_dim: int, dtype: torch.dtype, repeats: int = 20) -> float:
    """Median wall time [ms] of one latent energy and its gradient dE/dz at B = 1 (z ~ N(0, I), seeded)."""
    z = torch.randn(1, latent_dim, generator=torch.Generator().manual_seed(0), dtype=dtype).requires_grad_(True)
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        value, _ = energy.energy(z, None)
        torch.autograd.grad(value.sum(), z)
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times[1:])


def measure(
    cells: int,
    *,
    fit_steps: int = 5,
    warmup: int = 2,
    latent_steps: int = 5,
    full_steps: int = 1,
    full_max_n: int | None = None,
    cubature_elements: int = 200,
    cubature_samples: int = 64,
    batch: int = 64,
    batch_max_n: int | None = None,
    dtype: str = DTYPE,
) -> dict[str, Any]:
    """One row (module doc) for cross-section cells k = ``cells``, in this process.

    ``full_max_n`` / ``batch_max_n``: the largest n at which the full-space step / the all-element
    step at B = ``batch`` is run (None: every n); ``batch`` 0 skips the batched steps. ``dtype``: the name
    (:data:`redsim.devices.DTYPES`) of the dtype of the latent energy evaluations and steps.

    Raises:
        ValueError: an unknown ``dtype``.
    """
    if dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {', '.join(DTYPES)}, got {dtype!r}")
    solve_dtype = DTYPES[dtype]
    from redsim import scenes
    from redsim.cubature import CubatureConfig, CubatureEnergy, build_cubature
    from redsim.cubature.fit import default_load_scale
    from redsim.integrators import FullSpace, ImplicitEuler
    from redsim.integrators.implicit_euler import quiet_steps
    from redsim.runtime import LatentStepper
    from redsim.trainers import FitConfig, fit_subspace
    from redsim.trainers.fit import quiet_low_stretch
    from redsim.trainers.presets import preset

    scene = scenes.build("cantilever", cells_x=5 * cells, cells_yz=cells)
    n = scene.free_dof_count
    config = FitConfig(
        **{**preset("cantilever"), "hidden_width": 128, "hidden_layers": 5, "anchor_map": "none"},  # the MLP alone
        steps=warmup + fit_steps,
        checkpoint_every=0,
    )
    stamps: list[float] = []
    with quiet_low_stretch():  # a short fit for its step time and cost; its spread is not what the study measures
        result = fit_subspace(
            scene, config, progress=False, callbacks=[lambda _s, _t: stamps.append(time.perf_counter())]
        )
    fit_step = statistics.median(b - a for a, b in zip(stamps[warmup - 1 : -1], stamps[warmup:], strict=True))
    f = rest_at_origin(result.subspace, scene)
    row: dict[str, Any] = {"cells": cells, "n": n, "d": config.latent_dim}
    row["fit_s_per_1000"] = 1000.0 * fit_step
    for size in (1, 32):
        z = torch.randn(size, config.latent_dim)
        times = []
        with torch.no_grad():
            f(z)
            for _ in range(20):
                start = time.perf_counter()
                f(z)
                times.append(time.perf_counter() - start)
        row[f"forward_b{size}_ms"] = 1e3 * statistics.median(times)
    start = time.perf_counter()
    cubature = build_cubature(
        scene, f, CubatureConfig(elements=cubature_elements, samples=cubature_samples, episodes=0, seed=0)
    )
    row["cubature_build_s"] = time.perf_counter() - start
    row["cubature_kept"] = cubature.kept
    row["cubature_force_error"] = cubature.summary["held_out_force_error"]
    all_elements = LatentStepper(scene, f, DT, dtype=solve_dtype)
    cubature_energy = CubatureEnergy(scene, f, cubature, dtype=solve_dtype)
    reduced = LatentStepper(scene, f, DT, dtype=solve_dtype, energy=cubature_energy)
    row["dtype"] = dtype
    row["acceleration_resolution"] = all_elements.acceleration_resolution
    row["latent_eval_ms"] = _eval_ms(all_elements.energy, config.latent_dim, solve_dtype)
    row["cubature_eval_ms"] = _eval_ms(reduced.energy, config.latent_dim, solve_dtype)
    load = default_load_scale(scene)
    unconverged = {}
    row["latent_step_ms"], row["latent_iterations"], unconverged["latent"], row["latent_calls"] = _step_times(
        all_elements, 1, latent_steps, load
    )
    row["cubature_step_ms"], row["cubature_iterations"], unconverged["cubature"], row["cubature_calls"] = _step_times(
        reduced, 1, latent_steps, load
    )
    row["batch"] = batch
    row["latent_batch_ms"] = row["cubature_batch_ms"] = None
    if batch:
        row["cubature_batch_ms"], _, unconverged["cubature_batch"], _ = _step_times(reduced, batch, latent_steps, load)
        if batch_max_n is None or n <= batch_max_n:
            row["latent_batch_ms"], _, unconverged["latent_batch"], _ = _step_times(
                all_elements, batch, latent_steps, load
            )
    row["full_step_ms"] = row["full_iterations"] = None
    if full_max_n is None or n <= full_max_n:
        integrator = ImplicitEuler(FullSpace(scene.to(dtype=torch.float64)), DT, tol=1e-6)
        state = integrator.initial_state()
        times, iterations, unconverged["full"] = [], [], 0
        with quiet_steps():  # counted in the row
            for _ in range(full_steps):
                start = time.perf_counter()
                state, info = integrator.step(state)
                times.append(time.perf_counter() - start)
                iterations.append(info.iterations)
                unconverged["full"] += not info.converged
        row["full_step_ms"] = 1e3 * statistics.median(times)
        row["full_iterations"] = statistics.fmean(iterations)
    timed = {"latent": latent_steps, "cubature": latent_steps, "full": full_steps}
    timed |= {"latent_batch": latent_steps * batch, "cubature_batch": latent_steps * batch}
    row["unconverged"] = {key: [count, timed[key]] for key, count in unconverged.items()}
    row["peak_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return row


class SizeFailed(RuntimeError):
    """A size's process died without a result (a signal or a hard exit; the kernel's out-of-memory killer is the
    usual one at a large mesh) or raised; ``result`` holds the sizes measured before it (rows and exponents)."""

    def __init__(self, message: str, result: dict[str, Any]) -> None:
        super().__init__(message)
        self.result = result


def _child(args: tuple[int, dict[str, Any], int]) -> dict[str, Any]:
    cells, options, threads = args
    torch.set_num_threads(threads)
    return measure(cells, **options)


def bench_scaling(
    sizes: tuple[int, ...] = SIZES,
    *,
    threads: int = 1,
    on_row: Callable[[dict[str, Any]], None] | None = None,
    **options: Any,
) -> dict[str, Any]:
    """Rows of :func:`measure` for each size, each in a fresh process, and the growth exponents.

    ``on_row`` gets the result so far (rows and exponents) after each size, so a long run's
    finished sizes can be written out before the next one starts.

    Raises:
        ValueError: a size below 1.
        SizeFailed: a size's process died without a result or raised (the sizes before it are in its ``result``,
            the exception it raised is its ``__cause__``).
    """
    if any(int(k) != k or k < 1 for k in sizes):
        raise ValueError(f"sizes must be integers >= 1, got {sizes}")
    rows: list[dict[str, Any]] = []
    for cells in sizes:
        try:
            rows.append(processes.alone(_child, (int(cells), options, threads)))
        except ChildProcessError as err:
            done = {"rows": rows, "exponents": growth_exponents(rows)}
            raise SizeFailed(
                f"size k = {cells}: {err}; killed for memory, most likely (each size's peak is its own process's)",
                done,
            ) from err
        except Exception as err:  # raised in the size's process: the sizes before it are kept all the same
            done = {"rows": rows, "exponents": growth_exponents(rows)}
            raise SizeFailed(f"size k = {cells}: {type(err).__name__}: {err}", done) from err
        if on_row is not None:
            on_row({"rows": rows, "exponents": growth_exponents(rows)})
    return {"rows": rows, "exponents": growth_exponents(rows)}


def _points(rows: list[dict[str, Any]], key: str) -> list[tuple[int, float]]:
    """(n, value) of the rows where ``key`` was measured (a finite value > 0; None is "not run")."""
    out = []
    for row in rows:
        value = row.get(key)
        if isinstance(value, (int, float)) and math.isfinite(value) and value > 0:
            out.append((row["n"], float(value)))
    return out


def growth_exponents(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Slope of log(value) against log(n) per curve of :data:`CURVES` (NaN with fewer than 2 measured points)."""
    out = {}
    for key in CURVES:
        points = _points(rows, key)
        if len(points) < 2:
            out[key] = math.nan
            continue
        n, value = np.log(np.array(points, dtype=float)).T
        out[key] = float(np.polyfit(n, value, 1)[0])
    return out


HEADERS = {
    "n": "n",
    "fit_s_per_1000": "fit s / 1000 steps",
    "forward_b1_ms": "forward B=1 ms",
    "forward_b32_ms": "forward B=32 ms",
    "latent_eval_ms": "latent E+grad ms",
    "cubature_eval_ms": "cubature E+grad ms",
    "latent_step_ms": "latent step ms",
    "latent_iterations": "latent its",
    "cubature_step_ms": "cubature step ms",
    "cubature_iterations": "cubature its",
    "latent_batch_ms": "latent step B=64 ms",
    "cubature_batch_ms": "cubature step B=64 ms",
    "full_step_ms": "full step ms",
    "full_iterations": "full its",
    "cubature_build_s": "cubature build s",
    "cubature_kept": "cubature elements",
    "cubature_force_error": "cubature force error",
    "peak_mib": "peak MiB",
    "unconverged": "unconverged steps",
}
"""Table columns (the B=64 headers name the default batch; the row's ``batch`` is the one run)."""


def _batch(result: dict[str, Any]) -> int:
    """The batch size the rows ran (64 where none ran one)."""
    return next((r["batch"] for r in result["rows"] if r.get("batch")), 64)


def _header(key: str, result: dict[str, Any]) -> str:
    """The column name of ``key``, with the batch size the rows ran."""
    return HEADERS[key].replace("B=64", f"B={_batch(result)}")


def markdown_table(result: dict[str, Any]) -> str:
    """The rows and, last, the growth exponents, as a markdown table."""
    keys = list(HEADERS)
    names = [_header(k, result) for k in keys]
    batch = _batch(result)
    lines = ["| " + " | ".join(names) + " |", "|" + "---|" * len(keys)]

    def cell(value: Any) -> str:
        if value is None:
            return "not run"
        if isinstance(value, dict):  # unconverged: the curves with any
            bad = [f"{k.replace('_batch', f' B={batch}')} {n}/{of}" for k, (n, of) in value.items() if n]
            return ", ".join(bad) or "0"
        if isinstance(value, float):
            return f"{value:.3g}"  # a measured value that is not finite reads nan (inf), not hidden
        return str(value)

    def exponent(key: str) -> str:
        """The curve's growth exponent; – where fewer than 2 sizes measured it (nothing to fit)."""
        value = exponents.get(key, math.nan)
        return "–" if not math.isfinite(value) else f"{value:.3g}"

    for row in result["rows"]:
        lines.append("| " + " | ".join(cell(row.get(k)) for k in keys) + " |")
    exponents = result["exponents"]
    lines.append("| growth exponent | " + " | ".join(exponent(k) if k in CURVES else "" for k in keys[1:]) + " |")
    return "\n".join(lines)


def scaling_png(result: dict[str, Any], path: Path, machine: str) -> None:
    """Log-log plot of every curve against n (cubature dashed), with its exponent in the legend."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    palette = matplotlib.colormaps["tab20"]
    for i, key in enumerate(CURVES):
        points = _points(result["rows"], key)
        if not points:
            continue
        n, value = zip(*points, strict=True)
        style = "--" if key.startswith("cubature") else "-"
        label = f"{_header(key, result)} (n^{result['exponents'][key]:.2f})"
        ax.plot(n, value, style, marker="o", color=palette(2 * i % 20 + (2 * i >= 20)), label=label)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("free DOFs n")
    ax.set_ylabel("time [ms; s for fit and cubature build] / memory [MiB]")
    ax.set_title("cantilever beam, 5 x 128 MLP", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6, loc="upper left", ncol=2)
    fig.suptitle(machine, fontsize=7)
    fig.tight_layout()
    write_atomically(Path(path), lambda tmp: fig.savefig(tmp, format="png", dpi=120))  # Ctrl-C: no half a PNG


__all__ = [
    "CURVES",
    "DTYPE",
    "SIZES",
    "SizeFailed",
    "bench_scaling",
    "growth_exponents",
    "markdown_table",
    "measure",
    "rest_at_origin",
    "scaling_png",
]
