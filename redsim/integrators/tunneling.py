"""The ``tunneled`` test: a step whose path passes through a contact that neither end shows.

A penalty contact acts only on the states a solve visits. A time step starts at the inertial target
qbar = 2 q_t - q_{t-1}, so a state that moves farther in one step than a contact is thick lands beyond
it, converged and without a contact force: the chain thrown at its hook at 10 m/s moves 0.2 m in a
0.02 s step across a wire whose contact is 0.03 m deep from its surface to the far side of its centre
line (``feature_size``: the tube radius and both margins), its full-space step ends above the hook and
the chain flies off, every step converged and no energy gained. Continuous collision detection would
stop such a step; this test reports it.

For every point of an :class:`~redsim.effects.SDFContact` it takes the point's coordinates in the frame that carries
the shape at both ends of the step (exact there: each end's rotation is a rotation) and samples the part of the
straight path between them that lies inside the ball holding the shape (outside it the signed distance is positive),
at most an eighth of the smaller of the contact's ``feature_size`` and its shape's thinnest part apart
(:func:`sample_limit` bounds the samples of a leg by the ball's diameter). A state is flagged where some point's path
gets deeper into the contact (the shape's signed distance less the margin) than both of that point's ends by more than
half the ``feature_size`` (or the margin and the core, where less), and inside the shape itself deeper than its core:
half its thinnest part, less where the contact's points are sparse (:func:`core_depth`; a chord that only grazes the
margin, as a point swept along an arc by a fast turn does, is not a crossing). Only points that moved that far
relative to the shape are sampled, so ordinary steps cost one gather per contact. The relative path is a chord (a
point swept along an arc by a fast turn of its frame is checked along the chord of that arc), so the test is a
detector, not a proof.
Reported per step (:class:`redsim.integrators.StepInfo`, the envs' ``info["tunneled"]``); a full-space
ImplicitEuler step it flags is solved again within a trust radius (``retry_tunneled``), a latent one is not. That
solve's own path is known (the states it accepted, each a short move): :meth:`TunnelTest.along` applies the same
test to it in place of the chord, which cuts through a convex shape that a point went round (cloth wrapped round
its ball in one long step).
"""

from __future__ import annotations

import math

import scipy.spatial
import torch
from torch import Tensor

from redsim.effects import SDFContact
from redsim.scene import Scene

TUNNEL_SAMPLES = 256
"""Fewest samples :func:`sample_limit` allows a leg of one point's path (the most for an unbounded shape)."""
SAMPLED_POINTS = 1 << 20
"""Most sampled point positions evaluated at once (a blown-up batch is checked in chunks of this size)."""


class TunnelTest:
    """The test of the module doc for one scene's :class:`SDFContact` effects (the contacts with a finite
    ``feature_size``; the others have no thin part to cross).

    Call it with full configurations ``x_from`` [B, N] and ``x_to`` [B, N] (one step apart), and optionally
    ``rows`` [B] (bool: the states to test, e.g. those not ``diverged``), for the states [B] (bool) whose step
    passed through a contact. States that are not finite at either end are not tested (they are ``diverged``).
    The points of ``x_to`` are kept for the next call: where its ``x_from`` is that very tensor, unchanged (an
    env's next step), they are not computed again.
    """

    def __init__(self, scene: Scene) -> None:
        self.contacts = [e for e in scene.effects if isinstance(e, SDFContact) and math.isfinite(e.feature_size)]
        self._kept: tuple[Tensor, int, list[tuple[Tensor, Tensor]]] | None = None
        seed = scene.full_positions(scene.q_seed.unsqueeze(0)) if self.contacts else None
        self.cores = [core_depth(e, sample_gap(e, seed)) for e in self.contacts]
        """Per contact, how deep [m] into its shape a path must go to be a crossing (:func:`core_depth`)."""

    def __call__(self, x_from: Tensor, x_to: Tensor, rows: Tensor | None = None) -> Tensor:
        flagged = torch.zeros(x_from.shape[0], dtype=torch.bool, device=x_from.device)
        if not self.contacts:
            return flagged
        tested = torch.ones_like(flagged) if rows is None else rows.to(flagged.device, torch.bool)
        with torch.no_grad():
            kept = self._kept
            if kept is not None and kept[0] is x_from and kept[0]._version == kept[1]:
                starts = kept[2]
            else:
                starts = [e.frame_points(x_from) for e in self.contacts]
            ends = [e.frame_points(x_to) for e in self.contacts]
            self._kept = (x_to, x_to._version, ends)
            if bool(tested.any()):
                for effect, core, (a, valid), (b, _) in zip(self.contacts, self.cores, starts, ends, strict=True):
                    flagged |= _crossed(effect, core, a, b, valid, tested)
        return flagged

    def along(self, x: Tensor) -> bool:
        """Whether one state's path through the full configurations x [K, N] (K >= 2: the step's start, the states it
        went through, its end) passed through a contact: the test of the module doc with the path through every
        state in place of the chord between the ends (for the points that moved far enough between the ends)."""
        flagged = False
        with torch.no_grad():
            for effect, core in zip(self.contacts, self.cores, strict=True):
                points, valid = effect.frame_points(x)  # [K, M, 3]
                (point,) = torch.nonzero(_far(effect, points[:1], points[-1:])[0] & valid, as_tuple=True)
                if point.numel():
                    path = points[:, point]
                    deepest = _deepest(effect, path)
                    flagged |= bool(_through(effect, core, path[0], path[-1], deepest).any())
        return flagged


