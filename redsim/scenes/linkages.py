"""Linkages of the catalog: rigid bars joined by penalty joints (the Klann walking linkage, a rotary Stewart platform).

SI units (m, kg, s, N, J); aluminium bars, joint penalties of 1e4 N/m.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from redsim.effects import PointPairPenalty
from redsim.points import PointSet
from redsim.scene import Scene, SceneBuilder
from redsim.scenes import shapes, toolkit
from redsim.scenes.registry import Crank

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

KLANN_CRANK = Crank("crank_pin", KLANN_JOINTS["crank_ground"])
"""The Klann crank: its "crank_pin" handle turns about the crank-ground joint as the one DOF goes round."""


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
    params = toolkit.builder_params(locals())
    for key in ("bar_width", "bar_thickness", "density", "joint_stiffness", "axis_stiffness", "rigid_stiffness"):
        toolkit.check_positive(key, params[key])
    gravity = toolkit.check_bool("gravity", gravity)

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
        name: toolkit.add_rigid_body(
            b, shapes.bar(*spans[name], bar_width, bar_thickness), density=density, surface=name
        )
        for name in KLANN_BODIES
    }
    toolkit.add_rigidity(b, list(bodies.values()), rigid_stiffness)
    joints = toolkit.Joints(b)
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
        toolkit.add_gravity(b)
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
    under gravity (the plate sags 3 mm, mostly the joints' give). Driving is a torque on the hinge:
    the handles "arm_0".."arm_5" sit at the arm tips, where a force F along y (the tip's swing
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
    params = toolkit.builder_params(locals())
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
        toolkit.check_positive(key, params[key])
    gravity = toolkit.check_bool("gravity", gravity)

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
        toolkit.add_rigid_body(b, shapes.rod(p, t, 0.01), density=density, surface=f"arm_{i}")
        for i, (p, t) in enumerate(zip(pivots, tips, strict=True))
    ]
    struts = [
        toolkit.add_rigid_body(b, shapes.rod(a, t, 0.006), density=density, surface=f"strut_{i}")
        for i, (a, t) in enumerate(zip(tips, tops, strict=True))
    ]
    disc = shapes.cylinder_y((0.0, height, 0.0), plate_radius + 0.02, 0.01)
    plate = toolkit.add_rigid_body(b, disc, density=density, surface="plate")
    toolkit.add_rigidity(b, [*arms, *struts, plate], rigid_stiffness)

    joints = toolkit.Joints(b)
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
        toolkit.add_gravity(b)
    b.add_handle("top_plate", b.body_points(plate.body, torch.zeros(1, 3)))
    for i, (arm, tip) in enumerate(zip(arms, tips, strict=True)):
        b.add_handle(f"arm_{i}", b.body_points(arm.body, torch.as_tensor(arm.to_local(tip))))
    return b.finalize(
        "stewart",
        params=params,
        description=f"rotary Stewart platform, base radius {base_radius:g} m, plate at {height:g} m; 13 rigid bodies",
    )
