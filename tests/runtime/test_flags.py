"""The per-state flags a latent step reports: ``diverged`` (:func:`redsim.runtime.flags.diverged_states`, clause by
clause), ``out_of_range`` (:func:`redsim.runtime.flags.out_of_range_states`, periodic latents and the condition's
bounds) and ``converged`` (against the ``residual`` it reports).

Its doc names three ways a finite step diverged: Phi ended above Phi(z_t) beyond the noise (``worse``), U' changed by
more than DIVERGENCE_MARGIN F L (``released``), K rose by more than that (``faster``); and any non-finite Phi or K.
The stepper's own tests reach the ``released`` clause only (a repulsive energy that blows the chain apart); each
row below trips exactly one clause, so dropping any of them from the test fails here.
"""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from redsim import pretrained, scenes
from redsim.runtime import LatentStepper
from redsim.runtime.flags import DIVERGENCE_MARGIN, LATENT_RANGE, diverged_states, out_of_range_states
from redsim.scene import ConditionSpace

ALLOWANCE = 10.0  # F L [J]
NOISE = 1e-6  # [J]
LIMIT = DIVERGENCE_MARGIN * ALLOWANCE


def _flags(*rows: tuple[float, float, float, float, float]) -> list[bool]:
    """diverged_states of rows (phi_now, phi_next, kinetic_now, kinetic_next, inertia_next) [J]."""
    columns = torch.tensor(rows, dtype=torch.float64).T
    allowance = torch.full((len(rows),), ALLOWANCE, dtype=torch.float64)
    noise = torch.full((len(rows),), NOISE, dtype=torch.float64)
    return diverged_states(*columns, allowance, noise).tolist()


def test_a_step_that_trips_no_clause_is_not_diverged() -> None:
    """Staying put, a rise within the noise, a fall within F L, and K falling far (the ``faster`` test is one-sided):
    none diverged. Phi(z_t) = K_t + U'_t, Phi(z_{t+1}) = inertia + U'_{t+1}."""
    assert _flags(
        (1.0, 1.0, 0.0, 0.0, 0.0),
        (1.0, 1.0 + 0.5 * NOISE, 0.0, 0.0, 0.0),
        (1.0 + 0.5 * LIMIT, 1.0, 0.0, 0.0, 0.0),  # U' fell by half the limit
        (1.0 + 3.0 * LIMIT, 1.0, 3.0 * LIMIT, 0.0, 0.0),  # K fell by 3 F L, U' stayed: a body brought to rest
    ) == [False, False, False, False]


def test_each_clause_alone_flags_the_step() -> None:
    assert _flags(
        (1.0, 1.0 + 2.0 * NOISE, 0.0, 0.0, 0.0),  # worse: Phi rose past the noise, U' and K within the limit
        (1.0 + 1.5 * LIMIT, 1.0, 0.0, 0.0, 0.0),  # released: U' fell by 1.5 F L (Phi fell: not worse)
        (1.0 + 1.5 * LIMIT, 1.0 + 1.5 * LIMIT, 0.0, 1.5 * LIMIT, 0.0),  # faster: K rose by 1.5 F L; Phi and U' stayed
    ) == [True, True, True]


def test_the_released_and_faster_clauses_are_measured_against_divergence_margin_f_l() -> None:
    """Just inside DIVERGENCE_MARGIN F L is not diverged, just past it is (Phi falls or stays, so only the clause
    under test can trip)."""
    inside, past = 0.99 * LIMIT, 1.01 * LIMIT
    assert _flags(
        (1.0 + inside, 1.0, 0.0, 0.0, 0.0),
        (1.0 + past, 1.0, 0.0, 0.0, 0.0),
        (1.0 + inside, 1.0 + inside, 0.0, inside, 0.0),
        (1.0 + past, 1.0 + past, 0.0, past, 0.0),
    ) == [False, True, False, True]


