"""What the stepper's energy-gain flag weighs: K_t + E(z_t), K_{t+1} + E(z_{t+1}) and the loads' work, each
recomputed here from the step's latents (a rollout with carry and warm models, as the envs step)."""

from __future__ import annotations

import pytest
import torch

from redsim import pretrained, scenes
from redsim.runtime import LatentStepper, MapEnergy
from redsim.runtime import stepper as stepper_module


def test_the_energy_balance_is_of_z_t_and_z_next_and_the_loads_work_on_the_step(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    scene, f = scenes.build("mini_chain"), pretrained.load("mini_chain")
    dt = 0.02
    stepper = LatentStepper(scene, f, dt, dtype=torch.float64)
    energy = MapEnergy(scene, f, dtype=torch.float64)
    mass = scene.to(dtype=torch.float64).mass_matvec
    seen = []

    original = stepper_module.energy_gain_states

    def record(*balance):
        seen.append(balance[:3])
        return original(*balance)

    monkeypatch.setattr(stepper_module, "energy_gain_states", record)

    def kinetic(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        v = stepper.positions(b) - stepper.positions(a)
        return 0.5 * (v * mass(v)).sum(-1) / dt**2

    generator = torch.Generator().manual_seed(0)
    loads = 3.0 * torch.randn(3, len(scene.handles), scene.dim, generator=generator, dtype=torch.float64)
    z = z_prev = stepper.rest_latent().expand(3, -1).clone()
    model = carry = None
    for _ in range(6):
        z_next, stats = stepper.step(z, z_prev, loads, warm=model, carry=carry)
        assert bool(stats.converged.all())
        now, after, work = seen[-1]
        with torch.no_grad():
            e_now = energy.energy(z, None)[0]
            expected_work = (
                loads.reshape(3, -1)
                * (stepper.handle_positions(stepper.positions(z_next)) - stepper.handle_positions(stepper.positions(z)))
            ).sum(-1)
        assert torch.allclose(now, kinetic(z_prev, z) + e_now, rtol=1e-9, atol=1e-12)
        assert torch.allclose(after, kinetic(z, z_next) + stats.energy, rtol=1e-9, atol=1e-12)
        assert torch.allclose(work, expected_work, rtol=1e-9, atol=1e-12)
        assert bool((work.abs() > 1e-6).all())  # the loads do work here: its sign is checked
        z_prev, z, model, carry = z, z_next, stats.model, stats.carry
