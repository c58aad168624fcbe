"""``redsim cache info`` and ``redsim cache clear``: what redsim's user cache holds, and deleting it."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from redsim.cli.common import EXIT_OK, CliError, finish_command, json_out, out, shown_path, warn
from redsim.usercache import (
    CACHE_ENV,
    FOLDERS,
    ClearError,
    FolderUsage,
    cache_root,
    clear_user_cache,
    user_cache_usage,
)


def _megabytes(size: int) -> str:
    """``size`` [bytes] as bytes below 1 kB, kB below 1 MB, else MB (it printed ``1e-05 MB`` for 10 bytes)."""
    if size < 1000:
        return f"{size} B"
    return f"{size / 1e3:.3g} kB" if size < 1e6 else f"{size / 1e6:.1f} MB"


def _files(count: int) -> str:
    return f"{count} file" if count == 1 else f"{count} files"


def _rows(usage: list[FolderUsage]) -> list[dict[str, Any]]:
    return [{"folder": u.name, "path": str(u.path), "files": u.files, "bytes": u.bytes} for u in usage]


def _off() -> str:
    return f'the user cache is off (${CACHE_ENV} is "0", "off", "false", "no" or empty): nothing is kept on disk'


def _state(root: Path) -> str:
    """Whether the cache root is a ``"folder"``, ``"missing"`` (made at the first write) or ``"not a folder"``."""
    return "folder" if root.is_dir() else "not a folder" if root.exists() else "missing"


def _age(args: argparse.Namespace) -> float | None:
    days = args.older_than
    if days is not None and not (0.0 <= days < float("inf")):
        raise CliError(f"--older-than must be a finite number of days >= 0, got {days}")
    return days


def cmd_cache_info(args: argparse.Namespace) -> int:
    root = cache_root()
    usage = user_cache_usage(older_than_days=_age(args))
    if args.json:
        state = None if root is None else _state(root)
        json_out({"root": None if root is None else str(root), "state": state, "folders": _rows(usage)})
        return EXIT_OK
    if root is None:
        out(_off())
        return EXIT_OK
    older = "" if args.older_than is None else f" (files older than {args.older_than:g} days)"
    state = {"folder": "", "missing": " (not made yet: nothing is cached)"}.get(_state(root))
    if state is None:
        warn(f"${CACHE_ENV} names {shown_path(root)}, which is not a folder: nothing can be cached there")
    out(f"redsim user cache: {shown_path(root)}{older}{state or ''}")
    for u in usage:
        out(f"  {u.name:<11} {_files(u.files):>12} {_megabytes(u.bytes):>10}   {FOLDERS[u.name]}")
    out(f"  {'total':<11} {_files(sum(u.files for u in usage)):>12} {_megabytes(sum(u.bytes for u in usage)):>10}")
    return EXIT_OK


def cmd_cache_clear(args: argparse.Namespace) -> int:
    folders = args.folders or None
    unknown = [name for name in folders or () if name not in FOLDERS]
    if unknown:
        raise CliError(f"unknown cache folder(s) {', '.join(unknown)}; valid: {', '.join(FOLDERS)}")
    days = _age(args)
    root = cache_root()
    if root is None:
        if args.json:
            json_out({"root": None, "dry_run": args.dry_run, "deleted": []})
        else:
            out(_off())
        return EXIT_OK
    try:
        done, failed = (user_cache_usage if args.dry_run else clear_user_cache)(folders, days), None
    except ClearError as err:  # the others were deleted: say so, then which could not be
        done, failed = err.deleted, err
    if args.json:
        doc = {"root": str(root), "dry_run": args.dry_run, "deleted": _rows(done)}
        json_out({**doc, **({} if failed is None else {"failed": [str(path) for path, _ in failed.failed]})})
    else:
        verb = "would delete" if args.dry_run else "deleted"
        for u in done:
            out(f"{verb} {_files(u.files)} ({_megabytes(u.bytes)}) in {shown_path(u.path)}")
    if failed is not None:
        raise CliError(str(failed), code=1)  # as any file the command could not write (main)
    return EXIT_OK


def add_commands(sub: Any) -> None:
    """Add ``cache`` and its subcommands ``info`` and ``clear`` to the subcommands ``sub``."""
    described = "; ".join(f"{name}: {what}" for name, what in FOLDERS.items())
    p = sub.add_parser(
        "cache",
        help="show or clear redsim's user cache",
        description=(
            f"redsim's user cache (${CACHE_ENV}, by default $XDG_CACHE_HOME/redsim or ~/.cache/redsim; "
            f"{CACHE_ENV}=0 turns it off) keeps "
            f"work that a later process would otherwise repeat, in three folders ({described}). Every entry is "
            "computed again when it is missing, so clearing loses time, never results."
        ),
    )
    cache = p.add_subparsers(dest="cache_command", metavar="ACTION", required=True)
    p = cache.add_parser(
        "info", help="where the cache is and what it holds", description="Files and size of each cache folder."
    )
    p.add_argument(
        "--older-than", type=float, metavar="DAYS", help="count only files last written more than DAYS days ago"
    )
    finish_command(p, cmd_cache_info, "print one JSON object on stdout", threads=False)
    p = cache.add_parser(
        "clear",
        help="delete cached files",
        description=(
            "Delete the files in the named cache folders (default: all). Only the files redsim writes directly in "
            "those folders are deleted (named by their hash: <sha256>.npz, rest-latent-<sha256>.npz, "
            "SCENE-FINGERPRINT-OPTIONS.pt/.json/.fit.pt in subspaces), never a linked folder or file, another "
            "process's write in flight, a file of yours such as subspaces/chain.pt, or anything else under the cache "
            "root. Deleting subspaces/*.fit.pt makes an interrupted fit start over."
        ),
    )
    p.add_argument("folders", nargs="*", metavar="FOLDER", help=f"one of {', '.join(FOLDERS)} (default: all)")
    p.add_argument(
        "--older-than", type=float, metavar="DAYS", help="delete only files last written more than DAYS days ago"
    )
    p.add_argument("--dry-run", action="store_true", help="show what would be deleted, delete nothing")
    finish_command(p, cmd_cache_clear, "print one JSON object on stdout", threads=False)
