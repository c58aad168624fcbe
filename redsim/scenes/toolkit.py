"""The toolkit every scene builder uses: argument checks and putting meshes, bodies and joints into a SceneBuilder.

- checks: :func:`check_positive`, :func:`check_poisson`, :func:`check_int`, :func:`check_range`,
  :func:`check_bool` (each raises a ValueError naming the argument);
- deformables: :func:`add_fem` (neo-Hookean solid), :func:`add_cloth` (membrane + bending);
- rigid bodies: :func:`add_rigid_body`, :func:`add_rigidity`, :class:`Joints`;
- the rest: :func:`add_gravity`, :func:`select_vertices` (pin specs), :func:`builder_params`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Literal, NamedTuple

import numpy as np
import torch
from torch import Tensor

from redsim import meshes
from redsim.effects import DiscreteShellBending, NeoHookean, PointPairPenalty, RigidOrthogonality, StVKMembrane
from redsim.points import PointSet
from redsim.scene import SceneBuilder

if TYPE_CHECKING:  # imported where used: import redsim needs none of trimesh (slow to import)
    import trimesh

GRAVITY = 9.81
"""Gravitational acceleration [m/s^2]; every catalog scene pulls along -y."""

PinSpec = str | np.ndarray | Sequence[int] | Callable[[np.ndarray], np.ndarray] | None
"""Which vertices to pin: ``"min_y"``/``"max_y"``/``"min_x"``/... (the extreme layer along an
axis), ``"none"``/None, a boolean mask [V], an index list, or a callable mapping vertices
[V, D] to a boolean mask [V]."""


# -- argument checks ---------------------------------------------------------------------------
def _number(name: str, value: Any) -> float:
    """``value`` as a float; a ValueError names ``name`` otherwise (also for a string or a bool, which ``float``
    would take: "0.3" in a spec file, or False, read as 0)."""
    if isinstance(value, (str, bytes, bool, np.bool_)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a number, got {value!r}") from exc


def check_positive(name: str, value: Any, *, allow_zero: bool = False) -> float:
    """``value`` as a float, > 0 (or >= 0 with ``allow_zero``); a ValueError names ``name`` otherwise (also for a
    string or a bool, which ``float`` would take)."""
    out = _number(name, value)
    ok = out >= 0 if allow_zero else out > 0
    if not (ok and np.isfinite(out)):
        raise ValueError(f"{name} must be {'>= 0' if allow_zero else '> 0'} and finite, got {value!r}")
    return out


def check_poisson(value: Any, name: str = "poisson") -> float:
    """A Poisson ratio in (-1, 0.5) (not a string or a bool)."""
    out = _number(name, value)
    if not -1.0 < out < 0.5:
        raise ValueError(f"{name} must lie in (-1, 0.5), got {value!r}")
    return out


def check_int(name: str, value: Any, minimum: int) -> int:
    """An integer >= ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return int(value)


def check_range(name: str, value: Any, low: float, high: float) -> float:
    """A float in the closed interval [low, high] (not a string or a bool)."""
    out = _number(name, value)
    if not low <= out <= high:
        raise ValueError(f"{name} must lie in [{low}, {high}], got {value!r}")
    return out


def check_pair(name: str, value: Any) -> tuple[Any, Any]:
    """The two entries of a (low, high) parameter (each checked by the caller)."""
    if isinstance(value, str | bytes) or not hasattr(value, "__len__") or len(value) != 2:
        raise ValueError(f"{name} must be a pair (low, high), got {value!r}")
    return value[0], value[1]


def check_bool(name: str, value: Any) -> bool:
    """A flag that must really be a bool (so ``gravity="no"`` is an error, not True)."""
    if not isinstance(value, bool | np.bool_):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


