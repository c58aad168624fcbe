"""The StVK cloth membrane's element energies with a closed-form gradient.

:class:`MembraneEnergy` is a :class:`torch.autograd.Function` of a triangle's nine vertex coordinates (each [B, T])
whose forward builds no graph and whose backward is the analytic gradient, entry by entry: about half the
elementwise ops of autograd through :func:`redsim.effects.elastic.membrane_metric`, and none of its graph nodes.
Under ``create_graph`` (Hessians, modal derivatives) the backward recomputes its terms from the inputs with torch
ops, so it can be differentiated again to any order. (The same approach for the bending hinges was measured and
not kept: README "Env speed".)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor


def _dot(ux: Tensor, uy: Tensor, uz: Tensor, vx: Tensor, vy: Tensor, vz: Tensor) -> Tensor:
    """u . v of 3-vectors given entry by entry."""
    return torch.addcmul(torch.addcmul(ux * vx, uy, vy), uz, vz)


def _combine(*pairs: tuple[Tensor, Tensor]) -> Tensor:
    """sum_i c_i v_i of (coefficient, value) pairs."""
    (c, v), *rest = pairs
    out = c * v
    for c, v in rest:
        out = torch.addcmul(out, c, v)
    return out


def _vertex_gradients(edges: Sequence[Tensor]) -> list[Tensor]:
    """Gradients of vertices (0, 1, ..., k) from those of the k edges x_j - x_0, each 3 entries."""
    first = []
    for i in range(3):
        total = edges[i]
        for j in range(3 + i, len(edges), 3):
            total = total + edges[j]
        first.append(-total)
    return [*first, *edges]


# -- StVK membrane ----------------------------------------------------------------------------------


def membrane_coefficients(shape_gradients: Tensor) -> Tensor:
    """P [T, 9]: C = F^T F as (C_00, C_11, C_01) = P (s11, s12, s22), P row-major 3x3 per element.

    s = (a . a, a . b, b . b) of the edges a = x1 - x0, b = x2 - x0; D_m^-1 = ``shape_gradients[:, 1:]`` [T, 2, 2].
    """
    m = shape_gradients[:, 1:, :]
    m00, m01, m10, m11 = m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1]
    rows = [
        (m00 * m00, 2.0 * m00 * m10, m10 * m10),
        (m01 * m01, 2.0 * m01 * m11, m11 * m11),
        (m00 * m01, m00 * m11 + m10 * m01, m10 * m11),
    ]
    return torch.stack([c for row in rows for c in row], dim=-1)


def _membrane_terms(coords: Sequence[Tensor], p: Sequence[Tensor], mu: Tensor, lam: Tensor) -> tuple[Tensor, ...]:
    """psi [J/m^2] and the terms its gradient reads: (psi, ax, ay, az, bx, by, bz, e00, e11, e01, tr E)."""
    x0, y0, z0, x1, y1, z1, x2, y2, z2 = coords
    ax, ay, az, bx, by, bz = x1 - x0, y1 - y0, z1 - z0, x2 - x0, y2 - y0, z2 - z0
    s11, s12, s22 = _dot(ax, ay, az, ax, ay, az), _dot(ax, ay, az, bx, by, bz), _dot(bx, by, bz, bx, by, bz)
    c00, c11, c01 = (_combine((p[3 * r], s11), (p[3 * r + 1], s12), (p[3 * r + 2], s22)) for r in range(3))
    e00, e11, e01 = 0.5 * (c00 - 1.0), 0.5 * (c11 - 1.0), 0.5 * c01  # Green strain E = (C - I) / 2
    trace = e00 + e11
    square = torch.addcmul(torch.addcmul(e00 * e00, e11, e11), e01, e01, value=2.0)
    psi = torch.addcmul(mu * square, 0.5 * lam, trace * trace)
    return psi, ax, ay, az, bx, by, bz, e00, e11, e01, trace


def _membrane_gradient(terms: Sequence[Tensor], p: Sequence[Tensor], mu: Tensor, lam: Tensor, scale: Tensor) -> list:
    """d(scale * psi) / d coordinates (9 tensors) from :func:`_membrane_terms`."""
    _, ax, ay, az, bx, by, bz, e00, e11, e01, trace = terms
    half_lam_tr = 0.5 * lam * trace
    g00 = scale * torch.addcmul(half_lam_tr, mu, e00)  # d psi / d C_00
    g11 = scale * torch.addcmul(half_lam_tr, mu, e11)
    g01 = scale * (2.0 * mu * e01)
    d11, d12, d22 = (_combine((p[c], g00), (p[3 + c], g11), (p[6 + c], g01)) for c in range(3))  # d psi / d s
    a2, b2 = 2.0 * d11, 2.0 * d22
    grad_a = [torch.addcmul(a2 * u, d12, v) for u, v in ((ax, bx), (ay, by), (az, bz))]
    grad_b = [torch.addcmul(b2 * v, d12, u) for u, v in ((ax, bx), (ay, by), (az, bz))]
    return _vertex_gradients(grad_a + grad_b)


class MembraneEnergy(torch.autograd.Function):
    """StVK membrane energies [J], [B, T]: ``apply(coefficients, mu, lam, area, *coords)``.

    ``coefficients`` P^T [9, T] (:func:`membrane_coefficients`, transposed), mu and lam [J/m^2] (thickness
    included) and rest area [m^2], each [T], are constants (no gradient); ``coords`` = (x0, y0, z0, x1, ..., z2),
    each [B, T].
    """

    @staticmethod
    def forward(ctx: Any, coefficients: Tensor, mu: Tensor, lam: Tensor, area: Tensor, *coords: Tensor) -> Tensor:
        if any(ctx.needs_input_grad[:4]):
            raise ValueError("MembraneEnergy has no gradient with respect to its material constants")
        p = coefficients.unbind(0)
        terms = _membrane_terms(coords, p, mu, lam)
        ctx.save_for_backward(coefficients, mu, lam, area, *coords, *terms)
        return terms[0] * area

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        coefficients, mu, lam, area, *saved = ctx.saved_tensors
        coords, terms = saved[:9], saved[9:]
        p = coefficients.unbind(0)
        if torch.is_grad_enabled():  # create_graph: rebuild the terms as a graph of the coordinates
            terms = _membrane_terms(coords, p, mu, lam)
        return None, None, None, None, *_membrane_gradient(terms, p, mu, lam, grad * area)
