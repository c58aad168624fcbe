"""The length L of the convergence and round-off scales (:func:`redsim.integrators.length_scale`): the larger of the
seed's extent and its distance from the origin (a small part far out rounds at its coordinates' size)."""

from __future__ import annotations

import pytest
import torch

from redsim import SceneBuilder
from redsim.effects.elastic import StVKMembrane
from redsim.integrators import length_scale


def _triangle(offset: float):
    rest = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]], dtype=torch.float64) + offset
    b = SceneBuilder(dim=3)
    ids = b.add_particles(rest, torch.full((3,), 0.01))
    b.add_effect(StVKMembrane("membrane", b.particle_dofs(ids).reshape(1, 3, 3), rest[None], 1e4, 0.3))
    return b.finalize("triangle")


def test_a_small_part_far_from_the_origin_has_the_length_of_its_coordinates() -> None:
    assert length_scale(_triangle(0.0)) == pytest.approx(0.1)  # at the origin: its extent
    assert length_scale(_triangle(50.0)) == pytest.approx(50.1)  # far out: its largest coordinate
