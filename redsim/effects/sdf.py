"""Analytic signed distances [m] in a shape's own frame; negative inside.

Each shape maps local points [..., 3] to distances [...]. Square roots carry a tiny
``smoothing`` so gradients stay finite on axes and at centres.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

_SMOOTHING = 1e-12  # [m^2]


def _norm(v: Tensor) -> Tensor:
    return torch.sqrt((v * v).sum(-1) + _SMOOTHING)


@dataclass(frozen=True)
class Sphere:
    """Ball of ``radius`` [m] centred at the origin."""

    radius: float

    @property
    def feature_size(self) -> float:
        """Thinnest part [m]: a point moving further than this in one step may pass through."""
        return float(self.radius)

    def distance(self, p: Tensor) -> Tensor:
        return _norm(p) - self.radius


@dataclass(frozen=True)
class Plane:
    """Half-space {p : normal . p >= height} is outside; ``normal`` is a unit 3-vector."""

    normal: tuple[float, float, float]
    height: float = 0.0

    @property
    def feature_size(self) -> float:
        """A half-space has no thin part."""
        return float("inf")

    def distance(self, p: Tensor) -> Tensor:
        n = torch.as_tensor(self.normal, dtype=p.dtype, device=p.device)
        return (p * n).sum(-1) - self.height


@dataclass(frozen=True)
class Box:
    """Axis-aligned box with ``half_extents`` [m] centred at the origin."""

    half_extents: tuple[float, float, float]

    @property
    def feature_size(self) -> float:
        """Thinnest part [m]: a point moving further than this in one step may pass through."""
        return float(min(self.half_extents))

    def distance(self, p: Tensor) -> Tensor:
        h = torch.as_tensor(self.half_extents, dtype=p.dtype, device=p.device)
        q = p.abs() - h
        outside = _norm(q.clamp_min(0.0)) - _SMOOTHING**0.5
        inside = q.amax(-1).clamp_max(0.0)
        return outside + inside


@dataclass(frozen=True)
class Capsule:
    """Segment from z = -half_length to z = +half_length, swept by ``radius`` [m]."""

    half_length: float
    radius: float

    @property
    def feature_size(self) -> float:
        """Thinnest part [m]: a point moving further than this in one step may pass through."""
        return float(self.radius)

    def distance(self, p: Tensor) -> Tensor:
        z = p[..., 2].clamp(-self.half_length, self.half_length)
        closest = torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], dim=-1)
        return _norm(p - closest) - self.radius


@dataclass(frozen=True)
class Torus:
    """Ring in the local xy plane: centre-line radius ``major`` [m], tube radius ``minor`` [m]."""

    major: float
    minor: float

    @property
    def feature_size(self) -> float:
        """Thinnest part [m]: a point moving further than this in one step may pass through."""
        return float(self.minor)

    def distance(self, p: Tensor) -> Tensor:
        ring = _norm(p[..., :2]) - self.major
        return torch.sqrt(ring * ring + p[..., 2] ** 2 + _SMOOTHING) - self.minor


SHAPES = {"sphere": Sphere, "plane": Plane, "box": Box, "capsule": Capsule, "torus": Torus}