def path_spacing(effect: SDFContact) -> float:
    """Most distance [m] between two samples of a point's path: an eighth of the smaller of the contact's
    ``feature_size`` and its shape's thinnest part."""
    return 0.125 * min(float(effect.feature_size), float(effect.shape.feature_size))


def sample_gap(effect: SDFContact, x: Tensor) -> float:
    """The largest distance [m] from one of ``effect``'s points to its nearest neighbour among the points of its own
    frame pair (a chain link's centre-line samples against its neighbour), in the full configuration x [1, N]: a
    wire crossing another between two samples brings one within half of it of the other's centre line."""
    points, valid = effect.frame_points(x)
    groups = [points[0, valid]] if effect.single_frame else list(points[0].reshape(*effect.pair_mask.shape, 3))
    masks = [None] if effect.single_frame else list(effect.pair_mask > 0)
    gap = 0.0
    for group, mask in zip(groups, masks, strict=True):
        group = group if mask is None else group[mask]
        if group.shape[0] > 1:
            nearest, _ = scipy.spatial.cKDTree(group.detach().cpu().double().numpy()).query(
                group.detach().cpu().double().numpy(), k=2
            )
            gap = max(gap, float(nearest[:, 1].max()))
    return gap


def core_depth(effect: SDFContact, gap: float) -> float:
    """How deep [m] into its shape a point's sampled path must go to count as a crossing: half the shape's thinnest
    part t, or less where the points are sparse, t - gap / 2 - :func:`path_spacing` / 2 (a wire crossing another
    between two samples ``gap`` apart is only sure to bring one that deep), but at least t / 4 (a chord of a fast
    turn that grazes the margin is not a crossing)."""
    thin = float(effect.shape.feature_size)
    return max(0.25 * thin, min(0.5 * thin, thin - 0.5 * gap - 0.5 * path_spacing(effect)))


def _crossed(effect: SDFContact, core: float, a: Tensor, b: Tensor, valid: Tensor, tested: Tensor) -> Tensor:
    """States [B] of ``tested`` where a point of ``effect`` passed through its shape deeper than ``core`` [m] (module
    doc), from its points in their shapes' frames at the step's start ``a`` and end ``b`` [B, M, 3] (rows ``valid``
    [M] are points)."""
    state, point = torch.nonzero(_far(effect, a, b) & tested[:, None] & valid, as_tuple=True)
    flagged = torch.zeros(a.shape[0], dtype=torch.bool, device=a.device)
    if not state.numel():
        return flagged
    start, end = a[state, point], b[state, point]  # [m, 3]
    deepest = _deepest(effect, torch.stack([start, end]))
    flagged[state[_through(effect, core, start, end, deepest)]] = True
    return flagged


def _far(effect: SDFContact, a: Tensor, b: Tensor) -> Tensor:
    """Which points [B, M] moved from ``a`` to ``b`` [B, M, 3] (in their shapes' frames) by more than half the
    contact's ``feature_size``: those whose path is sampled (a shorter one cannot cross)."""
    step = b - a
    move = (step * step).sum(-1)  # [B, M] [m^2] (vector_norm on this strided layout: 100x slower)
    return (move > (0.5 * float(effect.feature_size)) ** 2) & torch.isfinite(move)  # a non-finite state is diverged


