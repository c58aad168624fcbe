"""`redsim bench step`'s per-stepper numbers (:func:`redsim.runtime.bench.run_stepper`) from a clock the test controls:
env-steps/s counts every state of the batch, and the warm-up steps are left out of the per-step counts."""

from __future__ import annotations

import itertools

import pytest
import torch

from redsim import pretrained, scenes
from redsim.runtime import LatentStepper
from redsim.runtime import bench as runtime_bench
from redsim.runtime.bench import load_magnitudes, load_sequence, run_stepper
from redsim.runtime.flags import LATENT_RANGE


class _Clock:
    """perf_counter one second and process_time half a second further at every reading: each step takes 1 s of
    wall time and 0.5 s of CPU time."""

    def __init__(self) -> None:
        self._wall, self._cpu = itertools.count(), itertools.count()

    def perf_counter(self) -> float:
        return float(next(self._wall))

    def process_time(self) -> float:
        return 0.5 * next(self._cpu)


@pytest.fixture(scope="module")
def stepper_and_loads() -> tuple[LatentStepper, torch.Tensor, torch.Tensor]:
    scene = scenes.build("mini_chain")
    stepper = LatentStepper(scene, pretrained.load("mini_chain"), 0.02)
    batch, steps = 3, 4
    loads = load_sequence(scene, load_magnitudes(stepper), steps, batch, seed=0)
    z0 = stepper.rest_latent().expand(batch, -1).clone()
    return stepper, z0, loads


def test_env_steps_per_s_counts_every_state_of_the_batch(stepper_and_loads, monkeypatch: pytest.MonkeyPatch) -> None:
    stepper, z0, loads = stepper_and_loads
    monkeypatch.setattr(runtime_bench, "time", _Clock())
    result = run_stepper(stepper, z0, loads, warmup=0)
    # 4 steps of 3 states, 1 s (0.5 s of CPU) each
    assert result["median_step_s"] == 1.0 and result["median_step_cpu_s"] == 0.5
    assert result["env_steps_per_s"] == pytest.approx(3.0)


def test_warm_up_steps_are_left_out_of_the_per_step_counts(stepper_and_loads) -> None:
    stepper, z0, loads = stepper_and_loads
    cold = run_stepper(stepper, z0, loads, warmup=0)
    warmed = run_stepper(stepper, z0, loads, warmup=2)  # the same timed steps, from the same start, after 2 others
    assert warmed["calls_per_step"] == cold["calls_per_step"] > 0
    assert warmed["rows_per_step"] == cold["rows_per_step"] >= 3
    assert torch.equal(warmed["trajectory"], cold["trajectory"])


def test_the_flag_fractions_are_each_flags_own(stepper_and_loads) -> None:
    stepper, z0, loads = stepper_and_loads
    far = z0 + 3.0 * LATENT_RANGE * torch.ones_like(z0)  # |z| far past LATENT_RANGE sqrt(d): its first step is out
    result = run_stepper(stepper, far, loads, warmup=0)
    # the chain pulls z back in range after one step (measured: 0.25 of 4 steps), none diverged
    assert result["out_of_range_fraction"] >= 0.25 and result["diverged_fraction"] == 0.0
