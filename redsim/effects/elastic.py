"""Elastic energies of meshes: stable neo-Hookean FEM, StVK cloth membrane, discrete-shell bending."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
from torch import Tensor

from redsim.effects.base import Effect, gather_coordinates, gather_elements, per_element
from redsim.effects.cloth_gradients import MembraneEnergy, hinge_energies, hinge_parts, membrane_coefficients
from redsim.effects.plane_gradients import PlaneNeoHookeanEnergy, plane_constants
from redsim.materials import lame_from_young_poisson


def _lame(
    young: float | Tensor, poisson: float | Tensor, count: int, plane: Literal["strain", "stress"] | None
) -> tuple[Tensor, Tensor]:
    """Lamé parameters (mu, lambda) [Pa], each [count], of per-element (scalar or [count]) young [Pa] and poisson."""
    young_t = per_element(young, count, "young", sign="positive")
    poisson_t = per_element(poisson, count, "poisson", sign="any")
    return lame_from_young_poisson(young_t, poisson_t, plane=plane)


def _check_rest(rest: Tensor, name: str) -> None:
    """Refuse rest positions [T, nv, D] with a NaN or infinite coordinate (naming the element)."""
    bad = torch.nonzero(~torch.isfinite(rest).reshape(rest.shape[0], -1).all(-1)).reshape(-1)
    if bad.numel():
        i = int(bad[0])
        raise ValueError(f"rest positions of {name!r} must be finite, got {rest[i].tolist()} for element {i}")


def _vertex_dofs(vertex_dofs: Tensor, rest: Tensor, name: str) -> Tensor:
    """``vertex_dofs`` as int64 [T, nv * D]: one index per coordinate of ``rest`` [T, nv, D] (or already flat).

    Raises:
        ValueError: its shape is neither [T, nv, D] nor [T, nv * D].
    """
    dofs = torch.as_tensor(vertex_dofs, dtype=torch.int64)
    T, nv, D = rest.shape
    if tuple(dofs.shape) not in ((T, nv, D), (T, nv * D)):
        raise ValueError(
            f"vertex_dofs of {name!r} must have shape [{T}, {nv}, {D}] (one index per coordinate of rest "
            f"{list(rest.shape)}), got {list(dofs.shape)}"
        )
    return dofs.reshape(T, nv * D)


def _edge_matrix(v: Tensor) -> Tensor:
    """Columns v[j+1] - v[0]: [..., D+1, D] -> [..., D, D]."""
    return (v[..., 1:, :] - v[..., :1, :]).transpose(-1, -2)


def _shape_gradients(rest_inverse: Tensor) -> Tensor:
    """Gradients of the linear shape functions, shape [T, D+1, D'] from D_m^-1 [T, D, D'].

    F = D_s D_m^-1 = sum_v x_v (x) G_v, a sum over the element's vertices.
    """
    return torch.cat([-rest_inverse.sum(-2, keepdim=True), rest_inverse], dim=-2)


def deformation_gradient(vertices: Tensor, shape_gradients: Tensor) -> Tensor:
    """F [B, T, D, D'] from element vertices [B, T, D+1, D] and shape gradients [T, D+1, D'].

    A broadcast matmul: on the CPU it is about 2.5x faster than the equivalent einsum, which
    permutes its operands into copies first (stiff_body, B = 32, float32, forward + backward).
    """
    return vertices.transpose(-1, -2) @ shape_gradients


def _det(F: Tensor) -> Tensor:
    """Determinant of 2x2 or 3x3 matrices [..., D, D] by the explicit formula."""
    if F.shape[-1] == 2:
        return F[..., 0, 0] * F[..., 1, 1] - F[..., 0, 1] * F[..., 1, 0]
    return (_cross(F[..., :, 0], F[..., :, 1]) * F[..., :, 2]).sum(-1)


def _cross(a: Tensor, b: Tensor) -> Tensor:
    """Cross product of 3-vectors [..., 3] (elementwise; faster than torch.linalg.cross on small batches)."""
    a0, a1, a2 = a.unbind(-1)
    b0, b1, b2 = b.unbind(-1)
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], dim=-1)


class NeoHookean(Effect):
    """Stable neo-Hookean FEM on linear triangles (2D) or tetrahedra (3D) [Smith et al. 2018].

    psi(F) = mu/2 (tr F^T F - D) + lam'/2 (det F - alpha)^2 - mu^2 / (2 lam'), with
    lam' = lam + mu and alpha = 1 + mu / lam'. It is a polynomial in F, so it is finite and
    smooth for inverted elements, and psi(R) = 0 with zero stress for every rotation R.

    Args:
        name: Term name.
        vertex_dofs: Full-configuration index of each element vertex coordinate,
            shape [T, D+1, D], int64.
        rest: Rest positions [m], shape [T, D+1, D].
        young: Young's modulus [Pa], scalar or shape [T] (heterogeneous materials).
        poisson: Poisson ratio, scalar or shape [T].
        thickness: Out-of-plane thickness [m] of 2D elements (ignored in 3D).
        plane: Plane model of 2D elements, "strain" or "stress".
        condition_scale: Optional (condition index i, element mask [T] bool): masked elements
            have their modulus multiplied by c[i] (conditional stiffness ratio).

    Raises:
        ValueError: on an inverted, degenerate or non-finite rest element (its index is named), ``vertex_dofs`` not
            of shape [T, D+1, D], a non-finite or non-positive modulus or 2D thickness, or a non-finite Poisson ratio.
    """

    kind = "neo_hookean"

    def __init__(
        self,
        name: str,
        vertex_dofs: Tensor,
        rest: Tensor,
        young: float | Tensor,
        poisson: float | Tensor,
        *,
        thickness: float = 1.0,
        plane: Literal["strain", "stress"] = "strain",
        condition_scale: tuple[int, Tensor] | None = None,
    ) -> None:
        rest = torch.as_tensor(rest, dtype=torch.float64)
        T, nv, D = rest.shape
        if nv != D + 1 or D not in (2, 3):
            raise ValueError(f"rest must have shape [T, D+1, D] with D in (2, 3), got {tuple(rest.shape)}")
        _check_rest(rest, name)
        element_dofs = _vertex_dofs(vertex_dofs, rest, name)
        if D == 2:
            per_element(thickness, 1, f"thickness of {name!r}", sign="positive")
        rest_edges = _edge_matrix(rest)
        det = torch.linalg.det(rest_edges)
        volume = det / (2.0 if D == 2 else 6.0)
        scale = rest_edges.abs().amax(dim=(-1, -2)).clamp_min(1e-300) ** D
        bad = torch.nonzero(det <= 1e-12 * scale).reshape(-1)
        if bad.numel():
            i = int(bad[0])
            kind = "inverted" if det[i] < 0 else "degenerate"
            raise ValueError(
                f"element {i} of {name!r} is {kind} (rest volume {float(volume[i]):.3g}); "
                f"{bad.numel()} bad element(s) in all"
            )
        mu, lam = _lame(young, poisson, T, plane if D == 2 else None)
        self.name = name
        self.dim = D
        self.element_dofs = element_dofs
        self.shape_gradients = _shape_gradients(torch.linalg.inv(rest_edges))
        self.rest_volume = volume * (thickness if D == 2 else 1.0)
        self.mu = mu
        self.lam = lam
        if D == 2:  # per-element constants of the closed-form kernel, each [T]
            self.plane_constants = plane_constants(self.shape_gradients, mu, lam, self.rest_volume)
            self.edge_dim = 2  # its kernel also takes the edges (:meth:`edge_energies`)
        self.condition_scale = None
        if condition_scale is not None:
            index, mask = condition_scale
            self.condition_scale = (int(index), torch.as_tensor(mask, dtype=torch.bool).reshape(T))
            self.uses_condition = True

    def element_energy(self, xe: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        if self.dim == 2:
            return self._plane_energies(xe.unbind(-1), cond)
        trace, det = _solid_invariants(xe, self.shape_gradients)
        return self._energy_density(trace, det, cond) * self.rest_volume

    def element_energies(self, x: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        """Energy of every element [J], shape [B, T], at full configurations x [B, N].

        In 2D the six vertex coordinates are gathered as [B, T] tensors (:func:`gather_coordinates`, as
        :meth:`invariants`) into :class:`redsim.effects.plane_gradients.PlaneNeoHookeanEnergy`, whose gradient
        is closed form; in 3D psi of :meth:`invariants`.
        """
        if self.dim == 2:
            return self._plane_energies(gather_coordinates(x, self.element_dofs), cond)
        trace, det = self.invariants(x)
        return self._energy_density(trace, det, cond) * self.rest_volume

    def invariants(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """tr(F^T F) and det F of every element, each [B, T], at full configurations x [B, N].

        In 2D the six vertex coordinates are gathered as [B, T] tensors (:func:`gather_coordinates`; over a
        whole mesh each its own contiguous one: the elementwise kernel then reads no strided views). Against F from
        batched matmuls of xe [B, T, 6]: 2.6x less CPU time for the energy and its gradient at B = 64 and 3.3x
        at B = 256, 0.95x at B = 1 (conditional_bar, float32; docs/env-speed.md, "ConditionalBar-v0: where its
        iterations go").
        """
        if self.dim == 2:
            return _plane_invariants(gather_coordinates(x, self.element_dofs), self.shape_gradients)
        return _solid_invariants(gather_elements(x, self.element_dofs), self.shape_gradients)

    def edge_energies(self, edges: Sequence[Tensor], cond: Tensor | None = None) -> Tensor:
        """Energies [J], [B, T], of 2D triangles from their four edge entries (x1 - x0, y1 - y0, x2 - x0, y2 - y0),
        each [B, T] (F reads only those; a cubature computes them from its features); 3D elements refuse."""
        if self.dim != 2:
            return super().edge_energies(edges, cond)
        return self._plane_energies(edges, cond)

    def _plane_energies(self, coords: Sequence[Tensor], cond: Tensor | None) -> Tensor:
        """Energies [J], [B, T], of triangles from their six vertex coordinates or four edge entries, each [B, T]."""
        return PlaneNeoHookeanEnergy.apply(self.plane_constants, self._scale(cond), *coords)

    def _energy_density(self, trace: Tensor, det: Tensor, cond: Tensor | None) -> Tensor:
        """psi [Pa], [B, T], from tr(F^T F) and det F [B, T] (class doc)."""
        mu, lam = self.mu, self.lam
        lam_s = lam + mu
        alpha = 1.0 + mu / lam_s
        psi = 0.5 * mu * (trace - self.dim) + 0.5 * lam_s * (det - alpha) ** 2 - 0.5 * mu * mu / lam_s
        scale = self._scale(cond)
        return psi if scale is None else psi * scale

    def _scale(self, cond: Tensor | None) -> Tensor | None:
        """The modulus factor [B, T] of ``condition_scale`` (c[i] on masked elements, else 1), or None without one.

        A factor scales mu and lam alike, so alpha stays and psi scales with it.
        """
        if self.condition_scale is None:
            return None
        if cond is None:
            raise ValueError(f"effect {self.name!r} needs a condition vector")
        index, mask = self.condition_scale
        return torch.where(mask, cond[:, index : index + 1], 1.0)


def _solid_invariants(xe: Tensor, shape_gradients: Tensor) -> tuple[Tensor, Tensor]:
    """tr(F^T F) and det F, each [B, T], of tetrahedra xe [B, T, 12] (shape gradients [T, 4, 3])."""
    B, T, _ = xe.shape
    F = deformation_gradient(xe.reshape(B, T, 4, 3), shape_gradients)
    return (F * F).sum((-1, -2)), _det(F)


def _plane_invariants(coords: Sequence[Tensor], shape_gradients: Tensor) -> tuple[Tensor, Tensor]:
    """tr(F^T F) and det F, each [B, T], of 2D triangles from their vertex coordinates (x0, y0, x1, y1, x2, y2).

    Each coordinate is [B, T]; ``shape_gradients`` [T, 3, 2]. F = D_s D_m^-1 with D_s = [x1 - x0, x2 - x0]
    and D_m^-1 = ``shape_gradients[:, 1:]``, entry by entry: elementwise [B, T] products instead of batched
    2x3 by 3x2 matmuls (those cost several times more on the CPU, forward and backward).
    """
    x0, y0, x1, y1, x2, y2 = coords
    a, b, c, d = x1 - x0, x2 - x0, y1 - y0, y2 - y0  # D_s = [[a, b], [c, d]]
    m = shape_gradients[:, 1:, :]
    m00, m01, m10, m11 = m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1]
    f00, f01 = a * m00 + b * m10, a * m01 + b * m11
    f10, f11 = c * m00 + d * m10, c * m01 + d * m11
    return f00 * f00 + f01 * f01 + f10 * f10 + f11 * f11, f00 * f11 - f01 * f10


def _triangle_frame(rest: Tensor) -> Tensor:
    """2x2 rest edge matrices of 3D triangles [T, 3, 3] in each triangle's own plane."""
    e1 = rest[:, 1] - rest[:, 0]
    e2 = rest[:, 2] - rest[:, 0]
    u = e1 / e1.norm(dim=-1, keepdim=True)
    n = torch.linalg.cross(e1, e2)
    v = torch.linalg.cross(n, u)
    v = v / v.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    row0 = torch.stack([(e1 * u).sum(-1), (e2 * u).sum(-1)], dim=-1)
    row1 = torch.stack([(e1 * v).sum(-1), (e2 * v).sum(-1)], dim=-1)
    return torch.stack([row0, row1], dim=-2)


class StVKMembrane(Effect):
    """Constant-strain Saint Venant-Kirchhoff membrane on 3D triangles (cloth stretching).

    psi = mu tr(E^2) + lam/2 tr(E)^2 with Green strain E = (F^T F - I)/2 and plane-stress
    Lamé parameters; energy = thickness * rest area * psi.

    Args:
        name: Term name.
        vertex_dofs: Index of each triangle vertex coordinate, shape [T, 3, 3], int64.
        rest: Rest positions [m], shape [T, 3, 3].
        young: Young's modulus [Pa], scalar or [T].
        poisson: Poisson ratio, scalar or [T].
        thickness: Sheet thickness [m], finite and > 0.

    Raises:
        ValueError: on a degenerate or non-finite rest triangle, ``vertex_dofs`` not of shape [T, 3, 3] or a bad
            material parameter (each named with its value).
    """

    kind = "stvk_membrane"
    edge_dim = 3

    def __init__(
        self,
        name: str,
        vertex_dofs: Tensor,
        rest: Tensor,
        young: float | Tensor,
        poisson: float | Tensor,
        *,
        thickness: float = 1e-3,
    ) -> None:
        rest = torch.as_tensor(rest, dtype=torch.float64)
        T = rest.shape[0]
        if rest.shape != (T, 3, 3):
            raise ValueError(f"rest must have shape [T, 3, 3], got {tuple(rest.shape)}")
        _check_rest(rest, name)
        element_dofs = _vertex_dofs(vertex_dofs, rest, name)
        per_element(thickness, 1, f"thickness of {name!r}", sign="positive")
        frame = _triangle_frame(rest)
        area = 0.5 * torch.linalg.det(frame)
        bad = torch.nonzero(area <= 1e-12 * frame.abs().amax(dim=(-1, -2)) ** 2).reshape(-1)
        if bad.numel():
            raise ValueError(f"triangle {int(bad[0])} of {name!r} is degenerate (rest area {float(area[bad[0]]):.3g})")
        mu, lam = _lame(young, poisson, T, "stress")
        self.name = name
        self.element_dofs = element_dofs
        self.shape_gradients = _shape_gradients(torch.linalg.inv(frame))
        self.metric_coefficients = membrane_coefficients(self.shape_gradients)
        self.rest_area = area
        self.mu = mu * thickness
        self.lam = lam * thickness

    def element_energy(self, xe: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        return self._energies(xe.unbind(-1))

    def element_energies(self, x: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        """Energy of every triangle [J], shape [B, T], at full configurations x [B, N].

        The nine vertex coordinates are gathered as [B, T] tensors (:func:`gather_coordinates`, as :meth:`metric`).
        """
        return self._energies(gather_coordinates(x, self.element_dofs))

    def edge_energies(self, edges: Sequence[Tensor], cond: Tensor | None = None) -> Tensor:
        """Energies [J], [B, T], of the six edge entries (x1 - x0, x2 - x0), each [B, T]: all a triangle's energy
        reads, and affine in the features of an affine output layer, so a cubature computes them straight from those
        (:class:`redsim.cubature.energy.CubatureEnergy`); the gradient is with respect to the edges."""
        return self._energies(edges)

    def _energies(self, entries: Sequence[Tensor]) -> Tensor:
        """Energies [J], [B, T], of the nine vertex coordinates or the six edge entries, each [B, T], with the
        closed-form gradient of :class:`redsim.effects.cloth_gradients.MembraneEnergy`."""
        coefficients = self.metric_coefficients.T.contiguous()
        return MembraneEnergy.apply(coefficients, self.mu, self.lam, self.rest_area, *entries)

    def metric(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(C_00, C_11, C_01) of C = F^T F of every triangle, each [B, T], at full configurations x [B, N].

        The nine vertex coordinates are gathered as [B, T] tensors (:func:`gather_coordinates`), as
        :meth:`NeoHookean.invariants` does in 2D: the elementwise kernel then reads no strided views.
        """
        return membrane_metric(gather_coordinates(x, self.element_dofs), self.shape_gradients)


def membrane_metric(coords: Sequence[Tensor], shape_gradients: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The entries (C_00, C_11, C_01), each [B, T], of C = F^T F of 3D triangles from their vertex coordinates.

    ``coords`` = (x0, y0, z0, x1, y1, z1, x2, y2, z2), each [B, T]; ``shape_gradients`` [T, 3, 2].
    C = D_m^-T (D_s^T D_s) D_m^-1 with D_s = [x1 - x0, x2 - x0] and D_m^-1 = ``shape_gradients[:, 1:]``
    [T, 2, 2], entry by entry: elementwise [B, T] products instead of a [B, T, 3, 2] F from batched
    3x3 by 3x2 matmuls (those cost 5-10x more on the CPU, forward and backward).
    """
    x0, y0, z0, x1, y1, z1, x2, y2, z2 = coords
    ax, ay, az, bx, by, bz = x1 - x0, y1 - y0, z1 - z0, x2 - x0, y2 - y0, z2 - z0
    s11, s12, s22 = ax * ax + ay * ay + az * az, ax * bx + ay * by + az * bz, bx * bx + by * by + bz * bz
    m = shape_gradients[:, 1:, :]
    m00, m01, m10, m11 = m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1]
    caa = m00 * m00 * s11 + 2.0 * m00 * m10 * s12 + m10 * m10 * s22
    cbb = m01 * m01 * s11 + 2.0 * m01 * m11 * s12 + m11 * m11 * s22
    cab = m00 * m01 * s11 + (m00 * m11 + m10 * m01) * s12 + m10 * m11 * s22
    return caa, cbb, cab


def hinge_angles(coords: Sequence[Tensor], length_eps: float) -> Tensor:
    """Signed dihedral angles [rad] of hinges from their vertex coordinates (x0, y0, z0, ..., x3, y3, z3), each
    a tensor of one shape (e.g. [B, E]): :func:`redsim.effects.cloth_gradients.hinge_parts`' first term (its doc
    has the formula); ``length_eps`` [m^2] keeps the edge length positive."""
    return hinge_parts(coords, length_eps)[0]


class DiscreteShellBending(Effect):
    """Discrete-shell bending on interior edges [Grinspun et al. 2003].

    E = stiffness * 3 |e|^2 / (A_a + A_b) * (theta - theta_rest)^2 per hinge, with rest edge
    length |e| and the rest areas of its two triangles; theta is the signed dihedral angle.
    It is zero at rest and invariant under rigid motions.

    Args:
        name: Term name.
        vertex_dofs: Index of each hinge vertex coordinate, shape [E, 4, 3], int64, ordered
            (edge start, edge end, apex of the triangle (x0, x1, x2), apex of (x1, x0, x3)).
        rest: Rest positions [m], shape [E, 4, 3].
        stiffness: Bending stiffness [J], scalar or [E], finite and >= 0.

    Raises:
        ValueError: on a zero-area or non-finite rest hinge, ``vertex_dofs`` not of shape [E, 4, 3] or a negative or
            non-finite stiffness.
    """

    kind = "discrete_shell_bending"
    edge_dim = 3

    def __init__(self, name: str, vertex_dofs: Tensor, rest: Tensor, stiffness: float | Tensor) -> None:
        rest = torch.as_tensor(rest, dtype=torch.float64)
        count = rest.shape[0]
        if rest.shape != (count, 4, 3):
            raise ValueError(f"rest must have shape [E, 4, 3], got {tuple(rest.shape)}")
        _check_rest(rest, name)
        element_dofs = _vertex_dofs(vertex_dofs, rest, name)
        stiffness_t = per_element(stiffness, count, f"stiffness of {name!r}")
        e = rest[:, 1] - rest[:, 0]
        area_a = 0.5 * torch.linalg.cross(e, rest[:, 2] - rest[:, 0]).norm(dim=-1)
        area_b = 0.5 * torch.linalg.cross(rest[:, 3] - rest[:, 0], e).norm(dim=-1)
        edge_sq = (e * e).sum(-1)
        if bool(torch.any(area_a + area_b <= 0)):
            raise ValueError(f"hinge {int(torch.argmin(area_a + area_b))} of {name!r} has zero rest area")
        self.name = name
        self.element_dofs = element_dofs
        self.length_eps = float(edge_sq.min()) * 1e-12
        self.rest_angle = hinge_angles(rest.reshape(count, 12).unbind(-1), self.length_eps)
        self.weight = stiffness_t * 3.0 * edge_sq / (area_a + area_b)

    def element_energy(self, xe: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        return self._energies(xe.unbind(-1))

    def element_energies(self, x: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        """Energy of every hinge [J], [B, E], at x [B, N]: the twelve vertex coordinates gathered as [B, E]
        tensors (:func:`gather_coordinates`, as :meth:`StVKMembrane.metric`). Against the gathered [B, E, 12]
        and [..., 3] cross products: 2.6-3.3x less CPU time for the term's energy and gradient at B = 16 to 256
        and 1.5x at B = 1 (hanging_sheet and cloth_ball, float32, an interleaved development A/B; the scenes'
        energies before and after in docs/cubature.md, "Before stop 36")."""
        return self._energies(gather_coordinates(x, self.element_dofs))

    def edge_energies(self, edges: Sequence[Tensor], cond: Tensor | None = None) -> Tensor:
        """Hinge energies [J], [B, E], of the nine edge entries (x1 - x0, x2 - x0, x3 - x0), each [B, E]: all a
        hinge's energy reads (as :meth:`StVKMembrane.edge_energies`); the gradient is with respect to the edges."""
        return self._energies(edges)

    def _energies(self, coords: Sequence[Tensor]) -> Tensor:
        """Hinge energies [J], [B, E], of the twelve vertex coordinates or the nine edge entries, each [B, E] (class
        doc), by :func:`redsim.effects.cloth_gradients.hinge_energies` (a closed-form gradient up to a size)."""
        return hinge_energies(self.weight, self.rest_angle, self.length_eps, coords)
