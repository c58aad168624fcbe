"""Polynomial maps: the affine f(z) = b + A z (modal analysis, PCA) and the quadratic one (modal derivatives).

Built by :mod:`redsim.baselines`; saved and loaded as checkpoints of kind "linear" and "quadratic".
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from redsim.subspace.base import MapModule, check_latent, dtype_name


class _PolynomialMap(MapModule):
    """The affine part b + A z shared by the linear and the quadratic map.

    Args:
        basis: A [configuration unit per unit z], shape [n, d].
        offset: b [configuration unit], shape [n].
        metadata: JSON-able description (scene, fingerprint, method parameters).
    """

    def __init__(self, basis: Tensor, offset: Tensor, metadata: dict[str, Any] | None = None) -> None:
        super().__init__(metadata)
        if basis.ndim != 2 or offset.shape != (basis.shape[0],):
            raise ValueError(f"basis must be [n, d] and offset [n], got {tuple(basis.shape)}, {tuple(offset.shape)}")
        self.register_buffer("basis", basis.detach().clone())
        self.register_buffer("offset", offset.detach().clone().to(basis.dtype))

    @property
    def latent_dim(self) -> int:
        return int(self.basis.shape[1])

    def affine(self, z: Tensor, cond: Tensor | None) -> Tensor:
        """b + A z [..., n] for latents z [..., d] (checked; no condition)."""
        check_latent(z, self.latent_dim, cond)
        return self.offset + z @ self.basis.T

    def shapes(self) -> dict[str, Any]:
        n, d = self.basis.shape
        return {"latent_dim": int(d), "output_dim": int(n), "dtype": dtype_name(self.basis.dtype)}

    @classmethod
    def from_shapes(cls, shapes: dict[str, Any], metadata: dict[str, Any]) -> _PolynomialMap:
        n, d = int(shapes["output_dim"]), int(shapes["latent_dim"])
        return cls.zeros(n, d, getattr(torch, shapes["dtype"]), metadata)

    @classmethod
    def zeros(cls, n: int, d: int, dtype: torch.dtype, metadata: dict[str, Any]) -> _PolynomialMap:
        """The map with every coefficient 0, for n outputs and d latents."""
        raise NotImplementedError


class LinearSubspace(_PolynomialMap):
    """The affine map f(z) = b + A z (modal analysis, PCA).

    Args:
        basis: A [configuration unit per unit z], shape [n, d].
        offset: b [configuration unit], shape [n].
        metadata: JSON-able description (scene, fingerprint, method parameters).
    """

    kind = "linear"

    def forward(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """Configurations q [..., n] from latents z [..., d]."""
        return self.affine(z, cond)

    @classmethod
    def zeros(cls, n: int, d: int, dtype: torch.dtype, metadata: dict[str, Any]) -> LinearSubspace:
        return cls(torch.zeros(n, d, dtype=dtype), torch.zeros(n, dtype=dtype), metadata)


class QuadraticSubspace(_PolynomialMap):
    """The quadratic map f(z) = b + A z + 1/2 sum_{i<=j} c_ij z_i z_j Psi_ij (modal derivatives).

    c_ij is the multiplicity of the pair in the symmetric double sum (1 for i = j, 2 for i < j),
    so f is the second-order Taylor polynomial with d^2 f / dz_i dz_j = Psi_ij (Barbič & James 2005).

    Args:
        basis: A, shape [n, d].
        offset: b, shape [n].
        quadratic: The Psi_ij as columns, shape [n, d(d+1)/2], pairs (i, j), i <= j, in row-major
            order (``torch.triu_indices(d, d)``).
        metadata: JSON-able description.
    """

    kind = "quadratic"

    def __init__(
        self, basis: Tensor, offset: Tensor, quadratic: Tensor, metadata: dict[str, Any] | None = None
    ) -> None:
        super().__init__(basis, offset, metadata)
        n, d = basis.shape
        if quadratic.shape != (n, d * (d + 1) // 2):
            raise ValueError(f"quadratic must have shape [{n}, {d * (d + 1) // 2}], got {tuple(quadratic.shape)}")
        self.register_buffer("quadratic", quadratic.detach().clone().to(basis.dtype))
        pairs = torch.triu_indices(d, d)
        self.register_buffer("pairs", pairs, persistent=False)
        self.register_buffer("pair_weight", torch.where(pairs[0] == pairs[1], 0.5, 1.0).to(basis.dtype), False)

    def monomials(self, z: Tensor) -> Tensor:
        """The weights 1/2 c_ij z_i z_j of the Psi_ij, shape [..., d(d+1)/2]."""
        return self.pair_weight * z[..., self.pairs[0]] * z[..., self.pairs[1]]

    def forward(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """Configurations q [..., n] from latents z [..., d]."""
        return self.affine(z, cond) + self.monomials(z) @ self.quadratic.T

    @classmethod
    def zeros(cls, n: int, d: int, dtype: torch.dtype, metadata: dict[str, Any]) -> QuadraticSubspace:
        zeros = torch.zeros(n, d * (d + 1) // 2, dtype=dtype)
        return cls(torch.zeros(n, d, dtype=dtype), torch.zeros(n, dtype=dtype), zeros, metadata)
