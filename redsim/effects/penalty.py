"""Penalty terms (paper eq. "penalty"): w_eq |C_eq|^2 for joints and pins, w_ineq |min(C_ineq, 0)|^2
for contact. All are finite for any input, because fitting samples violate constraints."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from redsim.effects.base import Effect, per_element, point_dofs, split_points
from redsim.effects.sdf import Box, Capsule, Plane, Sphere, Torus
from redsim.points import PointSet


class PointPairPenalty(Effect):
    """E = stiffness/2 * |a_i - b_i|^2 for matched points a_i, b_i.

    One class covers revolute/ball joints (a point on each body, or a body and the world),
    hinge-axis alignment (directions fixed in each body: ``PointSet.body_points(direction=True)``)
    and pins by penalty (a point and a fixed world point).

    Args:
        name: Term name.
        a: First points, P of them.
        b: Second points, P of them.
        stiffness: Penalty weight [N/m] between points, [J] between directions (unit vectors: |a - b| has no
            unit), scalar or [P], finite and >= 0.
        kind: Label shown by `redsim scenes` (e.g. "joint", "hinge_axis", "pin").

    Raises:
        ValueError: on a negative or non-finite stiffness or a non-finite point weight or offset (a world target).
    """

    def __init__(self, name: str, a: PointSet, b: PointSet, stiffness: float | Tensor, *, kind: str = "joint") -> None:
        if a.dim != b.dim:
            raise ValueError(f"point sets of {name!r} differ in dimension ({a.dim} vs {b.dim})")
        for side, points in (("a", a), ("b", b)):
            for field in ("weights", "offset"):
                values = getattr(points, field)
                if not bool(torch.isfinite(values).all()):
                    i = int(torch.nonzero(~torch.isfinite(values).reshape(values.shape[0], -1).all(-1))[0, 0])
                    raise ValueError(
                        f"points {side} of {name!r} must be finite: {field} of point {i} is {values[i].tolist()}"
                    )
        self.name = name
        self.kind = kind
        self.a, self.b = a, b
        self.element_dofs = point_dofs(a, b)
        self.stiffness = per_element(stiffness, a.count, f"stiffness of {name!r}")

    def element_energy(self, xe: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        pa, pb = split_points(xe, self.a, self.b)
        d = pa - pb
        return 0.5 * self.stiffness * (d * d).sum(-1)


class ConditionalPin(Effect):
    """Pins whose strength follows a condition: a movable support (conditional subspaces, §3.5).

    E = stiffness/2 * exp(-((location_i - c_j) / width)^2 / 2) * |p_i - target_i|^2.

    Args:
        name: Term name.
        points: The pinned points.
        targets: Where each point is held [m], shape [P, D].
        locations: Coordinate of each point along the support's range, shape [P].
        condition_index: Which entry j of the condition vector is the support location.
        width: Width of the support [same unit as locations].
        stiffness: Penalty weight [N/m].

    Raises:
        ValueError: on a non-finite target or location, or a non-positive or non-finite width, or a negative or
            non-finite stiffness.
    """

    kind = "conditional_pin"
    uses_condition = True

    def __init__(
        self,
        name: str,
        points: PointSet,
        targets: Tensor,
        locations: Tensor,
        condition_index: int,
        width: float,
        stiffness: float,
    ) -> None:
        if not 0 < width < math.inf:
            raise ValueError(f"width of {name!r} must be finite and > 0, got {width}")
        per_element(stiffness, 1, f"stiffness of {name!r}")
        self.name = name
        self.points = points
        self.element_dofs = points.local_dofs()
        self.targets = torch.as_tensor(targets, dtype=torch.float64).reshape(points.count, points.dim)
        locations = torch.as_tensor(locations, dtype=torch.float64).reshape(points.count)
        self.locations = per_element(locations, points.count, f"locations of {name!r}", sign="any")
        bad = torch.nonzero(~torch.isfinite(self.targets).all(-1)).reshape(-1)
        if bad.numel():
            i = int(bad[0])
            raise ValueError(f"targets of {name!r} must be finite, got {self.targets[i].tolist()} for point {i}")
        self.condition_index = int(condition_index)
        self.width = float(width)
        self.stiffness = float(stiffness)

    def element_energy(self, xe: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        if cond is None:
            raise ValueError(f"effect {self.name!r} needs a condition vector")
        d = self.points.local_positions(xe) - self.targets
        centre = cond[:, self.condition_index : self.condition_index + 1]
        weight = torch.exp(-0.5 * ((self.locations - centre) / self.width) ** 2)
        return 0.5 * self.stiffness * weight * (d * d).sum(-1)


@dataclass(frozen=True)
class FrameSet:
    """Affine frames ``[R | t]`` (row-major 12 numbers) read linearly from x, one per element.

    frame = x[dofs] * weights + offset; a rigid body has weights 1 and offset 0, the world
    has weights 0 and a fixed offset.

    Attributes:
        dofs: Indices, shape [P, 12], int64.
        weights: shape [P, 12].
        offset: shape [P, 12].
    """

    dofs: Tensor
    weights: Tensor
    offset: Tensor

    @staticmethod
    def body(body_dofs: Tensor, count: int) -> FrameSet:
        dofs = torch.as_tensor(body_dofs, dtype=torch.int64).reshape(1, 12).expand(count, 12).clone()
        return FrameSet(dofs, torch.ones(count, 12, dtype=torch.float64), torch.zeros(count, 12, dtype=torch.float64))

    @staticmethod
    def world(transform: Tensor, count: int) -> FrameSet:
        """A fixed frame; ``transform`` is a 3x4 ``[R | t]``."""
        flat = torch.as_tensor(transform, dtype=torch.float64).reshape(1, 12).expand(count, 12).clone()
        return FrameSet(torch.zeros(count, 12, dtype=torch.int64), torch.zeros(count, 12, dtype=torch.float64), flat)

    @staticmethod
    def cat(frames: list[FrameSet]) -> FrameSet:
        return FrameSet(*(torch.cat([getattr(f, k) for f in frames]) for k in ("dofs", "weights", "offset")))


NEAR_SLACK = 1e-5
"""[m] Points this far past the margin still get an energy graph in :meth:`SDFContact.energy` (a
round-off guard: the selecting distances and the differentiated ones are computed in another order)."""
SPARSE_FRACTION = 0.25
"""Above this fraction of near points, :meth:`SDFContact.energy` differentiates all points (where most points need
the per-point gathers anyway; a chosen threshold, not a measured crossing: docs/runtime.md, "Contact where it acts")."""


def _to_local(frame: Tensor, p: Tensor) -> Tensor:
    """R^T (p - t) [B, P, 3] of points p [B, P, 3] in frames [B, 3, 4] = [R | t] (components contiguous)."""
    local = torch.bmm(frame[..., :3].transpose(1, 2), (p - frame[:, None, :, 3]).transpose(1, 2))  # [B, 3, P]
    return local.transpose(1, 2)


class SDFContact(Effect):
    """Contact penalty between points and an analytic signed distance carried by a frame.

    E = stiffness/2 * min(sdf(R^T (p - t)) - margin, 0)^2 for each (point, frame) pair the
    scene declares; no other pairs are evaluated. R^T stands in for R^-1 (R is kept
    orthogonal by :class:`~redsim.effects.rigid.RigidOrthogonality`), so the term stays finite
    for any x.

    Args:
        name: Term name.
        points: Points that must stay outside the shape (3D), P of them.
        frames: The frame carrying the shape, one per point.
        shape: A shape from :mod:`redsim.effects.sdf`.
        stiffness: Penalty weight [N/m], finite and >= 0.
        margin: Distance [m] kept from the surface, finite and >= 0.

    Raises:
        ValueError: on points that are not 3D, not one frame per point, or a negative or non-finite stiffness or
            margin.
    """

    kind = "sdf_contact"

    def __init__(
        self,
        name: str,
        points: PointSet,
        frames: FrameSet,
        shape: Sphere | Plane | Box | Capsule | Torus,
        stiffness: float,
        *,
        margin: float = 0.0,
    ) -> None:
        if points.dim != 3:
            raise ValueError(f"contact points must be 3D, got {points.dim}D")
        if frames.dofs.shape != (points.count, 12):
            raise ValueError(f"need one frame per point: {points.count} points, frames {tuple(frames.dofs.shape)}")
        per_element(stiffness, 1, f"stiffness of {name!r}")
        per_element(margin, 1, f"margin of {name!r}")
        self.name = name
        self.kind = f"sdf_contact:{type(shape).__name__.lower()}"
        self.points = points
        self.frames = frames
        self.shape = shape
        self.stiffness = float(stiffness)
        self.margin = float(margin)
        self.element_dofs = torch.cat([points.local_dofs(), frames.dofs], dim=1)
        self.feature_size = shape.feature_size + 2.0 * self.margin
        self._build_pairs()

    def _build_pairs(self) -> None:
        """Group the points by (point source, frame) pair for :meth:`energy`.

        A point source is one row of point dofs (all points fixed in one body share it; a particle
        is its own); a frame is one (dofs, weights, offset) row. Each pair gets S slots (the largest
        pair's count, unused slots masked), so a body-body contact is two small matmuls per pair
        instead of a 24-entry gather per point. ``pair_lift`` [pairs, K (+D) + 1, S] stacks the
        point weights, offsets and a row of ones, so that one contraction per pair maps
        [R^T X | R^T | -R^T t] to the local points.
        """
        P, D, K = self.points.dofs.shape
        sources, source_index = torch.unique(self.points.dofs.reshape(P, D * K), dim=0, return_inverse=True)
        frame_rows = torch.cat(
            [self.frames.dofs.to(self.frames.weights.dtype), self.frames.weights, self.frames.offset], 1
        )
        frame_keys, frame_index = torch.unique(frame_rows, dim=0, return_inverse=True)
        pair_keys, pair_index = torch.unique(torch.stack([source_index, frame_index], 1), dim=0, return_inverse=True)
        pairs = pair_keys.shape[0]
        counts = torch.bincount(pair_index, minlength=pairs)
        slots = int(counts.max()) if P else 0
        order = torch.argsort(pair_index, stable=True)
        first = torch.cumsum(counts, 0) - counts
        device = self.points.weights.device  # a subset built for the runtime lives where the scene does
        slot = torch.arange(P, device=device) - first[pair_index[order]]
        weights = torch.zeros(pairs, K, slots, dtype=self.points.weights.dtype, device=device)
        offsets = torch.zeros(pairs, D, slots, dtype=self.points.offset.dtype, device=device)
        mask = torch.zeros(pairs, slots, dtype=self.points.weights.dtype, device=device)
        weights[pair_index[order], :, slot] = self.points.weights[order]
        offsets[pair_index[order], :, slot] = self.points.offset[order]
        mask[pair_index[order], slot] = 1.0
        frame_dofs = frame_keys[:, :12].to(torch.int64)  # [F, 12]
        # per pair, the entries of x it reads: its source's point dofs and its frame's 12 dofs
        self.pair_source_index = sources[pair_keys[:, 0]].reshape(-1).contiguous()  # [pairs * D * K]
        self.pair_frame_index = frame_dofs[pair_keys[:, 1]].reshape(-1).contiguous()  # [pairs * 12]
        self.pair_frame_weights = frame_keys[pair_keys[:, 1], 12:24]  # [pairs, 12]
        self.pair_frame_offset = frame_keys[pair_keys[:, 1], 24:]
        self.pair_weights = weights  # [pairs, K, S]
        self.pair_offsets = offsets if bool(offsets.any()) else None  # [pairs, D, S]
        self.pair_mask = mask  # [pairs, S]
        lift = [weights] + ([] if self.pair_offsets is None else [offsets]) + [torch.ones_like(mask).unsqueeze(1)]
        self.pair_lift = torch.cat(lift, 1)  # [pairs, K (+D) + 1, S]
        self.partial_slots = not bool(mask.all())  # False: every slot holds a point, no mask to apply
        # for :meth:`_point_distances`: the entries of x each pair reads (its source's D * K, then its frame's 12),
        # and each point's weights and offset by flat slot (pair * S + slot)
        self.pair_dofs = torch.cat([sources[pair_keys[:, 0]], frame_dofs[pair_keys[:, 1]]], 1)  # [pairs, D*K + 12]
        self.slot_weights = weights.transpose(1, 2).reshape(pairs * slots, K)
        self.slot_offsets = None if self.pair_offsets is None else offsets.transpose(1, 2).reshape(pairs * slots, D)
        # every frame a body's own 12 entries (weights 1, no offset): no affine map of the frame entries
        self.body_frames = bool((self.pair_frame_weights == 1.0).all() and not self.pair_frame_offset.any())
        # one frame for every point (particles against one body, e.g. a cloth and a ball): the
        # per-point form of :meth:`distances` (the pair tables would hold one point per pair)
        self.single_frame = bool(frame_keys.shape[0] == 1)
        plain = bool(K == 1 and (self.points.weights == 1.0).all() and not self.points.offset.any())
        self.point_weights = None if plain else self.points.weights  # [P, K]
        self.point_offset = None if plain else self.points.offset  # [P, D]

    def subset(self, index: Tensor) -> SDFContact:
        """The contact of the points ``index`` only (its pair tables rebuilt)."""
        out: SDFContact = super().subset(index)  # type: ignore[assignment]
        out._build_pairs()
        return out

    def signed_distance(self, xe: Tensor) -> Tensor:
        """Signed distance [m] of each point, shape [B, P], from element entries [B, P, k]."""
        return self.shape.distance(self.local_points(xe))

    def local_points(self, xe: Tensor) -> Tensor:
        """Each point in its frame's coordinates [m], shape [B, P, 3], from element entries [B, P, k]: where the
        shape sees it (:meth:`signed_distance` is the shape's distance of these)."""
        (p,) = split_points(xe, self.points)
        frame = xe[..., self.points.local_size :] * self.frames.weights + self.frames.offset
        frame = frame.reshape(*frame.shape[:-1], 3, 4)
        return (frame[..., :3].transpose(-1, -2) @ (p - frame[..., 3]).unsqueeze(-1)).squeeze(-1)

    def element_energy(self, xe: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        gap = (self.signed_distance(xe) - self.margin).clamp_max(0.0)
        return 0.5 * self.stiffness * gap * gap

    def energy(self, x: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        """The element sum [B]: every distance without autograd, then the energy (and its graph) only of
        the points within :data:`NEAR_SLACK` of the margin; the others contribute exactly 0 (value and
        every derivative). With one frame for every point, :meth:`near_energy` (a cheaper screen). Dense
        (all points in the graph) under ``torch.compile`` (no data-dependent shapes) and where more than
        :data:`SPARSE_FRACTION` of the points are near."""
        if not torch.compiler.is_compiling():
            if self.single_frame:
                return self.near_energy(x)
            with torch.no_grad():
                near = self._pair_distances(x) < self.margin + NEAR_SLACK
                if self.partial_slots:
                    near &= self.pair_mask.unsqueeze(1) > 0
            pair, state, slot = near.nonzero(as_tuple=True)  # sorted by pair, then state, then slot
            if pair.numel() <= SPARSE_FRACTION * x.shape[0] * self.element_count:
                gap = (self._point_distances(x, pair, state, slot) - self.margin).clamp_max(0.0)
                return x.new_zeros(x.shape[0]).index_add(0, state, 0.5 * self.stiffness * gap * gap)
        gap = (self._pair_distances(x) - self.margin).clamp_max(0.0)  # [pairs, B, S]
        return 0.5 * self.stiffness * (gap * gap * self.pair_mask.unsqueeze(1)).sum((0, 2))

    def _points_and_frame(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Every point p [B, P, 3] and the one frame [B, 3, 4] (single-frame contact)."""
        B = x.shape[0]
        P, D, K = self.points.dofs.shape
        gathered = x.index_select(1, self.points.dofs.reshape(-1))
        if self.point_weights is None:
            p = gathered.view(B, P, D)
        else:
            p = (gathered.view(B, P, D, K) * self.point_weights[:, None, :]).sum(-1) + self.point_offset
        frame = x.index_select(1, self.pair_frame_index[:12]) * self.pair_frame_weights[0] + self.pair_frame_offset[0]
        return p, frame.view(B, 3, 4)

    def near_energy(self, x: Tensor) -> Tensor:
        """The exact energy [B] of single-frame contact, differentiated through the points near the shape only.

        A point farther than the margin adds exactly zero energy and force, so a screen without
        gradients (:meth:`near_points`) keeps a superset of the points within the margin, and only those
        (a few per state, e.g. the cloth under a ball) are evaluated with autograd
        (:meth:`near_point_energy`). The result and its derivatives equal the all-point sum.
        """
        rows, cols = self.near_points(x)
        if not rows.shape[0]:
            return 0.0 * x[:, 0]  # zero, still a function of x (callers differentiate it)
        P, D, K = self.points.dofs.shape
        dofs = self.points.dofs.reshape(P, D * K).index_select(0, cols)  # [A, D*K]
        flat = (rows[:, None] * x.shape[1] + dofs).reshape(-1)
        entries = x.reshape(-1).index_select(0, flat).view(-1, D * K)
        return self.near_point_energy(rows, cols, entries, x.index_select(1, self.pair_frame_index[:12]))

    def near_points(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """The (state [A], point [A]) pairs of single-frame contact that may lie within the margin, without gradients.

        Keeps the points with |p - t| < (bounding radius + margin) / sigma_min(R) (a superset of those within
        the margin: |R^T d| >= sigma_min |d|); sigma_min is bounded from below by Gershgorin's circles of
        R^T R (where that bound is not positive, every point is kept). x [B, N] needs to hold only the
        points' and the frame's entries.
        """
        with torch.no_grad():
            p, frame = self._points_and_frame(x)
            near = ((p - frame[:, None, :, 3]).square().sum(-1) < self.screen_radius_sq(frame)[:, None]).nonzero()
        rows, cols = near.unbind(1)
        return rows, cols

    def screen_radius_sq(self, frame: Tensor) -> Tensor:
        """Squared radius [B] [m^2] about each frame's origin t outside which no point lies within the margin, of
        frames [B, 3, 4] = [R | t] (:meth:`near_points`; inf where Gershgorin's bound on sigma_min(R) fails)."""
        with torch.no_grad():
            reach = self.shape.bounding_radius + self.margin
            gram = frame[..., :3].transpose(1, 2) @ frame[..., :3]  # R^T R [B, 3, 3]
            diagonal = gram.diagonal(dim1=1, dim2=2)
            # Gershgorin: sigma_min(R)^2 = lambda_min(R^T R) >= min_i (G_ii - sum_{j != i} |G_ij|)
            low = (2.0 * diagonal - gram.abs().sum(-1)).amin(-1)  # [B]
            bound = torch.where(low > 0.0, (reach * (1.0 + 1e-3) + 1e-6) / low.clamp_min(1e-30).sqrt(), torch.inf)
        return bound.square()

    def near_point_energy(self, rows: Tensor, cols: Tensor, entries: Tensor, frame_entries: Tensor) -> Tensor:
        """The energy [B] of single-frame contact summed over the points ``cols`` [A] of states ``rows`` [A] only.

        Args:
            rows: State of each point, [A], int64.
            cols: Point index of each, [A], int64.
            entries: x[rows, points.dofs[cols]] [A, D*K], the points' entries of x (a graph only through these).
            frame_entries: x[:, frame dofs] [B, 12], the frame's raw entries (before its weights and offset).
        """
        B = frame_entries.shape[0]
        _, D, K = self.points.dofs.shape
        gathered = entries.view(-1, D, K)
        if self.point_weights is None:
            q = gathered[..., 0]
        else:
            q = (gathered * self.point_weights.index_select(0, cols)[:, None, :]).sum(-1)
            q = q + self.point_offset.index_select(0, cols)
        frames = (frame_entries * self.pair_frame_weights[0] + self.pair_frame_offset[0]).view(B, 3, 4)
        local = _to_local(frames.index_select(0, rows), q.unsqueeze(1))[:, 0]  # [A, 3]
        gap = (self.shape.distance(local) - self.margin).clamp_max(0.0)
        return frame_entries.new_zeros(B).index_add(0, rows, 0.5 * self.stiffness * gap * gap)

    def _point_distances(self, x: Tensor, pair: Tensor, state: Tensor, slot: Tensor) -> Tensor:
        """Signed distance [m] of single points [A], point ``slot`` of pair ``pair`` in state ``state`` (each [A]).

        One gather of each point's entries of x (one ``index_add_`` into x in the backward) through the
        precomputed per-pair index table, then two batched matvecs (~3x faster on the CPU than products
        and sums over the size-3 and size-4 axes at A = 2,000-20,000).
        """
        A = pair.shape[0]
        K = self.pair_weights.shape[1]
        rows = self.pair_dofs.index_select(0, pair) + (state * x.shape[1]).unsqueeze(1)  # [A, 3 K + 12]
        entries = x.reshape(-1).index_select(0, rows.reshape(-1)).view(A, rows.shape[1])
        frames = entries[:, 3 * K :]
        if not self.body_frames:
            frames = frames * self.pair_frame_weights.index_select(0, pair)
            frames = frames + self.pair_frame_offset.index_select(0, pair)
        frames = frames.view(A, 3, 4)
        flat = pair * self.pair_weights.shape[2] + slot
        point = entries[:, : 3 * K].view(A, 3, K) @ self.slot_weights.index_select(0, flat).unsqueeze(-1)  # [A, 3, 1]
        if self.slot_offsets is not None:
            point = point + self.slot_offsets.index_select(0, flat).unsqueeze(-1)
        local = frames[..., :3].transpose(-1, -2) @ (point - frames[..., 3:])  # R^T (p - t) [A, 3, 1]
        return self.shape.distance(local.squeeze(-1))

    def penetration(self, x: Tensor) -> Tensor:
        """Deepest penetration [m] past the margin, shape [B], of full configurations x [B, N] (0: none)."""
        return (-self.clearance(x)).clamp_min(0.0)

    def clearance(self, x: Tensor) -> Tensor:
        """Smallest signed distance [m] of a contact point beyond the margin, shape [B], of full configurations
        x [B, N]: negative inside the margin (minus the penetration), positive where no point touches (how far the
        nearest one is from touching); +inf without points."""
        if self.single_frame:
            with torch.no_grad():
                p, frame = self._points_and_frame(x)
                gap = self.shape.distance(_to_local(frame, p)) - self.margin
            return gap.amin(-1) if gap.shape[-1] else x.new_full((x.shape[0],), math.inf)
        gap = (self._pair_distances(x) - self.margin).masked_fill(self.pair_mask.unsqueeze(1) == 0, math.inf)
        return gap.transpose(0, 1).flatten(1).amin(-1)

    def _pair_distances(self, x: Tensor) -> Tensor:
        """Signed distance [m] of every point, by (point source, frame) pair: [pairs, B, S] (see
        :meth:`_build_pairs`; unused slots, ``pair_mask`` 0, hold the frame origin's distance)."""
        return self.shape.distance(self._pair_local(x))

    def pair_points(self, x: Tensor) -> Tensor:
        """Every point in its pair's frame [m], [pairs, B, S, 3], of full configurations x [B, N]: the pair tables'
        layout (slots where ``pair_mask`` is 0 hold the frame origin), each pair's points in their order."""
        return self._pair_local(x)

    def frame_points(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Every point in the coordinates of the frame that carries its shape [m], [B, M, 3], of full configurations
        x [B, N], and which of the M rows are points ([M] bool; the pair tables' unused slots are not). The layout is
        the cheapest one's (:meth:`near_points`' single frame, else the pair tables'), not the points' order."""
        if self.single_frame:
            p, frame = self._points_and_frame(x)
            local = _to_local(frame, p)
            return local, torch.ones(local.shape[1], dtype=torch.bool, device=local.device)
        local = self._pair_local(x)  # [pairs, B, S, 3]
        pairs, B, S = local.shape[:3]
        return local.permute(1, 0, 2, 3).reshape(B, pairs * S, 3), (self.pair_mask > 0).reshape(-1)

    def _pair_local(self, x: Tensor) -> Tensor:
        """Every point in its pair's frame [m], [pairs, B, S, 3] (:meth:`_pair_distances`' layout).

        local = R_f^T (X_g w + o - t_f) for the points (weights w, offsets o) of source g in frame f:
        A = [R_f^T X_g | R_f^T | -R_f^T t_f] once per pair, then one contraction with the pair's
        ``pair_lift``, batched over pairs (each a [3*B, K+D+1] x [K+D+1, S] matmul), whose output
        keeps x, y and z contiguous for the distance (it replaced per-(state, pair) 3x3
        matmuls on the chain; docs/runtime.md, "Where today's path spent its time").
        """
        B = x.shape[0]
        pairs, K = self.pair_weights.shape[:2]
        # gathers from x [B, N] only: their backward is one index_add_ into x (on a [B, pairs, ...]
        # tensor it is one slice-add per index, 10-40x slower at B = 1)
        # sizes spelled out, never -1: an empty batch (B = 0) has no size to infer
        sources = x.index_select(1, self.pair_source_index).reshape(B, pairs, 3, K)  # [B, pairs, 3, K]
        frames = x.index_select(1, self.pair_frame_index).reshape(B, pairs, 12)
        frames = (frames * self.pair_frame_weights + self.pair_frame_offset).reshape(B, pairs, 3, 4)
        rotation_t = frames[..., :3].transpose(-1, -2)  # [B, pairs, 3, 3]
        parts = [rotation_t @ sources]  # [B, pairs, 3, K]
        if self.pair_offsets is not None:
            parts.append(rotation_t)
        parts.append(-(rotation_t @ frames[..., 3:]))  # -R_f^T t_f
        # [pairs, 3, B, K (+D) + 1]: the contraction's output [pairs, 3 * B, S] then holds each
        # component of a pair's points in one contiguous block of B * S
        lifted = torch.cat(parts, -1).permute(1, 2, 0, 3)
        local = torch.bmm(lifted.reshape(pairs, 3 * B, lifted.shape[-1]), self.pair_lift)  # [pairs, 3 * B, S]
        S = self.pair_lift.shape[-1]
        return local.view(pairs, 3, B, S).permute(0, 2, 3, 1)
