"""Affine rigid bodies: 12 unconstrained numbers per body, kept rotational by a penalty (paper §5.1)."""

from __future__ import annotations

import torch
from torch import Tensor

from redsim.effects.base import Effect, per_element


class RigidOrthogonality(Effect):
    """E = stiffness * |R^T R - I|_F^2 per body, where a body's entries of x are ``[R | t]`` row-major.

    Args:
        name: Term name.
        body_dofs: The 12 entries of each body, shape [bodies, 12], int64.
        stiffness: Penalty weight [J], scalar or [bodies], finite and >= 0.
    """

    kind = "rigid_orthogonality"

    def __init__(self, name: str, body_dofs: Tensor, stiffness: float | Tensor) -> None:
        body_dofs = torch.as_tensor(body_dofs, dtype=torch.int64)
        if body_dofs.ndim != 2 or body_dofs.shape[1] != 12:
            raise ValueError(f"body_dofs must have shape [bodies, 12], got {tuple(body_dofs.shape)}")
        self.name = name
        self.element_dofs = body_dofs
        self.stiffness = per_element(stiffness, body_dofs.shape[0], f"stiffness of {name!r}")

    def element_energy(self, xe: Tensor, cond: Tensor | None = None, loads: Tensor | None = None) -> Tensor:
        B, T, _ = xe.shape
        R = xe.reshape(B, T, 3, 4)[..., :3]
        eye = torch.eye(3, dtype=xe.dtype, device=xe.device)
        defect = R.transpose(-1, -2) @ R - eye
        return self.stiffness * (defect * defect).sum((-1, -2))
