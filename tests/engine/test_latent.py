"""Latent-space solves: the same objective over z through a map q = f(z) (:class:`LatentSpace`).

Float64 affine maps that cover all of q are reparametrizations of the full space, so their
steps and equilibria must match :class:`FullSpace` to solver tolerance (1e-10 relative to the
motion, far above float64 round-off). Float32 maps are checked against their own float64 copy
at float32 resolution.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import Tensor

from redsim import Scene, SceneBuilder, scenes
from redsim.effects import NeoHookean
from redsim.hessian import energy_hessian
from redsim.integrators import (
    FullSpace,
    ImplicitEuler,
    Inertia,
    LatentSpace,
    PotentialObjective,
    latent_equilibrium,
    static_equilibrium,
)
from redsim.integrators.spaces import HESSIAN_FLOOR
from redsim.subspace import LinearSubspace, SubspaceConfig, SubspaceMap

LOAD = {"top": [1.0, 2.0, -0.5]}  # [N] on toy_two_tets' free top vertex


def Affine(b: Tensor, A: Tensor) -> LinearSubspace:
    """f(z) = b + A z (A [n, d], b [n]): the linear baseline serves as the test map."""
    return LinearSubspace(A, b)


def _tets() -> Scene:
    return scenes.build("toy_two_tets")


def _random_affine(scene: Scene, seed: int) -> Affine:
    """An invertible, non-orthogonal A [n, n] (condition number ~10) around the seed."""
    n = scene.free_dof_count
    g = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(n, n, generator=g, dtype=torch.float64))
    scales = torch.logspace(-1, 0, n, dtype=torch.float64)
    return Affine(scene.q_seed, Q * scales)


@pytest.mark.parametrize("minimizer", ["newton", "lbfgs"])
def test_identity_map_reproduces_full_space_steps_and_equilibria(minimizer: str) -> None:
    scene = _tets()
    n = scene.free_dof_count
    identity = Affine(scene.q_seed, torch.eye(n, dtype=torch.float64))
    full = ImplicitEuler(FullSpace(scene), 0.01, minimizer=minimizer, max_iter=200, strict=True)
    latent = ImplicitEuler(LatentSpace(scene, identity), 0.01, minimizer=minimizer, max_iter=200, strict=True)
    q_traj, _ = full.rollout(full.initial_state(), 8, LOAD)
    z_traj, infos = latent.rollout(latent.initial_state(), 8, LOAD)
    motion = float((q_traj - scene.q_seed).abs().max())
    assert motion > 1e-3
    torch.testing.assert_close(identity(z_traj), q_traj, rtol=0.0, atol=1e-8 * motion)
    assert all(i.converged for i in infos)

    q_star, _ = static_equilibrium(scene, LOAD, minimizer=minimizer, tol=1e-10)
    z_star, info = latent_equilibrium(LatentSpace(scene, identity), LOAD, minimizer=minimizer, tol=1e-10)
    assert info.converged, info.message
    torch.testing.assert_close(
        identity(z_star), q_star, rtol=0.0, atol=1e-8 * float((q_star - scene.q_seed).abs().max())
    )


def test_invertible_affine_reparametrization_matches_full_space() -> None:
    """The |J|-scaled convergence rule keeps tol meaningful: an anisotropic A converges to the same point."""
    scene = _tets()
    f = _random_affine(scene, 1)
    space = LatentSpace(scene, f)
    q_star, _ = static_equilibrium(scene, LOAD, tol=1e-10)
    z_star, info = latent_equilibrium(space, LOAD, tol=1e-10)
    assert info.converged, info.message
    scale = float((q_star - scene.q_seed).abs().max())
    torch.testing.assert_close(f(z_star), q_star, rtol=0.0, atol=1e-7 * scale)
    state = torch.linalg.solve(f.basis, torch.full((scene.free_dof_count,), 1e-3, dtype=torch.float64))
    full = ImplicitEuler(FullSpace(scene), 0.02, tol=1e-10)
    latent = ImplicitEuler(space, 0.02, tol=1e-10)
    q_next, _ = full.step(full.initial_state(f(state)), LOAD)
    z_next, info = latent.step(latent.initial_state(state), LOAD)
    assert info.converged
    torch.testing.assert_close(f(z_next.q), q_next.q, rtol=0.0, atol=1e-7 * float((q_next.q - f(state)).abs().max()))


def test_pullback_is_dense_jtaj_of_the_autograd_jacobian() -> None:
    scene = scenes.build("toy_tiny_bar_2d")
    n = scene.free_dof_count
    torch.manual_seed(0)
    model = SubspaceMap(SubspaceConfig(latent_dim=3, output_dim=n, hidden_width=16, hidden_layers=2, periodic=(1,)))
    model = model.double()
    space = LatentSpace(scene, model)
    z = torch.tensor([0.3, -1.2, 0.7], dtype=torch.float64)
    J = torch.autograd.functional.jacobian(lambda v: model(v), z).numpy()
    torch.testing.assert_close(torch.from_numpy(space.jacobian(z)), torch.from_numpy(J), rtol=1e-12, atol=1e-14)
    A = energy_hessian(scene, model(z).detach(), project=True) + scene.mass_matrix_scipy()
    got = space.pullback(z, A)
    want = J.T @ A.toarray() @ J
    assert isinstance(got, np.ndarray) and got.shape == (3, 3)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())
    assert space.gradient_scale(z) == pytest.approx(np.linalg.norm(J, 2), rel=1e-12)


def test_newton_hessian_is_the_exact_latent_hessian_with_absolute_eigenvalues() -> None:
    """Map curvature included; negative curvature is flipped (here at a z where the exact Hessian is indefinite)."""
    scene = scenes.build("toy_tiny_bar_2d")
    torch.manual_seed(0)
    model = SubspaceMap(
        SubspaceConfig(latent_dim=3, output_dim=scene.free_dof_count, hidden_width=16, hidden_layers=2, periodic=(1,))
    ).double()
    space = LatentSpace(scene, model)
    loads = scene.pack_loads({"tip": [0.0, -2.0]}, 1, scene.q_seed)
    mass = torch.from_numpy(scene.mass_matrix_scipy().toarray())
    dt = 0.02
    for z in ([0.3, -1.2, 0.7], [0.0, 0.0, 0.0]):
        z = torch.tensor(z, dtype=torch.float64)
        target = model(z).detach() + 0.01
        for inertia in (None, Inertia(target, dt)):

            def phi(v: Tensor, inertia: Inertia | None = inertia) -> Tensor:
                q = model(v)
                value = scene.energy(q[None], loads)[0]
                if inertia is not None:
                    value = value + 0.5 / dt**2 * (q - inertia.target) @ mass @ (q - inertia.target)
                return value

            objective = PotentialObjective(space, loads=loads, cond=None, inertia=inertia, force=None, reference=z)
            w, V = np.linalg.eigh(torch.autograd.functional.hessian(phi, z).numpy())
            if inertia is None and float(z.abs().max()) > 0.0:
                assert w.min() < 0.0  # the case the absolute value is for
            want = (V * np.maximum(np.abs(w), HESSIAN_FLOOR * np.abs(w).max())) @ V.T
            np.testing.assert_allclose(objective.hessian(z), want, rtol=1e-10, atol=1e-10 * np.abs(w).max())


def test_latent_newton_and_lbfgs_agree_on_a_nonlinear_map() -> None:
    """Newton's Hessian only shapes the path: both minimizers reach the same steps to solver tolerance."""
    scene = scenes.build("toy_tiny_bar_2d")
    torch.manual_seed(1)
    model = SubspaceMap(SubspaceConfig(latent_dim=3, output_dim=scene.free_dof_count, hidden_width=16)).double()
    space = LatentSpace(scene, model)
    loads = {"tip": [0.5, -2.0]}
    trajectories = {}
    for name, max_iter in (("newton", 50), ("lbfgs", 1000)):
        sim = ImplicitEuler(space, 0.02, minimizer=name, tol=1e-10, max_iter=max_iter, strict=True)
        z_traj, _ = sim.rollout(sim.initial_state(), 6, loads)
        trajectories[name] = model(z_traj).detach()
    motion = float((trajectories["newton"] - trajectories["newton"][0]).abs().max())
    assert motion > 1e-3
    torch.testing.assert_close(trajectories["lbfgs"], trajectories["newton"], rtol=0.0, atol=1e-6 * motion)