# -- putting meshes into a builder -----------------------------------------------------------
def add_fem(
    builder: SceneBuilder,
    vertices: np.ndarray,
    elements: np.ndarray,
    *,
    young: float | np.ndarray,
    poisson: float,
    density: float,
    thickness: float = 1.0,
    plane: Literal["strain", "stress"] = "strain",
    condition_scale: tuple[int, np.ndarray] | None = None,
    seed: np.ndarray | None = None,
    name: str = "elastic",
) -> Tensor:
    """Add a neo-Hookean solid (triangles in 2D, tets in 3D) with lumped masses and a drawable surface.

    Args:
        builder: The scene builder (its ``dim`` must match the vertices).
        vertices: Rest positions [m], shape [V, D].
        elements: Triangles [T, 3] (2D, counter-clockwise) or tets [T, 4] (3D, positive).
        young: Young's modulus [Pa], scalar or per element [T].
        poisson: Poisson ratio.
        density: Mass density [kg/m^3].
        thickness: Out-of-plane thickness [m] of 2D solids (mass and stiffness); ignored in 3D.
        plane: 2D plane model, "strain" or "stress".
        condition_scale: (condition index, element mask [T]) for a conditional modulus factor.
        seed: Seed positions [m], shape [V, D] (default: the rest positions).
        name: Effect name; the surface has the same name.

    Returns:
        The particle ids, shape [V].
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    elements = np.asarray(elements, dtype=np.int64)
    dim = vertices.shape[1]
    masses = meshes.lumped_masses(vertices, elements, density, thickness=thickness if dim == 2 else 1.0)
    start = vertices if seed is None else np.asarray(seed, dtype=np.float64)
    if start.shape != vertices.shape:
        raise ValueError(f"seed must have the shape of vertices {vertices.shape}, got {start.shape}")
    ids = builder.add_particles(torch.as_tensor(start), torch.as_tensor(masses))
    element_ids = ids[torch.as_tensor(elements)]
    builder.add_effect(
        NeoHookean(
            name,
            builder.particle_dofs(element_ids),
            torch.as_tensor(vertices[elements]),
            torch.as_tensor(young, dtype=torch.float64),
            poisson,
            thickness=thickness,
            plane=plane,
            condition_scale=None
            if condition_scale is None
            else (condition_scale[0], torch.as_tensor(condition_scale[1], dtype=torch.bool)),
        )
    )
    if dim == 2:
        builder.add_surface(name, builder.particle_points(ids), torch.as_tensor(elements))
    else:
        faces = meshes.tet_boundary_faces(elements)
        used, local = np.unique(faces, return_inverse=True)
        points = builder.particle_points(ids[torch.as_tensor(used)])
        builder.add_surface(name, points, torch.as_tensor(local.reshape(-1, 3)))
    return ids


def add_cloth(
    builder: SceneBuilder,
    vertices: np.ndarray,
    triangles: np.ndarray,
    *,
    young: float,
    poisson: float,
    thickness: float,
    density: float,
    bending: float,
) -> Tensor:
    """Add cloth: StVK membrane ("membrane") and, when ``bending > 0``, discrete-shell bending ("bending").

    Args:
        builder: A 3D scene builder.
        vertices: Rest = seed positions [m], shape [V, 3].
        triangles: Consistently oriented triangles [T, 3].
        young: Young's modulus of the sheet material [Pa].
        poisson: Poisson ratio.
        thickness: Sheet thickness [m].
        density: Material density [kg/m^3] (areal density = density * thickness).
        bending: Bending stiffness [J] per hinge (0 omits the bending term).

    Returns:
        The particle ids, shape [V].
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    masses = meshes.lumped_masses(vertices, triangles, density, thickness=thickness)
    ids = builder.add_particles(torch.as_tensor(vertices), torch.as_tensor(masses))
    tri_ids = ids[torch.as_tensor(triangles)]
    builder.add_effect(
        StVKMembrane(
            "membrane",
            builder.particle_dofs(tri_ids),
            torch.as_tensor(vertices[triangles]),
            young,
            poisson,
            thickness=thickness,
        )
    )
    hinges = meshes.interior_hinges(triangles)
    if bending > 0 and hinges.shape[0]:
        hinge_dofs = builder.particle_dofs(ids[torch.as_tensor(hinges)])
        builder.add_effect(DiscreteShellBending("bending", hinge_dofs, torch.as_tensor(vertices[hinges]), bending))
    builder.add_surface("cloth", builder.particle_points(ids), torch.as_tensor(triangles))
    return ids


