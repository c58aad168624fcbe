"""The shapes' signed distances against an independent oracle, at random points on every side of each shape.

The hand-computed cases in test_effects.py sit on one side of each shape (a capsule's points all had z >= 0), so a
distance that is right there and wrong on the other side passed them: a capsule whose segment was clamped to
[0, half_length] instead of [-half_length, half_length] (hand mutation audit, helper-283). Here every distance is
compared with one computed another way: the nearest of many points sampled densely along a capsule's segment or a
torus's centre circle, the box's nearest point by clamping (outside) and its nearest face (inside).
"""

from __future__ import annotations

import math

import pytest
import torch

from redsim.effects import Box, Capsule, Sphere, Torus

SAMPLES = 20001
"""Points sampled along a segment or circle: spacing 1e-4 of its length, so the sampled distance is within
(spacing / 2)^2 / (2 r) of the true one, far below the tolerance below."""


def _points(count: int = 400, seed: int = 0) -> torch.Tensor:
    """Random points [count, 3] in [-3, 3]^3 [m], on every side of every shape below (float64)."""
    g = torch.Generator().manual_seed(seed)
    return 6.0 * torch.rand(count, 3, generator=g, dtype=torch.float64) - 3.0


def _nearest(points: torch.Tensor, curve: torch.Tensor) -> torch.Tensor:
    """Distance [m] from each point [P, 3] to the nearest of the sampled points [S, 3]."""
    return torch.cdist(points, curve).amin(-1)


def _segment_oracle(points: torch.Tensor, half_length: float, radius: float) -> torch.Tensor:
    s = torch.linspace(-half_length, half_length, SAMPLES, dtype=points.dtype)
    segment = torch.stack([torch.zeros_like(s), torch.zeros_like(s), s], -1)
    return _nearest(points, segment) - radius


def _torus_oracle(points: torch.Tensor, major: float, minor: float) -> torch.Tensor:
    angle = torch.linspace(0.0, 2.0 * math.pi, SAMPLES, dtype=points.dtype)
    circle = torch.stack([major * torch.cos(angle), major * torch.sin(angle), torch.zeros_like(angle)], -1)
    return _nearest(points, circle) - minor


def _box_oracle(points: torch.Tensor, half: tuple[float, float, float]) -> torch.Tensor:
    h = torch.tensor(half, dtype=points.dtype)
    outside = (points - points.clamp(-h, h)).norm(dim=-1)
    inside = (h - points.abs()).amin(-1)  # distance to the nearest face, for points inside
    return torch.where(outside > 0, outside, -inside)


@pytest.mark.parametrize(
    ("shape", "oracle"),
    [
        (Sphere(1.2), lambda p: p.norm(dim=-1) - 1.2),
        (Capsule(1.0, 0.4), lambda p: _segment_oracle(p, 1.0, 0.4)),
        (Capsule(0.0, 0.7), lambda p: _segment_oracle(p, 0.0, 0.7)),
        (Torus(1.5, 0.5), lambda p: _torus_oracle(p, 1.5, 0.5)),
        (Box((0.5, 1.0, 1.5)), lambda p: _box_oracle(p, (0.5, 1.0, 1.5))),
    ],
    ids=["sphere", "capsule", "capsule_ball", "torus", "box"],
)
def test_signed_distances_match_an_independent_oracle_on_every_side(shape, oracle) -> None:
    points = _points()
    expected = oracle(points)
    assert bool((expected < 0).any()) and bool((expected > 0).any())  # points inside and outside
    got = shape.distance(points)
    assert torch.allclose(got, expected, atol=1e-5), float((got - expected).abs().max())


@pytest.mark.parametrize("shape", [Sphere(1.2), Capsule(1.0, 0.4), Torus(1.5, 0.5), Box((0.5, 1.0, 1.5))])
def test_signed_distances_are_even_in_each_coordinate(shape) -> None:
    """Every shape here is symmetric about its three coordinate planes: its distance is unchanged by flipping the
    sign of any one coordinate of the point."""
    points = _points(seed=1)
    base = shape.distance(points)
    for axis in range(3):
        flipped = points.clone()
        flipped[:, axis] = -flipped[:, axis]
        assert torch.allclose(shape.distance(flipped), base, atol=1e-12), axis
