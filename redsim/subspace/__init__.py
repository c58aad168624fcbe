"""Subspace maps f(z[, c]) -> q of every kind, their checkpoints and the kind registry.

- :mod:`~redsim.subspace.neural`: :class:`SubspaceMap`, the MLP fitted data-free, and its
  :class:`SubspaceConfig`.
- :mod:`~redsim.subspace.linear`: :class:`LinearSubspace` (modal analysis, PCA) and
  :class:`QuadraticSubspace` (modal derivatives); :mod:`~redsim.subspace.autoencoder`:
  :class:`AutoencoderSubspace` (the supervised baseline). Their builders are in :mod:`redsim.baselines`.
- :mod:`~redsim.subspace.anchored`: :class:`AnchoredSubspace`, modal derivatives plus an MLP stripped of its
  Taylor polynomial at z = 0 (the map is the polynomial one to second order there).
- :mod:`~redsim.subspace.latents`: latent sampling, periodic latents, the pair term of the fitting loss.
- :mod:`~redsim.subspace.checkpoint`: ``STEM.pt`` + ``STEM.json``, written and read;
  :mod:`~redsim.subspace.kinds`: :func:`load_subspace`, which rebuilds a checkpoint by its ``kind``.

Nothing here imports the solvers, integrators, baselines or metrics.
"""

from __future__ import annotations

from redsim.subspace.anchored import AnchoredSubspace
from redsim.subspace.autoencoder import AutoencoderSubspace
from redsim.subspace.base import MapModule
from redsim.subspace.checkpoint import (
    FORMAT_VERSION,
    CheckpointError,
    check_scene,
    checkpoint_path,
    map_fingerprint,
    read_metadata,
    write_atomically,
    write_checkpoint,
)
from redsim.subspace.kinds import KINDS, load_subspace
from redsim.subspace.latents import pair_log_ratios, periodic_latents, sample_latents
from redsim.subspace.linear import LinearSubspace, QuadraticSubspace
from redsim.subspace.neural import ACTIVATIONS, SubspaceConfig, SubspaceMap

__all__ = [
    "ACTIVATIONS",
    "FORMAT_VERSION",
    "KINDS",
    "AnchoredSubspace",
    "AutoencoderSubspace",
    "CheckpointError",
    "LinearSubspace",
    "MapModule",
    "QuadraticSubspace",
    "SubspaceConfig",
    "SubspaceMap",
    "check_scene",
    "checkpoint_path",
    "load_subspace",
    "map_fingerprint",
    "pair_log_ratios",
    "periodic_latents",
    "read_metadata",
    "sample_latents",
    "write_atomically",
    "write_checkpoint",
]
