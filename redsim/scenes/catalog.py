"""The scene catalog: the eleven systems of the paper's Table 1, plus a heterogeneous beam.

One keyword-only builder per scene; every parameter has a default and SI units (m, kg, s,
Pa, N, J). Gravity is 9.81 m/s^2 along -y wherever a ``gravity`` argument is offered, and
``gravity=False`` omits the "gravity" effect. Each builder passes all its arguments to
``finalize`` so the scene fingerprint captures them.

Materials are chosen so that implicit Euler with dt = 0.01..0.05 s behaves: rubber-like
solids (E = 1e5..1e7 Pa, density 1000 kg/m^3), cloth with E = 1e6 Pa and 1 mm thickness,
and rigid bodies of 0.01..5 kg held by joint and contact penalties of 1e4..1e5 N/m.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
import trimesh

from redsim import meshes
from redsim.effects import ConditionalPin, FrameSet, PointPairPenalty, SDFContact, Sphere, Torus
from redsim.points import PointSet
from redsim.scene import Scene, SceneBuilder
from redsim.scenes.from_mesh import (
    Joints,
    add_cloth,
    add_fem,
    add_gravity,
    add_rigid_body,
    add_rigidity,
    builder_params,
    check_bool,
    check_int,
    check_poisson,
    check_positive,
    check_range,
)


def _rotation_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rotation_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _bar(p0: np.ndarray, p1: np.ndarray, width: float, thickness: float) -> trimesh.Trimesh:
    """A box from p0 to p1 (in the z = const plane of p0), ``width`` wide in-plane, ``thickness`` along z."""
    d = np.asarray(p1, dtype=np.float64) - np.asarray(p0, dtype=np.float64)
    length = float(np.linalg.norm(d))
    box = trimesh.creation.box(extents=(length + width, width, thickness))
    transform = np.eye(4)
    transform[:3, :3] = _rotation_z(math.atan2(d[1], d[0]))
    transform[:3, 3] = 0.5 * (np.asarray(p0) + np.asarray(p1))
    return box.apply_transform(transform)


def _rod(p0: np.ndarray, p1: np.ndarray, radius: float) -> trimesh.Trimesh:
    """A capsule whose sphere centres are p0 and p1 [m]."""
    p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    d = p1 - p0
    capsule = trimesh.creation.capsule(height=float(np.linalg.norm(d)), radius=radius, count=[12, 12])
    transform = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], d / np.linalg.norm(d))
    transform[:3, 3] = 0.5 * (p0 + p1)
    return capsule.apply_transform(transform)


def _ellipsoid(centre: tuple[float, float, float], semi_axes: tuple[float, float, float]) -> trimesh.Trimesh:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    sphere.apply_scale(semi_axes)
    return sphere.apply_translation(centre)


def _cylinder_y(centre: tuple[float, float, float], radius: float, height: float) -> trimesh.Trimesh:
    """A cylinder with a vertical (y) axis."""
    cylinder = trimesh.creation.cylinder(radius=radius, height=height, sections=24)
    cylinder.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1.0, 0.0, 0.0]))
    return cylinder.apply_translation(centre)


# ---------------------------------------------------------------------------------------------
# Cloth
# ---------------------------------------------------------------------------------------------
def cloth_ball(
    *,
    cells: int = 44,
    size: float = 1.0,
    young: float = 1e6,
    poisson: float = 0.3,
    thickness: float = 1e-3,
    density: float = 200.0,
    bending: float = 1e-4,
    ball_radius: float = 0.12,
    ball_mass: float = 1.0,
    contact_stiffness: float = 1e4,
    contact_margin: float = 0.01,
    rigid_stiffness: float = 5000.0,
    gravity: bool = True,
) -> Scene:
    """A ball rolling on a square cloth pinned at its four corners (paper teaser; Table 1 n = 6069).

    The cloth lies flat in the y = 0 plane, centred on the origin; the ball (a rigid body)
    rests just above its centre. Contact is a penalty between every cloth vertex and the
    ball's sphere signed distance. Default n = 3 * ((cells+1)^2 - 4) + 12 = 6075.

    Args:
        cells: Cloth cells per side (vertices per side = cells + 1).
        size: Cloth side length [m].
        young: Cloth Young's modulus [Pa].
        poisson: Cloth Poisson ratio.
        thickness: Cloth thickness [m].
        density: Cloth material density [kg/m^3] (areal density = density * thickness).
        bending: Cloth bending stiffness per hinge [J].
        ball_radius: Ball radius [m].
        ball_mass: Ball mass [kg].
        contact_stiffness: Cloth-ball penalty weight [N/m] per vertex.
        contact_margin: Distance [m] cloth vertices keep from the ball surface.
        rigid_stiffness: Orthogonality penalty of the ball [J].
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: membrane, bending, rigid, contact, gravity, external_load. Handles: "ball" (its
    centre), "cloth_center" (the middle cloth vertex). Surfaces: "cloth", "ball".
    """
    params = builder_params(locals())
    cells = check_int("cells", cells, 2)
    for key in (
        "size",
        "young",
        "thickness",
        "density",
        "ball_radius",
        "ball_mass",
        "contact_stiffness",
        "rigid_stiffness",
    ):
        check_positive(key, params[key])
    check_poisson(poisson)
    check_positive("bending", bending, allow_zero=True)
    check_positive("contact_margin", contact_margin, allow_zero=True)
    gravity = check_bool("gravity", gravity)

    b = SceneBuilder(dim=3)
    half = 0.5 * size
    vertices, triangles = meshes.cloth_grid(
        size, size, (cells, cells), origin=(-half, 0.0, half), axis_u=(1.0, 0.0, 0.0), axis_v=(0.0, 0.0, -1.0)
    )
    ids = add_cloth(
        b, vertices, triangles, young=young, poisson=poisson, thickness=thickness, density=density, bending=bending
    )
    side = cells + 1
    corners = torch.tensor([0, cells, side * cells, side * side - 1])
    b.pin_particles(ids[corners])

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=ball_radius)
    ball_density = ball_mass / float(sphere.volume)
    lift = ball_radius + contact_margin + 0.005
    ball = add_rigid_body(b, sphere, density=ball_density, translation=(0.0, lift, 0.0), surface="ball")
    add_rigidity(b, [ball], rigid_stiffness)
    count = vertices.shape[0]
    b.add_effect(
        SDFContact(
            "contact",
            b.particle_points(ids),
            FrameSet.body(b.body_dofs(ball.body), count),
            Sphere(ball_radius),
            contact_stiffness,
            margin=contact_margin,
        )
    )
    if gravity:
        add_gravity(b)
    b.add_handle("ball", b.body_points(ball.body, torch.zeros(1, 3)))
    b.add_handle("cloth_center", b.particle_points(ids[torch.tensor([(side * side) // 2])]))
    return b.finalize(
        "cloth_ball",
        params=params,
        description=f"{size:g} m cloth pinned at 4 corners with a {ball_mass:g} kg ball of radius {ball_radius:g} m "
        "(m, kg, s)",
    )


def hanging_sheet(
    *,
    cells_x: int = 45,
    cells_y: int = 44,
    width: float = 1.0,
    height: float = 1.0,
    young: float = 1e6,
    poisson: float = 0.3,
    thickness: float = 1e-3,
    density: float = 200.0,
    bending: float = 1e-3,
    gravity: bool = True,
) -> Scene:
    """A thick cloth sheet hanging in the xy plane, its top edge pinned (Table 1 n = 6072).

    The top row (y = 0) is pinned; the sheet hangs down to y = -height. Default grid 46 x 45
    vertices with 46 pinned: n = 3 * 46 * 44 = 6072.

    Args:
        cells_x: Cells across (vertices = cells_x + 1).
        cells_y: Cells down (vertices = cells_y + 1).
        width: Sheet width [m].
        height: Sheet height [m].
        young: Young's modulus [Pa].
        poisson: Poisson ratio.
        thickness: Thickness [m].
        density: Material density [kg/m^3].
        bending: Bending stiffness per hinge [J] (a "thick" sheet).
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: membrane, bending, gravity, external_load. Handles: "bottom_left",
    "bottom_right" (corner vertices), "bottom_middle" (the bottom row). Surface: "cloth".
    """
    params = builder_params(locals())
    cells_x = check_int("cells_x", cells_x, 1)
    cells_y = check_int("cells_y", cells_y, 1)
    for key in ("width", "height", "young", "thickness", "density"):
        check_positive(key, params[key])
    check_poisson(poisson)
    check_positive("bending", bending, allow_zero=True)
    gravity = check_bool("gravity", gravity)

    b = SceneBuilder(dim=3)
    vertices, triangles = meshes.cloth_grid(width, height, (cells_x, cells_y), origin=(-0.5 * width, -height, 0.0))
    ids = add_cloth(
        b, vertices, triangles, young=young, poisson=poisson, thickness=thickness, density=density, bending=bending
    )
    row = cells_x + 1
    b.pin_particles(ids[cells_y * row :])
    if gravity:
        add_gravity(b)
    b.add_handle("bottom_left", b.particle_points(ids[:1]))
    b.add_handle("bottom_right", b.particle_points(ids[cells_x : cells_x + 1]))
    b.add_handle("bottom_middle", b.particle_points(ids[:row]))
    return b.finalize(
        "hanging_sheet",
        params=params,
        description=f"{width:g} x {height:g} m cloth hanging from its top edge (m, kg, s)",
    )


# ---------------------------------------------------------------------------------------------
# 2D elastic bars
# ---------------------------------------------------------------------------------------------
def _check_bar(params: dict[str, Any]) -> None:
    for key in ("length", "height", "young", "density", "thickness"):
        check_positive(key, params[key])
    check_poisson(params["poisson"])


def bistable_bar(
    *,
    cells_x: int = 42,
    cells_y: int = 9,
    length: float = 1.0,
    height: float = 0.1,
    compression: float = 0.8,
    young: float = 1e5,
    poisson: float = 0.45,
    density: float = 1000.0,
    thickness: float = 0.05,
    gravity: bool = False,
) -> Scene:
    """A 2D neo-Hookean bar whose ends are pinned closer than its rest length (Table 1 n = 830).

    The rest bar spans [0, length] x [0, height]; the seed is the same bar uniformly
    compressed along x to ``compression * length`` (a straight, unstable state), with its end
    columns pinned there, so it buckles into one of two arches. No gravity by default (it
    would break the up/down symmetry). Default n = 2 * 43 * 10 - 2 * 20 = 820.

    Args:
        cells_x: Cells along the bar.
        cells_y: Cells across the bar.
        length: Rest length [m].
        height: Bar height [m].
        compression: Pinned end distance / rest length, in (0, 1] (1: no compression).
        young: Young's modulus [Pa].
        poisson: Poisson ratio.
        density: Density [kg/m^3].
        thickness: Out-of-plane thickness [m] (plane strain).
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: elastic, [gravity], external_load. Handle: "middle" (the vertices of the middle
    column when cells_x is even, else the column just left of it). Surface: "elastic".
    """
    params = builder_params(locals())
    cells_x = check_int("cells_x", cells_x, 2)
    cells_y = check_int("cells_y", cells_y, 1)
    _check_bar(params)
    compression = check_range("compression", compression, 1e-3, 1.0)
    gravity = check_bool("gravity", gravity)

    rest, triangles = meshes.rectangle_grid(length, height, (cells_x, cells_y))
    seed = rest.copy()
    seed[:, 0] *= compression
    b = SceneBuilder(dim=2)
    ids = add_fem(b, rest, triangles, young=young, poisson=poisson, density=density, thickness=thickness, seed=seed)
    columns = torch.arange(rest.shape[0]) % (cells_x + 1)
    b.pin_particles(ids[(columns == 0) | (columns == cells_x)])
    if gravity:
        add_gravity(b)
    b.add_handle("middle", b.particle_points(ids[columns == cells_x // 2]))
    return b.finalize(
        "bistable_bar",
        params=params,
        description=f"2D bar {length:g} x {height:g} m compressed to {compression:g} of its length (m, kg, s)",
    )


def conditional_bar(
    *,
    cells_x: int = 47,
    cells_y: int = 9,
    length: float = 1.0,
    height: float = 0.1,
    young: float = 1e5,
    poisson: float = 0.45,
    density: float = 1000.0,
    thickness: float = 0.05,
    stiffness_ratio_range: tuple[float, float] = (0.2, 5.0),
    pin_location_range: tuple[float, float] = (0.3, 1.0),
    pin_width: float = 0.04,
    pin_stiffness: float = 1e4,
    gravity: bool = True,
) -> Scene:
    """A 2D neo-Hookean cantilever with two condition parameters (Table 1 n = 942, 2 conditions).

    The bar spans [0, length] x [0, height] with its left end pinned. Conditions (paper §3.5):

    - "stiffness_ratio": the Young's modulus of the right half (x > length/2) is multiplied by
      c[0] (default 1).
    - "pin_location": a support along the bottom edge at x = c[1] [m]: a penalty pulling the
      bottom vertices back to their rest positions with a Gaussian weight of width
      ``pin_width`` around c[1] (default: the middle of its range).

    Default n = 2 * (48 * 10 - 10) = 940.

    Args:
        cells_x: Cells along the bar.
        cells_y: Cells across the bar.
        length: Length [m].
        height: Height [m].
        young: Young's modulus [Pa] (of both halves at stiffness_ratio 1).
        poisson: Poisson ratio.
        density: Density [kg/m^3].
        thickness: Out-of-plane thickness [m] (plane strain).
        stiffness_ratio_range: (low, high) of the right half's modulus factor, both > 0.
        pin_location_range: (low, high) of the support position as fractions of ``length``.
        pin_width: Gaussian width of the support [m].
        pin_stiffness: Support penalty weight [N/m] per vertex at its centre.
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: elastic (conditional), pin (conditional), gravity, external_load. Handle: "tip"
    (the right end column). Surface: "elastic".
    """
    params = builder_params(locals())
    cells_x = check_int("cells_x", cells_x, 2)
    cells_y = check_int("cells_y", cells_y, 1)
    _check_bar(params)
    check_positive("pin_width", pin_width)
    check_positive("pin_stiffness", pin_stiffness)
    gravity = check_bool("gravity", gravity)
    ratio_low, ratio_high = (check_positive("stiffness_ratio_range", v) for v in stiffness_ratio_range)
    loc_low, loc_high = (check_range("pin_location_range", v, 0.0, 1.0) for v in pin_location_range)
    if not (ratio_low < ratio_high and loc_low < loc_high):
        raise ValueError("condition ranges must be (low, high) with low < high")

    vertices, triangles = meshes.rectangle_grid(length, height, (cells_x, cells_y))
    b = SceneBuilder(dim=2)
    ratio = b.add_condition("stiffness_ratio", ratio_low, ratio_high, default=min(max(1.0, ratio_low), ratio_high))
    location = b.add_condition("pin_location", loc_low * length, loc_high * length)
    centroid_x = vertices[triangles, 0].mean(axis=1)
    ids = add_fem(
        b,
        vertices,
        triangles,
        young=young,
        poisson=poisson,
        density=density,
        thickness=thickness,
        condition_scale=(ratio, centroid_x > 0.5 * length),
    )
    columns = torch.arange(vertices.shape[0]) % (cells_x + 1)
    b.pin_particles(ids[columns == 0])
    bottom = ids[1 : cells_x + 1]
    b.add_effect(
        ConditionalPin(
            "pin",
            b.particle_points(bottom),
            torch.as_tensor(vertices[1 : cells_x + 1]),
            torch.as_tensor(vertices[1 : cells_x + 1, 0]),
            location,
            pin_width,
            pin_stiffness,
        )
    )
    if gravity:
        add_gravity(b)
    b.add_handle("tip", b.particle_points(ids[columns == cells_x]))
    return b.finalize(
        "conditional_bar",
        params=params,
        description=f"2D cantilever {length:g} x {height:g} m; conditions: right-half stiffness ratio, "
        "support location [m] (m, kg, s)",
    )


# ---------------------------------------------------------------------------------------------
# 3D elastic bodies
# ---------------------------------------------------------------------------------------------
def _check_solid(params: dict[str, Any]) -> None:
    for key in ("young", "density"):
        check_positive(key, params[key])
    check_poisson(params["poisson"])


def _face_ids(vertices: np.ndarray, axis: int, value: float, tolerance: float) -> torch.Tensor:
    return torch.as_tensor(np.nonzero(np.abs(vertices[:, axis] - value) <= tolerance)[0])


def cantilever(
    *,
    cells_x: int = 20,
    cells_yz: int = 4,
    length: float = 1.0,
    width: float = 0.2,
    young: float = 1e6,
    poisson: float = 0.45,
    density: float = 1000.0,
    gravity: bool = True,
) -> Scene:
    """A 3D neo-Hookean beam clamped at x = 0 (Table 1 n = 1500).

    The beam spans [0, length] x [-width/2, width/2]^2 (x along the beam, y up). Default
    21 x 5 x 5 vertices, 25 clamped: n = 1500.

    Args:
        cells_x: Cells along the beam.
        cells_yz: Cells across (in y and in z).
        length: Length [m].
        width: Square cross-section side [m].
        young: Young's modulus [Pa].
        poisson: Poisson ratio.
        density: Density [kg/m^3].
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: elastic, gravity, external_load. Handle: "tip" (the free end face). Surface: "elastic".
    """
    params = builder_params(locals())
    cells_x = check_int("cells_x", cells_x, 1)
    cells_yz = check_int("cells_yz", cells_yz, 1)
    check_positive("length", length)
    check_positive("width", width)
    _check_solid(params)
    gravity = check_bool("gravity", gravity)

    vertices, tets = meshes.box_tet_grid(
        (length, width, width), (cells_x, cells_yz, cells_yz), origin=(0.0, -0.5 * width, -0.5 * width)
    )
    b = SceneBuilder(dim=3)
    ids = add_fem(b, vertices, tets, young=young, poisson=poisson, density=density)
    tol = 1e-9 * length
    b.pin_particles(ids[_face_ids(vertices, 0, 0.0, tol)])
    if gravity:
        add_gravity(b)
    b.add_handle("tip", b.particle_points(ids[_face_ids(vertices, 0, length, tol)]))
    return b.finalize(
        "cantilever", params=params, description=f"{length:g} m beam, {width:g} m square section, clamped at x = 0"
    )


def hetero_beam(
    *,
    cells_x: int = 26,
    cells_yz: int = 4,
    length: float = 1.2,
    width: float = 0.15,
    segments: int = 6,
    young_stiff: float = 2e6,
    young_soft: float = 1e5,
    poisson: float = 0.45,
    density: float = 1000.0,
    gravity: bool = True,
) -> Scene:
    """A 3D beam clamped at x = 0 whose Young's modulus alternates stiff/soft along it ("modes_comparison").

    The beam is cut into ``segments`` equal lengths along x; even segments (from the clamp)
    use ``young_stiff``, odd ones ``young_soft`` (per tet, by centroid). Default 27 x 5 x 5
    vertices, 25 clamped: n = 1950.

    Args:
        cells_x: Cells along the beam.
        cells_yz: Cells across (in y and in z).
        length: Length [m].
        width: Square cross-section side [m].
        segments: Number of alternating segments.
        young_stiff: Young's modulus of the stiff segments [Pa].
        young_soft: Young's modulus of the soft segments [Pa].
        poisson: Poisson ratio.
        density: Density [kg/m^3].
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: elastic, gravity, external_load. Handles: "middle" (the cross-section nearest
    x = length/2), "tip" (the free end face). Surface: "elastic".
    """
    params = builder_params(locals())
    cells_x = check_int("cells_x", cells_x, 1)
    cells_yz = check_int("cells_yz", cells_yz, 1)
    segments = check_int("segments", segments, 1)
    for key in ("length", "width", "young_stiff", "young_soft", "density"):
        check_positive(key, params[key])
    check_poisson(poisson)
    gravity = check_bool("gravity", gravity)

    vertices, tets = meshes.box_tet_grid(
        (length, width, width), (cells_x, cells_yz, cells_yz), origin=(0.0, -0.5 * width, -0.5 * width)
    )
    centroid_x = vertices[tets, 0].mean(axis=1)
    segment = np.minimum((centroid_x / length * segments).astype(np.int64), segments - 1)
    young = np.where(segment % 2 == 0, young_stiff, young_soft)
    b = SceneBuilder(dim=3)
    ids = add_fem(b, vertices, tets, young=young, poisson=poisson, density=density)
    tol = 1e-9 * length
    b.pin_particles(ids[_face_ids(vertices, 0, 0.0, tol)])
    if gravity:
        add_gravity(b)
    xs = np.unique(vertices[:, 0])
    middle = xs[np.argmin(np.abs(xs - 0.5 * length))]
    b.add_handle("middle", b.particle_points(ids[_face_ids(vertices, 0, middle, tol)]))
    b.add_handle("tip", b.particle_points(ids[_face_ids(vertices, 0, length, tol)]))
    return b.finalize(
        "hetero_beam",
        params=params,
        description=f"{length:g} m beam clamped at x = 0, {segments} segments alternating E = {young_stiff:g} / "
        f"{young_soft:g} Pa",
    )


def _cow_parts() -> list[trimesh.Trimesh]:
    """A cow-like body about 0.7 m long, 0.6 m tall, feet on y = 0 [m]."""
    torso = trimesh.creation.capsule(height=0.36, radius=0.12, count=[16, 16])
    torso.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [0.0, 1.0, 0.0]))
    torso.apply_translation((0.0, 0.35, 0.0))
    legs = [_cylinder_y((x, 0.135, z), 0.045, 0.27) for x in (-0.17, 0.17) for z in (-0.07, 0.07)]
    head = trimesh.creation.icosphere(subdivisions=3, radius=0.09).apply_translation((0.33, 0.45, 0.0))
    horns = [_rod(np.array([0.33, 0.52, z]), np.array([0.33, 0.6, 2.0 * z]), 0.02) for z in (-0.05, 0.05)]
    return [torso, *legs, head, *horns]


def stiff_body(
    *,
    voxel_pitch: float = 0.0236,
    young: float = 1e7,
    poisson: float = 0.45,
    density: float = 1000.0,
    pin_radius: float = 0.0,
    gravity: bool = True,
) -> Scene:
    """A stiff cow-like solid hanging from one point of its back ("rigidity" figure; Table 1 n = 14676).

    Built from trimesh primitives (capsule torso, four cylinder legs, sphere head, two rod
    horns; voxel sets OR-ed, no boolean backend needed), voxel-tetrahedralized. The vertex
    on top of the torso nearest x = 0 is pinned, so the body can swing about it. Default
    n = 14841 (about 33 kg, 0.75 m long).

    Args:
        voxel_pitch: Voxel side [m] (sets the resolution; 0.0236 gives n close to Table 1).
        young: Young's modulus [Pa] (stiff: gravity strains it by about 0.1%).
        poisson: Poisson ratio.
        density: Density [kg/m^3].
        pin_radius: Also pin every vertex within this distance [m] of the pinned vertex
            (0: pin exactly one vertex).
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: elastic, gravity, external_load. Handle: "head" (vertices within 0.05 m of the
    front of the head). Surface: "elastic".
    """
    params = builder_params(locals())
    pitch = check_positive("voxel_pitch", voxel_pitch)
    check_positive("pin_radius", pin_radius, allow_zero=True)
    _check_solid(params)
    gravity = check_bool("gravity", gravity)
    if pitch > 0.06:
        raise ValueError(f"voxel_pitch must be <= 0.06 m to resolve the legs, got {pitch}")

    vertices, tets = meshes.voxel_tet_mesh(_cow_parts(), pitch)
    b = SceneBuilder(dim=3)
    ids = add_fem(b, vertices, tets, young=young, poisson=poisson, density=density)
    torso = np.abs(vertices[:, 0]) <= 0.18
    top = np.nonzero(torso & (vertices[:, 1] >= vertices[torso, 1].max() - 1e-9))[0]
    anchor = vertices[top[np.argmin(np.linalg.norm(vertices[top][:, [0, 2]], axis=1))]]
    pinned = np.nonzero(np.linalg.norm(vertices - anchor, axis=1) <= pin_radius + 1e-9)[0]
    b.pin_particles(ids[torch.as_tensor(pinned)])
    if gravity:
        add_gravity(b)
    head = np.nonzero(vertices[:, 0] >= vertices[:, 0].max() - 0.05)[0]
    b.add_handle("head", b.particle_points(ids[torch.as_tensor(head)]))
    return b.finalize(
        "stiff_body",
        params=params,
        description=f"stiff cow-like voxel solid ({tets.shape[0]} tets, E = {young:g} Pa) hanging from one point",
    )


def _elephant_parts() -> list[trimesh.Trimesh]:
    """An elephant-like body about 1.3 m long, 1 m tall, feet on y = 0 [m]."""
    body = _ellipsoid((0.0, 0.62, 0.0), (0.42, 0.28, 0.26))
    legs = [_cylinder_y((x, 0.28, z), 0.085, 0.56) for x in (-0.24, 0.24) for z in (-0.14, 0.14)]
    head = trimesh.creation.icosphere(subdivisions=3, radius=0.19).apply_translation((0.5, 0.8, 0.0))
    trunk = _rod(np.array([0.62, 0.72, 0.0]), np.array([0.72, 0.25, 0.0]), 0.065)
    ears = [_ellipsoid((0.42, 0.86, z), (0.05, 0.16, 0.12)) for z in (-0.2, 0.2)]
    return [body, *legs, head, trunk, *ears]


def elephant(
    *,
    voxel_pitch: float = 0.105,
    young: float = 5e5,
    poisson: float = 0.45,
    density: float = 1000.0,
    gravity: bool = True,
) -> Scene:
    """An elephant-like soft solid standing on pinned feet ("fulton_compare"; Table 1 n = 1926).

    Built from primitives (ellipsoid body, four cylinder legs, sphere head, capsule trunk,
    ellipsoid ears), voxelized on one lattice and OR-ed, voxel-tetrahedralized. The bottom
    vertex layer (the soles) is pinned.

    Args:
        voxel_pitch: Voxel side [m] (0.105 gives n close to Table 1).
        young: Young's modulus [Pa].
        poisson: Poisson ratio.
        density: Density [kg/m^3].
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: elastic, gravity, external_load. Handles: "trunk_tip" (the lowest trunk
    vertices), "back" (the top of the body). Surface: "elastic".
    """
    params = builder_params(locals())
    pitch = check_positive("voxel_pitch", voxel_pitch)
    _check_solid(params)
    gravity = check_bool("gravity", gravity)
    if pitch > 0.15:
        raise ValueError(f"voxel_pitch must be <= 0.15 m to resolve the legs, got {pitch}")

    vertices, tets = meshes.voxel_tet_mesh(_elephant_parts(), pitch)
    b = SceneBuilder(dim=3)
    ids = add_fem(b, vertices, tets, young=young, poisson=poisson, density=density)
    y = vertices[:, 1]
    b.pin_particles(ids[torch.as_tensor(np.nonzero(y <= y.min() + 0.25 * pitch)[0])])
    if gravity:
        add_gravity(b)
    trunk = vertices[:, 0] >= 0.62
    trunk_tip = np.nonzero(trunk & (y <= y[trunk].min() + 0.25 * pitch))[0]
    back = np.nonzero(y >= y.max() - 0.25 * pitch)[0]
    b.add_handle("trunk_tip", b.particle_points(ids[torch.as_tensor(trunk_tip)]))
    b.add_handle("back", b.particle_points(ids[torch.as_tensor(back)]))
    return b.finalize(
        "elephant",
        params=params,
        description=f"elephant-like voxel solid ({tets.shape[0]} tets, E = {young:g} Pa) on pinned feet",
    )


# ---------------------------------------------------------------------------------------------
# Rigid bodies: chains and linkages
# ---------------------------------------------------------------------------------------------
def chain(
    *,
    links: int = 24,
    link_radius: float = 0.05,
    wire_radius: float = 0.01,
    density: float = 7800.0,
    contact_stiffness: float = 1e5,
    contact_samples: int = 24,
    rigid_stiffness: float = 5000.0,
    gravity: bool = True,
) -> Scene:
    """A hanging chain of torus links held together only by contact (Table 1 n = 288; ``links=2``: 24).

    Link k is a rigid torus (centre-line radius ``link_radius``, tube radius ``wire_radius``)
    centred at (0, -(k+1) s, 0) with s = 2 link_radius - 2.5 wire_radius; even links lie in
    the xy plane, odd ones are turned 90 degrees about y (yz plane), so neighbours interlock.
    Link 0 hangs from a fixed world torus (the hook, in the yz plane at the origin).

    Contact: for every neighbouring pair (hook-0, 0-1, ...), ``contact_samples`` points on each
    link's centre line must stay ``wire_radius`` outside the other's torus signed distance (so
    the centre lines stay 2 wire_radius apart), in both directions. No joints: separating two
    links needs their tubes to pass through each other. The seed has no contact.

    Args:
        links: Number of moving links (24 in the paper's chain, 2 in its mini chain).
        link_radius: Torus centre-line radius [m].
        wire_radius: Torus tube radius [m] (< link_radius / 2.5).
        density: Link density [kg/m^3] (steel).
        contact_stiffness: Contact penalty weight [N/m] per sample point.
        contact_samples: Centre-line sample points per link and neighbour.
        rigid_stiffness: Orthogonality penalty [J] per link.
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: rigid, contact, gravity, external_load. Handle: "bottom" (the centre of the last
    link). Surfaces: "link_0", ..., and "hook". Body k is link k (x entries 12k .. 12k+11).
    """
    params = builder_params(locals())
    return _chain_scene("chain", params, links)


def mini_chain(
    *,
    link_radius: float = 0.05,
    wire_radius: float = 0.01,
    density: float = 7800.0,
    contact_stiffness: float = 1e5,
    contact_samples: int = 24,
    rigid_stiffness: float = 5000.0,
    gravity: bool = True,
) -> Scene:
    """The two-link chain of the autoencoder comparison (Table 1 n = 24); see :func:`chain`.

    Args:
        link_radius: Torus centre-line radius [m].
        wire_radius: Torus tube radius [m] (< link_radius / 2.5).
        density: Link density [kg/m^3].
        contact_stiffness: Contact penalty weight [N/m] per sample point.
        contact_samples: Centre-line sample points per link and neighbour.
        rigid_stiffness: Orthogonality penalty [J] per link.
        gravity: Add gravity (9.81 m/s^2 along -y).
    """
    params = builder_params(locals())
    return _chain_scene("mini_chain", params, 2)


def _chain_scene(name: str, params: dict[str, Any], links: int) -> Scene:
    """Validate the chain parameters and build a chain of ``links`` links (see :func:`chain`)."""
    links = check_int("links", links, 1)
    samples = check_int("contact_samples", params["contact_samples"], 8)
    major, minor, density, contact_stiffness, rigid_stiffness = (
        check_positive(key, params[key])
        for key in ("link_radius", "wire_radius", "density", "contact_stiffness", "rigid_stiffness")
    )
    gravity = check_bool("gravity", params["gravity"])
    if not minor < major / 2.5:
        raise ValueError(f"wire_radius must be < link_radius / 2.5 = {major / 2.5:g}, got {minor}")
    b = SceneBuilder(dim=3)
    spacing = 2.0 * major - 2.5 * minor
    torus = trimesh.creation.torus(major_radius=major, minor_radius=minor, major_sections=24, minor_sections=8)
    turned = _rotation_y(0.5 * math.pi)
    bodies = [
        add_rigid_body(
            b,
            torus,
            density=density,
            rotation=np.eye(3) if k % 2 == 0 else turned,
            translation=(0.0, -(k + 1) * spacing, 0.0),
            surface=f"link_{k}",
        )
        for k in range(links)
    ]
    add_rigidity(b, bodies, rigid_stiffness)
    angles = np.linspace(0.0, 2.0 * math.pi, samples, endpoint=False)
    centre_line = np.stack([major * np.cos(angles), major * np.sin(angles), np.zeros(samples)], axis=1)
    hook_transform = np.concatenate([turned, np.zeros((3, 1))], axis=1)
    hook_points = PointSet.world(torch.as_tensor(centre_line @ turned.T), k=4)
    points, frames = [], []
    for k, body in enumerate(bodies):
        own = b.body_points(body.body, torch.as_tensor(centre_line))
        own_frame = FrameSet.body(b.body_dofs(body.body), samples)
        if k == 0:
            other_points, other_frame = hook_points, FrameSet.world(torch.as_tensor(hook_transform), samples)
        else:
            prev = bodies[k - 1].body
            other_points = b.body_points(prev, torch.as_tensor(centre_line))
            other_frame = FrameSet.body(b.body_dofs(prev), samples)
        points += [own, other_points]
        frames += [other_frame, own_frame]
    b.add_effect(
        SDFContact(
            "contact", PointSet.cat(points), FrameSet.cat(frames), Torus(major, minor), contact_stiffness, margin=minor
        )
    )
    if gravity:
        add_gravity(b)
    b.add_handle("bottom", b.body_points(bodies[-1].body, torch.zeros(1, 3)))
    b.add_surface(
        "hook",
        PointSet.world(torch.as_tensor(np.asarray(torus.vertices) @ turned.T)),
        torch.as_tensor(np.asarray(torus.faces)),
    )
    mass = float(meshes.affine_mass_block(torus, density)[0][3, 3])
    return b.finalize(
        name,
        params=params,
        description=f"{links} torus links ({mass:.3g} kg each, radius {major:g} m) hanging from a hook, "
        "held by contact only",
    )


KLANN_JOINTS: dict[str, tuple[float, float]] = {
    "crank_ground": (0.0, 0.08),
    "crank_coupler": (-0.046622, 0.097594),
    "coupler_lower_rocker": (-0.1736, 0.11205),
    "coupler_leg": (-0.31194, 0.16654),
    "upper_rocker_ground": (-0.13, 0.1875),
    "lower_rocker_ground": (-0.13, 0.045),
    "upper_rocker_leg": (-0.21981, 0.25102),
}
"""Seed (x, y) [m] of the Klann linkage's seven revolute joints (from the authors' public code)."""

KLANN_BODIES = ("crank", "coupler", "lower_rocker", "leg", "upper_rocker")
"""Body order of :func:`klann`: body i owns x entries 12 i .. 12 i + 11."""


def klann(
    *,
    bar_width: float = 0.02,
    bar_thickness: float = 0.01,
    density: float = 2700.0,
    joint_stiffness: float = 1e4,
    axis_stiffness: float = 100.0,
    rigid_stiffness: float = 5000.0,
    gravity: bool = True,
) -> Scene:
    """The planar Klann walking linkage: five rigid bars and seven revolute joints (1 DOF: the crank angle).

    Bodies, in x order (:data:`KLANN_BODIES`): crank, coupler, lower rocker, leg, upper
    rocker, each a bar (``bar_width`` x ``bar_thickness`` aluminium by default, 40-180 g)
    spanning its joints; the leg continues past the coupler joint to a foot at 1.5 times the
    rocker-coupler joint distance. Joints (:data:`KLANN_JOINTS`, in the z = 0 plane):
    crank-ground, crank-coupler, coupler-lower rocker, coupler-leg, upper rocker-ground,
    lower rocker-ground, upper rocker-leg. Each joint is a point penalty ("joints") plus
    alignment of the body z axes ("joint_axes"), so the bodies stay in the plane. At the
    seed all bodies are unrotated, every joint is exactly satisfied and the joint energy is 0.

    n = 60 (5 bodies x 12). Table 1 lists 84 (7 bodies); the authors' public code has the same
    5 moving bodies, so we keep this geometry rather than adding idle bodies.

    Args:
        bar_width: In-plane bar width [m].
        bar_thickness: Bar thickness along z [m].
        density: Bar density [kg/m^3].
        joint_stiffness: Joint point penalty weight [N/m].
        axis_stiffness: Hinge-axis alignment weight [J] (energy axis_stiffness/2 |a - b|^2).
        rigid_stiffness: Orthogonality penalty per body [J].
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: rigid, joints, joint_axes, gravity, external_load. Handles: "crank_pin" (the
    crank-coupler joint on the crank), "foot" (the end of the leg). Surfaces: one per body.
    Driver (fitting only, ``redsim fit --drive``): "crank", the crank pin round the crank-ground
    joint in the x-y plane, turned by latent 0.
    """
    params = builder_params(locals())
    for key in ("bar_width", "bar_thickness", "density", "joint_stiffness", "axis_stiffness", "rigid_stiffness"):
        check_positive(key, params[key])
    gravity = check_bool("gravity", gravity)

    J = {k: np.array([x, y, 0.0]) for k, (x, y) in KLANN_JOINTS.items()}
    foot = J["coupler_leg"] + 1.5 * (J["coupler_leg"] - J["upper_rocker_leg"])
    spans = {
        "crank": (J["crank_ground"], J["crank_coupler"]),
        "coupler": (J["crank_coupler"], J["coupler_leg"]),
        "lower_rocker": (J["coupler_lower_rocker"], J["lower_rocker_ground"]),
        "leg": (J["upper_rocker_leg"], foot),
        "upper_rocker": (J["upper_rocker_ground"], J["upper_rocker_leg"]),
    }
    b = SceneBuilder(dim=3)
    bodies = {
        name: add_rigid_body(b, _bar(*spans[name], bar_width, bar_thickness), density=density, surface=name)
        for name in KLANN_BODIES
    }
    add_rigidity(b, list(bodies.values()), rigid_stiffness)
    joints = Joints(b)
    pairs = [
        ("crank", None, "crank_ground"),
        ("crank", "coupler", "crank_coupler"),
        ("coupler", "lower_rocker", "coupler_lower_rocker"),
        ("coupler", "leg", "coupler_leg"),
        ("upper_rocker", None, "upper_rocker_ground"),
        ("lower_rocker", None, "lower_rocker_ground"),
        ("upper_rocker", "leg", "upper_rocker_leg"),
    ]
    z = np.array([0.0, 0.0, 1.0])
    for a, other, where in pairs:
        joints.pin(bodies[a], None if other is None else bodies[other], J[where])
        joints.align(bodies[a], None if other is None else bodies[other], z, axis_stiffness)
    joints.finish(joint_stiffness)
    if gravity:
        add_gravity(b)
    crank, leg = bodies["crank"], bodies["leg"]
    b.add_handle("crank_pin", b.body_points(crank.body, torch.as_tensor(crank.to_local(J["crank_coupler"]))))
    b.add_handle("foot", b.body_points(leg.body, torch.as_tensor(leg.to_local(foot))))
    b.add_driver("crank", "crank_pin", J["crank_ground"], ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)))
    return b.finalize(
        "klann", params=params, description="planar Klann linkage, 0.5 m across, 5 rigid bars + 7 revolute joints"
    )


def stewart(
    *,
    base_radius: float = 0.25,
    plate_radius: float = 0.15,
    height: float = 0.25,
    arm_length: float = 0.08,
    density: float = 2700.0,
    joint_stiffness: float = 1e4,
    axis_stiffness: float = 100.0,
    ball_axis_stiffness: float = 1.0,
    rigid_stiffness: float = 5000.0,
    servo_stiffness: float = 20.0,
    gravity: bool = True,
) -> Scene:
    """A rotary Stewart platform: 6 servo-held arms, 6 struts, a top plate (13 rigid bodies, 6 DOF).

    Base pivots sit on a circle of ``base_radius`` in y = 0 at 120k +- 20 degrees; each arm is
    hinged to the (fixed) world about its radial axis and points tangentially (away from its
    pair partner), ``arm_length`` long. Strut i runs from arm tip i to a point of the top
    plate (radius ``plate_radius``, at y = ``height``) at 120k +- 40 degrees. Joints: arm-world
    hinges (point + strong axis), arm-strut near-ball joints (point + weak alignment of the
    radial axis, which only fixes the strut's spin), strut-plate ball joints. At the seed all
    bodies are unrotated and every joint is exactly satisfied.

    Actuation, as in a real rotary Stewart platform: each arm is driven about its hinge by a
    servo. Holding (zero action) is the "servos" term, a torsional spring of
    ``servo_stiffness`` [N m/rad] per arm towards its seed angle (energy servo_stiffness/2 |a - a0|^2
    for the arm's direction a, ~ servo_stiffness/2 theta^2), stiff enough that the seed pose holds
    under gravity (the plate sags under a millimetre). Driving is a torque on the hinge: the
    handles "arm_0".."arm_5" sit at the arm tips, where a force F along y (the tip's swing
    direction at the seed) is a hinge torque F ``arm_length`` [N m].

    Body order: 6 arms, 6 struts, the plate (x entries 12 i .. 12 i + 11). n = 156 (13 bodies);
    Table 1 lists 168 (14 bodies, its base being a body).

    Args:
        base_radius: Radius of the arm pivots [m].
        plate_radius: Radius of the plate joints [m].
        height: Height of the plate above the base [m].
        arm_length: Arm length [m].
        density: Density of all parts [kg/m^3].
        joint_stiffness: Joint point penalty weight [N/m].
        axis_stiffness: Arm hinge-axis alignment weight [J].
        ball_axis_stiffness: Weak arm-strut axis alignment weight [J].
        rigid_stiffness: Orthogonality penalty per body [J].
        servo_stiffness: Torsional stiffness of each arm's servo about its seed angle [N m/rad].
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: rigid, joints, joint_axes, servos, gravity, external_load. Handles: "top_plate"
    (the plate centre), "arm_0".."arm_5" (the arm tips). Surfaces: "arm_i", "strut_i", "plate".
    """
    params = builder_params(locals())
    for key in (
        "base_radius",
        "plate_radius",
        "height",
        "arm_length",
        "density",
        "joint_stiffness",
        "axis_stiffness",
        "ball_axis_stiffness",
        "rigid_stiffness",
        "servo_stiffness",
    ):
        check_positive(key, params[key])
    gravity = check_bool("gravity", gravity)

    b = SceneBuilder(dim=3)
    base_angles, plate_angles, signs = [], [], []
    for k in range(3):
        for side in (-1.0, 1.0):
            base_angles.append(math.radians(120.0 * k + 20.0 * side))
            plate_angles.append(math.radians(120.0 * k + 40.0 * side))
            signs.append(side)

    def on_circle(radius: float, angle: float, y: float) -> np.ndarray:
        return np.array([radius * math.cos(angle), y, radius * math.sin(angle)])

    pivots = [on_circle(base_radius, a, 0.0) for a in base_angles]
    radial = [np.array([math.cos(a), 0.0, math.sin(a)]) for a in base_angles]
    tangent = [np.array([-math.sin(a), 0.0, math.cos(a)]) for a in base_angles]
    tips = [p + arm_length * s * t for p, s, t in zip(pivots, signs, tangent, strict=True)]
    tops = [on_circle(plate_radius, a, height) for a in plate_angles]

    arms = [
        add_rigid_body(b, _rod(p, t, 0.01), density=density, surface=f"arm_{i}")
        for i, (p, t) in enumerate(zip(pivots, tips, strict=True))
    ]
    struts = [
        add_rigid_body(b, _rod(a, t, 0.006), density=density, surface=f"strut_{i}")
        for i, (a, t) in enumerate(zip(tips, tops, strict=True))
    ]
    disc = _cylinder_y((0.0, height, 0.0), plate_radius + 0.02, 0.01)
    plate = add_rigid_body(b, disc, density=density, surface="plate")
    add_rigidity(b, [*arms, *struts, plate], rigid_stiffness)

    joints = Joints(b)
    for i in range(6):
        joints.pin(arms[i], None, pivots[i])
        joints.align(arms[i], None, radial[i], axis_stiffness)
        joints.pin(struts[i], arms[i], tips[i])
        joints.align(struts[i], arms[i], radial[i], ball_axis_stiffness)
        joints.pin(plate, struts[i], tops[i])
    joints.finish(joint_stiffness)
    swing = [s * t for s, t in zip(signs, tangent, strict=True)]  # arm directions, pivot to tip
    b.add_effect(
        PointPairPenalty(
            "servos",
            PointSet.cat(
                [
                    b.body_points(arm.body, torch.as_tensor(d @ arm.rotation).reshape(1, 3), direction=True)
                    for arm, d in zip(arms, swing, strict=True)
                ]
            ),
            PointSet.world(torch.as_tensor(np.stack(swing)), k=4),
            servo_stiffness,
            kind="servo",
        )
    )
    if gravity:
        add_gravity(b)
    b.add_handle("top_plate", b.body_points(plate.body, torch.zeros(1, 3)))
    for i, (arm, tip) in enumerate(zip(arms, tips, strict=True)):
        b.add_handle(f"arm_{i}", b.body_points(arm.body, torch.as_tensor(arm.to_local(tip))))
    return b.finalize(
        "stewart",
        params=params,
        description=f"rotary Stewart platform, base radius {base_radius:g} m, plate at {height:g} m; 13 rigid bodies",
    )


CATALOG = {
    "cloth_ball": cloth_ball,
    "klann": klann,
    "stewart": stewart,
    "bistable_bar": bistable_bar,
    "hanging_sheet": hanging_sheet,
    "conditional_bar": conditional_bar,
    "chain": chain,
    "mini_chain": mini_chain,
    "stiff_body": stiff_body,
    "cantilever": cantilever,
    "elephant": elephant,
    "hetero_beam": hetero_beam,
}
"""The catalog scenes by name, in Table 1 order (hetero_beam last)."""
