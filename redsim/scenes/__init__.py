"""The scene registry: ``names()`` lists the scenes, ``build(name, **params)`` makes one.

Catalog scenes (:mod:`redsim.scenes.catalog`) reproduce the systems of the paper's Table 1
plus a heterogeneous beam; toy scenes (:mod:`redsim.scenes.testing`, names starting with
``toy_``) are tiny systems for fast tests. Each has a :class:`SceneEntry` in :data:`ENTRIES`
saying what the rest of redsim needs to know about it (tags, a crank, reference states).
Scenes from your own meshes come from :func:`fem_scene_from_mesh` (a surface, voxelized),
:func:`tet_scene_from_mesh` (a tet mesh) and :func:`cloth_scene_from_mesh`;
:func:`redsim.scenes.spec.scene_from_spec` rebuilds any scene from
the record a checkpoint keeps.

Example::

    import redsim
    scene = redsim.scenes.build("chain", links=12, gravity=False)
    scene.describe()["n"]    # 144
    redsim.scenes.names("env")    # the scenes the environments run on
"""

from __future__ import annotations

import inspect
import numbers
import os
import re
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from redsim.scene import Scene
from redsim.scenes.catalog import CATALOG
from redsim.scenes.from_mesh import cloth_scene_from_mesh, fem_scene_from_mesh, tet_scene_from_mesh
from redsim.scenes.registry import TAGS, Crank, SceneEntry
from redsim.scenes.testing import TOYS

ENTRIES: dict[str, SceneEntry] = {e.name: e for e in (*CATALOG, *TOYS)}
"""Every named scene (catalog first, in Table 1 order, then the toys)."""

SCENES: dict[str, Callable[..., Scene]] = {name: e.builder for name, e in ENTRIES.items()}
"""Every named scene builder; each is keyword-only and every argument has a default."""


def names(tag: str | None = None) -> list[str]:
    """Names of all registered scenes (catalog first, then toys), or of those tagged ``tag``.

    Raises:
        ValueError: ``tag`` is not one of :data:`TAGS` (the message lists them).
    """
    if tag is None:
        return list(ENTRIES)
    if tag not in TAGS:
        raise ValueError(f"unknown scene tag {tag!r}; valid tags: {list(TAGS)}")
    return [name for name, e in ENTRIES.items() if tag in e.tags]


def entry(name: str) -> SceneEntry:
    """The registry entry of scene ``name``.

    Raises:
        ValueError: on an unknown name (the message lists the valid names).
    """
    if name not in ENTRIES:
        hint = ""
        if looks_like_an_env_id(name):
            hint = " (an env id: gymnasium.make makes it; here a scene goes)"
        elif looks_like_a_path(name):
            hint = (
                " (a path: build a mesh file's scene with fem_scene_from_mesh, tet_scene_from_mesh or "
                "cloth_scene_from_mesh, a spec's or a "
                "checkpoint's .json with redsim.scenes.spec.scene_from_spec)"
            )
        raise ValueError(f"unknown scene {name!r}{hint}; valid scenes: {names()}")
    return ENTRIES[name]


def looks_like_a_path(name: str) -> bool:
    """Whether a scene name given is a file path (a folder in it, or a file suffix; not an env id such as
    ``RedSim/Chain-v0``): its error says how to use one."""
    if looks_like_an_env_id(name):
        return False
    return "/" in name or os.sep in name or os.path.splitext(name)[1].lower() in _PATH_SUFFIXES


def looks_like_an_env_id(name: str) -> bool:
    """Whether a scene name given is a Gymnasium id (``RedSim/Chain-v0``, ``redsim:RedSim/Chain-v0``)."""
    return re.fullmatch(r"([\w.]+:)?[\w.-]+/[\w.-]+-v\d+", name) is not None


_PATH_SUFFIXES = (".obj", ".stl", ".ply", ".off", ".glb", ".gltf", ".msh", ".vtk", ".json", ".pt", ".npz")
"""File suffixes a scene name is taken for a path by (:func:`looks_like_a_path`)."""


def parameters(name: str) -> dict[str, Any]:
    """The parameters of scene ``name`` with their defaults."""
    builder = entry(name).builder
    return {k: p.default for k, p in inspect.signature(builder).parameters.items()}


def full_space_tol(name: str) -> float:
    """The relative gradient tolerance a float64 full-space Newton step of scene ``name`` reaches
    (:attr:`SceneEntry.full_space_tol`; a scene not in the registry, e.g. one built from a mesh: the default 1e-8)."""
    return ENTRIES[name].full_space_tol if name in ENTRIES else SceneEntry.full_space_tol


def build(name: str, **params: Any) -> Scene:
    """Build the scene called ``name`` with keyword ``params`` overriding its defaults.

    Raises:
        ValueError: on an unknown name (the message lists the valid names), an unknown
            parameter (it lists the scene's parameters) or a bad parameter value.
    """
    builder = entry(name).builder
    signature = inspect.signature(builder).parameters
    valid = list(signature)
    unknown = sorted(set(params) - set(valid))
    if unknown:
        raise ValueError(f"scene {name!r} has no parameter(s) {unknown}; valid parameters: {valid}")
    return builder(**{key: _as_default_type(key, value, signature[key].default) for key, value in params.items()})


_NOT_REAL = (torch.bool, torch.complex64, torch.complex128, np.dtype(bool), np.dtype(np.complex64), np.dtype(complex))
"""Dtypes of a one-number tensor or array that are no real number (a scene parameter refuses them)."""


def _as_default_type(key: str, value: Any, default: Any) -> Any:
    """A parameter whose default is a float, given as an int, as that float (``density=7800`` builds the scene, and
    its fingerprint, of ``density=7800.0``); so is a one-number torch tensor or NumPy array of a real dtype
    (``torch.tensor(7800.0)``); anything but a real number there is refused. Where the default is an int or a bool, a
    NumPy or one-number torch integer or bool is that Python int or bool, and a pair of floats given as ints is
    floats (each the same scene, and fingerprint, as the Python value; a NumPy int could not be written as JSON)."""
    if isinstance(default, tuple | list) and isinstance(value, tuple | list) and len(value) == len(default):
        return type(default)(
            _as_default_type(f"{key}[{i}]", v, d) for i, (v, d) in enumerate(zip(value, default, strict=True))
        )
    if isinstance(default, bool | int) and isinstance(value, torch.Tensor | np.ndarray | np.generic):
        item = value.item() if value.ndim == 0 else value
        if isinstance(default, bool) and isinstance(item, bool):
            return item
        if not isinstance(default, bool) and isinstance(item, int) and not isinstance(item, bool):
            return item
        return value
    if not isinstance(default, float):
        return value
    if isinstance(value, torch.Tensor | np.ndarray) and value.ndim == 0 and value.dtype not in _NOT_REAL:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"scene parameter {key} must be a number, got {value!r}")
    return float(value)


__all__ = [
    "ENTRIES",
    "SCENES",
    "TAGS",
    "Crank",
    "SceneEntry",
    "build",
    "cloth_scene_from_mesh",
    "entry",
    "fem_scene_from_mesh",
    "full_space_tol",
    "looks_like_a_path",
    "looks_like_an_env_id",
    "names",
    "parameters",
    "tet_scene_from_mesh",
]
