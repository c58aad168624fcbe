"""The info invariants (:mod:`redsim.envs.invariants`) on states whose values are known by hand: a body's rotation
scaled, one joint pulled apart, elements flattened or mirrored, the cloth pushed into its ball (a hand mutation audit
found a wrong sign, axis, reduction or comparison in each check passing every other test)."""

from __future__ import annotations

import math

import pytest
import torch

from redsim import scenes
from redsim.envs.invariants import Invariants


def seed_state(name: str) -> tuple[object, torch.Tensor]:
    scene = scenes.build(name)
    return scene, scene.full_positions(scene.q_seed.unsqueeze(0))


def test_orthogonality_error_is_the_frobenius_defect_of_a_scaled_rotation() -> None:
    """Body 1's rows (R_i0, R_i1, R_i2, t_i) with R scaled by 1 + e: R^T R - I = ((1 + e)^2 - 1) I, whose Frobenius
    norm is sqrt(3) ((1 + e)^2 - 1); a translation moves no rotation."""
    scene, x = seed_state("toy_three_link_chain")
    invariants = Invariants(scene)
    e = 0.01
    scaled, moved = x.clone(), x.clone()
    rotation = torch.tensor([0, 1, 2, 4, 5, 6, 8, 9, 10]) + 12
    scaled[:, rotation] *= 1 + e
    moved[:, [15, 19, 23]] += 0.3
    turned = x.clone().reshape(1, 3, 3, 4)  # every body turned a quarter about z: still a rotation
    turned[..., :3] = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=x.dtype)
    error = invariants(torch.cat([x, scaled, moved, turned.reshape(1, -1)]))["rigid_orthogonality_error"]
    assert error.tolist() == pytest.approx([0.0, math.sqrt(3) * ((1 + e) ** 2 - 1), 0.0, 0.0], abs=1e-12)


def test_max_gap_is_the_largest_joints_distance_and_a_translation_keeps_the_axes() -> None:
    """The last body (dofs 24-35, translation 27, 31, 35) moved by d: only its joint with body 1 opens, by d."""
    scene, x = seed_state("toy_three_link_chain")
    moved = x.clone()
    moved[:, [27, 31, 35]] += torch.tensor([0.03, 0.0, 0.04], dtype=x.dtype)  # d = 0.05
    values = Invariants(scene)(torch.cat([x, moved]))
    assert values["joints_max_gap"].tolist() == pytest.approx([0.0, 0.05], abs=1e-12)
    assert values["joint_axes_max_gap"].tolist() == pytest.approx([0.0, 0.0], abs=1e-12)


def test_a_flattened_element_counts_as_inverted_and_a_mirrored_one_has_det_f_minus_one() -> None:
    scene, x = seed_state("toy_two_tets")
    flat, mirrored = x.clone().reshape(1, -1, 3), x.clone().reshape(1, -1, 3)
    flat[..., 2] = 0.0
    mirrored[..., 2] *= -1.0
    values = Invariants(scene)(torch.cat([x, flat.reshape(1, -1), mirrored.reshape(1, -1)]))
    assert values["elastic_min_det_f"].tolist() == pytest.approx([1.0, 0.0, -1.0], abs=1e-12)
    assert values["elastic_inverted"].tolist() == [0.0, 2.0, 2.0]  # det F <= 0: no volume is no element either


def test_penetration_is_the_negated_clearance_of_a_point_inside_and_zero_outside() -> None:
    """The cloth over its ball clears it at the seed (penetration 0); with the ball moved to the cloth's centroid, the
    cloth's points are inside it: penetration is the depth, the clearance its negative."""
    scene, x = seed_state("cloth_ball")
    rigid = next(effect for effect in scene.effects if effect.name == "rigid")
    ball = rigid.element_dofs[0]
    cloth = torch.ones(x.shape[1], dtype=torch.bool)
    cloth[ball] = False
    sunk = x.clone()
    sunk[0, ball[[3, 7, 11]]] = x[0, cloth].reshape(-1, 3).mean(0)
    values = Invariants(scene)(torch.cat([x, sunk]))
    clearance, penetration = values["contact_clearance"], values["contact_penetration"]
    assert float(clearance[0]) > 0 and float(penetration[0]) == 0.0
    assert float(clearance[1]) < 0 and float(penetration[1]) == pytest.approx(-float(clearance[1]))
