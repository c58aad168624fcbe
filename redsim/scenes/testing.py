"""Tiny toy scenes for fast tests (registered in the catalog as ``toy_<name>``).

Each builds in milliseconds, has n <= 48 and at least one handle, and uses the same
effects as the big scenes, so fitting, integrators and envs can be smoke-tested on them.
"""

from __future__ import annotations

import numpy as np
import torch

from redsim import meshes
from redsim.scene import Scene, SceneBuilder
from redsim.scenes import toolkit
from redsim.scenes.registry import Crank, SceneEntry


def two_tets(*, young: float = 1e4, poisson: float = 0.4, density: float = 1000.0, gravity: bool = True) -> Scene:
    """Two unit-ish tets sharing the triangle (v0, v1, v2) in the y = 0 plane, which is pinned; n = 6.

    v3 sits 0.1 m above the shared face, v4 0.1 m below it.

    Args:
        young: Young's modulus [Pa].
        poisson: Poisson ratio.
        density: Density [kg/m^3].
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: elastic, [gravity], external_load. Handle: "top" (v3). Surface: "elastic".
    """
    params = toolkit.builder_params(locals())
    toolkit.check_positive("young", young)
    toolkit.check_poisson(poisson)
    toolkit.check_positive("density", density)
    gravity = toolkit.check_bool("gravity", gravity)
    vertices = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.0, 0.1], [0.03, 0.1, 0.03], [0.03, -0.1, 0.03]])
    tets = meshes.orient_tets(vertices, np.array([[0, 1, 2, 3], [0, 1, 2, 4]]))
    b = SceneBuilder(dim=3)
    ids = toolkit.add_fem(b, vertices, tets, young=young, poisson=poisson, density=density)
    b.pin_particles(ids[:3])
    if gravity:
        toolkit.add_gravity(b)
    b.add_handle("top", b.particle_points(ids[3:4]))
    return b.finalize("toy_two_tets", params=params, description="two tets, shared face pinned (m, kg, s)")


def three_link_chain(
    *,
    joint_stiffness: float = 1e4,
    axis_stiffness: float = 100.0,
    rigid_stiffness: float = 5000.0,
    density: float = 1000.0,
    gravity: bool = True,
) -> Scene:
    """A planar triple pendulum: three 0.2 m bars hinged end to end (z axes) below a world pivot; n = 36.

    Args:
        joint_stiffness: Joint point penalty weight [N/m].
        axis_stiffness: Hinge-axis alignment weight [J].
        rigid_stiffness: Orthogonality penalty per body [J].
        density: Bar density [kg/m^3] (each bar is a 0.02 x 0.22 x 0.02 m box, 0.088 kg by default).
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: rigid, joints, joint_axes, [gravity], external_load. Handle: "tip" (the free end
    of the last bar). Surfaces: "link_0".."link_2".
    """
    params = toolkit.builder_params(locals())  # first: the arguments alone (before any local name)
    import trimesh

    for key in ("joint_stiffness", "axis_stiffness", "rigid_stiffness", "density"):
        toolkit.check_positive(key, params[key])
    gravity = toolkit.check_bool("gravity", gravity)
    b = SceneBuilder(dim=3)
    ends = [np.array([0.0, -0.2 * k, 0.0]) for k in range(4)]
    bodies = []
    for k in range(3):
        box = trimesh.creation.box(extents=(0.02, 0.22, 0.02)).apply_translation(0.5 * (ends[k] + ends[k + 1]))
        bodies.append(toolkit.add_rigid_body(b, box, density=density, surface=f"link_{k}"))
    toolkit.add_rigidity(b, bodies, rigid_stiffness)
    joints = toolkit.Joints(b)
    z = np.array([0.0, 0.0, 1.0])
    for k in range(3):
        parent = bodies[k - 1] if k else None
        joints.pin(bodies[k], parent, ends[k])
        joints.align(bodies[k], parent, z, axis_stiffness)
    joints.finish(joint_stiffness)
    if gravity:
        toolkit.add_gravity(b)
    b.add_handle("tip", b.body_points(bodies[2].body, torch.as_tensor(bodies[2].to_local(ends[3]))))
    return b.finalize("toy_three_link_chain", params=params, description="planar triple pendulum of 0.2 m bars")


