"""Strain of a map's states: linear subspaces of a swinging stiff body shear where neural ones rotate."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from redsim.effects.elastic import NeoHookean, deformation_gradient
from redsim.metrics.common import Subspace, check_count, configurations, latent_space, latents, summary
from redsim.scene import Scene


def nonrigid_strain(
    scene: Scene, subspace: Subspace, *, samples: int = 256, seed: int = 0, cond: Tensor | None = None
) -> dict[str, Any]:
    """Mean Green strain of subspace states of a FEM scene (figure "rigidity").

    Per state: the rest-volume-weighted mean over all neo-Hookean elements of
    |E|_F = |F^T F - I|_F / 2, with F the element's deformation gradient. It is 0 for rigid
    motions of the rest shape, and about |strain| for small deformations; linear subspaces of a
    swinging stiff body shear (strain grows with the rotation angle) where neural ones rotate.

    Args:
        scene: A scene with :class:`redsim.effects.NeoHookean` effects.
        subspace: The map (module doc).
        samples: Number of latent samples z ~ N(0, I) (>= 1).
        seed: Seed of the latent samples.
        cond: Condition of a conditional map; default: the scene's.

    Returns:
        ``mean``, ``median``, ``max`` over the samples, ``seed_strain`` (of q_seed), ``samples``, ``seed``.

    Raises:
        ValueError: for a scene without neo-Hookean elements.
    """
    check_count("samples", samples, 1)
    space = latent_space(scene, subspace, cond)
    scene64 = space.scene
    fem = [e for e in scene64.effects if isinstance(e, NeoHookean)]
    if not fem:
        raise ValueError(
            f"scene {scene.name!r} has no neo-Hookean (FEM) effects; its effects are {[e.name for e in scene.effects]}"
        )
    z = latents(samples, space, seed)
    strain = torch.cat([_mean_strain(scene64, fem, q) for q in configurations(space, z)])
    seed_strain = float(_mean_strain(scene64, fem, scene64.q_seed.unsqueeze(0))[0])
    return {
        "samples": samples,
        "seed": seed,
        **summary(strain, ("mean", "median", "max")),
        "seed_strain": seed_strain,
    }


def _mean_strain(scene: Scene, effects: list[NeoHookean], q: Tensor) -> Tensor:
    """Rest-volume-weighted mean |F^T F - I|_F / 2 over the elements of ``effects``, shape [B], for q [B, n]."""
    x = scene.full_positions(q)
    total = q.new_zeros(q.shape[0])
    volume = 0.0
    for effect in effects:
        D = effect.dim
        xe = x[:, effect.element_dofs].reshape(q.shape[0], -1, D + 1, D)
        F = deformation_gradient(xe, effect.shape_gradients)
        strain = torch.linalg.matrix_norm(F.transpose(-1, -2) @ F - torch.eye(D, dtype=F.dtype)) / 2.0
        total = total + strain @ effect.rest_volume
        volume += float(effect.rest_volume.sum())
    return total / volume
