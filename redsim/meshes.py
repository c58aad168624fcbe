"""Geometry for scenes: generated grids, voxel tetrahedralization, mesh queries and mesh loading.

Everything here is plain numpy at build time (scenes convert to torch once). Conventions:

- Vertices are float64 arrays [V, D] in metres; element indices are int64 arrays.
- Triangles [T, 3] are counter-clockwise in 2D (positive area) and consistently oriented
  in 3D (every interior edge is traversed once in each direction).
- Tetrahedra [T, 4] are positively oriented: det[v1 - v0, v2 - v0, v3 - v0] > 0.
- Grid sizes are given as *cell* counts; a grid with ``cells=(cx, cy)`` has
  ``(cx + 1) * (cy + 1)`` vertices.
"""

from __future__ import annotations

import hashlib
import io
import math
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # imported where used: import redsim needs none of trimesh (slow to import)
    import trimesh

# The six Kuhn tetrahedra of the unit cube: corner c has offset bits (c & 1, c >> 1 & 1, c >> 2 & 1).
# Each walks from corner 0 to corner 7 along one permutation of the axes, so every face of
# every cube is split along the diagonal through its lowest and highest corner: neighbouring
# cubes agree and the tetrahedralization is conforming. Orders are chosen so all six are positive.
_KUHN = np.array(
    [
        [0, 1, 3, 7],
        [0, 3, 2, 7],
        [0, 2, 6, 7],
        [0, 6, 4, 7],
        [0, 4, 5, 7],
        [0, 5, 1, 7],
    ],
    dtype=np.int64,
)
_CUBE_CORNERS = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=np.int64)
# Faces of a positive tet (a, b, c, d) with outward normals (right-hand rule).
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)


