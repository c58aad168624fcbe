"""Analytic signed distances [m] in a shape's own frame; negative inside.

Each shape maps local points [..., 3] to distances [...]. Square roots carry a tiny
``smoothing`` so gradients stay finite on axes and at centres. The formulas work on the three
components (``p.unbind(-1)``), so a caller may pass a view whose components are each contiguous
(:class:`redsim.effects.penalty.SDFContact` does): no gather of the last axis, no temporaries of [..., 3].
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

_SMOOTHING = 1e-12  # [m^2]


def _norm(*components: Tensor) -> Tensor:
    """sqrt(sum of squares + smoothing) of equally shaped components."""
    total = components[0] * components[0]
    for c in components[1:]:
        total = total + c * c
    return torch.sqrt(total + _SMOOTHING)


def _check_lengths(shape: object, **lengths: float) -> None:
    """Refuse a shape's lengths [m] that are not finite numbers > 0 (a negative radius turns the shape inside out:
    its centre would count as outside)."""
    for name, value in lengths.items():
        if isinstance(value, torch.Tensor | np.ndarray | np.generic) and value.ndim == 0:  # a one-number tensor
            value = value.item()
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (math.isfinite(value) and value > 0):
            raise ValueError(f"{type(shape).__name__} {name} must be a finite number > 0 [m], got {value!r}")


@dataclass(frozen=True)
class Sphere:
    """Ball of ``radius`` [m] centred at the origin."""

    radius: float

    def __post_init__(self) -> None:
        _check_lengths(self, radius=self.radius)

    @property
    def feature_size(self) -> float:
        """Thinnest part [m]: a point moving further than this in one step may pass through."""
        return float(self.radius)

    @property
    def bounding_radius(self) -> float:
        """Radius [m] of a ball about the origin that holds the whole shape (inf: unbounded)."""
        return float(self.radius)

    def distance(self, p: Tensor) -> Tensor:
        return _norm(*p.unbind(-1)) - self.radius


@dataclass(frozen=True)
class Plane:
    """Half-space {p : normal . p >= height} is outside; ``normal`` is a unit 3-vector."""

    normal: tuple[float, float, float]
    height: float = 0.0

    def __post_init__(self) -> None:
        try:
            normal = [float(v) for v in self.normal]
        except (TypeError, ValueError) as err:
            raise ValueError(f"Plane normal must be 3 numbers, got {self.normal!r}") from err
        length = math.sqrt(sum(v * v for v in normal))
        if len(normal) != 3 or not math.isfinite(length) or abs(length - 1.0) > 1e-6:
            raise ValueError(
                f"Plane normal must be a unit 3-vector (its length scales every distance), got {self.normal!r}"
            )
        if not math.isfinite(float(self.height)):
            raise ValueError(f"Plane height must be finite [m], got {self.height!r}")

    @property
    def feature_size(self) -> float:
        """A half-space has no thin part."""
        return float("inf")

    @property
    def bounding_radius(self) -> float:
        """Radius [m] of a ball about the origin that holds the whole shape (inf: unbounded)."""
        return float("inf")

    def distance(self, p: Tensor) -> Tensor:
        x, y, z = p.unbind(-1)
        nx, ny, nz = (float(v) for v in self.normal)
        return nx * x + ny * y + nz * z - self.height


@dataclass(frozen=True)
class Box:
    """Axis-aligned box with ``half_extents`` [m] centred at the origin."""

    half_extents: tuple[float, float, float]

    def __post_init__(self) -> None:
        if len(self.half_extents) != 3:
            raise ValueError(f"Box half_extents must be 3 lengths [m], got {self.half_extents!r}")
        _check_lengths(self, **{f"half_extents[{i}]": h for i, h in enumerate(self.half_extents)})

    @property
    def feature_size(self) -> float:
        """Thinnest part [m]: a point moving further than this in one step may pass through."""
        return float(min(self.half_extents))

    @property
    def bounding_radius(self) -> float:
        """Radius [m] of a ball about the origin that holds the whole shape (inf: unbounded)."""
        return math.sqrt(sum(float(h) ** 2 for h in self.half_extents))

    def distance(self, p: Tensor) -> Tensor:
        qx, qy, qz = (c.abs() - float(h) for c, h in zip(p.unbind(-1), self.half_extents, strict=True))
        outside = _norm(qx.clamp_min(0.0), qy.clamp_min(0.0), qz.clamp_min(0.0)) - _SMOOTHING**0.5
        inside = torch.maximum(torch.maximum(qx, qy), qz).clamp_max(0.0)
        return outside + inside


@dataclass(frozen=True)
class Capsule:
    """Segment from z = -half_length to z = +half_length, swept by ``radius`` [m]."""

    half_length: float
    radius: float

    def __post_init__(self) -> None:
        _check_lengths(self, radius=self.radius)
        if not (math.isfinite(self.half_length) and self.half_length >= 0):
            raise ValueError(f"Capsule half_length must be a finite number >= 0 [m], got {self.half_length!r}")

    @property
    def feature_size(self) -> float:
        """Thinnest part [m]: a point moving further than this in one step may pass through."""
        return float(self.radius)

    @property
    def bounding_radius(self) -> float:
        """Radius [m] of a ball about the origin that holds the whole shape (inf: unbounded)."""
        return float(self.half_length + self.radius)

    def distance(self, p: Tensor) -> Tensor:
        x, y, z = p.unbind(-1)
        return _norm(x, y, z - z.clamp(-self.half_length, self.half_length)) - self.radius


@dataclass(frozen=True)
class Torus:
    """Ring in the local xy plane: centre-line radius ``major`` [m], tube radius ``minor`` [m]."""

    major: float
    minor: float

    def __post_init__(self) -> None:
        _check_lengths(self, major=self.major, minor=self.minor)

    @property
    def feature_size(self) -> float:
        """Thinnest part [m]: a point moving further than this in one step may pass through."""
        return float(self.minor)

    @property
    def bounding_radius(self) -> float:
        """Radius [m] of a ball about the origin that holds the whole shape (inf: unbounded)."""
        return float(self.major + self.minor)

    def distance(self, p: Tensor) -> Tensor:
        x, y, z = p.unbind(-1)
        return _norm(_norm(x, y) - self.major, z) - self.minor
