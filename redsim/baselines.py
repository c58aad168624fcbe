"""Builders of the classical and supervised subspaces the data-free neural map is compared against.

The maps they return live in :mod:`redsim.subspace` (and are re-exported here):
:class:`LinearSubspace`, :class:`QuadraticSubspace`, :class:`AutoencoderSubspace`, with the
interface of :class:`redsim.subspace.SubspaceMap`, so integrators, environments and metrics take
them in place of the neural map.

- :func:`modal_analysis` -> :class:`LinearSubspace` f(z) = b + A z: b the static equilibrium, A
  sigma times the d lowest generalized eigenvectors of (H(b), M), M-orthonormal. This is the
  sigma -> 0, lambda -> infinity limit of the paper's loss (Sharp et al. 2023, Prop. 1 and
  supplement A).
- :func:`modal_derivatives` -> :class:`QuadraticSubspace`: the same modes plus the static modal
  derivatives of Barbič & James 2005, "Real-Time Subspace Integration for St.Venant-Kirchhoff
  Deformable Models", as the second-order term of a quadratic map.
- :func:`pca_subspace` -> :class:`LinearSubspace`: mean plus the top-d M-weighted principal
  directions of a set of states (snapshot PCA), e.g. from :func:`simulated_states`.
- :func:`train_autoencoder` -> :class:`AutoencoderSubspace`: the supervised baseline of the
  paper's supplement B.2, an MLP encoder and an MLP decoder identical to the neural map, trained
  on states by M-norm reconstruction with a weak pull of the latents towards 0.

A baseline saves to ``STEM.pt`` (state dict) + ``STEM.json`` (``kind``, scene name and
fingerprint, shapes, metadata) and loads with :func:`redsim.subspace.load_subspace`.
"""

from __future__ import annotations

import logging
import math
from typing import Any, NamedTuple

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
import torch
from torch import Tensor

from redsim.hessian import energy_hessian
from redsim.integrators import FullSpace, FullState, ImplicitEuler, as_float64, static_equilibrium
from redsim.scene import Scene
from redsim.subspace import AutoencoderSubspace, LinearSubspace, QuadraticSubspace
from redsim.subspace.autoencoder import autoencoder_maps

logger = logging.getLogger(__name__)

DENSE_EIGEN_LIMIT = 3000
"""Largest n for which modal analysis uses a dense generalized eigensolver (above: sparse shift-invert)."""

DENSE_GRAM_LIMIT = 3000
"""Largest number of states for which PCA eigen-decomposes the dense S x S Gram matrix (above: Lanczos)."""

NULL_TOLERANCE = 1e-12
"""A mode with |eigenvalue| below this times max_k |H_kk| / M_kk (about the largest eigenvalue) is a null mode:
zero to the accuracy of a float64 eigensolve (about 1e-16 times the largest eigenvalue), with margin."""

SHIFT_FRACTION = 1e-6
"""Shift-invert eigensolves use the shift -SHIFT_FRACTION times the stiffness scale."""


# -- modal analysis and modal derivatives ---------------------------------------------------------


def _check_dim(dim: int, limit: int, what: str) -> None:
    if int(dim) != dim or not 1 <= dim <= limit:
        raise ValueError(f"dim must be an integer in [1, {limit}] ({what}), got {dim!r}")


def _scene_metadata(scene: Scene) -> dict[str, Any]:
    space = scene.condition_space
    return {
        "scene": scene.name,
        "scene_fingerprint": scene.fingerprint(),
        "scene_params": scene.params,
        "condition": None if space is None else dict(zip(space.names, space.default.tolist(), strict=True)),
    }


def _stiffness_scale(H: scipy.sparse.csr_matrix, M: scipy.sparse.csr_matrix) -> float:
    """max_k |H_kk| / M_kk [1/s^2]: the scale of the generalized eigenvalues, 1 if H has a zero diagonal."""
    scale = float(np.max(np.abs(H.diagonal()) / M.diagonal()))
    return scale if scale > 0.0 else 1.0


