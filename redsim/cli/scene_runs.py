"""A bench's loop over scenes that keeps its finished rows: a scene that raises is reported and the others run
(exit 1 at the end), and Ctrl-C ends the loop so that the rows finished before it are printed (exit 130)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, TypeVar

from redsim.cli.common import EXIT_INTERRUPTED, EXIT_OK, EXIT_SCENE_FAILED, CliError, error, out, warn

T = TypeVar("T")


@dataclass
class SceneRuns:
    """How a loop of :func:`run_scenes` ended: ``failed`` (``scene``, ``error``: 'TYPE: message') and
    ``interrupted`` (Ctrl-C). ``unit`` names what the loop runs in the messages ('scene', 'regime', 'size')."""

    command: str
    text: bool
    unit: str = "scene"
    failed: list[dict[str, str]] = field(default_factory=list)
    interrupted: bool = False

    def fields(self) -> dict[str, Any]:
        """The JSON document's ``failed`` and ``interrupted``."""
        return {"failed": self.failed, "interrupted": self.interrupted}

    def status(self, status: int = EXIT_OK) -> int:
        """The exit status, after the rows are printed: 130 if interrupted, else ``status`` (a bench's own failure,
        3 or 4) if not 0, else 1 if a scene raised; says which on stderr, each with its error (the text's
        ``failed:`` lines are on stdout, in the report; a JSON run's are in its ``failed``)."""
        if self.failed:
            names = ", ".join(f["scene"] for f in self.failed)
            reasons = "".join(f"; {f['scene']} raised {' '.join(str(f['error']).split())}" for f in self.failed)
            error(f"{self.command}: {len(self.failed)} {self.unit}(s) failed ({names}); the others ran{reasons}")
        if self.interrupted:
            if self.text:
                out(f"interrupted: the {self.unit}s finished before it")
            warn(f"interrupted: the table has the {self.unit}s finished before it")
            return EXIT_INTERRUPTED
        return status if status != EXIT_OK or not self.failed else EXIT_SCENE_FAILED


def run_scenes(
    command: str, scenes: Iterable[tuple[str, T]], run: Callable[[str, T], None], *, text: bool, unit: str = "scene"
) -> SceneRuns:
    """Call ``run(name, item)`` for each scene of ``scenes``; an Exception (not a :class:`CliError`, bad input) is
    recorded, with a ``failed: NAME: TYPE: message`` line when ``text``, and the next scene runs; a
    KeyboardInterrupt ends the loop. ``command`` (e.g. 'bench fit') and ``unit`` name the command and what it runs
    in the messages."""
    runs = SceneRuns(command, text, unit)
    try:
        for name, item in scenes:
            try:
                run(name, item)
            except CliError:
                raise
            except Exception as err:  # reported in the output and the exit status, not a traceback
                runs.failed.append({"scene": name, "error": f"{type(err).__name__}: {err}"})
                if text:
                    out(f"failed: {name}: {runs.failed[-1]['error']}")
    except KeyboardInterrupt:  # Ctrl-C: the caller prints the scenes finished before it, then exits 130
        runs.interrupted = True
    return runs


__all__ = ["SceneRuns", "run_scenes"]
