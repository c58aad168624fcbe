"""The per-state flags of a latent step a user can act on: ``out_of_range``, ``diverged`` and ``energy_gain``.

``energy_gain`` is the reference integrator's test too (:mod:`redsim.integrators.energy_gain`), re-exported here.

None of them is hidden or printed: they come back as [B] bool tensors in
:class:`redsim.runtime.stepper.StepStats`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from redsim.integrators.energy_gain import ENERGY_ROUNDOFF, energy_gain_states, energy_gain_tolerance
from redsim.scene import ConditionSpace

LATENT_RANGE = 4.0
"""A map was fitted on z ~ N(0, I): |z| beyond LATENT_RANGE * sqrt(d) (periodic latents left out) is out of range."""
DIVERGENCE_MARGIN = 1.0
"""A step diverged when its potential or kinetic energy changed by more than DIVERGENCE_MARGIN * F L (see below)."""


def out_of_range_states(
    z: Tensor, periodic: tuple[int, ...], cond: Tensor | None, space: ConditionSpace | None
) -> Tensor:
    """States [B] (bool) whose z [B, d] (or any of z [B, K, d]) or condition [B, m] is outside the fitted region.

    z is out of range when |z_free| > LATENT_RANGE sqrt(d_free) over its non-periodic entries
    (angles go round, they are never out of range); a condition when any entry is outside the
    condition space's [low, high].
    """
    z = z if z.ndim == 3 else z.unsqueeze(1)
    d = z.shape[-1]
    keep = [i for i in range(d) if i not in set(periodic)]
    out = ~torch.isfinite(z).all(-1).all(-1)
    if keep:
        norm = torch.linalg.vector_norm(z[..., keep], dim=-1)
        out = out | (norm > LATENT_RANGE * math.sqrt(len(keep))).any(-1)
    if cond is not None and space is not None:
        low = space.low.to(cond)
        high = space.high.to(cond)
        out = out | ((cond < low) | (cond > high)).any(-1)
    return out


def diverged_states(
    phi_now: Tensor,
    phi_next: Tensor,
    kinetic_now: Tensor,
    kinetic_next: Tensor,
    inertia_next: Tensor,
    allowance: Tensor,
    noise: Tensor,
) -> Tensor:
    """States [B] (bool) whose step gained more than a step could have, or is not finite.

    From the step's incremental potential Phi = inertia + U' (U' = potential - load work [J]) at
    q_t (where the inertia term is the kinetic energy K_t) and at q_{t+1}, and the kinetic energy
    K_{t+1} = |q_{t+1} - q_t|_M^2 / (2 h^2):

    - Phi(q_{t+1}) > Phi(q_t) + noise: the solve ended above staying put, a point every step can
      reach (the extrapolated start fell into a worse basin: a tunnelled contact, a map fold);
    - |U'(q_{t+1}) - U'(q_t)| or K_{t+1} - K_t above DIVERGENCE_MARGIN * ``allowance`` = F L: more
      energy than the step's force scale F (>= |diag M| L / h^2, the force that crosses the scene
      in one step) does over the scene size L.

    A non-finite Phi or K, at either end, counts as diverged (a step from a z_t without a finite energy cannot be
    checked against it). All arguments are [B] tensors [J].
    """
    finite = torch.isfinite(torch.stack([phi_now, phi_next, kinetic_now, kinetic_next])).all(0)
    worse = phi_next > phi_now + noise
    released = ((phi_next - inertia_next) - (phi_now - kinetic_now)).abs() > DIVERGENCE_MARGIN * allowance
    faster = kinetic_next - kinetic_now > DIVERGENCE_MARGIN * allowance
    return ~finite | worse | released | faster


__all__ = [
    "DIVERGENCE_MARGIN",
    "ENERGY_ROUNDOFF",
    "LATENT_RANGE",
    "diverged_states",
    "energy_gain_states",
    "energy_gain_tolerance",
    "out_of_range_states",
]
