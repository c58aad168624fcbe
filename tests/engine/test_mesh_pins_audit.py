"""Pins of mesh scenes and the registry's defaults, from a hand mutation audit: a given vertex no triangle uses pins
nothing (it was its nearest vertex under a dropped distance check), a mesh of two pieces pinned in each builds (a
check of the first pin's piece alone refused it), and a scene entry's full-space tolerance defaults to 1e-8."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import redsim
from redsim import meshes, scenes
from redsim.scenes.registry import SceneEntry


def test_a_pin_on_a_vertex_no_triangle_uses_pins_nothing_else() -> None:
    vertices, triangles = meshes.cloth_grid(0.5, 0.5, (6, 6), origin=(0.0, 0.0, 0.0))
    stray = np.vstack([[[0.5, 0.55, 0.0]], vertices])  # unused, 5 cm from the top corner (0.5, 0.5, 0)
    bottom = np.nonzero(np.isclose(stray[:, 1], 0.0))[0]
    mesh = trimesh.Trimesh(stray, triangles + 1, process=False)
    scene = redsim.scenes.cloth_scene_from_mesh(mesh, pin=np.concatenate([[0], bottom]))
    expected = redsim.scenes.cloth_scene_from_mesh(trimesh.Trimesh(vertices, triangles), pin="min_y")
    assert scene.free_dof_count == expected.free_dof_count  # the top corner is not pinned in the stray's place


def test_a_cloth_of_two_pieces_pinned_in_each_builds() -> None:
    vertices, triangles = meshes.cloth_grid(0.3, 0.3, (3, 3), origin=(0.0, -0.3, 0.0))
    above = np.array([[0.0, 1.0, 0.0], [0.1, 1.0, 0.0], [0.0, 1.1, 0.0]])
    two = trimesh.Trimesh(np.vstack([vertices, above]), np.vstack([triangles, [[16, 17, 18]]]), process=False)
    top = int(np.argmax(vertices[:, 1]))
    scene = redsim.scenes.cloth_scene_from_mesh(two, pin=[top, 18])
    assert scene.free_dof_count == 3 * (len(vertices) + 3 - 2)
    with pytest.raises(ValueError, match=r"1 of the mesh's 2 separate pieces hold no pinned vertex"):
        redsim.scenes.cloth_scene_from_mesh(two, pin=[top])


def test_a_scene_entrys_full_space_tolerance_defaults_to_1e_8() -> None:
    entry = SceneEntry(name="x", builder=lambda: None)
    assert entry.full_space_tol == 1e-8
    assert scenes.full_space_tol("toy_crank") == 1e-8
