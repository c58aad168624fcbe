"""The neural subspace map f(z[, c]) -> q: an ordinary MLP.

A :class:`SubspaceMap` maps latent coordinates z [..., d] (and an optional condition c
[..., m]) to free configurations q [..., n] of one scene. The seeded exploration schedule of
the paper lives in the fitter (:mod:`redsim.trainers.fit`), never here. It saves as a
checkpoint of :mod:`redsim.subspace.checkpoint` (kind "neural").
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from redsim.subspace.checkpoint import write_checkpoint

ACTIVATIONS = {"elu": nn.ELU, "tanh": nn.Tanh, "relu": nn.ReLU, "silu": nn.SiLU}


@dataclass(frozen=True)
class SubspaceConfig:
    """Architecture of a subspace map; every count means what it says.

    Attributes:
        latent_dim: d, the size of z.
        output_dim: n, the scene's free DOF count.
        condition_dim: m, the size of the condition vector (0 for none).
        hidden_width: Units per hidden layer.
        hidden_layers: Number of hidden layers (the output layer is not counted).
        activation: One of ``ACTIVATIONS``.
        periodic: Latent indices entered as (cos z_i, sin z_i), so that z_i is an angle
            (e.g. a crank that turns all the way round).
    """

    latent_dim: int
    output_dim: int
    condition_dim: int = 0
    hidden_width: int = 128
    hidden_layers: int = 5
    activation: str = "elu"
    periodic: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.latent_dim < 1 or self.output_dim < 1 or self.condition_dim < 0:
            raise ValueError(
                f"bad dimensions: latent {self.latent_dim}, output {self.output_dim}, condition {self.condition_dim}"
            )
        if self.hidden_width < 1 or self.hidden_layers < 1:
            raise ValueError(
                f"need hidden_width >= 1 and hidden_layers >= 1, got {self.hidden_width}, {self.hidden_layers}"
            )
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"unknown activation {self.activation!r}; valid: {sorted(ACTIVATIONS)}")
        if any(not 0 <= i < self.latent_dim for i in self.periodic) or len(set(self.periodic)) != len(self.periodic):
            raise ValueError(f"periodic indices {list(self.periodic)} must be distinct and in [0, {self.latent_dim})")


class SubspaceMap(nn.Module):
    """ELU MLP f(z[, c]) -> q.

    Attributes:
        config: The architecture.
        metadata: Scene fingerprint, hyperparameters, metrics and reproduce command (JSON-able).
    """

    kind: ClassVar[str] = "neural"

    def __init__(self, config: SubspaceConfig, metadata: dict[str, Any] | None = None) -> None:
        super().__init__()
        self.config = config
        self.metadata: dict[str, Any] = dict(metadata or {})
        act = ACTIVATIONS[config.activation]
        width = config.hidden_width
        layers: list[nn.Module] = [
            nn.Linear(config.latent_dim + len(config.periodic) + config.condition_dim, width),
            act(),
        ]
        for _ in range(config.hidden_layers - 1):
            layers += [nn.Linear(width, width), act()]
        layers.append(nn.Linear(width, config.output_dim))
        self.mlp = nn.Sequential(*layers)
        periodic = torch.zeros(config.latent_dim, dtype=torch.bool)
        periodic[list(config.periodic)] = True
        self.register_buffer("periodic_mask", periodic, persistent=False)
        # the periodic entries by index: selecting them by the mask would read its count back to the host per call
        self.register_buffer("periodic_index", periodic.nonzero().flatten(), persistent=False)

    @property
    def latent_dim(self) -> int:
        return self.config.latent_dim

    def features(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """MLP input: z with periodic entries replaced by (cos, sin), then c."""
        if z.shape[-1] != self.config.latent_dim:
            raise ValueError(f"z must have {self.config.latent_dim} entries in its last dim, got {tuple(z.shape)}")
        parts = [z]
        if self.config.periodic:
            angles = z.index_select(-1, self.periodic_index)
            parts = [torch.where(self.periodic_mask, torch.cos(z), z), torch.sin(angles)]
        if self.config.condition_dim:
            if cond is None or cond.shape[-1] != self.config.condition_dim:
                raise ValueError(f"this subspace needs a condition of size {self.config.condition_dim}")
            parts.append(cond.expand(*z.shape[:-1], -1))
        elif cond is not None:
            raise ValueError("this subspace takes no condition")
        return torch.cat(parts, dim=-1)

    def forward(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """Configurations q [..., n] from latents z [..., d] (and conditions c [..., m])."""
        return self.mlp(self.features(z, cond))

    def hidden(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """The last hidden layer h(z, c) [..., w] (q = the output layer's affine map of it)."""
        hidden = self.features(z, cond)
        for layer in list(self.mlp)[:-1]:
            hidden = layer(hidden)
        return hidden

    def save(self, stem: str | Path) -> tuple[Path, Path]:
        """Write ``stem.pt`` (weights) and ``stem.json`` (config and metadata); returns both paths."""
        return write_checkpoint(self, stem, dataclasses.asdict(self.config))

    @classmethod
    def from_shapes(cls, shapes: dict[str, Any], metadata: dict[str, Any]) -> SubspaceMap:
        """An untrained map with the architecture ``shapes`` (a checkpoint's ``config``), for loading weights."""
        return cls(SubspaceConfig(**{**shapes, "periodic": tuple(shapes.get("periodic", ()))}), metadata)
