"""`redsim bench env-ab` (:mod:`redsim.envs.bench_ab`) on the mini chain, with tiny rounds."""

from __future__ import annotations

import json

import numpy as np
import pytest

from redsim.cli import main
from redsim.envs.bench_ab import bench_env_ab

TINY = ["--num-envs", "3", "--rounds", "2", "--steps-per-round", "2", "--warmup", "1"]
WORK = ("iterations_per_step", "slowest_iterations_per_step", "calls_per_step", "rows_per_copy_step")


def test_env_ab_json_counts_the_work_and_the_same_setting_twice_does_the_same_work(
    capsys: pytest.CaptureFixture[str],
) -> None:
    args = ["bench", "env-ab", "RedSim/MiniChain-v0", "--setting", "a", "--setting", "again"]
    args += ["--setting", 'loose:stepper_options={"tol": 1e-4}', "--setting", "loose:include_q=false"]
    assert main([*args, *TINY, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["env_id"] == "RedSim/MiniChain-v0" and doc["num_envs"] == 3 and doc["rounds"] == 2
    assert doc["steps_per_round"] == 2 and doc["warmup"] == 1 and doc["seed"] == 0
    assert "load_average_1min" in doc["machine"] and "load_average_1min_end" in doc
    a, again, loose = doc["settings"]
    assert [a["name"], again["name"], loose["name"]] == ["a", "again", "loose"]
    assert a["env_args"] == again["env_args"] == {}
    assert loose["env_args"] == {"stepper_options": {"tol": 1e-4}, "include_q": False}  # a repeated NAME adds
    for row in (a, again, loose):
        assert len(row["round_cpu_s"]) == 2 and min(row["round_cpu_s"]) > 0
        assert row["cpu_ms_per_step"] > 0 and row["env_steps_per_cpu_s"] > 0
        # every vector step evaluates the start and z_t of each copy, then one call per iteration of the slowest
        assert row["calls_per_step"] >= 1 and row["rows_per_copy_step"] >= 2
        assert 0 < row["iterations_per_step"] <= row["slowest_iterations_per_step"] <= row["calls_per_step"] - 1
        assert 0.0 <= row["converged_fraction"] <= 1.0 and row["diverged"] == 0  # the mini chain under [-1, 1]
        ratio = row["ratio"]
        assert len(ratio["rounds"]) == 2 and ratio["min"] <= ratio["median"] <= ratio["max"]
    assert a["ratio"]["rounds"] == [1.0, 1.0]
    for key in (*WORK, "converged_fraction", "out_of_range", "diverged"):  # same seed, same actions: same solves
        assert a[key] == again[key], key
    assert loose["iterations_per_step"] < a["iterations_per_step"]  # a 100x looser tolerance stops sooner
    assert a["observation_gap"] == again["observation_gap"] == 0.0 < loose["observation_gap"]  # and ends elsewhere


def test_env_ab_divides_the_work_by_every_timed_step_even_where_every_copy_restarts() -> None:
    """With 2-step episodes every third vector step restarts every copy (NEXT_STEP autoreset): it solves nothing,
    yet it is a timed step, so it counts in the divisor (it was left out: a review's finding)."""
    from redsim.runtime.stepper import Evaluations

    doc = bench_env_ab(
        "RedSim/MiniChain-v0", {"a": {"max_episode_steps": 2}}, num_envs=2, rounds=2, steps_per_round=2, warmup=1
    )
    (row,) = doc["settings"]
    # the same env and actions stepped by hand: its calls per timed vector step
    import gymnasium as gym

    venv = gym.make_vec("RedSim/MiniChain-v0", 2, "vector_entry_point", max_episode_steps=2)
    venv.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1.0, 1.0, (5, 2, 3)).astype(np.float32)
    venv.step(actions[0])
    venv.unwrapped.sim.stepper.evaluations = Evaluations()
    for action in actions[1:]:
        venv.step(action)
    assert row["calls_per_step"] == venv.unwrapped.sim.stepper.evaluations.calls / 4
    venv.close()


def test_a_restarted_copys_flags_are_not_counted_as_its_steps() -> None:
    """A copy that NEXT_STEP autoreset restarts is not stepped: its slots hold the reset's ``out_of_range`` (a start
    beyond the map's region), not a step's, so the counts of flagged copy-steps leave it out."""
    from redsim.envs.bench_ab import _Work

    stepped = np.array([True, False, True])
    info = {
        "iterations": np.array([3, 0, 5]),
        "converged": np.array([True, False, False]),
        "_converged": stepped,
        "out_of_range": np.array([False, True, True]),
        "_out_of_range": np.ones(3, bool),
        "diverged": np.array([False, True, True]),
        "_diverged": stepped,
    }

    class Venv:
        def step(self, action: np.ndarray) -> tuple:
            return None, None, None, None, info

    work = _Work()
    work.run_round(Venv(), np.zeros((2, 3, 1), np.float32))
    solves = work.solves
    assert solves.out_of_range == 2 and solves.diverged == 2 and solves.converged == [0.5, 0.5]
    assert solves.slowest == [5.0, 5.0]


def test_env_ab_prints_a_row_per_setting_and_the_ratios(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["bench", "env-ab", "RedSim/MiniChain-v0", "--setting", "cold"]
    assert main([*args, "--setting", 'warm:stepper_options={"warm_start": true}', *TINY]) == 0
    text = capsys.readouterr().out
    assert "interleaved A/B of RedSim/MiniChain-v0: 3 envs, 2 rounds of 2 vector steps" in text
    assert "  cold: the env's defaults" in text and '  warm: stepper_options={"warm_start": true}' in text
    lines = text.splitlines()
    assert any(line.startswith("cold ") and "1.00x (1.00-1.00)" in line for line in lines)
    assert any(line.startswith("warm ") and line.endswith(")") for line in lines)
    assert "per-round CPU ratio vs cold" in text and "machine:" in text
    assert "obs gap: the largest difference of a setting's observations from cold's" in text
    assert "* no solver iteration" not in text
    # a tolerance the start already meets: no iteration, a step that ends where it started, said under the table
    assert main([*args, "--setting", 'idle:stepper_options={"tol": 1e3}', *TINY]) == 0
    text = capsys.readouterr().out
    assert "* no solver iteration in any timed step: each step took the solver's start as it was (no solve" in text
    assert any(line.startswith("idle ") and "* " in line for line in text.splitlines()), text


def test_env_ab_refuses_settings_on_different_thread_counts(capsys: pytest.CaptureFixture[str]) -> None:
    """Switching torch's thread count between the settings' alternating steps is what got timed (Chain-v0 at 64
    envs: 21 wall ms per step on one thread or two alone, 60 and 726 alternating), printed as a 0.04x setting. The
    same count everywhere runs; above one thread a note says the CPU ratio is a cost, not a speed."""
    args = ["bench", "env-ab", "RedSim/MiniChain-v0", "--setting", "a", "--setting", "two:threads=2", *TINY]
    assert main(args) == 2
    assert "different torch thread counts {'a': 1, 'two': 2}" in capsys.readouterr().err
    with pytest.raises(ValueError, match="different torch thread counts"):
        bench_env_ab("RedSim/MiniChain-v0", {"a": {}, "b": {"threads": 2}}, threads=1)
    assert main([*args[:5], "--setting", "b", *TINY, "--threads", "2"]) == 0
    assert "note: the settings ran on 2 torch threads" in capsys.readouterr().out
    assert main([*args[:5], "--setting", "b", *TINY]) == 0
    assert "torch threads" not in capsys.readouterr().out


def test_env_ab_renders_every_copy_after_each_timed_step(capsys: pytest.CaptureFixture[str]) -> None:
    """--render PX: frames of that size for every setting (a setting's camera key reaches its env), the renders'
    CPU time reported apart and counted in the step's."""
    args = ["bench", "env-ab", "RedSim/MiniChain-v0", "--setting", "merged", "--setting", 'all:camera={"merge_px": 0}']
    assert main([*args, *TINY, "--render", "32", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["render_size"] == 32
    for row in doc["settings"]:
        assert len(row["round_render_cpu_s"]) == 2
        assert 0 < row["render_cpu_ms"] < row["cpu_ms_per_step"]
    assert main([*args, *TINY, "--render", "32"]) == 0
    text = capsys.readouterr().out
    assert "each step then rendering every copy at 32 x 32 px" in text and "of it render" in text
    assert main([*args, *TINY, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["render_size"] is None and "render_cpu_ms" not in doc["settings"][0]


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        (["RedSim/Nope-v0", "--setting", "a", "--setting", "b"], "unknown env 'RedSim/Nope-v0'"),
        (["RedSim/MiniChain-v0", "--setting", "a"], "give at least two settings"),
        (["RedSim/MiniChain-v0", "--setting", "a", "--setting", "a:tol=1"], "give at least two settings"),
        (["RedSim/MiniChain-v0", "--setting", "a", "--setting", ":tol=1"], "malformed --setting ':tol=1'"),
        (["RedSim/MiniChain-v0", "--setting", "a", "--setting", "tol=1"], "malformed --setting 'tol=1'"),
        (["RedSim/MiniChain-v0", "--setting", "a", "--setting", "b:tol"], "setting 'b': malformed --setting 'tol'"),
        (["RedSim/MiniChain-v0", "--setting", "a", "--setting", "b:dtype=float64"], "VALUE must be a JSON literal"),
        (
            ["RedSim/MiniChain-v0", "--setting", "a", "--setting", "b:no_such_option=1"],
            "setting 'b': cannot make RedSim/MiniChain-v0 with --setting no_such_option=1",
        ),
        (["RedSim/MiniChain-v0", "--setting", "a", "--setting", 'b:device="cpu"'], "drop device="),
        (["RedSim/MiniChain-v0", "--setting", "a", "--setting", "b", "--num-envs", "0"], "--num-envs must be"),
        (["RedSim/MiniChain-v0", "--setting", "a", "--setting", "b", "--rounds", "0"], "--rounds must be"),
        (["RedSim/MiniChain-v0", "--setting", "a", "--setting", "b", "--steps-per-round", "0"], "--steps-per-round"),
        (["RedSim/MiniChain-v0", "--setting", "a", "--setting", "b", "--warmup", "-1"], "--warmup must be"),
        (["RedSim/MiniChain-v0", "--setting", "a", "--setting", "b", "--rounds", "two"], "invalid int value"),
        (["RedSim/MiniChain-v0", "--setting", "a", "--setting", "b", "--render", "4"], "--render must be"),
        (
            ["RedSim/MiniChain-v0", "--setting", "a", "--setting", "b", "--render", "5000"],
            "--render must be an integer in [8, 4096]",
        ),
    ],
)
def test_env_ab_bad_input_is_a_usage_error(extra: list[str], expected: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "env-ab", *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("redsim: error: ") and expected in err and "Traceback" not in err


@pytest.mark.parametrize(
    ("kwargs", "expected"),
    [
        ({"settings": {}}, "at least one setting"),
        ({"num_envs": 0}, "num_envs must be >= 1"),
        ({"rounds": 0}, "rounds must be >= 1"),
        ({"steps_per_round": 0}, "steps_per_round must be >= 1"),
        ({"warmup": -1}, "warmup must be >= 0"),
        ({"render": 0}, "render must be a frame size"),
        ({"render": 4097}, r"render must be a frame size in \[8, 4096\]"),
    ],
)
def test_bench_env_ab_rejects_bad_counts_before_making_envs(kwargs: dict, expected: str) -> None:
    call = {"settings": {"a": {}}, **kwargs}
    with pytest.raises(ValueError, match=expected):
        bench_env_ab("RedSim/MiniChain-v0", **call)


def test_the_observation_gap_of_settings_whose_observations_differ_in_shape_is_none() -> None:
    """ConditionalBar-v1 without its condition in the observation has 2 entries fewer: the gap crashed the command
    after all its timing (a review's finding); it is None (printed "-"), and a NaN is not dropped."""
    from redsim.envs.bench_ab import observation_gap

    a, b = [np.zeros((2, 22), np.float32)], [np.zeros((2, 20), np.float32)]
    assert observation_gap(a, b) is None
    nan = [np.array([[np.nan, 0.0]], np.float32), np.zeros((1, 2), np.float32)]
    assert np.isnan(observation_gap(nan, [np.zeros((1, 2), np.float32)] * 2))
    assert np.isnan(observation_gap(nan[::-1], [np.zeros((1, 2), np.float32)] * 2))  # Python's max kept the 0.0
    assert observation_gap([np.ones((1, 2), np.float32)], [np.zeros((1, 2), np.float32)]) == 1.0
    doc = bench_env_ab(
        "RedSim/ConditionalBar-v1",
        {"a": {}, "b": {"randomize_condition": False}},
        num_envs=2,
        rounds=1,
        steps_per_round=1,
        warmup=0,
    )
    assert [row["observation_gap"] for row in doc["settings"]] == [0.0, None]


def test_env_ab_of_one_round_prints_its_ratio_without_a_range(capsys: pytest.CaptureFixture[str]) -> None:
    """--rounds 1 printed "0.63x (0.63-0.63)" under "median (range)": a spread of one value, as if measured."""
    one = ["--num-envs", "2", "--rounds", "1", "--steps-per-round", "1", "--warmup", "0"]
    assert main(["bench", "env-ab", "RedSim/MiniChain-v0", "--setting", "a", "--setting", "b", *one]) == 0
    lines = capsys.readouterr().out.splitlines()
    (header,) = [line for line in lines if line.startswith("setting ")]
    assert header.endswith("vs a (one round)") and "median (range)" not in header
    (row,) = [line for line in lines if line.startswith("b ")]
    assert row.endswith("x") and "-" not in row.split()[-1], row
