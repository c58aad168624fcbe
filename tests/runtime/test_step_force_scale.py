"""A step's force scale F_b (the convergence rule's, :class:`redsim.runtime.LatentStepper`): base_force +
|M (q_t - q_{t-1})| / h^2 + |loads|, recomputed from the step's states and handed to the solver as |J_0|_2 F_b."""

from __future__ import annotations

import pytest
import torch

from redsim import pretrained, scenes
from redsim.runtime import LatentStepper
from redsim.runtime import stepper as stepper_module


@pytest.mark.parametrize("dt", [0.02, 0.005])
def test_the_solvers_scale_is_the_documented_force_of_the_step(dt: float, monkeypatch: pytest.MonkeyPatch) -> None:
    scene, f = scenes.build("mini_chain"), pretrained.load("mini_chain")
    stepper = LatentStepper(scene, f, dt, dtype=torch.float64)
    scales = []
    original = stepper_module.minimize

    def record(objective, z0, scale, *args, **kwargs):
        scales.append(scale.clone())
        return original(objective, z0, scale, *args, **kwargs)

    monkeypatch.setattr(stepper_module, "minimize", record)
    generator = torch.Generator().manual_seed(0)
    z = stepper.rest_latent().expand(3, -1).clone()
    z_prev = z + 0.2 * torch.randn(z.shape, generator=generator, dtype=torch.float64)  # moving states
    loads = 2.0 * torch.randn(3, len(scene.handles), scene.dim, generator=generator, dtype=torch.float64)
    stepper.step(z, z_prev, loads)
    v = stepper.positions(z) - stepper.positions(z_prev)
    inertia = torch.linalg.vector_norm(scene.to(dtype=torch.float64).mass_matvec(v), dim=-1) / dt**2
    force = stepper.base_force + inertia + torch.linalg.vector_norm(loads.reshape(3, -1), dim=-1)
    assert bool((inertia > 1e-4 * stepper.base_force).all())  # far above the rtol below: the term is felt
    assert torch.allclose(scales[0], stepper.jacobian_norm * force, rtol=1e-9)