class RigidBody(NamedTuple):
    """A rigid body added by :func:`add_rigid_body`.

    Attributes:
        body: Body id in the builder.
        rotation: Seed rotation R, shape [3, 3].
        centre: Seed centre of mass t [m], shape [3] (the frame origin).
        local: Body-frame vertices of its mesh [m], shape [V, 3].
        faces: Triangles of its mesh, shape [F, 3].
    """

    body: int
    rotation: np.ndarray
    centre: np.ndarray
    local: np.ndarray
    faces: np.ndarray

    def to_local(self, world: np.ndarray) -> np.ndarray:
        """Body-frame coordinates [P, 3] of seed world points [P, 3]: R^T (w - t)."""
        return (np.asarray(world, dtype=np.float64).reshape(-1, 3) - self.centre) @ self.rotation


def add_rigid_body(
    builder: SceneBuilder,
    mesh: trimesh.Trimesh,
    *,
    density: float,
    rotation: np.ndarray | None = None,
    translation: Sequence[float] = (0.0, 0.0, 0.0),
    surface: str | None = None,
) -> RigidBody:
    """Add a rigid body whose seed placement is ``R @ mesh + translation``.

    The body frame is centred on the centre of mass of ``mesh`` (so its seed ``t`` is the
    world centre of mass) and its axes are those of ``mesh`` rotated by R.

    Args:
        builder: A 3D scene builder.
        mesh: Watertight solid [m] in the body's canonical orientation.
        density: Mass density [kg/m^3].
        rotation: Seed rotation R [3, 3] (identity by default).
        translation: Seed translation [m] applied after rotating about the origin.
        surface: Name of the drawable surface to add (None: none).
    """
    R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
    if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-12) or np.linalg.det(R) < 0:
        raise ValueError("rotation must be a proper 3x3 rotation matrix")
    block, com = meshes.affine_mass_block(mesh, density)
    centre = R @ com + np.asarray(translation, dtype=np.float64).reshape(3)
    transform = np.concatenate([R, centre[:, None]], axis=1)
    body = builder.add_body(torch.as_tensor(block), torch.as_tensor(transform))
    local = meshes.recentered(mesh, com)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if surface is not None:
        builder.add_surface(surface, builder.body_points(body, torch.as_tensor(local)), torch.as_tensor(faces))
    return RigidBody(body, R, centre, local, faces)


def add_rigidity(builder: SceneBuilder, bodies: Sequence[RigidBody], stiffness: float) -> None:
    """The orthogonality penalty ("rigid") over ``bodies``."""
    dofs = torch.stack([builder.body_dofs(b.body) for b in bodies])
    builder.add_effect(RigidOrthogonality("rigid", dofs, stiffness))


