"""What `redsim bench env-ab` measures: an interleaved A/B of env settings by CPU time.

On a shared machine a speed difference between two settings of one env (solver options, another
subspace, the cubature) is only trustworthy when the settings run side by side under the same load.
So :func:`bench_env_ab` builds one native vector env per setting (``gym.make_vec(..., vectorization_mode=
"vector_entry_point")``) in one process, resets them all with the same seed, feeds every setting the
same uniform random actions, and after a few untimed steps alternates rounds of timed steps, the settings
in order in even rounds and in reverse order in odd ones (ABBA...), timing each round with
``time.process_time()`` (this process's CPU time, which other processes' load does not add to). Per
setting it reports the median CPU time of a vector step, the solver's work (iterations per copy,
value-and-gradient calls and the latent rows they evaluated, :class:`redsim.runtime.Evaluations`, as
``redsim bench envs`` counts them) and what the solves said (converged, out of range, diverged), and the
per-round CPU ratio of each setting against the first: the first's time over the setting's in the same
round, so a ratio above 1 means the setting is faster. With ``render`` (a frame size [px]) every timed step also
draws all copies' ``rgb_array`` frames (``render()``, timed on its own and counted in the ratio): what a pixel agent
pays per step.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from redsim.envs.base import MAX_IMAGE_SIDE
from redsim.envs.bench import SolveTally
from redsim.runtime import Evaluations


def bench_env_ab(
    env_id: str,
    settings: Mapping[str, Mapping[str, Any]],
    *,
    num_envs: int = 64,
    rounds: int = 4,
    steps_per_round: int = 10,
    warmup: int = 3,
    seed: int = 0,
    render: int | None = None,
    threads: int | None = 1,
) -> dict[str, Any]:
    """CPU time and solver work of ``env_id``'s native vector env under each of ``settings``, interleaved.

    Args:
        env_id: A registered id.
        settings: Name -> keyword arguments of ``gym.make_vec`` (``{}``: the env's defaults), in the order
            run; the first is the reference of the ratios. At least one.
        num_envs: Copies per vector env, N.
        rounds: Timed rounds; each runs ``steps_per_round`` vector steps of every setting.
        steps_per_round: Vector steps per setting and round.
        warmup: Untimed vector steps of each setting first (their actions are not reused).
        seed: Seeds the resets (copy i: ``seed + i``) and the actions.
        render: A frame size [px]: every setting gets ``render_mode="rgb_array"`` and that width and height (unless
            it names its own), and every timed step renders all copies after stepping them; None: no frames.
        threads: The envs' torch intra-op threads (:mod:`redsim.threads`), unless a setting names its own.

    Returns:
        ``env_id``, ``num_envs``, ``rounds``, ``steps_per_round``, ``warmup``, ``seed`` and ``settings``, a list in
        the order given, each with ``name``, ``env_args``, ``round_cpu_s`` (CPU seconds per vector step, per round),
        ``cpu_ms_per_step`` (their median [ms]), ``env_steps_per_cpu_s`` (N over that median), and over the timed
        steps: ``iterations_per_step`` (mean over steps and copies of ``info["iterations"]``),
        ``slowest_iterations_per_step`` (mean over steps of the slowest copy's), ``calls_per_step`` (the stepper's
        value-and-gradient calls per vector step), ``rows_per_copy_step`` (latent states those calls evaluated,
        per copy and step), ``converged_fraction`` (of copy-steps), ``out_of_range`` and ``diverged`` (copy-steps
        flagged; a copy restarted in a step is not stepped, and neither counts there), ``observation_gap`` (the
        largest absolute difference over the timed steps, copies and entries of its observations from the first
        setting's, which saw the same resets and actions: what the setting changes in the results; None where the
        observations' shapes differ), and ``ratio``
        against the first setting: ``rounds`` (its time over this one's, per round), ``median``, ``min``, ``max``. With
        ``render``, ``render_size``, and per setting ``round_render_cpu_s`` and ``render_cpu_ms`` (the renders' share
        of the round times, which include them).

    Raises:
        ValueError: no setting, a count < 1 (``warmup`` < 0), settings on different thread counts
            (:func:`check_same_threads`), or settings whose action spaces differ.
    """
    if not settings:
        raise ValueError("give at least one setting")
    for name, value in (("num_envs", num_envs), ("rounds", rounds), ("steps_per_round", steps_per_round)):
        if value < 1:
            raise ValueError(f"{name} must be >= 1, got {value}")
    if warmup < 0:
        raise ValueError(f"warmup must be >= 0, got {warmup}")
    if render is not None and not 8 <= render <= MAX_IMAGE_SIDE:
        raise ValueError(f"render must be a frame size in [8, {MAX_IMAGE_SIDE}] [px], got {render}")
    check_same_threads(settings, threads)
    frame = {} if render is None else {"render_mode": "rgb_array", "width": render, "height": render}
    frame["threads"] = threads
    venvs = {
        name: gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", **{**frame, **kwargs})
        for name, kwargs in settings.items()
    }
    try:
        shapes = {name: venv.action_space.shape for name, venv in venvs.items()}
        if len(set(shapes.values())) > 1:
            raise ValueError(f"the settings' action spaces differ: {shapes}")
        (shape,) = set(shapes.values())
        rng = np.random.default_rng(seed)
        actions = rng.uniform(-1.0, 1.0, (warmup + rounds * steps_per_round, *shape)).astype(np.float32)
        work = {name: _Work() for name in venvs}
        for venv in venvs.values():
            venv.reset(seed=seed)
            for action in actions[:warmup]:
                venv.step(action)
                if render is not None:
                    venv.render()
            venv.unwrapped.sim.stepper.evaluations = Evaluations()
        names = list(venvs)
        for r in range(rounds):
            block = actions[warmup + r * steps_per_round : warmup + (r + 1) * steps_per_round]
            for name in names if r % 2 == 0 else names[::-1]:
                work[name].run_round(venvs[name], block, render is not None)
        results = [_summary(name, settings[name], work[name], work[names[0]], venvs[name], num_envs) for name in names]
    finally:
        for venv in venvs.values():
            venv.close()
    return {
        "env_id": env_id,
        "num_envs": num_envs,
        "rounds": rounds,
        "steps_per_round": steps_per_round,
        "warmup": warmup,
        "seed": seed,
        "render_size": render,
        "settings": results,
    }


def check_same_threads(settings: Mapping[str, Mapping[str, Any]], threads: int | None) -> None:
    """Refuse settings on different torch thread counts (a setting's ``threads``, else ``threads``).

    Their steps alternate in one process, and switching the count between them is what gets timed: Chain-v0 at 64
    envs, 21 wall ms per vector step on one thread and 21 on two when each ran alone, took 60 and 726 ms with the two
    alternating (stop 68).

    Raises:
        ValueError: two settings' counts differ.
    """
    counts = {name: kwargs.get("threads", threads) for name, kwargs in settings.items()}
    if len(set(counts.values())) > 1:
        raise ValueError(
            f"the settings run on different torch thread counts {counts}: switching the count between their steps in "
            "one process is what env-ab would time (it slowed a Chain-v0 step 3-34x); time each with "
            "`redsim bench envs --threads N`"
        )


class _Work:
    """One setting's timed rounds: CPU seconds per vector step and what each step's ``info`` said."""

    def __init__(self) -> None:
        self.round_cpu_s: list[float] = []
        self.round_render_cpu_s: list[float] = []
        self.steps = 0  # timed vector steps
        self.solves = SolveTally()
        self.observations: list[np.ndarray] = []  # per timed step [N, obs]

    def run_round(self, venv: Any, actions: np.ndarray, render: bool = False) -> None:
        """Step ``venv`` once per action [N, A] (and render it after each step) and record the round's CPU time per
        step [s] (renders included) and the renders' share of it."""
        infos = []
        drawing = 0.0
        start = time.process_time()
        for action in actions:
            observation, _, _, _, info = venv.step(action)
            infos.append(info)
            self.observations.append(np.array(observation))
            if render:
                before = time.process_time()
                venv.render()
                drawing += time.process_time() - before
        self.round_cpu_s.append((time.process_time() - start) / len(actions))
        if render:
            self.round_render_cpu_s.append(drawing / len(actions))
        self.steps += len(infos)
        for info in infos:
            self.solves.add(info)


def observation_gap(observations: list[np.ndarray], reference: list[np.ndarray]) -> float | None:
    """The largest absolute difference of one setting's observations from another's over the same steps (NaN where
    either holds a NaN); None where their shapes differ (a map of another dimension: nothing to compare)."""
    if any(a.shape != b.shape for a, b in zip(observations, reference, strict=True)):
        return None
    gaps = [np.max(np.abs(a.astype(np.float64) - b)) for a, b in zip(observations, reference, strict=True)]
    return float(np.max(gaps))  # not max(gaps): Python's max keeps a finite value seen before a NaN


def _summary(
    name: str, env_args: Mapping[str, Any], work: _Work, first: _Work, venv: Any, num_envs: int
) -> dict[str, Any]:
    """One setting's row of :func:`bench_env_ab`."""
    steps = work.steps
    solves = work.solves.summary()
    evaluations = venv.unwrapped.sim.stepper.evaluations
    median_s = statistics.median(work.round_cpu_s)
    ratios = [a / b for a, b in zip(first.round_cpu_s, work.round_cpu_s, strict=True)]
    gap = observation_gap(work.observations, first.observations)
    rendered = (
        {
            "round_render_cpu_s": work.round_render_cpu_s,
            "render_cpu_ms": 1e3 * statistics.median(work.round_render_cpu_s),
        }
        if work.round_render_cpu_s
        else {}
    )
    return {
        "name": name,
        "env_args": dict(env_args),
        "round_cpu_s": work.round_cpu_s,
        **rendered,
        "cpu_ms_per_step": 1e3 * median_s,
        "env_steps_per_cpu_s": num_envs / median_s,
        "iterations_per_step": solves["iterations_per_step"],
        "slowest_iterations_per_step": solves["slowest_iterations_per_step"],
        "calls_per_step": evaluations.calls / steps,
        "rows_per_copy_step": evaluations.rows / (steps * num_envs),
        "converged_fraction": solves["converged_fraction"],
        "out_of_range": solves["out_of_range"],
        "diverged": solves["diverged"],
        "observation_gap": gap,
        "ratio": {"rounds": ratios, "median": statistics.median(ratios), "min": min(ratios), "max": max(ratios)},
    }


__all__ = ["bench_env_ab", "check_same_threads"]
