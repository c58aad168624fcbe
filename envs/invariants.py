"""Physical invariants a user watches in ``info``: one small batched check per kind of effect.

For every effect of a scene that has a check (rigid orthogonality, point-pair joints and pins,
FEM, cloth membranes, signed-distance contact), :class:`Invariants` returns named [B] tensors,
prefixed by the effect's name:

- ``<rigid>_orthogonality_error``: max over bodies of |R^T R - I|_F (0 for exact rotations);
- ``<joints>_max_gap`` [m]: max distance between the two points of a joint / pin; for a hinge's axis
  directions (``joint_axes``: unit vectors; Stewart's ``servos``: each arm's against its seed) the chord between them,
  unitless (~ the misalignment in rad);
- ``<elastic>_min_det_f`` and ``<elastic>_inverted`` (count of elements with det F <= 0);
- ``<membrane>_max_strain``: max principal stretch - 1 over the cloth triangles (0: unstretched);
- ``<contact>_penetration`` [m]: max depth of a contact point inside its shape's margin;
- ``<contact>_clearance`` [m]: the smallest distance of a contact point beyond that margin, negative when one is
  inside (the penetration, negated), positive when none touches: how far the nearest point is from contact;
- ``<contact>_unlinked`` (torus contacts whose point rings are interlocked with their tori at the seed: the chains'
  links and hook): how many (ring, torus) pairs no longer have the seed's linking number, i.e. passed through each
  other. Exact topology, where the tunnel test is a detector: it also counts a crossing whose end rests against the
  wire's far side, which that test cannot tell from a point resting in contact. Each interlocked pair of links is held
  from both sides (each link's ring against the other's torus), so one pair that came apart reads 2.

The checks run over blocks of rows sized so that one block's per-element [rows, elements] tensors stay in the
CPU's cache (:data:`BLOCK_ELEMENTS`; the values are the one pass's to round-off): at 256 copies the cloth envs'
checks took 3x less CPU time in blocks of 66-67 rows than in one pass, whose elementwise ops each stream
megabytes through memory; at 64 copies (one block either way) they are unchanged (docs/env-speed.md, "Stop 28's
measurements")."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from redsim.effects import NeoHookean, PointPairPenalty, RigidOrthogonality, SDFContact, StVKMembrane
from redsim.effects.base import Effect, gather_elements, split_points
from redsim.effects.sdf import Torus
from redsim.scene import Scene


def _orthogonality(effect: RigidOrthogonality, x: Tensor) -> dict[str, Tensor]:
    xe = gather_elements(x, effect.element_dofs)
    B, T, _ = xe.shape
    R = xe.reshape(B, T, 3, 4)[..., :3]
    defect = R.transpose(-1, -2) @ R - torch.eye(3, dtype=xe.dtype, device=xe.device)
    return {"orthogonality_error": defect.flatten(-2).norm(dim=-1).amax(-1)}


def _gap(effect: PointPairPenalty, x: Tensor) -> dict[str, Tensor]:
    xe = gather_elements(x, effect.element_dofs)
    a, b = split_points(xe, effect.a, effect.b)
    return {"max_gap": (a - b).norm(dim=-1).amax(-1)}


def _fem(effect: NeoHookean, x: Tensor) -> dict[str, Tensor]:
    _, det = effect.invariants(x)
    return {"min_det_f": det.amin(-1), "inverted": (det <= 0.0).sum(-1).to(x.dtype)}


def _membrane(effect: StVKMembrane, x: Tensor) -> dict[str, Tensor]:
    """The larger eigenvalue of C = F^T F (the squared principal stretch) in closed form, (C_00 + C_11) / 2 +
    hypot((C_00 - C_11) / 2, C_01), with the half sum and half difference taken from s = (a.a, a.b, b.b) of the
    edges a, b by folded coefficients (:func:`redsim.effects.cloth_gradients.membrane_coefficients`), in place on
    the gathered coordinates: 35 passes where :meth:`StVKMembrane.metric` and the eigenvalue took 54, each into a
    fresh tensor (1.38x less CPU time at 64 HangingCloth-v1 copies, float32; equal to round-off). Element-major
    ([T, B]: x transposed once, each coordinate gathered as whole rows of B copies, the coefficients contiguous
    [T, 1] columns) it took 1.9 ms where the copy-major [B, T] form's strided gathers and stride-9 coefficient rows
    took 3.6 (64 HangingCloth-v2 copies, float32; the same bits; docs/env-speed.md, "Stop 52")."""
    rows = x.T.contiguous()  # [N, B]
    x0, y0, z0, x1, y1, z1, x2, y2, z2 = (rows.index_select(0, dofs) for dofs in effect.element_dofs.T)  # [T, B]
    ax, ay, az, bx, by, bz = x1.sub_(x0), y1.sub_(y0), z1.sub_(z0), x2.sub_(x0), y2.sub_(y0), z2.sub_(z0)
    s11 = torch.mul(ax, ax, out=x0).addcmul_(ay, ay).addcmul_(az, az)
    s12 = torch.mul(ax, bx, out=y0).addcmul_(ay, by).addcmul_(az, bz)
    s22 = torch.mul(bx, bx, out=z0).addcmul_(by, by).addcmul_(bz, bz)
    p = effect.metric_coefficients.T.unsqueeze(-1)  # [9, T, 1]: C_00, C_11, C_01 = rows (0-2, 3-5, 6-8) . s
    mean_p, half_p, cab_p = (0.5 * (p[0:3] + p[3:6]), 0.5 * (p[0:3] - p[3:6]), p[6:9].contiguous())
    mean = torch.mul(s11, mean_p[0], out=ax).addcmul_(s12, mean_p[1]).addcmul_(s22, mean_p[2])
    half = torch.mul(s11, half_p[0], out=ay).addcmul_(s12, half_p[1]).addcmul_(s22, half_p[2])
    cab = torch.mul(s11, cab_p[0], out=az).addcmul_(s12, cab_p[1]).addcmul_(s22, cab_p[2])
    largest = mean.add_(torch.hypot(half, cab, out=bx))
    return {"max_strain": largest.amax(0).clamp_min(0.0).sqrt() - 1.0}


def _contact(effect: SDFContact, x: Tensor) -> dict[str, Tensor]:
    clearance = effect.clearance(x)
    return {"penetration": (-clearance).clamp_min(0.0), "clearance": clearance}


def linking_numbers(effect: SDFContact, ring: Tensor) -> Tensor:
    """The linking number [pairs, B] of each (point source, frame) pair's points ``ring`` [pairs, B, S, 3] in its frame
    (:meth:`SDFContact.pair_points`, every slot a point), taken in order as a closed polygon, with the centre circle of
    the pair's :class:`~redsim.effects.sdf.Torus` (the frame's xy plane, radius ``major``): the signed count of the
    polygon's edges that cross the circle's disk (+1 along the frame's z axis). Exact for a polygon that misses the
    circle itself."""
    start, end = ring, torch.roll(ring, -1, dims=2)
    z0, z1 = start[..., 2], end[..., 2]
    up, down = (z0 <= 0.0) & (z1 > 0.0), (z0 > 0.0) & (z1 <= 0.0)
    t = (z0 / torch.where(up | down, z0 - z1, torch.ones_like(z0))).unsqueeze(-1)
    at = start[..., :2] + t * (end[..., :2] - start[..., :2])  # where the edge meets the plane z = 0
    inside = (at * at).sum(-1) < float(effect.shape.major) ** 2
    return ((up & inside).to(ring.dtype) - (down & inside).to(ring.dtype)).sum(-1)


def _ring_contact(effect: SDFContact, x: Tensor, interlocked: Tensor, seed: Tensor) -> dict[str, Tensor]:
    """:func:`_contact`'s values and ``unlinked`` (module doc) of a ring contact, from one pass over its points: the
    pairs ``interlocked`` [pairs, 1] at the seed whose linking number is no longer ``seed``'s [pairs, 1]."""
    ring = effect.pair_points(x)  # [pairs, B, S, 3]
    clearance = (effect.shape.distance(ring) - effect.margin).amin(-1).amin(0)  # [B], as SDFContact.clearance
    changed = (linking_numbers(effect, ring) != seed) & interlocked  # [pairs, B]
    return {
        "penetration": (-clearance).clamp_min(0.0),
        "clearance": clearance,
        "unlinked": changed.sum(0).to(x.dtype),
    }


def _is_ring_contact(effect: Effect) -> bool:
    """A torus contact whose pair tables hold every slot (each pair's points can be read as a closed polygon)."""
    return isinstance(effect, SDFContact) and isinstance(effect.shape, Torus) and not effect.partial_slots


BLOCK_ELEMENTS = 262144
"""Rows x elements of one block of :meth:`Invariants.__call__` (1 MiB per float32 [rows, elements] tensor; blocks
of 33 rows were no faster on the cloth envs at 256 copies, and split 64 copies in two)."""

CHECKS: dict[type, Callable[..., dict[str, Tensor]]] = {
    RigidOrthogonality: _orthogonality,
    PointPairPenalty: _gap,
    NeoHookean: _fem,
    StVKMembrane: _membrane,
    SDFContact: _contact,
}
"""The check of each effect class, called with full configurations x [B, N]; effects of other classes
(gravity, loads, bending) have none."""


class Invariants:
    """The invariants of one scene (module doc), evaluated on full configurations x [B, N].

    Args:
        scene: The scene, in the dtype and device the configurations come in.
    """

    def __init__(self, scene: Scene) -> None:
        self._checks: list[tuple[Effect, Callable[..., dict[str, Tensor]]]] = [
            (effect, CHECKS[type(effect)]) for effect in scene.effects if type(effect) in CHECKS
        ]
        largest = max((effect.element_count for effect, _ in self._checks), default=1)
        self.block_rows = max(1, BLOCK_ELEMENTS // max(largest, 1))
        """Rows per block (module doc)."""
        seed = scene.full_positions(scene.q_seed.unsqueeze(0))
        self._links: dict[str, tuple[Tensor, Tensor]] = {}
        """Per ring contact's name: which of its pairs are interlocked at the seed [pairs, 1], their linking numbers."""
        for effect in scene.effects:
            if _is_ring_contact(effect):
                links = linking_numbers(effect, effect.pair_points(seed))  # [pairs, 1]
                if bool((links != 0).any()):
                    self._links[effect.name] = (links != 0, links)

    @torch.no_grad()
    def __call__(self, x: Tensor) -> dict[str, Tensor]:
        """Every invariant of the scene, each shape [B]."""
        blocks = [self._block(rows) for rows in x.split(self.block_rows)]
        if len(blocks) == 1:
            return blocks[0]
        return {key: torch.cat([block[key] for block in blocks]) for key in blocks[0]}

    def _block(self, x: Tensor) -> dict[str, Tensor]:
        out: dict[str, Tensor] = {}
        for effect, check in self._checks:
            links = self._links.get(effect.name)
            values = check(effect, x) if links is None else _ring_contact(effect, x, *links)
            for key, value in values.items():
                out[f"{effect.name}_{key}"] = value
        return out


__all__ = ["CHECKS", "Invariants", "linking_numbers"]
