"""Modal pull (``FitConfig.modal``, not in the paper): hold the map's rest state and its tangent there.

Prop. 1 of the paper: as sigma -> 0 the loss's minimiser is f(z) = b + sigma Phi z, b the static
equilibrium and Phi the d lowest generalized eigenvectors of (H(b), M): the map holds the small
linear responses to loads by construction. At the sigma a scene needs for its large motions nothing
forces this: a 3000-step cantilever fit's unloaded equilibrium sits 13 J above b and its Jacobian
there is nearly orthogonal to the two lowest modes (issue 12: response errors near 1). With
``modal > 0`` the loss gains, over a few conditions c_k (the default one; for a conditional fit also
seeded samples of the condition space),

    w(t)/2 mean_k ( |MLP(0, c_k) - b_k|^2_A + |J_k - sigma Phi_k R_k|^2_A ),   A = H(b_k) + lambda_d M,

with J_k = dMLP/dz at (0, c_k), [n, d], by central differences, R_k the orthogonal d x d matrix
nearest Phi_k^T M J_k (orthogonal Procrustes, so the modes' signs and their order within
near-degenerate groups do not matter), H the PSD-projected Hessian and lambda_d the d-th lowest
eigenvalue; w(t) (unitless) follows the anchor schedule (:func:`redsim.trainers.fit.anchor_at`).
The norm is the energy's own: |x|^2_H / 2 is the elastic energy a small error x costs, so an error
along a stiff element-level direction counts as much as it lifts the map's energy (an M-norm pull
left f(0) 0.007 kg^1/2 m from b on the cantilever, yet 37 J above it); lambda_d M keeps the lowest
modes (and null modes) weighted at least as the d-th. In that norm a map that starts as MLPs do
(output near 0, random Jacobian) begins 10^8 J off, so the fit starts from a flat map at b instead
(:func:`start_at_rest`). It needs no simulation data: b_k, H and Phi_k come from the energy alone
(its static equilibrium and Hessian, the inputs of linear modal analysis). Measured (README, "Small
responses"): the cantilever's response error falls from 0.98 to 0.30, the conditional bar's only to
0.76-0.84.
"""

from __future__ import annotations

import copy
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from redsim.baselines import modal_analysis, modal_derivatives
from redsim.hessian import energy_hessian
from redsim.integrators.reference import full_equilibrium
from redsim.scene import Scene
from redsim.subspace import SubspaceMap

MODAL_CONDITIONS = 8
"""Conditions a conditional fit holds the modes at: the default one and this many minus one seeded samples."""

MODAL_SAMPLES = 8
"""Latents per step at which ``FitConfig.modal_radius`` pulls the map to the modal-derivative map."""

START_SAMPLES = 2048
"""Latents of the least-squares start on the modal-derivative map (:func:`start_at_quadratic`), all conditions."""

MODAL_STEP = 1e-2
"""Latent step of the central differences that give the map's Jacobian at z = 0."""

START_SCALE = 1e-2
"""The output layer's initial weights are scaled by this when the fit starts at the rest state."""


class ModalTargets(NamedTuple):
    """The rest states and lowest modes a map is pulled to (:func:`modal_targets`), K conditions."""

    cond: Tensor | None
    """Conditions [K, m], or None for a map without condition input (then K = 1, the default condition)."""
    rest: Tensor
    """Static equilibria b_k [K, n]."""
    modes: Tensor
    """The d lowest generalized eigenvectors of (H(b_k), M), M-orthonormal, [K, n, d]."""
    metric: tuple[Tensor, ...]
    """A_k = H(b_k) + lambda_d M, sparse [n, n] [1/s^2 x kg], one per condition."""
    derivatives: Tensor | None = None
    """Modal derivatives Psi_k of the unit modes (:func:`redsim.baselines.modal_derivatives`, sigma = 1), pairs
    i <= j in ``torch.triu_indices(d, d)`` order, [K, n, d(d+1)/2]; None unless asked for."""

    def to(self, device: str | torch.device, dtype: torch.dtype) -> ModalTargets:
        """The same targets on ``device`` in ``dtype``."""
        cond = None if self.cond is None else self.cond.to(device=device, dtype=dtype)
        move = [t.to(device=device, dtype=dtype) for t in (self.rest, self.modes)]
        metric = tuple(a.to(device=device, dtype=dtype) for a in self.metric)
        psi = None if self.derivatives is None else self.derivatives.to(device=device, dtype=dtype)
        return ModalTargets(cond, *move, metric, psi)


