"""Shared test settings."""

from __future__ import annotations

from collections.abc import Callable, Iterator

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


@pytest.fixture
def cli(capsys: pytest.CaptureFixture[str]) -> Callable[..., tuple[int, str, str]]:
    """Run ``redsim ARGV...`` in-process: ``cli("simulate", ...) -> (exit status, stdout, stderr)``."""
    from redsim.cli import main

    def run(*argv: str) -> tuple[int, str, str]:
        code = main(list(argv))
        out, err = capsys.readouterr()
        return code, out, err

    return run
