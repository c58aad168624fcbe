"""Gymnasium's per-copy vector API (``get_attr``, ``set_attr``, ``call``, ``reset_mask``) for redsim's vector envs.

The copies of a :class:`redsim.envs.vector.LatentVectorEnv` (or of a sharded one) are rows of one batched
simulation built from one template env, so they share every setting: ``get_attr`` answers the template's value
for each copy, ``set_attr`` is refused (make the vector env with the setting instead), and ``call`` answers the
per-copy methods from the batched state (:data:`PER_COPY_CALLS`), a goal env's pure reward functions
(:data:`SHARED_METHODS`) and plain attributes, as ``SyncVectorEnv.call`` does.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium.envs.registration import EnvSpec
from gymnasium.error import ClosedEnvironmentError, ResetNeeded

if TYPE_CHECKING:
    from redsim.envs.base import LatentEnv


class ClosedVectorEnvError(ClosedEnvironmentError, RuntimeError):
    """A call on a closed redsim vector env: Gymnasium's ``ClosedEnvironmentError`` (what its ``AsyncVectorEnv``
    raises), and a RuntimeError as before."""


SHARED_METHODS = ("compute_reward", "compute_terminated", "compute_truncated")
"""Methods answered for every copy by the template: pure functions of their arguments (a goal env's)."""

PER_COPY_CALLS = ("get_state", "configuration", "render", "trimeshes")
"""Methods ``call`` answers copy by copy, from the batched simulation (no arguments)."""

VECTOR_KWARGS = (
    "num_envs",
    "vectorization_mode",
    "vector_kwargs",
    "wrappers",
    "max_episode_steps",
    "autoreset_mode",
    "shards",
    "timeout",
)
"""Keys of a vector env's ``spec.kwargs`` that are the vector env's, not its copies' (``gym.make_vec``'s and the
vector entry point's)."""

STATEFUL = ("sim", "np_random", "np_random_seed", "reset", "step", "set_state", "close")
"""The template's attributes that are not its copies' (its never-stepped state and generator, its own calls)."""


class SharedCopies:
    """``get_attr`` / ``set_attr`` / ``call`` of a vector env whose copies share ``template``'s settings."""

    template: LatentEnv
    num_envs: int
    max_episode_steps: int | None
    single_observation_space: Any
    single_action_space: Any
    _spec: EnvSpec | None = None

    @property
    def spec(self) -> EnvSpec | None:
        """The spec ``gym.make_vec`` gave the vector env, its kwargs in JSON form
        (:func:`redsim.envs.base.json_spec`: ``spec.to_json()`` works)."""
        return self._spec

    @spec.setter
    def spec(self, spec: EnvSpec | None) -> None:
        from redsim.envs.base import json_spec

        self._spec = json_spec(spec)

    def get_attr(self, name: str) -> tuple[Any, ...]:
        """Each copy's ``name``: the single observation or action space, its ``spec`` (:meth:`single_spec`), or the
        setting of the env every copy runs (``dt``, ``metadata``, ``scene``, ``task`` settings, ...).

        Raises:
            AttributeError: an attribute that holds a copy's state (:data:`STATEFUL`, :data:`PER_COPY_CALLS`: use
                ``call(name)``) or one the env does not have.
        """
        if name in ("observation_space", "action_space"):
            value = getattr(self, f"single_{name}")
        elif name == "spec":
            value = self.single_spec()
        elif name in PER_COPY_CALLS:
            raise AttributeError(f"{name!r} is a method: call({name!r}) answers it copy by copy")
        elif name in STATEFUL:
            raise AttributeError(
                f"{name!r} is not one value per copy here (the copies are rows of one batched simulation); "
                f"call() answers {list(PER_COPY_CALLS)} copy by copy, get_state() the whole batch (its 'rngs': each "
                "copy's generator state)"
            )
        else:
            value = getattr(self.template, name)
        return tuple(value for _ in range(self.num_envs))

    def single_spec(self) -> EnvSpec | None:
        """A copy's spec, as ``gym.make(id, **kwargs)`` of one copy gives it (Gymnasium's sync vector env answers
        each copy's): the vector env's spec without the vector arguments (:data:`VECTOR_KWARGS`), with the copies'
        ``max_episode_steps``; the template's spec where the vector env has none (not made by ``gym.make_vec``)."""
        if self.spec is None:
            return self.template.spec
        spec = copy.deepcopy(self.spec)
        spec.kwargs = {k: v for k, v in spec.kwargs.items() if k not in VECTOR_KWARGS}
        spec.max_episode_steps = self.max_episode_steps
        return spec

    def set_attr(self, name: str, values: Any) -> None:
        raise AttributeError(
            f"cannot set {name!r} per copy: the copies share one simulation and its settings; make the vector env "
            "with the setting instead (gym.make_vec(ENV_ID, num_envs=N, KEY=VALUE))"
        )

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """Each copy's ``name(*args, **kwargs)`` (:data:`PER_COPY_CALLS`, :data:`SHARED_METHODS`), or its attribute.

        Raises:
            AttributeError: another method (the copies have no methods of their own), or a state attribute.
            TypeError: arguments to a per-copy method.
        """
        if name in PER_COPY_CALLS:
            if args or kwargs:
                raise TypeError(f"call({name!r}) takes no arguments")
            return self._per_copy(name)
        value = self.get_attr(name)[0]
        if not callable(value):
            return tuple(value for _ in range(self.num_envs))
        if name not in SHARED_METHODS:
            raise AttributeError(
                f"call({name!r}): the copies share one simulation and have no methods of their own; call answers "
                f"{list(PER_COPY_CALLS + SHARED_METHODS)} and attributes"
            )
        result = value(*args, **kwargs)
        return tuple(result for _ in range(self.num_envs))

    def _per_copy(self, name: str) -> tuple[Any, ...]:
        """The answer of copy 0 .. N-1 to the method ``name`` of :data:`PER_COPY_CALLS`."""
        raise NotImplementedError


class NotStarted(ResetNeeded, RuntimeError):
    """A call on a vector env whose copies were not all reset: Gymnasium's ``ResetNeeded``, as its sync and async
    envs and a single env raise, and a ``RuntimeError``, as a step raised before stop 50."""


def check_started(unreset: np.ndarray, call: str = "step()") -> None:
    """Refuse ``call`` while copies [N] (bool) were never reset, as Gymnasium's sync env refuses a step (a masked
    first reset leaves the others unstarted).

    Raises:
        NotStarted: naming the copies (a ``gymnasium.error.ResetNeeded``).
    """
    if unreset.all():
        raise NotStarted(f"call reset() before {call}")
    if unreset.any():
        raise NotStarted(
            f"call reset() before {call}: copies {np.nonzero(unreset)[0].tolist()} were never reset "
            "(or their reset failed)"
        )


def reset_mask(options: dict[str, Any] | None, num_envs: int) -> np.ndarray | None:
    """``options["reset_mask"]`` checked as Gymnasium's sync vector env does (None: reset every copy).

    Raises:
        TypeError: not a NumPy bool array.
        ValueError: not of shape [N], or no copy in it.
    """
    if not options or "reset_mask" not in options:
        return None
    mask = options["reset_mask"]
    if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_:
        raise TypeError(f"options['reset_mask'] must be a numpy array of dtype np.bool_, got {mask!r:.80}")
    if mask.shape != (num_envs,):
        raise ValueError(f"options['reset_mask'] must have shape ({num_envs},), got {mask.shape}")
    if not mask.any():
        raise ValueError("options['reset_mask'] must reset at least one copy (all False)")
    return mask


def episode_clock(state: Mapping[str, Any], num_envs: int) -> tuple[np.ndarray, np.ndarray]:
    """A vector state's episode clock, checked: ``elapsed_steps`` [N] (int64) and ``autoresetting`` [N] (bool); zeros
    and False where the state holds none (a batched state of the simulation alone).

    Raises:
        ValueError: another shape, a step count that is not a whole number >= 0 (NaN, inf or 2.5 would be cast to
            a count that never reaches the episode limit, or to another one), or a flag other than True/False (1/0).
    """
    elapsed = np.asarray(state.get("elapsed_steps", np.zeros(num_envs, np.int64)))
    pending = np.asarray(state.get("autoresetting", np.zeros(num_envs, dtype=bool)))
    if elapsed.shape != (num_envs,) or pending.shape != (num_envs,):
        raise ValueError(
            f"state['elapsed_steps'] and state['autoresetting'] must have shape ({num_envs},), "
            f"got {elapsed.shape} and {pending.shape}"
        )
    whole = elapsed.dtype.kind in "iu"
    if elapsed.dtype.kind == "f":
        with np.errstate(invalid="ignore"):
            whole = bool((np.isfinite(elapsed) & (elapsed == np.floor(elapsed)) & (elapsed < 2.0**62)).all())
    if not whole or (elapsed < 0).any():
        raise ValueError(f"state['elapsed_steps'] must hold whole step counts >= 0, got {elapsed.tolist()}")
    flags = pending.dtype.kind == "b" or (pending.dtype.kind in "iuf" and bool(np.isin(pending, (0, 1)).all()))
    if not flags:
        raise ValueError(f"state['autoresetting'] must hold True/False per copy, got {pending.tolist()}")
    return elapsed.astype(np.int64), pending.astype(bool)


__all__ = [
    "PER_COPY_CALLS",
    "SHARED_METHODS",
    "STATEFUL",
    "VECTOR_KWARGS",
    "ClosedVectorEnvError",
    "NotStarted",
    "SharedCopies",
    "check_started",
    "episode_clock",
    "reset_mask",
]
