"""Subspace metrics on maps whose answers are known exactly.

Identity and isometric affine maps (float64) give the full-space answers (load errors at the
solver tolerance, FULL_TOL = 1e-5 of the forces acting; stretch 1 to round-off); rigid
rotations have zero strain to round-off and a simple shear has the closed-form Green strain
sqrt(2 s^2 + s^4) / 2.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import pytest
import torch
from torch import Tensor, nn

from redsim import Scene, SceneBuilder, metrics, scenes
from redsim.effects import NeoHookean
from redsim.integrators import static_equilibrium
from redsim.subspace import LinearSubspace, SubspaceConfig, SubspaceMap

pytestmark = pytest.mark.usefixtures("equilibrium_cache")

TET = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)


def Affine(b: Tensor, A: Tensor) -> LinearSubspace:
    """f(z) = b + A z (A [n, d], b [n]): the linear baseline serves as the test map."""
    return LinearSubspace(A, b)


class Rotation(nn.Module):
    """f(z) = R(z) x_rest with R(z) = exp([z]_x): rigid rotations of an unpinned rest shape (d = 3)."""

    latent_dim = 3

    def __init__(self, rest: Tensor) -> None:
        super().__init__()
        self.register_buffer("rest", rest.reshape(-1, 3).clone())

    def forward(self, z: Tensor) -> Tensor:
        zero = torch.zeros_like(z[..., 0])
        skew = torch.stack(
            [
                torch.stack([zero, -z[..., 2], z[..., 1]], -1),
                torch.stack([z[..., 2], zero, -z[..., 0]], -1),
                torch.stack([-z[..., 1], z[..., 0], zero], -1),
            ],
            -2,
        )
        return (self.rest @ torch.linalg.matrix_exp(skew).transpose(-1, -2)).flatten(-2)


def _free_tet() -> Scene:
    """One unpinned neo-Hookean tet (no handles, no gravity)."""
    b = SceneBuilder(dim=3)
    b.add_particles(TET, torch.ones(4))
    b.add_effect(NeoHookean("elastic", b.particle_dofs(torch.tensor([[0, 1, 2, 3]])), TET[None], 1e3, 0.3))
    return b.finalize("free_tet")


def _identity(scene: Scene) -> Affine:
    return Affine(scene.q_seed, torch.eye(scene.free_dof_count, dtype=torch.float64))


def test_load_response_is_zero_for_the_identity_and_large_for_a_bad_map(count_solves: Callable[[], list[int]]) -> None:
    scene = scenes.build("toy_two_tets")
    calls = count_solves()
    rest, converged = metrics.rest_state(scene)
    exact = metrics.load_response_error(scene, _identity(scene), count=4)
    assert len(calls) == 5  # the rest equilibrium (shared with rest_state) and one per load
    q = rest.unsqueeze(0).requires_grad_(True)
    (gradient,) = torch.autograd.grad(scene.to(dtype=torch.float64).energy(q).sum(), q)
    assert converged and rest.dtype == torch.float64 and float(gradient.norm()) < 1e-6
    # Both sides stop at a force balance of FULL_TOL = 1e-5 of F (the summed force norms, ~10x the load's).
    assert exact["max_error"] < 1e-3 and exact["rest_error"] < 1e-3 * min(exact["displacements"])
    assert max(exact["response_errors"]) < 2e-3 and exact["mean_response_error"] < 2e-3
    assert all(exact["full_converged"]) and all(exact["latent_converged"]) and exact["rest_converged"]
    loads = torch.tensor(exact["loads"], dtype=torch.float64)
    assert loads.shape == (4, 1, 3)
    torch.testing.assert_close(loads.norm(dim=-1), torch.full((4, 1), exact["magnitudes"]["top"], dtype=torch.float64))

    one_direction = torch.zeros(scene.free_dof_count, 1, dtype=torch.float64)
    one_direction[0] = 0.01  # x of the top vertex only
    bad = metrics.load_response_error(scene, Affine(scene.q_seed, one_direction), count=4)
    assert len(calls) == 5  # the full-space equilibria came from the cache
    assert bad["loads"] == exact["loads"] and bad["mean_error"] > 0.3 and bad["mean_response_error"] > 0.3
    assert all(g > 0.0 for g in bad["energy_gaps"])  # the subspace equilibrium is higher in energy

    bigger = metrics.load_response_error(scene, _identity(scene), count=4, response_fraction=0.3)
    assert bigger["magnitudes"]["top"] == pytest.approx(3.0 * exact["magnitudes"]["top"])
    assert bigger["response_fraction"] == 0.3 and bigger["max_error"] < 1e-3
    with pytest.raises(ValueError, match="response_fraction"):
        metrics.load_response_error(scene, _identity(scene), response_fraction=-1.0)
    other = metrics.load_response_error(scene, _identity(scene), count=2, seed=1, magnitude=2.0)
    assert other["loads"][0] != exact["loads"][0] and other["magnitudes"] == {"top": 2.0}
    explicit = metrics.load_response_error(scene, _identity(scene), loads=[{"top": [0.0, -3.0, 0.0]}], restarts=0)
    assert explicit["loads"] == [[[0.0, -3.0, 0.0]]] and explicit["magnitudes"] is None
    assert explicit["max_error"] < 1e-3
    with pytest.raises(ValueError, match="handles"):
        metrics.load_response_error(_free_tet(), _identity(_free_tet()))
    with pytest.raises(ValueError, match="count"):
        metrics.load_response_error(scene, _identity(scene), count=0)


def test_loads_the_scene_cannot_hold_are_left_out_of_the_load_errors() -> None:
    """cloth_ball's pushes on its ball roll it off the cloth: no static equilibrium exists, the full-space solve stops
    unconverged with the ball falling, and its error (against a falling state) entered the mean. A free tet pushed by
    a net force has none either; the zero load it holds is the only one averaged."""
    b = SceneBuilder(dim=3)
    ids = b.add_particles(TET, torch.ones(4))
    b.add_effect(NeoHookean("elastic", b.particle_dofs(torch.tensor([[0, 1, 2, 3]])), TET[None], 1e3, 0.3))
    b.add_handle("corner", b.particle_points(ids[:1]))
    scene = b.finalize("pushed_tet")
    pushed = metrics.load_response_error(
        scene, _identity(scene), loads=[{"corner": [0.0, 0.0, 0.0]}, {"corner": [1.0, 0.0, 0.0]}], restarts=0
    )
    assert pushed["full_converged"] == [True, False] and pushed["averaged_loads"] == 1
    assert pushed["mean_error"] == pushed["max_error"] == pushed["errors"][0] < 1e-3 < pushed["errors"][1]
    assert pushed["mean_response_error"] == pushed["response_errors"][0]
    never = metrics.load_response_error(scene, _identity(scene), loads=[{"corner": [1.0, 0.0, 0.0]}], restarts=0)
    assert never["averaged_loads"] == 0 and math.isnan(never["mean_error"]) and math.isnan(never["mean_response_error"])


def test_nonrigid_strain_is_zero_for_rotations_and_exact_for_a_shear() -> None:
    scene = _free_tet()
    rigid = metrics.nonrigid_strain(scene, Rotation(scene.q_seed), samples=64)
    assert rigid["max"] < 1e-12 and rigid["seed_strain"] == 0.0
    column = torch.zeros(4, 3, dtype=torch.float64)
    column[:, 0] = TET[:, 1]  # x += s y: F = I + s e_x e_y^T
    sheared = metrics.nonrigid_strain(scene, Affine(scene.q_seed, column.reshape(12, 1)), samples=64)
    s = torch.randn(64, 1, generator=torch.Generator().manual_seed(0), dtype=torch.float64)[:, 0]
    assert sheared["mean"] == pytest.approx(float((torch.sqrt(2 * s**2 + s**4) / 2).mean()), rel=1e-10)
    with pytest.raises(ValueError, match="neo-Hookean"):
        b = SceneBuilder(dim=3)
        b.add_particles(TET, torch.ones(4))
        b.add_gravity((0.0, -9.81, 0.0))
        particles = b.finalize("particles")
        metrics.nonrigid_strain(particles, _identity(particles))


def test_stretch_of_an_isometric_affine_map_is_one() -> None:
    scene = scenes.build("toy_two_tets")
    sigma, d = 0.05, 3
    mass = torch.as_tensor(scene.mass_matrix_scipy().diagonal())  # lumped: M is diagonal
    Q, _ = torch.linalg.qr(
        torch.randn(scene.free_dof_count, d, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    )
    A = sigma * Q / mass.sqrt()[:, None]  # A^T M A = sigma^2 I
    stats = metrics.stretch_stats(scene, Affine(scene.q_seed, A), sigma, samples=64)
    assert stats["pairs"] == 64 * 63 // 2
    for key in ("mean", "min", "max"):
        assert stats[key] == pytest.approx(1.0, abs=1e-10)
    assert stats["std"] < 1e-10 and abs(stats["mean_log"]) < 1e-10
    assert metrics.stretch_stats(scene, Affine(scene.q_seed, 2 * A), sigma, samples=16)["mean"] == pytest.approx(2.0)
    with pytest.raises(ValueError, match="sigma"):
        metrics.stretch_stats(scene, Affine(scene.q_seed, A), 0.0)


def test_energy_stats_are_seeded_and_relative_to_the_seed_to_rest_drop() -> None:
    scene = scenes.build("toy_two_tets")
    n = scene.free_dof_count
    small = Affine(scene.q_seed, 1e-3 * torch.eye(n, dtype=torch.float64))
    first = metrics.energy_stats(scene, small, samples=128, seed=3)
    assert first == metrics.energy_stats(scene, small, samples=128, seed=3)
    assert first["mean_energy"] != metrics.energy_stats(scene, small, samples=128, seed=4)["mean_energy"]
    assert all(math.isfinite(v) for k, v in first.items() if k.endswith("energy"))
    assert first["rest_converged"] and first["rest_energy"] < first["seed_energy"]
    assert first["excess_energy"] == pytest.approx(first["mean_energy"] - first["rest_energy"])
    zero = torch.zeros(n, 1, dtype=torch.float64)
    at_seed = metrics.energy_stats(scene, Affine(scene.q_seed, zero), samples=8)
    assert at_seed["relative_energy"] == pytest.approx(1.0)
    q_rest, _ = static_equilibrium(scene, tol=metrics.FULL_TOL)  # what energy_stats solves (Newton converges)
    assert metrics.energy_stats(scene, Affine(q_rest, zero), samples=8)["relative_energy"] == pytest.approx(
        0.0, abs=1e-12
    )
    no_gravity = scenes.build("toy_two_tets", gravity=False)
    assert metrics.energy_stats(no_gravity, small, samples=8)["relative_energy"] is None
    # samples far above the seed (a baseline's sheared states) leave it defined: the floor is the drop's, not theirs
    wild = metrics.energy_stats(scene, Affine(scene.q_seed, 100.0 * torch.eye(n, dtype=torch.float64)), samples=8)
    drop = wild["seed_energy"] - wild["rest_energy"]
    assert wild["mean_energy"] > 1e9 * drop and wild["relative_energy"] == pytest.approx(wild["excess_energy"] / drop)


def test_evaluate_subspace_bundles_the_metrics_as_json() -> None:
    scene = scenes.build("toy_tiny_bar_2d")
    torch.manual_seed(0)
    model = SubspaceMap(SubspaceConfig(latent_dim=2, output_dim=scene.free_dof_count, hidden_width=16, hidden_layers=2))
    with pytest.raises(ValueError, match="sigma"):
        metrics.evaluate_subspace(scene, model)
    model.metadata = {"fit": {"sigma": 0.1}}
    result = metrics.evaluate_subspace(scene, model, loads_count=2, samples=16)
    assert {"energy", "stretch", "load_response", "nonrigid_strain", "seconds"} <= set(result)
    assert result["latent_dim"] == 2 and result["stretch"]["sigma"] == 0.1
    assert len(result["load_response"]["errors"]) == 2
    json.dumps(result, allow_nan=False)
    free = _free_tet()
    no_loads = metrics.evaluate_subspace(free, Rotation(free.q_seed), sigma=1.0, samples=8)
    assert "load_response" not in no_loads and no_loads["nonrigid_strain"]["max"] < 1e-12


class _HandleOrbit(torch.nn.Module):
    """f(z): toy_two_tets' free top vertex on a circle of radius 0.1 m about (0, 1) at angle swing(z)."""

    latent_dim = 1

    def __init__(self, seed: Tensor, swing: Any) -> None:
        super().__init__()
        self.config = SimpleNamespace(periodic=(0,), condition_dim=0)
        self.register_buffer("seed", seed.clone())
        self.swing = swing

    def forward(self, z: Tensor) -> Tensor:
        angle = self.swing(z[..., 0])
        q = self.seed.expand(*z.shape[:-1], -1).clone()
        q[..., 0], q[..., 1] = 0.1 * torch.cos(angle), 1.0 + 0.1 * torch.sin(angle)
        return q


