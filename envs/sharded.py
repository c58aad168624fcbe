"""A native vector env split over worker processes, so that a batch of copies uses several CPU cores.

One :class:`LatentVectorEnv` steps all its copies in one batched solve, in one process: its small
tensor ops do not spread over cores (torch's intra-op threads do not help them). With ``shards=P``,
``gymnasium.make_vec(id, num_envs=N, vectorization_mode="vector_entry_point", shards=P)`` builds a
:class:`ShardedVectorEnv`: P worker processes, each holding a native vector env of a contiguous block
of the N copies (sizes differ by at most one), stepped in parallel. Copy i is seeded ``seed + i`` as
in the native vector env, so the two are the same env (equal step for step where the solve is tight
enough that the batch composition does not move it; see ``tests/envs/test_sharded.py``). A worker
that fails raises in the caller (:class:`ShardError`, with the worker's traceback), and the env is closed.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import traceback
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from redsim.envs.base import check_action

if TYPE_CHECKING:
    from redsim.envs.base import LatentEnv

JOIN_TIMEOUT_S = 10.0
"""Seconds :meth:`ShardedVectorEnv.close` waits for a worker to exit before terminating it."""


class ShardError(RuntimeError):
    """A worker process of a :class:`ShardedVectorEnv` failed (its traceback is in the message)."""


def shard_sizes(num_envs: int, shards: int) -> list[int]:
    """Copies per shard: ``num_envs`` split into ``shards`` contiguous blocks differing by at most one.

    Raises:
        ValueError: ``shards`` not an integer in [1, num_envs].
    """
    if isinstance(shards, bool) or int(shards) != shards or not 1 <= shards <= num_envs:
        raise ValueError(f"shards must be an integer in [1, num_envs = {num_envs}], got {shards!r}")
    base, extra = divmod(int(num_envs), int(shards))
    return [base + (i < extra) for i in range(int(shards))]


def _worker(pipe: Connection, build: Callable[[int], VectorEnv], num_envs: int, threads: int) -> None:
    """Serve one shard: ``build(num_envs)``, its native vector env, then answer (command, payload) requests
    until "close"."""
    import torch

    torch.set_num_threads(threads)
    venv = None
    try:
        venv = build(num_envs)
        pipe.send(("ok", None))
        while True:
            command, payload = pipe.recv()
            if command == "close":
                break
            if command == "step":
                result: Any = venv.step(payload)
            elif command == "reset":
                result = venv.reset(seed=payload[0], options=payload[1])
            elif command == "render":
                result = venv.render()
            elif command == "get_state":
                result = venv.get_state()
            elif command == "set_state":
                result = venv.set_state(payload)
            else:
                raise ValueError(f"unknown command {command!r}")
            pipe.send(("ok", result))
    except (KeyboardInterrupt, EOFError):
        pass
    except Exception:  # the caller raises it (ShardError): nothing is lost in the worker
        pipe.send(("error", traceback.format_exc()))
    finally:
        if venv is not None:
            venv.close()
        pipe.close()


class ShardedVectorEnv(VectorEnv):
    """N copies of a latent env in P worker processes, each a native vector env of its block (module doc).

    Args:
        build: ``build(n)`` makes a native vector env of n copies (picklable: each worker gets a copy).
        template: One env of the same id and arguments, in this process, for spaces, metadata and attributes
            (it is never stepped).
        num_envs: N.
        shards: P, in [1, N].
        threads: torch intra-op threads per worker (None: the CPU count over P, at least 1).
        context: The multiprocessing start method (None: "forkserver" where available, else "spawn";
            "fork" is refused: torch's thread pools do not survive it).
        autoreset_mode: The mode ``build`` makes the native envs with (for ``metadata``).
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
    ) -> None:
        if int(num_envs) != num_envs or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        self.sizes = shard_sizes(int(num_envs), shards)
        if threads is None:
            threads = max(1, (os.cpu_count() or 1) // len(self.sizes))
        if isinstance(threads, bool) or int(threads) != threads or threads < 1:
            raise ValueError(f"threads must be an integer >= 1, got {threads!r}")
        if context is None:
            context = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        if context == "fork":
            raise ValueError("context 'fork' is not supported (torch's thread pools do not survive it): use 'spawn'")
        mode = AutoresetMode(autoreset_mode)
        self.template = template
        self.num_envs = int(num_envs)
        self.render_mode = self.template.render_mode
        self.metadata = {**self.template.metadata, "autoreset_mode": mode}
        self.single_action_space = self.template.action_space
        self.single_observation_space = self.template.observation_space
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.dt = self.template.dt
        self.starts = np.cumsum([0, *self.sizes])[:-1].tolist()
        self._pipes: list[Connection] = []
        self._processes: list[Any] = []
        self.closed = False
        ctx = mp.get_context(context)
        try:
            for size in self.sizes:
                parent, child = ctx.Pipe()
                process = ctx.Process(target=_worker, args=(child, build, size, int(threads)), daemon=True)
                process.start()
                child.close()
                self._pipes.append(parent)
                self._processes.append(process)
            self._gather()  # each worker's "ok" once its env is built
        except BaseException:
            self.close()
            raise

    # -- the VectorEnv API ----------------------------------------------------------------------
    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset all copies, or those of ``options["reset_mask"]`` (bool [N]); seed copy i with ``seed + i``."""
        super().reset(seed=seed if isinstance(seed, int) or seed is None else None)
        seeds: list[Any] | None = None
        if seed is not None:
            seeds = [seed + i for i in range(self.num_envs)] if isinstance(seed, int) else list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"need {self.num_envs} seeds, got {len(seeds)}")
        mask = None if not options or "reset_mask" not in options else np.asarray(options["reset_mask"], dtype=bool)
        if mask is not None and mask.shape != (self.num_envs,):
            raise ValueError(f"options['reset_mask'] must have shape ({self.num_envs},), got {mask.shape}")
        for i, block in enumerate(self._blocks()):
            shard_options = None if options is None else {**options}
            if mask is not None:
                shard_options["reset_mask"] = mask[block]  # type: ignore[index]
            self._send(i, "reset", (None if seeds is None else seeds[block], shard_options))
        results = self._gather()
        return np.concatenate([obs for obs, _ in results]), _merge_infos([info for _, info in results], self.sizes)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every copy with actions [N, A]: each shard its block, in parallel."""
        act = check_action(actions, self.action_space.shape)
        for i, block in enumerate(self._blocks()):
            self._send(i, "step", act[block])
        results = self._gather()
        obs, reward, terminated, truncated = (np.concatenate([r[k] for r in results]) for k in range(4))
        return obs, reward, terminated, truncated, _merge_infos([r[4] for r in results], self.sizes)

    def render(self) -> tuple[np.ndarray, ...] | None:
        """One RGB frame [H, W, 3] per copy ("rgb_array"), else None."""
        if self.render_mode != "rgb_array":
            return None
        for i in range(len(self.sizes)):
            self._send(i, "render", None)
        return tuple(frame for frames in self._gather() for frame in frames)

    def get_state(self) -> list[dict[str, Any]]:
        """The dynamic state of each shard (its native vector env's :meth:`LatentVectorEnv.get_state`)."""
        for i in range(len(self.sizes)):
            self._send(i, "get_state", None)
        return self._gather()

    def set_state(self, state: Sequence[dict[str, Any]]) -> None:
        """Restore what :meth:`get_state` returned (one state per shard)."""
        if len(state) != len(self.sizes):
            raise ValueError(f"need one state per shard ({len(self.sizes)}), got {len(state)}")
        for i, part in enumerate(state):
            self._send(i, "set_state", part)
        self._gather()

    def close_extras(self, **kwargs: Any) -> None:
        for pipe in self._pipes:
            try:
                pipe.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
        for process in self._processes:
            process.join(JOIN_TIMEOUT_S)
            if process.is_alive():
                process.terminate()
                process.join(JOIN_TIMEOUT_S)
        for pipe in self._pipes:
            pipe.close()
        self._pipes, self._processes = [], []
        self.template.close()

    # -- internals --------------------------------------------------------------------------------
    def _blocks(self) -> list[slice]:
        return [slice(start, start + size) for start, size in zip(self.starts, self.sizes, strict=True)]

    def _send(self, shard: int, command: str, payload: Any) -> None:
        if self.closed or not self._pipes:
            raise RuntimeError("this ShardedVectorEnv is closed")
        try:
            self._pipes[shard].send((command, payload))
        except (BrokenPipeError, OSError) as error:
            self.close()
            raise ShardError(f"shard {shard} is gone ({error!r}); the env is closed") from error

    def _gather(self) -> list[Any]:
        """Every shard's answer, in order; raise :class:`ShardError` (and close) if any failed."""
        answers, failures = [], []
        for shard, pipe in enumerate(self._pipes):
            try:
                status, payload = pipe.recv()
            except (EOFError, OSError) as error:
                status, payload = "error", f"the worker process exited ({error!r})"
            if status != "ok":
                failures.append(f"shard {shard}:\n{payload}")
            answers.append(payload)
        if failures:
            self.close()
            raise ShardError("a worker of the sharded env failed; the env is closed\n" + "\n".join(failures))
        return answers


def _merge_infos(infos: Sequence[dict[str, Any]], sizes: Sequence[int]) -> dict[str, Any]:
    """One vector info from the shards' (Gymnasium's layout: ``key`` [N] values and ``_key`` [N] masks).

    A key that only some shards report (e.g. ``final_obs`` where a copy ended) gets, in the others, an
    empty entry of its kind and a False mask.
    """
    keys = list(dict.fromkeys(key for info in infos for key in info))
    out: dict[str, Any] = {}
    for key in keys:
        example = next(info[key] for info in infos if key in info)
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


__all__ = ["JOIN_TIMEOUT_S", "ShardError", "ShardedVectorEnv", "shard_sizes"]
