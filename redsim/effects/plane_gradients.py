"""2D stable neo-Hookean element energies with a closed-form gradient.

:class:`PlaneNeoHookeanEnergy` is a :class:`torch.autograd.Function` of a triangle's six vertex coordinates (each
[B, T]) whose forward builds no graph and whose backward is the analytic gradient, entry by entry. With the edge
matrix D_s = [[a, b], [c, d]] = [x1 - x0, x2 - x0] and K = D_m^-1 D_m^-T, tr(F^T F) = tr(D_s^T D_s K) and
det F = det D_s / det D_m, so

    E = A (tr(D_s^T D_s K) - 2) + B/2 (det D_s - beta)^2 - C,   dE/dD_s = 2A D_s K + B (det D_s - beta) cof D_s,

with the per-element constants A = mu V/2, B = (lam + mu) V / det(D_m)^2, beta = alpha det D_m and
C = mu^2 V / (2 (lam + mu)) (:func:`plane_constants`; V the rest area times thickness). D_s K is kept from the
forward for the backward. Energy and gradient of conditional_bar's elastic term take 64 aten ops (gathers
included) against 125 by autograd through psi of :func:`redsim.effects.elastic._plane_invariants`, and 1.6-1.9x less
CPU time at B = 2 to 64 (float32, its cubature's 200 and all 846 triangles, an interleaved A/B); RedSim/
ConditionalBar-v1 steps 1.08x faster (64 envs). Under ``create_graph`` (Hessians) the backward recomputes its terms
from the inputs with torch ops, so it can be differentiated again to any order.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from redsim.effects.base import edge_vectors


def plane_constants(shape_gradients: Tensor, mu: Tensor, lam: Tensor, volume: Tensor) -> tuple[Tensor, ...]:
    """(K_00, K_01, K_11, -beta, A, 2A, B, -C), each [T] and contiguous (module doc for the symbols).

    From the shape gradients [T, 3, 2] (D_m^-1 = ``shape_gradients[:, 1:]``), Lamé parameters mu and lam [Pa] and
    rest volumes V [m^3] (area times thickness), each [T].
    """
    m = shape_gradients[:, 1:, :]
    k = m @ m.transpose(-1, -2)
    inv_det = torch.linalg.det(m)  # 1 / det D_m
    lam_s = lam + mu
    alpha = 1.0 + mu / lam_s
    shear = 0.5 * mu * volume
    constants = (
        k[:, 0, 0],
        k[:, 0, 1],
        k[:, 1, 1],
        -alpha / inv_det,
        shear,
        2.0 * shear,
        lam_s * volume * inv_det * inv_det,
        -0.5 * mu * mu / lam_s * volume,
    )
    return tuple(c.contiguous() for c in constants)


def _terms(entries: Sequence[Tensor], constants: Sequence[Tensor]) -> tuple[Tensor, ...]:
    """Energies E [J] and what the gradient reads: (E, a, b, c, d, (D_s K)_00, _01, _10, _11, B (det D_s - beta)), of
    the six vertex coordinates or the four edge entries (x1 - x0, y1 - y0, x2 - x0, y2 - y0) = (a, c, b, d)."""
    k00, k01, k11, neg_beta, shear, _, bulk, neg_offset = constants
    a, c, b, d = entries if len(entries) == 4 else edge_vectors(entries, 2)
    u00, u01 = torch.addcmul(a * k00, b, k01), torch.addcmul(a * k01, b, k11)
    u10, u11 = torch.addcmul(c * k00, d, k01), torch.addcmul(c * k01, d, k11)
    stretch = torch.addcmul(torch.addcmul(torch.addcmul(a * u00 - 2.0, b, u01), c, u10), d, u11)  # tr F^T F - 2
    volume = torch.addcmul(torch.addcmul(neg_beta, a, d), b, c, value=-1.0)  # det D_s - beta
    q = bulk * volume
    energy = torch.addcmul(torch.addcmul(neg_offset, shear, stretch), q, volume, value=0.5)
    return energy, a, b, c, d, u00, u01, u10, u11, q


def _gradient(terms: Sequence[Tensor], shear2: Tensor, grad: Tensor, vertices: bool = True) -> list[Tensor]:
    """d(grad * E) / d coordinates (six tensors; ``vertices`` False: d / d edge entries, four) from :func:`_terms`;
    ``grad`` [B, T]."""
    _, a, b, c, d, u00, u01, u10, u11, q = terms
    t, s = grad * shear2, grad * q
    da, db = torch.addcmul(t * u00, s, d), torch.addcmul(t * u01, s, c, value=-1.0)
    dc, dd = torch.addcmul(t * u10, s, b, value=-1.0), torch.addcmul(t * u11, s, a)
    return [-(da + db), -(dc + dd), da, dc, db, dd] if vertices else [da, dc, db, dd]


class PlaneNeoHookeanEnergy(torch.autograd.Function):
    """Stable neo-Hookean energies [J], [B, T], of 2D triangles: ``apply(constants, scale, *coords)``.

    ``constants`` is :func:`plane_constants`' tuple (no gradient); ``scale`` a per-element modulus factor [B, T]
    (differentiable) or None; ``coords`` = (x0, y0, x1, y1, x2, y2) or the four edge entries (x1 - x0, y1 - y0,
    x2 - x0, y2 - y0), each [B, T] (the gradient is with respect to what was given).
    """

    @staticmethod
    def forward(ctx: Any, constants: tuple[Tensor, ...], scale: Tensor | None, *coords: Tensor) -> Tensor:
        if any(c.requires_grad for c in constants):
            raise ValueError("PlaneNeoHookeanEnergy has no gradient with respect to its material constants")
        if len(coords) not in (4, 6):
            raise ValueError(f"PlaneNeoHookeanEnergy takes 6 vertex coordinates or 4 edge entries, got {len(coords)}")
        terms = _terms(coords, constants)
        ctx.constants = constants
        ctx.save_for_backward(scale, *coords, *terms)
        return terms[0] if scale is None else terms[0] * scale

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        scale, *saved = ctx.saved_tensors
        count = len(saved) - 10  # the entries given, then the 10 terms
        coords, terms = saved[:count], saved[count:]
        if torch.is_grad_enabled():  # create_graph: rebuild the terms as a graph of the coordinates
            terms = _terms(coords, ctx.constants)
        grad_scale = grad * terms[0] if ctx.needs_input_grad[1] else None
        if scale is not None:
            grad = grad * scale
        return None, grad_scale, *_gradient(terms, ctx.constants[5], grad, vertices=count == 6)
