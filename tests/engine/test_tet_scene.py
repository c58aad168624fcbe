"""A tetrahedral mesh of the user's own (`tet_scene_from_mesh`, `--kind tets`): the solid it holds, used as given."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import redsim
from redsim import meshes
from redsim.scene import SceneBuilder
from redsim.scenes.spec import SceneSpecError, scene_from_spec, scene_spec
from redsim.scenes.toolkit import add_fem, add_gravity

EXTENTS, CELLS = (0.2, 0.04, 0.04), (5, 1, 1)


@pytest.fixture
def bar(tmp_path: Path) -> tuple[Path, np.ndarray, np.ndarray]:
    """A 0.2 x 0.04 x 0.04 m bar of 30 tets in a .npz, and its arrays."""
    vertices, tets = meshes.box_tet_grid(EXTENTS, CELLS)
    path = tmp_path / "bar.npz"
    np.savez(path, vertices=vertices, tets=tets)
    return path, vertices, tets


def test_a_tet_mesh_is_the_solid_it_holds(bar: tuple[Path, np.ndarray, np.ndarray]) -> None:
    """Energy and gradient equal those of the same tets built by hand with the toolkit, pins and mass included."""
    path, vertices, tets = bar
    scene = redsim.scenes.tet_scene_from_mesh(path, young=2e5, pin="min_x", handles={"tip": "max_x"})
    b = SceneBuilder(dim=3)
    ids = add_fem(b, vertices, tets, young=2e5, poisson=0.45, density=1000.0)
    b.pin_particles(ids[torch.as_tensor(np.nonzero(vertices[:, 0] < 1e-9)[0])])
    add_gravity(b)
    by_hand = b.finalize("by_hand")
    assert scene.free_dof_count == by_hand.free_dof_count == 3 * (vertices.shape[0] - 4)
    q = scene.q_seed + 0.003 * torch.randn(8, scene.free_dof_count, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(scene.energy(q), by_hand.energy(q), rtol=1e-12, atol=1e-12)
    q.requires_grad_(True)
    (grad,) = torch.autograd.grad(scene.energy(q).sum(), q)
    (expected,) = torch.autograd.grad(by_hand.energy(q).sum(), q)
    torch.testing.assert_close(grad, expected, rtol=1e-10, atol=1e-10)
    assert scene.handle_names == ("body", "tip") and scene.params["builder"] == "tets"
    torch.testing.assert_close(float(scene.handle("tip").position(scene.full_positions(scene.q_seed[None]))[0, 0]), 0.2)
    assert abs(float(scene.energy_terms(scene.q_seed.unsqueeze(0))["elastic"])) < 1e-12  # the rest is the mesh


def test_tets_of_either_orientation_and_unused_vertices_are_taken(bar: tuple[Path, np.ndarray, np.ndarray]) -> None:
    """A mesher's negative tets are reordered; a vertex no tet uses is left out, and a pin by index still counts
    the vertices as given."""
    _, vertices, tets = bar
    reference = redsim.scenes.tet_scene_from_mesh((vertices, tets), pin=[0, 1])
    flipped = tets.copy()
    flipped[::2, [2, 3]] = flipped[::2, [3, 2]]
    extra = np.vstack([[[9.0, 9.0, 9.0]], vertices])  # vertex 0 is a geometry point no tet uses
    scene = redsim.scenes.tet_scene_from_mesh((extra, flipped + 1), pin=[1, 2])
    assert scene.free_dof_count == reference.free_dof_count
    torch.testing.assert_close(scene.q_seed, reference.q_seed)
    q = reference.q_seed + 0.003 * torch.randn(4, reference.free_dof_count, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(scene.energy(q), reference.energy(q), rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match=r"pin .* selects no vertex"):  # the unused vertex pins nothing
        redsim.scenes.tet_scene_from_mesh((extra, tets + 1), pin=[0])
    soup = vertices[tets].reshape(-1, 3)  # each tet with its own four corners: nothing joins them
    with pytest.warns(UserWarning, match=r"vertices sit where another does; the mesh is used as given \(not welded\)"):
        redsim.scenes.tet_scene_from_mesh((soup, np.arange(soup.shape[0]).reshape(-1, 4)), gravity=False)


def test_the_spec_rebuilds_a_tet_scene_from_its_file(bar: tuple[Path, np.ndarray, np.ndarray]) -> None:
    path, vertices, tets = bar
    scene = redsim.scenes.tet_scene_from_mesh(path, pin=[0, 1, 2, 3], handles={"tip": "max_x"}, name="bar")
    spec = scene_spec(scene)
    assert spec["scene_params"]["selections"] == {"pin": [0, 1, 2, 3]} and len(spec["scene_params"]["mesh_sha256"])
    assert scene_from_spec(spec).fingerprint() == scene.fingerprint()
    np.savez(path, vertices=vertices * 2, tets=tets)
    with pytest.raises(SceneSpecError, match="changed since the scene was recorded"):
        scene_from_spec(spec)
    in_memory = scene_spec(redsim.scenes.tet_scene_from_mesh((vertices, tets)))
    with pytest.raises(SceneSpecError, match=r"in-memory mesh \(source '<arrays>'\); save the arrays with numpy"):
        scene_from_spec(in_memory)


def test_a_file_that_is_not_a_tet_mesh_is_named(tmp_path: Path, bar: tuple[Path, np.ndarray, np.ndarray]) -> None:
    _, vertices, tets = bar
    build = redsim.scenes.tet_scene_from_mesh
    with pytest.raises(FileNotFoundError, match=r"nowhere\.npz"):
        build(tmp_path / "nowhere.npz")
    surface = tmp_path / "part.stl"
    surface.write_text("solid part\nendsolid part\n")
    with pytest.raises(ValueError, match=r"part\.stl' is not a \.npz .* voxelized by fem_scene_from_mesh"):
        build(surface)
    np.save(tmp_path / "v.npy", vertices)
    with pytest.raises(ValueError, match=r"is a single \.npy array; a tetrahedral mesh goes in a \.npz"):
        build(tmp_path / "v.npy")
    np.savez(tmp_path / "extra.npz", vertices=vertices, tets=tets, meta=np.array([{"units": "m"}], dtype=object))
    assert build(tmp_path / "extra.npz", pin="min_x").free_dof_count > 0  # an array it does not read may be anything
    np.savez(tmp_path / "named.npz", points=vertices, tetra=tets)
    with pytest.raises(ValueError, match=r"holds arrays \['points', 'tetra'\], not \['vertices', 'tets'\]"):
        build(tmp_path / "named.npz")
    for args, match in (
        ((vertices[:, :2], tets), r"vertices must have shape \[V >= 4, 3\], got \[24, 2\]"),
        ((np.where(np.arange(72).reshape(24, 3) == 5, np.nan, vertices), tets), "non-finite"),
        ((vertices, tets[:, :3]), r"tets must have shape \[T >= 1, 4\]"),
        ((vertices, tets + 0.5), "whole vertex indices"),
        ((vertices, np.vstack([tets, [[0, 1, 2, 24]]])), r"must lie in \[0, 24\) \(counted from 0\), got 24"),
        ((vertices, np.vstack([tets, [[0, 1, 1, 2]]])), r"tet 30 repeats a vertex \[0, 1, 1, 2\]"),
        ((vertices, np.vstack([tets, [[0, 1, 2, 3]]])), "tet 30 is degenerate .* tets of nonzero volume"),
        ((vertices, np.vstack([tets, tets[4:5]])), r"tet 30 repeats tet 4 \(.*\); list each tet once"),
        ((vertices, tets, None), "a .npz file path or a \\(vertices, tets\\) pair"),
    ):
        with pytest.raises(ValueError, match=match):
            build(args)


def test_a_volume_mesh_file_given_as_a_surface_names_the_tet_route(tmp_path: Path) -> None:
    path = tmp_path / "part.msh"
    path.write_text("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n")
    with pytest.raises(ValueError, match=r"part\.msh.*a tetrahedral mesh goes in a \.npz .* \(--kind tets\)"):
        redsim.scenes.fem_scene_from_mesh(path)
