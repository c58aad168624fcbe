"""redsim's user cache folder (``$REDSIM_CACHE``, by default ``~/.cache/redsim``), shared by the caches that use it."""

from __future__ import annotations

import logging
import os
import re
import tempfile
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)

CACHE_ENV = "REDSIM_CACHE"
"""Environment variable naming redsim's cache folder; "0", "off", "false", "no" or "" turn the disk cache off."""
FOLDERS = {
    "equilibria": "full-space static solves (the metrics' and benches' reference equilibria)",
    "subspaces": "maps fitted for scene parameters no shipped map covers (fit_if_missing), with resumable fits",
    "envs": "the envs' settled work (rest latents, held targets, Stewart's camera frame)",
}
"""The folders of redsim's user cache and what each holds; :func:`clear_user_cache` deletes files in these only."""
CACHE_FILES = {
    "equilibria": re.compile(r"[0-9a-f]{64}\.npz"),
    "subspaces": re.compile(r".+-[0-9a-f]{16}-[0-9a-f]{12}\.(?:pt|json|fit\.pt)"),
    "envs": re.compile(r"(?:[a-z0-9-]+-)?[0-9a-f]{64}\.npz"),
}
"""The names of the files redsim writes in each folder: an equilibrium's key hash (``<sha256>.npz``), a fitted map's
``SCENE-FINGERPRINT-OPTIONS`` stem (:func:`redsim.envs.fitted.cache_stem`: ``.pt``, ``.json`` and, while its fit is
unfinished, ``.fit.pt``), an env's settled work (``rest-latent-<sha256>.npz``; ``<sha256>.npz`` from earlier versions).
Nothing else there is counted or deleted: ``$REDSIM_CACHE`` may name a folder of the user's, whose own fits in
``subspaces/`` (README: ``redsim fit ... --out subspaces/SCENE``) are not the cache's."""
STALE_TEMPORARY_DAYS = 1.0
"""Age [days] past which a temporary file a writer left behind (an interrupted process: ``.*.npz.tmp``,
``*.pt.XXXXXXXXtmp``, ``*.json.XXXXXXXXtmp``; ``*.pt.tmp`` before stop 44) counts as cache; a younger one may be
another process's write in flight."""
TEMPORARY = re.compile(r"\.?(?P<name>.+?)(?:\.tmp|\.[a-z0-9_]{8}tmp)")
"""A temporary file's name: the file it will replace (``name``), a writer's own random part, ``tmp``."""
ARRAYS_TEMPORARY = re.compile(r"\.[a-z0-9_]{8}\.npz\.tmp")
"""A temporary file of :func:`write_arrays`: a writer's own random part, not the name of the file it replaces."""


def cache_root() -> Path | None:
    """redsim's user cache folder, or None when it is off (read at every use).

    ``$REDSIM_CACHE`` when the variable names a folder; off when it is "0", "off", "false", "no"
    or empty; by default ``$XDG_CACHE_HOME/redsim``, else ``~/.cache/redsim``. Its ``equilibria``
    folder holds full-space equilibria (:func:`redsim.integrators.cache.cache_directory`), its
    ``subspaces`` folder the maps the envs fit on request (:mod:`redsim.envs.fitted`), its ``envs`` folder the envs'
    settled work (held targets, Stewart's camera frame: :func:`redsim.envs.base.cached`).
    """
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        if value.strip().lower() in ("", "0", "off", "false", "no"):
            return None
        return Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "redsim"


def read_arrays(path: Path, key: str, what: str) -> dict[str, np.ndarray] | None:
    """The arrays a cache file at ``path`` holds for ``key`` (:func:`write_arrays`), or None: no file, or an unusable
    one (truncated, not a zip, another key), which is warned about (naming ``what`` it holds) and left for the
    caller to compute again. A path that cannot even be checked (a folder without permission, a name too long) is
    warned about too: the cache never stops the caller."""
    try:
        if not path.is_file():
            return None
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: np.array(data[name]) for name in data.files}
        if str(arrays.pop("key", None)) != key:
            raise ValueError("the file belongs to another key")
    except Exception as error:  # any damage means: compute again
        logger.warning("ignoring unreadable %s cache file %s (%s); computing again", what, path, error)
        return None
    return arrays


def write_arrays(path: Path, key: str, arrays: Mapping[str, np.ndarray], what: str) -> None:
    """Store ``arrays`` under ``key`` at ``path`` atomically (a temporary file, then a rename); a failure is
    warned about, never raised (the caller has its result; only the next process computes it again)."""
    temporary: Path | None = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=".", suffix=".npz.tmp", delete=False) as file:
            temporary = Path(file.name)
            np.savez(file, key=np.array(key), **arrays)
        temporary.chmod(0o644)  # a temporary file is private; the cache is not
        os.replace(temporary, path)
    except OSError as error:
        logger.warning("could not write the %s cache file %s (%s)", what, path, error)
        if temporary is not None:
            temporary.unlink(missing_ok=True)


@dataclass(frozen=True)
class FolderUsage:
    """One folder of the user cache: its path, files and their total size [bytes]."""

    name: str
    path: Path
    files: int
    bytes: int


