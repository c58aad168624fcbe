"""Primitive meshes the catalog scenes are made of (boxes, rods, ellipsoids, cylinders) and rotations."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # imported where used: import redsim needs none of trimesh (slow to import)
    import trimesh


def rotation_y(angle: float) -> np.ndarray:
    """Rotation by ``angle`` [rad] about y, shape [3, 3]."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rotation_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def bar(p0: np.ndarray, p1: np.ndarray, width: float, thickness: float) -> trimesh.Trimesh:
    """A box from p0 to p1 (in the z = const plane of p0), ``width`` wide in-plane, ``thickness`` along z."""
    import trimesh

    d = np.asarray(p1, dtype=np.float64) - np.asarray(p0, dtype=np.float64)
    length = float(np.linalg.norm(d))
    box = trimesh.creation.box(extents=(length + width, width, thickness))
    transform = np.eye(4)
    transform[:3, :3] = _rotation_z(math.atan2(d[1], d[0]))
    transform[:3, 3] = 0.5 * (np.asarray(p0) + np.asarray(p1))
    return box.apply_transform(transform)


def rod(p0: np.ndarray, p1: np.ndarray, radius: float) -> trimesh.Trimesh:
    """A capsule whose sphere centres are p0 and p1 [m]."""
    import trimesh

    p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    d = p1 - p0
    capsule = trimesh.creation.capsule(height=float(np.linalg.norm(d)), radius=radius, count=[12, 12])
    transform = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], d / np.linalg.norm(d))
    transform[:3, 3] = 0.5 * (p0 + p1)
    return capsule.apply_transform(transform)


def ellipsoid(centre: tuple[float, float, float], semi_axes: tuple[float, float, float]) -> trimesh.Trimesh:
    """An ellipsoid (icosphere, 3 subdivisions) with ``semi_axes`` [m] centred at ``centre`` [m]."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    sphere.apply_scale(semi_axes)
    return sphere.apply_translation(centre)


def cylinder_y(centre: tuple[float, float, float], radius: float, height: float) -> trimesh.Trimesh:
    """A cylinder of ``radius`` and ``height`` [m] with a vertical (y) axis, centred at ``centre`` [m]."""
    import trimesh

    cylinder = trimesh.creation.cylinder(radius=radius, height=height, sections=24)
    cylinder.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1.0, 0.0, 0.0]))
    return cylinder.apply_translation(centre)