def modal_targets(
    scene: Scene, latent_dim: int, conditional: bool, seed: int, derivatives: bool = False
) -> ModalTargets:
    """Rest states and lowest modes (float64) at the default condition and, if ``conditional``, at
    MODAL_CONDITIONS - 1 conditions sampled from the scene's space with a generator seeded by ``seed``;
    with ``derivatives`` also the modal derivatives there.

    The rest states are :func:`redsim.integrators.reference.full_equilibrium` (the load errors'
    reference, cached).
    """
    scene64 = scene.to(dtype=torch.float64)
    conds: list[Tensor | None] = [None]
    if conditional:
        assert scene64.condition_space is not None  # checked by fit_subspace
        generator = torch.Generator().manual_seed(seed)
        conds += list(scene64.condition_space.sample(MODAL_CONDITIONS - 1, generator).to(torch.float64))
    mass = scene64.mass_matrix_scipy()
    rests, modes, metrics, psis = [], [], [], []
    for cond in conds:
        rest, _, _ = full_equilibrium(scene64, None, cond)
        build = modal_derivatives if derivatives else modal_analysis
        linear = build(scene64, latent_dim, sigma=1.0, rest=rest, cond=cond)
        if derivatives:
            psis.append(linear.quadratic)
        stiffness = energy_hessian(scene64, rest, None, cond, project=True)
        metric = (stiffness + max(linear.metadata["eigenvalues"][-1], 0.0) * mass).tocoo()
        indices = torch.from_numpy(np.vstack([metric.row, metric.col]).astype(np.int64))
        values = torch.from_numpy(metric.data)
        metrics.append(torch.sparse_coo_tensor(indices, values, metric.shape, check_invariants=True).coalesce())
        rests.append(rest)
        modes.append(linear.basis)
    packed = None
    if conditional:
        packed = torch.stack([scene64.pack_condition(c, 1)[0] for c in conds])  # type: ignore[index]
    psi = torch.stack(psis) if derivatives else None
    return ModalTargets(packed, torch.stack(rests), torch.stack(modes), tuple(metrics), psi)


def modal_gap(
    scene: Scene, model: SubspaceMap, targets: ModalTargets, sigma: float, samples: Tensor | None = None
) -> Tensor:
    """mean_k |MLP(0, c_k) - b_k|^2_A + |J_k - sigma Phi_k R_k|^2_A [J] (module doc), a 0-dim tensor; with
    ``samples`` z_s [S, d] also + mean_s |MLP(z_s, c_k) - Q_k(R_k z_s)|^2_A, Q_k the modal-derivative map.

    ``targets`` must be in the model's dtype and device (with ``derivatives`` when ``samples`` are given).
    """
    K, n, d = targets.modes.shape
    steps = MODAL_STEP * torch.eye(d, dtype=targets.rest.dtype, device=targets.rest.device)
    z = torch.cat([torch.zeros_like(steps[:1]), steps, -steps, *([] if samples is None else [samples])])
    cond = None
    if targets.cond is not None:
        cond = targets.cond.repeat_interleave(len(z), 0)
    y = model(z.repeat(K, 1), cond).reshape(K, len(z), n)
    offset = y[:, 0] - targets.rest  # [K, n]
    jacobian = ((y[:, 1 : d + 1] - y[:, d + 1 : 2 * d + 1]) / (2 * MODAL_STEP)).transpose(1, 2)  # [K, n, d]
    mass_jac = scene.mass_matvec(jacobian.transpose(1, 2)).transpose(1, 2)  # M J, [K, n, d]
    with torch.no_grad():
        u, _, vh = torch.linalg.svd(targets.modes.transpose(1, 2) @ mass_jac)  # Phi^T M J = U S V^T
        rotation = u @ vh
    gap = torch.cat([offset.unsqueeze(-1), jacobian - sigma * targets.modes @ rotation], -1)  # [K, n, 1 + d]
    if samples is not None:
        if targets.derivatives is None:
            raise ValueError("samples need targets with the modal derivatives (modal_targets(derivatives=True))")
        far = y[:, 2 * d + 1 :] - quadratic_map(targets, sigma, samples @ rotation.transpose(1, 2))  # [K, S, n]
        gap = torch.cat([gap, far.transpose(1, 2) / len(samples) ** 0.5], -1)
    return torch.stack([(g * torch.sparse.mm(a, g)).sum() for g, a in zip(gap, targets.metric, strict=True)]).mean()


