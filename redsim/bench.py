"""Benchmarks behind `redsim bench`: wall times of scene energies and gradients and of fitting steps.

Timings are medians over repeated calls after warm-up, measured in one process side by side;
they are reported together with :func:`machine_info` so every number names the machine it came
from.
"""

from __future__ import annotations

import dataclasses
import os
import platform
import statistics
import time
from typing import Any

import torch

from redsim import scenes
from redsim.scene import Scene


def machine_info() -> dict[str, Any]:
    """The machine a benchmark ran on: CPU, core count, load, torch version, kernels and threads, GPU if any.

    ``load_average_1min`` (None where the OS has none) tells whether other processes were competing
    for the cores while the benchmark ran. ``cpu_family_model`` (Linux's ``"family F model M"``, else
    None) tells apart CPUs of one model name ("AMD EPYC" of two generations), and ``cpu_capability``
    the vector kernels torch runs on it (``"AVX512"``, ``"AVX2"``, ``"DEFAULT"``; ``ATEN_CPU_CAPABILITY``
    lowers it): float32 results that amplify round-off, as a chaotic rollout's deviation does, differ
    between them.
    """
    return {
        "processor": _cpu_info("model name") or platform.processor() or platform.machine(),
        "cpu_family_model": _cpu_family_model(),
        "machine": platform.machine(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "torch": torch.__version__,
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "torch_threads": torch.get_num_threads(),
        "cuda_device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }


def _cpu_info(field: str) -> str | None:
    """The first CPU's ``field`` ("model name", "cpu family", ...) where the OS tells it (Linux's /proc/cpuinfo;
    ``platform.processor()`` is empty there)."""
    try:
        with open("/proc/cpuinfo") as info:
            values = [line.split(":", 1)[1].strip() for line in info if line.split(":", 1)[0].strip() == field]
    except OSError:
        return None
    return values[0] if values else None


def _cpu_family_model() -> str | None:
    """``"family F model M"`` of the first CPU where /proc/cpuinfo has both, else None."""
    family, model = _cpu_info("cpu family"), _cpu_info("model")
    return f"family {family} model {model}" if family and model else None


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def bench_energy(
    scene: Scene,
    batch: int,
    repeats: int,
    *,
    warmup: int = 2,
    time_budget: float | None = None,
    perturbation: float = 1e-3,
    seed: int = 0,
) -> dict[str, Any]:
    """Median wall time of ``scene.energy`` plus its gradient (backward) on a batch of states.

    The states are the seed plus Gaussian noise of standard deviation ``perturbation`` times
    the largest seed entry (at least 1), in the scene's dtype and device, with
    ``requires_grad``. Each timed call evaluates the summed energy and ``torch.autograd.grad``
    of it with respect to q.

    Args:
        scene: The scene (its dtype and device are the ones measured).
        batch: Number of states B per call.
        repeats: Timed calls; the median is reported.
        warmup: Untimed calls before timing.
        time_budget: If given, fewer repeats (at least 3) are timed when ``repeats`` calls would
            take longer than this many seconds, judged from the last warm-up call.
        perturbation: Relative size of the random perturbation of the seed.
        seed: Seed of the perturbation.

    Returns:
        ``scene``, ``n``, ``dtype``, ``device``, ``batch``, ``repeats`` (timed calls),
        ``median_s``, ``min_s``, ``max_s`` and ``per_state_s`` (median / batch).

    Raises:
        ValueError: if ``batch`` or ``repeats`` is below 1.
    """
    if batch < 1 or repeats < 1:
        raise ValueError(f"batch and repeats must be >= 1, got batch={batch}, repeats={repeats}")
    generator = torch.Generator().manual_seed(seed)
    scale = perturbation * max(1.0, float(scene.q_seed.abs().max()))
    noise = torch.randn(batch, scene.free_dof_count, generator=generator, dtype=torch.float64)
    q0 = (scene.q_seed.to(torch.float64).cpu() + scale * noise).to(device=scene.device, dtype=scene.dtype)

    def call() -> float:
        q = q0.clone().requires_grad_(True)
        _sync(scene.device)
        start = time.perf_counter()
        energy = scene.energy(q).sum()
        torch.autograd.grad(energy, q)
        _sync(scene.device)
        return time.perf_counter() - start

    last = 0.0
    for _ in range(max(1, warmup)):
        last = call()
    if time_budget is not None and last * repeats > time_budget:
        repeats = min(repeats, max(3, int(time_budget / max(last, 1e-9))))  # at least 3, never above repeats
    times = [call() for _ in range(repeats)]
    median = statistics.median(times)
    return {
        "scene": scene.name,
        "n": scene.free_dof_count,
        "dtype": str(scene.dtype).removeprefix("torch."),
        "device": str(scene.device),
        "batch": batch,
        "repeats": repeats,
        "median_s": median,
        "min_s": min(times),
        "max_s": max(times),
        "per_state_s": median / batch,
    }


FIT_VARIANTS: dict[str, dict[str, bool]] = {
    "eager": {"compile": False, "fused_adam": False},
    "fused": {"compile": False, "fused_adam": True},
    "compiled_fused": {"compile": True, "fused_adam": True},
}
"""The fitter settings `redsim bench fit` compares: FitConfig ``compile`` and ``fused_adam`` values by name."""


def bench_fit(scene: Scene, config: Any, *, steps: int = 20, warmup: int = 3, seed: int = 0) -> dict[str, Any]:
    """Median wall time of one step of :func:`redsim.trainers.fit_subspace` with ``config``.

    The real fit runs for ``warmup + steps`` steps (no checkpoints, no progress bar); a callback
    stamps the end of every step, and the timed steps are the last ``steps``. A step is the latent
    sample, the loss (MLP forward, scene energy, pair term), its backward and the Adam step.

    Args:
        scene: The scene (fitted in ``config.dtype`` on ``config.device``).
        config: A :class:`redsim.trainers.FitConfig`; ``steps`` and ``checkpoint_every`` are replaced.
        steps: Timed steps.
        warmup: Untimed steps first (at least 1; a compiled fit compiles in its first step).
        seed: Seed of the fit.

    Returns:
        ``scene``, ``n``, ``d``, ``batch``, ``dtype``, ``device``, ``compile``, ``fused_adam``,
        ``steps``, ``warmup``, ``times_s`` (each timed step), ``median_s``, ``min_s``, ``max_s``,
        ``first_step_s`` (call to end of step 1: setup, compilation and one step), ``startup_s``
        (``first_step_s - median_s``: the one-off cost, mostly compilation), ``final_loss`` and
        ``graphs_compiled_timed`` (torch.compile graphs compiled during the timed steps; 0 unless
        something recompiles per step).

    Raises:
        ValueError: if ``steps`` or ``warmup`` is below 1.
    """
    from torch._dynamo.utils import counters

    from redsim.trainers import fit_subspace
    from redsim.trainers.fit import quiet_low_stretch

    if steps < 1 or warmup < 1:
        raise ValueError(f"steps and warmup must be >= 1, got steps={steps}, warmup={warmup}")
    config = dataclasses.replace(config, steps=warmup + steps, checkpoint_every=0)
    device = torch.device(config.device)
    stamps: list[float] = []
    graphs: list[int] = []

    def stamp(_step: int, _terms: dict[str, float]) -> None:
        _sync(device)
        stamps.append(time.perf_counter())
        graphs.append(counters["stats"]["unique_graphs"])

    start = time.perf_counter()
    with quiet_low_stretch():  # a timing fit: its map is not used
        result = fit_subspace(scene, config, seed=seed, progress=False, callbacks=[stamp])
    times = [b - a for a, b in zip(stamps[warmup - 1 : -1], stamps[warmup:], strict=True)]
    median = statistics.median(times)
    return {
        "scene": scene.name,
        "n": scene.free_dof_count,
        "d": config.latent_dim,
        "batch": config.batch_size,
        "dtype": config.dtype,
        "device": config.device,
        "compile": config.compile,
        "fused_adam": config.fused_adam,
        "steps": steps,
        "warmup": warmup,
        "times_s": times,
        "median_s": median,
        "min_s": min(times),
        "max_s": max(times),
        "first_step_s": stamps[0] - start,
        "startup_s": stamps[0] - start - median,
        "final_loss": result.history[-1]["loss"],
        "graphs_compiled_timed": graphs[-1] - graphs[warmup - 1],
    }


def bench_fit_variants(
    scene: Scene,
    config: Any,
    *,
    variants: dict[str, dict[str, Any]] = FIT_VARIANTS,
    steps: int = 20,
    warmup: int = 3,
    rounds: int = 2,
    seed: int = 0,
) -> dict[str, dict[str, Any]]:
    """:func:`bench_fit` of several settings of ``config``, interleaved so that load changes hit all alike.

    Each of ``rounds`` rounds runs every variant (in reverse order every other round) for its share of
    ``steps`` (``steps // rounds``, one more in the first ``steps % rounds``; a round of none is skipped) timed
    steps after ``warmup`` untimed ones; the timed steps of all rounds are pooled. Compilation happens in the
    first round; later rounds reuse the compiled code.

    Args:
        scene: The scene.
        config: The :class:`redsim.trainers.FitConfig` the variants modify.
        variants: Name -> FitConfig fields replaced (default :data:`FIT_VARIANTS`).
        steps: Timed steps per variant, over all rounds.
        warmup: Untimed steps at the start of every round.
        rounds: Rounds (at least 1).
        seed: Seed of the fits.

    Returns:
        Name -> the first round's :func:`bench_fit` result (its ``first_step_s`` and ``startup_s``
        hold the compile) with ``steps``, ``times_s``, ``median_s``, ``min_s``, ``max_s`` and
        ``graphs_compiled_timed`` over all rounds, and ``rounds``.
    """
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    shares = [count for r in range(rounds) if (count := steps // rounds + (r < steps % rounds))]
    names = list(variants)
    results: dict[str, dict[str, Any]] = {}
    for r, share in enumerate(shares):
        for name in names if r % 2 == 0 else names[::-1]:
            run = bench_fit(scene, dataclasses.replace(config, **variants[name]), steps=share, warmup=warmup, seed=seed)
            if name not in results:
                results[name] = {**run, "rounds": len(shares)}
                continue
            pooled = results[name]
            pooled["times_s"] = pooled["times_s"] + run["times_s"]
            pooled["graphs_compiled_timed"] += run["graphs_compiled_timed"]
    for pooled in results.values():
        times = pooled["times_s"]
        pooled.update(steps=len(times), median_s=statistics.median(times), min_s=min(times), max_s=max(times))
    return results


def compare_subspaces(
    scene: Scene,
    neural: torch.nn.Module,
    *,
    sigma: float,
    loads_count: int = 8,
    response_fraction: float = 0.1,
    samples: int = 256,
    seed: int = 0,
) -> dict[str, dict[str, Any]]:
    """Metrics of a fitted neural map next to linear modes and modal derivatives of the same d and σ.

    The baselines are built at :func:`redsim.metrics.rest_state`, the full-space rest equilibrium
    the load errors are measured around (their wall time, without that cached solve, is reported
    as ``build_seconds``); all three
    are evaluated by :func:`redsim.metrics.evaluate_subspace` on the same seeded samples and
    loads, so the full-space reference solves are shared.

    Args:
        scene: The scene.
        neural: The fitted map (``latent_dim`` gives d).
        sigma: σ of the fit, also the scale of the baselines' modes.
        loads_count: Loads of the load-response error.
        response_fraction: Their size: the linear response along each handle's softest
            direction, as a fraction of the scene size (:func:`redsim.metrics.load_response_error`).
        samples: Latent samples of the energy, stretch and strain statistics.
        seed: Seed of samples and loads.

    What a scene's registry entry (:class:`redsim.scenes.SceneEntry`) declares adds checks:
    ``reference_states`` (the bistable bar's two buckled equilibria) add
    :func:`redsim.metrics.reach_error` for each method, under ``"reach"``; a ``crank`` (klann)
    adds, for maps with a periodic latent, :func:`redsim.metrics.handle_winding` of the crank
    handle about its pivot, under ``"loop"``.

    Returns:
        ``{"neural": ..., "modes": ..., "modal_derivatives": ...}``, each an evaluate_subspace dict.
    """
    from redsim.baselines import modal_analysis, modal_derivatives
    from redsim.integrators.reference import rest_or_warn
    from redsim.metrics import evaluate_subspace, handle_winding, reach_error
    from redsim.subspace import periodic_latents

    dim = int(neural.latent_dim)
    rest = rest_or_warn(scene, "the linear-mode and modal-derivative baselines")
    start = time.perf_counter()
    modes = modal_analysis(scene, dim, sigma=sigma, rest=rest)
    modes_seconds = time.perf_counter() - start
    start = time.perf_counter()
    derivatives = modal_derivatives(scene, dim, sigma=sigma, rest=modes.offset)
    derivatives_seconds = modes_seconds + time.perf_counter() - start
    declared = scenes.ENTRIES.get(scene.name)
    targets = None if declared is None else declared.compute_reference_states(scene)
    crank = None if declared is None else declared.crank
    out: dict[str, dict[str, Any]] = {}
    for name, subspace, seconds in (
        ("neural", neural, float(getattr(neural, "metadata", {}).get("fit_seconds", float("nan")))),
        ("modes", modes, modes_seconds),
        ("modal_derivatives", derivatives, derivatives_seconds),
    ):
        result = evaluate_subspace(
            scene,
            subspace,
            sigma=sigma,
            loads_count=loads_count,
            response_fraction=response_fraction,
            samples=samples,
            seed=seed,
        )
        if targets is not None:
            result["reach"] = reach_error(scene, subspace, targets, seed=seed)
        if crank is not None and periodic_latents(subspace):
            result["loop"] = handle_winding(scene, subspace, *crank, latent=periodic_latents(subspace)[0])
        out[name] = {**result, "build_seconds": seconds}
    return out
