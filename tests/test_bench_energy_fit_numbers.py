"""`redsim bench energy` and `redsim bench fit`'s derived numbers from a clock the test controls: the time per state
is the median call over the batch, the start-up the first step's time less the median step."""

from __future__ import annotations

import itertools

import pytest

from redsim import bench, scenes


class _Clock:
    """perf_counter that advances ``tick`` seconds at every reading."""

    def __init__(self, tick: float) -> None:
        self._ticks, self.tick = itertools.count(), tick

    def perf_counter(self) -> float:
        return self.tick * next(self._ticks)


def test_the_time_per_state_is_the_median_call_over_the_batch(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(bench, "time", _Clock(0.5))  # each call: two readings, 0.5 s apart
    result = bench.bench_energy(scenes.build("mini_chain"), batch=4, repeats=3, warmup=1)
    assert result["median_s"] == pytest.approx(0.5) and result["repeats"] == 3
    assert result["per_state_s"] == pytest.approx(0.125)


def test_the_fits_start_up_is_its_first_step_less_the_median_step(monkeypatch: pytest.MonkeyPatch) -> None:
    from redsim.trainers import FitConfig

    monkeypatch.setattr(bench, "time", _Clock(1.0))  # the start and each step's stamp: one second apart
    config = FitConfig(latent_dim=2, batch_size=4, dtype="float64", device="cpu", compile=False)
    result = bench.bench_fit(scenes.build("mini_chain"), config, steps=3, warmup=2)
    assert result["times_s"] == [1.0, 1.0, 1.0] and result["median_s"] == 1.0
    assert result["first_step_s"] == 1.0  # one reading after the start
    assert result["startup_s"] == 0.0  # no one-off cost on this clock: the first step took a median step
