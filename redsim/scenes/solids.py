"""Elastic solids of the catalog: 2D bars (bistable, conditional) and 3D bodies (cantilever,
heterogeneous beam, stiff cow-like body, elephant), all neo-Hookean.

SI units (m, kg, s, Pa, N, J); rubber-like materials, E = 1e5..1e7 Pa, density 1000 kg/m^3.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from redsim import meshes
from redsim.effects import ConditionalPin
from redsim.scene import Scene, SceneBuilder
from redsim.scenes import shapes, toolkit

if TYPE_CHECKING:  # imported where used: import redsim needs none of trimesh (slow to import)
    import trimesh


# ---------------------------------------------------------------------------------------------
# 2D elastic bars
# ---------------------------------------------------------------------------------------------
def _check_bar(params: dict[str, Any]) -> None:
    for key in ("length", "height", "young", "density", "thickness"):
        toolkit.check_positive(key, params[key])
    toolkit.check_poisson(params["poisson"])


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
    Mirror (fitting only, ``redsim fit --mirror``): up-down across the centre line y = height / 2,
    which swaps the two buckled states. Without gravity it leaves the energy unchanged up to the
    checkerboard diagonals, which it maps onto themselves only for even ``cells_y`` (default 9:
    the mirrored up state lies 0.4% of its distance from the seed away from the down state).
    """
    params = toolkit.builder_params(locals())
    cells_x = toolkit.check_int("cells_x", cells_x, 2)
    cells_y = toolkit.check_int("cells_y", cells_y, 1)
    _check_bar(params)
    compression = toolkit.check_range("compression", compression, 1e-3, 1.0)
    gravity = toolkit.check_bool("gravity", gravity)

    rest, triangles = meshes.rectangle_grid(length, height, (cells_x, cells_y))
    seed = rest.copy()
    seed[:, 0] *= compression
    b = SceneBuilder(dim=2)
    ids = toolkit.add_fem(
        b, rest, triangles, young=young, poisson=poisson, density=density, thickness=thickness, seed=seed
    )
    columns = torch.arange(rest.shape[0]) % (cells_x + 1)
    b.pin_particles(ids[(columns == 0) | (columns == cells_x)])
    if gravity:
        toolkit.add_gravity(b)
    b.add_handle("middle", b.particle_points(ids[columns == cells_x // 2]))
    rows = torch.arange(rest.shape[0]) // (cells_x + 1)
    b.mirror_particles(ids[(cells_y - rows) * (cells_x + 1) + columns], axis=1, plane=0.5 * height)
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
    params = toolkit.builder_params(locals())
    cells_x = toolkit.check_int("cells_x", cells_x, 2)
    cells_y = toolkit.check_int("cells_y", cells_y, 1)
    _check_bar(params)
    toolkit.check_positive("pin_width", pin_width)
    toolkit.check_positive("pin_stiffness", pin_stiffness)
    gravity = toolkit.check_bool("gravity", gravity)
    ratio_low, ratio_high = (
        toolkit.check_positive("stiffness_ratio_range", v)
        for v in toolkit.check_pair("stiffness_ratio_range", stiffness_ratio_range)
    )
    loc_low, loc_high = (
        toolkit.check_range("pin_location_range", v, 0.0, 1.0)
        for v in toolkit.check_pair("pin_location_range", pin_location_range)
    )
    if not (ratio_low < ratio_high and loc_low < loc_high):
        raise ValueError("condition ranges must be (low, high) with low < high")

    vertices, triangles = meshes.rectangle_grid(length, height, (cells_x, cells_y))
    b = SceneBuilder(dim=2)
    ratio = b.add_condition("stiffness_ratio", ratio_low, ratio_high, default=min(max(1.0, ratio_low), ratio_high))
    location = b.add_condition("pin_location", loc_low * length, loc_high * length)
    centroid_x = vertices[triangles, 0].mean(axis=1)
    ids = toolkit.add_fem(
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
        toolkit.add_gravity(b)
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
        toolkit.check_positive(key, params[key])
    toolkit.check_poisson(params["poisson"])


def _face_ids(vertices: np.ndarray, axis: int, value: float, tolerance: float) -> torch.Tensor:
    return torch.as_tensor(np.nonzero(np.abs(vertices[:, axis] - value) <= tolerance)[0])


def _beam_mesh(length: float, width: float, cells_x: int, cells_yz: int) -> tuple[np.ndarray, np.ndarray]:
    """Tets of the beam [0, length] x [-width/2, width/2]^2 [m]: vertices [V, 3], tets [T, 4]."""
    return meshes.box_tet_grid(
        (length, width, width), (cells_x, cells_yz, cells_yz), origin=(0.0, -0.5 * width, -0.5 * width)
    )


def _clamped_body(
    vertices: np.ndarray,
    tets: np.ndarray,
    young: float | np.ndarray,
    poisson: float,
    density: float,
    gravity: bool,
) -> tuple[SceneBuilder, torch.Tensor, float]:
    """A new 3D builder holding a beam mesh as one neo-Hookean body, its x = 0 face pinned, with gravity if asked.

    Returns:
        (builder, particle ids [V], the distance [m] within which a vertex counts as on a face).
    """
    b = SceneBuilder(dim=3)
    ids = toolkit.add_fem(b, vertices, tets, young=young, poisson=poisson, density=density)
    tol = 1e-9 * float(vertices[:, 0].max())
    b.pin_particles(ids[_face_ids(vertices, 0, 0.0, tol)])
    if gravity:
        toolkit.add_gravity(b)
    return b, ids, tol


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
    params = toolkit.builder_params(locals())
    cells_x = toolkit.check_int("cells_x", cells_x, 1)
    cells_yz = toolkit.check_int("cells_yz", cells_yz, 1)
    toolkit.check_positive("length", length)
    toolkit.check_positive("width", width)
    _check_solid(params)
    gravity = toolkit.check_bool("gravity", gravity)

    vertices, tets = _beam_mesh(length, width, cells_x, cells_yz)
    b, ids, tol = _clamped_body(vertices, tets, young, poisson, density, gravity)
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
        cells_x: Cells along the beam (>= 2).
        cells_yz: Cells across (in y and in z).
        length: Length [m].
        width: Square cross-section side [m].
        segments: Number of alternating segments (at most ``cells_x``).
        young_stiff: Young's modulus of the stiff segments [Pa].
        young_soft: Young's modulus of the soft segments [Pa].
        poisson: Poisson ratio.
        density: Density [kg/m^3].
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: elastic, gravity, external_load. Handles: "middle" (the cross-section nearest
    x = length/2), "tip" (the free end face). Surface: "elastic".
    """
    params = toolkit.builder_params(locals())
    cells_x = toolkit.check_int("cells_x", cells_x, 2)  # one cell: the section nearest the middle is the clamp
    cells_yz = toolkit.check_int("cells_yz", cells_yz, 1)
    segments = toolkit.check_int("segments", segments, 1)
    if segments > cells_x:  # materials go per tet: a segment shorter than a cell aliases (13 on 4 cells: 10 seen)
        raise ValueError(f"segments must be at most cells_x ({cells_x}) to alternate along the beam, got {segments}")
    for key in ("length", "width", "young_stiff", "young_soft", "density"):
        toolkit.check_positive(key, params[key])
    toolkit.check_poisson(poisson)
    gravity = toolkit.check_bool("gravity", gravity)

    vertices, tets = _beam_mesh(length, width, cells_x, cells_yz)
    centroid_x = vertices[tets, 0].mean(axis=1)
    segment = np.minimum((centroid_x / length * segments).astype(np.int64), segments - 1)
    young = np.where(segment % 2 == 0, young_stiff, young_soft)
    b, ids, tol = _clamped_body(vertices, tets, young, poisson, density, gravity)
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


def _voxel_solid(
    parts: Callable[[], list[trimesh.Trimesh]], params: dict[str, Any], *, max_pitch: float
) -> tuple[SceneBuilder, np.ndarray, np.ndarray, torch.Tensor, float]:
    """One neo-Hookean body voxel-tetrahedralized from the union of ``parts()``, in a new 3D builder.

    Args:
        parts: Makes the primitive meshes [m] (called after the checks).
        params: The builder's arguments: ``voxel_pitch`` [m], ``young``, ``poisson``, ``density``.
        max_pitch: Largest voxel side [m] that still resolves the thinnest parts (the legs).

    Returns:
        (builder, vertices [V, 3] [m], tets [T, 4], particle ids [V], voxel pitch [m]).
    """
    pitch = toolkit.check_positive("voxel_pitch", params["voxel_pitch"])
    _check_solid(params)
    if pitch > max_pitch:
        raise ValueError(f"voxel_pitch must be <= {max_pitch:g} m to resolve the legs, got {pitch}")
    vertices, tets = meshes.voxel_tet_mesh(parts(), pitch)
    b = SceneBuilder(dim=3)
    ids = toolkit.add_fem(
        b, vertices, tets, young=params["young"], poisson=params["poisson"], density=params["density"]
    )
    return b, vertices, tets, ids, pitch


def _cow_parts() -> list[trimesh.Trimesh]:
    """A cow-like body about 0.7 m long, 0.6 m tall, feet on y = 0 [m]."""
    import trimesh

    torso = trimesh.creation.capsule(height=0.36, radius=0.12, count=[16, 16])
    torso.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [0.0, 1.0, 0.0]))
    torso.apply_translation((0.0, 0.35, 0.0))
    legs = [shapes.cylinder_y((x, 0.135, z), 0.045, 0.27) for x in (-0.17, 0.17) for z in (-0.07, 0.07)]
    head = trimesh.creation.icosphere(subdivisions=3, radius=0.09).apply_translation((0.33, 0.45, 0.0))
    horns = [shapes.rod(np.array([0.33, 0.52, z]), np.array([0.33, 0.6, 2.0 * z]), 0.02) for z in (-0.05, 0.05)]
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
    n = 14841 (about 47 kg, 0.75 m long: the voxel solid keeps every voxel the surface passes through, so it holds
    more than the primitives' volume).

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
    params = toolkit.builder_params(locals())
    toolkit.check_positive("pin_radius", pin_radius, allow_zero=True)
    gravity = toolkit.check_bool("gravity", gravity)
    b, vertices, tets, ids, _ = _voxel_solid(_cow_parts, params, max_pitch=0.06)
    torso = np.abs(vertices[:, 0]) <= 0.18
    top = np.nonzero(torso & (vertices[:, 1] >= vertices[torso, 1].max() - 1e-9))[0]
    anchor = vertices[top[np.argmin(np.linalg.norm(vertices[top][:, [0, 2]], axis=1))]]
    pinned = np.nonzero(np.linalg.norm(vertices - anchor, axis=1) <= pin_radius + 1e-9)[0]
    b.pin_particles(ids[torch.as_tensor(pinned)])
    if gravity:
        toolkit.add_gravity(b)
    head = np.nonzero(vertices[:, 0] >= vertices[:, 0].max() - 0.05)[0]
    b.add_handle("head", b.particle_points(ids[torch.as_tensor(head)]))
    return b.finalize(
        "stiff_body",
        params=params,
        description=f"stiff cow-like voxel solid ({tets.shape[0]} tets, E = {young:g} Pa) hanging from one point",
    )


def _elephant_parts() -> list[trimesh.Trimesh]:
    """An elephant-like body about 1.3 m long, 1 m tall, feet on y = 0 [m]."""
    import trimesh

    body = shapes.ellipsoid((0.0, 0.62, 0.0), (0.42, 0.28, 0.26))
    legs = [shapes.cylinder_y((x, 0.28, z), 0.085, 0.56) for x in (-0.24, 0.24) for z in (-0.14, 0.14)]
    head = trimesh.creation.icosphere(subdivisions=3, radius=0.19).apply_translation((0.5, 0.8, 0.0))
    trunk = shapes.rod(np.array([0.62, 0.72, 0.0]), np.array([0.72, 0.25, 0.0]), 0.065)
    ears = [shapes.ellipsoid((0.42, 0.86, z), (0.05, 0.16, 0.12)) for z in (-0.2, 0.2)]
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
    vertices), "back" (the top vertex layer of the body's middle, |x| <= 0.25 m; before stop 44 the mesh's top
    layer, which is the ears' tips and the head's top). Surface: "elastic".
    """
    params = toolkit.builder_params(locals())
    gravity = toolkit.check_bool("gravity", gravity)
    b, vertices, tets, ids, pitch = _voxel_solid(_elephant_parts, params, max_pitch=0.15)
    y = vertices[:, 1]
    b.pin_particles(ids[torch.as_tensor(np.nonzero(y <= y.min() + 0.25 * pitch)[0])])
    if gravity:
        toolkit.add_gravity(b)
    trunk = vertices[:, 0] >= 0.62
    trunk_tip = np.nonzero(trunk & (y <= y[trunk].min() + 0.25 * pitch))[0]
    body = np.abs(vertices[:, 0]) <= 0.25  # the body's middle, clear of the head (x >= 0.31) and ears (0.37-0.47)
    back = np.nonzero(body & (y >= y[body].max() - 0.25 * pitch))[0]  # the mesh's top layer is the ears' tips
    b.add_handle("trunk_tip", b.particle_points(ids[torch.as_tensor(trunk_tip)]))
    b.add_handle("back", b.particle_points(ids[torch.as_tensor(back)]))
    return b.finalize(
        "elephant",
        params=params,
        description=f"elephant-like voxel solid ({tets.shape[0]} tets, E = {young:g} Pa) on pinned feet",
    )