def _lowest_modes(
    H: scipy.sparse.csr_matrix, M: scipy.sparse.csr_matrix, dim: int
) -> tuple[np.ndarray, np.ndarray, str]:
    """The ``dim`` smallest generalized eigenpairs of H phi = lambda M phi, ascending, with Phi^T M Phi = I.

    Each vector's sign is fixed (its largest entry in magnitude is positive), and ARPACK starts from a seeded vector
    (its default is a fresh random one): the same inputs give the same basis on every run, so the baselines' sampled
    metrics (which map fixed latent draws through the basis) repeat."""
    n = H.shape[0]
    if n <= DENSE_EIGEN_LIMIT:
        values, vectors = scipy.linalg.eigh(H.toarray(), M.toarray(), subset_by_index=[0, dim - 1])
        return values, _signed(vectors), "dense"
    shift = -SHIFT_FRACTION * _stiffness_scale(H, M)
    start = np.random.default_rng(0).standard_normal(n)
    values, vectors = scipy.sparse.linalg.eigsh(H.tocsc(), k=dim, M=M.tocsc(), sigma=shift, which="LM", v0=start)
    order = np.argsort(values)
    values, vectors = values[order], vectors[:, order]
    gram = vectors.T @ (M @ vectors)  # ARPACK's vectors are M-orthonormal up to round-off; make them exactly so
    vectors = scipy.linalg.solve_triangular(np.linalg.cholesky(gram), vectors.T, lower=True).T
    return values, _signed(vectors), "shift-invert"


def _signed(vectors: np.ndarray) -> np.ndarray:
    """``vectors`` [n, d] with each column's sign chosen so that its largest entry in magnitude is positive."""
    rows = np.argmax(np.abs(vectors), axis=0)
    return vectors * np.sign(vectors[rows, np.arange(vectors.shape[1])])


class _Modes(NamedTuple):
    """The lowest modes of a scene at its rest state (see :func:`modal_analysis`)."""

    scene: Scene
    """The float64 scene."""
    rest: Tensor
    """b [n]."""
    hessian: scipy.sparse.csr_matrix
    """H(b), symmetrized, unprojected."""
    mass: scipy.sparse.csr_matrix
    """M."""
    values: np.ndarray
    """The ``dim`` lowest generalized eigenvalues [1/s^2], ascending."""
    vectors: np.ndarray
    """Their M-orthonormal eigenvectors, [n, dim]."""
    basis: Tensor
    """sigma times the eigenvectors, [n, dim] (float64)."""
    meta: dict[str, Any]
    """Scene, eigenvalues, eigensolver, stiffness scale, null-mode count, equilibrium solve."""


def _modes(scene: Scene, dim: int, sigma: float, rest: Tensor | None, cond: Tensor | None = None) -> _Modes:
    """The ``dim`` lowest modes at b (``rest``, default the static equilibrium), columns scaled by sigma.

    ``cond`` [m]: the condition of the energy (None: the scene's default).
    """
    if not (math.isfinite(sigma) and sigma > 0.0):
        raise ValueError(f"sigma must be finite and > 0, got {sigma!r}")
    scene = as_float64(scene)
    n = scene.free_dof_count
    _check_dim(dim, n, f"n = {n}")
    if rest is None:
        b, info = static_equilibrium(scene, None, cond)
        if not info.converged:
            logger.warning(
                "static equilibrium of %r did not converge (%s); modes are taken there", scene.name, info.message
            )
        equilibrium = {"converged": info.converged, "iterations": info.iterations, "grad_norm": info.grad_norm}
    else:
        b = torch.as_tensor(rest, dtype=torch.float64, device=scene.device).detach().clone()
        if b.shape != (n,) or not bool(torch.isfinite(b).all()):
            raise ValueError(f"rest must be a finite configuration of shape [{n}], got {tuple(b.shape)}")
        equilibrium = None
    H = energy_hessian(scene, b, None, cond, project=False)
    H = (0.5 * (H + H.T)).tocsr()
    M = scene.mass_matrix_scipy()
    values, vectors, solver = _lowest_modes(H, M, int(dim))
    scale = _stiffness_scale(H, M)
    if values[0] < -NULL_TOLERANCE * scale:
        logger.warning(
            "the Hessian of %r at the rest state has a negative eigenvalue %.3g: not a minimum", scene.name, values[0]
        )
    meta = {
        **_scene_metadata(scene),
        "eigenvalues": values.tolist(),
        "eigensolver": solver,
        "stiffness_scale": scale,
        "null_modes": int(np.sum(np.abs(values) <= NULL_TOLERANCE * scale)),
        "equilibrium": equilibrium,
    }
    basis = sigma * torch.as_tensor(vectors, dtype=torch.float64)
    return _Modes(scene, b, H, M, values, vectors, basis, meta)


