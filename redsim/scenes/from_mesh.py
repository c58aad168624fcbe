"""Scenes from user meshes.

- :func:`fem_scene_from_mesh`: a watertight surface mesh, voxel-tetrahedralized, as a
  neo-Hookean solid.
- :func:`tet_scene_from_mesh`: a tetrahedral mesh of your own (a ``.npz`` of vertices and tets), used as given.
- :func:`cloth_scene_from_mesh`: a triangle surface, used directly as cloth.

Both are made with the builder toolkit the catalog uses (:mod:`redsim.scenes.toolkit`).
"""

from __future__ import annotations

import functools
import hashlib
import os
import warnings
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from redsim import meshes
from redsim.scene import Scene, SceneBuilder
from redsim.scenes.toolkit import (
    PinSpec,
    add_cloth,
    add_fem,
    add_gravity,
    check_bool,
    check_int,
    check_poisson,
    check_positive,
    select_vertices,
)

if TYPE_CHECKING:  # imported where used: import redsim needs none of trimesh (slow to import)
    import trimesh

LARGE_MESH_M = 10.0  # a mesh spanning more [m] is warned about: likely a file in millimetres or centimetres
SMALL_MESH_M = 1e-3  # a mesh spanning less [m] is warned about: likely a file in kilometres, or a wrong scale
INFLATED_SOLID = 2.0  # a voxel solid of more than this many times its mesh's volume is warned about
IN_MEMORY_TETS = "<arrays>"  # the source of a tet scene built from arrays: a spec cannot rebuild it
MAX_VOXELS = 200_000_000  # cells of the voxel grid over the bounding box; more is refused (minutes and GBs)


def _check_voxel_count(mesh: trimesh.Trimesh, pitch: float) -> None:
    """Refuse a voxel pitch [m] whose voxel grid over the mesh's bounding box has more than :data:`MAX_VOXELS` cells:
    voxelizing fills a dense array of them (two 1 cm cubes 1 m apart at 2 mm: 1.3e8 cells, 11 s and 0.9 GB)."""
    cells = meshes.grid_cells(mesh, pitch)
    if cells > MAX_VOXELS:
        raise ValueError(
            f"voxel_pitch {pitch:g} m would voxelize this mesh's {' x '.join(f'{e:.3g}' for e in mesh.extents)} m "
            f"bounding box into ~{cells:.3g} cells (at most {MAX_VOXELS:.0e}); choose a larger voxel_pitch, or "
            "target_dofs instead"
        )


def _mesh_input(mesh_or_path: trimesh.Trimesh | str | os.PathLike[str]) -> tuple[trimesh.Trimesh, str]:
    import trimesh

    if isinstance(mesh_or_path, trimesh.Trimesh):
        mesh = mesh_or_path.copy()
        if len(mesh.faces) == 0:
            raise ValueError("the mesh has no faces")
        if not bool(np.isfinite(mesh.vertices).all()):  # as meshes.load_mesh refuses a file's
            raise ValueError("the mesh has non-finite vertex coordinates")
        return mesh, "<trimesh>"
    if isinstance(mesh_or_path, str | os.PathLike):
        return meshes.load_mesh(mesh_or_path), os.path.abspath(os.fspath(mesh_or_path))
    raise ValueError(f"expected a trimesh.Trimesh or a file path, got {type(mesh_or_path).__name__}")


def _scaled(mesh: trimesh.Trimesh, scale: float, source: str) -> trimesh.Trimesh:
    """The mesh with its coordinates multiplied by ``scale`` (in place); a warning where the result spans more than
    :data:`LARGE_MESH_M` metres, the size of a file in millimetres or centimetres read as metres."""
    if scale != 1.0:
        mesh.apply_scale(scale)
    _warn_span(float(np.max(mesh.extents)), source)
    return mesh


