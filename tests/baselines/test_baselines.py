"""Classical and supervised baselines: modal analysis, modal derivatives, PCA, autoencoder, checkpoints.

Everything except the autoencoder and the neural fit runs in float64, so the algebraic identities
(M-orthonormality, the generalized eigen-equation, the modal-derivative system) hold to round-off
relative to the matrices' scale; the finite-difference check of third derivatives holds to its
O(eps^2) truncation. The Proposition 1 test compares a float32 neural fit with modal analysis to
within degrees, the accuracy a short stochastic fit reaches.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import scipy.linalg
import torch

import redsim.baselines as baselines
from redsim import Scene, SceneBuilder, scenes
from redsim.baselines import (
    hessian_directional_derivative,
    modal_analysis,
    modal_derivatives,
    pca_subspace,
    simulated_states,
    train_autoencoder,
)
from redsim.effects import NeoHookean
from redsim.hessian import energy_hessian
from redsim.integrators import LatentSpace, latent_equilibrium, static_equilibrium
from redsim.subspace import (
    AutoencoderSubspace,
    CheckpointError,
    LinearSubspace,
    QuadraticSubspace,
    SubspaceConfig,
    SubspaceMap,
    load_subspace,
)
from redsim.trainers import fit_subspace

TET = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)


@pytest.fixture(scope="module")
def bar() -> Scene:
    return scenes.build("toy_tiny_bar_2d")


@pytest.fixture(scope="module")
def bar_states(bar: Scene) -> torch.Tensor:
    return simulated_states(bar, steps=20, dt=0.02, episodes=2, seed=0, load_scale=5.0)


def _m_orthonormal(A: np.ndarray, M: object) -> np.ndarray:
    """Columns of A made M-orthonormal (same span)."""
    L = np.linalg.cholesky(A.T @ (M @ A))
    return scipy.linalg.solve_triangular(L, A.T, lower=True).T


def _principal_angles(A: np.ndarray, B: np.ndarray, M: object) -> np.ndarray:
    """Principal angles [deg] between span(A) and span(B) in the M inner product, ascending."""
    cosines = np.linalg.svd(_m_orthonormal(A, M).T @ (M @ _m_orthonormal(B, M)), compute_uv=False)
    return np.sort(np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0))))


def _free_tet() -> Scene:
    """One unpinned elastic tet without gravity: six exact null modes (rigid motions)."""
    b = SceneBuilder(3)
    ids = b.add_particles(TET, torch.tensor([1.0, 1.0, 1.0, 2.0]))
    b.add_effect(NeoHookean("elastic", b.particle_dofs(torch.tensor([[0, 1, 2, 3]])), TET[None], 1e3, 0.3))
    b.add_handle("tip", b.particle_points(ids[3:]))
    return b.finalize("free_tet", params={})


# -- modal analysis ---------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["toy_tiny_bar_2d", "toy_three_link_chain", "toy_small_cloth"])
def test_modes_are_m_orthonormal_lowest_generalized_eigenvectors(name: str) -> None:
    scene = scenes.build(name)
    sigma = 0.3
    sub = modal_analysis(scene, 4, sigma=sigma)
    A, b = sub.basis.numpy(), sub.offset
    M = scene.mass_matrix_scipy()
    H = energy_hessian(scene, b, project=False)
    eigs = np.array(sub.metadata["eigenvalues"])
    assert sub.latent_dim == 4 and sub.kind == "linear" and sub.metadata["eigensolver"] == "dense"
    np.testing.assert_allclose(A.T @ (M @ A), sigma**2 * np.eye(4), atol=1e-12)
    # H A = M A diag(eigs): relative to |H A|, at the round-off of a matrix whose spectrum spans up to 1e10.
    residual = H @ A - (M @ A) * eigs
    assert np.abs(residual).max() <= 1e-8 * np.abs(H @ A).max()
    all_eigs = scipy.linalg.eigh(H.toarray(), M.toarray(), eigvals_only=True)
    # Eigenvalues to float64 eigensolver accuracy, a round-off of about eps times the largest one.
    np.testing.assert_allclose(eigs, all_eigs[:4], rtol=1e-9, atol=1e-13 * all_eigs.max())
    # b is the static equilibrium: f(0) = b and the force there vanishes relative to gravity's.
    q = b.clone().requires_grad_(True)
    terms = scene.energy_terms(q)
    (force,) = torch.autograd.grad(sum(terms.values()), q, retain_graph=True)
    (weight,) = torch.autograd.grad(terms["gravity"], q)
    assert float(force.norm()) <= 1e-6 * float(weight.norm())
    assert torch.equal(sub(torch.zeros(4, dtype=torch.float64)), b)


def test_shift_invert_matches_the_dense_eigensolver(bar: Scene, monkeypatch: pytest.MonkeyPatch) -> None:
    dense = modal_analysis(bar, 3)
    monkeypatch.setattr(baselines, "DENSE_EIGEN_LIMIT", 0)
    sparse = modal_analysis(bar, 3)
    assert sparse.metadata["eigensolver"] == "shift-invert"
    np.testing.assert_allclose(sparse.metadata["eigenvalues"], dense.metadata["eigenvalues"], rtol=1e-9)
    M = bar.mass_matrix_scipy()
    np.testing.assert_allclose(sparse.basis.numpy().T @ (M @ sparse.basis.numpy()), np.eye(3), atol=1e-12)
    assert _principal_angles(sparse.basis.numpy(), dense.basis.numpy(), M).max() < 1e-4
    # the same basis on every run, signs included: ARPACK's default start vector is random, and the baselines'
    # sampled energies (fixed draws through the basis) moved between runs of `bench subspace` (sheet: 2.4e4-3.4e4 J)
    again = modal_analysis(bar, 3)
    np.testing.assert_array_equal(again.basis.numpy(), sparse.basis.numpy())
    np.testing.assert_allclose(sparse.basis.numpy(), dense.basis.numpy(), atol=1e-4 * float(dense.basis.abs().max()))


def test_stiff_pinned_scene_at_tiny_sigma_stays_near_the_equilibrium_energy() -> None:
    """E(f(z)) - E(b) = 1/2 sigma^2 sum_i lambda_i z_i^2 up to the cubic term, O(sigma) relative."""
    scene = scenes.build("toy_tiny_bar_2d", young=1e7)
    sigma = 1e-5
    sub = modal_analysis(scene, 3, sigma=sigma)
    z = torch.randn(16, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    rise = scene.energy(sub(z)) - scene.energy(sub.offset)
    predicted = 0.5 * sigma**2 * (z**2 * torch.tensor(sub.metadata["eigenvalues"], dtype=torch.float64)).sum(-1)
    assert float(rise.abs().max()) < 1e-4 * abs(float(scene.energy(sub.offset)))  # E(b) is about 1 J (gravity)
    torch.testing.assert_close(rise, predicted, rtol=1e-3, atol=0.0)


def test_modal_subspace_plugs_into_latent_solves(bar: Scene) -> None:
    """The latent equilibrium of a modal subspace under no load is z = 0; under a load it is above the full one."""
    sub = modal_analysis(bar, 3, sigma=0.01)
    space = LatentSpace(bar, sub)
    z, info = latent_equilibrium(space, z0=torch.full((3,), 0.5, dtype=torch.float64))
    assert info.converged and float(z.abs().max()) < 1e-6
    load = {"tip": [0.0, -2.0]}
    z, info = latent_equilibrium(space, load)
    q_full, _ = static_equilibrium(bar, load)
    assert info.converged
    assert float(bar.energy(space.configuration(z[None])[0], load)) >= float(bar.energy(q_full, load)) - 1e-9


@pytest.mark.parametrize("bad", [0, 17, 2.5])
def test_bad_dim_raises(bar: Scene, bad: float) -> None:
    with pytest.raises(ValueError, match="dim"):
        modal_analysis(bar, bad)  # type: ignore[arg-type]


def test_bad_inputs_to_the_maps_raise(bar: Scene) -> None:
    sub = modal_analysis(bar, 2)
    with pytest.raises(ValueError, match="2 entries"):
        sub(torch.zeros(3, dtype=torch.float64))
    with pytest.raises(ValueError, match="no condition"):
        sub(torch.zeros(2, dtype=torch.float64), torch.zeros(1))
    with pytest.raises(ValueError, match="sigma"):
        modal_analysis(bar, 2, sigma=0.0)
    with pytest.raises(ValueError, match="rest"):
        modal_analysis(bar, 2, rest=torch.zeros(3))


# -- modal derivatives ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["toy_tiny_bar_2d", "toy_three_link_chain", "toy_small_cloth"])
def test_hessian_directional_derivative_is_symmetric_and_matches_finite_differences(name: str) -> None:
    scene = scenes.build(name)
    q, _ = static_equilibrium(scene)
    g = torch.Generator().manual_seed(1)
    u, v = torch.randn(2, 3, scene.free_dof_count, generator=g, dtype=torch.float64)
    uv = hessian_directional_derivative(scene, q, u, v)
    vu = hessian_directional_derivative(scene, q, v, u)
    torch.testing.assert_close(uv, vu, rtol=1e-10, atol=1e-10 * float(uv.abs().max()))
    eps = 1e-5 * float(q.abs().max())
    for p in range(3):
        plus = energy_hessian(scene, q + eps * v[p], project=False)
        minus = energy_hessian(scene, q - eps * v[p], project=False)
        fd = (plus - minus) @ u[p].numpy() / (2 * eps)
        np.testing.assert_allclose(uv[p].numpy(), fd, rtol=0, atol=1e-5 * np.abs(fd).max())


@pytest.mark.parametrize("name", ["toy_tiny_bar_2d", "toy_small_cloth"])
def test_modal_derivatives_solve_their_system_symmetrically(name: str) -> None:
    scene = scenes.build(name)
    d, sigma = 3, 0.05
    sub = modal_derivatives(scene, d, sigma=sigma)
    modal = modal_analysis(scene, d, sigma=sigma)
    assert isinstance(sub, QuadraticSubspace) and sub.kind == "quadratic" and sub.metadata["regularization"] == 0.0
    torch.testing.assert_close(sub.basis, modal.basis, rtol=0, atol=1e-12)
    torch.testing.assert_close(sub.offset, modal.offset, rtol=0, atol=0)
    H = energy_hessian(scene, sub.offset, project=False)
    i, j = torch.triu_indices(d, d)
    for first, second in ((i, j), (j, i)):  # H Psi_ij = -(dH[a_j]) a_i, with either order of the pair
        rhs = hessian_directional_derivative(scene, sub.offset, sub.basis[:, first].T, sub.basis[:, second].T)
        residual = H @ sub.quadratic.numpy() + rhs.T.numpy()
        assert np.abs(residual).max() <= 1e-9 * np.abs(rhs.numpy()).max()
    # f is the second-order Taylor polynomial: d^2 f / dz_i dz_j = Psi_ij.
    hess = torch.func.jacrev(torch.func.jacrev(lambda z: sub(z)))(torch.zeros(d, dtype=torch.float64))  # [n, d, d]
    torch.testing.assert_close(hess[:, i, j], sub.quadratic, rtol=0, atol=1e-12)
    torch.testing.assert_close(hess[:, j, i], sub.quadratic, rtol=0, atol=1e-12)


def test_modal_derivatives_scale_with_sigma_squared(bar: Scene) -> None:
    small, large = modal_derivatives(bar, 2, sigma=0.01), modal_derivatives(bar, 2, sigma=0.03)
    torch.testing.assert_close(large.quadratic, 9.0 * small.quadratic, rtol=1e-9, atol=0.0)


def test_modal_derivatives_project_out_null_modes() -> None:
    """A free tet: six null modes; the right-hand side has rotation components, the solution must not."""
    scene = _free_tet()
    d = 8
    sub = modal_derivatives(scene, d, sigma=0.1, rest=scene.q_seed)
    assert sub.metadata["null_modes"] == 6 and sub.metadata["regularization"] > 0.0
    M = scene.mass_matrix_scipy()
    null = sub.basis.numpy()[:, :6] / 0.1
    psi = sub.quadratic.numpy()
    assert np.isfinite(psi).all()
    assert np.abs(null.T @ (M @ psi)).max() < 1e-12 * np.abs(psi).max()
    H = energy_hessian(scene, scene.q_seed, project=False)
    i, j = torch.triu_indices(d, d)
    rhs = hessian_directional_derivative(scene, scene.q_seed, sub.basis[:, i].T, sub.basis[:, j].T).T.numpy()
    assert np.abs(null.T @ rhs).max() > 1e-3 * np.abs(rhs).max()  # rotations do couple to stretches
    projected = rhs - M @ (null @ (null.T @ rhs))
    assert np.abs(H @ psi + projected).max() <= 1e-8 * np.abs(rhs).max()


# -- snapshot methods -------------------------------------------------------------------------------


@pytest.mark.parametrize("lanczos", [False, True])
def test_pca_reproduces_a_dataset_on_an_affine_plane(lanczos: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """States c + Z B^T (d = 3) on the three-link chain, whose M has 4x4 rigid-body blocks."""
    scene = scenes.build("toy_three_link_chain")
    if lanczos:
        monkeypatch.setattr(baselines, "DENSE_GRAM_LIMIT", 0)
    g = torch.Generator().manual_seed(2)
    n, d, S = scene.free_dof_count, 3, 40
    plane = torch.randn(n, d, generator=g, dtype=torch.float64)
    states = scene.q_seed + torch.randn(S, d, generator=g, dtype=torch.float64) @ plane.T
    sub = pca_subspace(states, d, scene=scene)
    M = scene.mass_matrix_scipy()
    A = sub.basis.numpy()
    torch.testing.assert_close(sub.offset, states.mean(0))
    X = (states - states.mean(0)).numpy()
    np.testing.assert_allclose(A @ A.T, X.T @ X / (S - 1), atol=1e-10 * np.abs(X).max() ** 2)
    # Every state is its own M-orthogonal projection onto the subspace.
    Z = np.linalg.solve(A.T @ (M @ A), A.T @ (M @ X.T)).T
    np.testing.assert_allclose(sub(torch.as_tensor(Z)).numpy(), states.numpy(), atol=1e-10)
    assert sub.metadata["explained_fraction"] == pytest.approx(1.0, abs=1e-10)
    variances = np.array(sub.metadata["variances"])
    assert np.all(np.diff(variances) <= 0) and variances[-1] > 0
    # Columns are M-orthogonal with |a_k|_M^2 = the variance along them.
    np.testing.assert_allclose(A.T @ (M @ A), np.diag(variances), atol=1e-10 * variances[0])


def test_pca_rejects_bad_states(bar: Scene, bar_states: torch.Tensor) -> None:
    with pytest.raises(ValueError, match="shape"):
        pca_subspace(bar_states[:, :5], 2, scene=bar)
    with pytest.raises(ValueError, match="shape"):
        pca_subspace(bar_states[0], 2, scene=bar)
    with pytest.raises(ValueError, match="dim"):
        pca_subspace(bar_states[:3], 3, scene=bar)
    with pytest.raises(ValueError, match="finite"):
        pca_subspace(bar_states * float("nan"), 2, scene=bar)


def test_simulated_states_are_seeded_and_finite(bar: Scene, bar_states: torch.Tensor) -> None:
    again = simulated_states(bar, steps=20, dt=0.02, episodes=2, seed=0, load_scale=5.0)
    other = simulated_states(bar, steps=20, dt=0.02, episodes=2, seed=1, load_scale=5.0)
    assert bar_states.shape == (40, bar.free_dof_count) and bar_states.dtype == torch.float64
    assert bool(torch.isfinite(bar_states).all())
    assert torch.equal(again, bar_states)
    assert not torch.allclose(other, bar_states)
    assert float((bar_states - bar.q_seed).abs().max()) > 1e-3  # the bar moves [m]
    with pytest.raises(ValueError, match="steps"):
        simulated_states(bar, steps=0, dt=0.02, episodes=1, load_scale=1.0)
    with pytest.raises(ValueError, match="load_scale"):
        simulated_states(bar, steps=1, dt=0.02, episodes=1, load_scale=-1.0)


def test_autoencoder_reconstruction_improves_with_training(bar: Scene, bar_states: torch.Tensor) -> None:
    small = {"hidden_width": 32, "hidden_layers": 2, "seed": 0}
    untrained = train_autoencoder(bar, bar_states, 2, steps=1, **small)
    trained = train_autoencoder(bar, bar_states, 2, steps=300, **small)
    assert isinstance(trained, AutoencoderSubspace) and trained.kind == "autoencoder" and trained.latent_dim == 2
    before = untrained.reconstruction_error(bar_states, bar)
    after = trained.reconstruction_error(bar_states, bar)
    assert after < 0.3 * before and after < 0.3
    assert trained.metadata["reconstruction_error"] == pytest.approx(after)
    with torch.no_grad():
        z = trained.encode(bar_states.float())
        assert trained(z).shape == bar_states.shape
    # Latent axes are standardized over the training states.
    torch.testing.assert_close(z.mean(0), torch.zeros(2), rtol=0, atol=1e-4)
    torch.testing.assert_close(z.std(0), torch.ones(2), rtol=0, atol=1e-4)
    with pytest.raises(ValueError, match="shape"):
        train_autoencoder(bar, bar_states[:, :3], 2, steps=1)
    with pytest.raises(ValueError, match="all equal"):
        train_autoencoder(bar, bar_states[:1].expand(4, -1), 2, steps=1)


# -- checkpoints ------------------------------------------------------------------------------------


def test_save_load_round_trip_and_wrong_scene(tmp_path, bar: Scene, bar_states: torch.Tensor) -> None:
    subs = {
        "modal": modal_analysis(bar, 2, sigma=0.01),
        "md": modal_derivatives(bar, 2, sigma=0.01),
        "pca": pca_subspace(bar_states, 2, scene=bar).to(torch.float32),
        "ae": train_autoencoder(bar, bar_states, 2, steps=2, hidden_width=8, hidden_layers=1),
    }
    z = torch.randn(5, 2, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    other = scenes.build("toy_tiny_bar_2d", young=2e4)
    for key, sub in subs.items():
        weights, meta = sub.save(tmp_path / key)
        doc = json.loads(meta.read_text())
        assert doc["kind"] == sub.kind and doc["scene"] == bar.name
        assert doc["scene_fingerprint"] == bar.fingerprint() and doc["format_version"] == 1
        loaded = load_subspace(weights, scene=bar)
        assert type(loaded) is type(sub) and loaded.metadata == json.loads(json.dumps(sub.metadata))
        zz = z.to(next(iter(sub.buffers())).dtype)
        with torch.no_grad():
            torch.testing.assert_close(loaded(zz), sub(zz), rtol=0, atol=0)
        with pytest.raises(CheckpointError, match="not to scene"):
            load_subspace(weights, scene=other)
        with pytest.raises(CheckpointError, match="not to scene"):
            load_subspace(weights, scene=scenes.build("toy_two_tets"))
    (tmp_path / "modal.pt").write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="corrupt"):
        load_subspace(tmp_path / "modal.json", scene=bar)


def test_load_subspace_reads_neural_maps_too(tmp_path, bar: Scene) -> None:
    neural = SubspaceMap(
        SubspaceConfig(latent_dim=2, output_dim=bar.free_dof_count, hidden_width=4, hidden_layers=1),
        {"scene": bar.name, "scene_fingerprint": bar.fingerprint()},
    )
    neural.save(tmp_path / "neural")
    assert isinstance(load_subspace(tmp_path / "neural.pt", scene=bar), SubspaceMap)


def test_float32_cast_keeps_the_interface(bar: Scene) -> None:
    sub = modal_derivatives(bar, 2, sigma=0.01).to(torch.float32)
    q = sub(torch.ones(4, 2))
    assert q.dtype == torch.float32 and q.shape == (4, bar.free_dof_count)
    assert isinstance(modal_analysis(bar, 1), LinearSubspace)


# -- Proposition 1: the fitter's limit is modal analysis --------------------------------------------


def _prop1_fit(young: float, sigma: float, lam: float, steps: int, seed: int) -> dict[str, object]:
    """Fit a d = 2 neural map to a stiffened tiny bar and compare it with modal analysis at z = 0.

    The default bar (1e4 Pa) sags by tens of cm under its weight, and at sigma = 1e-3 the energy
    gap between the second and third mode is too small for a short fit to resolve (angles of 50-90
    degrees after 1500 steps). Stiffer bars keep sigma-sized motions linear while the gaps
    1/2 sigma^2 (lambda_3 - lambda_2) stay well above the fit's noise.
    """
    scene = scenes.build("toy_tiny_bar_2d", young=young)
    modal = modal_analysis(scene, 2, sigma=sigma)
    fit = fit_subspace(
        scene,
        dim=2,
        sigma=sigma,
        lam=lam,
        steps=steps,
        hidden_width=32,
        learning_rate=3e-3,
        exploration_fraction=0.3,
        checkpoint_every=0,
        seed=seed,
        progress=False,
    )
    f = fit.subspace.double()
    z0 = torch.zeros(2, dtype=torch.float64)
    J = torch.func.jacrev(lambda z: f(z))(z0).detach().numpy()  # [n, 2]
    M = scene.mass_matrix_scipy()
    offset = (f(z0).detach() - modal.offset).numpy()
    sag = (scene.q_seed - modal.offset).numpy()
    return {
        "angles": _principal_angles(J, modal.basis.numpy(), M),
        "offset": math.sqrt(offset @ (M @ offset)) / sigma,  # |f(0) - b|_M in units of sigma
        "sag": math.sqrt(sag @ (M @ sag)) / sigma,  # |q_seed - b|_M in units of sigma
        "gram": J.T @ (M @ J) / sigma**2,  # A^T M A / sigma^2, = I in the limit
    }


def _check_prop1(result: dict[str, object]) -> None:
    assert np.max(result["angles"]) < 10.0, result
    assert result["offset"] < 0.3, result
    np.testing.assert_allclose(result["gram"], np.eye(2), atol=0.1)


def test_fitted_map_at_small_sigma_large_lambda_is_modal_analysis() -> None:
    """Prop. 1: with sigma small and lambda large the Jacobian at z = 0 spans the lowest two modes.

    Seed 0 gives principal angles of 0.75 and 2.6 degrees, |f(0) - b|_M = 0.17 sigma and
    J^T M J / sigma^2 within 0.03 of I (about 8 s on one core). Seeds 1-3 (slow) reach at most 4.4 degrees.
    """
    _check_prop1(_prop1_fit(young=1e7, sigma=1e-2, lam=300.0, steps=3000, seed=0))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_prop1_holds_across_seeds(seed: int) -> None:
    _check_prop1(_prop1_fit(young=1e7, sigma=1e-2, lam=300.0, steps=3000, seed=seed))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_prop1_offset_is_the_sagged_equilibrium(seed: int) -> None:
    """A softer bar sags 2.7 sigma under gravity; f(0) must follow the equilibrium, not the seed.

    Seeds 0-2 give angles up to 7.2 degrees and |f(0) - b|_M of 0.09-0.15 sigma.
    """
    result = _prop1_fit(young=1e6, sigma=3e-3, lam=30.0, steps=3000, seed=seed)
    _check_prop1(result)
    assert result["sag"] > 2.0 and result["offset"] < 0.1 * result["sag"], result
