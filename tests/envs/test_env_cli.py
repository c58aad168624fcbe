"""`redsim demo` and `redsim bench envs` on the mini chain, with tiny budgets."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from redsim.cli import main


def test_demo_prints_return_and_speed_and_writes_gif_and_picture(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["demo", "RedSim/MiniChain-v0", "--steps", "6", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "return" in text and "env steps/s" in text
    assert "(shipped policy MiniChain-v0.zip, seed 0)" in text  # a policy is shipped for the mini chain
    assert (tmp_path / "minichain.gif").stat().st_size > 0 and (tmp_path / "minichain.png").stat().st_size > 0
    assert main(["demo", "RedSim/MiniChain-v0", "--steps", "6", "--out", str(tmp_path), "--scripted"]) == 0
    assert "(scripted controller, seed 0)" in capsys.readouterr().out


def test_bench_envs_json(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["bench", "envs", "--envs", "RedSim/MiniChain-v0", "--batches", "2", "--steps", "2", "--json"]
    assert main(args) == 0
    doc = json.loads(capsys.readouterr().out)
    (row,) = doc["results"]
    assert row["n"] == 24 and row["d"] == 4 and row["action_size"] == 3 and row["observation_size"] == 14
    assert row["vector"]["2"]["env_steps_per_s"] > 0 and row["full_space"]["step_s"] > 0
    assert "machine" in doc and "available" in doc["mujoco"]


@pytest.mark.parametrize("argv", [["demo", "RedSim/Nope-v0"], ["bench", "envs", "--envs", "Nope"]])
def test_unknown_env_id_is_a_usage_error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(argv) == 2
    assert "unknown env" in capsys.readouterr().err
