"""The modal pull: its targets (rest state and lowest modes), its gap by hand, and a short fit that it steers."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from redsim import metrics, scenes
from redsim.baselines import modal_analysis
from redsim.subspace import LinearSubspace
from redsim.trainers import FitConfig, fit_subspace
from redsim.trainers import fit as fit_module
from redsim.trainers.fit import fit_command, subspace_loss
from redsim.trainers.modal import MODAL_CONDITIONS, modal_gap, modal_targets


def _bar():
    return scenes.build("toy_tiny_bar_2d")


def _principal_angles_deg(a: np.ndarray, b: np.ndarray, mass) -> np.ndarray:
    """Principal angles [deg] between the column spans of a and b [n, d] in the M inner product."""
    la = np.linalg.cholesky(a.T @ (mass @ a))
    lb = np.linalg.cholesky(b.T @ (mass @ b))
    oa = np.linalg.solve(la, a.T).T
    ob = np.linalg.solve(lb, b.T).T
    cosines = np.linalg.svd(oa.T @ (mass @ ob), compute_uv=False).clip(-1.0, 1.0)
    return np.degrees(np.arccos(cosines))


def test_targets_are_the_rest_equilibrium_and_its_lowest_modes() -> None:
    scene = _bar()
    targets = modal_targets(scene, 2, conditional=False, seed=0)
    rest, _ = metrics.rest_state(scene)
    assert targets.cond is None and targets.rest.shape == (1, scene.free_dof_count)
    torch.testing.assert_close(targets.rest[0], rest)
    modes = modal_analysis(scene, 2, rest=rest)
    mass = scene.mass_matrix_scipy()
    assert _principal_angles_deg(targets.modes[0].numpy(), modes.basis.numpy(), mass).max() < 1e-4
    np.testing.assert_allclose(targets.modes[0].numpy().T @ (mass @ targets.modes[0].numpy()), np.eye(2), atol=1e-10)


def test_conditional_targets_cover_the_default_and_sampled_conditions() -> None:
    scene = scenes.build("conditional_bar", cells_x=6, cells_y=2)
    targets = modal_targets(scene, 2, conditional=True, seed=0)
    assert targets.cond is not None and targets.cond.shape == (MODAL_CONDITIONS, 2)
    torch.testing.assert_close(targets.cond[0], scene.condition_space.default.to(torch.float64))
    assert targets.rest.shape == (MODAL_CONDITIONS, scene.free_dof_count)
    assert targets.modes.shape == (MODAL_CONDITIONS, scene.free_dof_count, 2)
    space = scene.condition_space
    assert bool(((targets.cond >= space.low) & (targets.cond <= space.high)).all())
    result = fit_subspace(
        scene, dim=2, sigma=0.05, lam=10.0, steps=3, conditional=True, modal=10.0, modal_fraction=2.0, progress=False
    )
    assert all(math.isfinite(h["modal"]) and h["modal"] > 0 for h in result.history)
    assert "--cond" in result.subspace.metadata["command"] and "--modal 10.0" in result.subspace.metadata["command"]


def test_gap_by_hand_is_zero_for_the_modal_map_in_any_rotation() -> None:
    """b + sigma Phi R z has gap 0 for every orthogonal R (signs, order); b + 2 sigma Phi z and b + x + sigma Phi z
    have gaps |sigma Phi|^2_A and |x|^2_A, A = H + lambda_d M."""
    scene = _bar()
    targets = modal_targets(scene, 2, conditional=False, seed=0)
    rest, modes, sigma = targets.rest[0], targets.modes[0], 0.05
    metric = targets.metric[0].to_dense()
    angle = 0.7
    flip = torch.tensor(
        [[math.cos(angle), math.sin(angle)], [math.sin(angle), -math.cos(angle)]], dtype=torch.float64
    )  # a reflection: det -1
    eigenvalues = modal_analysis(scene, 2).metadata["eigenvalues"]
    stretched = float(torch.trace(sigma**2 * modes.T @ metric @ modes))
    assert stretched == pytest.approx(sigma**2 * (sum(eigenvalues) + 2 * eigenvalues[-1]), rel=1e-3)  # H ~ projected
    for basis, want in ((sigma * modes @ flip, 0.0), (2 * sigma * modes, stretched)):
        gap = float(modal_gap(scene, LinearSubspace(basis, rest), targets, sigma))
        assert gap == pytest.approx(want, rel=1e-9, abs=1e-9 * stretched)
    offset = torch.full_like(rest, 0.01)
    shifted = float(modal_gap(scene, LinearSubspace(sigma * modes, rest + offset), targets, sigma))
    assert shifted == pytest.approx(float(offset @ metric @ offset), rel=1e-9)


def test_modal_option_is_validated_scheduled_and_recorded() -> None:
    for bad in ({"modal": -1.0}, {"modal": math.nan}, {"modal_fraction": 0.0}, {"modal_fraction": 2.5}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            FitConfig(**bad)
    config = FitConfig(latent_dim=2, sigma=0.05, steps=100, modal=1e3, modal_fraction=0.8)
    assert [fit_module.modal_at(k, config) for k in (0, 40, 60, 80)] == pytest.approx([1e3, 1e3, 500.0, 0.0])
    held = dataclasses.replace(config, modal_fraction=2.0)
    assert fit_module.modal_at(99, held) == 1e3
    assert "--modal 1000.0 --modal-fraction 0.8" in fit_command(_bar(), config, 0, None)
    assert "--modal" not in fit_command(_bar(), FitConfig(), 0, None)
    scene = _bar()
    targets = modal_targets(scene, 2, conditional=False, seed=0)
    model = LinearSubspace(0.05 * targets.modes[0] + 0.001, targets.rest[0])
    z = torch.randn(4, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    total, terms = subspace_loss(scene, model, z, None, 1.0, config, modal=targets)
    plain, _ = subspace_loss(scene, model, z, None, 1.0, dataclasses.replace(config, modal=0.0))
    want = 0.5 * 1e3 * float(modal_gap(scene, model, targets, 0.05))
    assert terms["modal"] == pytest.approx(want, rel=1e-9) and want > 0
    assert float(total.detach()) == pytest.approx(float(plain.detach()) + want, rel=1e-9)
    with pytest.raises(ValueError, match="needs the modal targets"):
        subspace_loss(scene, model, z, None, 1.0, config)


def test_modal_fit_holds_the_rest_state_and_the_lowest_modes_at_z0() -> None:
    """A 300-step fit of the tiny bar: with the pull held (2.0), the map's Jacobian at z = 0 spans the two
    lowest modes (measured 0.005 deg) and f(0) sits at the rest state (8e-6 of the scene size); without it, it
    does neither (33 deg, 0.075)."""
    scene = _bar()
    targets = modal_targets(scene, 2, conditional=False, seed=0)
    mass = scene.mass_matrix_scipy()
    size = metrics.common.scene_size(scene, mass)
    found = {}
    for modal in (0.0, 1e3):
        sub = fit_subspace(
            scene, dim=2, sigma=0.05, lam=10.0, steps=300, modal=modal, modal_fraction=2.0, progress=False
        ).subspace.double()
        origin = torch.zeros(2, dtype=torch.float64)
        jacobian = torch.autograd.functional.jacobian(lambda z, f=sub: f(z[None])[0], origin)
        angles = _principal_angles_deg(jacobian.detach().numpy(), targets.modes[0].numpy(), mass)
        offset = metrics.common.m_norm(mass, sub(torch.zeros(1, 2, dtype=torch.float64))[0] - targets.rest[0])
        found[modal] = (float(angles.max()), offset / size)
    assert found[1e3][0] < 1.0 and found[1e3][1] < 1e-3, found
    assert found[0.0][0] > 20.0 and found[0.0][1] > 0.03, found
