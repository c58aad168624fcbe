"""Cloth scenes of the catalog: a ball on a pinned sheet (the paper's teaser) and a hanging sheet.

SI units (m, kg, s, Pa, N, J); cloth is StVK membrane + discrete-shell bending, E = 1e6 Pa, 1 mm thick.
"""

from __future__ import annotations

import numpy as np
import torch

from redsim import meshes
from redsim.effects import FrameSet, SDFContact, Sphere
from redsim.scene import Scene, SceneBuilder
from redsim.scenes import toolkit


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
    centre), "cloth_center" (the cloth vertex nearest the middle: the middle one for an even ``cells``, one of
    the four around it for an odd). Surfaces: "cloth", "ball".
    """
    params = toolkit.builder_params(locals())  # first: the arguments alone (before any local name)
    import trimesh

    cells = toolkit.check_int("cells", cells, 2)
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
        toolkit.check_positive(key, params[key])
    toolkit.check_poisson(poisson)
    toolkit.check_positive("bending", bending, allow_zero=True)
    toolkit.check_positive("contact_margin", contact_margin, allow_zero=True)
    gravity = toolkit.check_bool("gravity", gravity)

    b = SceneBuilder(dim=3)
    half = 0.5 * size
    vertices, triangles = meshes.cloth_grid(
        size, size, (cells, cells), origin=(-half, 0.0, half), axis_u=(1.0, 0.0, 0.0), axis_v=(0.0, 0.0, -1.0)
    )
    ids = toolkit.add_cloth(
        b, vertices, triangles, young=young, poisson=poisson, thickness=thickness, density=density, bending=bending
    )
    side = cells + 1
    corners = torch.tensor([0, cells, side * cells, side * side - 1])
    b.pin_particles(ids[corners])

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=ball_radius)
    ball_density = ball_mass / float(sphere.volume)
    lift = ball_radius + contact_margin + 0.005
    ball = toolkit.add_rigid_body(b, sphere, density=ball_density, translation=(0.0, lift, 0.0), surface="ball")
    toolkit.add_rigidity(b, [ball], rigid_stiffness)
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
        toolkit.add_gravity(b)
    b.add_handle("ball", b.body_points(ball.body, torch.zeros(1, 3)))
    middle = int(np.argmin(np.linalg.norm(np.asarray(vertices)[:, [0, 2]], axis=1)))  # index (side * side) // 2
    b.add_handle("cloth_center", b.particle_points(ids[torch.tensor([middle])]))  # where cells is even
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
    params = toolkit.builder_params(locals())
    cells_x = toolkit.check_int("cells_x", cells_x, 1)
    cells_y = toolkit.check_int("cells_y", cells_y, 1)
    for key in ("width", "height", "young", "thickness", "density"):
        toolkit.check_positive(key, params[key])
    toolkit.check_poisson(poisson)
    toolkit.check_positive("bending", bending, allow_zero=True)
    gravity = toolkit.check_bool("gravity", gravity)

    b = SceneBuilder(dim=3)
    vertices, triangles = meshes.cloth_grid(width, height, (cells_x, cells_y), origin=(-0.5 * width, -height, 0.0))
    ids = toolkit.add_cloth(
        b, vertices, triangles, young=young, poisson=poisson, thickness=thickness, density=density, bending=bending
    )
    row = cells_x + 1
    b.pin_particles(ids[cells_y * row :])
    if gravity:
        toolkit.add_gravity(b)
    b.add_handle("bottom_left", b.particle_points(ids[:1]))
    b.add_handle("bottom_right", b.particle_points(ids[cells_x : cells_x + 1]))
    b.add_handle("bottom_middle", b.particle_points(ids[:row]))
    return b.finalize(
        "hanging_sheet",
        params=params,
        description=f"{width:g} x {height:g} m cloth hanging from its top edge (m, kg, s)",
    )