def small_cloth(
    *,
    young: float = 1e5,
    poisson: float = 0.3,
    thickness: float = 1e-3,
    density: float = 200.0,
    bending: float = 1e-4,
    gravity: bool = True,
) -> Scene:
    """A 0.3 m square cloth of 4 x 4 vertices hanging from its two top corners (xy plane); n = 42.

    Args:
        young: Young's modulus [Pa].
        poisson: Poisson ratio.
        thickness: Thickness [m].
        density: Density [kg/m^3].
        bending: Bending stiffness per hinge [J].
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: membrane, bending, [gravity], external_load. Handle: "bottom_corner". Surface: "cloth".
    """
    params = toolkit.builder_params(locals())
    for key in ("young", "thickness", "density"):
        toolkit.check_positive(key, params[key])
    toolkit.check_poisson(poisson)
    toolkit.check_positive("bending", bending, allow_zero=True)
    gravity = toolkit.check_bool("gravity", gravity)
    vertices, triangles = meshes.cloth_grid(0.3, 0.3, (3, 3), origin=(0.0, -0.3, 0.0))
    b = SceneBuilder(dim=3)
    ids = toolkit.add_cloth(
        b, vertices, triangles, young=young, poisson=poisson, thickness=thickness, density=density, bending=bending
    )
    b.pin_particles(ids[torch.tensor([12, 15])])
    if gravity:
        toolkit.add_gravity(b)
    b.add_handle("bottom_corner", b.particle_points(ids[:1]))
    return b.finalize("toy_small_cloth", params=params, description="0.3 m 4x4-vertex cloth hanging from two corners")


def tiny_bar_2d(
    *, young: float = 1e4, poisson: float = 0.4, density: float = 1000.0, thickness: float = 0.05, gravity: bool = True
) -> Scene:
    """A 2D neo-Hookean bar 0.4 x 0.1 m of 5 x 2 vertices, left end pinned; n = 16.

    Args:
        young: Young's modulus [Pa].
        poisson: Poisson ratio.
        density: Density [kg/m^3].
        thickness: Out-of-plane thickness [m].
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: elastic, [gravity], external_load. Handle: "tip" (the right end). Surface: "elastic".
    """
    params = toolkit.builder_params(locals())
    for key in ("young", "density", "thickness"):
        toolkit.check_positive(key, params[key])
    toolkit.check_poisson(poisson)
    gravity = toolkit.check_bool("gravity", gravity)
    vertices, triangles = meshes.rectangle_grid(0.4, 0.1, (4, 1))
    b = SceneBuilder(dim=2)
    ids = toolkit.add_fem(b, vertices, triangles, young=young, poisson=poisson, density=density, thickness=thickness)
    b.pin_particles(ids[torch.tensor([0, 5])])
    if gravity:
        toolkit.add_gravity(b)
    b.add_handle("tip", b.particle_points(ids[torch.tensor([4, 9])]))
    return b.finalize("toy_tiny_bar_2d", params=params, description="2D bar 0.4 x 0.1 m, left end pinned")


def crank(
    *,
    joint_stiffness: float = 1e4,
    axis_stiffness: float = 100.0,
    rigid_stiffness: float = 5000.0,
    density: float = 1000.0,
    gravity: bool = False,
) -> Scene:
    """One 0.2 m bar hinged to the world at one end (z axis), free to turn all the way round; n = 12.

    The smallest mechanism whose motion is a loop: its crank angle. Without gravity (the default)
    every angle has zero energy.

    Args:
        joint_stiffness: Hinge point penalty weight [N/m].
        axis_stiffness: Hinge-axis alignment weight [J].
        rigid_stiffness: Orthogonality penalty [J].
        density: Bar density [kg/m^3] (a 0.02 x 0.22 x 0.02 m box, 0.088 kg by default).
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: rigid, joints, joint_axes, [gravity], external_load. Handle: "pin" (the free end). Driver
    (fitting only): "crank", the pin round the hinge in the x-y plane, turned by latent 0.
    Surface: "bar".
    """
    params = toolkit.builder_params(locals())  # first: the arguments alone (before any local name)
    import trimesh

    for key in ("joint_stiffness", "axis_stiffness", "rigid_stiffness", "density"):
        toolkit.check_positive(key, params[key])
    gravity = toolkit.check_bool("gravity", gravity)
    b = SceneBuilder(dim=3)
    hinge, end = np.zeros(3), np.array([0.2, 0.0, 0.0])
    bar = toolkit.add_rigid_body(
        b, trimesh.creation.box(extents=(0.22, 0.02, 0.02)).apply_translation(0.5 * end), density=density, surface="bar"
    )
    toolkit.add_rigidity(b, [bar], rigid_stiffness)
    joints = toolkit.Joints(b)
    joints.pin(bar, None, hinge)
    joints.align(bar, None, np.array([0.0, 0.0, 1.0]), axis_stiffness)
    joints.finish(joint_stiffness)
    if gravity:
        toolkit.add_gravity(b)
    b.add_handle("pin", b.body_points(bar.body, torch.as_tensor(bar.to_local(end))))
    b.add_driver("crank", "pin", hinge, ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)))
    return b.finalize("toy_crank", params=params, description="one 0.2 m bar hinged at one end (m, kg, s)")


TOYS: tuple[SceneEntry, ...] = (
    SceneEntry("toy_two_tets", two_tets, tags=("toy",)),
    SceneEntry("toy_three_link_chain", three_link_chain, tags=("toy",)),
    SceneEntry("toy_small_cloth", small_cloth, tags=("toy",)),
    SceneEntry("toy_tiny_bar_2d", tiny_bar_2d, tags=("toy",)),
    SceneEntry("toy_crank", crank, tags=("toy",), crank=Crank("pin", (0.0, 0.0))),
)
"""The toy scenes (tag "toy")."""
