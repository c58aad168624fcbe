"""The ``tunneled`` test: a step whose path passes through a contact that neither end shows.

A penalty contact acts only on the states a solve visits. A time step starts at the inertial target
qbar = 2 q_t - q_{t-1}, so a state that moves farther in one step than a contact is thick lands beyond
it, converged and without a contact force: the chain thrown at its hook at 10 m/s moves 0.2 m in a
0.02 s step across a wire whose contact is 0.03 m deep from its surface to the far side of its centre
line (``feature_size``: the tube radius and both margins), its full-space step ends above the hook and
the chain flies off, every step converged and no energy gained. Continuous collision detection would
stop such a step; this test reports it.

For every point of an :class:`~redsim.effects.SDFContact` it takes the point's coordinates in the frame
that carries the shape at both ends of the step (exact there: each end's rotation is a rotation) and
samples the straight path between them, at most a quarter of the contact's ``feature_size`` apart
(at most :data:`TUNNEL_SAMPLES` samples). A state is flagged where some point's path gets deeper into
the contact (the shape's signed distance less the margin) than both of that point's ends by more than
half the ``feature_size``, and inside the shape itself by more than half its thinnest part (a chord that
only grazes the margin, as a point swept along an arc by a fast turn does, is not a crossing). Only
points that moved that far relative to the shape are sampled, so ordinary steps cost one gather per
contact. The relative path is a chord (a point swept along an arc by a fast turn of its frame is checked
along the chord of that arc), so the test is a detector, not a proof.
Reported per step (:class:`redsim.integrators.StepInfo`, the envs' ``info["tunneled"]``), never acted on.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from redsim.effects import SDFContact
from redsim.effects.base import gather_elements
from redsim.scene import Scene

TUNNEL_SAMPLES = 256
"""Most samples of one point's path in a step (a faster point is sampled more coarsely)."""
SAMPLED_POINTS = 1 << 20
"""Most sampled point positions evaluated at once (a blown-up batch is checked in chunks of this size)."""


class TunnelTest:
    """The test of the module doc for one scene's :class:`SDFContact` effects (the contacts with a finite
    ``feature_size``; the others have no thin part to cross).

    Call it with full configurations ``x_from`` [B, N] and ``x_to`` [B, N] (one step apart), and optionally
    ``rows`` [B] (bool: the states to test, e.g. those not ``diverged``), for the states [B] (bool) whose step
    passed through a contact. States that are not finite at either end are not tested (they are ``diverged``).
    """

    def __init__(self, scene: Scene) -> None:
        self.contacts = [e for e in scene.effects if isinstance(e, SDFContact) and math.isfinite(e.feature_size)]

    def __call__(self, x_from: Tensor, x_to: Tensor, rows: Tensor | None = None) -> Tensor:
        flagged = torch.zeros(x_from.shape[0], dtype=torch.bool, device=x_from.device)
        tested = torch.isfinite(x_from).all(-1) & torch.isfinite(x_to).all(-1)
        if rows is not None:
            tested &= rows.to(tested.device)
        if not self.contacts or not bool(tested.any()):
            return flagged
        with torch.no_grad():
            for effect in self.contacts:
                flagged |= _crossed(effect, x_from, x_to, tested)
        return flagged


def _crossed(effect: SDFContact, x_from: Tensor, x_to: Tensor, tested: Tensor) -> Tensor:
    """States [B] of ``tested`` where a point of ``effect`` passed through its shape (module doc)."""
    size, margin, core = float(effect.feature_size), float(effect.margin), 0.5 * float(effect.shape.feature_size)
    a = effect.local_points(gather_elements(x_from, effect.element_dofs))  # [B, P, 3]
    b = effect.local_points(gather_elements(x_to, effect.element_dofs))
    move = torch.linalg.vector_norm(b - a, dim=-1)  # [B, P] [m], relative to the shape
    state, point = torch.nonzero((move > 0.5 * size) & tested[:, None], as_tuple=True)
    flagged = torch.zeros(x_from.shape[0], dtype=torch.bool, device=x_from.device)
    if not state.numel():
        return flagged
    start, end = a[state, point], b[state, point]  # [M, 3]
    samples = min(TUNNEL_SAMPLES, math.ceil(float(move[state, point].max()) / (0.25 * size)))
    s = torch.arange(1, samples + 1, dtype=a.dtype, device=a.device)[:, None, None] / (samples + 1)
    ends = torch.minimum(effect.shape.distance(start), effect.shape.distance(end)) - margin  # [M]
    chunk = max(1, SAMPLED_POINTS // samples)
    for i in range(0, start.shape[0], chunk):
        path = start[i : i + chunk] + s * (end[i : i + chunk] - start[i : i + chunk])  # [samples, m, 3]
        deepest = effect.shape.distance(path).amin(0)  # [m], the signed distance
        through = (deepest < -core) & (deepest - margin < ends[i : i + chunk] - 0.5 * size)
        flagged[state[i : i + chunk][through]] = True
    return flagged


__all__ = ["SAMPLED_POINTS", "TUNNEL_SAMPLES", "TunnelTest"]
