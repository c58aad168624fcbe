"""The stability bench's ledger by hand: the loads' work keeps its sign, a step's energy scale is the larger of its
two ends, and the invariants' worst state sums every effect's count (hand mutation audit, helper-281)."""

from __future__ import annotations

import numpy as np
import torch

from redsim.benches import stability
from redsim.scene import SceneBuilder


def _pushed_particle():
    b = SceneBuilder(dim=3)
    ids = b.add_particles(torch.zeros(1, 3, dtype=torch.float64), torch.full((1,), 2.0))
    b.add_gravity((0.0, -9.81, 0.0))
    b.add_handle("p", b.particle_points(ids))
    return b.finalize("pushed_particle")


def test_a_load_against_the_motion_does_negative_work() -> None:
    scene = _pushed_particle()
    dt = 0.1
    q = torch.zeros(3, scene.free_dof_count, dtype=torch.float64)
    q[:, 0] = torch.tensor([0.0, 0.1, 0.2])  # moving +x by 0.1 m a step
    against = torch.zeros(2, 1, 3, dtype=torch.float64)
    against[:, 0, 0] = -1.0  # 1 N along -x: brakes it
    mechanical, work = stability.energy_account(scene, q, against, dt)
    torch.testing.assert_close(work, torch.tensor([0.0, -0.1, -0.2], dtype=torch.float64))
    # K_t = m |v|^2 / 2 with v = 1 m/s after the first step (q_prev defaults to q[0]: starting at rest)
    torch.testing.assert_close(mechanical, torch.tensor([0.0, 1.0, 1.0], dtype=torch.float64))
    _, along = stability.energy_account(scene, q, -against, dt)
    torch.testing.assert_close(along, -work)
    # H = K + E - W: braked, the ledger rises by the work the brake took out (never as a gain hidden by |W|)
    torch.testing.assert_close(
        stability.ledger(scene, q, against, dt), torch.tensor([0.0, 1.1, 1.2], dtype=torch.float64)
    )


def test_a_steps_energy_scale_is_the_larger_of_its_two_ends() -> None:
    h = torch.tensor([0.0, 5.0])  # a rise of 5 J
    unflagged = torch.zeros(1, dtype=torch.bool)
    # the step starts at a mechanical energy of 100 J: 5 J is within 10% of it
    assert stability.unreported_rises(h, unflagged, 0.1, scale=torch.tensor([100.0, 1.0])) == []
    assert stability.unreported_rises(h, unflagged, 0.1, scale=torch.tensor([1.0, 100.0])) == []
    assert stability.unreported_rises(h, unflagged, 0.1, scale=torch.tensor([1.0, 1.0])) == [0]


def test_the_worst_state_sums_every_effects_count() -> None:
    values = {"a_inverted": np.array([1, 1, 0]), "b_inverted": np.array([1, 0, 0]), "_x_inverted": np.array([9, 9, 9])}
    assert stability.most(values, "inverted") == 2  # state 0: one of each (a private key is not a count)
    assert stability.most(values, "unlinked") is None
