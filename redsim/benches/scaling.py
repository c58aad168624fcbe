"""`redsim bench scaling`: how cost grows with the mesh (the paper's supplement B.3).

One elastic shape, the ``cantilever`` beam (neo-Hookean, clamped at one end, under gravity),
meshed with ``cells_x = 5 k`` and ``cells_yz = k`` cells for each k of :data:`SIZES`, and the same
5 x 128 MLP (the cantilever preset's d and σ, λ). Per size, each in its own process (so peak
memory is that size's):

- fit time per 1000 steps: the median of ``fit_steps`` timed steps of the real fit loop (after
  ``warmup``) times 1000;
- forward pass: f(z) for B = 1 and B = 32 (float32, no grad), median of 20;
- latent step: the runtime (:class:`redsim.runtime.LatentStepper`, float32, B = 1) on the briefly
  fitted map from z = 0 under gravity, median of ``latent_steps`` steps (the iteration count too);
- full-space step: float64 Newton implicit Euler (tol 1e-6) from the seed under gravity, median of
  ``full_steps`` steps;
- peak resident memory of the process [MiB].

Each curve's growth exponent is the least-squares slope of log(time) against log(n).
"""

from __future__ import annotations

import math
import multiprocessing
import resource
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

SIZES = (4, 6, 8, 11)
"""Cross-section cells k of the measured meshes (n = 1500, 4410, 9720, 23760)."""
CURVES = ("fit_s_per_1000", "forward_b1_ms", "forward_b32_ms", "latent_step_ms", "full_step_ms", "peak_mib")
"""The measured columns whose growth exponents are fitted."""
DT = 0.02


def measure(
    cells: int, *, fit_steps: int = 5, warmup: int = 2, latent_steps: int = 5, full_steps: int = 1, full: bool = True
) -> dict[str, Any]:
    """One row (module doc) for cross-section cells k = ``cells``, in this process."""
    from redsim import scenes
    from redsim.integrators import FullSpace, ImplicitEuler
    from redsim.runtime import LatentStepper
    from redsim.trainers import FitConfig, fit_subspace
    from redsim.trainers.presets import preset

    scene = scenes.build("cantilever", cells_x=5 * cells, cells_yz=cells)
    config = FitConfig(
        **{**preset("cantilever"), "hidden_width": 128, "hidden_layers": 5},
        steps=warmup + fit_steps,
        checkpoint_every=0,
    )
    stamps: list[float] = []
    result = fit_subspace(scene, config, progress=False, callbacks=[lambda _s, _t: stamps.append(time.perf_counter())])
    fit_step = statistics.median(b - a for a, b in zip(stamps[warmup - 1 : -1], stamps[warmup:], strict=True))
    f = result.subspace
    row: dict[str, Any] = {"cells": cells, "n": scene.free_dof_count, "d": config.latent_dim}
    row["fit_s_per_1000"] = 1000.0 * fit_step
    for batch in (1, 32):
        z = torch.randn(batch, config.latent_dim)
        times = []
        with torch.no_grad():
            f(z)
            for _ in range(20):
                start = time.perf_counter()
                f(z)
                times.append(time.perf_counter() - start)
        row[f"forward_b{batch}_ms"] = 1e3 * statistics.median(times)
    stepper = LatentStepper(scene, f, DT)
    z = torch.zeros(1, config.latent_dim)
    z_prev = z.clone()
    times, iterations, model = [], [], None
    for _ in range(latent_steps + 1):
        start = time.perf_counter()
        z_next, stats = stepper.step(z, z_prev, warm=model)
        model = stats.model
        times.append(time.perf_counter() - start)
        iterations.append(float(stats.iterations.float().mean()))
        z_prev, z = z, z_next
    row["latent_step_ms"] = 1e3 * statistics.median(times[1:])
    row["latent_iterations"] = statistics.fmean(iterations[1:])
    row["full_step_ms"] = math.nan
    row["full_iterations"] = math.nan
    if full:
        integrator = ImplicitEuler(FullSpace(scene.to(dtype=torch.float64)), DT, tol=1e-6)
        state = integrator.initial_state()
        times, iterations = [], []
        for _ in range(full_steps):
            start = time.perf_counter()
            state, info = integrator.step(state)
            times.append(time.perf_counter() - start)
            iterations.append(info.iterations)
        row["full_step_ms"] = 1e3 * statistics.median(times)
        row["full_iterations"] = statistics.fmean(iterations)
    row["peak_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return row


def _child(args: tuple[int, dict[str, Any], int]) -> dict[str, Any]:
    cells, options, threads = args
    torch.set_num_threads(threads)
    return measure(cells, **options)


def bench_scaling(sizes: tuple[int, ...] = SIZES, *, threads: int = 1, **options: Any) -> dict[str, Any]:
    """Rows of :func:`measure` for each size, each in a fresh process, and the growth exponents.

    Raises:
        ValueError: a size below 1.
    """
    if any(int(k) != k or k < 1 for k in sizes):
        raise ValueError(f"sizes must be integers >= 1, got {sizes}")
    context = multiprocessing.get_context("spawn")
    rows = []
    for cells in sizes:
        with context.Pool(1) as pool:
            rows.append(pool.map(_child, [(int(cells), options, threads)])[0])
    return {"rows": rows, "exponents": growth_exponents(rows)}


def growth_exponents(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Slope of log(value) against log(n) per curve of :data:`CURVES` (NaN with fewer than 2 finite points)."""
    out = {}
    for key in CURVES:
        points = [(r["n"], r[key]) for r in rows if math.isfinite(r.get(key, math.nan)) and r[key] > 0]
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
    "latent_step_ms": "latent step ms",
    "latent_iterations": "latent its",
    "full_step_ms": "full step ms",
    "full_iterations": "full its",
    "peak_mib": "peak MiB",
}


def markdown_table(result: dict[str, Any]) -> str:
    """The rows and, last, the growth exponents, as a markdown table."""
    keys = list(HEADERS)
    lines = ["| " + " | ".join(HEADERS[k] for k in keys) + " |", "|" + "---|" * len(keys)]

    def cell(value: Any) -> str:
        if isinstance(value, float):
            return "–" if not math.isfinite(value) else f"{value:.3g}"
        return str(value)

    for row in result["rows"]:
        lines.append("| " + " | ".join(cell(row[k]) for k in keys) + " |")
    exponents = result["exponents"]
    lines.append(
        "| growth exponent | "
        + " | ".join(cell(exponents.get(k, math.nan)) if k in CURVES else "" for k in keys[1:])
        + " |"
    )
    return "\n".join(lines)


def scaling_png(result: dict[str, Any], path: Path, machine: str) -> None:
    """Log-log plot of every curve against n, with its exponent in the legend."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for key in CURVES:
        points = [(r["n"], r[key]) for r in result["rows"] if math.isfinite(r[key])]
        if not points:
            continue
        n, value = zip(*points, strict=True)
        ax.plot(n, value, marker="o", label=f"{HEADERS[key]} (n^{result['exponents'][key]:.2f})")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("free DOFs n")
    ax.set_ylabel("time [ms, s for the fit] / memory [MiB]")
    ax.set_title("cantilever beam, 5 x 128 MLP", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.suptitle(machine, fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


__all__ = ["CURVES", "SIZES", "bench_scaling", "growth_exponents", "markdown_table", "measure", "scaling_png"]
