"""The autoencoder of the supervised baseline (paper supplement B.2), whose decoder is the subspace map.

Trained by :func:`redsim.baselines.train_autoencoder`; saved and loaded as checkpoints of kind
"autoencoder".
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from redsim.scene import Scene
from redsim.subspace.base import MapModule, check_latent, dtype_name
from redsim.subspace.neural import SubspaceConfig, SubspaceMap


def autoencoder_maps(n: int, dim: int, hidden_width: int, hidden_layers: int) -> tuple[SubspaceMap, SubspaceMap]:
    """Untrained encoder (n -> dim) and decoder (dim -> n) MLPs of the given size."""
    encoder = SubspaceMap(SubspaceConfig(n, dim, hidden_width=hidden_width, hidden_layers=hidden_layers))
    decoder = SubspaceMap(SubspaceConfig(dim, n, hidden_width=hidden_width, hidden_layers=hidden_layers))
    return encoder, decoder


class AutoencoderSubspace(MapModule):
    """An autoencoder whose decoder is the subspace map (paper supplement B.2).

    Calling the module decodes; :meth:`encode` maps configurations to latents. The encoder reads
    (q - input_mean) / input_scale.

    Args:
        encoder: MLP from n normalized coordinates to d latents (a :class:`SubspaceMap` with
            ``latent_dim = n``, ``output_dim = d``).
        decoder: MLP from d latents to q, the same architecture as the neural subspace map.
        input_mean: Mean state [configuration unit], shape [n].
        input_scale: Standard deviation of the states' entries about the mean, shape [].
        metadata: JSON-able description.
    """

    kind = "autoencoder"

    def __init__(
        self,
        encoder: SubspaceMap,
        decoder: SubspaceMap,
        input_mean: Tensor,
        input_scale: Tensor,
        metadata: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(metadata)
        n, d = decoder.config.output_dim, decoder.config.latent_dim
        if (encoder.config.latent_dim, encoder.config.output_dim) != (n, d) or input_mean.shape != (n,):
            raise ValueError(
                f"encoder must map {n} -> {d} and input_mean have shape [{n}], got encoder "
                f"{encoder.config.latent_dim} -> {encoder.config.output_dim}, input_mean {tuple(input_mean.shape)}"
            )
        self.encoder = encoder
        self.decoder = decoder
        self.register_buffer("input_mean", input_mean.detach().clone())
        self.register_buffer("input_scale", torch.as_tensor(input_scale, dtype=input_mean.dtype).detach().clone())

    @property
    def latent_dim(self) -> int:
        return self.decoder.latent_dim

    def encode(self, q: Tensor) -> Tensor:
        """Latents z [..., d] of configurations q [..., n]."""
        return self.encoder((q - self.input_mean) / self.input_scale)

    def forward(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """Configurations q [..., n] decoded from latents z [..., d]."""
        check_latent(z, self.latent_dim, cond)
        return self.decoder(z)

    def reconstruction_error(self, states: Tensor, scene: Scene) -> float:
        """Relative M-norm reconstruction error sqrt(sum |f(g(q)) - q|_M^2 / sum |q - mean|_M^2) over states [S, n]."""
        with torch.no_grad():
            states = states.to(self.input_mean.dtype)
            residual = self(self.encode(states)) - states
            spread = states - states.mean(0)
            return math.sqrt(float(scene.mass_norm_sq(residual).sum() / scene.mass_norm_sq(spread).sum()))

    def shapes(self) -> dict[str, Any]:
        config = self.decoder.config
        return {
            "latent_dim": config.latent_dim,
            "output_dim": config.output_dim,
            "hidden_width": config.hidden_width,
            "hidden_layers": config.hidden_layers,
            "dtype": dtype_name(self.input_mean.dtype),
        }

    @classmethod
    def from_shapes(cls, shapes: dict[str, Any], metadata: dict[str, Any]) -> AutoencoderSubspace:
        dtype = getattr(torch, shapes["dtype"])
        n, d = int(shapes["output_dim"]), int(shapes["latent_dim"])
        encoder, decoder = autoencoder_maps(n, d, int(shapes["hidden_width"]), int(shapes["hidden_layers"]))
        return cls(
            encoder.to(dtype), decoder.to(dtype), torch.zeros(n, dtype=dtype), torch.ones((), dtype=dtype), metadata
        )
