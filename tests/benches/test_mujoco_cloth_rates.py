"""`time_flex_cloth`'s rates from a step time the test sets: steps/s = 1 / t, simulated s per wall s = h / t."""

from __future__ import annotations

import pytest
import torch

import redsim

pytest.importorskip("mujoco")

from redsim.benches import mujoco_cloth


def test_the_rates_are_of_the_median_step_time(monkeypatch: pytest.MonkeyPatch) -> None:
    scene = redsim.scenes.build("hanging_sheet").to(dtype=torch.float64)
    calls = []

    def median_time(call, steps, budget):
        for _ in range(steps):
            call()
        calls.append(steps)
        return 0.004, steps  # each step takes 4 ms

    monkeypatch.setattr(mujoco_cloth, "median_time", median_time)
    result = mujoco_cloth.time_flex_cloth(scene, steps=3, warmup=1)
    assert calls == [3] and result["steps"] == 3 and result["finite"]
    assert result["steps_per_s"] == pytest.approx(250.0)
    assert result["sim_s_per_wall_s"] == pytest.approx(result["timestep"] / 0.004)
    assert result["timestep"] == mujoco_cloth.CLOTH_TIMESTEP
