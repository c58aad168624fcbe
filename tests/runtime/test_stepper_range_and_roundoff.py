"""The stepper's out-of-range flag looks at z_t as well as z_next, and its measured gradient round-off
(:meth:`LatentStepper._gradient_roundoff`) is the size of the float32 gradient's error at one point."""

from __future__ import annotations

import math

import pytest
import torch

from redsim import pretrained, scenes
from redsim.runtime import LatentStepper
from redsim.runtime.flags import LATENT_RANGE


@pytest.fixture(scope="module")
def mini_chain() -> tuple:
    return scenes.build("mini_chain"), pretrained.load("mini_chain")


def test_a_step_from_out_of_range_back_into_range_is_flagged(mini_chain) -> None:
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, 0.02)
    d = stepper.latent_dim
    assert stepper.energy.periodic == ()
    limit = LATENT_RANGE * math.sqrt(d)
    direction = torch.ones(1, d) / math.sqrt(d)
    # z_t just past the range, moving inwards fast: the extrapolated start is z = 0 and the step ends inside
    z, z_prev = 1.05 * limit * direction, 2.1 * limit * direction
    z_next, stats = stepper.step(z, z_prev)
    assert bool(stats.converged[0])
    assert float(torch.linalg.vector_norm(z_next)) < limit  # the step ended in range ...
    assert bool(stats.out_of_range[0])  # ... but started outside it, where the map was not fitted


@pytest.mark.parametrize("name", ["mini_chain", "bistable_bar"])
def test_the_measured_round_off_is_the_float32_gradients_error_at_one_point(name: str) -> None:
    scene, f = scenes.build(name), pretrained.load(name)
    s32 = LatentStepper(scene, f, 0.02)
    s64 = LatentStepper(scene, f, 0.02, dtype=torch.float64)
    d = s32.latent_dim
    # the same float32-representable points near z = 0, and the same target, in both dtypes
    z = (1e-3 * torch.randn(64, d, generator=torch.Generator().manual_seed(1), dtype=torch.float64)).float()
    qbar = s64._coords(torch.zeros(1, d, dtype=torch.float64), None).expand(64, -1)
    _, g64, _ = s64._eager_value_and_grad(z.double(), qbar, None, None)
    _, g32, _ = s32._eager_value_and_grad(z, qbar.float(), None, None)
    error = float(torch.linalg.vector_norm(g32.double() - g64, dim=-1).median())
    # measured 1.29x (mini_chain) and 0.79x (bistable_bar) the probe: its / sqrt(6) is one point's share of the
    # second difference's three independent round-offs
    assert 0.5 < error / s32._gradient_roundoff() < 2.0
