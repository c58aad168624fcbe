"""The ``redsim`` command line: ``scenes``, ``simulate``, ``fit``, ``inspect``, ``sample``, ``animate``, ``bench``,
``demo``, ``train-agent``, ``eval-agent``, ``cache``.

Every subcommand has ``--help`` and ``--json`` (one JSON document on stdout; human-readable
text otherwise). Bad input is reported as a single ``redsim: error: ...`` line on stderr with
exit status 2, never as a traceback. Commands that take a scene take a catalog name or a
user's mesh (``--mesh PATH --kind fem|tets|cloth``); commands that take a checkpoint rebuild its
scene from the checkpoint's ``.json`` (:func:`redsim.scenes.spec.scene_from_spec`).

Modules: :mod:`~redsim.cli.parser` (the parser, and the ``main`` that :func:`main` loads and runs),
:mod:`~redsim.cli.common` (errors, output, shared options), and one per command group: :mod:`~redsim.cli.scenes`
(scenes, simulate), :mod:`~redsim.cli.subspaces` (fit, inspect, sample, animate),
:mod:`~redsim.cli.bench` (bench), :mod:`~redsim.cli.envs` (demo, bench envs, bench env-ab), :mod:`~redsim.cli.agents`
(train-agent, eval-agent), :mod:`~redsim.cli.cache` (cache info, cache clear).

Exit status: 0 success; 1 a scene failed to build (``scenes``), a size's process died or raised (``bench scaling``) or
a file could not be read or written; 2 bad input; 3 NaN or inf; 4 a simulation step failed (implausible for its scene);
130 interrupted (Ctrl-C or SIGTERM).
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the lazy names (:data:`_LAZY`), for type checkers and IDEs; imported on first use at run time
    from redsim.cli.common import CliError
    from redsim.cli.parser import build_parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``redsim`` command line (:func:`redsim.cli.parser.main`). Its modules load here, under the same Ctrl-C
    handling as a command: one ``redsim: warning: interrupted`` line and exit 130 (a Ctrl-C in that first tenth of a
    second printed a traceback of the imports)."""
    try:
        from redsim.cli.parser import main as run
    except KeyboardInterrupt:
        if sys.stderr is not None:
            print("redsim: warning: interrupted", file=sys.stderr, flush=True)
        return 130  # redsim.cli.common.EXIT_INTERRUPTED: common is among the modules a Ctrl-C may stop
    return run(argv)


_LAZY = {"CliError": "redsim.cli.common", "build_parser": "redsim.cli.parser"}
"""Public name -> the module that defines it, imported on first use (PEP 562): ``from redsim.cli import main`` (the
``redsim`` script) loads none of the commands, so :func:`main` can catch a Ctrl-C while they load."""


def __getattr__(name: str) -> object:
    """Import a public name (:data:`_LAZY`) on first use."""
    if name not in _LAZY:
        raise AttributeError(f"module 'redsim.cli' has no attribute {name!r}")
    return getattr(importlib.import_module(_LAZY[name]), name)


__all__ = ["CliError", "build_parser", "main"]
