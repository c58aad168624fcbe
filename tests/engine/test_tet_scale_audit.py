"""``tet_scene_from_mesh(..., scale=s)`` reads a tet mesh's coordinates times s (1e-3 for a file in millimetres), as
the surface-mesh builders do. With the multiplication dropped (hand mutation audit, helper-283) the scene stayed in the
file's units, its masses 1e9 times too large for a millimetre file, and every test passed: none built a tet scene
with a scale other than 1."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from redsim.meshes import box_tet_grid
from redsim.scenes import tet_scene_from_mesh


def test_a_tet_mesh_s_scale_multiplies_its_coordinates_and_sets_its_masses() -> None:
    vertices, tets = box_tet_grid((100.0, 50.0, 20.0), (2, 2, 1))  # millimetres
    scene = tet_scene_from_mesh((vertices, tets), scale=1e-3, density=1000.0, gravity=False)
    x = scene.full_positions(scene.q_seed[None])[0].reshape(-1, 3)
    extent = (x.max(0).values - x.min(0).values).tolist()
    assert extent == pytest.approx([0.1, 0.05, 0.02])
    total_mass = float(torch.as_tensor(scene.mass_matrix_scipy().diagonal()).sum()) / 3  # free DOFs' lumped masses
    assert total_mass <= 1000.0 * 0.1 * 0.05 * 0.02 + 1e-12  # the pinned vertices' share is not in M
    assert total_mass > 0.5 * 1000.0 * 0.1 * 0.05 * 0.02
    assert np.isclose(scene.params["scale"], 1e-3)
