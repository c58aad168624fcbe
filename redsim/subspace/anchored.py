"""The anchored map: a fixed polynomial map plus an MLP that only adds terms of order |z|^3 and higher.

    f(z[, c]) = W r(z, c) + A z + Q m(z) + b,
    r(z, c)   = h(z, c) - h(0, c*) - Jh(0, c*) z - 1/2 Hh(0, c*)[z, z],

with b + A z + Q m(z) a :class:`redsim.subspace.QuadraticSubspace` (modal derivatives, Barbič & James
2005: b the rest state, A = sigma Phi, Q = the sigma^2 Psi_ij, m(z) its monomials 1/2 c_ij z_i z_j),
h [..., w] the MLP's last hidden layer (the architecture of :class:`redsim.subspace.SubspaceMap`) and W
[n, w] its output weights (no output bias). r is h minus its Taylor polynomial at z = 0 (of ``order``
1 or 2), so near z = 0 the map is the polynomial map to that order, exactly, whatever the MLP's
weights: the MLP only adds what the fit's loss asks for further out. c* is c itself (``anchor_cond``
None: the Taylor polynomial is taken at (0, c) for each condition) or one fixed condition (then at other
conditions h(0, c) - h(0, c*) lets the map move its rest state). The Taylor coefficients come from a
second-order jet pushed through the hidden layers (:func:`hidden_jet`), differentiable in the weights.

With a ``radius`` R > 0 the polynomial's terms fade out beyond R: A z + Q m(z) becomes (A z + Q m(z)) g(z),
g(z) = exp(-|z|^2 / (2 R^2)) = 1 - |z|^2 / (2 R^2) + ..., which leaves the map's Taylor polynomial to second order
unchanged (the cubic term changes) and lets the MLP alone shape the map far out, where the polynomial's large
motions cost much energy (modal derivatives stretch cloth and bars by orders of magnitude at the sigma of a fit).

f stays affine in the features [r, z g(z), m(z) g(z)] with output weight [W, A, Q] and bias b
(:meth:`AnchoredSubspace.affine_features`), which is what :class:`redsim.cubature.output.AffineOutput` needs.
Checkpoints have kind "anchored".
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from redsim.subspace.base import dtype_name
from redsim.subspace.checkpoint import write_checkpoint
from redsim.subspace.linear import QuadraticSubspace
from redsim.subspace.neural import SubspaceConfig, SubspaceMap

ORDERS = (1, 2)
"""Orders of the Taylor polynomial the MLP's hidden layer is stripped of."""


def _activation_derivatives(act: nn.Module, v: Tensor) -> tuple[Tensor, Tensor]:
    """sigma'(v) and sigma''(v) of one of the activations of :data:`redsim.subspace.ACTIVATIONS`, elementwise."""
    if isinstance(act, nn.ELU):
        neg = act.alpha * torch.exp(torch.clamp(v, max=0.0))
        return torch.where(v > 0, torch.ones_like(v), neg), torch.where(v > 0, torch.zeros_like(v), neg)
    if isinstance(act, nn.Tanh):
        t = torch.tanh(v)
        return 1 - t**2, -2 * t * (1 - t**2)
    if isinstance(act, nn.SiLU):
        s = torch.sigmoid(v)
        return s * (1 + v * (1 - s)), s * (1 - s) * (2 + v * (1 - 2 * s))
    if isinstance(act, nn.ReLU):
        return (v > 0).to(v), torch.zeros_like(v)
    raise ValueError(f"no derivatives for activation {type(act).__name__}")


