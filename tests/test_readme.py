"""README.md's code blocks run as written: every ```python block on its own, top to bottom, in an
empty folder; every `redsim ...` command line of the ```bash blocks parses, and the cheap ones run.

The commands that take minutes (fits with presets, `bench`, `simulate` of real scenes) are only
parsed by default; the slow test runs the `simulate` lines too.
"""

from __future__ import annotations

import re
import shlex
import shutil
from pathlib import Path

import pytest

from redsim import pretrained
from redsim.cli import build_parser, main

README = Path(__file__).resolve().parents[1] / "README.md"
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
CHEAP = ("scenes", "inspect", "sample", "animate")
"""Commands that run in seconds (`inspect`/`sample`/`animate` on the shipped mini chain map)."""


def blocks(language: str) -> list[str]:
    return [body for lang, body in FENCE.findall(README.read_text()) if lang == language]


def redsim_commands() -> list[list[str]]:
    """Every `redsim ...` command of the bash blocks (split at `&&`, comments dropped), as argv lists."""
    commands = []
    for block in blocks("bash"):
        for line in block.splitlines():
            for part in line.split("&&"):
                argv = shlex.split(part, comments=True)
                if argv and argv[0] == "redsim":
                    commands.append(argv[1:])
    return commands


def test_readme_has_the_blocks_this_test_reads() -> None:
    assert len(blocks("python")) >= 2
    commands = [argv[0] for argv in redsim_commands()]
    assert {"scenes", "simulate", "fit", "inspect", "sample", "animate"} <= set(commands)


@pytest.mark.parametrize("index", range(len(blocks("python"))))
def test_python_block_runs_on_its_own(index: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    code = blocks("python")[index]
    exec(compile(code, f"README.md python block {index}", "exec"), {"__name__": "__main__"})  # as a script runs it


@pytest.mark.parametrize("argv", redsim_commands(), ids=lambda a: " ".join(a)[:60])
def test_redsim_command_parses(argv: list[str]) -> None:
    args = build_parser().parse_args(argv)
    assert callable(args.func)


def _shipped_mini_chain(folder: Path) -> None:
    """Put the shipped mini chain map where the README's fit writes it (it was made by that command)."""
    target = folder / "subspaces"
    target.mkdir(exist_ok=True)
    for suffix in (".pt", ".json"):
        shutil.copy(pretrained.path("mini_chain").with_suffix(suffix), target / f"mini_chain{suffix}")


def _runnable(kinds: tuple[str, ...]) -> list[list[str]]:
    return [a for a in redsim_commands() if a[0] in kinds and not any(p.startswith("subspaces/part") for p in a)]


@pytest.mark.parametrize("argv", _runnable(CHEAP), ids=lambda a: " ".join(a)[:60])
def test_cheap_redsim_command_runs(argv: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    _shipped_mini_chain(tmp_path)
    assert main(argv) == 0


@pytest.mark.slow
@pytest.mark.parametrize("argv", _runnable(("simulate",)), ids=lambda a: " ".join(a)[:60])
def test_simulate_command_runs(argv: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    if "--mesh" in argv:
        pytest.skip("needs the user's own mesh file")
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 0
