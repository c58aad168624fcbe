"""`redsim bench cubature --timed-steps 1` is refused (the bench needs two timed steps; a hand mutation audit found
the bound at 1 passing every test, which tried only 0 and -3)."""

from __future__ import annotations

import pytest

from redsim.cli import main


def test_bench_cubature_refuses_a_single_timed_step(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "cubature", "--sweep", "2", "--timed-steps", "1", "--batches", "1"]) == 2
    assert "--timed-steps >= 2" in capsys.readouterr().err
