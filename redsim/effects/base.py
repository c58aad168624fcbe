"""The one interface every energy term implements.

An effect is a sum over independent *elements* (a tet, a triangle, a hinge edge, a joint, a
contact point). Each element reads a fixed set of entries of the full configuration x,
``element_dofs`` [T, k], and :meth:`Effect.element_energy` returns one energy per element.
The total is their sum. The same two members give the batched energy used by fitting and
envs and the per-element Hessians the full-space Newton solver assembles, so there is one
definition of each physical term.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor

from redsim.points import PointSet
from redsim.tensors import cast_tensors, map_tensors


class Effect:
    """Base class of energy terms. Subclasses set ``element_dofs`` and implement ``element_energy``.

    Attributes:
        name: Unique name of this term within a scene (e.g. ``"gravity"``, ``"joints"``).
        element_dofs: Full-configuration indices read by each element, shape [T, k], int64.
        uses_loads: True for terms that read the per-step loads (external forces). The latent runtime and the
            cubature take only :class:`redsim.effects.external.ExternalLoad`
            (:meth:`redsim.scene.Scene.load_free_effects`).
        uses_condition: True for terms that read the condition vector c.
    """

    kind: ClassVar[str] = "effect"
    feature_size: float = math.inf
    """Thinnest feature [m] this term resolves (contact shapes): static full-space solves keep their Newton steps
    below half of it, and an :class:`~redsim.effects.SDFContact` point that moves farther relative to its shape in a
    time step is checked for tunneling (:mod:`redsim.integrators.tunneling`)."""
    edge_dim: int | None = None
    """Coordinates per vertex of an effect whose elements' energies read only their edges x_j - x_0 and that offers
    them as :meth:`edge_energies` (a cubature then computes the edges straight from its features); None: not one."""
    uses_loads: ClassVar[bool] = False
    uses_condition: ClassVar[bool] = False

    name: str
    element_dofs: Tensor

    @property
    def element_count(self) -> int:
        return int(self.element_dofs.shape[0])

    def element_energy(self, xe: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        """Energy of every element [J], shape [B, T], from xe = x[:, element_dofs], shape [B, T, k].

        Args:
            xe: Gathered configuration entries.
            cond: Condition vectors, shape [B, m], for terms with ``uses_condition``.
            loads: Loads, shape [B, H, D] (force [N] per handle), for terms with ``uses_loads``.
        """
        raise NotImplementedError(
            f"{type(self).__name__} must implement element_energy(xe [B, T, k], cond, loads) -> [B, T] (or override "
            "element_energies / energy)"
        )

    def element_energies(self, x: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        """Energy of every element [J], shape [B, T], at configurations x [B, N], read at ``element_dofs`` only.

        :meth:`element_energy` of the gathered entries; kernels that gather each coordinate on its own override it.
        """
        return self.element_energy(gather_elements(x, self.element_dofs), cond, loads)

    def edge_energies(self, edges: Sequence[Tensor], cond: Tensor | None = None) -> Tensor:
        """Energy of every element [J], [B, T], of its edge entries (:func:`edge_vectors` of its vertex coordinates,
        each [B, T]), for an effect with ``edge_dim``; the gradient is with respect to the edges."""
        raise NotImplementedError(f"{type(self).__name__} {self.name!r} does not read its elements by their edges")

    def energy(self, x: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        """Total energy [J], shape [B], of full configurations x, shape [B, N]."""
        return self.element_energies(x, cond, loads).sum(-1)

    def describe(self) -> dict[str, Any]:
        """Name, kind and element count, for `redsim scenes`."""
        return {"name": self.name, "kind": self.kind, "elements": self.element_count}

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Effect:
        """A copy with floating tensors cast to ``dtype`` and every tensor moved to ``device``."""
        out = copy.copy(self)
        for key, value in vars(self).items():
            setattr(out, key, cast_tensors(value, device, dtype))
        return out

    def subset(self, index: Tensor) -> Effect:
        """A copy of this term over the elements ``index`` [K] only (int64, each in [0, T)).

        Every per-element field (a tensor, or a dataclass such as a :class:`PointSet`, whose leading
        dimension is T) is selected; other fields are shared. A cubature evaluates the subset's
        ``element_energy`` on ``gather_elements(x, subset.element_dofs)``.
        """
        index = torch.as_tensor(index, dtype=torch.int64, device=self.element_dofs.device)
        count = self.element_count
        if index.ndim != 1 or (index.numel() and (int(index.min()) < 0 or int(index.max()) >= count)):
            raise ValueError(f"element indices must be a 1-D tensor in [0, {count}) for {self.name!r}")

        def select(t: Tensor) -> Tensor:
            return t.index_select(0, index) if t.ndim and t.shape[0] == count else t

        out = copy.copy(self)
        for key, value in vars(self).items():
            setattr(out, key, map_tensors(value, select))
        return out

    def reindexed(self, element_dofs: Tensor) -> Effect:
        """A copy whose elements read x at ``element_dofs`` [T, k] instead (e.g. positions in a slice of x).

        Only :meth:`element_energy` and :meth:`element_energies` hold for the copy (:meth:`energy` of an effect
        with its own index tables, such as contact's, does not).
        """
        element_dofs = torch.as_tensor(element_dofs, dtype=torch.int64, device=self.element_dofs.device)
        if element_dofs.shape != self.element_dofs.shape:
            raise ValueError(f"element_dofs must have shape {tuple(self.element_dofs.shape)} for {self.name!r}")
        out = copy.copy(self)
        out.element_dofs = element_dofs
        return out

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, elements={self.element_count})"


def gather_elements(x: Tensor, element_dofs: Tensor) -> Tensor:
    """xe = x[:, element_dofs], shape [B, T, k], from x [B, N] and element_dofs [T, k].

    By ``index_select`` on the flattened indices: the same values as advanced indexing, but its
    backward is an ``index_add`` instead of a sorting, accumulating ``index_put_`` (several times
    faster on the CPU for the thousands of repeated indices of a mesh).
    """
    return x.index_select(1, element_dofs.reshape(-1)).reshape(x.shape[0], *element_dofs.shape)


def edge_vectors(coords: Sequence[Tensor], dim: int = 3) -> list[Tensor]:
    """The edges x_j - x_0 (j = 1, 2, ...), entry by entry, of an element's vertex coordinates (x0, y0[, z0], x1, ...,
    each one shape; ``dim`` per vertex): dim (k - 1) tensors of k vertices' dim k, edge-major."""
    origin = coords[:dim]
    return [c - o for j in range(dim, len(coords), dim) for c, o in zip(coords[j : j + dim], origin, strict=True)]


