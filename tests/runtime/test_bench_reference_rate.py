"""`redsim bench step`: the reference's rate is the median over its rounds, as every stepper's is."""

from __future__ import annotations

import json
import statistics

import pytest

from redsim.cli import main


def test_the_reference_rate_is_the_median_of_its_rounds(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["bench", "step", "--scenes", "mini_chain", "--batches", "1", "--steps", "2", "--reference-steps", "2"]
    code = main([*argv, "--no-compile", "--rounds", "2", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    (row,) = json.loads(out)["rows"]
    rounds = row["reference"]["rounds_env_steps_per_s"]
    assert len(rounds) == 2 and rounds[0] != rounds[1]  # two timings of wall time: never equal to the bit
    assert row["reference"]["env_steps_per_s"] == pytest.approx(statistics.median(rounds), rel=1e-12)
