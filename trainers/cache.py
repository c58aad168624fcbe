"""Fit what is missing: a subspace for a scene and a :class:`FitConfig`, reused from a checkpoint stem if one is there.

The benches that compare fitted maps (``redsim bench subspace``, ``redsim bench accuracy --dims``)
keep their fits under a folder the user names; a second run reuses them instead of fitting again. A file there that
is not the fit asked for (a user's own fit, one of another scene of the same name) is never overwritten: the new fit
goes beside it, to a stem suffixed with :func:`fit_key`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from redsim.scene import Scene
from redsim.subspace import CheckpointError, checkpoint_path, load_subspace
from redsim.trainers.fit import FitConfig, existing_fit, fit_command, fit_subspace, planned_steps

RUNTIME_FIELDS = ("checkpoint_every", "device", "fused_adam", "compile")
"""FitConfig fields that say how a fit runs, not what it fits: a checkpoint may differ in them."""


def fitted_subspace(
    scene: Scene,
    config: FitConfig,
    stem: str | Path,
    *,
    seed: int = 0,
    also: Sequence[str | Path] = (),
    refit: bool = False,
    progress: bool = True,
    warn: Callable[[str], None] | None = None,
) -> tuple[nn.Module, str]:
    """The map saved at ``STEM.pt``, ``STEM_KEY.pt`` or the first of ``also`` that qualifies, else a fit of ``config``
    saved to the first of STEM and STEM_KEY that holds no other fit.

    KEY hashes the scene's fingerprint, the config's fit and ``seed`` (:func:`fit_key`), so that another scene of the
    same name, or another fit, never overwrites a checkpoint it cannot use. A checkpoint qualifies if it loads for
    ``scene`` and records the config's fit (every field but :data:`RUNTIME_FIELDS`; a field recorded before it existed
    counts as its default) and ``seed``, and was not extended by a resumed fit (its schedules were planned for fewer
    steps); one that exists but does not qualify is reported through ``warn`` and skipped. Where none qualifies, this
    fit stopped before it saved its map (Ctrl-C, a kill: a training state of this fit at STEM or STEM_KEY, and no map
    there) is resumed, saying so through ``warn``: the same map as a fit from the start (it was fitted afresh into
    STEM_KEY, and refused after a second interruption there).

    Args:
        scene: The scene.
        config: The fit to reuse or run (a scene preset, possibly with other d or steps).
        stem: Where the fit is kept (``STEM.pt`` + ``STEM.json``).
        seed: Seed of a new fit.
        also: Further checkpoints tried after STEM's (e.g. the shipped map).
        refit: Fit even if a checkpoint qualifies (replacing the one at STEM or STEM_KEY, not one whose resumed
            extension is under way: its STEM.fit.pt plans another length), and from the start, not resuming one.
        progress: Show the fit's progress bar.
        warn: Called with one line per checkpoint skipped, and where a fit goes to STEM_KEY.

    Returns:
        The map and where it came from (the checkpoint's path).

    Raises:
        FileExistsError: both STEM and STEM_KEY hold files (``.pt``, ``.json`` or ``.fit.pt``) of other fits.
    """
    stems = [Path(stem), Path(stem).with_name(f"{Path(stem).name}_{fit_key(scene, config, seed)}")]
    if not refit:
        for path in [*(checkpoint_path(s, ".pt") for s in stems), *(Path(p) for p in also)]:
            subspace = _qualified(path, scene, config, seed, warn)
            if subspace is not None:
                return subspace, str(path)
        for at in stems:  # this fit, interrupted (Ctrl-C, a kill) before it saved its map: continued, not redone
            if (done := _interrupted(at, scene, config, seed)) is None:
                continue
            if warn:
                state = checkpoint_path(at, ".fit.pt")
                warn(f"resuming the interrupted fit at {state} ({done} of {config.steps} steps)")
            try:
                result = fit_subspace(scene, config, seed=seed, out=at, resume=True, progress=progress)
            except CheckpointError as err:  # a state it cannot continue (another device): fitted afresh below
                if warn:
                    warn(f"not resuming it: {err}")
                continue
            return result.subspace, str(checkpoint_path(at, ".pt"))
    free = [s for s in stems if existing_fit(s) is None or (refit and _replaceable(s, scene, config, seed))]
    if not free:
        raise FileExistsError(
            f"not fitting into {stems[0]} or {stems[1]}: both hold files of another fit; move them away, or keep the "
            "fits in another folder"
        )
    if free[0] != stems[0] and warn:
        warn(f"fitting into {checkpoint_path(free[0], '.pt')}, keeping the other fit at {stems[0]}")
    result = fit_subspace(
        scene,
        config,
        seed=seed,
        out=free[0],
        overwrite=refit,  # a refit replaces only a stem it may (_replaceable); the others are free
        progress=progress,
        command=fit_command(scene, config, seed, free[0]),
    )
    return result.subspace, str(checkpoint_path(free[0], ".pt"))


def fit_key(scene: Scene, config: FitConfig, seed: int) -> str:
    """8 hex digits of a hash of ``scene``'s fingerprint, the fields of ``config``'s fit (all but
    :data:`RUNTIME_FIELDS`) that differ from FitConfig's defaults, and ``seed``: what a checkpoint must match to be
    reused. A field added to FitConfig later, or 1 given for 1.0, leaves the key as it was."""
    fit = {
        field.name: _comparable(getattr(config, field.name))
        for field in dataclasses.fields(config)
        if field.name not in RUNTIME_FIELDS and _comparable(getattr(config, field.name)) != _comparable(field.default)
    }
    doc = {"scene": scene.fingerprint(), "fit": fit, "seed": seed}
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()[:8]


def _interrupted(stem: Path, scene: Scene, config: FitConfig, seed: int) -> int | None:
    """The steps done where ``stem`` holds ``config``'s fit of ``scene`` with ``seed`` stopped before it saved its map:
    its training state (``STEM.fit.pt``, planned for ``config.steps`` and never extended) and no ``STEM.pt`` or
    ``STEM.json``; None otherwise (a fit there took the stem, and a fit of its own goes to STEM_KEY)."""
    if checkpoint_path(stem, ".pt").exists() or checkpoint_path(stem, ".json").exists():
        return None
    try:
        state = torch.load(checkpoint_path(stem, ".fit.pt"), map_location="cpu", weights_only=True)
        recorded, done, fingerprint = dict(state["config"]), int(state["step"]), state["scene_fingerprint"]
    except Exception:  # none, or unreadable: not continued (a fit of its own goes to STEM_KEY)
        return None
    ours = scene.accepts(fingerprint) and state.get("seed") == seed and not state.get("extensions")
    if not ours or _comparable(recorded.get("steps")) != _comparable(config.steps) or _differences(recorded, config):
        return None
    return done


def _replaceable(stem: Path, scene: Scene, config: FitConfig, seed: int) -> bool:
    """Whether a refit may overwrite ``stem``: its map qualifies and its training state (``STEM.fit.pt``), if any, is
    that finished fit's, not a resumed extension of it still under way (an interrupted ``--resume --steps N``)."""
    in_progress = checkpoint_path(stem, ".fit.pt").exists() and planned_steps(stem) != config.steps
    return not in_progress and _qualified(checkpoint_path(stem, ".pt"), scene, config, seed) is not None


def _qualified(
    path: Path, scene: Scene, config: FitConfig, seed: int, warn: Callable[[str], None] | None = None
) -> nn.Module | None:
    """The map at ``path`` if it is ``config``'s fit of ``scene`` with ``seed``; None (and why, to ``warn``) if not."""
    if not path.is_file():
        return None
    try:
        subspace = load_subspace(path, scene=scene)
    except CheckpointError as err:
        if warn:
            warn(f"not using {path}: {err}")
        return None
    metadata = getattr(subspace, "metadata", {})
    fit = {"latent_dim": int(subspace.latent_dim), **metadata.get("fit", {})}
    differs = _differences(fit, config)
    if metadata.get("seed", seed) != seed:
        differs.append(f"seed = {metadata['seed']!r}, not {seed!r}")
    for extension in metadata.get("schedule", {}).get("extensions", []):  # its schedule was planned for less
        differs.append(f"extended from {extension['from_steps']} steps (--resume), not fitted for {config.steps}")
    if differs:
        if warn:
            warn(f"not using {path}: it records {', '.join(differs)}")
        return None
    return subspace


def _comparable(value: Any) -> Any:
    """A fit setting as compared and hashed: numbers as float (1 == 1.0), tuples as lists."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    return [_comparable(v) for v in value] if isinstance(value, (list, tuple)) else value


def _differences(recorded: dict[str, Any], config: FitConfig) -> list[str]:
    """``"field = recorded, not wanted"`` for each field of ``config`` (but :data:`RUNTIME_FIELDS`) that a
    checkpoint's recorded fit differs in (a field it does not record: FitConfig's default)."""
    out = []
    for field in dataclasses.fields(config):
        if field.name in RUNTIME_FIELDS:
            continue
        wanted = getattr(config, field.name)
        value = recorded.get(field.name, field.default)
        if _comparable(value) != _comparable(wanted):
            out.append(f"{field.name} = {value!r}, not {wanted!r}")
    return out


__all__ = ["RUNTIME_FIELDS", "fit_key", "fitted_subspace"]
