"""Scene specs: the JSON-able record of how to rebuild a scene, and the one function that rebuilds it.

A spec is ``{"scene": NAME, "scene_params": {...}}``, the two keys a checkpoint's ``.json``
holds, so a checkpoint's metadata is itself a spec. For a catalog scene the params are its
builder arguments. For a scene from a user's mesh (:func:`fem_scene_from_mesh`,
:func:`tet_scene_from_mesh`, :func:`cloth_scene_from_mesh`) they also hold ``builder`` ("fem", "tets" or "cloth"),
``source`` (the
mesh file's absolute path; a relative one, in a spec file written by hand, is read from the spec file's folder)
and ``mesh_sha256`` (the file's hash, which a hand-written spec may leave out): the file is re-read and must be
unchanged; ``selections`` holds the file's vertex indices of a ``pin`` or handle given as a mask or an
index list.

Example::

    spec = scene_spec(scene)            # {"scene": "mesh_fem", "scene_params": {"builder": "fem", ...}}
    again = scene_from_spec(spec)       # same fingerprint
"""

from __future__ import annotations

import difflib
import inspect
import json
import os
from collections.abc import Callable, Mapping
from typing import Any

from redsim.meshes import file_sha256
from redsim.scene import Scene
from redsim.scenes.from_mesh import IN_MEMORY_TETS, cloth_scene_from_mesh, fem_scene_from_mesh, tet_scene_from_mesh

MESH_BUILDERS: dict[str, Callable[..., Scene]] = {
    "fem": fem_scene_from_mesh,
    "tets": tet_scene_from_mesh,
    "cloth": cloth_scene_from_mesh,
}
"""Builders of scenes from a user's mesh file, by ``--kind``."""

_RECORD_ONLY = ("builder", "source", "mesh_sha256", "mesh_digest", "selections")
"""Mesh-scene params that describe the input rather than being builder arguments."""


class SceneSpecError(ValueError):
    """A spec that cannot be turned back into its scene (unknown scene, missing or changed mesh file, ...)."""


def read_spec(path: str | os.PathLike[str]) -> Mapping[str, Any]:
    """The JSON object in the file at ``path`` (a ``.pt``: the ``.json`` beside it).

    Raises:
        SceneSpecError: the file cannot be read, or holds no JSON object.
    """
    path = os.fspath(path)
    if path.endswith(".pt"):  # a checkpoint's .json (a training state STEM.fit.pt: its fit's STEM.json)
        beside = path[: -len(".pt")] + ".json"
        path = beside if os.path.isfile(beside) or not path.endswith(".fit.pt") else path[: -len(".fit.pt")] + ".json"
    try:
        with open(path) as handle:
            doc = json.load(handle)
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as err:
        raise SceneSpecError(f"cannot read the scene spec {path}: {err}") from err
    if not isinstance(doc, dict):
        raise SceneSpecError(f"the scene spec {path} is not a JSON object")
    return doc


def scene_spec(scene: Scene) -> dict[str, Any]:
    """The spec that rebuilds ``scene`` (see the module doc)."""
    return {"scene": scene.name, "scene_params": dict(scene.params)}


def scene_arguments(scene: Scene) -> list[str]:
    """The ``redsim`` command-line arguments that build ``scene``: ``NAME --param K=V ...`` for a catalog
    scene, ``--mesh PATH --kind KIND --param K=V ...`` for a scene from a mesh file."""
    params = dict(scene.params)
    kind = params.get("builder")
    if kind is None:
        parts = [scene.name]
    else:
        parts = ["--mesh", str(params.get("source")), "--kind", str(kind)]
        params = _builder_args(scene.name, params, strict=False)  # recorded selections as indices: rerunnable
        params["name"] = scene.name
    for key, value in sorted(params.items()):
        parts += ["--param", f"{key}={json.dumps(value)}"]
    return parts


def mesh_scene(kind: str, path: str | os.PathLike[str], **params: Any) -> Scene:
    """A scene from the mesh file at ``path`` with builder ``kind`` ("fem", "tets" or "cloth") and its arguments.

    Raises:
        SceneSpecError: an unknown kind.
        ValueError: a parameter the builder does not take (the valid ones are named).
        FileNotFoundError, ValueError: from the builder (missing file, bad mesh or argument).
    """
    if kind not in MESH_BUILDERS:
        raise SceneSpecError(f"unknown mesh builder kind {kind!r}; valid: {', '.join(MESH_BUILDERS)}")
    _check_builder_params(kind, params)
    return MESH_BUILDERS[kind](path, **params)


def _check_builder_params(kind: str, params: Mapping[str, Any], *, leave_out: tuple[str, ...] = ()) -> None:
    """Raise ValueError naming the valid ones where ``params`` holds one the ``kind`` builder does not take (or one
    of ``leave_out``, which the caller gives itself)."""
    valid = [key for key in list(inspect.signature(MESH_BUILDERS[kind]).parameters)[1:] if key not in leave_out]
    if unknown := [key for key in params if key not in valid]:
        raise ValueError(f"unknown parameter(s) {unknown} of a {kind} mesh scene; valid: {', '.join(valid)}")


