"""Metric numbers by hand where the paper's metrics had no check (hand mutation audit, helper-281): the stretch's
rms_log of a uniformly stretched map, and the generated loads taking the handles in turn."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from redsim import meshes, metrics, scenes
from redsim.effects import NeoHookean
from redsim.scene import SceneBuilder
from redsim.scenes import toolkit
from redsim.subspace import LinearSubspace

pytestmark = pytest.mark.usefixtures("equilibrium_cache")


def test_rms_log_of_a_map_stretched_twice_is_log_2() -> None:
    """rms_log is the root of the fitting loss's pair term, mean(log s)^2 included: log 2 for s = 2 on every pair
    (a standard deviation of log s would read 0)."""
    scene = scenes.build("toy_two_tets")
    sigma = 0.05
    mass = torch.as_tensor(scene.mass_matrix_scipy().diagonal())
    Q, _ = torch.linalg.qr(
        torch.randn(scene.free_dof_count, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    )
    stats = metrics.stretch_stats(scene, LinearSubspace(2.0 * sigma * Q / mass.sqrt()[:, None], scene.q_seed), sigma)
    assert stats["mean_log"] == pytest.approx(math.log(2.0), rel=1e-9)
    assert stats["rms_log"] == pytest.approx(math.log(2.0), rel=1e-9)


def _two_handled_tets():
    """toy_two_tets with a handle on each free vertex."""
    vertices = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.0, 0.1], [0.03, 0.1, 0.03], [0.03, -0.1, 0.03]])
    b = SceneBuilder(dim=3)
    ids = toolkit.add_fem(
        b,
        vertices,
        meshes.orient_tets(vertices, np.array([[0, 1, 2, 3], [0, 1, 2, 4]])),
        young=1e5,
        poisson=0.3,
        density=1e3,
    )
    b.pin_particles(ids[:3])
    b.add_handle("top", b.particle_points(ids[3:4]))
    b.add_handle("bottom", b.particle_points(ids[4:5]))
    return b.finalize("two_handled_tets")


def test_generated_loads_take_the_handles_in_turn() -> None:
    scene = _two_handled_tets()
    identity = LinearSubspace(torch.eye(scene.free_dof_count, dtype=torch.float64), scene.q_seed)
    result = metrics.load_response_error(scene, identity, count=4, magnitude=2.0, restarts=0)
    loads = torch.tensor(result["loads"])  # [4, H, D]
    pushed = loads.norm(dim=-1)  # [4, H]
    torch.testing.assert_close(
        pushed, torch.tensor([[2.0, 0.0], [0.0, 2.0], [2.0, 0.0], [0.0, 2.0]], dtype=pushed.dtype)
    )
    assert result["max_error"] < 1e-3  # the identity answers every load


def test_the_response_error_leaves_out_a_fixed_offset_of_the_maps_rest() -> None:
    """A free tet pulled apart at two corners (no net force): its energy and the loads' work do not change under a
    translation, so a map shifted by one rests shifted and responds alike. The error counts the shift, the response
    error (measured from the map's own unloaded equilibrium) does not."""
    tet = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    b = SceneBuilder(dim=3)
    ids = b.add_particles(tet, torch.ones(4))
    b.add_effect(NeoHookean("elastic", b.particle_dofs(torch.tensor([[0, 1, 2, 3]])), tet[None], 1e3, 0.3))
    b.add_handle("a", b.particle_points(ids[:1]))
    b.add_handle("b", b.particle_points(ids[1:2]))
    scene = b.finalize("stretched_tet")
    loads = [{"a": [-50.0, 0.0, 0.0], "b": [50.0, 0.0, 0.0]}]
    shift = torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64).repeat(4)
    runs = [
        metrics.load_response_error(
            scene, LinearSubspace(torch.eye(12, dtype=torch.float64), scene.q_seed + offset), loads=loads, restarts=0
        )
        for offset in (torch.zeros_like(shift), shift)
    ]
    assert all(r["full_converged"] == [True] and r["latent_converged"] == [True] for r in runs)
    assert runs[0]["rest_error"] == 0.0 and runs[1]["rest_error"] == pytest.approx(0.6)  # |0.3 e_x|_M over 4 kg
    assert runs[1]["errors"][0] > runs[0]["errors"][0] + 0.1
    assert runs[1]["response_errors"][0] == pytest.approx(runs[0]["response_errors"][0], rel=1e-9)