def _warn_span(span: float, source: str) -> None:
    """Warn where a mesh spans [m] more than :data:`LARGE_MESH_M` (a file in millimetres or centimetres read as
    metres) or less than :data:`SMALL_MESH_M`; the warning points at the builder's caller."""
    if span > LARGE_MESH_M:
        warnings.warn(
            f"mesh {source!r} spans {span:.4g} m: redsim reads a mesh's coordinates in metres; for a file in "
            "millimetres give scale=1e-3 (centimetres: 1e-2; on the command line --param scale=0.001)",
            UserWarning,
            stacklevel=4,
        )
    elif 0.0 < span < SMALL_MESH_M:
        warnings.warn(
            f"mesh {source!r} spans {span:.4g} m, less than a millimetre: redsim reads a mesh's coordinates in "
            "metres; give scale= to convert them (on the command line --param scale=...)",
            UserWarning,
            stacklevel=4,
        )


def _tet_input(
    mesh_or_path: tuple[np.ndarray, np.ndarray] | str | os.PathLike[str], scale: float
) -> tuple[np.ndarray, np.ndarray, str]:
    """(vertices [V, 3] [m] times ``scale``, tets [T, 4], source): from a ``.npz`` file (its absolute path is the
    source) or a (vertices, tets) pair (``"<arrays>"``), checked by :func:`redsim.meshes.check_tet_mesh`."""
    if isinstance(mesh_or_path, str | os.PathLike):
        vertices, tets = meshes.load_tets(mesh_or_path)
        source = os.path.abspath(os.fspath(mesh_or_path))
    elif isinstance(mesh_or_path, tuple | list) and len(mesh_or_path) == 2:
        vertices, tets = meshes.check_tet_mesh(*mesh_or_path, IN_MEMORY_TETS)
        source = IN_MEMORY_TETS
    else:
        raise ValueError(
            f"expected a .npz file path or a (vertices, tets) pair, got {type(mesh_or_path).__name__}; "
            f"{meshes.TET_FILE_HINT}"
        )
    vertices = vertices * scale
    _warn_span(float(np.max(vertices.max(0) - vertices.min(0))), source)
    return vertices, tets, source


def _volume(mesh: trimesh.Trimesh) -> float:
    """The mesh's enclosed volume [m^3], 0 for a flat one (trimesh's centre of mass divides by it)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return abs(float(mesh.volume))


def _warn_if_inflated(mesh: trimesh.Trimesh, tets: np.ndarray, pitch: float, source: str, chosen: bool) -> None:
    """Warn where the voxel solid (``tets`` [T, 4], six per voxel of side ``pitch`` [m]) holds more than
    :data:`INFLATED_SOLID` times the mesh's volume: its mass, and every load scaled by it, grow the same."""
    ratio = tets.shape[0] / 6 * pitch**3 / _volume(mesh)
    if ratio > INFLATED_SOLID:
        fix = "more target_dofs, or a voxel_pitch" if chosen else "a voxel_pitch"
        warnings.warn(
            f"the voxel solid of mesh {source!r} at pitch {pitch:.3g} m has {ratio:.1f}x the mesh's volume (and "
            f"mass): every voxel the surface passes through is kept, so parts thinner than a few voxels grow; "
            f"give {fix} well below the mesh's thinnest part",
            UserWarning,
            stacklevel=3,
        )


def _weld(mesh: trimesh.Trimesh) -> None:
    """Merge the vertices that share a position (in place). A file's UV seams and per-face normals (a textured or
    flat-shaded export) split one vertex into several, which would cut cloth apart and open a closed surface."""
    mesh.merge_vertices(merge_tex=True, merge_norm=True)


