"""redsim's user cache folder (``$REDSIM_CACHE``, by default ``~/.cache/redsim``), shared by the caches that use it."""

from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV = "REDSIM_CACHE"
"""Environment variable naming redsim's cache folder; "0", "off", "false", "no" or "" turn the disk cache off."""


def cache_root() -> Path | None:
    """redsim's user cache folder, or None when it is off (read at every use).

    ``$REDSIM_CACHE`` when the variable names a folder; off when it is "0", "off", "false", "no"
    or empty; by default ``$XDG_CACHE_HOME/redsim``, else ``~/.cache/redsim``. Its ``equilibria``
    folder holds full-space equilibria (:func:`redsim.integrators.cache.cache_directory`), its
    ``subspaces`` folder the maps the envs fit on request (:mod:`redsim.envs.fitted`).
    """
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        if value.strip().lower() in ("", "0", "off", "false", "no"):
            return None
        return Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "redsim"


__all__ = ["CACHE_ENV", "cache_root"]
