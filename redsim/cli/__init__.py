"""The ``redsim`` command line: ``scenes``, ``simulate``, ``fit``, ``inspect``, ``sample``, ``animate``, ``bench``,
``demo``, ``train-agent``, ``eval-agent``, ``cache``.

Every subcommand has ``--help`` and ``--json`` (one JSON document on stdout; human-readable
text otherwise). Bad input is reported as a single ``redsim: error: ...`` line on stderr with
exit status 2, never as a traceback. Commands that take a scene take a catalog name or a
user's mesh (``--mesh PATH --kind fem|tets|cloth``); commands that take a checkpoint rebuild its
scene from the checkpoint's ``.json`` (:func:`redsim.scenes.spec.scene_from_spec`).

Modules: :mod:`~redsim.cli.parser` (the parser and :func:`main`), :mod:`~redsim.cli.common`
(errors, output, shared options), and one per command group: :mod:`~redsim.cli.scenes`
(scenes, simulate), :mod:`~redsim.cli.subspaces` (fit, inspect, sample, animate),
:mod:`~redsim.cli.bench` (bench), :mod:`~redsim.cli.envs` (demo, bench envs, bench env-ab), :mod:`~redsim.cli.agents`
(train-agent, eval-agent), :mod:`~redsim.cli.cache` (cache info, cache clear).

Exit status: 0 success; 1 a scene failed to build (``scenes``), a size's process died (``bench scaling``) or a file
could not be read or written; 2 bad input; 3 NaN or inf; 4 a simulation step failed (implausible for its scene); 130
interrupted (Ctrl-C or SIGTERM).
"""

from __future__ import annotations

from redsim.cli.common import CliError
from redsim.cli.parser import build_parser, main

__all__ = ["CliError", "build_parser", "main"]