def hidden_jet(net: SubspaceMap, cond: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """Value, Jacobian and Hessian in z of the last hidden layer h(z, c) at z = 0.

    Args:
        net: A map without periodic latents.
        cond: Conditions [K, m] (None for a map without condition input: K = 1).

    Returns:
        h [K, w], dh/dz [K, w, d], d^2h/dz^2 [K, w, d, d] (differentiable in the weights).
    """
    layers = list(net.mlp)[:-1]
    d = net.latent_dim
    first = layers[0]
    z = torch.zeros(1 if cond is None else cond.shape[0], d, dtype=first.weight.dtype, device=first.weight.device)
    value = first(net.features(z, cond))
    jac = first.weight[:, :d].expand(z.shape[0], -1, -1)  # [K, w, d]
    hess = torch.zeros(*jac.shape, d, dtype=jac.dtype, device=jac.device)
    for index in range(1, len(layers), 2):
        act, linear = layers[index], layers[index + 1] if index + 1 < len(layers) else None
        slope, curve = _activation_derivatives(act, value)
        hess = slope[..., None, None] * hess + curve[..., None, None] * jac[..., :, None] * jac[..., None, :]
        jac = slope[..., None] * jac
        value = act(value)
        if linear is not None:
            value = linear(value)
            jac = torch.einsum("ow,kwd->kod", linear.weight, jac)
            hess = torch.einsum("ow,kwde->kode", linear.weight, hess)
    return value, jac, hess


class AnchoredSubspace(nn.Module):
    """f(z[, c]) = W r(z, c) + A z + Q m(z) + b (module doc).

    Args:
        config: The MLP's architecture (no periodic latents; ``output_dim`` n, ``latent_dim`` d as the polynomial's).
        polynomial: The fixed map b + A z + Q m(z) (copied into buffers); its dtype is the map's.
        order: 2: r has no terms below |z|^3 (f is the polynomial map to second order at z = 0); 1: below |z|^2
            (f is its affine part to first order; the MLP supplies the quadratic term).
        anchor_cond: The condition c* [m] the Taylor polynomial is taken at, or None for c itself (conditional
            maps only; ignored without a condition input).
        radius: R of the taper g (module doc), in units of z; 0: no taper (g = 1).
        metadata: JSON-able description.

    Attributes:
        net: The MLP (its output layer's bias is 0 and frozen: b is the map's only constant).
        polynomial: The fixed quadratic (or, with a zero Q, affine) map.
    """

    kind: ClassVar[str] = "anchored"

    def __init__(
        self,
        config: SubspaceConfig,
        polynomial: QuadraticSubspace,
        order: int = 2,
        anchor_cond: Tensor | None = None,
        radius: float = 0.0,
        metadata: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        if config.periodic:
            raise ValueError("an anchored map takes no periodic latents (its Taylor polynomial is in z)")
        if order not in ORDERS:
            raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
        n, d = polynomial.basis.shape
        if (config.output_dim, config.latent_dim) != (n, d):
            raise ValueError(
                f"the MLP maps d = {config.latent_dim} to n = {config.output_dim}, the polynomial d = {d} to n = {n}"
            )
        if not (math.isfinite(radius) and radius >= 0.0):
            raise ValueError(f"radius must be finite and >= 0 (0: no taper), got {radius!r}")
        if anchor_cond is not None and anchor_cond.shape != (config.condition_dim,):
            raise ValueError(f"anchor_cond must have shape [{config.condition_dim}], got {tuple(anchor_cond.shape)}")
        self.config = config
        self.order = int(order)
        self.radius = float(radius)
        self.net = SubspaceMap(config).to(polynomial.basis.dtype)
        with torch.no_grad():
            self.net.mlp[-1].bias.zero_()
        self.net.mlp[-1].bias.requires_grad_(False)
        self.polynomial = QuadraticSubspace(polynomial.basis, polynomial.offset, polynomial.quadratic)
        self.register_buffer("anchor_cond", None if anchor_cond is None else anchor_cond.detach().clone())
        self.metadata: dict[str, Any] = {**dict(metadata or {}), "kind": self.kind}
        self._jet_cache: tuple[tuple[Any, ...], tuple[Tensor, Tensor, Tensor]] | None = None

    @property
    def latent_dim(self) -> int:
        return self.config.latent_dim

    @property
    def output_weight(self) -> Tensor:
        """W [n, w]: the MLP's output weights."""
        return self.net.mlp[-1].weight

    def hidden(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """h(z, c) [..., w], the MLP's last hidden layer."""
        return self.net.hidden(z, cond)

    def remainder(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """r(z, c) [B, w] for latents z [B, d] (and conditions [B, m]): h minus its Taylor polynomial at z = 0."""
        if z.ndim != 2:
            raise ValueError(f"z must have shape [B, {self.latent_dim}], got {tuple(z.shape)}")
        hidden = self.hidden(z, cond)
        value, jac, pairs = self._taylor(cond, z.shape[0])
        if len(value) == 1:
            taylor = value + z @ jac[0].T
            if self.order == 2:
                taylor = taylor + self.polynomial.monomials(z) @ pairs[0].T
        else:
            taylor = value + torch.einsum("bwd,bd->bw", jac, z)
            if self.order == 2:
                taylor = taylor + torch.einsum("bwp,bp->bw", pairs, self.polynomial.monomials(z))
        return hidden - taylor

    def _taylor(self, cond: Tensor | None, rows: int) -> tuple[Tensor, Tensor, Tensor]:
        """h, dh/dz [K, w, d] and the Hessian's pairs d^2h/dz_i dz_j, i <= j [K, w, d(d+1)/2] at z = 0: K = 1 (no
        condition, or the anchor condition) or ``rows`` (one per condition).

        Without gradients to the weights (a map in use, not in a fit) a single-point jet is kept until a weight
        changes (in-place updates bump a tensor's version; a cast or a move changes its storage).
        """
        if cond is not None and self.anchor_cond is None:
            return self._pair_jet(cond.expand(rows, -1))
        at = None if cond is None else self.anchor_cond[None]
        params = list(self.net.parameters())
        if torch.is_grad_enabled() and any(p.requires_grad for p in params):
            return self._pair_jet(at)
        tensors = [*params, *([] if at is None else [self.anchor_cond])]
        key = tuple((id(t), t._version, t.data_ptr(), t.dtype) for t in tensors)
        if self._jet_cache is None or self._jet_cache[0] != key:
            self._jet_cache = (key, tuple(t.detach() for t in self._pair_jet(at)))
        return self._jet_cache[1]

    def _pair_jet(self, at: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        value, jac, hess = hidden_jet(self.net, at)
        return value, jac, hess[..., self.polynomial.pairs[0], self.polynomial.pairs[1]]

    def taper(self, z: Tensor) -> Tensor:
        """g(z) [B, 1] (module doc): 1 without a radius."""
        if not self.radius:
            return torch.ones_like(z[..., :1])
        return torch.exp(-0.5 * (z * z).sum(-1, keepdim=True) / self.radius**2)

    def affine_features(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """[r(z, c), z g(z), m(z) g(z)] [B, w + d + d(d+1)/2]: f = features @ :meth:`affine_weight`.T + b."""
        taper = self.taper(z)
        return torch.cat([self.remainder(z, cond), z * taper, self.polynomial.monomials(z) * taper], -1)

    def affine_weight(self) -> Tensor:
        """[W, A, Q] [n, w + d + d(d+1)/2]."""
        return torch.cat([self.output_weight, self.polynomial.basis, self.polynomial.quadratic], 1)

    def forward(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """Configurations q [..., n] from latents z [..., d] (and conditions c [..., m])."""
        flat = z.reshape(-1, z.shape[-1])
        flat_cond = None if cond is None else cond.expand(*z.shape[:-1], -1).reshape(flat.shape[0], -1)
        poly = self.polynomial
        near = (flat @ poly.basis.T + poly.monomials(flat) @ poly.quadratic.T) * self.taper(flat)
        q = self.remainder(flat, flat_cond) @ self.output_weight.T + near + poly.offset
        return q.reshape(*z.shape[:-1], -1)

    def shapes(self) -> dict[str, Any]:
        """What :meth:`from_shapes` needs: the MLP's config, the order, whether it has an anchor condition, and the
        dtype (of the polynomial; a fit casts the whole map to one)."""
        return {
            **dataclasses.asdict(self.config),
            "order": self.order,
            "radius": self.radius,
            "anchor_cond": self.anchor_cond is not None,
            "dtype": dtype_name(self.polynomial.basis.dtype),
        }

    @classmethod
    def from_shapes(cls, shapes: dict[str, Any], metadata: dict[str, Any]) -> AnchoredSubspace:
        """An untrained map of these shapes (a checkpoint's ``config``), for loading a state dict."""
        fields = {f.name for f in dataclasses.fields(SubspaceConfig)}
        config = SubspaceConfig(**{k: v for k, v in shapes.items() if k in fields})
        dtype = getattr(torch, shapes["dtype"])
        zeros = QuadraticSubspace.zeros(config.output_dim, config.latent_dim, dtype, {})
        cond = torch.zeros(config.condition_dim, dtype=dtype) if shapes["anchor_cond"] else None
        radius = float(shapes.get("radius", 0.0))
        return cls(config, zeros, int(shapes["order"]), cond, radius, metadata).to(dtype)

    def save(self, stem: str | Path) -> tuple[Path, Path]:
        """Write ``stem.pt`` (weights and polynomial) and ``stem.json`` (shapes and metadata); returns both paths."""
        self.metadata["kind"] = self.kind
        return write_checkpoint(self, stem, self.shapes())
