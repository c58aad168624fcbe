"""Benchmarks behind `redsim bench`: wall times of scene energies and gradients.

Timings are medians over repeated calls after warm-up, measured in one process side by side;
they are reported together with :func:`machine_info` so every number names the machine it came
from.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from typing import Any

import torch

from redsim.scene import Scene


def machine_info() -> dict[str, Any]:
    """The machine a benchmark ran on: CPU, core count, load, torch version and threads, GPU if any.

    ``load_average_1min`` (None where the OS has none) tells whether other processes were competing
    for the cores while the benchmark ran.
    """
    return {
        "processor": platform.processor() or platform.machine(),
        "machine": platform.machine(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "cuda_device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }


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
        repeats = max(3, min(repeats, int(time_budget / max(last, 1e-9))))
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


def compare_subspaces(
    scene: Scene,
    neural: torch.nn.Module,
    *,
    sigma: float,
    loads_count: int = 8,
    samples: int = 256,
    seed: int = 0,
) -> dict[str, dict[str, Any]]:
    """Metrics of a fitted neural map next to linear modes and modal derivatives of the same d and σ.

    The baselines are built here (their wall time is reported as ``build_seconds``); all three
    are evaluated by :func:`redsim.metrics.evaluate_subspace` on the same seeded samples and
    loads, so the full-space reference solves are shared.

    Args:
        scene: The scene.
        neural: The fitted map (``latent_dim`` gives d).
        sigma: σ of the fit, also the scale of the baselines' modes.
        loads_count: Loads of the load-response error.
        samples: Latent samples of the energy, stretch and strain statistics.
        seed: Seed of samples and loads.

    Returns:
        ``{"neural": ..., "modes": ..., "modal_derivatives": ...}``, each an evaluate_subspace dict.
    """
    from redsim.baselines import modal_analysis, modal_derivatives
    from redsim.metrics import evaluate_subspace

    dim = int(neural.latent_dim)
    start = time.perf_counter()
    modes = modal_analysis(scene, dim, sigma=sigma)
    modes_seconds = time.perf_counter() - start
    start = time.perf_counter()
    derivatives = modal_derivatives(scene, dim, sigma=sigma, rest=modes.offset)
    derivatives_seconds = modes_seconds + time.perf_counter() - start
    out: dict[str, dict[str, Any]] = {}
    for name, subspace, seconds in (
        ("neural", neural, float(getattr(neural, "metadata", {}).get("fit_seconds", float("nan")))),
        ("modes", modes, modes_seconds),
        ("modal_derivatives", derivatives, derivatives_seconds),
    ):
        result = evaluate_subspace(scene, subspace, sigma=sigma, loads_count=loads_count, samples=samples, seed=seed)
        out[name] = {**result, "build_seconds": seconds}
    return out
