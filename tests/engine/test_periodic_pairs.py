"""The fitting loss's pair term measures an angle latent's difference along the circle, whichever sample comes first
(hand mutation audit, helper-281: wrapping into [0, 2 pi) instead of [-pi, pi) passed tests/engine/test_subspace.py
and tests/trainers/test_fit.py, while a pair 0.08 rad apart across +-pi read 6.2 rad apart in one order)."""

from __future__ import annotations

import math

import pytest
import torch

from redsim import scenes
from redsim.subspace import pair_log_ratios

GAP = 2.0 * math.pi - 6.2
"""-3.1 and 3.1 rad: 0.083 rad apart along the circle."""


@pytest.mark.parametrize(("a", "b"), [(-3.1, 3.1), (3.1, -3.1), (0.5, 0.5 + GAP), (0.5 + GAP, 0.5)])
def test_a_pair_across_the_seam_is_as_close_as_its_angle_along_the_circle(a: float, b: float) -> None:
    scene = scenes.build("toy_two_tets").to(dtype=torch.float64)
    y = torch.stack([scene.q_seed, scene.q_seed + 0.01])  # the same two outputs for every latent pair
    expected = pair_log_ratios(y, torch.tensor([[0.0], [GAP]], dtype=torch.float64), scene, 1.0)  # plain latents
    z = torch.tensor([[a], [b]], dtype=torch.float64)
    torch.testing.assert_close(pair_log_ratios(y, z, scene, 1.0, (0,)), expected)
    if abs(a - b) > math.pi:  # as plain latents, the pair is 6.2 apart
        plain = pair_log_ratios(y, z, scene, 1.0)
        torch.testing.assert_close(plain - expected, torch.tensor([math.log(GAP / 6.2)], dtype=torch.float64))
