"""Subspaces for scene parameters that no shipped map covers, fitted on request into the user cache.

The shipped maps (:mod:`redsim.pretrained`) are fitted to each catalog scene's default
parameters. An env built with other ``scene_params`` and ``fit_if_missing=True`` gets a map
fitted by :func:`redsim.trainers.fit_subspace` (the options its shipped map was fitted with,
:func:`redsim.pretrained.fit_record`, updated by ``fit_options``; a tqdm progress bar), saved under
``cache_root()/subspaces`` (:func:`redsim.usercache.cache_root`: ``$REDSIM_CACHE`` or
``~/.cache/redsim``) and loaded from there the next time. With the cache off
(``REDSIM_CACHE=0``) the map is fitted and kept in memory only, marked
:data:`IN_MEMORY_ATTRIBUTE`: a pickled or copied env carries it instead of
fitting again. An interrupted fit resumes from its training state (``STEM.fit.pt``) on the
next call.

Import direction: the trainers are imported inside :func:`cached_subspace` (envs may import
trainers; nothing below the envs does).
"""

from __future__ import annotations

import hashlib
import json
import logging
import tempfile
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from torch import nn

from redsim.scene import Scene
from redsim.subspace import CheckpointError
from redsim.usercache import cache_root

log = logging.getLogger(__name__)

SPEED_ONLY = ("checkpoint_every", "fused_adam", "compile")
"""Fit options that change how often a fit saves or how fast it runs, not its map (a resume ignores them too)."""

FOLDER = "subspaces"
"""Folder of the fitted maps inside redsim's user cache."""
IN_MEMORY_ATTRIBUTE = "redsim_in_memory"
"""Attribute (True) of a map fitted with no checkpoint file behind it (the cache off): an env pickles such a map with
itself (:meth:`redsim.envs.base.LatentEnv.__getstate__`), as a rebuild from its arguments would fit it again."""


def cache_stem(scene_name: str, scene: Scene, options: Mapping[str, Any]) -> Path | None:
    """``cache_root()/subspaces/SCENE-FINGERPRINT-OPTIONS`` (no suffix), or None with the cache off.

    OPTIONS hashes the fit options but those that only say how often it saves or how fast it runs
    (:data:`SPEED_ONLY`), ``device`` included where it is not the CPU: a fit on a GPU draws from a CUDA generator
    (another map than the CPU's), and its resumable training state cannot continue on the CPU."""
    root = cache_root()
    if root is None:
        return None
    what = {k: v for k, v in options.items() if k not in SPEED_ONLY and not (k == "device" and str(v) == "cpu")}
    digest = hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()[:12]
    return root / FOLDER / f"{scene_name}-{scene.fingerprint()}-{digest}"


RESERVED_FIT_OPTIONS = frozenset(
    {"scene", "config", "out", "resume", "overwrite", "progress", "callbacks", "command", "stop_at"}
)
"""``fit_subspace`` arguments the env's cache sets itself (``fit_options`` may not: they clashed as a TypeError)."""


