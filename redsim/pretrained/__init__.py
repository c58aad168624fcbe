"""Fitted subspaces shipped with redsim, one per scene the Gymnasium environments use.

Each is ``SCENE.pt`` + ``SCENE.json`` in this folder, written by ``redsim fit`` for the scene
with its default parameters; the JSON's ``command`` is the exact command line that reproduces
it (run it in an empty folder: it writes ``SCENE.pt`` + ``SCENE.json`` there). Some scenes also
ship ``SCENE.cubature.json``, a cubature energy for that map (:mod:`redsim.cubature`; its
``command`` rebuilds it).

    >>> from redsim import pretrained
    >>> f = pretrained.load("mini_chain")   # a SubspaceMap, checked against scenes.build("mini_chain")
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch import Tensor, nn

from redsim import scenes
from redsim.scene import Scene
from redsim.subspace.checkpoint import beside_checkpoint

FOLDER = Path(__file__).resolve().parent
ENV_SCENES = tuple(scenes.names("env"))
"""The scenes the environments run on (registry tag "env"); each has a shipped subspace."""


def names() -> list[str]:
    """Scenes with a shipped subspace, sorted."""
    return sorted(p.stem for p in FOLDER.glob("*.json") if beside_checkpoint(p) is None)


def rest_start(scene_name: str, fingerprint: str) -> Tensor | None:
    """Where the rest solve of the shipped map of ``scene_name`` starts, [d] float64, from ``SCENE.rest.json``; None
    where none is shipped or ``fingerprint`` (the map's :func:`redsim.subspace.map_fingerprint`) is another map's.

    :meth:`redsim.runtime.LatentStepper.rest_latent` solves the rest latent by Newton from here, else from z = 0. Where
    a map's latent energy has near-degenerate minima near z = 0, the path from z = 0 ends in one or another by the
    CPU's round-off (the file's ``why`` says what was measured), and an env (or a bench) would start from another state
    on another machine; from a start inside one basin every machine converges to the same minimum.
    """
    file = FOLDER / f"{scene_name}.rest.json"
    if not file.is_file():
        return None
    doc = json.loads(file.read_text())
    if fingerprint != doc["map"]:
        return None
    return torch.tensor(doc["start"], dtype=torch.float64)


class NotShipped(KeyError):
    """No subspace is shipped for the scene; a KeyError whose message prints as written (KeyError's is quoted)."""

    def __str__(self) -> str:
        return str(self.args[0])


def path(scene_name: str) -> Path:
    """The shipped checkpoint ``SCENE.pt`` of ``scene_name``.

    Raises:
        NotShipped: a KeyError; no subspace is shipped for this scene (the message lists those that are).
    """
    weights = FOLDER / f"{scene_name}.pt"
    if not (weights.is_file() and weights.with_suffix(".json").is_file()):
        raise NotShipped(f"no shipped subspace for scene {scene_name!r}; shipped: {', '.join(names()) or 'none'}")
    return weights


def fit_record(scene_name: str) -> dict:
    """The fit options the shipped map of ``scene_name`` was fitted with: its JSON's ``fit`` record plus ``seed``
    (FitConfig's field names; a record older than a field lacks it, and that field was at its default).

    An env fits a map for parameters no shipped map covers with these (:func:`redsim.envs.fitted.cached_subspace`),
    so its cached map is made as its shipped one was, which the env's settings were chosen on; a scene's fitting
    preset may since have moved on (README "Shipped subspaces").

    Raises:
        NotShipped: a KeyError; no subspace is shipped for this scene.
    """
    doc = json.loads(path(scene_name).with_suffix(".json").read_text())
    return {**doc["fit"], "seed": doc["seed"]}


def load(scene_name: str, scene: Scene | None = None, *, device: str | torch.device = "cpu") -> nn.Module:
    """The shipped subspace of ``scene_name``, checked against ``scene``.

    Args:
        scene_name: Catalog name.
        scene: The scene it will run on (default: rebuilt from the checkpoint's record,
            :func:`redsim.scenes.spec.scene_from_spec`). A scene built with other parameters is refused:
            the subspace was fitted to the defaults.
        device: Where to put the weights.

    Raises:
        NotShipped: a KeyError; no subspace is shipped for this scene.
        redsim.subspace.CheckpointError: the scene differs from the one the subspace was fitted to.
        ValueError: a device redsim cannot run on (:func:`redsim.devices.check_device`).
    """
    from redsim.scenes.spec import scene_from_spec
    from redsim.subspace import load_subspace, read_metadata

    weights = path(scene_name)
    scene = scene_from_spec(read_metadata(weights)) if scene is None else scene
    return load_subspace(weights, scene=scene, device=device)


__all__ = ["ENV_SCENES", "FOLDER", "NotShipped", "fit_record", "load", "names", "path"]
