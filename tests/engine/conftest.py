"""Fixtures of the engine tests: a private equilibrium cache and a counter of full-space solves."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from redsim.integrators import cache, reference


@pytest.fixture
def equilibrium_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """An own empty disk cache (never the user's) and an empty memory cache; yields the cache folder."""
    monkeypatch.setenv(cache.CACHE_ENV, str(tmp_path / "cache"))
    cache.clear_cache()
    yield tmp_path / "cache" / "equilibria"
    cache.clear_cache()


@pytest.fixture
def count_solves(monkeypatch: pytest.MonkeyPatch) -> Callable[[], list[int]]:
    """Call it to start counting the full-space solves (cache misses of memory and disk): one entry per solve."""

    def start() -> list[int]:
        calls: list[int] = []
        solve = reference._solve_full

        def counted(*args: Any, **kwargs: Any) -> Any:
            calls.append(1)
            return solve(*args, **kwargs)

        monkeypatch.setattr(reference, "_solve_full", counted)
        return calls

    return start