# -- grids -----------------------------------------------------------------------------------
def rectangle_grid(width: float, height: float, cells: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Triangulated rectangle [0, width] x [0, height] in the plane.

    Diagonals alternate in a checkerboard, so the mesh has no preferred shear direction.

    Args:
        width: Size along x [m].
        height: Size along y [m].
        cells: Cell counts (cx, cy) along x and y.

    Returns:
        vertices [(cx+1)(cy+1), 2] (x fastest), triangles [2 cx cy, 3], counter-clockwise.
    """
    cx, cy = _cell_counts(cells, 2)
    if not (width > 0 and height > 0):
        raise ValueError(f"rectangle sides must be > 0, got {width} x {height}")
    xs = np.linspace(0.0, width, cx + 1)
    ys = np.linspace(0.0, height, cy + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    vertices = np.stack([gx.ravel(), gy.ravel()], axis=1)
    j, i = np.meshgrid(np.arange(cy), np.arange(cx), indexing="ij")
    i, j = i.ravel(), j.ravel()
    v00 = j * (cx + 1) + i
    v10, v01 = v00 + 1, v00 + cx + 1
    v11 = v01 + 1
    even = (i + j) % 2 == 0
    first = np.where(even[:, None], np.stack([v00, v10, v11], 1), np.stack([v00, v10, v01], 1))
    second = np.where(even[:, None], np.stack([v00, v11, v01], 1), np.stack([v10, v11, v01], 1))
    triangles = np.stack([first, second], axis=1).reshape(-1, 3)
    return vertices, triangles.astype(np.int64)


def cloth_grid(
    width: float,
    height: float,
    cells: tuple[int, int],
    *,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
    axis_u: Sequence[float] = (1.0, 0.0, 0.0),
    axis_v: Sequence[float] = (0.0, 1.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """A flat triangulated sheet in 3D: ``origin + u * axis_u + v * axis_v`` for u in [0, width], v in [0, height].

    Args:
        width: Extent along ``axis_u`` [m].
        height: Extent along ``axis_v`` [m].
        cells: Cell counts (cu, cv).
        origin: Position of the (u, v) = (0, 0) corner [m], shape [3].
        axis_u: Unit direction of u, shape [3].
        axis_v: Unit direction of v, shape [3], orthogonal to ``axis_u``.

    Returns:
        vertices [(cu+1)(cv+1), 3] (u fastest), triangles [2 cu cv, 3], consistently oriented
        with normal ``axis_u x axis_v``.
    """
    uv, triangles = rectangle_grid(width, height, cells)
    o, a, b = (np.asarray(x, dtype=np.float64).reshape(3) for x in (origin, axis_u, axis_v))
    if abs(np.linalg.norm(a) - 1) > 1e-9 or abs(np.linalg.norm(b) - 1) > 1e-9 or abs(a @ b) > 1e-9:
        raise ValueError(f"axis_u and axis_v must be orthonormal, got {a} and {b}")
    return o + uv[:, :1] * a + uv[:, 1:] * b, triangles


def box_tet_grid(
    extents: Sequence[float], cells: tuple[int, int, int], *, origin: Sequence[float] = (0.0, 0.0, 0.0)
) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedralized box ``origin + [0, ex] x [0, ey] x [0, ez]``, six Kuhn tets per cell.

    Args:
        extents: Box sides (ex, ey, ez) [m].
        cells: Cell counts (cx, cy, cz).
        origin: Lowest corner [m].

    Returns:
        vertices [(cx+1)(cy+1)(cz+1), 3], tets [6 cx cy cz, 4], positively oriented.
    """
    counts = _cell_counts(cells, 3)
    ext = np.asarray(extents, dtype=np.float64).reshape(3)
    if not bool(np.all(ext > 0)):
        raise ValueError(f"box extents must be > 0, got {tuple(ext)}")
    grid = np.stack(np.meshgrid(*(np.arange(c) for c in counts), indexing="ij"), axis=-1).reshape(-1, 3)
    return cells_to_tets(grid, ext / np.asarray(counts), origin=origin)


def cells_to_tets(
    cells: np.ndarray, spacing: Sequence[float] | float, *, origin: Sequence[float] = (0.0, 0.0, 0.0)
) -> tuple[np.ndarray, np.ndarray]:
    """Conforming tet mesh of a set of grid cells (Kuhn subdivision, shared corner vertices).

    Cell (i, j, k) is the box ``origin + [i, i+1] x [j, j+1] x [k, k+1] * spacing``.

    Args:
        cells: Integer cell indices, shape [K, 3] (duplicates are merged).
        spacing: Cell size [m], scalar or shape [3].
        origin: Position of the corner of cell (0, 0, 0) [m].

    Returns:
        vertices [V, 3] (only corners of the given cells), tets [6K', 4] for the K' distinct cells.
    """
    cells = np.unique(np.asarray(cells, dtype=np.int64).reshape(-1, 3), axis=0)
    if cells.shape[0] == 0:
        raise ValueError("no cells to tetrahedralize")
    h = np.broadcast_to(np.asarray(spacing, dtype=np.float64), (3,))
    if not bool(np.all(h > 0)):
        raise ValueError(f"cell spacing must be > 0, got {tuple(h)}")
    low = cells.min(axis=0)
    shape = cells.max(axis=0) - low + 2  # corner lattice size
    corners = (cells - low)[:, None, :] + _CUBE_CORNERS[None]  # [K, 8, 3]
    keys = (corners[..., 0] * shape[1] + corners[..., 1]) * shape[2] + corners[..., 2]
    unique_keys, inverse = np.unique(keys.ravel(), return_inverse=True)
    lattice = np.stack(np.unravel_index(unique_keys, tuple(shape)), axis=1) + low
    vertices = np.asarray(origin, dtype=np.float64).reshape(3) + lattice * h
    tets = inverse.reshape(-1, 8)[:, _KUHN].reshape(-1, 4)
    return vertices, orient_tets(vertices, tets)


def orient_tets(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Tets reordered so that every one has positive volume (swaps the last two vertices of negative ones).

    Raises:
        ValueError: on a degenerate (zero-volume) tet.
    """
    tets = np.asarray(tets, dtype=np.int64).copy()
    vol = signed_tet_volumes(vertices, tets)
    scale = np.abs(vol).max() if vol.size else 1.0
    flat = np.nonzero(np.abs(vol) <= 1e-12 * scale)[0]
    if flat.size:
        raise ValueError(f"tet {int(flat[0])} is degenerate (volume {vol[flat[0]]:.3g}); {flat.size} in all")
    neg = vol < 0
    tets[neg, 2], tets[neg, 3] = tets[neg, 3], tets[neg, 2].copy()
    return tets


def signed_tet_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume [m^3] of each tet, shape [T]."""
    v = np.asarray(vertices, dtype=np.float64)[np.asarray(tets, dtype=np.int64)]
    return np.linalg.det(np.stack([v[:, 1] - v[:, 0], v[:, 2] - v[:, 0], v[:, 3] - v[:, 0]], axis=-1)) / 6.0


# -- voxelization ----------------------------------------------------------------------------
def voxel_cells(mesh: trimesh.Trimesh, pitch: float) -> np.ndarray:
    """Filled voxels of a watertight mesh on the global lattice of spacing ``pitch``.

    Voxel (i, j, k) is the cube of side ``pitch`` centred at ``(i, j, k) * pitch``, so cells of
    different meshes voxelized with one pitch share the lattice and can be united by concatenation.
    Every voxel the surface touches is kept, so the voxel solid is slightly larger than the mesh
    (by up to half a pitch on each side).

    Args:
        mesh: A watertight triangle mesh [m].
        pitch: Voxel side [m].

    Returns:
        Integer voxel indices, shape [K, 3].

    Raises:
        ValueError: on a non-positive pitch, a mesh that is not watertight, or no voxels.
    """
    if not pitch > 0:
        raise ValueError(f"voxel pitch must be > 0, got {pitch}")
    if not mesh.is_watertight:
        raise ValueError("voxelization needs a watertight mesh (closed surface, consistent winding)")
    grid = mesh.voxelized(pitch).fill()
    cells = np.round(np.asarray(grid.points) / pitch).astype(np.int64)
    if cells.shape[0] == 0:
        raise ValueError(f"mesh produced no voxels at pitch {pitch:g} m")
    return cells


def voxel_tet_mesh(meshes: trimesh.Trimesh | Sequence[trimesh.Trimesh], pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """Voxel tet mesh of a watertight mesh, or of the union of several (their voxel sets are OR-ed).

    Args:
        meshes: One watertight mesh or a sequence of them [m].
        pitch: Voxel side [m].

    Returns:
        vertices [V, 3], positively oriented tets [6K, 4] (six Kuhn tets per voxel).
    """
    import trimesh

    parts = [meshes] if isinstance(meshes, trimesh.Trimesh) else list(meshes)
    cells = np.concatenate([voxel_cells(m, pitch) for m in parts])
    return cells_to_tets(cells, pitch, origin=(-0.5 * pitch,) * 3)


def grid_cells(meshes: trimesh.Trimesh | Sequence[trimesh.Trimesh], pitch: float) -> float:
    """Cells of the dense voxel grids :func:`voxel_tet_mesh` fills at ``pitch`` [m]: each mesh's bounding box."""
    import trimesh

    parts = [meshes] if isinstance(meshes, trimesh.Trimesh) else list(meshes)
    return sum(float(np.prod(np.ceil(np.asarray(m.extents, dtype=np.float64) / pitch) + 1.0)) for m in parts)


def pitch_for_vertex_count(
    meshes: trimesh.Trimesh | Sequence[trimesh.Trimesh],
    target: int,
    *,
    iterations: int = 4,
    max_cells: float | None = None,
) -> float:
    """Voxel pitch [m] whose :func:`voxel_tet_mesh` has about ``target`` vertices.

    Starts from volume / target and corrects with the measured count (count ~ pitch^-3).

    Args:
        meshes: Watertight mesh(es) [m].
        target: Wanted vertex count (> 8).
        iterations: Voxelizations spent refining the estimate.
        max_cells: Refuse (ValueError) a pitch whose voxel grids (:func:`grid_cells`) would have more cells, before
            voxelizing at it (a solid that fills little of its bounding box needs a dense grid); None: no limit.
    """
    import trimesh

    if target < 8:
        raise ValueError(f"target vertex count must be >= 8, got {target}")
    parts = [meshes] if isinstance(meshes, trimesh.Trimesh) else list(meshes)
    volume = sum(abs(float(m.volume)) for m in parts)
    if not volume > 0:
        raise ValueError("mesh volume must be > 0 to choose a voxel pitch")
    pitch = (volume / target) ** (1.0 / 3.0)
    for _ in range(iterations):
        cells = grid_cells(parts, pitch)
        if max_cells is not None and cells > max_cells:
            raise ValueError(
                f"about {target} vertices need a voxel pitch near {pitch:.3g} m, whose grid over the mesh's bounding "
                f"box has ~{cells:.3g} cells (at most {max_cells:.0e}): the solid fills little of its bounding box"
            )
        count = voxel_tet_mesh(parts, pitch)[0].shape[0]
        if abs(count - target) <= 0.03 * target:
            break
        pitch *= (count / target) ** (1.0 / 3.0)
    return pitch


# -- mesh queries ----------------------------------------------------------------------------
def check_manifold(triangles: np.ndarray, vertices: np.ndarray | None = None) -> None:
    """Refuse a triangle surface that is not a manifold (with or without boundary), whatever its orientation.

    Args:
        triangles: Triangles [T, 3], int.
        vertices: Their positions [V, D], to name the offending vertices by where they are as well (a mesh file's
            numbering changes when its vertices are welded); None: by index only.

    Raises:
        ValueError: a triangle that repeats a vertex, two triangles on the same three vertices, an edge shared by
            more than two triangles, or a vertex where separate fans of triangles meet at a single point (two sheets
            touching at a corner), naming the first such triangle, edge or vertex.
    """

    def at(*ids: int) -> str:
        if vertices is None:
            return ""
        return " at " + " - ".join(str(np.round(np.asarray(vertices)[i], 6).tolist()) for i in ids)

    import scipy.sparse
    from scipy.sparse.csgraph import connected_components

    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if not tri.size:
        return
    ordered = np.sort(tri, axis=1)
    repeats = np.nonzero((ordered[:, 1:] == ordered[:, :-1]).any(axis=1))[0]
    if repeats.size:
        t = int(repeats[0])
        raise ValueError(f"triangle {t} {tri[t].tolist()}{at(*tri[t])} repeats a vertex: remove degenerate triangles")
    _, inverse, seen = np.unique(ordered, axis=0, return_inverse=True, return_counts=True)
    twice = np.flatnonzero(seen[inverse.reshape(-1)] > 1)
    if twice.size:
        t = int(twice[0])
        raise ValueError(
            f"triangle {t} {tri[t].tolist()}{at(*tri[t])} appears {int(seen[inverse.reshape(-1)[t]])} times: remove "
            "duplicate triangles (a cloth surface is a manifold)"
        )
    corners = np.arange(tri.size).reshape(-1, 3)
    start, end = tri.ravel(), tri[:, [1, 2, 0]].ravel()  # half-edge c runs from corner c to corner nxt[c]
    nxt = corners[:, [1, 2, 0]].ravel()
    base = int(tri.max()) + 1
    keys = np.minimum(start, end) * base + np.maximum(start, end)
    order = np.argsort(keys, kind="stable")
    unique, counts = np.unique(keys, return_counts=True)
    if bool((counts > 2).any()):
        k = int(unique[counts > 2][0])
        raise ValueError(
            f"edge ({k // base}, {k % base}){at(k // base, k % base)} is shared by {int(counts[counts > 2][0])} "
            "triangles: a cloth surface "
            "must be a manifold (at most two triangles per edge)"
        )
    same = np.nonzero(keys[order[1:]] == keys[order[:-1]])[0]
    i, j = order[same], order[same + 1]  # the two half-edges of each interior edge
    along = start[j] == start[i]  # both run the same way (an orientation to fix later), or opposite ways
    # the corners of start[i] and of end[i] in the two triangles are one fan around each of those vertices
    left = np.concatenate([i, nxt[i]])
    right = np.concatenate([np.where(along, j, nxt[j]), np.where(along, nxt[j], j)])
    graph = scipy.sparse.coo_matrix((np.ones(left.size), (left, right)), shape=(tri.size, tri.size))
    _, label = connected_components(graph, directed=False)
    fans = np.unique(np.stack([start, label], axis=1), axis=0)[:, 0]
    count = np.bincount(fans, minlength=base)
    if bool((count > 1).any()):
        v = int(np.nonzero(count > 1)[0][0])
        raise ValueError(
            f"vertex {v}{at(v)} joins {int(count[v])} separate fans of triangles (surfaces touching at one point): "
            "a cloth surface must be a manifold; split the vertex or join the surfaces along an edge"
        )


def interior_hinges(triangles: np.ndarray) -> np.ndarray:
    """Hinges of the interior edges of a consistently oriented triangle mesh (for shell bending).

    Each hinge is (v0, v1, v2, v3): the shared edge v0-v1, the apex v2 of the triangle
    containing the directed edge v0 -> v1 (so it is (v0, v1, v2) up to rotation) and the
    apex v3 of the neighbour, which contains v1 -> v0 (so it is (v1, v0, v3)).

    Args:
        triangles: Triangles [T, 3], int.

    Returns:
        Hinges [E, 4], int64, one per interior edge.

    Raises:
        ValueError: if an edge is used twice in the same direction (inconsistent orientation
            or a non-manifold edge).
    """
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    heads = tri.ravel()
    tails = tri[:, [1, 2, 0]].ravel()
    apex = tri[:, [2, 0, 1]].ravel()
    base = int(tri.max()) + 1 if tri.size else 1
    keys = heads * base + tails
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    if sorted_keys.size and bool(np.any(sorted_keys[1:] == sorted_keys[:-1])):
        k = int(sorted_keys[1:][sorted_keys[1:] == sorted_keys[:-1]][0])
        raise ValueError(
            f"edge ({k // base}, {k % base}) appears twice with the same direction: the triangles are "
            "not consistently oriented or the edge is non-manifold"
        )
    forward = np.nonzero(heads < tails)[0]
    reverse_keys = tails[forward] * base + heads[forward]
    pos = np.clip(np.searchsorted(sorted_keys, reverse_keys), 0, max(sorted_keys.size - 1, 0))
    found = sorted_keys[pos] == reverse_keys
    first = forward[found]
    second = order[pos[found]]
    return np.stack([heads[first], tails[first], apex[first], apex[second]], axis=1)


def tet_boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Boundary triangles of a positively oriented tet mesh, outward facing, shape [F, 3]."""
    tets = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    faces = tets[:, _TET_FACES].reshape(-1, 3)
    _, index, counts = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True)
    return faces[np.sort(index[counts == 1])]


def simplex_measures(vertices: np.ndarray, elements: np.ndarray) -> np.ndarray:
    """Unsigned length/area/volume of simplices (edges, triangles, tets) in 2D or 3D, shape [T].

    Uses the Gram determinant sqrt(det(E^T E)) / k! of the k edge vectors E, so triangles in 3D work.
    """
    v = np.asarray(vertices, dtype=np.float64)[np.asarray(elements, dtype=np.int64)]
    edges = v[:, 1:] - v[:, :1]  # [T, k, D]
    k = edges.shape[1]
    gram = edges @ edges.transpose(0, 2, 1)
    return np.sqrt(np.clip(np.linalg.det(gram), 0.0, None)) / math.factorial(k)


def lumped_masses(vertices: np.ndarray, elements: np.ndarray, density: float, *, thickness: float = 1.0) -> np.ndarray:
    """Lumped vertex masses [kg]: each element's measure x thickness x density, split evenly over its vertices.

    Args:
        vertices: [V, D] [m].
        elements: Triangles or tets [T, k+1].
        density: Mass density [kg/m^3] (volume elements) or, with ``thickness``, of a sheet.
        thickness: Out-of-plane thickness [m] of triangles (2D solids, cloth); 1 for tets.

    Returns:
        Masses, shape [V]; vertices in no element get 0.
    """
    elements = np.asarray(elements, dtype=np.int64)
    share = simplex_measures(vertices, elements) * thickness * density / elements.shape[1]
    return np.bincount(elements.ravel(), weights=np.repeat(share, elements.shape[1]), minlength=len(vertices))


def affine_mass_block(mesh: trimesh.Trimesh, density: float) -> tuple[np.ndarray, np.ndarray]:
    """The 4x4 affine mass matrix of a solid about its centre of mass, and that centre.

    Block = sum_v m_v [v; 1][v; 1]^T over the mass distribution with v measured from the
    centre of mass: ``[[S, 0], [0, m]]`` with second moment S = tr(I)/2 Id - I from the
    inertia tensor I about the centre of mass. Body-frame points are ``world - centre``.

    Args:
        mesh: A watertight solid [m] in its seed orientation.
        density: Mass density [kg/m^3].

    Returns:
        (block [4, 4] [kg, kg m^2], centre of mass [3] [m]).

    Raises:
        ValueError: on a non-positive density or a mesh without positive volume.
    """
    import trimesh

    if not density > 0:
        raise ValueError(f"density must be > 0, got {density}")
    if not mesh.is_watertight or not mesh.volume > 0:
        raise ValueError("a rigid body needs a watertight, outward-oriented mesh with positive volume")
    props = trimesh.triangles.mass_properties(mesh.triangles, density=density)
    inertia = np.asarray(props.inertia, dtype=np.float64)
    block = np.zeros((4, 4))
    block[:3, :3] = 0.5 * np.trace(inertia) * np.eye(3) - inertia
    block[3, 3] = float(props.mass)
    return block, np.asarray(props.center_mass, dtype=np.float64)


def recentered(mesh: trimesh.Trimesh, centre: np.ndarray) -> np.ndarray:
    """Body-frame vertices [V, 3] of ``mesh``: its vertices minus ``centre`` (the centre of mass)."""
    return np.asarray(mesh.vertices, dtype=np.float64) - np.asarray(centre, dtype=np.float64).reshape(1, 3)


# -- loading ---------------------------------------------------------------------------------
def file_sha256(path: str | os.PathLike[str]) -> str:
    """SHA-256 hex digest of a file's bytes (how a scene records the mesh file it was built from)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def load_mesh(path: str | os.PathLike[str]) -> trimesh.Trimesh:
    """Load a triangle mesh from a file (any format trimesh reads: .obj, .stl, .ply, .off, .glb, ...).

    Multi-part files are concatenated into one mesh.

    Raises:
        FileNotFoundError: if ``path`` does not exist (the message names it).
        ValueError: if the file cannot be parsed, is not a triangle mesh, or has no faces.
    """
    import trimesh

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"mesh file not found: {str(p)!r}")
    if not p.is_file():
        raise ValueError(f"mesh path {str(p)!r} is not a file")
    try:
        # as written: no vertex dropped (a NaN one, an unreferenced one) nor reordered, so the checks below see
        # the file's vertices and pin indices count in the file's numbering (the scene builders weld duplicates)
        options = {"force": "mesh", "process": False, "maintain_order": True}
        absolute = absolute_obj_indices(p.read_bytes()) if p.suffix.lower() == ".obj" else None
        if absolute is None:
            mesh = trimesh.load(p, **options)
        else:  # its materials (mtllib) are still found beside it
            resolver = trimesh.resolvers.FilePathResolver(p)
            mesh = trimesh.load(io.BytesIO(absolute), file_type="obj", resolver=resolver, **options)
    except Exception as exc:
        hint = f"; {TET_FILE_HINT}" if p.suffix.lower() in TET_MESH_SUFFIXES else ""
        raise ValueError(f"could not read mesh file {str(p)!r}: {type(exc).__name__}: {exc}{hint}") from exc
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"{str(p)!r} does not contain a triangle mesh (got {type(mesh).__name__})")
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise ValueError(f"{str(p)!r} holds no triangles: it is empty or not a mesh file")
    if not bool(np.isfinite(mesh.vertices).all()):
        raise ValueError(f"{str(p)!r} has non-finite vertex coordinates")
    return mesh


OBJ_ELEMENTS = (b"v", b"vt", b"vn")
"""What a face's ``v/vt/vn`` references count, each in its own list."""


def absolute_obj_indices(text: bytes) -> bytes | None:
    """An OBJ file's ``text`` with its relative (negative) face indices made absolute, or None where it has none.

    In the OBJ format ``-k`` is the k-th last ``v`` (``vt``, ``vn``) declared above the face line. trimesh resolves
    it against the whole file's list instead (wrong where vertices and faces interleave: trimesh issue #2364), and
    with texture or normal references and ``maintain_order=True`` it fails ("IndexError: index -4 is out of bounds
    for axis 0 with size 0").
    """
    if re.search(rb"^[ \t]*f[ \t][^\n#]*-\d", text, re.MULTILINE) is None:
        return None
    counts = dict.fromkeys(OBJ_ELEMENTS, 0)
    lines = text.split(b"\n")
    for n, line in enumerate(lines):
        words = line.split(b"#", 1)[0].split()
        if words and words[0] in counts:
            counts[words[0]] += 1
        elif words and words[0] == b"f":
            references = [
                b"/".join(
                    _absolute_reference(index, kind, counts[kind], n + 1) if index.startswith(b"-") else index
                    for kind, index in zip(OBJ_ELEMENTS, word.split(b"/"), strict=False)
                )
                for word in words[1:]
            ]
            lines[n] = b" ".join([b"f", *references])
    return b"\n".join(lines)


def _absolute_reference(index: bytes, kind: bytes, declared: int, line: int) -> bytes:
    """The 1-based index of the relative reference ``index`` (-1: the last) to the ``declared`` ``kind`` elements
    above face line ``line``; a ValueError naming the line where it reaches past the first."""
    absolute = declared + int(index) + 1
    if absolute < 1:
        raise ValueError(
            f"line {line}: face index {index.decode()} refers past the first {kind.decode()} ({declared} declared "
            "above it)"
        )
    return str(absolute).encode()


TET_FILE_HINT = (
    "a tetrahedral mesh goes in a .npz file with arrays 'vertices' [V, 3] and 'tets' [T, 4] (e.g. from meshio: "
    "m = meshio.read(PATH); numpy.savez('part.npz', vertices=m.points, tets=m.cells_dict['tetra'])), built by "
    "tet_scene_from_mesh (--kind tets)"
)
"""How a tet mesh reaches redsim: named where a file cannot be read as one."""
TET_MESH_SUFFIXES = (".msh", ".vtk", ".vtu", ".mesh", ".ele", ".node", ".inp", ".npz")
"""Suffixes of volume-mesh files a triangle-mesh reader refuses; its error then names :data:`TET_FILE_HINT`."""
SURFACE_MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb", ".gltf", ".dae", ".3mf")
"""Suffixes of surface-mesh files, which the tet reader refuses naming the voxelizing builder."""


def load_tets(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """A tetrahedral mesh from a ``.npz`` file holding ``vertices`` [V, 3] [m] and ``tets`` [T, 4] (vertex
    indices from 0), checked by :func:`check_tet_mesh`.

    Raises:
        FileNotFoundError: if ``path`` does not exist (the message names it).
        ValueError: if the file is not such a ``.npz`` (the arrays it holds are named) or the mesh is invalid.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"tet mesh file not found: {str(p)!r}")
    if not p.is_file():
        raise ValueError(f"tet mesh path {str(p)!r} is not a file")
    surface = p.suffix.lower() in SURFACE_MESH_SUFFIXES
    hint = "a surface mesh is voxelized by fem_scene_from_mesh (--kind fem)" if surface else TET_FILE_HINT
    with open(p, "rb") as handle:
        head = handle.read(6)
    if not head.startswith(b"PK\x03\x04"):  # a .npz is a zip of .npy files
        what = "a single .npy array" if head.startswith(b"\x93NUMPY") else "not a .npz (a zip of numpy arrays)"
        raise ValueError(f"{str(p)!r} is {what}; {hint}")
    try:
        with np.load(p, allow_pickle=False) as data:  # reads only the two arrays: the others may hold anything
            names = sorted(data.files)
            arrays = {key: data[key] for key in ("vertices", "tets") if key in names}
    except Exception as exc:
        raise ValueError(f"could not read {str(p)!r} as a .npz of arrays: {type(exc).__name__}: {exc}; {hint}") from exc
    if missing := [key for key in ("vertices", "tets") if key not in arrays]:
        raise ValueError(f"{str(p)!r} holds arrays {names}, not {missing}; {TET_FILE_HINT}")
    return check_tet_mesh(arrays["vertices"], arrays["tets"], str(p))


def check_tet_mesh(vertices: np.ndarray, tets: np.ndarray, source: str) -> tuple[np.ndarray, np.ndarray]:
    """``vertices`` as float64 [V, 3] and ``tets`` as int64 [T, 4], checked (``source`` names them in errors).

    Raises:
        ValueError: a wrong shape, a non-finite vertex, an index that is not a whole number or lies outside
            [0, V), a tet that repeats a vertex, or one listed twice.
    """
    vertices, tets = np.asarray(vertices), np.asarray(tets)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] < 4:
        raise ValueError(f"{source!r}: vertices must have shape [V >= 4, 3], got {list(vertices.shape)}")
    if not np.issubdtype(vertices.dtype, np.number) or not bool(np.isfinite(vertices).all()):
        raise ValueError(f"{source!r} has non-finite (or non-numeric) vertex coordinates")
    if tets.ndim != 2 or tets.shape[1] != 4 or tets.shape[0] == 0:
        raise ValueError(f"{source!r}: tets must have shape [T >= 1, 4] (vertex indices), got {list(tets.shape)}")
    if not np.issubdtype(tets.dtype, np.number) or not bool(np.all(np.asarray(tets, np.float64) % 1 == 0)):
        raise ValueError(f"{source!r}: tets must hold whole vertex indices, got dtype {tets.dtype}")
    tets = tets.astype(np.int64)
    low, high = int(tets.min()), int(tets.max())
    if low < 0 or high >= vertices.shape[0]:
        raise ValueError(
            f"{source!r}: tet vertex indices must lie in [0, {vertices.shape[0]}) (counted from 0), got "
            f"{low if low < 0 else high}"
        )
    ordered = np.sort(tets, axis=1)
    repeated = np.nonzero((ordered[:, 1:] == ordered[:, :-1]).any(axis=1))[0]
    if repeated.size:
        raise ValueError(f"{source!r}: tet {int(repeated[0])} repeats a vertex {tets[repeated[0]].tolist()}")
    _, first, count = np.unique(ordered, axis=0, return_index=True, return_counts=True)
    if (count > 1).any():  # its stiffness and mass would count twice
        twice = int(np.sort(first[count > 1])[0])
        later = int(np.nonzero((ordered == ordered[twice]).all(axis=1))[0][1])
        raise ValueError(f"{source!r}: tet {later} repeats tet {twice} ({tets[twice].tolist()}); list each tet once")
    return vertices.astype(np.float64), tets


def _cell_counts(cells: Sequence[int], dim: int) -> tuple[int, ...]:
    counts = tuple(int(c) for c in cells)
    if len(counts) != dim or any(c < 1 or c != x for c, x in zip(counts, cells, strict=True)):
        raise ValueError(f"cells must be {dim} positive integers, got {tuple(cells)}")
    return counts
