"""A map's affine output layer, q = r(z[, c]) W^T + b, and its slice to a few DOFs.

Every map kind redsim ships ends in an affine layer: the neural map's last ``nn.Linear`` (r = the
last hidden activation, width w = 64..128), the linear map (r = z) and the quadratic map
(r = [z, 1/2 c_ij z_i z_j]) and the anchored map (r = [MLP remainder, z, 1/2 c_ij z_i z_j], see
:class:`redsim.subspace.AnchoredSubspace`). A cubature energy evaluates r once per state and then only what its
kept elements read from it: their edges through differences of W's rows (an edge layer), or their DOFs through the
rows of W (a sliced output layer), and the step's inertia term exactly in r with the precomputed w x w Gram W^T M W
(see :class:`redsim.cubature.energy.CubatureEnergy`).
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor, nn

from redsim.scene import Scene
from redsim.subspace import AnchoredSubspace, LinearSubspace, QuadraticSubspace, SubspaceMap
from redsim.subspace.base import check_latent


class AffineOutput(nn.Module):
    """q = r(z[, c]) @ weight.T + bias for one map (copied, gradients off).

    Attributes:
        weight: W, shape [n, w], in the map's units per feature.
        bias: b, shape [n].
        feature_dim: w.

    Raises:
        ValueError: a map kind without an affine output layer (the autoencoder baseline).
    """

    def __init__(self, subspace: nn.Module) -> None:
        super().__init__()
        self.map = copy.deepcopy(subspace)
        if isinstance(subspace, SubspaceMap):
            weight, bias = subspace.mlp[-1].weight, subspace.mlp[-1].bias
        elif isinstance(subspace, AnchoredSubspace):
            weight, bias = subspace.affine_weight(), subspace.polynomial.offset
        elif isinstance(subspace, QuadraticSubspace):
            weight, bias = torch.cat([subspace.basis, subspace.quadratic], 1), subspace.offset
        elif isinstance(subspace, LinearSubspace):
            weight, bias = subspace.basis, subspace.offset
        else:
            raise ValueError(
                "a cubature needs a map with an affine output layer (neural, anchored, linear or quadratic), "
                f"got {type(subspace).__name__}"
            )
        self.register_buffer("weight", weight.detach().clone())
        self.register_buffer("bias", bias.detach().clone())
        self.requires_grad_(False)

    @property
    def feature_dim(self) -> int:
        return int(self.weight.shape[1])

    def features(self, z: Tensor, cond: Tensor | None) -> Tensor:
        """r [B, w] of latents z [B, d] (and conditions [B, m])."""
        f = self.map
        if isinstance(f, SubspaceMap):
            return f.hidden(z, cond)
        if isinstance(f, AnchoredSubspace):
            return f.affine_features(z, cond)
        check_latent(z, f.latent_dim, cond)
        return torch.cat([z, f.monomials(z)], -1) if isinstance(f, QuadraticSubspace) else z

    def forward(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """All of q [B, n] (the unsliced map), by one ``addmm``: the same bits as ``r @ W.T + b``, without its second
        pass over [B, n] (1.15-1.3 against 1.25-3.2 ms at B = 64, n = 6,072, w = 128, float32, the larger where the
        [B, n] temporary's allocation showed; docs/env-speed.md, "Stop 52")."""
        return torch.addmm(self.bias, self.features(z, cond), self.weight.T)


def sliced_layer(output: AffineOutput, scene: Scene, full_index: Tensor) -> tuple[Tensor, Tensor]:
    """The rows of the output layer that give x[:, full_index] (full DOFs, pinned ones included).

    Returns W_S [s, w] and b_S [s] with x_S = r @ W_S.T + b_S: a free DOF's row of W and b, a pinned
    DOF's zero row and its pinned value.
    """
    free_of = scene.dof_map.full_to_free().to(full_index.device)[full_index]
    free = free_of >= 0
    rows = free_of.clamp_min(0)
    weight = output.weight.index_select(0, rows) * free[:, None].to(output.weight.dtype)
    pinned = scene.dof_map.full_values.to(output.bias)[full_index]
    bias = torch.where(free, output.bias.index_select(0, rows), pinned)
    return weight, bias


def column_major(weight: Tensor) -> Tensor:
    """``weight`` [K, w] (same values) stored column-major, so that ``torch.addmm(b, r, weight.T)`` and its backward
    multiply by a contiguous [w, K] matrix: at K = 7,500, w = 128, float32, one thread, 1.74x less CPU time for the
    product and its backward at 1 row and 1.64-1.66x at 2-3 (the row loop's tail calls), the same from 4 rows on
    (docs/env-speed.md, "Stop 55")."""
    return weight.T.contiguous().T


__all__ = ["AffineOutput", "column_major", "sliced_layer"]