def modal_analysis(
    scene: Scene, dim: int, *, sigma: float = 1.0, rest: Tensor | None = None, cond: Tensor | None = None
) -> LinearSubspace:
    """Linear modal analysis: f(z) = b + sigma * Phi z (the limit of the paper's Prop. 1).

    b is the static equilibrium reached from the seed (at the default condition of a conditional
    scene), H = d^2E/dq^2 (b) the true (unprojected) Hessian, and Phi [n, d] the d generalized
    eigenvectors of H phi = lambda M phi with the smallest eigenvalues, M-orthonormal (Phi^T M Phi = I),
    so that A^T M A = sigma^2 I as Prop. 1 requires. Null and near-null modes (free rigid motions,
    links of a chain that only touch by contact) have the smallest eigenvalues and are kept: they
    are legitimate lowest modes, and the reason linear modes hold no useful motion for such systems.
    The eigenvalues lambda_k = omega_k^2 [1/s^2] are recorded in ``metadata["eigenvalues"]``.

    Dense ``scipy.linalg.eigh`` for n <= DENSE_EIGEN_LIMIT, otherwise ARPACK shift-invert
    ``eigsh`` around a small negative shift (H - shift M is then positive definite for a PSD H).

    Args:
        scene: The system (solved in float64).
        dim: d, the number of modes, 1 <= d <= n.
        sigma: Scale of the columns [configuration unit x kg^(1/2) per unit z], the paper's σ.
        rest: The rest state b [n]; default: :func:`redsim.integrators.static_equilibrium` from the seed.
        cond: Condition [m] of the energy (equilibrium and Hessian) for a conditional scene; default:
            the scene's default condition. The returned map itself is not conditional.

    Returns:
        The float64 subspace; metadata holds sigma, the eigenvalues, the eigensolver, and the
        equilibrium solve's outcome.

    Raises:
        ValueError: on a bad dim, sigma or rest.
    """
    modes = _modes(scene, dim, sigma, rest, cond)
    return LinearSubspace(modes.basis, modes.rest, {**modes.meta, "method": "modal_analysis", "sigma": float(sigma)})