def quadratic_map(targets: ModalTargets, sigma: float, w: Tensor) -> Tensor:
    """Q_k(w) = b_k + sigma Phi_k w + sigma^2/2 sum_ij w_i w_j Psi_k,ij [K, S, n] at modal coordinates w [K, S, d]
    (the modal-derivative map of :func:`redsim.baselines.modal_derivatives`, condition k)."""
    assert targets.derivatives is not None  # checked by the caller
    i, j = torch.triu_indices(w.shape[-1], w.shape[-1], device=w.device)
    monomials = torch.where(i == j, 0.5, 1.0).to(w.dtype) * w[..., i] * w[..., j]  # [K, S, P]
    linear = sigma * w @ targets.modes.transpose(1, 2)
    return targets.rest.unsqueeze(1) + linear + sigma**2 * monomials @ targets.derivatives.transpose(1, 2)


def start_at_quadratic(model: SubspaceMap, targets: ModalTargets, sigma: float, radius: float, seed: int) -> None:
    """Start the map on the modal-derivative maps Q_k: the output layer solves the least-squares fit
    MLP(z_s, c_k) = Q_k(z_s) (float64) over START_SAMPLES latents z_s ~ N(0, radius^2 I) split over the conditions.

    The hidden layers keep their random start; their features at small |z| are smooth functions whose
    Taylor terms span the constant, linear and quadratic monomials of z, so the fit holds Q_k to third order.
    The least-squares solution is the same in every norm (each output is fitted on the same features), so
    it is the A-norm fit too. ``targets`` must hold the modal derivatives.
    """
    K, n, d = targets.modes.shape
    generator = torch.Generator().manual_seed(seed)
    per = -(-START_SAMPLES // K)
    z = radius * torch.randn(K, per, d, generator=generator, dtype=torch.float64)
    work = copy.deepcopy(model).to(device="cpu", dtype=torch.float64)
    cpu = targets.to("cpu", torch.float64)
    cond = None if cpu.cond is None else cpu.cond.repeat_interleave(per, 0)
    with torch.no_grad():
        hidden = work.mlp[:-1](work.features(z.reshape(K * per, d), cond))  # [K per, width]
        design = torch.cat([hidden, torch.ones_like(hidden[:, :1])], 1)
        solution = torch.linalg.lstsq(design, quadratic_map(cpu, sigma, z).reshape(K * per, n)).solution
        model.mlp[-1].weight.copy_(solution[:-1].T)
        model.mlp[-1].bias.copy_(solution[-1])


def start_at_rest(model: SubspaceMap, targets: ModalTargets) -> None:
    """Start the map flat at the default condition's rest state: output bias b_0, output weights x START_SCALE.

    The pull's energy norm weighs the stiff element-level directions by their stiffness, so a map that starts
    far from b or with a random Jacobian begins with a pull of 10^8 J (the cantilever) that swamps every other
    term; from a flat map at b the Jacobian grows along the soft directions the pull asks for.
    """
    with torch.no_grad():
        model.mlp[-1].bias.copy_(targets.rest[0])
        model.mlp[-1].weight.mul_(START_SCALE)
