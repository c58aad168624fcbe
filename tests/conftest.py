"""Shared test settings."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread() -> Iterator[None]:
    """One intra-op thread: on a busy shared CPU, multi-threaded tiny matmuls stall for a scheduler tick each."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(autouse=True)
def _no_user_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    """Tests never read or write the user's disk cache of full-space equilibria (REDSIM_CACHE=0)."""
    monkeypatch.setenv("REDSIM_CACHE", "0")