def scene_from_spec(doc: Mapping[str, Any] | str | os.PathLike[str]) -> Scene:
    """Rebuild the scene a spec (or a checkpoint's metadata) describes.

    Args:
        doc: The spec, or the path of a JSON file holding one (a spec file, or a checkpoint's ``.json``; a
            checkpoint's ``.pt`` reads the ``.json`` beside it).

    Raises:
        SceneSpecError: an unreadable file or one that is not a JSON object, no scene name, an unknown catalog
            scene, a mesh scene built from an in-memory mesh or from a vertex selection that is not recorded (a
            Python function's), or a mesh file that is missing or whose SHA-256 differs from the recorded one (both
            hashes are named).
        ValueError: parameters the builder rejects, or does not take (the valid ones are named).
    """
    from redsim import scenes

    folder = None
    if isinstance(doc, (str, os.PathLike)):
        folder = os.path.dirname(os.path.abspath(doc))
        doc = read_spec(doc)
    name = doc.get("scene")
    if not isinstance(name, str):
        raise SceneSpecError("the spec names no scene (expected a 'scene' string)")
    if "scene_params" not in doc and (typo := difflib.get_close_matches("scene_params", list(doc), 1, 0.8)):
        raise SceneSpecError(f"scene {name!r}: the spec has no 'scene_params' but has {typo[0]!r}: a typo?")
    given = doc.get("scene_params") or {}
    if not isinstance(given, Mapping):  # a list of pairs was taken as one, other lists gave dict()'s own message
        raise SceneSpecError(f"scene {name!r}: scene_params must be a JSON object, got {type(given).__name__}")
    params = dict(given)
    kind = params.get("builder")
    if kind is None:
        if name not in scenes.names():
            raise SceneSpecError(
                f"unknown scene {name!r} (not in the catalog and not built from a mesh file; "
                f"a scene built in Python must be passed in as an object)"
            )
        return scenes.build(name, **params)
    if kind not in MESH_BUILDERS:
        raise SceneSpecError(f"scene {name!r}: unknown mesh builder {kind!r}; valid: {', '.join(MESH_BUILDERS)}")
    source, recorded = params.get("source"), params.get("mesh_sha256")
    if source in ("<trimesh>", IN_MEMORY_TETS):
        fix = "save the mesh to a file" if source == "<trimesh>" else "save the arrays with numpy.savez"
        raise SceneSpecError(
            f"scene {name!r} was built from an in-memory mesh (source {source!r}); {fix} and build the scene from "
            "that file to rebuild it"
        )
    if not isinstance(source, str) or not source:
        raise SceneSpecError(f"scene {name!r}: its spec names no mesh file (a 'source' path in scene_params)")
    if folder is not None and not os.path.isabs(source):  # a hand-written spec file's relative path
        source = os.path.join(folder, source)
    if not os.path.isfile(source):
        raise SceneSpecError(f"scene {name!r}: mesh file {source!r} is missing")
    now = file_sha256(source)
    if recorded is not None and now != recorded:
        raise SceneSpecError(
            f"scene {name!r}: mesh file {source!r} changed since the scene was recorded "
            f"(sha256 {recorded} recorded, {now} now)"
        )
    args = _builder_args(name, params)
    _check_builder_params(kind, args, leave_out=("name",))  # the spec's 'scene' names it
    return MESH_BUILDERS[kind](source, name=name, **args)


def _builder_args(name: str, params: Mapping[str, Any], *, strict: bool = True) -> dict[str, Any]:
    """A mesh scene's builder arguments from its params: the record-only keys left out, and a ``pin`` or handle
    recorded by a hash label (``ids:...``) given as the file's vertex indices ``selections`` holds. One not recorded
    (a Python function's, or recorded before redsim recorded them) raises :class:`SceneSpecError` where ``strict``,
    else keeps its label."""
    args = {k: v for k, v in params.items() if k not in _RECORD_ONLY}
    selections = params.get("selections") or {}
    if str(args.get("pin", "")).startswith("ids:"):
        if "pin" in selections:
            args["pin"] = selections["pin"]
        elif strict:
            raise SceneSpecError(
                f"scene {name!r} pinned a vertex selection that is not recorded ({args['pin']}: a Python function's, "
                "or a mask or index list recorded before redsim recorded them); rebuild it in Python"
            )
    given = args.get("handles")
    handles = dict(given) if isinstance(given, Mapping) else {}  # not a dict: the builder refuses it, naming it
    for key, label in handles.items():
        if str(label).startswith("ids:"):
            if key in selections.get("handles", {}):
                handles[key] = selections["handles"][key]
            elif strict:
                raise SceneSpecError(
                    f"scene {name!r} placed handle {key!r} on a vertex selection that is not recorded ({label}: a "
                    "Python function's, or a mask or index list recorded before redsim recorded them); rebuild it "
                    "in Python"
                )
    if handles:
        args["handles"] = handles
    return args


__all__ = [
    "MESH_BUILDERS",
    "SceneSpecError",
    "mesh_scene",
    "read_spec",
    "scene_arguments",
    "scene_from_spec",
    "scene_spec",
]
