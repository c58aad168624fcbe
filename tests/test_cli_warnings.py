"""Python warnings on the command line: one ``redsim: warning: ...`` line each (redsim.cli.common.show_warning), with
Python's filters still deciding, and Python's own display back once :func:`redsim.cli.main` returns."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import trimesh

import redsim
from redsim.cli import main

Cli = Callable[..., tuple[int, str, str]]


@pytest.fixture(scope="module")
def sheet_in_mm(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 0.5 m cloth sheet written in millimetres: building it warns that it spans 500 m (redsim.scenes.from_mesh)."""
    vertices, triangles = redsim.meshes.cloth_grid(0.5, 0.5, (4, 4), origin=(0.0, -0.5, 0.0))
    path = tmp_path_factory.mktemp("mesh") / "sheet_mm.obj"
    trimesh.Trimesh(1e3 * vertices, triangles).export(path)
    return path


def simulate(sheet: Path) -> list[str]:
    return ["simulate", "--mesh", str(sheet), "--kind", "cloth", "--steps", "1", "--json"]


def warn_in_cache_info(warn: Callable[[], None], cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``redsim cache info`` (of the cache folder ``cache``) calls ``warn()`` first: a command that warns as a test
    says."""
    from redsim.cli import cache as command

    usage = command.user_cache_usage

    def warning_usage(*args: object, **kwargs: object) -> object:
        warn()
        return usage(*args, **kwargs)

    monkeypatch.setattr(command, "user_cache_usage", warning_usage)
    monkeypatch.setenv("REDSIM_CACHE", str(cache))


def test_a_warning_in_a_command_is_one_line_and_the_callers_display_comes_back(cli: Cli, sheet_in_mm: Path) -> None:
    """It was Python's display: `/.../redsim/scenes/spec.py:100: UserWarning: mesh ...` and the source line of the
    call (`return MESH_BUILDERS[kind](path, **params)`), a path and code of ours that say nothing to the user."""
    shown = warnings.showwarning
    code, _, err = cli(*simulate(sheet_in_mm))  # not under a catch_warnings of the test's: main restores the display
    assert code == 0, err
    assert err == (
        f"redsim: warning: mesh {str(sheet_in_mm)!r} spans 500 m: redsim reads a mesh's coordinates in metres; for a "
        "file in millimetres give scale=1e-3 (centimetres: 1e-2; on the command line --param scale=0.001)\n"
    )
    assert warnings.showwarning is shown  # the library keeps Python's display (and pytest its capture) after main
    with pytest.warns(UserWarning, match="spans 500 m"):
        redsim.scenes.cloth_scene_from_mesh(sheet_in_mm)


def test_python_filters_still_decide(cli: Cli, sheet_in_mm: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        code, _, err = cli(*simulate(sheet_in_mm))
    assert code == 0 and err == ""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(UserWarning, match="spans 500 m"):
            main(simulate(sheet_in_mm))


def test_dash_w_error_still_fails_the_command(sheet_in_mm: Path) -> None:
    """``python -W error`` (a category, so that a dependency's DeprecationWarning at import cannot be what fails)."""
    argv = [sys.executable, "-W", "error::UserWarning", "-m", "redsim", *simulate(sheet_in_mm), "--threads", "1"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1 and done.stdout == "", done.stderr
    assert done.stderr.splitlines()[-1].startswith(f"UserWarning: mesh {str(sheet_in_mm)!r} spans 500 m"), done.stderr


def test_a_third_party_warning_names_its_package_and_category(
    cli: Cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Gymnasium's logger colours its warnings and starts them with "WARN: "; the line names gymnasium (the code that
    warned, not the logger) and the category. Each location still warns once (Python's default), and a message's
    further lines are indented under its first."""
    import gymnasium

    def warn() -> None:
        for _ in range(2):  # float64 bounds cast to float32: gymnasium warns for low and for high
            gymnasium.spaces.Box(low=np.array([0.1]), high=np.array([1.0]), dtype=np.float32)
        warnings.warn("first line\nsecond line\n\nfourth line", FutureWarning, stacklevel=1)

    warn_in_cache_info(warn, tmp_path, monkeypatch)
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        code, _, err = cli("cache", "info", "--json")
    assert code == 0, err
    module = __name__.partition(".")[0]  # this test's module, as pytest imported it
    assert err.splitlines() == [
        "redsim: warning (gymnasium, UserWarning): Box low's precision lowered by casting to float32, current "
        "low.dtype=float64",
        "redsim: warning (gymnasium, UserWarning): Box high's precision lowered by casting to float32, current "
        "high.dtype=float64",
        f"redsim: warning ({module}, FutureWarning): first line",
        "  second line",
        "",
        "  fourth line",
    ]


def test_a_warning_is_said_once_per_run_though_pythons_memory_of_it_is_reset(
    cli: Cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Python shows a location's warning once until any ``catch_warnings`` or filter change in the process resets its
    memory (the standard library's ``subprocess`` does, Gymnasium's and our own): a command said the same line again
    after each. Now each line once per run, and every time where an ``always`` filter asks for it."""

    def warn() -> None:
        for _ in range(3):
            with warnings.catch_warnings():  # what resets Python's once-per-location memory
                pass
            warnings.warn("the same warning", UserWarning, stacklevel=1)
        warnings.warn("another warning", UserWarning, stacklevel=1)

    warn_in_cache_info(warn, tmp_path, monkeypatch)
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        code, _, err = cli("cache", "info", "--json")
        said = f"redsim: warning ({__name__.partition('.')[0]}, UserWarning): "  # this test's module warns
        assert code == 0 and err.splitlines() == [f"{said}the same warning", f"{said}another warning"]
        code, _, err = cli("cache", "info", "--json")  # a run of its own: said again
        assert code == 0 and err.count("the same warning") == 1
        warnings.filterwarnings("always", message="the same")
        code, _, err = cli("cache", "info", "--json")
    assert code == 0 and err.count("the same warning") == 3 and err.count("another warning") == 1


def test_without_stderr_a_warning_is_dropped_not_written_into_stdout(
    sheet_in_mm: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """With stderr closed (``redsim ... 2>&-``) Python's ``sys.stderr`` is None, and ``print(file=None)`` writes to
    stdout: the warning line went into the ``--json`` document. As Python's own display, it is now dropped."""
    monkeypatch.setattr(sys, "stderr", None)
    code = main(simulate(sheet_in_mm))
    out = capsys.readouterr().out
    assert code == 0 and "warning" not in out, out
    assert json.loads(out)["scene"] == "mesh_cloth"


def test_without_stderr_an_error_is_dropped_not_written_into_stdout(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The CLI's own lines (``redsim: error: ...``, warnings and progress notes) went into stdout as well."""
    monkeypatch.setattr(sys, "stderr", None)
    code = main(["simulate", "no_such_scene", "--json"])
    assert code == 2 and capsys.readouterr().out == ""


def test_bench_scaling_s_spawned_sizes_warn_of_float32_round_off_only(cli: Cli) -> None:
    """bench scaling measures each size in a spawned process, which showed its warnings in Python's display (the file,
    line and source line), twice per size: the stepper's float32 warning that it resolved accelerations only to more
    than 1% of g at k = 3 (3.8 m/s^2 at k = 4, 2.7e4 at k = 17), for its two steppers: a map whose f(0) was far from
    rest set the stepper's force scale, and no step felt the tip load. The bench steps the map with f(0) at rest now
    (redsim.benches.scaling.rest_at_origin): in float64 nothing is left to warn of. In float32 the stepper's measured
    gradient round-off (LatentStepper.roundoff_tol, cd1e79b) is above tol 1e-6 on this beam (its cubature step ends
    unconverged): that warning is true, and each stepper that meets it says so on one line (the cubature's at 9.4x tol;
    the all-element one's at 1.04x, so a CPU that rounds a little better may leave it out). The one-line display of a
    spawned process's warning: tests/test_processes.py."""
    small = ["--fit-steps", "1", "--fit-warmup", "1", "--latent-steps", "1", "--cubature-elements", "5", "--no-full"]
    code, _, err = cli("bench", "scaling", "--sizes", "3", *small, "--dtype", "float64", "--json")
    assert code == 0 and err == "", err
    code, _, err = cli("bench", "scaling", "--sizes", "3", *small, "--dtype", "float32", "--json")
    lines = err.splitlines()
    assert code == 0 and 1 <= len(lines) <= 2, err
    assert all(line.startswith("redsim: warning: torch.float32's round-off in the reduced force") for line in lines)


def logged_in_cache_info(logging_lines: str, cache: Path) -> list[str]:
    """The stderr lines of ``redsim -v cache info`` (of the cache folder ``cache``), run in a new process whose
    command first runs ``logging_lines`` (Python lines, each indented by 4): the command line's own log handler,
    which an in-process run (pytest's handlers) does not get."""
    code = (
        "import logging, sys\n"
        "from redsim.cli import cache, main\n"
        "usage = cache.user_cache_usage\n"
        "def logging_usage(*args, **kwargs):\n"
        f"{logging_lines}"
        "    return usage(*args, **kwargs)\n"
        "cache.user_cache_usage = logging_usage\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    env = {**os.environ, "REDSIM_CACHE": str(cache)}
    done = subprocess.run(
        [sys.executable, "-c", code, "-v", "cache", "info"], capture_output=True, text=True, timeout=120, env=env
    )
    assert done.returncode == 0, done.stderr
    return done.stderr.splitlines()


def test_a_logged_warning_is_the_same_one_line_as_a_python_warning(tmp_path: Path) -> None:
    """A library's log warning (SB3 rollout rounding, an unreadable cache file) read ``redsim: WARNING:
    redsim.usercache: ...``, unlike every other warning line; ``-v`` progress keeps its logger's name."""
    lines = (
        "    logging.getLogger('redsim.usercache').warning('could not write the %s cache file', 'rest')\n"
        "    logging.getLogger('redsim.usercache').info('looked')\n"
    )
    assert logged_in_cache_info(lines, tmp_path) == [
        "redsim: warning: could not write the rest cache file",
        "redsim: INFO: redsim.usercache: looked",
    ]


def test_a_warning_logged_at_every_step_is_said_once_with_its_count_at_the_end(tmp_path: Path) -> None:
    """A library's log warning repeated at every step printed one ``redsim: warning: ...`` line per step (Python's
    warnings were said once, logged ones not); a different one is still said, and -v's progress lines each time."""
    lines = (
        "    log = logging.getLogger('redsim.integrators.implicit_euler')\n"
        "    for step in range(5):\n"
        "        log.warning('the step did not converge')\n"
        "    log.warning('another warning')\n"
        "    log.info('step')\n"
        "    log.info('step')\n"
    )
    assert logged_in_cache_info(lines, tmp_path) == [
        "redsim: warning: the step did not converge",
        "redsim: warning: another warning",
        "redsim: INFO: redsim.integrators.implicit_euler: step",
        "redsim: INFO: redsim.integrators.implicit_euler: step",
        "redsim: warning: the step did not converge (logged 5 times, shown once above)",
    ]
