"""The ``redsim`` argument parser, assembled from the command groups, and :func:`main`."""

from __future__ import annotations

import argparse
import functools
import logging
import os
import shlex
import signal
import sys
import threading
import warnings
from collections.abc import Sequence
from pathlib import Path

import redsim
from redsim.cli import agents, bench, cache, cubature, envs, scenes, subspaces
from redsim.cli.common import (
    EXIT_INTERRUPTED,
    CliError,
    Parser,
    StdoutClosed,
    check_writable,
    command_threads,
    error,
    expand_home,
    show_warning,
    warn,
)
from redsim.interrupts import deferred_interrupts


def build_parser() -> argparse.ArgumentParser:
    """The ``redsim`` argument parser with its subcommands."""
    parser = Parser(
        prog="redsim",
        description="Data-free neural reduced-order simulation and control of physical systems.",
    )
    parser.add_argument("--version", action="version", version=f"redsim {redsim.__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress (INFO) to stderr")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    scenes.add_commands(sub)
    subspaces.add_commands(sub)
    cubature.add_commands(sub)
    envs.add_commands(sub, bench.add_commands(sub))
    agents.add_commands(sub)
    cache.add_commands(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``redsim`` command line.

    Args:
        argv: Arguments without the program name (default: ``sys.argv[1:]``).

    Returns:
        The exit status (0 ok, 1 a scene failed to build, a file could not be read or written, or memory ran out,
        2 bad input, 3 NaN, 4 a failed simulation step, 130 interrupted: Ctrl-C, or SIGTERM as a batch scheduler or
        ``kill`` sends it, which takes the same path, so an interrupted fit or training run saves what it has).

    Python warnings are shown as one ``redsim: warning: ...`` line each (:func:`redsim.cli.common.show_warning`),
    each line once per run, while it runs; the caller's ``warnings.showwarning`` and filters are back when it returns.
    """
    try:
        if argv is None:  # the command line's own stdout, not an in-process caller's
            _stdout_writes_any_character()
        with warnings.catch_warnings():  # restores showwarning (and the filters) on return: tests call main in-process
            warnings.showwarning = functools.partial(show_warning, said=set())  # a partial adds no frame to walk
            return _run(argv)
    except KeyboardInterrupt:  # outside a command: while the parser is built or a command's options load (fit's torch)
        warn("interrupted")
        return EXIT_INTERRUPTED


def _run(argv: Sequence[str] | None) -> int:
    """:func:`main` under the command line's warning display."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as done:  # --help and --version
        return int(done.code or 0)
    except CliError as err:
        error(str(err))
        return err.code
    args.command_line = shlex.join(["redsim", *(sys.argv[1:] if argv is None else argv)])  # said with "rerun: "
    if not logging.root.handlers:  # as basicConfig: a caller's own logging setup (a notebook, pytest) stays
        handler = logging.StreamHandler()
        handler.setFormatter(LogFormat())
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, handlers=[handler])
    said_once = WarnedOnce.install()
    terminate = _interrupt_on_sigterm()
    try:
        _load_torch(args)
        with command_threads(args), warnings.catch_warnings():  # the CLI says it in one line (parse_env_id)
            expand_home(args)
            _check_out(args)
            warnings.filterwarnings(
                "ignore", message=".*The environment RedSim/.* is out of date", category=DeprecationWarning
            )
            return int(args.func(args))
    except CliError as err:
        error(str(err))
        return err.code
    except StdoutClosed:  # stdout's reader left (`redsim ... | head`): no traceback, and none at exit
        if argv is None:  # the command line, not an in-process caller whose stdout this would close
            _silence_stdout()
        return 1
    except OSError as err:  # a file the command could not read or write (a full disk, a path the OS refuses)
        error(f"{err.strerror or err}: {err.filename}" if err.filename else str(err))
        return 1
    except KeyboardInterrupt:  # a command without its own handler (fit and train-agent save and say more)
        warn("interrupted")
        return EXIT_INTERRUPTED
    except (MemoryError, RuntimeError) as err:
        if not _out_of_memory(err):
            raise
        error(
            f"out of memory: {str(err).splitlines()[0] if str(err) else type(err).__name__}; ask for less (fewer "
            "batches, envs, samples or states), or free memory"
        )
        return 1
    finally:
        if terminate is not None:
            signal.signal(signal.SIGTERM, terminate)
        if said_once is not None:
            said_once.uninstall()