def _pinned(
    given: np.ndarray, vertices: np.ndarray, pin: PinSpec, *, tolerance: float, nearest: bool = False, what: str = "pin"
) -> np.ndarray:
    """The indices into ``vertices`` (the welded, cleaned mesh, or the voxel solid) of the pin. A mask or index list
    counts the vertices as given (``given`` [V0, D], the file's): they are found again by position (``nearest``:
    each pins the vertex nearest it, as a voxel solid's grid holds none of the file's); names and callables see
    ``vertices``."""
    if pin is None or isinstance(pin, str) or callable(pin):
        return select_vertices(vertices, pin, tolerance=tolerance, what=what)
    import scipy.spatial

    points = given[select_vertices(given, pin, tolerance=tolerance, what=what)]
    distance, index = scipy.spatial.cKDTree(vertices).query(points)
    if nearest:
        return np.unique(index)
    scale = max(float(np.abs(vertices).max()), 1.0)  # welding merges within ~1e-8: found within 1e-6 of the size
    return np.unique(index[distance <= 1e-6 * scale])  # a given vertex no triangle uses is not in the cloth


def _check_pins(pin: PinSpec, pinned: np.ndarray, vertices: np.ndarray, elements: np.ndarray, gravity: bool) -> None:
    """Refuse pins [P] that leave nothing to move, or, under gravity, a piece of the mesh (vertices [V, D] joined by
    elements [T, k]) with nothing to hang from."""
    count = vertices.shape[0]
    if pinned.size == count:
        flat = isinstance(pin, str) and pin != "none"  # e.g. a sheet lying in the plane the default 'max_y' names
        fix = ": the mesh is flat along that axis; pin another side (e.g. pin='min_x') or vertex indices"
        raise ValueError(f"pin {_shown(pin)} selects every vertex; nothing would move" + (fix if flat else ""))
    if not gravity:
        return
    shown = _shown(pin)
    if pinned.size == 0:
        raise ValueError(
            f"pin {shown} selects no vertex: under gravity the body free-falls and its energy has no minimum; "
            "pin some vertices (e.g. pin='max_y') or give gravity=False"
        )
    import scipy.sparse
    from scipy.sparse.csgraph import connected_components

    heads = np.repeat(elements[:, :1], elements.shape[1], axis=1).ravel()
    graph = scipy.sparse.coo_matrix((np.ones(heads.size), (heads, elements.ravel())), shape=(count, count))
    pieces, label = connected_components(graph, directed=False)
    loose = np.setdiff1d(np.arange(pieces), label[pinned])
    if loose.size:
        first = int(np.nonzero(label == loose[0])[0][0])
        raise ValueError(
            f"{loose.size} of the mesh's {pieces} separate pieces hold no pinned vertex (pin {shown}), e.g. the "
            f"one with vertex {first} at {np.round(vertices[first], 6).tolist()}: under gravity it free-falls; pin "
            "it too, remove it, or give gravity=False"
        )


def _digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def _scale_param(scale: float) -> dict[str, float]:
    """``{"scale": scale}``, or nothing at 1: the params (and so the fingerprint) of a scene made before the
    option existed stay its own."""
    return {} if scale == 1.0 else {"scale": scale}


def _handles_param(labels: dict[str, str]) -> dict[str, dict[str, str]]:
    """``{"handles": labels}``, or nothing without extra handles (the fingerprints of scenes made before the option
    stay their own)."""
    return {"handles": labels} if labels else {}


def _shown(spec: PinSpec) -> str:
    """A vertex selection as an error message names it: a name quoted, a short list or mask as written, a long one
    by its kind and length, a callable by its name."""
    if callable(spec):
        return getattr(spec, "__name__", type(spec).__name__)
    if spec is None or isinstance(spec, str):
        return repr(spec)
    values = np.asarray(spec).tolist()
    text = repr(values)
    return text if len(text) <= 40 else f"{type(spec).__name__} of {len(values)} entries"


def _selections_param(given: np.ndarray, pin: PinSpec, handles: Mapping[str, PinSpec] | None) -> dict[str, Any]:
    """``{"selections": {"pin": indices, "handles": {name: indices}}}``: the file's vertex indices of each selection
    given as a mask or an index list (its label is a hash, ``ids:...``), so that a spec rebuilds it; nothing without
    any (a name is its own record, a callable cannot be recorded). Left out of the fingerprint, which hashes what they
    select."""

    def indices(spec: PinSpec, what: str) -> list[int] | None:
        if spec is None or isinstance(spec, str) or callable(spec):
            return None
        return select_vertices(given, spec, tolerance=0.0, what=what).tolist()

    recorded: dict[str, Any] = {}
    if (chosen := indices(pin, "pin")) is not None:
        recorded["pin"] = chosen
    kept = {name: indices(spec, f"handle {name!r} selection") for name, spec in (handles or {}).items()}
    if kept := {name: chosen for name, chosen in kept.items() if chosen is not None}:
        recorded["handles"] = kept
    return {"selections": recorded} if recorded else {}


