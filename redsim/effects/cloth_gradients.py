"""The cloth's element energies (StVK membrane, discrete-shell bending) with closed-form gradients.

:class:`MembraneEnergy` and :class:`HingeEnergy` are :class:`torch.autograd.Function` s of an element's vertex
coordinates (each [B, T]) whose forward builds no graph and whose backward is the analytic gradient, entry by entry:
fewer elementwise ops than autograd through the plain formulas (:func:`redsim.effects.elastic.membrane_metric`,
:func:`hinge_parts`; a hinge's 81 against 124, most of them in place), and none of their graph nodes. The hinge's
backward is the chain rule through the very expressions its forward evaluates (atan2 of the triple-product sine and
the normals' cosine), so it is as accurate as autograd's in float32; a textbook gradient of the dihedral angle from
the normals and the heights was measured before and not kept, 3x less accurate near flat hinges, and one writing a
fresh tensor per op was slower than autograd on whole sheets at B >= 16 (docs/env-speed.md, "Stop 49"). Under
``create_graph`` (Hessians, modal derivatives) the membrane's backward recomputes its terms from the inputs with torch
ops and the hinges' is autograd of their plain formula, so either can be differentiated again to any order.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from redsim.effects.base import edge_vectors


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


def _membrane_terms(entries: Sequence[Tensor], p: Sequence[Tensor], mu: Tensor, lam: Tensor) -> tuple[Tensor, ...]:
    """psi [J/m^2] and the terms its gradient reads: (psi, ax, ay, az, bx, by, bz, e00, e11, e01, tr E), of the
    nine vertex coordinates or the six edge entries (a, b) = (x1 - x0, x2 - x0) (:class:`MembraneEnergy`)."""
    ax, ay, az, bx, by, bz = entries if len(entries) == 6 else edge_vectors(entries)
    s11, s12, s22 = _dot(ax, ay, az, ax, ay, az), _dot(ax, ay, az, bx, by, bz), _dot(bx, by, bz, bx, by, bz)
    c00, c11, c01 = (_combine((p[3 * r], s11), (p[3 * r + 1], s12), (p[3 * r + 2], s22)) for r in range(3))
    e00, e11, e01 = 0.5 * (c00 - 1.0), 0.5 * (c11 - 1.0), 0.5 * c01  # Green strain E = (C - I) / 2
    trace = e00 + e11
    square = torch.addcmul(torch.addcmul(e00 * e00, e11, e11), e01, e01, value=2.0)
    psi = torch.addcmul(mu * square, 0.5 * lam, trace * trace)
    return psi, ax, ay, az, bx, by, bz, e00, e11, e01, trace


def _membrane_gradient(terms: Sequence[Tensor], p: Sequence[Tensor], mu: Tensor, lam: Tensor, scale: Tensor) -> list:
    """d(scale * psi) / d edges (a, b) (6 tensors) from :func:`_membrane_terms`."""
    _, ax, ay, az, bx, by, bz, e00, e11, e01, trace = terms
    half_lam_tr = 0.5 * lam * trace
    g00 = scale * torch.addcmul(half_lam_tr, mu, e00)  # d psi / d C_00
    g11 = scale * torch.addcmul(half_lam_tr, mu, e11)
    g01 = scale * (2.0 * mu * e01)
    d11, d12, d22 = (_combine((p[c], g00), (p[3 + c], g11), (p[6 + c], g01)) for c in range(3))  # d psi / d s
    a2, b2 = 2.0 * d11, 2.0 * d22
    grad_a = [torch.addcmul(a2 * u, d12, v) for u, v in ((ax, bx), (ay, by), (az, bz))]
    grad_b = [torch.addcmul(b2 * v, d12, u) for u, v in ((ax, bx), (ay, by), (az, bz))]
    return grad_a + grad_b


class MembraneEnergy(torch.autograd.Function):
    """StVK membrane energies [J], [B, T]: ``apply(coefficients, mu, lam, area, *entries)``.

    ``coefficients`` P^T [9, T] (:func:`membrane_coefficients`, transposed), mu and lam [J/m^2] (thickness
    included) and rest area [m^2], each [T], are constants (no gradient); ``entries`` are the nine vertex
    coordinates (x0, y0, z0, x1, ..., z2) or the six edge entries (ax, ay, az, bx, by, bz) = (x1 - x0, x2 - x0)
    (a cubature computes those straight from its features, :class:`redsim.cubature.energy.CubatureEnergy`), each
    [B, T]; the gradient is with respect to what was given.
    """

    @staticmethod
    def forward(ctx: Any, coefficients: Tensor, mu: Tensor, lam: Tensor, area: Tensor, *entries: Tensor) -> Tensor:
        if any(ctx.needs_input_grad[:4]):
            raise ValueError("MembraneEnergy has no gradient with respect to its material constants")
        if len(entries) not in (6, 9):
            raise ValueError(f"MembraneEnergy takes 9 vertex coordinates or 6 edge entries, got {len(entries)}")
        p = coefficients.unbind(0)
        terms = _membrane_terms(entries, p, mu, lam)
        ctx.save_for_backward(coefficients, mu, lam, area, *entries, *terms)
        return terms[0] * area

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        coefficients, mu, lam, area, *saved = ctx.saved_tensors
        count = len(saved) - 11  # the entries given, then the 11 terms
        entries, terms = saved[:count], saved[count:]
        p = coefficients.unbind(0)
        if torch.is_grad_enabled():  # create_graph: rebuild the terms as a graph of the entries
            terms = _membrane_terms(entries, p, mu, lam)
        edges = _membrane_gradient(terms, p, mu, lam, grad * area)
        return None, None, None, None, *(edges if count == 6 else _vertex_gradients(edges))


# -- discrete-shell bending ---------------------------------------------------------------------------


def _cross(u: Sequence[Tensor], v: Sequence[Tensor]) -> list[Tensor]:
    """u x v of 3-vectors given entry by entry (each entry one product, then a fused multiply-subtract in place)."""
    ux, uy, uz = u
    vx, vy, vz = v
    return [
        torch.mul(uy, vz).addcmul_(uz, vy, value=-1.0),
        torch.mul(uz, vx).addcmul_(ux, vz, value=-1.0),
        torch.mul(ux, vy).addcmul_(uy, vx, value=-1.0),
    ]


def hinge_parts(coords: Sequence[Tensor], length_eps: float) -> tuple[Tensor, ...]:
    """The signed dihedral angle theta [rad] of hinges and the terms its gradient reads:
    (theta, ex, ey, ez, ax, ay, az, bx, by, bz, nax, nay, naz, nbx, nby, nbz, cos, sin, edge_sq, u, length, m).

    ``coords`` = (x0, y0, z0, ..., x3, y3, z3), each [B, E] (any one shape), or the nine edge entries (ex, ey, ez,
    ax, ..., bz) defined next (they are all it reads). The hinge's shared edge is x0-x1, its
    triangles (x0, x1, x2) and (x1, x0, x3). With e = x1 - x0, a = x2 - x0, b = x3 - x0 and the normals
    n_a = e x a, n_b = b x e: cos ~ n_a . n_b and sin ~ (n_a x n_b) . e / |e| = -|e|^2 (n_a . b) / |e|
    ((e x a) x (b x e) = -((e x a) . b) e), entry by entry: elementwise products of the coordinates instead of
    [..., 3] cross products (their stacks and strided views cost 2.6-3.3x more CPU time at B >= 16, forward and
    backward). ``length_eps`` [m^2] keeps |e| = length = edge_sq u, u = 1 / sqrt(edge_sq + eps), positive; m = n_a . b.
    """
    ex, ey, ez, ax, ay, az, bx, by, bz = coords if len(coords) == 9 else edge_vectors(coords)
    nax, nay, naz = ey * az - ez * ay, ez * ax - ex * az, ex * ay - ey * ax  # n_a = e x a
    nbx, nby, nbz = by * ez - bz * ey, bz * ex - bx * ez, bx * ey - by * ex  # n_b = b x e
    cos = nax * nbx + nay * nby + naz * nbz
    edge_sq = ex * ex + ey * ey + ez * ez
    u = torch.rsqrt(edge_sq + length_eps)
    length = edge_sq * u
    m = nax * bx + nay * by + naz * bz
    sin = -length * m
    theta = torch.atan2(sin, cos)
    return (theta, ex, ey, ez, ax, ay, az, bx, by, bz, nax, nay, naz, nbx, nby, nbz, cos, sin, edge_sq, u, length, m)


def _hinge_gradient(parts: Sequence[Tensor], g_theta: Tensor, vertices: bool = True) -> list[Tensor]:
    """d(theta) / d coordinates (12 tensors; ``vertices`` False: d / d edges (e, a, b), 9) times ``g_theta`` [B, E],
    from :func:`hinge_parts`.

    With k = -g_theta / (sin^2 + cos^2) (atan2's derivative, sign folded in; 0 where sin = cos = 0, a collapsed
    hinge, as torch's atan2 backward), P = k cos and Q = k sin, and
    h = P length b + Q n_b (the gradient at n_a), the chain rule through the forward's expressions gives
    d/db = P length n_a + Q (e x n_a), d/da = h x e,
    d/de = 2 P m (u - edge_sq u^3 / 2) e + a x h + Q (n_a x b), and d/dx0 = -(d/de + d/da + d/db).
    """
    _, ex, ey, ez, ax, ay, az, bx, by, bz, nax, nay, naz, nbx, nby, nbz, cos, sin, edge_sq, u, length, m = parts
    e, a, b, n_a = (ex, ey, ez), (ax, ay, az), (bx, by, bz), (nax, nay, naz)
    # every product below is a fresh tensor, so the sums accumulate into it in place: one allocation per entry
    radius_sq = torch.mul(sin, sin).addcmul_(cos, cos)
    k = radius_sq.reciprocal().masked_fill_(radius_sq == 0.0, 0.0).mul_(g_theta).neg_()  # 0 at (0, 0), as autograd
    p, q = k * cos, k.mul_(sin)
    p_length = p * length
    h = [torch.mul(p_length, bi).addcmul_(q, ni) for bi, ni in zip(b, (nbx, nby, nbz), strict=True)]
    e_na = _cross(e, n_a)
    grad_b = [ci.mul_(q).addcmul_(p_length, ni) for ni, ci in zip(n_a, e_na, strict=True)]
    grad_a = _cross(h, e)
    dlength = torch.mul(edge_sq, u).mul_(u).mul_(u).mul_(-0.5).add_(u)  # d length / d edge_sq
    pe = dlength.mul_(m).mul_(p).mul_(2.0)
    na_b = _cross(n_a, b)
    grad_e = [ahi.addcmul_(q, ci).addcmul_(pe, ei) for ahi, ci, ei in zip(_cross(a, h), na_b, e, strict=True)]
    if not vertices:
        return [*grad_e, *grad_a, *grad_b]
    grad_0 = [torch.add(ge, ga).add_(gb).neg_() for ge, ga, gb in zip(grad_e, grad_a, grad_b, strict=True)]
    return [*grad_0, *grad_e, *grad_a, *grad_b]


HINGE_CLOSED_FORM_ENTRIES = 65536
"""The most entries [B x E] of one coordinate tensor for which :func:`hinge_energies` takes :class:`HingeEnergy`'s
closed-form gradient; above, autograd through the plain formula. The closed form's terms all stay alive to the end of
its backward, while autograd consumes each as it goes: inside a whole sheet's energy (5851 hinges beside the
membrane's terms) the closed form took 1.1-1.25x autograd's time at B = 16 and 64 (`redsim bench energy`), while on a
cubature's 500 hinges it took 0.79-0.89x from B = 1 to 256 and on the whole sheet at B = 1 0.89x (the term alone;
docs/env-speed.md, "Stop 49")."""


def hinge_energies(weight: Tensor, rest_angle: Tensor, length_eps: float, coords: Sequence[Tensor]) -> Tensor:
    """Discrete-shell bending energies [J], [B, E], weight * (theta - rest_angle)^2 per hinge, of the twelve vertex
    coordinates or the nine edge entries (each [B, E]; :func:`hinge_parts`): through :class:`HingeEnergy` up to
    :data:`HINGE_CLOSED_FORM_ENTRIES` entries per coordinate, else by autograd of the same formula."""
    if coords[0].numel() > HINGE_CLOSED_FORM_ENTRIES:
        return weight * (hinge_parts(coords, length_eps)[0] - rest_angle) ** 2
    return HingeEnergy.apply(weight, rest_angle, length_eps, *coords)


class HingeEnergy(torch.autograd.Function):
    """Discrete-shell bending energies [J], [B, E]: ``apply(weight, rest_angle, length_eps, *coords)``,
    weight * (theta - rest_angle)^2 per hinge.

    ``weight`` [J] and ``rest_angle`` [rad], each [E], are constants (no gradient), ``length_eps`` [m^2] a float
    (:func:`hinge_parts`); ``coords`` = (x0, y0, z0, ..., x3, y3, z3) or the nine edge entries, each [B, E]
    (the gradient is with respect to what was given). The backward is
    :func:`_hinge_gradient` (in place on its own fresh tensors); under ``create_graph`` (Hessians) it is autograd
    of the plain formula through :func:`hinge_parts` instead, differentiable to any order.
    """

    @staticmethod
    def forward(ctx: Any, weight: Tensor, rest_angle: Tensor, length_eps: float, *coords: Tensor) -> Tensor:
        if any(ctx.needs_input_grad[:2]):
            raise ValueError("HingeEnergy has no gradient with respect to its weights and rest angles")
        if len(coords) not in (9, 12):
            raise ValueError(f"HingeEnergy takes 12 vertex coordinates or 9 edge entries, got {len(coords)}")
        parts = hinge_parts(coords, length_eps)
        deviation = parts[0] - rest_angle
        ctx.length_eps = length_eps
        ctx.save_for_backward(weight, rest_angle, deviation, *coords, *parts)
        return weight * deviation**2

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        weight, rest_angle, deviation, *saved = ctx.saved_tensors
        count = len(saved) - 22  # the entries given, then hinge_parts' 22 terms
        coords, parts = saved[:count], saved[count:]
        if torch.is_grad_enabled():  # create_graph: autograd through the plain formula, a graph of the inputs
            energy = weight * (hinge_parts(coords, ctx.length_eps)[0] - rest_angle) ** 2
            needs = ctx.needs_input_grad[3:]  # a coordinate without a gradient gets None (autograd.grad refuses it)
            inputs = [c for c, need in zip(coords, needs, strict=True) if need]
            wanted = iter(torch.autograd.grad(energy, inputs, grad, create_graph=True))
            return None, None, None, *(next(wanted) if need else None for need in needs)
        return None, None, None, *_hinge_gradient(parts, (2.0 * grad) * weight * deviation, vertices=count == 12)
