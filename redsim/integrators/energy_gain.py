"""The ``energy_gain`` test: a step whose K + E rose by more than the loads' work on it, beyond round-off.

Implicit Euler dissipates: a converged step of a convex energy satisfies
K_{t+1} + E_{t+1} - (K_t + E_t) <= W_t - |v_{t+1} - v_t|_M^2 / 2, with W_t = F . (p_{t+1} - p_t)
the work of the step's (constant) handle loads. A rise beyond W_t is an artefact: a non-convex
region the step jumped across (a contact entered at speed, a buckling energy), a map's curvature
(the minimum over f(z) is not one over q), or an inexact solve. It is reported, not acted on: the
state is finite and usable. Both steppers say it per step: the latent runtime
(:class:`redsim.runtime.StepStats`) and the reference (:class:`redsim.integrators.StepInfo`).
"""

from __future__ import annotations

import torch
from torch import Tensor

ENERGY_ROUNDOFF = 1000.0
"""Round-off allowance of the ``energy_gain`` test, in eps of the dtype times the energies summed [J]."""


def energy_gain_tolerance(
    mechanical_now: Tensor, mechanical_next: Tensor, work: Tensor, inexact: Tensor, eps: float
) -> Tensor:
    """The rise [B] [J] :func:`energy_gain_states` allows: ``inexact`` plus the round-off of the sums (its doc)."""
    return inexact + ENERGY_ROUNDOFF * eps * (mechanical_now.abs() + mechanical_next.abs() + work.abs())


def energy_gain_states(
    mechanical_now: Tensor, mechanical_next: Tensor, work: Tensor, inexact: Tensor, eps: float
) -> Tensor:
    """States [B] (bool) whose step raised K + E by more than the loads' work on it, beyond round-off.

    The tolerance [J] is ``inexact`` (|dPhi/du| |u_{t+1} - u_t|: what the solve's leftover gradient
    can put into the balance; an exact minimum has none) plus ENERGY_ROUNDOFF ``eps`` (|K_t + E_t| +
    |K_{t+1} + E_{t+1}| + |W_t|), the round-off of the sums. A non-finite gain counts as a gain.

    Args:
        mechanical_now: K_t + E(q_t) [B] [J].
        mechanical_next: K_{t+1} + E(q_{t+1}) [B] [J].
        work: W_t [B] [J].
        inexact: [B] [J], see above; a caller adds the round-off of E itself where its terms cancel (an elastic
            solid near rest: :attr:`redsim.integrators.SceneConstants.energy_noise`), which eps |K + E| misses.
        eps: Machine epsilon of the dtype the energies were computed in.
    """
    gain = mechanical_next - mechanical_now - work
    return ~torch.isfinite(gain) | (gain > energy_gain_tolerance(mechanical_now, mechanical_next, work, inexact, eps))


__all__ = ["ENERGY_ROUNDOFF", "energy_gain_states", "energy_gain_tolerance"]