def hessian_directional_derivative(scene: Scene, q: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """Third-derivative contractions d/dq (u_p^T H(q) v_p) = (dH/dq[v_p]) u_p, batched over rows p.

    Computed by three reverse passes through ``scene.energy`` on a batch of P copies of q (each
    copy only sees its own row, since the energy of a batch is a sum of independent rows).

    Args:
        scene: The system.
        q: Configuration, shape [n].
        u: Directions, shape [P, n].
        v: Directions, shape [P, n].

    Returns:
        The contractions [energy unit per configuration unit^3 x u x v], shape [P, n]; symmetric in u, v.
    """
    if u.ndim != 2 or u.shape != v.shape or u.shape[1] != q.shape[-1]:
        raise ValueError(f"u and v must both have shape [P, {q.shape[-1]}], got {tuple(u.shape)}, {tuple(v.shape)}")
    batch = q.detach().reshape(1, -1).expand(u.shape[0], -1).clone().requires_grad_(True)
    zero = torch.zeros_like(batch)
    with torch.enable_grad():
        energy = scene.energy(batch)
        if not energy.requires_grad:
            return zero
        (grad,) = torch.autograd.grad(energy.sum(), batch, create_graph=True)
        if not grad.requires_grad:
            return zero
        (hv,) = torch.autograd.grad((grad * v).sum(), batch, create_graph=True, allow_unused=True)
        if hv is None or not hv.requires_grad:
            return zero
        (out,) = torch.autograd.grad((hv * u).sum(), batch, allow_unused=True)
    return zero if out is None else out.detach()


def modal_derivatives(scene: Scene, dim: int, *, sigma: float = 1.0, rest: Tensor | None = None) -> QuadraticSubspace:
    """Linear modes plus static modal derivatives (Barbič & James 2005) as a quadratic map.

    With the modes a_i = sigma phi_i of :func:`modal_analysis`, the modal derivative of the pair
    (i, j) solves

        H Psi_ij = -(dH/dq[a_j]) a_i = -d/dq (a_i^T H(q) a_j),

    symmetric in i, j, and f(z) = b + A z + 1/2 sum_{i<=j} c_ij z_i z_j Psi_ij. Because the a_i
    carry sigma, Psi_ij carries sigma^2: the quadratic term is the second-order Taylor term of the
    same map that z ~ N(0, I) samples at scale sigma.

    H is singular along free rigid motions, and the right-hand side generally is not orthogonal to
    them (a linearized rotation of a deformed body changes its strain). Null modes N among the d
    computed ones (|eigenvalue| at most NULL_TOLERANCE times max_k |H_kk| / M_kk) are therefore
    projected out of the right-hand side, r -> (I - M N N^T) r, the system is solved with H + delta M,
    delta = that threshold, and the solution is made M-orthogonal to N: the modal derivative is
    only defined up to null directions, and this picks the one without them. Without null modes
    delta = 0 and the system is exactly H Psi_ij = -r_ij. Null directions beyond the d computed
    modes are only regularized by delta (a warning is logged when every computed mode is a null mode).

    Args:
        scene: The system (solved in float64).
        dim: d, 1 <= d <= n; the map has d(d+1)/2 modal derivatives.
        sigma: Scale of the linear columns (the paper's σ), as in :func:`modal_analysis`.
        rest: The rest state b [n]; default: the static equilibrium from the seed.

    Returns:
        The float64 quadratic subspace; metadata as :func:`modal_analysis` plus ``regularization`` (delta).

    Raises:
        ValueError: on a bad dim, sigma or rest.
    """
    scene, b, H, M, values, vectors, basis, meta = _modes(scene, dim, sigma, rest)
    i, j = torch.triu_indices(basis.shape[1], basis.shape[1])
    rhs = -hessian_directional_derivative(scene, b, basis[:, i].T, basis[:, j].T).T.cpu().numpy()  # [n, P]
    threshold = NULL_TOLERANCE * meta["stiffness_scale"]
    null = vectors[:, np.abs(values) <= threshold]  # [n, k], M-orthonormal
    delta = threshold if null.shape[1] else 0.0
    if null.shape[1] == vectors.shape[1]:
        logger.warning(
            "all %d computed modes of %r are null modes; the null space may be larger, and modal "
            "derivatives along the rest of it are only regularized",
            null.shape[1],
            scene.name,
        )
    rhs = rhs - M @ (null @ (null.T @ rhs))
    psi = scipy.sparse.linalg.splu((H + delta * M).tocsc()).solve(rhs)
    psi = psi - null @ (null.T @ (M @ psi))  # drop the round-off that 1 / delta amplified along the null modes
    quadratic = torch.as_tensor(psi, dtype=torch.float64)
    meta = {**meta, "method": "modal_derivatives", "sigma": float(sigma), "regularization": delta}
    return QuadraticSubspace(basis, b, quadratic, meta)


# -- snapshot methods -----------------------------------------------------------------------------


def _check_states(scene: Scene, states: Tensor) -> Tensor:
    states = torch.as_tensor(states)
    n = scene.free_dof_count
    if states.ndim != 2 or states.shape[1] != n or states.shape[0] < 2:
        raise ValueError(f"states must have shape [S, {n}] with S >= 2, got {tuple(states.shape)}")
    if not bool(torch.isfinite(states).all()):
        raise ValueError("states must be finite")
    return states


def pca_subspace(states: Tensor, dim: int, *, scene: Scene) -> LinearSubspace:
    """Snapshot PCA in the M inner product: f(z) = mean + A z.

    With X the centred states [S, n] and G = X M X^T [S, S] their M-Gram matrix, G u_k = mu_k u_k
    (mu_k the largest d), the principal directions w_k = X^T u_k / sqrt(mu_k) are M-orthonormal and
    the data's variance along them is mu_k / (S - 1). The columns a_k = X^T u_k / sqrt(S - 1) =
    w_k * std_k make z ~ N(0, I) reproduce the data's covariance within the subspace. The Gram
    matrix is eigen-decomposed densely for S <= DENSE_GRAM_LIMIT, otherwise by Lanczos on
    u -> X M X^T u (never formed).

    Args:
        states: Configurations [configuration unit], shape [S, n], S >= 2.
        dim: d, 1 <= d <= min(n, S - 1).
        scene: Supplies M (and the metadata).

    Returns:
        A float64 subspace; metadata holds the variances mu_k / (S - 1) [kg x unit^2] and the
        fraction of the total M-variance they explain.

    Raises:
        ValueError: on a bad shape, non-finite states, or a bad dim.
    """
    scene = as_float64(scene)
    states = _check_states(scene, states).to(device=scene.device, dtype=torch.float64)
    S, n = states.shape
    _check_dim(dim, min(n, S - 1), f"n = {n}, S - 1 = {S - 1}")
    mean = states.mean(0)
    X = states - mean
    MX = scene.mass_matvec(X)
    if S <= DENSE_GRAM_LIMIT:
        mu, U = torch.linalg.eigh(X @ MX.T)
        mu, U = mu.flip(0)[:dim], U.flip(1)[:, :dim]
    else:
        operator = scipy.sparse.linalg.LinearOperator(
            (S, S), matvec=lambda u: (X @ (MX.T @ torch.as_tensor(u).reshape(-1))).numpy(), dtype=np.float64
        )
        values, vectors = scipy.sparse.linalg.eigsh(operator, k=dim, which="LA")
        order = np.argsort(values)[::-1].copy()
        mu, U = torch.as_tensor(values[order]), torch.as_tensor(vectors[:, order])
    basis = X.T @ U / math.sqrt(S - 1)
    variance = mu.clamp_min(0.0) / (S - 1)
    total = float(scene.mass_norm_sq(X).sum()) / (S - 1)
    meta = {
        **_scene_metadata(scene),
        "method": "pca",
        "states": S,
        "variances": variance.tolist(),
        "explained_fraction": float(variance.sum()) / total if total > 0.0 else 1.0,
    }
    return LinearSubspace(basis, mean, meta)


def simulated_states(
    scene: Scene, *, steps: int, dt: float, episodes: int, seed: int = 0, load_scale: float, hold: int = 10
) -> Tensor:
    """States of full-space implicit-Euler trajectories under random piecewise-constant loads.

    Each episode starts at rest at the seed and runs ``steps`` steps of
    :class:`redsim.integrators.ImplicitEuler` over :class:`FullSpace` (default condition); every
    ``hold`` steps each handle's load is redrawn from N(0, load_scale^2 I). This is the "states from
    full-space simulations" that :func:`pca_subspace` and :func:`train_autoencoder` learn from.

    Args:
        scene: The system; it needs at least one handle.
        steps: Steps per episode (>= 1).
        dt: Time step [s].
        episodes: Number of episodes (>= 1).
        seed: Seeds the loads; the same seed gives the same states.
        load_scale: Standard deviation of each load component [N] (>= 0).
        hold: Steps each load is held (>= 1).

    Returns:
        The states after every step, episode after episode, float64, shape [episodes * steps, n].

    Raises:
        ValueError: on bad counts, a bad load_scale, or a scene without handles.
    """
    counts = {"steps": steps, "episodes": episodes, "hold": hold}
    bad = {k: v for k, v in counts.items() if int(v) != v or v < 1}
    if bad:
        raise ValueError(f"{sorted(bad)} must be integers >= 1, got {bad}")
    if not (math.isfinite(load_scale) and load_scale >= 0.0):
        raise ValueError(f"load_scale must be finite and >= 0 [N], got {load_scale!r}")
    if not scene.handles:
        raise ValueError(f"scene {scene.name!r} has no handles to load")
    integrator = ImplicitEuler(FullSpace(scene), dt)
    generator = torch.Generator().manual_seed(seed)
    segments = -(-int(steps) // int(hold))
    loads = load_scale * torch.randn(
        int(episodes), segments, len(scene.handles), scene.dim, generator=generator, dtype=torch.float64
    ).to(integrator.scene.device)
    out = []
    for episode in range(int(episodes)):

        def schedule(index: int, _state: FullState, episode: int = episode) -> Tensor:
            return loads[episode, index // int(hold)]

        trajectory, infos = integrator.rollout(integrator.initial_state(), int(steps), schedule)
        failed = sum(not info.converged for info in infos)
        if failed:
            logger.warning("episode %d of %r: %d of %d steps did not converge", episode, scene.name, failed, steps)
        out.append(trajectory[1:])
    return torch.cat(out)


def train_autoencoder(
    scene: Scene,
    states: Tensor,
    dim: int,
    *,
    steps: int,
    seed: int = 0,
    hidden_width: int = 128,
    hidden_layers: int = 5,
    batch_size: int = 256,
    learning_rate: float = 1e-3,
    latent_weight: float = 1e-3,
    device: str = "cpu",
) -> AutoencoderSubspace:
    """The supervised baseline of the paper's supplement B.2: an autoencoder trained on states.

    Encoder and decoder are ELU MLPs of the given size; the decoder is exactly the neural subspace
    map's architecture (:class:`SubspaceMap`, d -> n). The loss on a batch is

        mean_s |f(g(q_s)) - q_s|_M^2 / mean_s |q_s - mean|_M^2  +  latent_weight * mean_s |g(q_s)|^2,

    relative M-norm reconstruction plus a weak pull of the latents towards 0 (Adam, float32, the
    learning rate halved after each quarter of the steps; the decoder's output bias starts at the
    mean state). After training, the latent axes are shifted and scaled (folded exactly into the
    encoder's last and the decoder's first layer) so the encoded states have mean 0 and standard
    deviation 1 per coordinate, the scale on which z ~ N(0, I) is sampled elsewhere.

    Args:
        scene: The system (supplies M and the metadata).
        states: Training configurations, shape [S, n], S >= 2.
        dim: d, 1 <= d <= n.
        steps: Adam steps (>= 1).
        seed: Seeds the initialisation and the batches.
        hidden_width: Units per hidden layer (both MLPs).
        hidden_layers: Hidden layers (both MLPs).
        batch_size: States per step (at most S).
        learning_rate: Initial Adam learning rate.
        latent_weight: Weight of the latent regularizer.
        device: Torch device for training; the result is on the CPU.

    Returns:
        The float32 autoencoder; metadata holds the settings and the final relative reconstruction error.

    Raises:
        ValueError: on bad shapes or settings, or states without any spread.
    """
    states = _check_states(scene, states)
    S, n = states.shape
    _check_dim(dim, n, f"n = {n}")
    if int(steps) != steps or steps < 1 or batch_size < 1 or not learning_rate > 0.0 or not latent_weight >= 0.0:
        raise ValueError(
            f"need steps >= 1, batch_size >= 1, learning_rate > 0, latent_weight >= 0; got {steps}, "
            f"{batch_size}, {learning_rate}, {latent_weight}"
        )
    work = scene.to(device=device, dtype=torch.float32)
    data = states.to(device=device, dtype=torch.float32)
    mean = data.mean(0)
    spread = float(work.mass_norm_sq(data - mean).mean())
    scale = (data - mean).std()
    if not spread > 0.0:
        raise ValueError("states are all equal; there is nothing to encode")
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        encoder, decoder = autoencoder_maps(n, int(dim), hidden_width, hidden_layers)
    with torch.no_grad():
        decoder.mlp[-1].bias.copy_(mean.cpu())
    model = AutoencoderSubspace(encoder, decoder, mean, scale).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=learning_rate)
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=max(1, int(steps) // 4), gamma=0.5)
    generator = torch.Generator(device=device).manual_seed(seed)
    batch = min(int(batch_size), S)
    for _ in range(int(steps)):
        q = data[torch.randint(S, (batch,), generator=generator, device=device)]
        z = model.encode(q)
        loss = work.mass_norm_sq(model(z) - q).mean() / spread + latent_weight * (z**2).sum(-1).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
    _standardize_latents(model, data)
    model = model.cpu()
    model.metadata.update(
        {
            **_scene_metadata(scene),
            "method": "autoencoder",
            "states": S,
            "steps": int(steps),
            "seed": seed,
            "batch_size": batch,
            "learning_rate": learning_rate,
            "latent_weight": latent_weight,
            "reconstruction_error": model.reconstruction_error(states, scene),
        }
    )
    return model


def _standardize_latents(model: AutoencoderSubspace, data: Tensor) -> None:
    """Re-coordinate z' = (z - m) / s so that encoded ``data`` have mean 0 and std 1 per axis (decoding unchanged)."""
    with torch.no_grad():
        z = model.encode(data)
        shift, stretch = z.mean(0), z.std(0)
        stretch = torch.where(stretch > 0, stretch, torch.ones_like(stretch))  # a dead latent axis stays as is
        last, first = model.encoder.mlp[-1], model.decoder.mlp[0]
        last.weight.div_(stretch[:, None])
        last.bias.sub_(shift).div_(stretch)
        first.bias.add_(first.weight @ shift)
        first.weight.mul_(stretch)


__all__ = [
    "AutoencoderSubspace",
    "LinearSubspace",
    "QuadraticSubspace",
    "hessian_directional_derivative",
    "modal_analysis",
    "modal_derivatives",
    "pca_subspace",
    "simulated_states",
    "train_autoencoder",
]