class Joints:
    """Collects joint point pairs and hinge-axis pairs between rigid bodies (or a body and the world)."""

    def __init__(self, builder: SceneBuilder) -> None:
        self.builder = builder
        self.points: list[tuple[PointSet, PointSet]] = []
        self.axes: list[tuple[PointSet, PointSet, float]] = []

    def _point(self, body: RigidBody | None, world: np.ndarray, *, direction: bool = False) -> PointSet:
        world = np.asarray(world, dtype=np.float64).reshape(1, 3)
        if body is None:
            return PointSet.world(torch.as_tensor(world), k=4)
        local = world @ body.rotation if direction else body.to_local(world)
        return self.builder.body_points(body.body, torch.as_tensor(local), direction=direction)

    def pin(self, a: RigidBody, b: RigidBody | None, at: np.ndarray) -> None:
        """Make the seed world point ``at`` [m] coincide in body a and body b (None: the world)."""
        self.points.append((self._point(a, at), self._point(b, at)))

    def align(self, a: RigidBody, b: RigidBody | None, axis: np.ndarray, stiffness: float) -> None:
        """Keep the seed world direction ``axis`` (unit) the same in body a and body b (None: the world)."""
        axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
        self.axes.append((self._point(a, axis, direction=True), self._point(b, axis, direction=True), stiffness))

    def finish(self, stiffness: float) -> None:
        """Add the "joints" (point) and "joint_axes" (direction) penalties."""
        self.builder.add_effect(
            PointPairPenalty(
                "joints",
                PointSet.cat([p[0] for p in self.points]),
                PointSet.cat([p[1] for p in self.points]),
                stiffness,
                kind="joint",
            )
        )
        if self.axes:
            self.builder.add_effect(
                PointPairPenalty(
                    "joint_axes",
                    PointSet.cat([a[0] for a in self.axes]),
                    PointSet.cat([a[1] for a in self.axes]),
                    torch.tensor([a[2] for a in self.axes], dtype=torch.float64),
                    kind="hinge_axis",
                )
            )


def builder_params(arguments: dict[str, Any]) -> dict[str, Any]:
    """The builder's arguments (``locals()`` at its top) as a JSON-friendly dict."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in arguments.items()}


def add_gravity(builder: SceneBuilder) -> None:
    """Gravity of :data:`GRAVITY` along -y (2D or 3D)."""
    builder.add_gravity((0.0, -GRAVITY) if builder.dim == 2 else (0.0, -GRAVITY, 0.0))


def select_vertices(vertices: np.ndarray, spec: PinSpec, *, tolerance: float, what: str = "pin") -> np.ndarray:
    """Indices of the vertices chosen by ``spec`` (see :data:`PinSpec`), shape [P], int64.

    Args:
        vertices: [V, D] [m].
        spec: The selection.
        tolerance: Distance [m] from the extreme coordinate still counted as on the extreme layer.
        what: What the selection is for, as the errors name it.

    Raises:
        ValueError: on an unknown name, a mask of the wrong shape, indices that are not integers or out of range.
    """
    V, D = vertices.shape
    if spec is None or (isinstance(spec, str) and spec == "none"):
        return np.zeros(0, dtype=np.int64)
    if isinstance(spec, str):
        names = [f"{e}_{a}" for e in ("min", "max") for a in "xyz"[:D]]
        if spec not in names:
            raise ValueError(f"unknown {what} {spec!r}; use one of {[*names, 'none']}, a mask, indices or a callable")
        extreme, axis = spec.split("_")
        coord = vertices[:, "xyz".index(axis)]
        if extreme == "min":
            return np.nonzero(coord <= coord.min() + tolerance)[0]
        return np.nonzero(coord >= coord.max() - tolerance)[0]
    chosen = np.asarray(spec(vertices.copy()) if callable(spec) else spec)
    if chosen.dtype == bool:
        if chosen.shape != (V,):
            raise ValueError(f"{what} mask must have shape [{V}], got {chosen.shape}")
        return np.nonzero(chosen)[0]
    if chosen.size and not np.issubdtype(chosen.dtype, np.integer):  # [0.0, 0.4, 0.0]: a position, not indices
        raise ValueError(
            f"{what} indices must be integers (or a bool mask, a name, a callable), got {chosen.dtype} values"
        )
    chosen = chosen.astype(np.int64).reshape(-1)
    if chosen.size and (chosen.min() < 0 or chosen.max() >= V):
        raise ValueError(f"{what} indices must lie in [0, {V}), got range [{chosen.min()}, {chosen.max()}]")
    return np.unique(chosen)