def gather_coordinates(x: Tensor, element_dofs: Tensor) -> Sequence[Tensor]:
    """x[:, element_dofs[:, j]] for each j: k tensors [B, T] from x [B, N] and element_dofs [T, k].

    For elementwise kernels that work coordinate by coordinate (unlike the columns of
    :func:`gather_elements`' [B, T, k], each is contiguous within its rows). Where the elements
    cover most of x (T >= N / 2, a whole mesh) each coordinate is its own ``index_select``;
    where they are few against x (a cubature's kept elements in its slice) one ``index_select``
    in coordinate-major order gives all k, since the backward of each separate one fills a
    zero [B, N] gradient (docs/cubature.md, "Before stop 36").
    """
    count, k = element_dofs.shape
    if 2 * count >= x.shape[1]:
        return [x.index_select(1, dofs) for dofs in element_dofs.T.contiguous()]
    return x.index_select(1, element_dofs.T.reshape(-1)).view(x.shape[0], k, count).unbind(1)


def per_element(
    value: float | Tensor, count: int, what: str, *, sign: Literal["nonnegative", "positive", "any"] = "nonnegative"
) -> Tensor:
    """A per-element parameter (stiffness, modulus) as float64 [count]: a scalar is broadcast.

    Every entry must be finite and, by ``sign``, >= 0 (the default: a zero stiffness switches an element off),
    > 0 (a modulus) or of ``"any"`` sign (a Poisson ratio, whose range its own conversion checks).

    Raises:
        ValueError: ``value`` is neither a scalar nor of shape [count], or an entry is not finite or has the
            wrong sign (``what`` names it, with the value).
    """
    given = torch.as_tensor(value, dtype=torch.float64)
    out = given.expand(count).clone() if given.ndim == 0 else given.clone()
    if out.shape != (count,):
        raise ValueError(f"{what} must be a scalar or have shape [{count}], got {tuple(out.shape)}")
    ok = torch.isfinite(out)
    if sign != "any":
        ok &= out > 0 if sign == "positive" else out >= 0
    if not bool(ok.all()):
        rule = {"nonnegative": "finite and >= 0", "positive": "finite and > 0", "any": "finite"}[sign]
        i = int(torch.nonzero(~ok)[0, 0])
        shown = f"{float(out[i])!r}" if given.ndim == 0 else f"{float(out[i])!r} at element {i}"
        raise ValueError(f"{what} must be {rule}, got {shown}")
    return out


def point_dofs(*point_sets: PointSet) -> Tensor:
    """Element dofs for elements made of one point from each set, shape [P, sum(D*K)]."""
    counts = {s.count for s in point_sets}
    if len(counts) != 1:
        raise ValueError(f"point sets must have equal counts, got {sorted(counts)}")
    return torch.cat([s.local_dofs() for s in point_sets], dim=1)


def split_points(xe: Tensor, *point_sets: PointSet) -> list[Tensor]:
    """Positions [B, P, D] of each set from element entries built by :func:`point_dofs`."""
    out, start = [], 0
    for s in point_sets:
        out.append(s.local_positions(xe[..., start : start + s.local_size]))
        start += s.local_size
    return out
