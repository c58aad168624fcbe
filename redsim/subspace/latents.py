"""Latent coordinates: how they are sampled, which are angles, and how pairs of them compare.

:func:`pair_log_ratios` is the pair term of the fitting loss (:mod:`redsim.trainers.fit`) and
of the stretch metric (:func:`redsim.metrics.stretch_stats`); it lives here, beside the maps,
so that fitting does not import the solver stack.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from redsim.scene import Scene


def periodic_latents(subspace: Any) -> tuple[int, ...]:
    """Indices of a map's latents that are angles (``subspace.config.periodic``; () for other maps)."""
    return tuple(getattr(getattr(subspace, "config", None), "periodic", ()))


def sample_latents(
    count: int,
    latent_dim: int,
    periodic: tuple[int, ...] = (),
    *,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> Tensor:
    """Latent samples [count, d]: z ~ N(0, 1) per entry, angles (``periodic``) uniform in [-pi, pi).

    Angles are uniform so that every point of the loop they parameterize is sampled alike (a
    normal angle would leave the far side of the circle, near +-pi, almost unseen).
    """
    z = torch.randn(count, latent_dim, generator=generator, dtype=dtype, device=device)
    if periodic:
        angles = torch.rand(count, len(periodic), generator=generator, dtype=dtype, device=device)
        z[:, list(periodic)] = (2.0 * angles - 1.0) * math.pi
    return z


def pair_log_ratios(y: Tensor, z: Tensor, scene: Scene, sigma: float, periodic: Sequence[int] = ()) -> Tensor:
    """log(|y_i - y_j|_M / (sigma |z_i - z_j|)) for all pairs i < j, shape [B(B-1)/2].

    M-norm distances come from the B x B Gram matrix of the centred batch (never a B x B x n
    tensor; centring keeps small differences in float32). Periodic latents are angles: their
    difference is wrapped into [-pi, pi) (the distance along the circle), so two samples
    2 pi apart count as the same point.

    Args:
        y: Map outputs, shape [B, n].
        z: Latents, shape [B, d].
        scene: Supplies the mass matrix (in y's dtype).
        sigma: Scale σ [the unit of |q|_M per unit z].
        periodic: Indices of the latents that are angles.
    """
    y = y - y.mean(0, keepdim=True)
    gram = y @ scene.mass_matvec(y).T
    diag = torch.arange(y.shape[0], device=y.device)
    sq = gram[diag, diag]  # not gram.diagonal(): its torch.compile lowering warns in torch 2.13
    i, j = torch.triu_indices(y.shape[0], y.shape[0], offset=1, device=y.device)
    dq2 = (sq[i] + sq[j] - 2.0 * gram[i, j]).clamp_min(torch.finfo(y.dtype).tiny)
    dz = z[i] - z[j]
    if periodic:
        angle = torch.zeros(z.shape[-1], dtype=torch.bool, device=z.device)
        angle[list(periodic)] = True
        dz = torch.where(angle, torch.remainder(dz + math.pi, 2.0 * math.pi) - math.pi, dz)
    dz2 = (dz**2).sum(-1).clamp_min(torch.finfo(z.dtype).tiny)  # equal samples do occur (d = 1, float32)
    return 0.5 * (torch.log(dq2) - torch.log(dz2)) - math.log(sigma)
