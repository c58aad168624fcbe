"""The numbers `redsim bench envs` and `bench env-ab` derive from their timings, checked against timings fixed by
hand: rates per copy, simulated s per wall s, solver rows per copy, the per-round ratios, the ABBA order and the
table's cells (a hand mutation audit found each could be wrong with every other test passing)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from redsim.cli import main
from redsim.envs import bench, bench_ab
from redsim.runtime import Evaluations

STEP_S = 0.01
"""The median step [s] every timed part reports under :func:`fixed_median_time`."""


def fixed_median_time(call: Any, repeats: int, budget: float) -> tuple[float, int]:
    """:func:`redsim.envs.bench.median_time` with its timing fixed: ``repeats`` calls, each taken as STEP_S."""
    for _ in range(repeats):
        call()
    return STEP_S, repeats


def test_bench_env_rates_are_copies_and_simulated_seconds_over_the_median_step(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(bench, "median_time", fixed_median_time)
    row = bench.bench_env("RedSim/MiniChain-v0", batches=(2, 3), steps=3, warmup=1, budget=100.0, frame_skip=2)
    dt = row["dt"]
    assert row["single"]["env_steps_per_s"] == pytest.approx(1 / STEP_S)
    assert row["single"]["sim_s_per_wall_s"] == pytest.approx(dt / STEP_S)
    for batch in (2, 3):
        part = row["vector"][batch]
        assert part["env_steps_per_s"] == pytest.approx(batch / STEP_S)
        assert part["sim_s_per_wall_s"] == pytest.approx(batch * dt / STEP_S)  # every copy advances dt
    # a full-space step is one of the frame_skip substeps of an env step: the env step takes frame_skip of them
    full = row["full_space"]
    assert full["step_s"] == pytest.approx(2 * STEP_S)
    assert full["sim_s_per_wall_s"] == pytest.approx(dt / (2 * STEP_S))


def test_bench_env_rows_are_per_copy_and_step(monkeypatch: pytest.MonkeyPatch) -> None:
    """The same seeded vector env stepped by hand: its stepper's rows over (timed steps x copies)."""
    monkeypatch.setattr(bench, "median_time", fixed_median_time)
    steps, warmup, batch = 3, 1, 3
    row = bench.bench_env("RedSim/MiniChain-v0", batches=(batch,), steps=steps, warmup=warmup, full_space=False)
    venv = gym.make_vec("RedSim/MiniChain-v0", batch, "vector_entry_point")
    venv.reset(seed=0)
    actions = np.random.default_rng((0, batch)).uniform(-1.0, 1.0, (steps + warmup, batch, 3)).astype(np.float32)
    venv.step(actions[0])
    venv.unwrapped.sim.stepper.evaluations = Evaluations()
    for action in actions[1:]:
        venv.step(action)
    evaluations = venv.unwrapped.sim.stepper.evaluations
    venv.close()
    part = row["vector"][batch]
    assert part["calls_per_step"] == pytest.approx(evaluations.calls / steps)
    assert part["rows_per_copy_step"] == pytest.approx(evaluations.rows / (steps * batch))


def work(round_cpu_s: list[float]) -> bench_ab._Work:
    done = bench_ab._Work()
    done.round_cpu_s = round_cpu_s
    done.steps = 4
    flags = {"converged": np.ones(2, bool), "out_of_range": np.zeros(2, bool), "diverged": np.zeros(2, bool)}
    done.solves.add({"iterations": np.array([2, 4]), **flags})
    done.observations = [np.zeros((2, 1))]
    return done


def test_env_ab_ratio_is_the_first_settings_time_over_the_settings_and_rates_count_copies() -> None:
    venv = SimpleNamespace(unwrapped=SimpleNamespace(sim=SimpleNamespace(stepper=SimpleNamespace(
        evaluations=SimpleNamespace(calls=12, rows=40)))))  # fmt: skip
    first, fast = work([0.04, 0.02, 0.04]), work([0.01, 0.01, 0.02])
    row = bench_ab._summary("fast", {}, fast, first, venv, num_envs=2)
    assert row["ratio"]["rounds"] == pytest.approx([4.0, 2.0, 2.0])  # > 1: faster than the first
    assert row["ratio"]["median"] == pytest.approx(2.0) and row["ratio"]["max"] == pytest.approx(4.0)
    assert row["cpu_ms_per_step"] == pytest.approx(10.0)
    assert row["env_steps_per_cpu_s"] == pytest.approx(200.0)  # 2 copies per 10 ms vector step
    assert row["calls_per_step"] == pytest.approx(3.0) and row["rows_per_copy_step"] == pytest.approx(5.0)
    assert row["iterations_per_step"] == 3.0 and row["slowest_iterations_per_step"] == 4.0


def test_env_ab_reverses_the_order_of_the_settings_every_other_round(monkeypatch: pytest.MonkeyPatch) -> None:
    order: list[str] = []
    run_round = bench_ab._Work.run_round

    def recorded(self: bench_ab._Work, venv: Any, actions: np.ndarray, render: bool = False) -> None:
        order.append(venv.unwrapped.spec_name)
        run_round(self, venv, actions, render)

    real_make_vec = gym.make_vec

    def make_vec(env_id: str, **kwargs: Any) -> Any:
        name = kwargs.pop("name")
        venv = real_make_vec(env_id, **kwargs)
        venv.unwrapped.spec_name = name
        return venv

    monkeypatch.setattr(bench_ab._Work, "run_round", recorded)
    monkeypatch.setattr(bench_ab.gym, "make_vec", make_vec)
    settings = {"a": {"name": "a"}, "b": {"name": "b"}, "c": {"name": "c"}}
    bench_ab.bench_env_ab("RedSim/MiniChain-v0", settings, num_envs=2, rounds=3, steps_per_round=1, warmup=0)
    assert order == ["a", "b", "c", "c", "b", "a", "a", "b", "c"]


def test_bench_envs_table_shows_the_fastest_batchs_simulated_rate_and_marks_out_of_range_steps() -> None:
    from redsim.cli.envs import _failed_solves, _row_line

    solved = {"converged_fraction": 1.0, "out_of_range": 0, "diverged": 0}
    row = {"id": "RedSim/X-v0", "n": 1, "d": 1, "action_size": 1, "observation_size": 1, "render": {"frames_per_s": 1}}
    row |= {"single": {"env_steps_per_s": 1.0, "sim_s_per_wall_s": 0.02, **solved}, "full_space": None}
    row["vector"] = {
        2: {"env_steps_per_s": 2.0, "sim_s_per_wall_s": 1.5, **solved},
        4: {"env_steps_per_s": 4.0, "sim_s_per_wall_s": 7.5, **solved},
    }
    line = _row_line(row, [2, 4])
    assert " 7.5 " in line and " 1.5 " not in line and "!" not in line
    row["vector"][4] = {**row["vector"][4], "out_of_range": 3}
    assert _failed_solves(row, [2, 4]) == ["N=4: 100.0% converged, 0 diverged, 3 out of range"]
    assert _row_line(row, [2, 4]).startswith("RedSim/X-v0!")


def test_env_ab_per_round_ratios_list_the_settings_after_the_first(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["bench", "env-ab", "RedSim/MiniChain-v0", "--setting", "ref", "--setting", "other"]
    assert main([*args, "--num-envs", "2", "--rounds", "2", "--steps-per-round", "1", "--warmup", "0"]) == 0
    text = capsys.readouterr().out
    ratios = text.split("per-round CPU ratio vs ref")[1].splitlines()[1:]
    listed = [line.split(":")[0].strip() for line in ratios if line.startswith("  ")]
    assert listed == ["other"]
