"""The kind registry: which class a checkpoint's ``kind`` rebuilds, and :func:`load_subspace`.

A checkpoint without a ``kind`` holds a neural map (the format before baselines existed).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

import torch
from torch import Tensor, nn

from redsim.devices import check_device
from redsim.scene import Scene
from redsim.subspace.anchored import AnchoredSubspace
from redsim.subspace.autoencoder import AutoencoderSubspace
from redsim.subspace.checkpoint import (
    PAIR_KEY,
    CheckpointError,
    beside_checkpoint,
    check_pair,
    check_scene,
    checkpoint_path,
    read_metadata,
)
from redsim.subspace.linear import LinearSubspace, QuadraticSubspace
from redsim.subspace.neural import SubspaceMap


class MapKind(Protocol):
    """A map class a checkpoint can hold: rebuilt empty from its ``config`` and metadata, then loaded."""

    kind: str

    @classmethod
    def from_shapes(cls, shapes: dict[str, Any], metadata: dict[str, Any]) -> nn.Module: ...


KINDS: dict[str, type[MapKind]] = {
    cls.kind: cls for cls in (SubspaceMap, LinearSubspace, QuadraticSubspace, AutoencoderSubspace, AnchoredSubspace)
}
"""Map classes by ``kind``, the key stored in their checkpoints ("neural" when absent)."""


def load_subspace(path: str | Path, scene: Scene | None = None, *, device: str | torch.device = "cpu") -> nn.Module:
    """Load any saved subspace: a neural map, or a baseline of :mod:`redsim.baselines` (by its ``kind``).

    Its tensors keep the dtype they were saved in (the shipped maps: float32), whatever ``torch.get_default_dtype()``
    is: a process that made float64 its default loads the same map as any other.

    Args:
        path: ``STEM.pt``, ``STEM.json`` or ``STEM``.
        scene: With it, refuse a checkpoint made for another scene.
        device: Where to put the weights.

    Raises:
        CheckpointError: missing or corrupt files, an unknown kind, weights other than the ones the .json records
            (two saves wrote the pair), or a scene whose name, fingerprint or n differ.
        ValueError: a device redsim cannot run on (:func:`redsim.devices.check_device`).
    """
    device = check_device(device)  # torch.load's own error for it was reported as "weights are corrupt or truncated"
    if (why := beside_checkpoint(path)) is not None:
        raise CheckpointError(why)
    weights = checkpoint_path(path, ".pt")
    if weights.name.endswith(".fit.pt") and not weights.with_suffix(".json").is_file():  # a fit's resumable state
        mapped = weights.with_name(weights.name[: -len(".fit.pt")] + ".pt")
        done = (
            f"the fitted map is {mapped}" if mapped.is_file() else f"the fit is unfinished: resuming it writes {mapped}"
        )
        raise CheckpointError(f"a fit's training state, not a subspace checkpoint: {done}", str(weights))
    if not weights.is_file():
        raise CheckpointError("the weights file is missing", str(weights))
    doc = read_metadata(path)
    if scene is not None:
        check_scene(doc, scene, str(weights))
    metadata = {k: v for k, v in doc.items() if k not in ("format_version", "config", PAIR_KEY)}
    kind = doc.get("kind", SubspaceMap.kind)
    if kind not in KINDS:
        valid = [SubspaceMap.kind, *sorted(k for k in KINDS if k != SubspaceMap.kind)]
        raise CheckpointError(f"unknown kind {kind!r}; valid: {', '.join(valid)}", str(weights))
    try:
        with torch.random.fork_rng(devices=[]):  # the layers' throwaway init must not use up the caller's stream
            model = KINDS[kind].from_shapes(doc["config"], metadata)
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise CheckpointError(f"bad config in metadata ({err!r})", str(weights)) from None
    try:
        state = torch.load(weights, map_location=device, weights_only=True)
    except Exception as err:  # torch raises several types for truncated/corrupt zips
        # one line, without torch's advice to load the file unsafely (weights_only=False)
        first = (str(err).strip().splitlines() or [""])[0]
        why = "not a checkpoint torch loads safely" if "weights_only" in first else first
        raise CheckpointError(f"weights are corrupt or truncated ({type(err).__name__}: {why})", str(weights)) from None
    mismatch = _state_mismatch(model.state_dict(), state)
    if mismatch:
        raise CheckpointError(f"the weights do not fit the .json beside them: {mismatch}", str(weights))
    try:  # assign: the weights keep the checkpoint's dtype, whatever torch's default dtype built the layers in
        model.load_state_dict(state, assign=True)
    except (RuntimeError, KeyError) as err:
        raise CheckpointError(f"weights do not match the config ({err})", str(weights)) from None
    check_pair(doc, model, str(weights))
    return model.to(device)


def _state_mismatch(expected: dict[str, Tensor], saved: dict[str, Any]) -> str:
    """One line on how a saved state dict differs from the one a config builds ("" when they fit)."""
    missing = sorted(set(expected) - set(saved))
    extra = sorted(set(saved) - set(expected))
    if missing or extra:
        return f"the .pt lacks {missing or 'nothing'} and has extra {extra or 'nothing'}"
    for key, want in expected.items():
        got = saved[key]
        if not isinstance(got, Tensor) or tuple(got.shape) != tuple(want.shape):
            shape = list(got.shape) if isinstance(got, Tensor) else type(got).__name__
            return (
                f"{key} has shape {shape} in the .pt but {list(want.shape)} by the .json "
                "(weights of another scene or fit?)"
            )
    return ""
