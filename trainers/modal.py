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
(its static equilibrium and Hessian, the inputs of linear modal analysis). Measured (docs/fitting.md, "Small
responses"): the cantilever's response error falls from 0.98 to 0.30, the conditional bar's only to
0.76-0.84.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from redsim.baselines import modal_analysis
from redsim.hessian import energy_hessian
from redsim.integrators.reference import full_equilibrium
from redsim.scene import Scene
from redsim.subspace import SubspaceMap

MODAL_CONDITIONS = 8
"""Conditions a conditional fit holds the modes at: the default one and this many minus one seeded samples."""

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

    def to(self, device: str | torch.device, dtype: torch.dtype) -> ModalTargets:
        """The same targets on ``device`` in ``dtype``."""
        cond = None if self.cond is None else self.cond.to(device=device, dtype=dtype)
        move = [t.to(device=device, dtype=dtype) for t in (self.rest, self.modes)]
        return ModalTargets(cond, *move, tuple(a.to(device=device, dtype=dtype) for a in self.metric))


def modal_targets(scene: Scene, latent_dim: int, conditional: bool, seed: int) -> ModalTargets:
    """Rest states and lowest modes (float64) at the default condition and, if ``conditional``, at
    MODAL_CONDITIONS - 1 conditions sampled from the scene's space with a generator seeded by ``seed``.

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
    rests, modes, metrics = [], [], []
    for cond in conds:
        rest, _, _ = full_equilibrium(scene64, None, cond)
        linear = modal_analysis(scene64, latent_dim, sigma=1.0, rest=rest, cond=cond)
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
    return ModalTargets(packed, torch.stack(rests), torch.stack(modes), tuple(metrics))


def modal_gap(scene: Scene, model: SubspaceMap, targets: ModalTargets, sigma: float) -> Tensor:
    """mean_k |MLP(0, c_k) - b_k|^2_A + |J_k - sigma Phi_k R_k|^2_A [J] (module doc), a 0-dim tensor.

    ``targets`` must be in the model's dtype and device.
    """
    K, n, d = targets.modes.shape
    steps = MODAL_STEP * torch.eye(d, dtype=targets.rest.dtype, device=targets.rest.device)
    z = torch.cat([torch.zeros_like(steps[:1]), steps, -steps])  # [1 + 2d, d]
    cond = None
    if targets.cond is not None:
        cond = targets.cond.repeat_interleave(len(z), 0)
    y = model(z.repeat(K, 1), cond).reshape(K, len(z), n)
    offset = y[:, 0] - targets.rest  # [K, n]
    jacobian = ((y[:, 1 : d + 1] - y[:, d + 1 :]) / (2 * MODAL_STEP)).transpose(1, 2)  # [K, n, d]
    mass_jac = scene.mass_matvec(jacobian.transpose(1, 2)).transpose(1, 2)  # M J, [K, n, d]
    with torch.no_grad():
        u, _, vh = torch.linalg.svd(targets.modes.transpose(1, 2) @ mass_jac)  # Phi^T M J = U S V^T
        rotation = u @ vh
    gap = torch.cat([offset.unsqueeze(-1), jacobian - sigma * targets.modes @ rotation], -1)  # [K, n, 1 + d]
    return torch.stack([(g * torch.sparse.mm(a, g)).sum() for g, a in zip(gap, targets.metric, strict=True)]).mean()


def start_at_rest(model: SubspaceMap, targets: ModalTargets) -> None:
    """Start the map flat at the default condition's rest state: output bias b_0, output weights x START_SCALE.

    The pull's energy norm weighs the stiff element-level directions by their stiffness, so a map that starts
    far from b or with a random Jacobian begins with a pull of 10^8 J (the cantilever) that swamps every other
    term; from a flat map at b the Jacobian grows along the soft directions the pull asks for.
    """
    with torch.no_grad():
        model.mlp[-1].bias.copy_(targets.rest[0])
        model.mlp[-1].weight.mul_(START_SCALE)