def test_handle_winding_tells_a_closed_loop_from_a_swing() -> None:
    scene = scenes.build("toy_two_tets")
    loop = metrics.handle_winding(scene, _HandleOrbit(scene.q_seed, lambda z: z), "top", (0.0, 1.0), samples=90)
    assert loop["winding"] == 1 and loop["turn_degrees"] == pytest.approx(360.0)
    backwards = metrics.handle_winding(scene, _HandleOrbit(scene.q_seed, lambda z: -z), "top", (0.0, 1.0))
    assert backwards["winding"] == -1
    swing = metrics.handle_winding(scene, _HandleOrbit(scene.q_seed, lambda z: 0.3 * torch.sin(z)), "top", (0, 1))
    assert swing["winding"] == 0 and swing["turn_degrees"] == pytest.approx(2 * math.degrees(0.3), rel=1e-3)
    assert swing["energy_min"] <= swing["energy_max"] and math.isfinite(swing["seed_energy"])
    with pytest.raises(ValueError, match="handle"):
        metrics.handle_winding(scene, _HandleOrbit(scene.q_seed, lambda z: z), "nope", (0.0, 1.0))
    with pytest.raises(ValueError, match="periodic"):
        metrics.handle_winding(scene, _identity(scene), "top", (0.0, 1.0))
