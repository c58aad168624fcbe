"""What `redsim bench envs` measures: env steps per second, single and vectorized, against the full-space step.

For each env id, in one process, side by side: construction time, then the median wall time of
an env step of the single env (random actions) and of the native vector env at each batch size,
as env steps/s (copies x steps / s) and simulated seconds per wall second (env steps/s x the
env's dt). For scale, the same scene's float64 full-space implicit-Euler step
(:class:`redsim.integrators.ImplicitEuler` over :class:`FullSpace`, Newton, under a random load of
the env's force size) is timed too, and so is drawing the single env's picture at 480 x 480
(``render_mode="rgb_array"``'s frame, :mod:`redsim.raster`), as frames per second. With ``mujoco``
installed the same run times the MuJoCo anchors RL users know (:func:`mujoco_anchors`: MuJoCo's
24-capsule chain and ``HalfCheetah-v5``; ``redsim bench envs`` adds MuJoCo's flex cloth,
:mod:`redsim.benches.mujoco_cloth`); without it they are skipped with the reason.
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import math
import statistics
import sys
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from redsim import scenes
from redsim.envs.sharded import check_timeout
from redsim.runtime import Evaluations

logger = logging.getLogger(__name__)

DEFAULT_BATCHES = (16, 64, 256)
RENDER_SIZE = (480, 480)
"""Width and height [px] of the timed frame (Gymnasium's and the envs' default)."""


def median_time(call: Callable[[], Any], repeats: int, budget: float) -> tuple[float, int]:
    """Median wall time [s] of ``call`` over up to ``repeats`` calls (fewer once ``budget`` seconds are spent).

    Returns:
        The median and the number of calls timed (at least one).
    """
    times: list[float] = []
    spent = 0.0
    while len(times) < repeats and (not times or spent < budget):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
        spent += times[-1]
    return statistics.median(times), len(times)


class SolveTally:
    """What the solves of timed env steps said, from each step's ``info`` (a single env's, or a vector env's with a
    value per copy): iterations per copy (a restarted copy counts 0) and of the slowest copy, and over the copies the
    step solved (a copy restarted in it is not, and its flags, a reset's out_of_range for its start, are left out) the
    converged fraction and the out_of_range and diverged counts (a diverged copy is then restarted, its step timed as
    any other): a rate over steps whose solves failed is not that of a working env."""

    def __init__(self) -> None:
        self.iterations: list[float] = []
        self.slowest: list[float] = []
        self.converged: list[float] = []
        self.out_of_range = 0
        self.diverged = 0

    def add(self, info: dict[str, Any]) -> None:
        """Count one step's ``info``."""
        if "iterations" not in info:  # every copy restarted (NEXT_STEP autoreset): no solve, no statistics
            return
        iterations = np.atleast_1d(info["iterations"])
        stepped = np.broadcast_to(info.get("_converged", True), iterations.shape)  # a single env's step: it stepped
        self.iterations.append(float(np.mean(iterations)))
        self.slowest.append(float(np.max(iterations)))
        self.converged.append(float(np.mean(np.atleast_1d(info["converged"])[stepped])))
        self.out_of_range += int(np.sum(np.atleast_1d(info["out_of_range"])[stepped]))
        self.diverged += int(np.sum(np.atleast_1d(info["diverged"])[stepped]))

    def summary(self) -> dict[str, Any]:
        """``iterations_per_step`` and ``slowest_iterations_per_step`` (means over steps), ``converged_fraction`` (the
        mean over steps of the solved copies' fraction), ``out_of_range`` and ``diverged`` (copy-steps); the means are
        NaN where no timed step solved a copy (every copy restarted in each)."""

        def mean(values: list[float]) -> float:
            return statistics.fmean(values) if values else math.nan

        return {
            "iterations_per_step": mean(self.iterations),
            "slowest_iterations_per_step": mean(self.slowest),
            "converged_fraction": mean(self.converged),
            "out_of_range": self.out_of_range,
            "diverged": self.diverged,
        }


def _full_space_step(
    env: Any, repeats: int, budget: float, rng: np.random.Generator, warmup: int = 3
) -> dict[str, Any]:
    """Median wall time of one float64 full-space step of the env's scene, each under the load of a fresh uniform
    random action as the env's steps, from the env's reset state lifted into the full space (f(z)) after ``warmup``
    untimed steps (f(z) is not the full space's rest: its first steps take more Newton iterations), Newton to the
    scene's ``full_space_tol`` (:class:`redsim.scenes.SceneEntry`)."""
    from redsim.integrators import FullSpace, ImplicitEuler
    from redsim.integrators.implicit_euler import quiet_steps

    sim = env.sim
    scene = sim.source_scene.to(dtype=torch.float64)
    tol = scenes.full_space_tol(scene.name)
    integrator = ImplicitEuler(FullSpace(scene), sim.dt / sim.frame_skip, minimizer="newton", tol=tol, max_iter=50)
    env.reset(seed=int(rng.integers(2**31)))
    q0 = sim.positions(sim.z[:1])[0].to("cpu", torch.float64)
    holder = {"state": integrator.initial_state(q0), "converged": True, "iterations": []}

    def call() -> None:
        draw = rng.uniform(-1.0, 1.0, (1, *env.action_space.shape))
        action = torch.as_tensor(draw, dtype=sim.torch_dtype, device=sim.device)
        loads = sim.task_loads(action, sim.params)[0].to(torch.float64).cpu()
        holder["state"], info = integrator.step(holder["state"], loads)
        holder["converged"] = holder["converged"] and info.converged
        holder["iterations"].append(info.iterations)

    with quiet_steps():  # the timed steps' convergence is returned (the table's footnote), the warm-up's is not timed
        start = time.perf_counter()
        for _ in range(warmup):  # within the budget too (a loaded cloth's full-space step took 138 s)
            call()
            if time.perf_counter() - start >= budget:
                break
        holder["iterations"], holder["converged"] = [], True
        seconds, count = median_time(call, repeats, budget)
    return {
        "step_s": seconds * sim.frame_skip,
        "sim_s_per_wall_s": env.dt / (seconds * sim.frame_skip),
        "repeats": count,
        "converged": holder["converged"],
        "iterations_per_step": statistics.fmean(holder["iterations"]),
        "tol": tol,
    }


@contextlib.contextmanager
def old_versions_quiet() -> Iterator[None]:
    """Gymnasium's "is out of date" warning silenced: the bench times every version of an id on purpose."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*is out of date", category=DeprecationWarning)
        yield


def attempt(part: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """``part()``, or ``{"failed": "TYPE: message"}`` where it raised an :class:`Exception` (its traceback logged at
    INFO, ``redsim -v``): one part of a long run that fails is reported in its place and the others still run.
    KeyboardInterrupt and SystemExit are not caught: Ctrl-C stops the run."""
    try:
        return part()
    except Exception as err:
        logger.info("a bench part failed", exc_info=True)
        return {"failed": f"{type(err).__name__}: {err}"}


def failed_parts(row: dict[str, Any]) -> dict[str, str]:
    """The parts of a :func:`bench_env` row that failed (:func:`attempt`), each with its error: ``env`` where the
    id as a whole did (its row holds only ``id`` and ``failed``), else ``single``, ``render``, ``N=B`` and
    ``full space``."""
    if "failed" in row:
        return {"env": row["failed"]}
    parts = {"single": row["single"], "render": row["render"], **{f"N={b}": v for b, v in row["vector"].items()}}
    parts["full space"] = row["full_space"] or {}
    return {name: part["failed"] for name, part in parts.items() if "failed" in part}


def bench_env(
    env_id: str,
    *,
    batches: Sequence[int] = DEFAULT_BATCHES,
    steps: int = 20,
    warmup: int = 3,
    budget: float = 20.0,
    full_space: bool = True,
    seed: int = 0,
    shards: int = 1,
    shard_timeout: float | None = None,
    **env_kwargs: Any,
) -> dict[str, Any]:
    """Timings of one env id (module doc).

    Args:
        env_id: A registered id.
        batches: Vector env sizes.
        steps: Timed steps per configuration (fewer once ``budget`` seconds are spent).
        warmup: Untimed steps first.
        budget: Seconds of timing per configuration.
        full_space: Also time the scene's full-space step.
        seed: Seeds resets and actions: each batch size's actions and the full-space step's draw from their own
            streams (``(seed, batch)``, ``(seed, 0)``), so no part depends on which others run.
        shards: Worker processes of each vector env (1: the native vector env in this process; P > 1: a
            :class:`redsim.envs.sharded.ShardedVectorEnv`, whose solver calls and rows are not counted: None).
        shard_timeout: With ``shards`` > 1, seconds each vector env call waits for its workers: past it, that
            batch's part fails (:class:`redsim.envs.sharded.ShardTimeoutError`) and the others run (None: for ever).
        **env_kwargs: Passed to ``gym.make``/``gym.make_vec``.

    Returns:
        ``id``, ``scene`` (its name), ``n``, ``d``, ``action_size``, ``observation_size``, ``dt`` [s], ``make_s``,
        ``single`` and ``vector`` (per batch) with ``env_steps_per_s`` and ``sim_s_per_wall_s``, what the timed
        steps' solves said (:meth:`SolveTally.summary`: ``iterations_per_step``, the mean over copies of
        ``info["iterations"]``; ``slowest_iterations_per_step``, the mean over steps of the slowest copy's
        iterations (a vector step makes at least that many objective calls); ``converged_fraction``,
        ``out_of_range``, ``diverged``) and for ``vector`` the solver's calls per timed vector step
        (``calls_per_step``, the stepper's value-and-gradient calls; ``rows_per_copy_step``, the latent states those
        calls evaluated per copy),
        ``full_space`` (``step_s``, ``sim_s_per_wall_s``) or None, ``render`` (``frames_per_s`` of the single
        env's ``rgb_array`` frame at :data:`RENDER_SIZE`, the map's full configuration included). A part that
        raised is ``{"failed": "TYPE: message"}`` and the others are still timed (:func:`attempt`,
        :func:`failed_parts`).

    Raises:
        ValueError: a ``shard_timeout`` with ``shards`` 1 (no worker to wait for), or not a number of seconds > 0.
        Exception: what making the env or reading its sizes raised (no part can be timed without them).
    """
    if check_timeout(shard_timeout) is not None and shards == 1:
        raise ValueError(
            f"shard_timeout={shard_timeout!r} bounds the wait for a sharded env's workers: give shards > 1"
        )
    start = time.perf_counter()
    with old_versions_quiet():
        env = gym.make(env_id, **env_kwargs).unwrapped
    make_s = time.perf_counter() - start
    try:
        row: dict[str, Any] = {
            "id": env_id,
            "n": env.sim.scene.free_dof_count,
            "d": env.sim.latent_dim,
            "action_size": int(env.action_space.shape[0]),
            "observation_size": int(env.observation_space.shape[0]),
            "scene": env.sim.scene.name,
            "dt": env.dt,
            "make_s": make_s,
            "single": attempt(lambda: _single_env(env, steps, warmup, budget, seed)),
            "render": attempt(lambda: _render(env, steps, budget)),
        }
        timings = {"steps": steps, "warmup": warmup, "budget": budget, "seed": seed, "shards": shards}
        timings["shard_timeout"] = shard_timeout
        row["vector"] = {
            int(b): attempt(lambda b=b: _vector_env(env_id, int(b), env.dt, **timings, env_kwargs=env_kwargs))
            for b in batches
        }
        row["full_space"] = None
        if full_space:
            row["full_space"] = attempt(
                lambda: _full_space_step(env, max(3, steps // 4), budget, np.random.default_rng((seed, 0)), warmup)
            )
    finally:
        env.close()
    return row


def _single_env(env: Any, steps: int, warmup: int, budget: float, seed: int) -> dict[str, Any]:
    """The single env's part of :func:`bench_env`: its median step over random actions, from a reset with ``seed``."""
    env.reset(seed=seed)
    solves = SolveTally()

    def single_step() -> None:
        _, _, terminated, _, info = env.step(env.action_space.sample())
        solves.add(info)
        if terminated:  # a diverged step too: counted, then the env restarts as a vector env's copy does
            env.reset()

    env.action_space.seed(seed)
    for _ in range(warmup):
        single_step()
    solves = SolveTally()  # the timed steps' only
    seconds, count = median_time(single_step, steps, budget)
    return {
        "env_steps_per_s": 1.0 / seconds,
        "sim_s_per_wall_s": env.dt / seconds,
        "repeats": count,
        **solves.summary(),
    }


