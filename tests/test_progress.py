"""Progress bars redraw sparsely in a log file and as tqdm does on a terminal."""

from __future__ import annotations

import io
import os
import subprocess
import sys

import pytest

from redsim.progress import LOG_INTERVAL, progress_bar


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _redraws(stream: io.StringIO, steps: int = 200) -> int:
    bar = progress_bar(total=steps, desc="fit", file=stream)
    for _ in range(steps):
        bar.update(1)
    bar.close()
    return stream.getvalue().count("\r")


def test_a_bar_in_a_log_file_redraws_only_every_log_interval(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TQDM_MININTERVAL", raising=False)
    clock = iter(range(10**6))
    monkeypatch.setattr("tqdm.std.time", lambda: float(next(clock)) * 0.2)  # 0.2 s per read of tqdm's clock
    log, terminal = io.StringIO(), Terminal()
    assert progress_bar(total=1, file=log).mininterval == LOG_INTERVAL
    assert progress_bar(total=1, file=terminal).mininterval == 0.1
    logged, shown = _redraws(log), _redraws(terminal)
    assert logged <= 6 < 50 <= shown, (logged, shown)
    assert "200/200" in log.getvalue()  # the last state is written when the bar closes


def test_the_user_setting_of_tqdm_wins() -> None:
    code = "import io; from redsim.progress import progress_bar; print(progress_bar(file=io.StringIO()).mininterval)"
    env = {**os.environ, "TQDM_MININTERVAL": "2"}  # tqdm reads it when it is imported
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert done.stdout.strip() == "2.0", done.stderr
