"""The in-memory and on-disk cache of full-space equilibria (:mod:`redsim.integrators.reference`).

Full-space equilibria are the expensive part of measuring a subspace; they are cached per scene
content, condition and load, in memory (least recently used dropped first) and on disk
(:func:`cache_directory`: under ``$REDSIM_CACHE``, by default ``~/.cache/redsim``;
``REDSIM_CACHE=0`` turns the disk cache off), so comparing several subspaces of one scene, in
one process or across runs, solves the full space once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from collections import OrderedDict
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from redsim.scene import Scene
from redsim.usercache import CACHE_ENV as CACHE_ENV  # re-exported: redsim.metrics and the tests name it here
from redsim.usercache import cache_root, clear_user_cache, read_arrays, write_arrays
from redsim.version import __version__

logger = logging.getLogger(__name__)

CACHE_SIZE = 256
"""Full-space equilibria kept in the in-memory cache (least recently used dropped first)."""
DISK_CACHE_VERSION = 1
"""Part of every disk cache key (with redsim's version): bump it when the full-space solver or an
energy changes what the solves return without changing the scene's data (the digest covers data, not code)."""

Result = tuple[Tensor, bool, float]
"""A cached equilibrium: q [n] (float64), converged, energy [J]."""

_CACHE: OrderedDict[tuple[str, ...], Result] = OrderedDict()


def clear_cache(*, disk: bool = False) -> None:
    """Forget the cached full-space equilibria: in memory, and with ``disk=True`` also on disk."""
    _CACHE.clear()
    if disk:
        clear_user_cache(["equilibria"])


def cache_directory() -> Path | None:
    """The folder of the disk cache of full-space equilibria, or None when it is off.

    ``$REDSIM_CACHE/equilibria`` when the variable names a folder; off when it is "0", "off",
    "false", "no" or empty; by default ``$XDG_CACHE_HOME/redsim/equilibria``, else
    ``~/.cache/redsim/equilibria``. Read at every use, so tests can point it elsewhere.

    Entries are keyed like the in-memory cache (scene content digest, condition, load) plus
    redsim's version, DISK_CACHE_VERSION and the solver settings (those of
    :mod:`redsim.integrators.reference`: FULL_TOL, NEWTON_ITER, NEWTON_REUSE, RELAX_STEPS,
    RELAX_MOVE, ESCAPES), one ``.npz`` file each, written atomically;
    unreadable or mismatched files are ignored with a warning and solved again. Non-converged
    results are kept too (they say so). The digest covers the scene's data, not the code of its
    energies: after changing an energy's code, bump DISK_CACHE_VERSION or call
    ``clear_cache(disk=True)``.
    """
    root = cache_root()
    return None if root is None else root / "equilibria"


def lookup(
    scene: Scene, load: Tensor | None, cond: Tensor | None, settings: tuple[Any, ...], solve: Callable[[], Result]
) -> Result:
    """The cached result for (scene content, condition, load), else ``solve()``, stored in memory and on disk.

    Args:
        scene: The (float64) scene; its content digest is part of the key.
        load: Loads [H, D] of the solve, or None.
        cond: Condition [m], or None for the scene's default.
        settings: The solver's settings (reprs go into the disk key, with redsim's version and
            DISK_CACHE_VERSION), so results of other settings are never read back.
        solve: Computes the result on a miss of both caches.
    """
    packed_cond = scene.pack_condition(cond, 1, scene.q_seed)
    key = (
        scene_digest(scene),
        "" if packed_cond is None else packed_cond.numpy().tobytes().hex(),
        "" if load is None else load.numpy().tobytes().hex(),
    )
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    disk_key = "|".join([*map(repr, (__version__, DISK_CACHE_VERSION, *settings)), *key])
    directory = cache_directory()
    path = None if directory is None else directory / f"{hashlib.sha256(disk_key.encode()).hexdigest()}.npz"
    result = None if path is None else _read_entry(path, disk_key, scene.free_dof_count)
    if result is None:
        result = solve()
        if path is not None:
            _write_entry(path, disk_key, result)
    _CACHE[key] = result
    while len(_CACHE) > CACHE_SIZE:
        _CACHE.popitem(last=False)
    return result


def _read_entry(path: Path, key: str, n: int) -> Result | None:
    """A disk cache entry (q [n], converged, energy), or None if there is none or it is unusable (warned)."""
    data = read_arrays(path, key, "equilibrium")
    if data is None:
        return None
    try:
        q, converged, energy = np.array(data["q"], dtype=np.float64), bool(data["converged"]), float(data["energy"])
        if q.shape != (n,) or not np.all(np.isfinite(q)):
            raise ValueError(f"q has shape {q.shape} or is not finite; expected [{n}]")
    except Exception as error:  # missing fields, a wrong shape: solve again
        logger.warning("ignoring unreadable equilibrium cache file %s (%s); solving again", path, error)
        return None
    logger.debug("full-space equilibrium from the disk cache %s", path)
    return torch.from_numpy(q), converged, energy


def _write_entry(path: Path, key: str, result: Result) -> None:
    """Store a result atomically (:func:`redsim.usercache.write_arrays`); failures are warned, never raised."""
    q, converged, energy = result
    arrays = {
        "q": q.detach().cpu().numpy().astype(np.float64),
        "converged": np.array(bool(converged)),
        "energy": np.array(float(energy)),
    }
    write_arrays(path, key, arrays, "equilibrium")


def scene_digest(scene: Scene) -> str:
    """Hash of everything a scene holds (its fingerprint alone does not tell apart scenes built by hand)."""
    digest = hashlib.sha256(scene.fingerprint().encode())
    _feed(digest, [scene.dof_map, scene.mass_matrix, scene.q_seed, scene.effects, scene.handles, scene.condition_space])
    return digest.hexdigest()


def _feed(digest: Any, value: Any) -> None:
    if isinstance(value, Tensor):
        if value.is_sparse:
            value = value.coalesce()
            _feed(digest, [value.indices(), value.values()])
            return
        digest.update(f"{value.dtype}{tuple(value.shape)}".encode())
        digest.update(value.detach().cpu().contiguous().numpy().tobytes())
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        digest.update(type(value).__name__.encode())
        _feed(digest, [getattr(value, f.name) for f in dataclasses.fields(value)])
    elif isinstance(value, Mapping):
        for key in sorted(value, key=str):
            digest.update(str(key).encode())
            _feed(digest, value[key])
    elif isinstance(value, (list, tuple)):
        digest.update(f"[{len(value)}".encode())
        for item in value:
            _feed(digest, item)
    elif hasattr(value, "__dict__") and not isinstance(value, type):
        digest.update(type(value).__name__.encode())
        _feed(digest, vars(value))
    else:
        digest.update(repr(value).encode())
