"""The fit's driver penalty sums over every driver a scene declares, each turned by its own latent.

Every catalog scene with drivers declares one (Klann-v0's crank, toy_crank), so keeping only the last driver's gap in
:func:`redsim.trainers.fit.drive_energy` passed the driver tests of tests/trainers/test_fit.py (hand mutation audit,
helper-276). Here two particles, each pulled round its own centre on a 0.2 m circle.
"""

from __future__ import annotations

import math

import pytest
import torch

from redsim import SceneBuilder
from redsim.trainers import fit as fit_module


def test_the_driver_penalty_sums_every_driver_by_hand() -> None:
    b = SceneBuilder(dim=3)
    seed = torch.tensor([[0.2, 0.0, 0.0], [1.2, 0.0, 0.0]], dtype=torch.float64)
    ids = b.add_particles(seed, torch.ones(2, dtype=torch.float64))
    b.add_handle("a", b.particle_points(ids[:1]))
    b.add_handle("b", b.particle_points(ids[1:]))
    plane = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    b.add_driver("first", "a", (0.0, 0.0, 0.0), plane, latent=0)
    b.add_driver("second", "b", (1.0, 0.0, 0.0), plane, latent=1)
    scene = b.finalize("two_cranks")
    q = scene.q_seed.unsqueeze(0)
    # z = (pi/2, pi): the first target is (0, 0.2, 0), 0.2 sqrt(2) m from its particle; the second (0.8, 0, 0), 0.4 m
    z = torch.tensor([[math.pi / 2, math.pi]], dtype=torch.float64)
    assert float(fit_module.drive_energy(scene, q, z, 100.0)) == pytest.approx(0.5 * 100.0 * (0.08 + 0.16), rel=1e-12)
    # each driver reads its own latent: turning only the second moves only the second target
    z = torch.tensor([[0.0, math.pi]], dtype=torch.float64)
    assert float(fit_module.drive_energy(scene, q, z, 100.0)) == pytest.approx(0.5 * 100.0 * 0.16, rel=1e-12)