def test_a_non_finite_energy_at_either_end_is_diverged() -> None:
    nan, inf = float("nan"), float("inf")
    assert _flags(
        (nan, 1.0, 0.0, 0.0, 0.0),
        (1.0, nan, 0.0, 0.0, 0.0),
        (1.0, 1.0, inf, 0.0, 0.0),
        (1.0, 1.0, 0.0, inf, 0.0),
    ) == [True, True, True, True]


def test_out_of_range_leaves_periodic_latents_out_of_the_radius() -> None:
    """d = 3 with latent 0 periodic (a crank angle, which grows by 2 pi a turn): the radius is LATENT_RANGE sqrt(2)
    over latents 1 and 2 alone (sqrt(3) over all three let a free |z| of 6.9 pass), and any angle is in range."""
    radius = LATENT_RANGE * math.sqrt(2.0)
    z = torch.tensor(
        [
            [1e3, 0.0, 0.0],  # many turns of the crank
            [0.0, 0.99 * radius, 0.0],
            [0.0, 0.0, 1.01 * radius],
            [0.0, 0.8 * radius, 0.8 * radius],  # |z_free| = 1.13 radius, each entry inside it
            [float("nan"), 0.0, 0.0],  # not finite, periodic or not
        ],
        dtype=torch.float64,
    )
    assert out_of_range_states(z, (0,), None, None).tolist() == [False, False, True, True, True]
    # [B, K, d]: out where any of the K latents is (a step's z and z_next)
    pairs = torch.stack([torch.zeros_like(z[:2]), z[1:3]], 1)
    assert out_of_range_states(pairs, (0,), None, None).tolist() == [False, True]
    # without the periodic latent the radius is LATENT_RANGE sqrt(3) over all three, and the angle counts
    assert out_of_range_states(z[:1], (), None, None).tolist() == [True]


def test_out_of_range_reads_both_bounds_of_the_condition() -> None:
    space = ConditionSpace(
        ("stiffness_ratio", "pin"),
        torch.tensor([0.2, -1.0], dtype=torch.float64),
        torch.tensor([5.0, 1.0], dtype=torch.float64),
        torch.tensor([1.0, 0.0], dtype=torch.float64),
    )
    cond = torch.tensor(
        [[0.2, -1.0], [5.0, 1.0], [0.19, 0.0], [5.01, 0.0], [1.0, -1.01], [1.0, 1.01]], dtype=torch.float64
    )
    z = torch.zeros(cond.shape[0], 2, dtype=torch.float64)
    assert out_of_range_states(z, (), cond, space).tolist() == [False, False, True, True, True, True]


@pytest.mark.parametrize("hessian", ["exact", "bfgs"])
def test_converged_is_the_reported_residual_within_tol(hessian: str) -> None:
    """StepStats: ``converged`` is "the relative gradient norm met tol", ``residual`` that norm, |dPhi/dz| / (|J_0|_2
    F_b). The solve's threshold must carry the same scale: on mini_chain |J_0|_2 is 0.5, and a threshold of tol F_b
    alone called 361 of 640 converged states (32 copies x 20 steps of 10 N random loads, float32, tol 1e-4, exact
    Hessian; measured) converged at residuals above tol, up to 2 tol."""
    scene = scenes.build("mini_chain")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the resolution warning of a loose float32 tol
        stepper = LatentStepper(scene, pretrained.load("mini_chain", scene), 0.02, hessian=hessian, tol=1e-4)
    assert abs(stepper.jacobian_norm - 1.0) > 0.2  # the scale matters here
    g = torch.Generator().manual_seed(0)
    batch = 16
    z = stepper.rest_latent().expand(batch, -1).clone()
    z_prev = z.clone()
    converged = 0
    for _ in range(8):
        loads = 10.0 * torch.randn(batch, len(scene.handles), scene.dim, generator=g)
        z_next, stats = stepper.step(z, z_prev, loads)
        assert bool(torch.isfinite(stats.residual).all())
        assert torch.equal(stats.converged, stats.residual <= stepper.tol), (stats.converged, stats.residual)
        converged += int(stats.converged.sum())
        z_prev, z = z, z_next
    assert converged > batch  # most steps converge: the test compares converged states, not only failures
