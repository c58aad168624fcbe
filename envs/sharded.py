"""A native vector env split over worker processes, so that a batch of copies uses several CPU cores.

One :class:`LatentVectorEnv` steps all its copies in one batched solve, in one process: its small
tensor ops do not spread over cores (torch's intra-op threads do not help them). With ``shards=P``,
``gymnasium.make_vec(id, num_envs=N, vectorization_mode="vector_entry_point", shards=P)`` builds a
:class:`ShardedVectorEnv`: P worker processes, each holding a native vector env of a contiguous block
of the N copies (sizes differ by at most one), stepped in parallel. Copy i is seeded ``seed + i`` as
in the native vector env, so the two are the same env (equal step for step where the solve is tight
enough that the batch composition does not move it; see ``tests/envs/test_sharded.py``). A worker
that fails raises in the caller (its own exception, or :class:`ShardError`, with the worker's traceback), and
the env is closed, as it is when the caller is interrupted in the middle of a request. With ``timeout=S``, a
request that some shard does not answer within S seconds (a worker stuck in a solve, stopped, deadlocked) raises
:class:`ShardTimeoutError` (a :class:`multiprocessing.TimeoutError`, as Gymnasium's ``AsyncVectorEnv.step_wait``
raises), the workers stopped and the env closed; ``None`` (the default) waits for ever.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing as mp
import numbers
import os
import pickle
import sys
import time
import traceback
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any, NoReturn

import gymnasium as gym
import numpy as np
import torch
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from redsim.envs.base import (
    NO_HUMAN,
    NO_RENDER_MODE,
    VECTOR_RENDER_MODES,
    check_action,
    copy_seeds,
    restored_generator,
)
from redsim.envs.vector_api import ClosedVectorEnvError, SharedCopies, check_started, episode_clock, reset_mask

if TYPE_CHECKING:
    from redsim.envs.base import LatentEnv

JOIN_TIMEOUT_S = 10.0
"""Seconds :meth:`ShardedVectorEnv.close` waits for its workers to exit before terminating them (the env's
``timeout`` where that is shorter)."""
KILL_AFTER_S = 1.0
"""Seconds a terminated worker (SIGTERM) has to exit before it is killed (SIGKILL): a stopped process (SIGSTOP)
keeps SIGTERM pending until it is continued, and would be left behind (and hold up this interpreter's exit)."""
STARTUP_HINT = (
    '; its stderr says why. A script must make a sharded env under `if __name__ == "__main__":` (each worker'
    " re-imports the main module), and the env class and its arguments must be importable by the worker"
    " (not defined in a notebook or in the main module)"
)
"""What a worker that exits while starting most often means (added to the :class:`ShardError`)."""


class ShardError(RuntimeError):
    """A worker process of a :class:`ShardedVectorEnv` failed (its traceback is in the message)."""


class ShardTimeoutError(ShardError, mp.TimeoutError):
    """Some worker of a :class:`ShardedVectorEnv` did not answer a request within the env's ``timeout`` (the
    message names the shards, their copies and worker ids, and the seconds waited); the env is closed.

    Also a :class:`multiprocessing.TimeoutError`, what Gymnasium's ``AsyncVectorEnv.step_wait(timeout)`` raises.
    """


def check_timeout(timeout: float | None) -> float | None:
    """``timeout`` as seconds (float), or None (wait for ever).

    Raises:
        ValueError: anything but None or a finite number > 0 (NaN, inf, 0, a negative number, a bool, a string).
    """
    if timeout is None:
        return None
    if isinstance(timeout, bool) or not isinstance(timeout, numbers.Real) or not math.isfinite(timeout) or timeout <= 0:
        raise ValueError(f"timeout must be None (wait for ever) or a finite number of seconds > 0, got {timeout!r}")
    return float(timeout)


def shard_sizes(num_envs: int, shards: int) -> list[int]:
    """Copies per shard: ``num_envs`` split into ``shards`` contiguous blocks differing by at most one.

    Raises:
        ValueError: ``shards`` not an integer in [1, num_envs].
    """
    if isinstance(shards, bool) or int(shards) != shards or not 1 <= shards <= num_envs:
        raise ValueError(f"shards must be an integer in [1, num_envs = {num_envs}], got {shards!r}")
    base, extra = divmod(int(num_envs), int(shards))
    return [base + (i < extra) for i in range(int(shards))]


def _warning_display() -> bytes | None:
    """The caller's ``warnings.showwarning`` pickled where it pickles (the command line's one-line display,
    ``redsim.cli.common.show_warning``: a spawned worker would print Python's ``file:line: UserWarning`` form
    instead), else None (the worker keeps Python's). Bytes, which the worker unpickles itself: a function pickled by
    reference to a module the worker cannot import (a notebook's ``__main__``) must not kill it before it starts. The
    worker's filters come from the interpreter's ``-W`` options, which a spawned process inherits."""
    try:
        return pickle.dumps(warnings.showwarning)
    except Exception:
        return None


@contextlib.contextmanager
def _unreadable_main_hidden() -> Iterator[None]:
    """Hide the main module's ``__file__`` while the workers start where it names no file to read (a script read
    from stdin, ``python - <<EOF``: ``'<stdin>'``): a spawned or forkserver worker runs the main module again from
    that path, and each one died of ``FileNotFoundError: '<stdin>'`` before it started. Without it the worker does
    not run the main module, as for ``python -c`` (whose main has no ``__file__``)."""
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    named = getattr(getattr(main, "__spec__", None), "name", None)  # ``python -m``: the worker imports it by name
    if (
        not isinstance(path, str)
        or named is not None
        or os.path.isfile(os.path.join(mp.process.ORIGINAL_DIR or "", path))
    ):
        yield
        return
    del main.__file__
    try:
        yield
    finally:
        main.__file__ = path


def _worker(pipe: Connection, build: bytes, num_envs: int, threads: int, display: bytes | None) -> None:
    """Serve one shard: build its native vector env (``build``: a pickled ``build(n)``), then answer (command,
    payload) requests until "close". A request that raises is answered ("error", (the exception pickled, or None
    where it does not pickle, and its traceback)), and the worker goes on serving. ``display``: the caller's
    ``warnings.showwarning`` pickled (:func:`_warning_display`), so a worker's warnings read as the caller's do where
    the worker can unpickle it (else Python's display)."""
    import torch

    if display is not None:
        try:
            warnings.showwarning = pickle.loads(display)
        except Exception:  # the caller's display is not importable here: the worker keeps Python's
            pass
    torch.set_num_threads(threads)
    venv = None
    try:
        try:
            venv = pickle.loads(build)(num_envs)
        except Exception:
            pipe.send(("error", _failure()))
            return
        pipe.send(("ok", None))
        while True:
            command, payload = pipe.recv()
            if command == "close":
                break
            try:
                pipe.send(("ok", _serve(venv, command, payload)))
            except Exception:
                pipe.send(("error", _failure()))
    except (KeyboardInterrupt, EOFError, BrokenPipeError):
        pass
    finally:
        if venv is not None:
            venv.close()
        pipe.close()


def _serve(venv: VectorEnv, command: str, payload: Any) -> Any:
    """The answer of a native vector env to one request."""
    if command == "step":
        return venv.step(payload)
    if command == "reset":
        if payload[1] and "reset_mask" in payload[1] and not payload[1]["reset_mask"].any():  # no copy of this shard
            sim = venv.sim  # type: ignore[attr-defined]
            if not sim.params:  # never reset: the native env's unreset rows (rest, zero task parameters)
                sim.params = sim.drawn_params()
            return sim.observe(), {}
        return venv.reset(seed=payload[0], options=payload[1])
    if command == "call":
        return venv.call(payload)
    if command == "frame":  # a tracking camera's points: this shard's overlay markers, and copy 0's shape (shard 0)
        sim = venv.sim  # type: ignore[attr-defined]
        return sim.marker_points(range(venv.num_envs)), sim.first_shape() if payload else None
    if command == "render":
        if payload is not None:  # the view of every shard's copies (a tracking camera reframed)
            venv.frame_on(*payload)  # type: ignore[attr-defined]
        return venv.render()
    if command == "get_state":
        return venv.get_state()  # type: ignore[attr-defined]
    if command == "set_state":
        return venv.set_state(payload)  # type: ignore[attr-defined]
    raise ValueError(f"unknown command {command!r}")


def _failure() -> tuple[bytes | None, str]:
    """The exception being handled, pickled (None where it does not pickle), and its traceback."""
    error = sys.exc_info()[1]
    try:
        pickled: bytes | None = pickle.dumps(error)
    except Exception:
        pickled = None
    return pickled, traceback.format_exc()


class ShardedVectorEnv(SharedCopies, VectorEnv):
    """N copies of a latent env in P worker processes, each a native vector env of its block (module doc).

    Args:
        build: ``build(n)`` makes a native vector env of n copies (picklable: each worker gets a copy).
        template: One env of the same id and arguments, in this process, for spaces, metadata and attributes
            (it is never stepped; not in render_mode "human": a ValueError, :data:`redsim.envs.base.NO_HUMAN`).
        num_envs: N.
        shards: P, in [1, N].
        threads: torch intra-op threads of each worker process outside its env's calls, which run on the env's own
            ``threads`` (default 1; :mod:`redsim.threads`) (None: the CPU count over P, at least 1).
        context: The multiprocessing start method (None: "forkserver" where available, else "spawn";
            "fork" is refused: torch's thread pools do not survive it).
        autoreset_mode: The mode ``build`` makes the native envs with (for ``metadata``).
        max_episode_steps: The episode length ``build`` gives them (an attribute, as the native env's).
        timeout: Seconds each request (``reset``, ``step``, ``render``, ``get_state``, ``set_state``, ``call``)
            waits for every shard's answer, from when it is sent; past it, :class:`ShardTimeoutError` and the env
            is closed (None: wait for ever). Starting the workers (which may fit a missing subspace) is not timed,
            as Gymnasium's ``AsyncVectorEnv`` does not time its start.
    """

    def __init__(
        self,
        build: Callable[[int], VectorEnv],
        template: LatentEnv,
        num_envs: int,
        shards: int,
        *,
        threads: int | None = None,
        context: str | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        max_episode_steps: int | None = None,
        timeout: float | None = None,
    ) -> None:
        self.timeout = check_timeout(timeout)
        if int(num_envs) != num_envs or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        self.sizes = shard_sizes(int(num_envs), shards)
        if threads is None:
            threads = max(1, _cpu_count() // len(self.sizes))
        if isinstance(threads, bool) or int(threads) != threads or threads < 1:
            raise ValueError(f"threads must be an integer >= 1, got {threads!r}")
        if context is None:
            context = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        if context == "fork":
            raise ValueError("context 'fork' is not supported (torch's thread pools do not survive it): use 'spawn'")
        mode = AutoresetMode(autoreset_mode)
        if template.render_mode == "human":
            raise ValueError(NO_HUMAN)
        self.template = template
        self.observation_structure = template.observation_structure
        self.max_episode_steps = max_episode_steps
        self.num_envs = int(num_envs)
        self.render_mode = self.template.render_mode
        self.metadata = {**self.template.metadata, "render_modes": list(VECTOR_RENDER_MODES), "autoreset_mode": mode}
        self.single_action_space = self.template.action_space
        self.single_observation_space = self.template.observation_space
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.dt = self.template.dt
        self.frame_skip = self.template.frame_skip
        self.starts = np.cumsum([0, *self.sizes])[:-1].tolist()
        self._pipes: list[Connection] = []
        self._processes: list[Any] = []
        self._unreset = np.ones(self.num_envs, dtype=bool)  # copies never reset (nor restored by set_state)
        self._ended = np.zeros(self.num_envs, dtype=bool)  # DISABLED: copies that ended and were not reset
        self._view: Any = None  # a tracking camera's view of all the copies (:meth:`_framing`)
        self.closed = False
        ctx = mp.get_context(context)
        payload = pickle.dumps(build)  # here, so that a build that does not pickle fails in the caller
        display = _warning_display()
        try:
            with _unreadable_main_hidden():
                for size in self.sizes:
                    parent, child = ctx.Pipe()
                    process = ctx.Process(
                        target=_worker, args=(child, payload, size, int(threads), display), daemon=True
                    )
                    process.start()
                    child.close()
                    self._pipes.append(parent)
                    self._processes.append(process)
            self._gather(STARTUP_HINT)  # each worker's "ok" once its env is built
        except BaseException:
            self._abort()
            raise

    def __getstate__(self) -> dict[str, Any]:
        """Refused: the env holds worker processes and their pipes, which do not pickle (nor ``copy.deepcopy``).

        Raises:
            TypeError: always, naming what does pickle: :meth:`get_state` (restored with :meth:`set_state` into a
                sharded env made again) or a native vector env (``shards=1``).
        """
        raise TypeError(
            "a sharded vector env holds worker processes and does not pickle: pickle its get_state() and restore it "
            "with set_state() into one made again (gymnasium.make_vec(..., shards=P)), or use a native vector env "
            "(shards=1), which pickles"
        )

    # -- the VectorEnv API ----------------------------------------------------------------------
    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset all copies, or those of ``options["reset_mask"]`` (bool [N]); seed copy i with ``seed + i``. A seed
        of a reset copy (only those are checked, as in the native env) or an option refused is refused before any
        shard resets (the env stays open)."""
        mask = reset_mask(options, self.num_envs)
        if set(options or ()) - {"reset_mask"} and not self.template.sim.params:
            self.template.reset(seed=0)  # one draw, for the parameters' shapes (a refused option closes no shard)
        self.template.sim.episode_options(options, vector=True)
        own, seeds = copy_seeds(seed, self.num_envs)
        rows = range(self.num_envs) if mask is None else np.nonzero(mask)[0]
        for i in rows if seeds is not None else ():  # the reset copies' seeds, as the native env's reset checks them,
            if seeds[i] is not None:  # here: a worker's refusal closes the env
                seeding.np_random(seeds[i])  # Gymnasium's rule (gymnasium.error.Error), before any shard is seeded
        super().reset(seed=own)
        requests = []
        for block in self._blocks():
            shard_options = None if options is None else {**options}
            if mask is not None:
                shard_options["reset_mask"] = mask[block]  # type: ignore[index]
            requests.append(("reset", (None if seeds is None else seeds[block], shard_options)))
        results = self._call(requests)
        self._view = None  # a tracking camera frames anew after a reset, as the native env's
        self._ended[slice(None) if mask is None else mask] = False
        self._unreset[slice(None) if mask is None else mask] = False
        return np.concatenate([obs for obs, _ in results]), _merge_infos([info for _, info in results], self.sizes)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every copy with actions [N, A]: each shard its block, in parallel."""
        check_started(self._unreset)
        if self._ended.any():  # as the native env, here: a shard's error would close the env
            raise RuntimeError(
                f"copies {np.nonzero(self._ended)[0].tolist()} ended and autoreset_mode is DISABLED: reset them "
                "with reset(options={'reset_mask': mask}) before the next step"
            )
        act = check_action(actions, self.action_space.shape)
        results = self._call([("step", act[block]) for block in self._blocks()])
        obs, reward, terminated, truncated = (np.concatenate([r[k] for r in results]) for k in range(4))
        if self.metadata["autoreset_mode"] == AutoresetMode.DISABLED:
            self._ended = terminated | truncated
        return obs, reward, terminated, truncated, _merge_infos([r[4] for r in results], self.sizes)

    def render(self) -> tuple[np.ndarray, ...] | None:
        """One RGB frame [H, W, 3] per copy ("rgb_array"), else None (with a warning, as a single env's).

        Raises:
            gymnasium.error.ResetNeeded: a copy was never reset (nor restored by :meth:`set_state`); the env stays open.
            ClosedVectorEnvError: the env is closed (with or without a render mode, as the native env).
        """
        if self.closed or not self._pipes:  # before the render mode's warning, which would not say why
            raise ClosedVectorEnvError("this ShardedVectorEnv is closed")
        if self.render_mode != "rgb_array":
            gym.logger.warn(NO_RENDER_MODE)
            return None
        check_started(self._unreset, "render()")  # here: a shard's error would close the env
        framing = self._framing() if self.template._camera.get("track", False) else None
        return tuple(frame for frames in self._call([("render", framing)] * len(self.sizes)) for frame in frames)

    def _framing(self) -> tuple[torch.Tensor, np.ndarray | None] | None:
        """A tracking camera frames every copy as the native env of all of them does (copy 0's shape and every
        copy's markers, reframed when a marker leaves the view): (q [n], points [P, D]) to frame the shards' views on
        where this render reframes, else None (each shard keeps the view it was last sent)."""
        answers = self._call([("frame", shard == 0) for shard in range(len(self.sizes))])
        found = [points for points, _ in answers if points is not None]
        points = np.concatenate(found) if found else None
        if self._view is not None and (points is None or self._view.contains(points)):
            return None
        q = answers[0][1]
        self._view = self.template.sim.view_on(*self.template._render_size, self.template._camera, q, points)
        return q, points

    def get_state(self) -> dict[str, Any]:
        """The batched state of all copies, as the native env's :meth:`LatentVectorEnv.get_state` (the shards'
        states joined along the copies), so a state moves between sharded and native envs of the same copies.

        Raises:
            gymnasium.error.ResetNeeded: a copy was never reset (nor restored by :meth:`set_state`).
        """
        check_started(self._unreset, "get_state()")  # here: a shard's error would close the env
        return _join_states(self._call([("get_state", None)] * len(self.sizes)))

    def set_state(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`get_state`'s state (or a native env's of as many copies).

        Raises:
            ValueError: a state whose ``cond``, ``z``, ``z_prev``, ``loads`` or task parameters have another shape or
                are not finite, a condition outside the scene's range, an episode clock the native env refuses
                (:func:`~redsim.envs.vector_api.episode_clock`), an ``rngs`` entry that is not a NumPy generator
                state, then a task parameter ``reset(options=...)`` would refuse and latents too far out for the map
                (checked here, in that order, as the native env does: the env stays open).
        """
        if not isinstance(state, Mapping):
            raise ValueError(f"need the dict get_state() returns, got {type(state).__name__}")
        self._check_state_shapes(state)
        _, pending = episode_clock(state, self.num_envs)
        rngs = state.get("rngs")
        if rngs is not None:
            if len(rngs) != self.num_envs:
                raise ValueError(f"state['rngs'] must hold {self.num_envs} generator states, got {len(rngs)}")
            for saved in rngs:
                restored_generator(None, saved)
        if isinstance(state.get("params"), Mapping):
            self.template.sim.check_state_params(state["params"])
            self._check_state_latents(state)
        parts = [_state_rows(state, block) for block in self._blocks()]
        self._call([("set_state", part) for part in parts])
        self._view = None
        if self.metadata["autoreset_mode"] == AutoresetMode.DISABLED:
            self._ended = pending
        self._unreset[:] = False

    def _per_copy(self, name: str) -> tuple[Any, ...]:
        if name == "render":
            frames = self.render()
            return frames if frames is not None else (None,) * self.num_envs
        if name == "get_state":
            check_started(self._unreset, "call('get_state')")
        return tuple(answer for answers in self._call([("call", name)] * len(self.sizes)) for answer in answers)

    def close_extras(self, **kwargs: Any) -> None:
        for pipe in self._pipes:
            try:
                pipe.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
        self._stop(JOIN_TIMEOUT_S if self.timeout is None else min(JOIN_TIMEOUT_S, self.timeout))
        self.template.close()

    # -- internals --------------------------------------------------------------------------------
    def _check_state_latents(self, state: Mapping[str, Any]) -> None:
        """Refuse, here, latents too far out for the map (:meth:`LatentSim.decode_state_latents` on the template's
        sim, all copies at once; a worker's refusal would close the env)."""
        sim = self.template.sim

        def tensor(value: Any) -> torch.Tensor:
            return torch.as_tensor(np.asarray(value, dtype=np.float64), dtype=sim.torch_dtype, device=sim.device)

        z_before = state.get("z_before")
        latents = {"z": state["z"], "z_before": state["z_prev"] if z_before is None else z_before}
        latents["z_prev"] = state["z_prev"]
        cond = None if sim.cond is None else tensor(state["cond"])
        params = {k: torch.as_tensor(np.asarray(v), device=sim.device) for k, v in state["params"].items()}
        sim.decode_state_latents({k: tensor(v) for k, v in latents.items()}, cond, params)

    def _check_state_shapes(self, state: Mapping[str, Any]) -> None:
        """Refuse a state of another env or shape, in the native env's order (:meth:`LatentSim.set_state`): its
        ``setting``, a missing key, ``cond`` [N, m], ``z`` and ``z_prev`` [N, d], ``model`` [N, d, d], ``carry``
        [N, k], ``loads`` [N, H, D] and each task parameter [N, ...] as the env's own (ValueError naming the key and
        both shapes)."""
        sim, n = self.template.sim, self.num_envs
        theirs, mine = state.get("setting"), sim.setting()
        if theirs is not None and not isinstance(theirs, Mapping):
            raise ValueError(f"state['setting'] must be the dict get_state() wrote, got {theirs!r:.80}")
        if theirs is not None and dict(theirs) != mine:
            differ = ", ".join(f"{k} {theirs.get(k)!r} (here {v!r})" for k, v in mine.items() if theirs.get(k) != v)
            raise ValueError(f"the state belongs to another env: {differ}")
        missing = {"z", "z_prev", "cond", "params"} - set(state)
        if missing:
            raise ValueError(f"state is missing {sorted(missing)}")

        def check(key: str, value: Any, want: tuple[int, ...] | None, finite: bool = False) -> None:
            """``want`` None: [N, ...]; ``finite``: also refuse NaN and inf (as the workers would)."""
            try:
                got = tuple(np.shape(value))
            except ValueError:  # ragged nesting
                got = None
            if got is None or (got != want if want is not None else not got or got[0] != n):
                expected = f"[{n}, ...]" if want is None else str(list(want))
                raise ValueError(f"state[{key!r}] must have shape {expected} (one row per copy), got {got}")
            if finite and not np.isfinite(np.asarray(value, dtype=np.float64)).all():
                raise ValueError(f"state[{key!r}] must be finite")

        d = sim.latent_dim
        if sim.cond is not None:
            check("cond", state["cond"], (n, *sim.cond.shape[1:]), finite=True)
            sim.check_cond(torch.as_tensor(np.asarray(state["cond"], dtype=np.float64), dtype=sim.cond.dtype))
        check("z", state["z"], (n, d), finite=True)
        check("z_prev", state["z_prev"], (n, d), finite=True)
        if state.get("z_before") is not None:
            check("z_before", state["z_before"], (n, d), finite=True)
        if state.get("model") is not None:
            check("model", state["model"], (n, d, d))
        if state.get("carry") is not None:
            check("carry", state["carry"], (n, *sim.carry.shape[1:]))
        if state.get("loads") is not None:
            check("loads", state["loads"], (n, *sim.loads.shape[1:]), finite=True)
        params = state["params"]
        if not isinstance(params, Mapping):
            return  # the workers refuse what is not a dict of arrays
        if not sim.params:
            self.template.reset(seed=0)  # one draw, for the parameters' keys and shapes
        if sim.params and set(params) != set(sim.params):
            raise ValueError(f"state['params'] must have keys {sorted(sim.params)}, got {sorted(params)}")
        for key, value in params.items():
            check(f"params.{key}", value, (n, *sim.params[key].shape[1:]) if key in sim.params else None)
            try:  # numbers, as the native env converts them (before the task's own checks read them)
                np.asarray(value, dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(
                    f"state['params.{key}'] must be a numeric array (one row per copy), got {value!r:.80}"
                ) from None

    def _blocks(self) -> list[slice]:
        return [slice(start, start + size) for start, size in zip(self.starts, self.sizes, strict=True)]

    def _call(self, requests: Sequence[tuple[str, Any]]) -> list[Any]:
        """Send request i to shard i, then gather every answer, in order.

        Anything that interrupts this (an exception in this process, a worker gone) leaves answers unread in
        the pipes, so the env is closed and its workers stopped before it propagates; a worker's own error
        closes the env too (its shards may now differ) and is raised here (:meth:`_gather`).
        """
        if self.closed or not self._pipes:
            raise ClosedVectorEnvError("this ShardedVectorEnv is closed")
        try:
            for shard, request in enumerate(requests):
                try:
                    self._pipes[shard].send(request)
                except (BrokenPipeError, OSError) as error:
                    code = self._processes[shard].exitcode
                    raise ShardError(
                        f"shard {shard}: the worker process exited (exit code {code}, {error!r}); the env is closed"
                    ) from error
            return self._gather(what=requests[0][0] if requests[0][0] != "call" else f"call({requests[0][1]!r})")
        except BaseException:
            self._abort()
            raise

    def _gather(self, hint: str = "", what: str | None = None) -> list[Any]:
        """Every shard's answer, in order. A worker's error is raised as itself (its traceback in a note; a
        :class:`ShardError` where it does not unpickle), a worker gone as :class:`ShardError` (with ``hint``), a
        request ``what`` (None: the start, never timed) not answered within :attr:`timeout` as
        :class:`ShardTimeoutError`."""
        answers, failures, first = [], [], None
        timeout = None if what is None else self.timeout
        deadline = None if timeout is None else time.monotonic() + timeout
        for shard, pipe in enumerate(self._pipes):
            if deadline is not None and not pipe.poll(max(0.0, deadline - time.monotonic())):
                # this shard did not answer in time (an answer just past the deadline does not change that)
                later = [i for i in range(shard + 1, len(self._pipes)) if not self._pipes[i].poll(0)]
                self._time_out(what, [shard, *later], failures)
            try:
                status, payload = pipe.recv()
            except (EOFError, OSError) as error:
                process = self._processes[shard]
                process.join(1.0)  # a worker that just exited: its exit code
                code = process.exitcode
                failures.append(f"shard {shard}: the worker process exited (exit code {code}, {error!r}){hint}")
                answers.append(None)
                continue
            if status != "ok":
                pickled, trace = payload
                failures.append(f"shard {shard}:\n{trace}")
                if first is None and pickled is not None:
                    try:
                        first = pickle.loads(pickled)
                    except Exception:
                        first = None
            answers.append(payload)
        if failures:
            self._abort()
            report = "a worker of the sharded env failed; the env is closed\n" + "\n".join(failures)
            if isinstance(first, Exception):
                first.add_note(report)
                raise first
            raise ShardError(report)
        return answers

    def _time_out(self, what: str | None, hung: Sequence[int], failures: Sequence[str] = ()) -> NoReturn:
        """Close the env and raise :class:`ShardTimeoutError`: the shards ``hung`` did not answer ``what``; the
        ``failures`` of the shards that answered with an error before are kept in the message."""
        copies = [
            f"copy {start}" if size == 1 else f"copies {start}-{start + size - 1}"
            for start, size in zip(self.starts, self.sizes, strict=True)
        ]
        names = ", ".join(f"shard {i} ({copies[i]}, worker pid {self._processes[i].pid})" for i in hung)
        self._abort()
        raise ShardTimeoutError(
            f"the sharded env's {what} timed out after {self.timeout:g} s: {names} did not answer (a worker stuck in "
            "a solve, stopped or deadlocked); the workers were stopped and the env is closed (its shards may be out "
            "of step). Make the env again, with a longer timeout (None waits for ever) if a request can take this "
            "long" + "".join(f"\nA worker failed before it: {failure}" for failure in failures)
        )

    def _abort(self) -> None:
        """Stop the workers now (answers may be unread) and mark the env closed."""
        self._stop(0.0)
        self.closed = True
        self.template.close()

    def _stop(self, timeout: float) -> None:
        """Join the workers within ``timeout`` seconds in all, terminate those still alive, kill those a terminate
        does not stop within :data:`KILL_AFTER_S` (a stopped process), close the pipes."""
        _join(self._processes, timeout)
        alive = [process for process in self._processes if process.is_alive()]
        for process in alive:
            process.terminate()
        _join(alive, KILL_AFTER_S)
        for process in alive:
            if process.is_alive():
                process.kill()
        _join(alive, JOIN_TIMEOUT_S)
        for pipe in self._pipes:
            pipe.close()
        self._pipes, self._processes = [], []


def _join(processes: Sequence[Any], timeout: float) -> None:
    """Join ``processes`` within ``timeout`` seconds in all."""
    deadline = time.monotonic() + timeout
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))


def _cpu_count() -> int:
    """CPUs this process may run on (its affinity, where the OS tells it), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)


def _join_states(parts: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The shards' batched states joined along the copies (None stays None; nested dicts key by key; the
    ``setting`` all shards share, once; a list, such as the copies' generator states, stays a list, as the native
    vector env's)."""
    joined: dict[str, Any] = {}
    for key, first in parts[0].items():
        if first is None or key == "setting":
            joined[key] = first
        elif isinstance(first, Mapping):
            joined[key] = _join_states([part[key] for part in parts])
        elif isinstance(first, list):
            joined[key] = [entry for part in parts for entry in part[key]]
        else:
            joined[key] = np.concatenate([np.asarray(part[key]) for part in parts])
    return joined


def _state_rows(state: Mapping[str, Any], rows: slice) -> dict[str, Any]:
    """A shard's block ``rows`` of a batched state (its ``setting`` as it is).

    Raises:
        ValueError: an entry that is not one value per copy (a number, where a batch of them was written).
    """
    block: dict[str, Any] = {}
    for key, value in state.items():
        if value is None or key == "setting":
            block[key] = value
        elif isinstance(value, Mapping):
            block[key] = _state_rows(value, rows)
        else:
            array = np.asarray(value)
            if array.ndim == 0:
                raise ValueError(f"state[{key!r}] must hold one entry per copy (get_state()'s), got {value!r:.60}")
            block[key] = array[rows]
    return block


def _merge_infos(infos: Sequence[dict[str, Any]], sizes: Sequence[int]) -> dict[str, Any]:
    """One vector info from the shards' (Gymnasium's layout: ``key`` [N] values and ``_key`` [N] masks).

    A key that only some shards report (e.g. ``final_obs`` where a copy ended) gets, in the others, an
    empty entry of its kind and a False mask; a nested info (``final_info``) is merged the same way, a shard
    without it giving its own step values under False masks (the native env's masked entries keep the step's value).
    """
    keys = list(dict.fromkeys(key for info in infos for key in info))
    out: dict[str, Any] = {}
    for key in keys:
        example = next(info[key] for info in infos if key in info)
        if isinstance(example, Mapping):
            out[key] = _merge_infos([info[key] if key in info else _hidden(info) for info in infos], sizes)
            continue
        parts = []
        for info, size in zip(infos, sizes, strict=True):
            if key in info:
                parts.append(np.asarray(info[key]))
            elif example.dtype == object:
                parts.append(np.empty(size, dtype=object))
            else:
                parts.append(np.zeros((size, *example.shape[1:]), dtype=example.dtype))
        out[key] = np.concatenate(parts)
    return out


def _hidden(info: Mapping[str, Any]) -> dict[str, Any]:
    """A shard's step values (its info less masks, nested infos and ``final_obs``) under False masks."""
    values = {k: v for k, v in info.items() if not (k.startswith("_") or isinstance(v, Mapping) or k == "final_obs")}
    return values | {f"_{k}": np.zeros(len(v), dtype=bool) for k, v in values.items()}


__all__ = [
    "JOIN_TIMEOUT_S",
    "KILL_AFTER_S",
    "ShardError",
    "ShardTimeoutError",
    "ShardedVectorEnv",
    "check_timeout",
    "shard_sizes",
]
