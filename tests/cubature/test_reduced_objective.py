"""The reduced inertia (q = r W^T + b) gives the same Phi, load term (handles A W r + (A b + p0)) included, and the
same |M v| as all of q."""

from __future__ import annotations

import torch

from redsim import pretrained, scenes
from redsim.cubature import CubatureConfig, CubatureEnergy, build_cubature
from redsim.runtime import LatentStepper


def test_an_all_element_cubature_steppers_objective_is_the_map_energys() -> None:
    scene = scenes.build("mini_chain")
    f = pretrained.load("mini_chain", scene)
    cub = build_cubature(scene, f, CubatureConfig(elements=1000, samples=48, episodes=0))
    reduced = LatentStepper(
        scene, f, 0.02, dtype=torch.float64, energy=CubatureEnergy(scene, f, cub, dtype=torch.float64)
    )
    full = LatentStepper(scene, f, 0.02, dtype=torch.float64)
    generator = torch.Generator().manual_seed(0)
    z = reduced.rest_latent().expand(3, -1).clone()
    z_prev = z + 0.05 * torch.randn(z.shape, generator=generator, dtype=torch.float64)
    candidate = z + 0.1 * torch.randn(z.shape, generator=generator, dtype=torch.float64)
    loads = 2.0 * torch.randn(3, len(scene.handles), scene.dim, generator=generator, dtype=torch.float64)
    for given in (None, loads):
        a, b = full.objective(candidate, z, z_prev, given), reduced.objective(candidate, z, z_prev, given)
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-9 * float(a.abs().max())), (a, b)


def test_the_reduced_mass_norm_is_that_of_the_full_velocity() -> None:
    """|M v| of v = dr W^T (the stepper's inertia force scale) from W^T M^2 W in r equals |M v| over all of q."""
    scene = scenes.build("mini_chain")
    f = pretrained.load("mini_chain", scene)
    cub = build_cubature(scene, f, CubatureConfig(elements=1000, samples=48, episodes=0))
    energy = CubatureEnergy(scene, f, cub, dtype=torch.float64)
    reduced = LatentStepper(scene, f, 0.02, dtype=torch.float64, energy=energy)
    weight = energy.output_weight.to(torch.float64)
    dr = torch.randn(4, weight.shape[1], generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    full = torch.linalg.vector_norm(scene.to(dtype=torch.float64).mass_matvec(dr @ weight.T), dim=-1)
    assert torch.allclose(reduced._mass_norm(dr, reduced._mass(dr)), full, rtol=1e-9)