def _pin_label(spec: PinSpec, pinned: np.ndarray) -> str:
    return spec if isinstance(spec, str) else ("none" if spec is None else f"ids:{_digest(pinned)}")


def _add_handles(
    b: SceneBuilder,
    ids: torch.Tensor,
    masses: np.ndarray,
    pinned: np.ndarray,
    handles: Mapping[str, PinSpec] | None,
    select: Callable[..., np.ndarray],
    whole: str,
) -> dict[str, str]:
    """Add each of ``handles`` (name -> a vertex selection, as a pin's; ``select`` turns one into vertex indices)
    at the mass-weighted centre of its vertices, after the whole body's handle ``whole``, in name order (the order
    a spec's JSON, its keys sorted, rebuilds); their labels for the params ({} without any)."""
    if handles is None:
        return {}
    if not isinstance(handles, Mapping):
        raise ValueError(
            f"handles must be a dict of name -> vertex selection (e.g. {{'tip': 'max_x'}}), got {handles!r}"
        )
    labels = {}
    for name in handles:
        if not isinstance(name, str) or not name or name == whole:
            raise ValueError(f"a handle name must be a non-empty string other than {whole!r}, got {name!r}")
    for name in sorted(handles):
        spec = handles[name]
        chosen = select(spec, what=f"handle {name!r} selection")
        if chosen.size == 0:
            raise ValueError(f"handle {name!r} ({_shown(spec)}) selects no vertex")
        if np.isin(chosen, pinned).all():
            raise ValueError(
                f"handle {name!r} ({_shown(spec)}) selects only pinned vertices: a load on it would move nothing"
            )
        label = _pin_label(spec, chosen)
        b.add_handle(name, b.particle_points(ids[torch.as_tensor(chosen)]), torch.as_tensor(masses[chosen]))
        labels[name] = label
    return labels