def _files(root: Path, name: str, older_than_days: float | None = None) -> list[Path]:
    """redsim's files (:data:`CACHE_FILES`, and temporary files older than :data:`STALE_TEMPORARY_DAYS`) directly in
    ``root/name``, only those last written more than ``older_than_days`` days ago when given. None where the folder
    is missing, or is a link (``$REDSIM_CACHE`` may name a user's folder: a linked ``envs`` could lead anywhere);
    links and anything else in it are never counted."""
    folder = root / name
    if folder.is_symlink() or not folder.is_dir():
        return []
    now = time.time()
    cutoff = None if older_than_days is None else now - 86400.0 * older_than_days
    found = []
    for path in folder.iterdir():
        temporary = path.name.endswith("tmp") and (found_name := TEMPORARY.fullmatch(path.name)) is not None
        stem = found_name["name"] if temporary else path.name
        arrays = name != "subspaces" and ARRAYS_TEMPORARY.fullmatch(path.name) is not None
        if not (arrays or CACHE_FILES[name].fullmatch(stem)):
            continue
        try:
            if path.is_symlink() or not path.is_file():
                continue
            written = path.stat().st_mtime
        except OSError:  # removed meanwhile by another process
            continue
        if temporary and written > now - 86400.0 * STALE_TEMPORARY_DAYS:
            continue
        if cutoff is None or written < cutoff:
            found.append(path)
    return found


def _size(path: Path) -> int | None:
    """The size of ``path`` [bytes], None if another process removed it meanwhile."""
    try:
        return path.stat().st_size
    except OSError:
        return None


def _selected(folders: Iterable[str] | None, older_than_days: float | None) -> dict[str, tuple[Path, list[Path]]]:
    """Each chosen folder's path and files ({} with the cache off); refuses unknown names and bad ages up front."""
    chosen = list(FOLDERS) if folders is None else list(dict.fromkeys(folders))
    unknown = [name for name in chosen if name not in FOLDERS]
    if unknown:
        raise ValueError(f"unknown cache folder(s) {unknown}; valid: {list(FOLDERS)}")
    if older_than_days is not None and not (0.0 <= older_than_days < float("inf")):
        raise ValueError(f"older_than_days must be a finite number >= 0 [days], got {older_than_days}")
    root = cache_root()
    if root is None:
        return {}
    return {name: (root / name, _files(root, name, older_than_days)) for name in chosen}


def user_cache_usage(folders: Iterable[str] | None = None, older_than_days: float | None = None) -> list[FolderUsage]:
    """Files and bytes in each of ``folders`` (default: all of :data:`FOLDERS`) of the user cache, counting only
    files last written more than ``older_than_days`` days ago when given; [] with the cache off.

    Raises:
        ValueError: a name not in :data:`FOLDERS`, or a negative or non-finite ``older_than_days``.
    """
    usage = []
    for name, (folder, files) in _selected(folders, older_than_days).items():
        sizes = [size for size in map(_size, files) if size is not None]
        usage.append(FolderUsage(name, folder, len(sizes), sum(sizes)))
    return usage


class ClearError(OSError):
    """Files of the user cache that could not be deleted (permissions, a read-only folder); the others were.

    Attributes:
        deleted: What was deleted per folder (as :func:`clear_user_cache` returns it).
        failed: Each file not deleted, with its error.
    """

    def __init__(self, deleted: list[FolderUsage], failed: list[tuple[Path, OSError]]) -> None:
        path, first = failed[0]
        others = f" and {len(failed) - 1} more file(s)" if len(failed) > 1 else ""
        super().__init__(
            first.errno, f"could not delete {path}{others} of redsim's user cache ({first.strerror or first})"
        )
        self.deleted, self.failed = deleted, failed


def clear_user_cache(folders: Iterable[str] | None = None, older_than_days: float | None = None) -> list[FolderUsage]:
    """Delete the files in ``folders`` (default: all of :data:`FOLDERS`) of the user cache, only those last
    written more than ``older_than_days`` days ago when given; returns what was deleted per folder ([] with the
    cache off). Only redsim's own files directly in those folders are touched (:data:`CACHE_FILES`; never the cache
    root itself, which ``$REDSIM_CACHE`` may point anywhere, a linked folder or file, or another process's write in
    flight). Every entry is computed again when next needed; deleting a fit's
    training state (``subspaces/*.fit.pt``) means an interrupted fit starts over. A file another process removed
    meanwhile is skipped; those that cannot be deleted are raised about once the others are.

    Raises:
        ValueError: as :func:`user_cache_usage`, before anything is deleted.
        ClearError: an OSError; files that exist but could not be deleted (permissions), after the others were.
    """
    deleted, failed = [], []
    for name, (folder, files) in _selected(folders, older_than_days).items():
        count = total = 0
        for path in files:
            size = _size(path)
            try:
                path.unlink()
            except FileNotFoundError:
                continue
            except OSError as error:
                failed.append((path, error))
                continue
            count += 1
            total += size or 0
        deleted.append(FolderUsage(name, folder, count, total))
    if failed:
        raise ClearError(deleted, failed)
    return deleted


__all__ = [
    "CACHE_ENV",
    "FOLDERS",
    "ClearError",
    "FolderUsage",
    "cache_root",
    "clear_user_cache",
    "read_arrays",
    "user_cache_usage",
    "write_arrays",
]
