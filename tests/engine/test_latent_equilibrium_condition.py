"""latent_equilibrium over a LatentSpace made for a condition solves that condition's energy by default."""

from __future__ import annotations

import torch

from redsim import pretrained, scenes
from redsim.integrators import LatentSpace, latent_equilibrium


def test_the_spaces_condition_is_the_energys_condition_by_default() -> None:
    scene, f = scenes.build("conditional_bar"), pretrained.load("conditional_bar")
    space = scene.condition_space
    cond = (space.low + 0.1 * (space.high - space.low)).to(torch.float64)  # far from the default (1.0, 0.65)
    latent = LatentSpace(scene, f, cond=cond)
    loads = {"tip": torch.tensor([0.0, -5.0, 0.0], dtype=torch.float64)[: scene.dim]}
    z_default, info_default = latent_equilibrium(latent, loads)
    z_given, info_given = latent_equilibrium(latent, loads, cond)
    z_scene, _ = latent_equilibrium(latent, loads, space.default.to(torch.float64))
    assert info_default.converged and info_given.converged
    assert torch.allclose(z_default, z_given, atol=1e-9)
    # and the condition matters here: the scene's default condition has another equilibrium
    assert float(torch.linalg.vector_norm(z_scene - z_given)) > 1e-3