# -- public builders ---------------------------------------------------------------------------
def fem_scene_from_mesh(
    mesh_or_path: trimesh.Trimesh | str | os.PathLike[str],
    *,
    voxel_pitch: float | None = None,
    target_dofs: int = 3000,
    young: float = 1e5,
    poisson: float = 0.45,
    density: float = 1000.0,
    pin: PinSpec = "min_y",
    gravity: bool = True,
    scale: float = 1.0,
    handles: Mapping[str, PinSpec] | None = None,
    name: str = "mesh_fem",
) -> Scene:
    """A neo-Hookean solid from a watertight surface mesh, voxel-tetrahedralized.

    The mesh is voxelized (trimesh ``voxelized(pitch).fill()``) and each voxel split into six conforming
    Kuhn tets. Every voxel the surface passes through is kept, so the solid is larger than the mesh by up to
    about a voxel on each side (a 0.2 x 0.04 x 0.04 m bar at pitch 0.01 m: 0.21 x 0.05 x 0.05 m, 60% more
    mass): choose a pitch well below the mesh's thinnest part (a solid of more than :data:`INFLATED_SOLID` times the
    mesh's volume is warned about). Coordinates stay those of the mesh; gravity pulls along -y.

    Args:
        mesh_or_path: A ``trimesh.Trimesh`` or a mesh file path [m].
        voxel_pitch: Voxel side [m]; None chooses one so that n is about ``target_dofs``.
        target_dofs: Wanted free DOF count when ``voxel_pitch`` is None.
        young: Young's modulus [Pa].
        poisson: Poisson ratio in (-1, 0.5).
        density: Mass density [kg/m^3].
        pin: Which vertices to pin (see :data:`PinSpec`): a name or callable selects among the solid's (voxel
            grid) vertices ("min_y" pins the bottom voxel layer); a mask or index list counts the mesh file's own
            vertices, each pinning the solid's vertex nearest it.
        gravity: Add gravity (9.81 m/s^2 along -y).
        scale: Multiplies the mesh's coordinates (1e-3 for a file in millimetres); a mesh spanning more than
            :data:`LARGE_MESH_M` or less than :data:`SMALL_MESH_M` metres after it is warned about.
        handles: More handles, name -> a vertex selection as ``pin`` takes (e.g. ``{"tip": "max_x"}``): each at
            the mass-weighted centre of its vertices, after "body" in name order (a load there spreads over them
            by mass).
        name: Scene name.

    Returns:
        The scene; handle "body" (mass-weighted over all vertices, i.e. a force at the centre of
        mass), then ``handles``; surface "elastic" (the voxel boundary).

    Raises:
        FileNotFoundError: for a missing file.
        ValueError: for an unreadable, non-watertight or flat mesh, non-finite vertices, a bad parameter, or pins
            that select every vertex (or none, under gravity).
    """
    young = check_positive("young", young)
    poisson = check_poisson(poisson)
    density = check_positive("density", density)
    gravity = check_bool("gravity", gravity)
    scale = check_positive("scale", scale)
    mesh, source = _mesh_input(mesh_or_path)
    _scaled(mesh, scale, source)
    given = np.asarray(mesh.vertices, dtype=np.float64).copy()
    _weld(mesh)
    # zero-area and repeated faces (an exporter's) close nothing and open nothing: dropped, as the cloth does
    mesh.update_faces(mesh.nondegenerate_faces() & mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise ValueError(f"every face of mesh {source!r} has zero area: it encloses no volume")
    if not mesh.is_watertight:
        faces_per_edge = np.unique(mesh.edges_sorted, axis=0, return_counts=True)[1]  # 2 on a closed surface
        open_edges, joints = int((faces_per_edge == 1).sum()), int((faces_per_edge > 2).sum())
        joined = f" and {joints} edges shared by more than two faces, where parts meet: separate them" if joints else ""
        raise ValueError(
            f"mesh {source!r} is not watertight ({open_edges} open edges{joined}); a solid needs a closed surface: "
            "close it first (e.g. trimesh's fill_holes() or a mesh repair tool), or simulate it as a sheet with "
            "cloth_scene_from_mesh (--kind cloth)"
        )
    if _volume(mesh) <= 1e-9 * float(np.prod(np.maximum(mesh.extents, 1e-300))):
        raise ValueError(f"mesh {source!r} is closed but encloses no volume (its faces are flat)")
    if voxel_pitch is None:
        target = check_int("target_dofs", target_dofs, 24)
        try:
            pitch = meshes.pitch_for_vertex_count(mesh, target // 3, max_cells=MAX_VOXELS)
        except ValueError as exc:
            raise ValueError(f"target_dofs {target_dofs} for mesh {source!r}: {exc}; give fewer target_dofs") from exc
    else:
        pitch = check_positive("voxel_pitch", voxel_pitch)
        _check_voxel_count(mesh, pitch)
    vertices, tets = meshes.voxel_tet_mesh(mesh, pitch)
    if tets.shape[0] <= 6:  # one voxel (six tets): voxelizing always fills at least one, whatever the pitch
        size = " x ".join(f"{e:.3g}" for e in mesh.extents)
        given = f"voxel_pitch {pitch:g} m" if voxel_pitch is not None else f"target_dofs {target_dofs}"
        fix = "a smaller voxel_pitch" if voxel_pitch is not None else "more target_dofs (or a voxel_pitch)"
        raise ValueError(
            f"{given} voxelizes this mesh ({size} m) into a single voxel (pitch {pitch:.3g} m, as large as the mesh):"
            f" no solid to simulate; choose {fix}"
        )
    _warn_if_inflated(mesh, tets, pitch, source, chosen=voxel_pitch is None)
    select = functools.partial(_pinned, given, vertices, tolerance=0.25 * pitch, nearest=True)
    record = {
        "builder": "fem",
        "source": source,
        "mesh_sha256": None if source == "<trimesh>" else meshes.file_sha256(source),
        "mesh_digest": _digest(np.asarray(mesh.vertices), np.asarray(mesh.faces)),
        "voxel_pitch": pitch,
    }
    material = {"young": young, "poisson": poisson, "density": density}
    return _solid(
        vertices,
        tets,
        given,
        select,
        pin=pin,
        handles=handles,
        gravity=gravity,
        scale=scale,
        material=material,
        record=record,
        name=name,
        description=f"neo-Hookean voxel solid from {source} ({tets.shape[0]} tets, pitch {pitch:.3g} m); SI units",
    )


def _solid(
    vertices: np.ndarray,
    tets: np.ndarray,
    given: np.ndarray,
    select: Callable[..., np.ndarray],
    *,
    pin: PinSpec,
    handles: Mapping[str, PinSpec] | None,
    gravity: bool,
    scale: float,
    material: dict[str, float],
    record: dict[str, Any],
    name: str,
    description: str,
) -> Scene:
    """The neo-Hookean solid of ``tets`` [T, 4] on ``vertices`` [V, 3] [m] (``material``: young [Pa], poisson,
    density [kg/m^3]): ``pin`` held, the whole body's handle "body" then ``handles`` (``select`` turns a selection
    into vertex indices; ``given`` [V0, 3] are the vertices a mask or index list counts), gravity; its params are
    ``record`` (builder, source, hashes, ...) then the material and options."""
    pinned = select(pin)
    _check_pins(pin, pinned, vertices, tets, gravity)
    b = SceneBuilder(dim=3)
    ids = add_fem(b, vertices, tets, **material)
    if pinned.size:
        b.pin_particles(ids[torch.as_tensor(pinned)])
    masses = meshes.lumped_masses(vertices, tets, material["density"])
    b.add_handle("body", b.particle_points(ids), torch.as_tensor(masses))
    labels = _add_handles(b, ids, masses, pinned, handles, select, "body")
    if gravity:
        add_gravity(b)
    params = (
        record
        | material
        | {"pin": _pin_label(pin, pinned), "gravity": gravity}
        | _scale_param(scale)
        | _handles_param(labels)
        | _selections_param(given, pin, handles)
    )
    return b.finalize(name, params=params, description=description)


def tet_scene_from_mesh(
    mesh_or_path: tuple[np.ndarray, np.ndarray] | str | os.PathLike[str],
    *,
    young: float = 1e5,
    poisson: float = 0.45,
    density: float = 1000.0,
    pin: PinSpec = "min_y",
    gravity: bool = True,
    scale: float = 1.0,
    handles: Mapping[str, PinSpec] | None = None,
    name: str = "mesh_tets",
) -> Scene:
    """A neo-Hookean solid on a tetrahedral mesh of your own, used as given (no voxelization).

    A tet mesher's file (Gmsh ``.msh``, VTK, ...) becomes the ``.npz`` this reads in two lines, e.g. with meshio:
    ``m = meshio.read("part.msh"); numpy.savez("part.npz", vertices=m.points, tets=m.cells_dict["tetra"])``.
    Tets of either orientation are taken (negative ones are reordered); vertices no tet uses (a mesher's geometry
    points) are left out. Gravity pulls along -y.

    Args:
        mesh_or_path: A ``.npz`` file path holding ``vertices`` [V, 3] [m] and ``tets`` [T, 4] (vertex indices
            counted from 0), or the pair (vertices, tets).
        young: Young's modulus [Pa].
        poisson: Poisson ratio in (-1, 0.5).
        density: Mass density [kg/m^3].
        pin: Which vertices to pin (see :data:`PinSpec`): a name (within 0.1% of the bounding-box diagonal, e.g.
            "min_y" pins the bottom), a callable, or a mask or index list of the given vertices.
        gravity: Add gravity (9.81 m/s^2 along -y).
        scale: Multiplies the coordinates (1e-3 for millimetres); a mesh spanning more than :data:`LARGE_MESH_M`
            or less than :data:`SMALL_MESH_M` metres after it is warned about.
        handles: More handles, name -> a vertex selection as ``pin`` takes (e.g. ``{"tip": "max_x"}``): each at
            the mass-weighted centre of its vertices, after "body" in name order.
        name: Scene name.

    Returns:
        The scene; handle "body" (mass-weighted over all vertices: a force at the centre of mass), then
        ``handles``; surface "elastic" (the mesh's boundary faces).

    Raises:
        FileNotFoundError: for a missing file.
        ValueError: for a file that is not such a ``.npz``, a wrong shape, a non-finite vertex, an index outside
            the vertices, a degenerate (zero-volume) tet, a bad parameter, or pins that select every vertex (or,
            under gravity, none, or leave a piece of the mesh hanging from nothing).
    """
    young = check_positive("young", young)
    poisson = check_poisson(poisson)
    density = check_positive("density", density)
    gravity = check_bool("gravity", gravity)
    scale = check_positive("scale", scale)
    given, given_tets, source = _tet_input(mesh_or_path, scale)
    used = np.unique(given_tets)  # the vertices some tet holds, in the given order
    renumber = np.full(given.shape[0], -1, dtype=np.int64)
    renumber[used] = np.arange(used.size)
    vertices = given[used]
    _, copies = np.unique(vertices, axis=0, return_counts=True)
    if (copies > 1).any():  # a "tet soup" (each tet its own corners) would fall apart into loose tets
        warnings.warn(
            f"mesh {source!r}: {int((copies - 1).sum())} vertices sit where another does; the mesh is used as given "
            "(not welded), so tets that meet only at such copies are not joined",
            UserWarning,
            stacklevel=2,
        )
    try:
        tets = meshes.orient_tets(vertices, renumber[given_tets])
    except ValueError as exc:
        raise ValueError(f"mesh {source!r}: {exc}; a solid needs tets of nonzero volume") from exc
    tolerance = 1e-3 * float(np.linalg.norm(vertices.max(0) - vertices.min(0)))

    def select(spec: PinSpec, what: str = "pin") -> np.ndarray:
        """Indices into ``vertices`` of a selection: a name or callable sees the used vertices, a mask or index
        list counts the given ones (a vertex no tet uses selects nothing)."""
        if spec is None or isinstance(spec, str) or callable(spec):
            return select_vertices(vertices, spec, tolerance=tolerance, what=what)
        chosen = renumber[select_vertices(given, spec, tolerance=tolerance, what=what)]
        return np.unique(chosen[chosen >= 0])

    record = {
        "builder": "tets",
        "source": source,
        "mesh_sha256": None if source == IN_MEMORY_TETS else meshes.file_sha256(source),
        "mesh_digest": _digest(given, given_tets),
    }
    return _solid(
        vertices,
        tets,
        given,
        select,
        pin=pin,
        handles=handles,
        gravity=gravity,
        scale=scale,
        material={"young": young, "poisson": poisson, "density": density},
        record=record,
        name=name,
        description=f"neo-Hookean solid on the tet mesh {source} ({tets.shape[0]} tets); SI units",
    )


def cloth_scene_from_mesh(
    mesh_or_path: trimesh.Trimesh | str | os.PathLike[str],
    *,
    young: float = 1e6,
    poisson: float = 0.3,
    thickness: float = 1e-3,
    bending: float = 1e-4,
    density: float = 200.0,
    pin: PinSpec = "max_y",
    gravity: bool = True,
    scale: float = 1.0,
    handles: Mapping[str, PinSpec] | None = None,
    name: str = "mesh_cloth",
) -> Scene:
    """Cloth made directly from the triangles of a surface mesh (StVK membrane + discrete-shell bending).

    Args:
        mesh_or_path: A ``trimesh.Trimesh`` or a mesh file path [m]; open or closed, manifold.
        young: Young's modulus of the sheet [Pa].
        poisson: Poisson ratio in (-1, 0.5).
        thickness: Sheet thickness [m].
        bending: Bending stiffness per hinge [J] (0: no bending term).
        density: Material density [kg/m^3] (areal density = density * thickness).
        pin: Which vertices to pin (see :data:`PinSpec`); "max_y" pins the top (within 0.1% of
            the bounding-box diagonal).
        gravity: Add gravity (9.81 m/s^2 along -y).
        scale: Multiplies the mesh's coordinates (1e-3 for a file in millimetres); a mesh spanning more than
            :data:`LARGE_MESH_M` or less than :data:`SMALL_MESH_M` metres after it is warned about.
        handles: More handles, name -> a vertex selection as ``pin`` takes (e.g. ``{"corner": [12]}``): each at
            the mass-weighted centre of its vertices, after "cloth" in name order.
        name: Scene name.

    Returns:
        The scene; handle "cloth" (mass-weighted over all vertices), then ``handles``; surface "cloth".

    Raises:
        FileNotFoundError: for a missing file.
        ValueError: for an unreadable or non-manifold mesh (an edge of three triangles, surfaces touching at a
            vertex), non-finite vertices, a bad parameter, or pins that select every vertex (or none, under gravity).
    """
    import trimesh

    young = check_positive("young", young)
    poisson = check_poisson(poisson)
    thickness = check_positive("thickness", thickness)
    bending = check_positive("bending", bending, allow_zero=True)
    density = check_positive("density", density)
    gravity = check_bool("gravity", gravity)
    scale = check_positive("scale", scale)
    mesh, source = _mesh_input(mesh_or_path)
    _scaled(mesh, scale, source)
    given = np.asarray(mesh.vertices, dtype=np.float64).copy()
    _weld(mesh)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise ValueError(f"mesh {source!r} has no triangle of nonzero area")
    try:
        meshes.check_manifold(mesh.faces, mesh.vertices)  # before fix_winding, which cannot orient a non-manifold one
    except ValueError as exc:
        raise ValueError(f"mesh {source!r} cannot be used as cloth: {exc}") from exc
    if not mesh.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    triangles = np.asarray(mesh.faces, dtype=np.int64)
    try:
        meshes.interior_hinges(triangles)
    except ValueError as exc:
        raise ValueError(f"mesh {source!r} cannot be used as cloth: {exc}") from exc
    diagonal = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    pinned = _pinned(given, vertices, pin, tolerance=1e-3 * diagonal)
    _check_pins(pin, pinned, vertices, triangles, gravity)
    b = SceneBuilder(dim=3)
    ids = add_cloth(
        b, vertices, triangles, young=young, poisson=poisson, thickness=thickness, density=density, bending=bending
    )
    if pinned.size:
        b.pin_particles(ids[torch.as_tensor(pinned)])
    masses = meshes.lumped_masses(vertices, triangles, density, thickness=thickness)
    b.add_handle("cloth", b.particle_points(ids), torch.as_tensor(masses))
    select = functools.partial(_pinned, given, vertices, tolerance=1e-3 * diagonal)
    labels = _add_handles(b, ids, masses, pinned, handles, select, "cloth")
    if gravity:
        add_gravity(b)
    params = (
        {
            "builder": "cloth",
            "source": source,
            "mesh_sha256": None if source == "<trimesh>" else meshes.file_sha256(source),
            "mesh_digest": _digest(vertices, triangles),
            "young": young,
            "poisson": poisson,
            "thickness": thickness,
            "bending": bending,
            "density": density,
            "pin": _pin_label(pin, pinned),
            "gravity": gravity,
        }
        | _scale_param(scale)
        | _handles_param(labels)
        | _selections_param(given, pin, handles)
    )
    return b.finalize(
        name,
        params=params,
        description=f"cloth from {source} ({triangles.shape[0]} triangles); SI units",
    )
