"""The scene catalog: ``names()`` lists the scenes, ``build(name, **params)`` makes one.

Catalog scenes (:mod:`redsim.scenes.catalog`) reproduce the systems of the paper's Table 1
plus a heterogeneous beam; toy scenes (:mod:`redsim.scenes.testing`, names starting with
``toy_``) are tiny systems for fast tests. Scenes from your own meshes come from
:func:`fem_scene_from_mesh` and :func:`cloth_scene_from_mesh`; :func:`scene_from_spec` rebuilds any
of them from the record a checkpoint keeps (:mod:`redsim.scenes.spec`).

Example::

    import redsim
    scene = redsim.scenes.build("chain", links=12, gravity=False)
    scene.describe()["n"]    # 144
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

from redsim.scene import Scene
from redsim.scenes.catalog import CATALOG
from redsim.scenes.from_mesh import cloth_scene_from_mesh, fem_scene_from_mesh
from redsim.scenes.spec import SceneSpecError, mesh_scene, scene_from_spec, scene_spec
from redsim.scenes.testing import TOYS

SCENES: dict[str, Callable[..., Scene]] = {**CATALOG, **TOYS}
"""Every named scene builder; each is keyword-only and every argument has a default."""


def names() -> list[str]:
    """Names of all registered scenes (catalog first, then toys)."""
    return list(SCENES)


def parameters(name: str) -> dict[str, Any]:
    """The parameters of scene ``name`` with their defaults."""
    builder = _builder(name)
    return {k: p.default for k, p in inspect.signature(builder).parameters.items()}


def build(name: str, **params: Any) -> Scene:
    """Build the scene called ``name`` with keyword ``params`` overriding its defaults.

    Raises:
        ValueError: on an unknown name (the message lists the valid names), an unknown
            parameter (it lists the scene's parameters) or a bad parameter value.
    """
    builder = _builder(name)
    valid = list(inspect.signature(builder).parameters)
    unknown = sorted(set(params) - set(valid))
    if unknown:
        raise ValueError(f"scene {name!r} has no parameter(s) {unknown}; valid parameters: {valid}")
    return builder(**params)


def _builder(name: str) -> Callable[..., Scene]:
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; valid scenes: {names()}")
    return SCENES[name]


__all__ = [
    "SCENES",
    "SceneSpecError",
    "build",
    "cloth_scene_from_mesh",
    "fem_scene_from_mesh",
    "mesh_scene",
    "names",
    "parameters",
    "scene_from_spec",
    "scene_spec",
]
