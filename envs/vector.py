"""The native vector env: N copies of a latent env advanced by one batched stepper call per substep.

``gymnasium.make_vec("RedSim/Chain-v0", num_envs=N, vectorization_mode="vector_entry_point")``
builds a :class:`LatentVectorEnv`. Copy i draws its episodes from its own generator, seeded
``seed + i`` by ``reset(seed=seed)`` exactly as a single env seeded ``seed + i``, so the
vector env equals N single envs step for step, to the solve's tolerance (a float32 solve stops at a
relative force balance of 1e-6, and another batch composition lands elsewhere inside it: ~5e-4 in z
after a step, which grows under random actions on MiniChain-v0 to 0.1 in z after 4 steps and saturates near 0.3
(1.7 cm at the handle) by 8, every step converged; in float64 (``dtype="float64"``) they agree to
~1e-6 over the steps the tests take; docs/envs.md, "From the README: how far copies, batches and versions agree").
Autoreset follows Gymnasium: by default
``AutoresetMode.NEXT_STEP`` (the step after a copy ends resets it and ignores its action;
reward 0, not terminated); ``AutoresetMode.SAME_STEP`` resets in the same step and puts the
last observation and info in ``info["final_obs"]`` (an object array, None for the other copies) and
``info["final_info"]`` (a dict of [N] arrays with ``_key`` masks), as Gymnasium's sync vector env: the ended
copies' entries of the top-level keys are masked out (their ``_key`` False). There a masked entry keeps the ended
step's value (the benches count every copy's solver work), where the sync env holds zeros; with ``NEXT_STEP`` the
solver skips the copies the step resets (the sync env calls their ``reset``, not their ``step``), and their
step-only entries (``converged``, ``diverged``, ``energy``, ...) hold zeros, as the sync env's.
For stable-baselines3 use :class:`redsim.envs.sb3.SB3VecEnv`.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from gymnasium.wrappers import TimeLimit
from torch import Tensor

from redsim.envs.base import (
    NO_HUMAN,
    NO_RENDER_MODE,
    VECTOR_RENDER_MODES,
    LatentEnv,
    check_action,
    copy_seeds,
    on_env_threads,
    restored_generator,
    state_row,
    with_fitted_map,
)
from redsim.envs.sharded import ShardedVectorEnv, check_timeout, shard_sizes
from redsim.envs.vector_api import ClosedVectorEnvError, SharedCopies, check_started, episode_clock, reset_mask
from redsim.threads import torch_threads


class LatentVectorEnv(SharedCopies, VectorEnv):
    """N copies of a latent env in one batched simulation.

    Args:
        env: A single env whose scene, subspace, task and settings every copy uses.
        num_envs: N.
        max_episode_steps: Truncate each copy's episode after this many steps (None: never).
        autoreset_mode: ``AutoresetMode.NEXT_STEP`` (Gymnasium's default), ``SAME_STEP`` or ``DISABLED`` (the caller
            resets ended copies with ``options["reset_mask"]``).

    Raises:
        TypeError: ``env`` is not a :class:`LatentEnv` (a wrapped one: pass ``env.unwrapped``; its wrappers would
            not act on the copies, and a ``TimeLimit``'s length goes in ``max_episode_steps``).
        ValueError: a bad count or autoreset mode, an env with ``render_mode="human"``
            (:data:`redsim.envs.base.NO_HUMAN`), and (in :meth:`step`) a bad action batch.
    """

    def __init__(
        self,
        env: LatentEnv,
        num_envs: int,
        *,
        max_episode_steps: int | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
    ) -> None:
        mode = check_vector_args(num_envs, max_episode_steps, autoreset_mode)
        check_latent_env(env)
        if env.render_mode == "human":
            raise ValueError(NO_HUMAN)
        self.num_envs = int(num_envs)
        self.threads = env.threads  # torch threads it computes on (the single env's, :mod:`redsim.threads`)
        with torch_threads(self.threads):  # the copies' sim: its rest solve, a task's settling
            self.sim = env.sim.clone(self.num_envs, copy.deepcopy(env.task))
        self.template = env
        self.render_mode = env.render_mode
        self.metadata = {**env.metadata, "render_modes": list(VECTOR_RENDER_MODES), "autoreset_mode": mode}
        self.single_action_space = env.action_space
        self.single_observation_space = env.observation_space
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.observation_structure = env.observation_structure
        self.max_episode_steps = None if max_episode_steps is None else int(max_episode_steps)
        self.dt = env.dt
        self.frame_skip = env.frame_skip
        self._rngs: list[np.random.Generator] = [seeding.np_random()[0] for _ in range(self.num_envs)]
        self._elapsed = np.zeros(self.num_envs, dtype=np.int64)
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        self._unreset = np.ones(self.num_envs, dtype=bool)  # copies never reset (nor restored by set_state)
        self._view: Any = None

    @on_env_threads
    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset all copies, or those of ``options["reset_mask"]`` (bool [N]); seed copy i with ``seed + i``, or with
        ``seed[i]`` for a sequence (None: copy i keeps its generator, as in Gymnasium's sync vector env). The other
        options set parts of every reset copy's draw, as in the single env's ``reset`` (autoresets draw them).

        The seed of every copy being reset is checked (Gymnasium's rule: an int >= 0, else
        ``gymnasium.error.Error``; the others' are not used) before any copy's generator is replaced, so a refused
        seed changes nothing."""
        self._check_open()
        given = reset_mask(options, self.num_envs)
        chosen = self.sim.episode_options(options, vector=True)
        mask = np.ones(self.num_envs, dtype=bool) if given is None else given
        own, seeds = copy_seeds(seed, self.num_envs)
        rows = [int(i) for i in np.nonzero(mask)[0]]
        fresh = {i: seeding.np_random(seeds[i])[0] for i in rows if seeds is not None and seeds[i] is not None}
        super().reset(seed=own)
        for i, generator in fresh.items():
            self._rngs[i] = generator
        self._unreset[mask] = True  # until the draws succeed (a task may refuse an option's value)
        self.sim.reset_rows(rows, [self._rngs[i] for i in rows], chosen)
        self._elapsed[mask] = 0
        self._autoreset[mask] = False
        self._unreset[mask] = False
        self._unframe()
        return self.sim.observe(), _with_masks(self.sim.state_info(mask, start=True), mask)

    @on_env_threads
    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every copy with actions [N, A] in one batched simulation step (module doc for autoreset)."""
        self._check_open()
        check_started(self._unreset)
        mode = self.metadata["autoreset_mode"]
        if mode == AutoresetMode.DISABLED and self._autoreset.any():
            raise RuntimeError(
                f"copies {np.nonzero(self._autoreset)[0].tolist()} ended and autoreset_mode is DISABLED: reset them "
                "with reset(options={'reset_mask': mask}) before the next step"
            )
        act = check_action(actions, self.action_space.shape)
        saved = (
            self.sim.snapshot(),
            self._elapsed.copy(),
            self._autoreset.copy(),
            [g.bit_generator.state for g in self._rngs],
        )
        try:
            return self._step(act, mode)
        except BaseException:  # atomic: an interrupt in an autoreset or the observation leaves every copy as it was
            sim, self._elapsed, self._autoreset, rngs = saved
            self.sim.restore(sim)
            for generator, state in zip(self._rngs, rngs, strict=True):
                generator.bit_generator.state = state
            raise

    def _step(
        self, act: np.ndarray, mode: AutoresetMode
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        # NEXT_STEP: the copies that ended last step are reset, not stepped (the solver skips them)
        restart = self._autoreset.copy() if mode == AutoresetMode.NEXT_STEP else np.zeros(self.num_envs, bool)
        reward, terminated, info = self.sim.step(act, active=~restart if restart.any() else None)
        self._elapsed += 1
        truncated = np.zeros(self.num_envs, dtype=bool)
        if self.max_episode_steps is not None:
            truncated = self._elapsed >= self.max_episode_steps
        if mode == AutoresetMode.DISABLED:  # the caller resets ended copies (reset with options["reset_mask"])
            self._autoreset = terminated | truncated
            return self.sim.observe(), reward, terminated, truncated, _with_masks(info, np.ones(self.num_envs, bool))
        if mode == AutoresetMode.NEXT_STEP:
            if restart.any():
                rows = [int(i) for i in np.nonzero(restart)[0]]
                self.sim.reset_rows(rows, [self._rngs[i] for i in rows])
                reward[restart], terminated[restart], truncated[restart] = 0.0, False, False
                self._elapsed[restart] = 0
            obs = self.sim.observe()
            # the restarted copies were not stepped: their slots hold zeros, as the sync env's (a review read a
            # diverged copy's flag and energy twice when they held a discarded step's), then their reset info
            stepped = {
                key: np.where(_rows(restart, value.ndim), np.zeros_like(value), value) for key, value in info.items()
            }
            infos = _with_reset_info(_with_masks(stepped, ~restart), self.sim.state_info(restart, start=True), restart)
        else:
            # as Gymnasium's sync vector env: an ended copy's step info only in ``final_info`` (batched, masked)
            done = terminated | truncated
            infos = _with_masks(info, ~done)
            obs = self.sim.observe()
            if done.any():
                rows = [int(i) for i in np.nonzero(done)[0]]
                final_obs = np.full(self.num_envs, None, dtype=object)
                for i in rows:
                    final_obs[i] = obs[i].copy()
                final_info = _with_masks({k: v.copy() for k, v in info.items()}, done)
                self.sim.reset_rows(rows, [self._rngs[i] for i in rows])
                self._elapsed[done] = 0
                obs = self.sim.observe()
                infos = _with_reset_info(infos, self.sim.state_info(done, start=True), done)
                infos.update(
                    final_obs=final_obs, _final_obs=done.copy(), final_info=final_info, _final_info=done.copy()
                )
        self._autoreset = (terminated | truncated) if mode == AutoresetMode.NEXT_STEP else self._autoreset
        return obs, reward, terminated, truncated, infos

    @property
    def autoresetting(self) -> np.ndarray:
        """Copies [N] (bool) that the next step resets and whose action it ignores (``NEXT_STEP``: their episode
        ended in the last step; ``DISABLED``: ended and not reset yet, so the next step raises); all False with
        ``SAME_STEP``."""
        return self._autoreset.copy()

    @on_env_threads
    def render(self) -> tuple[np.ndarray, ...] | None:
        """One RGB frame [H, W, 3] per copy ("rgb_array"), else None (with a warning, as a single env's).

        Raises:
            gymnasium.error.ResetNeeded: a copy was never reset (nor restored by :meth:`set_state`), as Gymnasium's
                sync vector env's copies refuse it (their ``OrderEnforcing``).
            ClosedVectorEnvError: after :meth:`close`, as the sharded env raises (it drew on as if open).
        """
        self._check_open()
        if self.render_mode != "rgb_array":
            gym.logger.warn(NO_RENDER_MODE)
            return None
        check_started(self._unreset, "render()")
        rows, camera = range(self.num_envs), self.template._camera
        sim = self.sim if camera.get("track", False) else self.template.sim  # fixed: the single env's camera
        self._view = sim.framed_view(self._view, *self.template._render_size, camera, rows)
        # one batched drawing of every copy; each frame its own array (a kept frame must not hold all N)
        return tuple(np.array(frame) for frame in self.sim.draw_rows(self._view, rows))

    def get_state(self) -> dict[str, Any]:
        """The batched dynamic state (:meth:`redsim.envs.base.LatentSim.get_state`), each copy's episode clock,
        ``elapsed_steps`` [N] (int) and ``autoresetting`` [N] (bool), and each copy's generator state ``rngs`` (what
        its autoresets draw), so a restored state steps exactly alike, episode ends and autoresets included.

        Raises:
            gymnasium.error.ResetNeeded: a copy was never reset (nor restored by :meth:`set_state`).
            ClosedVectorEnvError: after :meth:`close`, as the sharded env raises.
        """
        self._check_open()
        check_started(self._unreset, "get_state()")
        clock = {"elapsed_steps": self._elapsed.copy(), "autoresetting": self._autoreset.copy()}
        return {**self.sim.get_state(), **clock, "rngs": [g.bit_generator.state for g in self._rngs]}

    @on_env_threads
    def set_state(self, state: dict[str, Any]) -> None:
        """Restore :meth:`get_state`'s state. Without the episode clock (a batched state of the simulation alone),
        every copy's episode count starts at 0 and none is pending an autoreset.

        Raises:
            ValueError: a state of another env or batch, a task parameter ``reset(options=...)`` would refuse
                (:meth:`redsim.envs.base.LatentSim.set_state`), a clock or ``rngs`` of another length, an
                ``elapsed_steps`` entry that is not a whole number >= 0 (NaN, 2.5) or an ``autoresetting`` one other
                than True/False (:func:`~redsim.envs.vector_api.episode_clock`), or an ``rngs`` entry that is not a
                NumPy generator state (each may be of any bit generator: PCG64, Philox, ...);
                nothing changes then.
            ClosedVectorEnvError: after :meth:`close`, as the sharded env raises.
        """
        self._check_open()
        elapsed, pending = episode_clock(state, self.num_envs)
        rngs = state.get("rngs")
        if rngs is not None and len(rngs) != self.num_envs:
            raise ValueError(f"state['rngs'] must hold {self.num_envs} generator states, got {len(rngs)}")
        generators = None if rngs is None else [restored_generator(None, saved) for saved in rngs]  # checked first
        self.sim.set_state({k: v for k, v in state.items() if k not in ("elapsed_steps", "autoresetting", "rngs")})
        if generators is not None:
            self._rngs = generators
        self._elapsed[:] = elapsed
        self._autoreset[:] = pending & (self.metadata["autoreset_mode"] != AutoresetMode.SAME_STEP)
        self._unreset[:] = False
        self._unframe()

    def frame_on(self, q: Tensor, points: np.ndarray | None) -> None:
        """Frame the next renders of a tracking camera on configuration q [n] and the points [P, D] (or None): the
        sharded env's view of all its shards' copies (:meth:`redsim.envs.sharded.ShardedVectorEnv.render`), so each
        shard draws what the native env of all the copies draws."""
        self._view = self.sim.view_on(*self.template._render_size, self.template._camera, q, points)

    def _unframe(self) -> None:
        """A tracking camera frames the picture anew at the next render after a ``reset`` or ``set_state`` call, as the
        single env's does, so a state draws the same picture whatever came before it (the fixed camera never moves)."""
        if self.template._camera.get("track", False):
            self._view = None

    @on_env_threads
    def _per_copy(self, name: str) -> tuple[Any, ...]:
        self._check_open()  # every per-copy call (call("configuration"), ...) after close(), as the sharded env
        if name == "render":
            frames = self.render()
            return frames if frames is not None else (None,) * self.num_envs
        if name == "trimeshes":
            return tuple(self.sim.trimeshes(i) for i in range(self.num_envs))
        if name == "get_state":
            check_started(self._unreset, "call('get_state')")
            state = self.sim.get_state()  # each copy's as a single env's: with its generator
            return tuple({**state_row(state, i), "rng": g.bit_generator.state} for i, g in enumerate(self._rngs))
        q = self.sim.positions(self.sim.z).detach().cpu().numpy()  # configuration
        return tuple(q[i] for i in range(self.num_envs))

    def close_extras(self, **kwargs: Any) -> None:
        if hasattr(self, "template"):  # not where the constructor refused its arguments (garbage collection closes it)
            self.template.close()

    def _check_open(self) -> None:
        """Refuse a call after :meth:`close`, as the sharded env does (a closed env stepped on as if open)."""
        if self.closed:
            raise ClosedVectorEnvError("this LatentVectorEnv is closed")


def check_latent_env(env: Any) -> None:
    """Refuse a vector env's template that is not a :class:`LatentEnv`, naming the fix for a wrapped one.

    Raises:
        TypeError: ``env`` is a wrapper (pass ``env.unwrapped``: the wrappers would be dropped silently; a
            ``TimeLimit``'s length is named as the ``max_episode_steps`` to pass) or not an env of redsim's.
    """
    if isinstance(env, LatentEnv):
        return
    if isinstance(env, gym.Wrapper) and isinstance(env.unwrapped, LatentEnv):
        limit, wrapper = "", env
        while isinstance(wrapper, gym.Wrapper):
            if isinstance(wrapper, TimeLimit):
                limit = f"; for its TimeLimit pass max_episode_steps={wrapper._max_episode_steps}"
            wrapper = wrapper.env
        raise TypeError(
            f"the vector env takes the LatentEnv itself, got it wrapped in {env}: pass env.unwrapped (its wrappers "
            f"would not act on the copies{limit})"
        )
    raise TypeError(f"the vector env takes a redsim LatentEnv, got {type(env).__name__}")


def check_vector_args(
    num_envs: int, max_episode_steps: int | None, autoreset_mode: AutoresetMode | str
) -> AutoresetMode:
    """The autoreset mode, after checking a vector env's arguments.

    Raises:
        ValueError: a bad copy count, episode length or autoreset mode.
    """
    try:
        whole = int(num_envs) == num_envs and not isinstance(num_envs, (bool, str))
    except (TypeError, ValueError, OverflowError):  # NaN, inf, None
        whole = False
    if not whole or num_envs < 1:
        raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
    mode = AutoresetMode(autoreset_mode)
    if max_episode_steps is not None and (int(max_episode_steps) != max_episode_steps or max_episode_steps < 1):
        raise ValueError(f"max_episode_steps must be None or an integer >= 1, got {max_episode_steps!r}")
    return mode


def _with_reset_info(infos: dict[str, Any], reset: dict[str, np.ndarray], rows: np.ndarray) -> dict[str, Any]:
    """``infos`` with the reset info [N, ...] of the copies ``rows`` [N] (bool) that were just reset, as
    Gymnasium's sync vector env puts a reset env's info in its slot."""
    if not rows.any():
        return infos
    out = dict(infos)
    for key, value in reset.items():
        if key in out:
            merged = out[key].copy()
            merged[rows] = value[rows]
            out[key], out[f"_{key}"] = merged, out[f"_{key}"] | rows
        else:
            out[key], out[f"_{key}"] = value, rows.copy()
    return out


def _rows(rows: np.ndarray, ndim: int) -> np.ndarray:
    """The copies ``rows`` [N] (bool) shaped to broadcast against an info value of ``ndim`` dimensions [N, ...]."""
    return rows.reshape(-1, *([1] * (ndim - 1)))


def _with_masks(info: dict[str, np.ndarray], mask: np.ndarray) -> dict[str, Any]:
    """``info`` with a ``_key`` mask [N] per key; no keys where no copy reports this step (as SyncVectorEnv's)."""
    if not mask.any():
        return {}
    out: dict[str, Any] = {}
    for key, value in info.items():
        out[key] = value
        out[f"_{key}"] = mask.copy()
    return out


def _native(
    create: Callable[..., LatentEnv],
    max_episode_steps: int | None,
    autoreset_mode: AutoresetMode | str,
    num_envs: int,
) -> LatentVectorEnv:
    """A :class:`LatentVectorEnv` of ``num_envs`` copies of the env ``create()`` makes (module level, and ``create``
    a ``functools.partial`` with keyword arguments: a shard's worker process unpickles it)."""
    return LatentVectorEnv(create(), num_envs, max_episode_steps=max_episode_steps, autoreset_mode=autoreset_mode)


def registered_steps(env_class: type[LatentEnv]) -> int | None:
    """The ``max_episode_steps`` of the ``RedSim/`` ids registered with ``env_class`` (None: not registered, or ids
    disagree); read from Gymnasium's registry, which ``import redsim.envs`` fills (this module imports no package
    above it: redsim.envs imports it through :func:`redsim.envs.make_vec`)."""
    entry = f"redsim.envs.{env_class.__module__.rsplit('.', 1)[-1]}:{env_class.__name__}"
    steps = {
        spec.max_episode_steps
        for spec in gym.registry.values()
        if spec.namespace == "RedSim" and spec.entry_point == entry
    }
    return steps.pop() if len(steps) == 1 else None


def vector_of(
    create: functools.partial[LatentEnv],
    num_envs: int,
    max_episode_steps: int | None,
    autoreset_mode: AutoresetMode | str,
    shards: int,
    timeout: float | None = None,
) -> LatentVectorEnv | ShardedVectorEnv:
    """``num_envs`` copies of the env ``create()`` makes (a partial with keyword arguments, ``render_mode`` among
    them if any), in one :class:`LatentVectorEnv` or, with ``shards`` P > 1, a
    :class:`redsim.envs.sharded.ShardedVectorEnv` of P worker processes, each request waiting at most ``timeout``
    seconds for them (None: for ever); ``max_episode_steps`` None: no limit.

    Raises:
        ValueError: a bad render mode, ``timeout`` (:func:`~redsim.envs.sharded.check_timeout`, or one with
            ``shards`` 1: no worker to wait for), copy count, episode length, autoreset mode or shard count.
    """
    if check_timeout(timeout) is not None and shards == 1:
        raise ValueError(
            f"timeout={timeout!r} bounds the wait for a sharded env's worker processes, and shards=1 makes the native "
            "vector env, which steps in this process: drop timeout, or give shards > 1"
        )
    render = create.keywords.get("render_mode")
    if render == "human":  # before any env or worker is made (or a display is asked for)
        raise ValueError(NO_HUMAN)
    if render is not None and render not in VECTOR_RENDER_MODES:
        raise ValueError(
            f"a vector env's render_mode must be None or 'rgb_array' (one frame per copy; keep a list of them "
            f"yourself, or use vectorization_mode='sync' for Gymnasium's per-copy wrappers), got {render!r}"
        )
    build = functools.partial(_native, create, max_episode_steps, autoreset_mode)
    if shards == 1:
        return build(num_envs)
    mode = check_vector_args(num_envs, max_episode_steps, autoreset_mode)  # before any env or worker is made
    shard_sizes(num_envs, shards)
    template = create()
    carried = template.unbacked_subspace()
    if carried is not None:  # fitted in memory here: the workers take the map instead of fitting it again
        carrying = functools.partial(create.func, *create.args, **with_fitted_map(create.keywords, carried))
        build = functools.partial(_native, carrying, max_episode_steps, autoreset_mode)
    return ShardedVectorEnv(
        build, template, num_envs, shards, autoreset_mode=mode, max_episode_steps=max_episode_steps, timeout=timeout
    )


def episode_limit(max_episode_steps: int | None, default: int | None) -> int | None:
    """``max_episode_steps`` as ``gym.make`` reads it: None is ``default`` (the id's length), -1 no limit.

    Raises:
        ValueError: anything else but an integer >= 1.
    """
    if max_episode_steps is None:
        return default
    if max_episode_steps == -1:
        return None
    if isinstance(max_episode_steps, bool) or int(max_episode_steps) != max_episode_steps or max_episode_steps < 1:
        raise ValueError(
            f"max_episode_steps must be None (the id's length), -1 (no limit) or an integer >= 1, got "
            f"{max_episode_steps!r}"
        )
    return int(max_episode_steps)


def vector_entry(env_class: type[LatentEnv]) -> Callable[..., LatentVectorEnv | ShardedVectorEnv]:
    """The ``vector_entry_point`` of a registered env class (Gymnasium passes ``num_envs`` and the spec's kwargs)."""

    def make_vec(
        num_envs: int = 1,
        *,
        max_episode_steps: int | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        shards: int = 1,
        timeout: float | None = None,
        **kwargs: Any,
    ) -> LatentVectorEnv | ShardedVectorEnv:
        limit = episode_limit(max_episode_steps, registered_steps(env_class))
        return vector_of(functools.partial(env_class, **kwargs), num_envs, limit, autoreset_mode, shards, timeout)

    make_vec.__doc__ = (
        f"A :class:`LatentVectorEnv` of ``num_envs`` copies of :class:`{env_class.__name__}`; with ``shards`` P > 1,"
        " a :class:`redsim.envs.sharded.ShardedVectorEnv` of them in P worker processes, whose requests wait at most"
        " ``timeout`` seconds for the workers (None: for ever). ``max_episode_steps`` as in ``gym.make``: None is the"
        " registered id's episode length, -1 no limit."
    )
    return make_vec


__all__ = ["LatentVectorEnv", "check_vector_args", "episode_limit", "vector_entry", "vector_of"]
