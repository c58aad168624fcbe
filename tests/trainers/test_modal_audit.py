"""The modal pull (redsim.trainers.modal) where the hand mutation audit (helper-283) found no test holding it.

- ``modal_gap`` aligns the map's Jacobian with the modes by the orthogonal R nearest Phi^T M J: for a map
  b + sigma Phi R z with R a proper rotation the gap is 0. test_modal.py's case is a reflection, which is its own
  transpose, so R^T in place of R (``vh^T u^T`` for ``u vh``) passed it.
- ``start_at_rest`` starts the map at the *default* condition's rest state (the targets' first row); the last
  row (a sampled condition's) passed every test, which have one condition.
"""

from __future__ import annotations

import math

import pytest
import torch

from redsim import scenes
from redsim.subspace import LinearSubspace, SubspaceConfig, SubspaceMap
from redsim.trainers.modal import ModalTargets, modal_gap, modal_targets, start_at_rest


def test_gap_is_zero_for_the_modal_map_turned_by_a_proper_rotation() -> None:
    scene = scenes.build("toy_tiny_bar_2d")
    targets = modal_targets(scene, 2, conditional=False, seed=0)
    rest, modes, sigma = targets.rest[0], targets.modes[0], 0.05
    c, s = math.cos(0.7), math.sin(0.7)
    rotation = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)  # det +1, not symmetric
    stretched = float(modal_gap(scene, LinearSubspace(2 * sigma * modes, rest), targets, sigma))
    gap = float(modal_gap(scene, LinearSubspace(sigma * modes @ rotation, rest), targets, sigma))
    assert gap == pytest.approx(0.0, abs=1e-9 * stretched)


def test_the_map_starts_at_the_default_condition_s_rest_state() -> None:
    n, d = 5, 2
    rest = torch.stack([torch.full((n,), 1.0), torch.full((n,), 2.0), torch.full((n,), 3.0)]).to(torch.float64)
    targets = ModalTargets(torch.zeros(3, 1, dtype=torch.float64), rest, torch.zeros(3, n, d), ())
    model = SubspaceMap(SubspaceConfig(latent_dim=d, output_dim=n, condition_dim=1, hidden_width=16)).double()
    weight = model.mlp[-1].weight.detach().clone()
    start_at_rest(model, targets)
    assert torch.equal(model.mlp[-1].bias.detach(), rest[0])
    assert torch.allclose(model.mlp[-1].weight.detach(), 1e-2 * weight)
