"""The reference objective's force scale F (:class:`PotentialObjective`, the rule every convergence test uses) and
the latent stepper's ``base_force`` are measured by separate code; at f(0) with no motion and no loads both are the
effects' force norms plus |diag M| L / h^2, and agree."""

from __future__ import annotations

import pytest
import torch

from redsim import pretrained, scenes
from redsim.integrators import FullSpace
from redsim.integrators.objective import Inertia, PotentialObjective
from redsim.runtime import LatentStepper


@pytest.mark.parametrize("name", ["mini_chain", "bistable_bar"])
@pytest.mark.parametrize("dt", [0.02, 0.005])
def test_the_reference_and_the_stepper_measure_one_force_scale(name: str, dt: float) -> None:
    scene, f = scenes.build(name), pretrained.load(name)
    stepper = LatentStepper(scene, f, dt, dtype=torch.float64)
    q0 = stepper.positions(torch.zeros(1, stepper.latent_dim, dtype=torch.float64))[0]
    objective = PotentialObjective(
        FullSpace(scene.to(dtype=torch.float64)),
        loads=None,
        cond=None,
        inertia=Inertia(q0, dt),  # qbar = q: no drift term
        force=None,
        reference=q0,
    )
    assert objective.force_scale == pytest.approx(stepper.base_force, rel=1e-9)
