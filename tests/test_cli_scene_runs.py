"""The stderr line of a bench whose scene raised (redsim.cli.scene_runs.SceneRuns.status)."""

from __future__ import annotations

import pytest

from redsim.cli.common import EXIT_SCENE_FAILED
from redsim.cli.scene_runs import SceneRuns


def test_a_failed_scenes_error_is_one_line_on_stderr(capsys: pytest.CaptureFixture[str]) -> None:
    """An error message of several lines (a solver's report, a traceback's text) is folded into the one stderr line
    that names the failed scenes: the CLI's errors are one line each."""
    runs = SceneRuns("bench step", text=True)
    runs.failed.append({"scene": "chain", "error": "RuntimeError: not converged\n  |g| = 3.2\n  threshold 1e-6"})
    assert runs.status() == EXIT_SCENE_FAILED
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert err.endswith("chain raised RuntimeError: not converged |g| = 3.2 threshold 1e-6")