def cached_subspace(
    scene_name: str, scene: Scene, fit_options: Mapping[str, Any] | None = None, *, progress: bool = True
) -> nn.Module:
    """The user-cache map of ``scene`` (catalog scene ``scene_name`` built with non-default parameters).

    Loaded when the cache has it; otherwise fitted (the options the shipped map was fitted with, but those of
    :data:`SPEED_ONLY` and ``device``, updated by ``fit_options``; with a progress bar unless ``progress=False``),
    saved to the cache and returned (with the cache off, marked :data:`IN_MEMORY_ATTRIBUTE`). Not the scene's
    fitting preset: where a preset has moved on (the chain's 1.6·10^5 steps against its shipped map's 10^4), the
    env's settings were chosen on the shipped map's kind of fit, which also steps faster.

    Raises:
        ValueError: an unknown or bad fit option (from the fitter, before any step), or one the cache sets itself
            (:data:`RESERVED_FIT_OPTIONS`).
        redsim.subspace.CheckpointError: a corrupt cached checkpoint or training state (the message names the files
            to delete to fit again or start over).
    """
    from redsim.subspace import checkpoint_path, load_subspace
    from redsim.trainers.fit import FIT_ALIASES, fit_subspace

    reserved = sorted(set(fit_options or {}) & RESERVED_FIT_OPTIONS)
    if reserved:
        raise ValueError(
            f"fit_options cannot set {reserved}: the env's cache chooses where its fit is saved, resumed and shown "
            "(fit options are FitConfig's fields and seed)"
        )
    given = dict(fit_options or {})
    for alias, field in FIT_ALIASES.items():  # dim=2 replaces the recorded latent_dim (not "two values that differ")
        if alias in given and field not in given:
            given[field] = given.pop(alias)
    options = {**_shipped_recipe(scene_name), **given}  # the same cache entry for either spelling
    stem = cache_stem(scene_name, scene, options)
    if stem is not None and checkpoint_path(stem, ".pt").is_file() and checkpoint_path(stem, ".json").is_file():
        try:
            return load_subspace(stem, scene=scene)
        except CheckpointError as err:
            files = f"{checkpoint_path(stem, '.pt')} and {checkpoint_path(stem, '.json')}"
            raise _damaged(err, f"delete {files} to fit it again") from None
    if stem is not None and not _writable(stem.parent):  # as the other caches: it never stops the caller
        warnings.warn(
            f"the user cache cannot hold this fit ({stem.parent} is not a writable folder): fitting in memory (set "
            "$REDSIM_CACHE to a writable folder, or to 0 to turn the cache off)",
            UserWarning,
            stacklevel=2,
        )
        stem = None
    state = None if stem is None else checkpoint_path(stem, ".fit.pt")
    resume = state is not None and state.is_file()
    log.info("fitting a subspace for %s (%s) into %s", scene_name, scene.fingerprint(), stem or "memory (cache off)")
    try:
        result = fit_subspace(scene, out=stem, resume=resume, overwrite=not resume, progress=progress, **options)
    except CheckpointError as err:
        if not resume:
            raise
        raise _damaged(err, f"delete {state} to start its fit over") from None
    except ValueError:
        if not resume or state.is_file():
            raise
        # "nothing to resume": another process (a SubprocVecEnv worker fitting the same map) finished this fit, or
        # started it over, between the check and the load; its map is there now, or this one fits from the start
        return cached_subspace(scene_name, scene, fit_options, progress=progress)
    if state is not None:
        state.unlink(missing_ok=True)
    if stem is None:  # no file behind it: an env pickles it rather than fit it again
        setattr(result.subspace, IN_MEMORY_ATTRIBUTE, True)
    return result.subspace


def _damaged(err: CheckpointError, remedy: str) -> CheckpointError:
    """``err`` (about a file of the cache's ``subspaces`` folder) with what to do about it."""
    damaged = CheckpointError(f"{err}; it is an entry of redsim's user cache ($REDSIM_CACHE): {remedy}")
    damaged.path = err.path
    return damaged


def _shipped_recipe(scene_name: str) -> dict[str, Any]:
    """The fit options of the shipped map of ``scene_name`` but the speed and device ones; the scene's preset itself
    where it fits that same map (seed 0), so the cache entries made when the envs fitted presets keep their names
    (cloth_ball, klann, mini_chain, stewart). The conditional bar's and the sheet's presets moved on in stop 47: their
    entries made before are keyed by the old preset dicts, and the same map is fitted once more under the record's."""
    from redsim.pretrained import fit_record
    from redsim.trainers.fit import FitConfig
    from redsim.trainers.presets import preset

    record = {k: v for k, v in fit_record(scene_name).items() if k not in (*SPEED_ONLY, "device")}
    record = {k: tuple(v) if isinstance(v, list) else v for k, v in record.items()}  # periodic, soften: tuples
    seed = record.pop("seed")
    if seed == 0 and FitConfig(**record) == FitConfig(**preset(scene_name)):
        return preset(scene_name)
    return {**record, "seed": seed}


def _writable(folder: Path) -> bool:
    """Whether ``folder`` exists or can be made, and a file can be written in it."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            return True
    except OSError:
        return False


__all__ = ["FOLDER", "IN_MEMORY_ATTRIBUTE", "RESERVED_FIT_OPTIONS", "cache_stem", "cached_subspace"]
