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
    assert progress_bar(total=1, file=log).maxinterval == LOG_INTERVAL  # tqdm's monitor thread waits as long
    assert progress_bar(total=1, file=terminal).mininterval == 0.1
    logged, shown = _redraws(log), _redraws(terminal)
    assert logged <= 8 < 50 <= shown, (logged, shown)  # ~40 s of its clock: a redraw per 30 s, the first, the last
    assert "200/200" in log.getvalue()  # the last state is written when the bar closes


def test_the_user_setting_of_tqdm_wins() -> None:
    code = "import io; from redsim.progress import progress_bar; print(progress_bar(file=io.StringIO()).mininterval)"
    env = {**os.environ, "TQDM_MININTERVAL": "2"}  # tqdm reads it when it is imported
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert done.stdout.strip() == "2.0", done.stderr


def test_the_fit_and_cubature_bars_redraw_sparsely_in_a_log(monkeypatch: pytest.MonkeyPatch) -> None:
    from redsim import pretrained, scenes
    from redsim.cubature import CubatureConfig, build_cubature
    from redsim.trainers import fit_subspace

    monkeypatch.delenv("TQDM_MININTERVAL", raising=False)
    log = io.StringIO()
    monkeypatch.setattr(sys, "stderr", log)
    fit_subspace(scenes.build("toy_two_tets"), dim=2, hidden_width=8, hidden_layers=1, steps=200, progress=True)
    scene = scenes.build("conditional_bar")
    config = CubatureConfig(elements=20, samples=32, episodes=0)
    build_cubature(scene, pretrained.load("conditional_bar", scene), config, progress=True)
    bars = log.getvalue()
    assert "200/200" in bars and "cubature elastic" in bars  # both bars were written, with their final state
    assert bars.count("\r") <= 12, bars.count("\r")  # a few per bar, not one per step (200) or element