def test_float32_map_runs_in_float32_and_solves_at_its_resolution() -> None:
    scene = scenes.build("toy_tiny_bar_2d")
    torch.manual_seed(0)
    model32 = SubspaceMap(SubspaceConfig(latent_dim=2, output_dim=scene.free_dof_count, hidden_width=16))
    model64 = SubspaceMap(model32.config).double()
    model64.load_state_dict(model32.state_dict())
    space32, space64 = LatentSpace(scene, model32), LatentSpace(scene, model64)
    assert space32.map_dtype == torch.float32 and space32.roundoff > 0.0 and space64.roundoff == 0.0
    z = torch.zeros(1, 2, dtype=torch.float64, requires_grad=True)
    q = space32.configuration(z)
    assert q.dtype == torch.float64
    (grad,) = torch.autograd.grad(scene.energy(q).sum(), z)
    assert bool(torch.isfinite(grad).all()) and float(grad.abs().max()) > 0.0
    loads = {"tip": [0.0, -2.0]}
    z32, info32 = latent_equilibrium(space32, loads)
    z64, info64 = latent_equilibrium(space64, loads)
    assert info32.converged and info64.converged, (info32.message, info64.message)
    torch.testing.assert_close(z32, z64, rtol=0.0, atol=1e-3 * float(z64.abs().max()))
    sim = ImplicitEuler(space32, 0.02, strict=True)
    trajectory, infos = sim.rollout(sim.initial_state(), 4, loads)
    assert bool(torch.isfinite(trajectory).all()) and all(i.converged for i in infos)


