"""redsim's user cache folder (``$REDSIM_CACHE``, by default ``~/.cache/redsim``), shared by the caches that use it."""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)

CACHE_ENV = "REDSIM_CACHE"
"""Environment variable naming redsim's cache folder; "0", "off", "false", "no" or "" turn the disk cache off."""


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


__all__ = ["CACHE_ENV", "cache_root", "read_arrays", "write_arrays"]
