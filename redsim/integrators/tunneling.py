"""The ``tunneled`` test: a step whose straight path passes through a contact that neither end shows.

A penalty contact acts only on the states a solve visits. A time step starts at the inertial target
qbar = 2 q_t - q_{t-1}, so a state that moves farther in one step than a contact shape is thick lands
beyond it, converged and without a contact force: the chain thrown at its hook at 10 m/s moves 0.2 m in
a 0.02 s step against a wire 0.03 m thick (tube and margins), its full-space step ends above the hook and
the chain flies off, every step converged and no energy gained. Continuous collision detection would
stop such a step; this test reports it.

It samples the straight path x_t + s (x_{t+1} - x_t), 0 < s < 1, at a spacing of at most a quarter of a
contact's ``feature_size`` in any entry the contact reads, and flags a state whose path gets deeper
into a contact (its ``clearance``: the smallest signed distance of a point beyond the margin) than both
ends by more than half that feature size. A step that moves no entry a contact reads by half its feature
size is not sampled (nothing that thick can be crossed), so ordinary steps cost one comparison per
contact. Rotation entries are interpolated as entries (a chord, not an arc): the test is a detector, not
a proof. Reported per step (:class:`redsim.integrators.StepInfo`, the envs' ``info["tunneled"]``), never
acted on.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from redsim.scene import Scene

TUNNEL_SAMPLES = 256
"""Most states sampled on one step's path per contact (a faster step is sampled more coarsely)."""


class TunnelTest:
    """The test of the module doc for one scene: its contacts and the entries each reads, gathered once.

    Call it with full configurations ``x_from`` [B, N] and ``x_to`` [B, N] (one step apart) for the states [B]
    (bool) whose step passed through a contact. Non-finite states are not flagged here (they are ``diverged``).
    """

    def __init__(self, scene: Scene) -> None:
        self.contacts = [
            (effect, effect.element_dofs.reshape(-1).unique(), float(effect.feature_size))
            for effect in scene.effects
            if math.isfinite(effect.feature_size) and hasattr(effect, "clearance")
        ]

    def __call__(self, x_from: Tensor, x_to: Tensor) -> Tensor:
        flagged = torch.zeros(x_from.shape[0], dtype=torch.bool, device=x_from.device)
        with torch.no_grad():
            for effect, dofs, size in self.contacts:
                dofs = dofs.to(x_from.device)
                move = (x_to.index_select(1, dofs) - x_from.index_select(1, dofs)).abs().amax(-1)  # [B]
                for row in torch.nonzero(move > 0.5 * size).flatten().tolist():
                    samples = min(TUNNEL_SAMPLES, math.ceil(float(move[row]) / (0.25 * size)))
                    s = torch.arange(1, samples + 1, dtype=x_from.dtype, device=x_from.device) / (samples + 1)
                    path = x_from[row] + s[:, None] * (x_to[row] - x_from[row])  # [samples, N]
                    ends = effect.clearance(torch.stack([x_from[row], x_to[row]])).amin()
                    flagged[row] |= bool(effect.clearance(path).amin() < ends - 0.5 * size)
        return flagged


__all__ = ["TUNNEL_SAMPLES", "TunnelTest"]