def test_conditional_map_gets_its_condition_and_bad_maps_raise() -> None:
    b = SceneBuilder(dim=3)
    tet = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    ids = b.add_particles(tet, torch.ones(4))
    b.pin_particles(ids[:3])
    stiff = b.add_condition("stiffness", 0.5, 2.0, default=1.5)
    b.add_effect(
        NeoHookean(
            "elastic",
            b.particle_dofs(torch.tensor([[0, 1, 2, 3]])),
            tet[None],
            1e3,
            0.3,
            condition_scale=(stiff, torch.tensor([True])),
        )
    )
    b.add_gravity((0.0, -9.81, 0.0))
    scene = b.finalize("conditional_tet")
    model = SubspaceMap(SubspaceConfig(latent_dim=1, output_dim=3, condition_dim=1, hidden_width=8)).double()
    space = LatentSpace(scene, model)
    torch.testing.assert_close(space.condition, torch.tensor([1.5], dtype=torch.float64))
    z = torch.tensor([[0.4]], dtype=torch.float64)
    torch.testing.assert_close(space.configuration(z), model(z, torch.tensor([1.5], dtype=torch.float64)))
    other = LatentSpace(scene, model, cond=torch.tensor([0.7]))
    torch.testing.assert_close(other.configuration(z), model(z, torch.tensor([0.7], dtype=torch.float64)))
    _, info = latent_equilibrium(other)
    assert info.converged

    tets = _tets()
    with pytest.raises(ValueError, match="latent_dim"):
        LatentSpace(tets, lambda z: z)
    with pytest.raises(ValueError, match="needs"):
        LatentSpace(tets, Affine(torch.zeros(4, dtype=torch.float64), torch.zeros(4, 2, dtype=torch.float64)))
    identity = Affine(tets.q_seed, torch.eye(6, dtype=torch.float64))
    with pytest.raises(ValueError, match="no condition"):
        LatentSpace(tets, identity, cond=torch.tensor([1.0]))
    with pytest.raises(ValueError, match="z0"):
        latent_equilibrium(LatentSpace(tets, identity), z0=torch.zeros(3))


def test_lbfgs_reports_a_singular_latent_metric_instead_of_raising() -> None:
    """A map with a dead latent direction has a singular metric J^T M J: a failed solve, not an exception."""
    scene = scenes.build("toy_two_tets")
    basis = torch.zeros(scene.free_dof_count, 2, dtype=torch.float64)
    basis[0, 0] = 1.0  # latent 1 moves nothing
    z, info = latent_equilibrium(LatentSpace(scene, Affine(scene.q_seed, basis)), LOAD, minimizer="lbfgs")
    assert not info.converged and "singular" in info.message and torch.equal(z, torch.zeros(2, dtype=torch.float64))