def _render(env: Any, steps: int, budget: float) -> dict[str, Any]:
    """The frame's part of :func:`bench_env`: the single env's picture at :data:`RENDER_SIZE`, per second."""
    view = env.sim.fixed_view(*RENDER_SIZE, env._camera)  # the fixed camera render() draws with
    env.sim.draw(view, 0)
    frame_s, frames = median_time(lambda: env.sim.draw(view, 0), steps, budget)
    return {"frames_per_s": 1.0 / frame_s, "size": list(RENDER_SIZE), "repeats": frames}


def _vector_env(
    env_id: str,
    batch: int,
    dt: float,
    *,
    steps: int,
    warmup: int,
    budget: float,
    seed: int,
    shards: int,
    shard_timeout: float | None,
    env_kwargs: dict[str, Any],
) -> dict[str, Any]:
    """One batch size's part of :func:`bench_env`: a fresh vector env of ``batch`` copies (env step ``dt`` [s]),
    its median step over uniform random actions drawn from the stream ``(seed, batch)``."""
    sharding = {"shards": shards, "timeout": shard_timeout} if shards != 1 else {}
    with old_versions_quiet():
        venv = gym.make_vec(env_id, num_envs=batch, vectorization_mode="vector_entry_point", **sharding, **env_kwargs)
    try:
        venv.reset(seed=seed)
        rng = np.random.default_rng((seed, batch))
        actions = iter(rng.uniform(-1.0, 1.0, (max(steps, 1) + warmup, *venv.action_space.shape)).astype(np.float32))
        tally = [SolveTally()]

        def vector_step() -> None:
            tally[0].add(venv.step(next(actions))[4])

        for _ in range(warmup):
            vector_step()
        tally[0] = SolveTally()  # the timed steps' only
        stepper = None if shards != 1 else venv.unwrapped.sim.stepper
        if stepper is not None:
            stepper.evaluations = Evaluations()
        seconds, count = median_time(vector_step, steps, budget)
        return {
            "env_steps_per_s": batch / seconds,
            "sim_s_per_wall_s": batch * dt / seconds,
            "repeats": count,
            **tally[0].summary(),
            "calls_per_step": None if stepper is None else stepper.evaluations.calls / count,
            "rows_per_copy_step": None if stepper is None else stepper.evaluations.rows / (count * batch),
            "shards": shards,
        }
    finally:
        venv.close()