class LogFormat(logging.Formatter):
    """The command line's log lines on stderr: a warning as ``redsim: warning: MESSAGE``, the line a Python warning and
    the command's own warnings make (it was ``redsim: WARNING: redsim.trainers.agents: MESSAGE``); progress (``-v``)
    and the other levels as ``redsim: INFO: LOGGER: MESSAGE``."""

    def __init__(self) -> None:
        super().__init__("redsim: %(levelname)s: %(name)s: %(message)s")

    def formatMessage(self, record: logging.LogRecord) -> str:
        if record.levelno == logging.WARNING:
            return f"redsim: warning: {record.message}"
        return super().formatMessage(record)


class WarnedOnce(logging.Filter):
    """Each logged warning line once per run on the command line's log handler (:class:`LogFormat`): one a library
    logs at every step said it hundreds of times. A Python warning is said once already
    (:func:`redsim.cli.common.show_warning`); the count of each repeated one is said at the end."""

    def __init__(self, handler: logging.Handler) -> None:
        super().__init__()
        self.handler = handler
        self.times: dict[str, int] = {}
        """Each warning's message -> the times it was logged."""

    @classmethod
    def install(cls) -> WarnedOnce | None:
        """Filter the command line's log handler for this run; None where the root logger has none (a caller's own
        logging setup: a notebook, pytest)."""
        handler = next((h for h in logging.root.handlers if isinstance(h.formatter, LogFormat)), None)
        if handler is None:
            return None
        said = cls(handler)
        handler.addFilter(said)
        return said

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno != logging.WARNING:
            return True
        text = record.getMessage()
        self.times[text] = self.times.get(text, 0) + 1
        return self.times[text] == 1

    def uninstall(self) -> None:
        """Say each repeated warning's count, and take the filter off."""
        self.handler.removeFilter(self)
        for text, times in self.times.items():
            if times > 1:
                warn(f"{text.splitlines()[0]} (logged {times} times, shown once above)")


def _out_of_memory(err: BaseException) -> bool:
    """Whether ``err`` says memory ran out: Python's MemoryError, torch's CPU allocator ("can't allocate memory") or
    its device one (``torch.OutOfMemoryError``)."""
    text = str(err)
    return (
        isinstance(err, MemoryError)
        or type(err).__name__ == "OutOfMemoryError"
        or "can't allocate memory" in text
        or "out of memory" in text.lower()
    )


def _load_torch(args: argparse.Namespace) -> None:
    """Load torch for a command that runs it (all but ``cache``), with Ctrl-C held until it has loaded, a second
    one too (:func:`redsim.interrupts.deferred_interrupts`, ``forced=False``): a KeyboardInterrupt raised inside
    torch's C++ start-up (``torch._C._c10d_init`` calls back into Python) escaped as a C++ exception, and the process
    aborted ("terminate called after throwing an instance of 'pybind11::error_already_set'", exit 134)."""
    if args.command == "cache":
        return
    with deferred_interrupts(forced=False):  # a Ctrl-C is raised as the block ends
        import torch  # noqa: F401


def _raise_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def _interrupt_on_sigterm() -> object:
    """Make SIGTERM raise KeyboardInterrupt while a command runs (main thread only); returns the handler it replaced
    (None off the main thread, where none is set)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    return signal.SIG_DFL if previous is None else previous


def _check_out(args: argparse.Namespace) -> None:
    """Refuse an ``--out`` whose folder could not be made or written, before any work (a fit or a bench that ends
    in a traceback loses its results): :func:`redsim.cli.common.check_writable`. An empty path is refused (it read as
    the default, or as no output at all)."""
    for flag in ("out", "meshes"):
        if getattr(args, flag, None) == "":
            raise CliError(f"--{flag} is empty: name a path, or leave the option out for its default")
    out = getattr(args, "out", None)
    if out is None:
        return
    if not getattr(args, "out_is_folder", False) and (
        out.endswith(("/", os.sep)) or os.path.basename(out) in ("", ".", "..")  # a stem may share a folder's name
    ):
        raise CliError(f"--out {out} is a folder; name a file in it (e.g. {Path(out) / 'NAME'})")
    check_writable(out, "--out", folder=getattr(args, "out_is_folder", False))


def _stdout_writes_any_character() -> None:
    """Write a character stdout's encoding lacks as a ``\\u`` escape: where it is not UTF-8 (Windows when stdout is a
    file or a pipe: cp1252; ``PYTHONIOENCODING=ascii``), the σ and ρ of ``redsim fit --help`` and the ± of
    ``eval-agent`` ended the command in a UnicodeEncodeError traceback. stderr does so already (Python's default)."""
    stream = sys.stdout
    encoding = (getattr(stream, "encoding", None) or "").lower().replace("-", "").replace("_", "")
    if encoding != "utf8" and hasattr(stream, "reconfigure"):
        stream.reconfigure(errors="backslashreplace")


def _silence_stdout() -> None:
    """Point stdout at the null device, so the interpreter's final flush does not raise again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # no file descriptor (a captured stdout)
        pass
