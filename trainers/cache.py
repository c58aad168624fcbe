"""Fit what is missing: a subspace for a scene and a :class:`FitConfig`, reused from a checkpoint stem if one is there.

The benches that compare fitted maps (``redsim bench subspace``, ``redsim bench accuracy --dims``)
keep their fits under a folder the user names; a second run reuses them instead of fitting again.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from torch import nn

from redsim.scene import Scene
from redsim.subspace import CheckpointError, checkpoint_path, load_subspace
from redsim.trainers.fit import FitConfig, fit_command, fit_subspace

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
    """The map saved at ``STEM.pt`` (or at the first of ``also`` that loads), else a fit of ``config`` saved to STEM.

    A checkpoint is used only if it loads for ``scene`` and records the config's fit (every field but
    :data:`RUNTIME_FIELDS`; a field recorded before it existed counts as its default) and ``seed``, and was not
    extended by a resumed fit (its schedules were planned for fewer steps); one that
    exists but does not qualify is reported through ``warn`` and skipped.

    Args:
        scene: The scene.
        config: The fit to reuse or run (a scene preset, possibly with other d or steps).
        stem: Where the fit is kept (``STEM.pt`` + ``STEM.json``).
        seed: Seed of a new fit.
        also: Further checkpoints tried after ``STEM.pt`` (e.g. the shipped map).
        refit: Fit even if a checkpoint qualifies.
        progress: Show the fit's progress bar.
        warn: Called with one line per checkpoint skipped.

    Returns:
        The map and where it came from (the checkpoint's path).
    """
    candidates = [checkpoint_path(stem, ".pt"), *(Path(p) for p in also)]
    for path in [] if refit else candidates:
        if not path.is_file():
            continue
        try:
            subspace = load_subspace(path, scene=scene)
        except CheckpointError as err:
            if warn:
                warn(f"not using {path}: {err}")
            continue
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
            continue
        return subspace, str(path)
    result = fit_subspace(
        scene, config, seed=seed, out=stem, progress=progress, command=fit_command(scene, config, seed, stem)
    )
    return result.subspace, str(candidates[0])


def _differences(recorded: dict[str, Any], config: FitConfig) -> list[str]:
    """``"field = recorded, not wanted"`` for each field of ``config`` (but :data:`RUNTIME_FIELDS`) that a
    checkpoint's recorded fit differs in (a field it does not record: FitConfig's default)."""
    out = []
    for field in dataclasses.fields(config):
        if field.name in RUNTIME_FIELDS:
            continue
        wanted = getattr(config, field.name)
        value = recorded.get(field.name, field.default)
        if (list(value) if isinstance(value, (list, tuple)) else value) != (
            list(wanted) if isinstance(wanted, tuple) else wanted
        ):
            out.append(f"{field.name} = {value!r}, not {wanted!r}")
    return out


__all__ = ["RUNTIME_FIELDS", "fitted_subspace"]
