"""Fixtures of the engine tests: a private equilibrium cache, a counter of full-space solves and the derivatives
of an energy to third order (for the closed-form kernels against autograd)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import torch

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


def _derivatives(
    energies: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor, u: torch.Tensor, v: torch.Tensor
) -> list[torch.Tensor]:
    """Energies, gradient, Hessian . u and third derivative . (u, v) of the summed energies at x (all detached)."""
    x = x.detach().requires_grad_(True)
    e = energies(x)
    (g,) = torch.autograd.grad(e.sum(), x, create_graph=True)
    (hu,) = torch.autograd.grad((g * u).sum(), x, create_graph=True)
    (tuv,) = torch.autograd.grad((hu * v).sum(), x)
    return [t.detach() for t in (e, g, hu, tuv)]


@pytest.fixture
def derivatives() -> Callable[..., list[torch.Tensor]]:
    """The function of :func:`_derivatives`: an energy's derivatives to third order, to compare two kernels."""
    return _derivatives
