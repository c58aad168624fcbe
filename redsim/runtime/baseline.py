"""Another redsim version's reference path, timed beside this one (`redsim bench step --baseline DIR`).

A speedup "over today's path" means over the path as it was when a target was set, not over the
reference of the same checkout (which shares every kernel made faster since). This runs
``ImplicitEuler(LatentSpace(scene, f), dt)`` of the ``redsim`` package found in a source tree
``DIR`` (e.g. ``git worktree add --detach DIR <commit>``) in a subprocess, on the scene of the same
name, that version's shipped map (its weights are compared with the map benched here), the same
loads and the same start, so that both versions run in one bench, round by round.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn


def weights_digest(module: nn.Module) -> str:
    """sha256 of a module's state dict (names, dtypes, shapes and values), to tell whether two maps are one."""
    digest = hashlib.sha256()
    for name, value in sorted(module.state_dict().items()):
        tensor = value.detach().cpu().contiguous()
        digest.update(f"{name}:{tensor.dtype}:{tuple(tensor.shape)}".encode())
        digest.update(tensor.numpy().tobytes())
    return digest.hexdigest()


_STEPS = """
import hashlib, json, sys, time
import torch
import redsim
from redsim import pretrained, scenes
from redsim.integrators import ImplicitEuler, LatentSpace

job = torch.load(sys.argv[1])
torch.set_num_threads(job["threads"])
scene = scenes.build(job["scene"])
subspace = pretrained.load(job["scene"], scene)
integrator = ImplicitEuler(LatentSpace(scene, subspace), job["dt"])
state = integrator.initial_state(job["z0"])
for load in job["loads"][: job["warmup"]]:
    state, _ = integrator.step(state, load)
state = integrator.initial_state(job["z0"])
times, iterations = [], []
for load in job["loads"]:
    start = time.perf_counter()
    state, info = integrator.step(state, load)
    times.append(time.perf_counter() - start)
    iterations.append(info.iterations)
print(json.dumps({
    "env_steps_per_s": len(times) / sum(times),
    "iterations_per_step": sum(iterations) / len(iterations),
    "redsim_file": redsim.__file__,
    "weights": weights_digest(subspace),
}))
"""


def check_source(source: Path) -> Path:
    """``source`` resolved, or ValueError if it holds no ``redsim`` package (``source/redsim/__init__.py``)."""
    source = Path(source).resolve()
    if not (source / "redsim" / "__init__.py").is_file():
        raise ValueError(f"{source} holds no redsim package (no redsim/__init__.py): give a source tree of redsim")
    return source


def run_baseline(
    source: Path,
    scene_name: str,
    subspace: nn.Module,
    dt: float,
    z0: Tensor,
    loads: Tensor,
    *,
    threads: int = 1,
    warmup: int = 0,
) -> dict[str, Any]:
    """The reference path of the redsim in ``source`` on one state from z0 [d] through ``loads`` [steps, H, D] [N],
    after its first ``warmup`` steps once untimed from the same start (a fresh process pays first-call costs).

    Returns env_steps_per_s (steps / wall time of the steps), iterations_per_step, redsim_file (the
    package that ran) and same_weights (its shipped map for ``scene_name`` is ``subspace``).

    Raises:
        ValueError: ``source`` holds no redsim package.
        RuntimeError: the subprocess failed or imported redsim from elsewhere (its stderr's end in the message).
    """
    source = check_source(source)
    with tempfile.TemporaryDirectory() as folder:
        job = Path(folder) / "job.pt"
        torch.save(
            {
                "scene": scene_name,
                "dt": float(dt),
                "z0": z0.detach().cpu().to(torch.float64),
                "loads": loads.detach().cpu().to(torch.float64),
                "threads": int(threads),
                "warmup": int(warmup),
            },
            job,
        )
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(source), os.environ.get("PYTHONPATH", "")])}
        script = "from __future__ import annotations\n" + inspect.getsource(weights_digest) + _STEPS
        # cwd: a folder with no redsim in it, so that the first match on sys.path is the one in source
        done = subprocess.run(
            [sys.executable, "-c", script, str(job)], cwd=folder, env=env, capture_output=True, text=True
        )
    if done.returncode != 0:
        raise RuntimeError(f"the baseline in {source} failed: {done.stderr.strip()[-2000:]}")
    result = json.loads(done.stdout.strip().splitlines()[-1])
    if not Path(result["redsim_file"]).resolve().is_relative_to(source):
        raise RuntimeError(f"the baseline imported redsim from {result['redsim_file']}, not from {source}")
    result["same_weights"] = result.pop("weights") == weights_digest(subspace)
    result["source"] = str(source)
    return result


__all__ = ["check_source", "run_baseline", "weights_digest"]
