"""An accuracy row's derived numbers by hand: the time per dt of simulated time of a run with a larger step, and the
mean error over the steps after the start (hand mutation audit, helper-281)."""

from __future__ import annotations

import pytest
import torch

from redsim import scenes
from redsim.benches import accuracy
from redsim.benches.accuracy import Run


def _reference():
    scene = scenes.build("mini_chain").to(dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    q = scene.q_seed + 0.01 * torch.randn(11, scene.free_dof_count, generator=g, dtype=torch.float64)
    return scene, Run(q, torch.arange(11), [0.002] * 10)


def test_a_run_at_twice_the_step_is_timed_per_dt_of_simulated_time() -> None:
    scene, reference = _reference()
    coarse = Run(reference.q[::2], torch.arange(0, 11, 2), [0.006] * 5, stride=2)  # 6 ms per 2 dt: 3 ms per dt
    row = accuracy._row("push", "dt2x", "full", coarse, reference, scene, "bottom", 0.002)
    assert row["ms_per_step"] == pytest.approx(3.0)
    assert row["speedup"] == pytest.approx(2.0 / 3.0)  # slower than the reference's 2 ms per dt
    assert row["steps_run"] == 5


def test_the_mean_error_leaves_out_the_start() -> None:
    scene, reference = _reference()
    still = Run(reference.q[:1].expand(11, -1), torch.arange(11), [0.001] * 10)
    errors = accuracy.trajectory_errors(scene, still, reference, "bottom")
    d = reference.q - reference.q[0]
    norms = (d * scene.mass_matvec(d)).sum(-1).sqrt()
    by_hand = norms / norms.max()  # the run stands still: its error is the reference's own motion
    assert errors["rel_error_mean"] == pytest.approx(float(by_hand[1:].mean()), rel=1e-12)
    assert errors["rel_error_final"] == pytest.approx(float(by_hand[-1]), rel=1e-12)