RATES = ("env_steps_per_s", "sim_s_per_wall_s", "steps_per_s", "frames_per_s")
"""The keys of the rates a round measures (in :func:`bench_env`'s rows and the anchors), which :func:`median_rounds`
takes the median of."""

HEALTH_FLAGS = ("finite", "converged")
"""The keys of what a round's run says of its own health (the flex cloth's state ended ``finite``, a full-space step
``converged``): :func:`median_rounds` holds one True only where every round's is (a blown-up round is not hidden
behind the first one's True)."""


def median_rounds(rounds: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """One result of several rounds of the same measurement (:func:`bench_env`'s row of one id, or an anchor): the
    first round's, with each rate (:data:`RATES`) in it, nested too, replaced by its median over the rounds and the
    rounds' values listed beside it under ``rounds_<key>``, and each health flag (:data:`HEALTH_FLAGS`) True only
    where it is in every round. Everything else is the first round's: the sizes, the solver's work (the same seeded
    steps in every round) and what only the first round measured (a part the others hold as None or without the same
    keys: the full-space step). A part that failed in any round (:func:`attempt`) is that round's failure: its other
    rounds' rates are not the median of all.

    Raises:
        ValueError: no rounds.
    """
    if not rounds:
        raise ValueError("need at least one round")

    def merge(parts: Sequence[Any]) -> Any:
        failed = [p for p in parts if isinstance(p, dict) and "failed" in p]
        if failed:
            return failed[0]
        head = parts[0]
        if not isinstance(head, dict) or any(not isinstance(p, dict) or p.keys() != head.keys() for p in parts):
            return head
        out = {}
        for key, value in head.items():
            if key in RATES and isinstance(value, float | int):
                values = [float(part[key]) for part in parts]
                out[key] = statistics.median(values)
                out[f"rounds_{key}"] = values
            elif key in HEALTH_FLAGS and isinstance(value, bool):
                out[key] = all(part[key] for part in parts)
            else:
                out[key] = merge([part[key] for part in parts])
        return out

    return merge(list(rounds)) if len(rounds) > 1 else rounds[0]


MUJOCO_MISSING = "mujoco is not installed (pip install 'redsim[bench]')"
ANCHOR_STEPS = 2000
"""Timed steps of each MuJoCo anchor (after :data:`ANCHOR_WARMUP` untimed ones)."""
ANCHOR_WARMUP = 100
"""Untimed steps of each MuJoCo anchor first."""


def mujoco_anchors(steps: int = ANCHOR_STEPS) -> dict[str, Any]:
    """Speed of the MuJoCo anchors RL users know, where ``mujoco`` is installed, else the reason.

    Two anchors, each as steps/s and simulated seconds per wall second: MuJoCo's hanging chain of
    24 capsules on ball joints (:func:`redsim.runtime.bench.mujoco_chain`, RK4 at dt 0.01 s,
    the same model as ``redsim bench step``; each ``mj_step`` timed) and Gymnasium's
    ``HalfCheetah-v5`` (single env, random actions; its env step is 5 MuJoCo steps, dt 0.05 s),
    median over ``steps`` steps. (``redsim bench envs`` adds the flex cloth of
    :mod:`redsim.benches.mujoco_cloth`, a benchmark module above this one.)

    Returns:
        ``{"available": False, "reason": ...}``, or ``available`` with ``chain`` (``steps_per_s``,
        ``sim_s_per_wall_s``, ``nv``, ``integrator``, ``timestep``) and ``HalfCheetah-v5``
        (``env_steps_per_s``, ``sim_s_per_wall_s``, ``dt``), the latter a ``reason`` where
        Gymnasium's MuJoCo envs cannot be made; an anchor that raised is ``{"failed": ...}`` (:func:`attempt`).
    """
    if importlib.util.find_spec("mujoco") is None:
        return {"available": False, "reason": MUJOCO_MISSING}
    chain = attempt(lambda: _chain_anchor(steps))
    return {"available": True, "chain": chain, "HalfCheetah-v5": attempt(lambda: _cheetah_anchor(steps))}


def _chain_anchor(steps: int) -> dict[str, Any]:
    """The MuJoCo chain's steps/s (:func:`mujoco_anchors`): the median ``mj_step``, as every row is timed."""
    import mujoco

    from redsim.runtime.bench import mujoco_chain

    integrator, timestep = "RK4", 0.01
    model, data = mujoco_chain(integrator=integrator, timestep=timestep)
    for _ in range(ANCHOR_WARMUP):
        mujoco.mj_step(model, data)
    seconds, _ = median_time(lambda: mujoco.mj_step(model, data), steps, budget=float("inf"))
    return {
        "integrator": integrator,
        "timestep": timestep,
        "nv": int(model.nv),
        "steps_per_s": 1.0 / seconds,
        "sim_s_per_wall_s": timestep / seconds,
    }


def _cheetah_anchor(steps: int) -> dict[str, Any]:
    """``HalfCheetah-v5``'s env steps/s (:func:`mujoco_anchors`), or a ``reason``: the unwrapped env, as
    :func:`bench_env` times redsim's single env (gym.make's checker and time limit cost ~10% of a step)."""
    try:
        env = _quiet_settotalmass(lambda: gym.make("HalfCheetah-v5")).unwrapped
    except (gym.error.Error, ImportError) as err:
        return {"reason": f"HalfCheetah-v5: {err}"}
    env.reset(seed=0)
    env.action_space.seed(0)

    def cheetah_step() -> None:
        _, _, terminated, _, _ = env.step(env.action_space.sample())
        if terminated:  # never, for HalfCheetah; the unwrapped env has no time limit to truncate it
            env.reset()

    for _ in range(ANCHOR_WARMUP):
        cheetah_step()
    seconds, _ = median_time(cheetah_step, steps, budget=float("inf"))
    dt = float(env.dt)
    env.close()
    return {"env_steps_per_s": 1.0 / seconds, "sim_s_per_wall_s": dt / seconds, "dt": dt}


def _quiet_settotalmass(make: Callable[[], Any]) -> Any:
    """``make()`` without MuJoCo's deprecation warning on Gymnasium's ``settotalmass`` (half_cheetah.xml);
    every other MuJoCo warning passes through to the handler before (MuJoCo's own: stderr)."""
    import mujoco

    previous = mujoco.get_mju_user_warning()

    def forward(text: str) -> None:
        if "settotalmass" in text:
            return
        if previous is not None:
            previous(text)
        else:
            print(f"WARNING: {text}", file=sys.stderr)

    mujoco.set_mju_user_warning(forward)
    try:
        return make()
    finally:
        mujoco.set_mju_user_warning(previous)


def anchor_lines(anchors: dict[str, Any]) -> list[str]:
    """The anchors of :func:`mujoco_anchors` as printed lines."""
    if not anchors["available"]:
        return [f"MuJoCo anchors skipped: {anchors['reason']}"]
    chain, cheetah = anchors["chain"], anchors["HalfCheetah-v5"]
    if "failed" in chain:
        lines = [f"MuJoCo chain failed: {chain['failed']}"]
    else:
        lines = [
            f"MuJoCo chain (24 capsules, nv {chain['nv']}, {chain['integrator']} dt {chain['timestep']} s): "
            f"{chain['steps_per_s']:.0f} steps/s, {chain['sim_s_per_wall_s']:.1f} sim s per wall s"
        ]
    if "failed" in cheetah:
        return [*lines, f"MuJoCo HalfCheetah-v5 failed: {cheetah['failed']}"]
    if "reason" in cheetah:
        return [*lines, f"MuJoCo HalfCheetah-v5 skipped: {cheetah['reason']}"]
    return [
        *lines,
        f"MuJoCo HalfCheetah-v5 (single env, dt {cheetah['dt']} s): {cheetah['env_steps_per_s']:.0f} env steps/s, "
        f"{cheetah['sim_s_per_wall_s']:.1f} sim s per wall s",
    ]


__all__ = [
    "ANCHOR_STEPS",
    "ANCHOR_WARMUP",
    "DEFAULT_BATCHES",
    "HEALTH_FLAGS",
    "MUJOCO_MISSING",
    "RATES",
    "RENDER_SIZE",
    "anchor_lines",
    "attempt",
    "bench_env",
    "failed_parts",
    "median_rounds",
    "median_time",
    "mujoco_anchors",
]
