"""The ``redsim`` argument parser, assembled from the command groups, and :func:`main`."""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence

import torch

import redsim
from redsim.cli import agents, bench, cubature, envs, scenes, subspaces
from redsim.cli.common import CliError, Parser, apply_threads, error


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
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``redsim`` command line.

    Args:
        argv: Arguments without the program name (default: ``sys.argv[1:]``).

    Returns:
        The exit status (0 ok, 1 a scene failed to build, 2 bad input, 3 NaN, 4 a failed simulation
        step, 130 interrupted).
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as done:  # --help and --version
        return int(done.code or 0)
    except CliError as err:
        error(str(err))
        return err.code
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="redsim: %(levelname)s: %(name)s: %(message)s",
    )
    threads = torch.get_num_threads()
    try:
        apply_threads(args)
        return int(args.func(args))
    except CliError as err:
        error(str(err))
        return err.code
    finally:
        torch.set_num_threads(threads)  # in-process callers (tests, notebooks) keep their setting