def _deepest(effect: SDFContact, path: Tensor) -> Tensor:
    """The least signed distance [m], [m], of ``effect``'s shape along each point's path through the positions
    ``path`` [K, m, 3] (K >= 2, in the frame that carries the shape), each leg sampled straight at most
    :func:`path_spacing` apart."""
    start, end = _inside_bounding_ball(effect.shape.bounding_radius, path[:-1], path[1:])
    legs = end - start  # [K - 1, m, 3]
    longest = float((legs * legs).sum(-1).max())
    # the deepest sample lies within spacing / 2 of the chord's deepest point and the signed distance is 1-Lipschitz
    # (a quarter of the feature size apart, a 0.05 m move across the mini chain's 0.01 m wire went 5.1 mm deep with its
    # deepest sample short of 5 mm)
    samples = min(sample_limit(effect), math.ceil(math.sqrt(longest) / path_spacing(effect)))
    s = torch.arange(0, samples + 2, dtype=path.dtype, device=path.device)[:, None, None, None] / (samples + 1)
    chunk = max(1, SAMPLED_POINTS // ((samples + 2) * legs.shape[0]))
    deepest = []
    for i in range(0, path.shape[1], chunk):
        samples_of = start[:, i : i + chunk] + s * legs[:, i : i + chunk]  # [samples + 2, K - 1, m, 3]
        deepest.append(effect.shape.distance(samples_of).flatten(0, 1).amin(0))
    deepest = torch.cat(deepest)
    if path.shape[0] > 2:  # the states between the ends
        deepest = torch.minimum(deepest, effect.shape.distance(path[1:-1]).amin(0))
    return deepest


def sample_limit(effect: SDFContact) -> int:
    """Most samples of one leg of a point's path: enough to sample the shape's bounding ball's diameter
    :func:`path_spacing` apart (a clipped leg is no longer: a 2 m plate 1 cm thick is sampled finely across), at least
    :data:`TUNNEL_SAMPLES`, which alone bounds an unbounded shape's legs (a plane's distance is linear along a leg)."""
    radius = float(effect.shape.bounding_radius)
    if not math.isfinite(radius):
        return TUNNEL_SAMPLES
    return max(TUNNEL_SAMPLES, math.ceil(2.0 * radius / path_spacing(effect)))


def _inside_bounding_ball(radius: float, start: Tensor, end: Tensor) -> tuple[Tensor, Tensor]:
    """The part of each straight leg from ``start`` to ``end`` [..., 3] (in the shape's frame) inside the ball of
    ``radius`` [m] about the origin that holds the shape, as its new ends [..., 3]; a leg that misses the ball keeps
    only its point nearest the ball (outside it the signed distance is positive, so no crossing lies there). Only that
    part is sampled, so a point thrown metres past a thin wire in one step is sampled as finely across the wire as a
    slow one (sampling the whole leg at most :data:`TUNNEL_SAMPLES` times stepped over it)."""
    if not math.isfinite(radius):
        return start, end
    leg = end - start
    length_sq = (leg * leg).sum(-1)
    safe = torch.where(length_sq > 0, length_sq, torch.ones_like(length_sq))
    # the line's point nearest the origin, then half the chord through the ball (in place of the quadratic's roots,
    # whose discriminant b^2 - a c cancels in float32: a 300 m leg kept one point, a 1e6 m one 537 m)
    nearest = -(start * leg).sum(-1) / safe  # [...] (0 at the start, 1 at the end)
    closest = start + nearest[..., None] * leg
    half = torch.sqrt(torch.clamp(radius * radius - (closest * closest).sum(-1), min=0.0) / safe)
    # a product past the dtype's range (a float32 point 1e20 m out) leaves NaN: the whole leg is kept, as before
    enter = torch.clamp(nearest - half, 0.0, 1.0).nan_to_num(0.0)
    leave = torch.clamp(nearest + half, 0.0, 1.0).nan_to_num(1.0)
    return start + enter[..., None] * leg, start + leave[..., None] * leg


def _through(effect: SDFContact, core: float, start: Tensor, end: Tensor, deepest: Tensor) -> Tensor:
    """Which paths [m] from ``start`` to ``end`` [m, 3], ``deepest`` [m] [m] at their deepest, crossed the shape:
    deeper than ``core`` inside it, and deeper into the contact than both ends by the rise (module doc)."""
    size, margin = float(effect.feature_size), float(effect.margin)
    ends = torch.minimum(effect.shape.distance(start), effect.shape.distance(end)) - margin  # [m]
    rise = min(0.5 * size, margin + core)  # from the margin's edge to the core at least
    return (deepest < -core) & (deepest - margin < ends - rise)


__all__ = ["SAMPLED_POINTS", "TUNNEL_SAMPLES", "TunnelTest", "sample_limit"]
