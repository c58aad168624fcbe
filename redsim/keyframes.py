"""Latent keyframe paths: closed curves through keyframes, for animations in latent space."""

from __future__ import annotations

import torch


def catmull_rom_loop(keys: torch.Tensor, frames: int) -> torch.Tensor:
    """A closed uniform Catmull-Rom spline through ``keys`` [K, d], sampled at ``frames`` points [frames, d].

    Point ``i * frames / K`` of the result is key i exactly; the curve closes from the last key
    back to the first with a continuous tangent.
    """
    if keys.ndim != 2 or keys.shape[0] < 2:
        raise ValueError(f"keys must have shape [K, d] with K >= 2, got {tuple(keys.shape)}")
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    K = keys.shape[0]
    t = torch.arange(frames, dtype=keys.dtype) * K / frames
    i = t.floor().long()
    u = (t - i).unsqueeze(-1)
    p0, p1, p2, p3 = (keys[(i + k) % K] for k in (-1, 0, 1, 2))
    return 0.5 * (2 * p1 + (p2 - p0) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u**2 + (3 * p1 - p0 - 3 * p2 + p3) * u**3)
