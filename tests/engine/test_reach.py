"""Reach of a subspace (how close it comes to given states) and the bistable bar's two buckled states."""

from __future__ import annotations

import pytest
import torch

from redsim import metrics, scenes
from redsim.metrics.common import m_norm
from redsim.subspace import LinearSubspace


@pytest.fixture(scope="module")
def bar_and_arches() -> tuple:
    scene = scenes.build("bistable_bar", cells_x=12, cells_y=2)
    return scene, metrics.buckled_states(scene)


def test_buckled_states_are_mirror_arches(bar_and_arches: tuple) -> None:
    scene, (up, down) = bar_and_arches
    y_up = scene.full_positions(up.unsqueeze(0))[0].reshape(-1, 2)[:, 1]
    y_down = scene.full_positions(down.unsqueeze(0))[0].reshape(-1, 2)[:, 1]
    y_seed = scene.full_positions(scene.q_seed.unsqueeze(0))[0].reshape(-1, 2)[:, 1]
    assert float((y_up - y_seed).mean()) > 0.02 > -0.02 > float((y_down - y_seed).mean())
    rise, drop = float((y_up - y_seed).max()), float((y_seed - y_down).max())
    assert rise == pytest.approx(drop, rel=0.05)  # up-down symmetric up to the mesh's diagonals


def test_reach_error_is_zero_on_the_subspace_and_large_off_it(bar_and_arches: tuple) -> None:
    scene, (up, down) = bar_and_arches
    through_both = LinearSubspace(((down - up) / 2.0).unsqueeze(1), (up + down) / 2.0)
    result = metrics.reach_error(scene, through_both, [up, down], samples=64)
    assert max(result["errors"]) < 1e-6
    assert [round(z[0]) for z in result["latents"]] == [-1, 1]
    only_up = LinearSubspace(torch.zeros(up.shape[0], 1, dtype=up.dtype), up)
    result = metrics.reach_error(scene, only_up, [up, down], samples=8)
    mass = scene.mass_matrix_scipy()
    expected = m_norm(mass, down - up) / m_norm(mass, down - scene.q_seed)
    assert result["errors"][0] < 1e-9 and result["errors"][1] == pytest.approx(expected, rel=1e-9)


def test_a_straight_bar_has_no_two_buckled_states() -> None:
    with pytest.raises(RuntimeError, match="same equilibrium"):
        metrics.buckled_states(scenes.build("bistable_bar", cells_x=12, cells_y=2, compression=1.0))
