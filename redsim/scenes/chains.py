"""Chains of the catalog: rigid torus links held together by contact only (24 links, and the 2-link mini chain).

SI units (m, kg, s, N, J); steel links, contact penalties of 1e5 N/m.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from redsim import meshes
from redsim.effects import FrameSet, SDFContact, Torus
from redsim.points import PointSet
from redsim.scene import Scene, SceneBuilder
from redsim.scenes import shapes, toolkit


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
        density: Link density [kg/m^3] (steel). A link's mass and inertia are those of its drawn mesh (24 x 8
            sections), 11% below the smooth torus that contact uses (2 pi^2 R r^2 density): 0.685 kg, not 0.770 kg,
            at the defaults.
        contact_stiffness: Contact penalty weight [N/m] per sample point.
        contact_samples: Centre-line sample points per link and neighbour.
        rigid_stiffness: Orthogonality penalty [J] per link.
        gravity: Add gravity (9.81 m/s^2 along -y).

    Effects: rigid, contact, gravity, external_load. Handle: "bottom" (the centre of the last
    link). Surfaces: "link_0", ..., and "hook". Body k is link k (x entries 12k .. 12k+11).
    """
    params = toolkit.builder_params(locals())
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
    params = toolkit.builder_params(locals())
    return _chain_scene("mini_chain", params, 2)


def _chain_scene(name: str, params: dict[str, Any], links: int) -> Scene:
    """Validate the chain parameters and build a chain of ``links`` links (see :func:`chain`)."""
    import trimesh

    links = toolkit.check_int("links", links, 1)
    samples = toolkit.check_int("contact_samples", params["contact_samples"], 8)
    major, minor, density, contact_stiffness, rigid_stiffness = (
        toolkit.check_positive(key, params[key])
        for key in ("link_radius", "wire_radius", "density", "contact_stiffness", "rigid_stiffness")
    )
    gravity = toolkit.check_bool("gravity", params["gravity"])
    if not minor < major / 2.5:
        raise ValueError(f"wire_radius must be < link_radius / 2.5 = {major / 2.5:g}, got {minor}")
    b = SceneBuilder(dim=3)
    spacing = 2.0 * major - 2.5 * minor
    torus = trimesh.creation.torus(major_radius=major, minor_radius=minor, major_sections=24, minor_sections=8)
    turned = shapes.rotation_y(0.5 * math.pi)
    bodies = [
        toolkit.add_rigid_body(
            b,
            torus,
            density=density,
            rotation=np.eye(3) if k % 2 == 0 else turned,
            translation=(0.0, -(k + 1) * spacing, 0.0),
            surface=f"link_{k}",
        )
        for k in range(links)
    ]
    toolkit.add_rigidity(b, bodies, rigid_stiffness)
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
        toolkit.add_gravity(b)
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
