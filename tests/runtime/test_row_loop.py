"""The row-selected loop's bookkeeping (index lists, selections of every row skipped) on a toy objective whose first
trials are all rejected and non-finite, then some finite but rejected (the model relearned from them): the same
iterates as the dense loop, which updates every state by masks."""

from __future__ import annotations

import torch
from torch import Tensor

from redsim.runtime.solver import minimize

LIMIT = 50.0
"""|z| beyond which the toy objective is NaN (a non-finite trial)."""


class _Quartic:
    """Phi_b(z) = sum_j c_bj (z_j^2 / 2 + z_j^4 / 4), NaN where any |z_j| > LIMIT; records each call's rows."""

    def __init__(self, c: Tensor) -> None:
        self.c = c
        self.calls: list[tuple[Tensor, Tensor]] = []

    def value_and_grad(self, z: Tensor, index: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        c = self.c[index]
        value = (c * (0.5 * z**2 + 0.25 * z**4)).sum(-1)
        grad = c * (z + z**3)
        bad = (z.abs() > LIMIT).any(-1)
        value = torch.where(bad, torch.nan, value)
        grad = torch.where(bad[:, None], torch.nan, grad)
        self.calls.append((index.clone(), torch.isfinite(value)))
        return value, grad, value

    def metric(self, z: Tensor, index: Tensor) -> Tensor:
        return torch.diag_embed(self.c[index])


def _solve(dense: bool) -> tuple[object, _Quartic]:
    g = torch.Generator().manual_seed(0)
    batch, d = 6, 3
    objective = _Quartic(1.0 + torch.rand(batch, d, generator=g, dtype=torch.float64))
    z0 = torch.randn(batch, d, generator=g, dtype=torch.float64)
    # a warm model far too soft: every first step is ~1e5-1e15 long (NaN trials, then backtracks)
    soft = torch.tensor([1e-14, 1e-14, 1e-14, 1e-6, 1e-6, 1e-6], dtype=torch.float64)
    warm = soft[:, None, None] * torch.eye(d, dtype=torch.float64)
    result = minimize(
        objective,
        z0,
        torch.ones(batch, dtype=torch.float64),
        torch.zeros(batch, dtype=torch.float64),
        tol=1e-10,
        max_iter=50,
        hessian="bfgs",
        warm=warm,
        warm_refresh=False,
        dense=dense,
    )
    return result, objective


def test_row_loop_equals_dense_loop_through_rejections_and_restarts() -> None:
    rows, calls = _solve(dense=False)
    dense, _ = _solve(dense=True)
    first_index, first_finite = calls.calls[1]  # (calls[0]: the start)
    assert first_index.numel() == 6 and not bool(first_finite.any())  # every first trial rejected, non-finite
    assert bool(rows.converged.all()) and bool(dense.converged.all())
    assert torch.equal(rows.iterations, dense.iterations)
    torch.testing.assert_close(rows.z, dense.z, rtol=0.0, atol=1e-12)
    # the row loop's numpy arithmetic and the dense loop's torch differ by an ulp or two per op, which ~50 BFGS updates
    # from a 1e-14 model compound to ~2e-10 on entries of size ~1 (measured; the iterates agree to 1e-12)
    torch.testing.assert_close(rows.model, dense.model, rtol=1e-9, atol=1e-9)
    # calls whose trials were all non-finite (all rejected), all finite, and a mix
    kinds = {(bool(finite.all()), bool(finite.any())) for _, finite in calls.calls[1:]}
    assert kinds == {(False, False), (True, True), (False, True)}


def test_finite_is_isfinite() -> None:
    from redsim.runtime.solver import _finite

    for dtype in (torch.float32, torch.float64):
        big = torch.finfo(dtype).max
        t = torch.tensor([torch.nan, torch.inf, -torch.inf, 0.0, -0.0, 1e-45, big, -big, 3.0], dtype=dtype)
        assert torch.equal(_finite(t), torch.isfinite(t))


class _Walled(_Quartic):
    """:class:`_Quartic` whose states ``walled`` [B] (bool) have a non-finite value (NaN, inf or -inf by row) at every
    point but their start: each line search from there fails, restarts once from a fresh model, fails again."""

    def __init__(self, c: Tensor, start: Tensor, walled: Tensor) -> None:
        super().__init__(c)
        self.start, self.walled = start, walled

    def value_and_grad(self, z: Tensor, index: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        value, grad, energy = super().value_and_grad(z, index)
        wall = torch.tensor([torch.nan, torch.inf, -torch.inf], dtype=z.dtype)[index % 3]
        off = self.walled[index] & (z != self.start[index]).any(-1)  # (the dense loop's idle rows sit at z)
        return torch.where(off, wall, value), grad, energy


def test_row_loop_equals_dense_loop_where_line_searches_fail_and_restart() -> None:
    """The restart path (MAX_BACKTRACKS rejected trials, a fresh model, MAX_BACKTRACKS more, then stalled), which
    the test above does not reach, for a mix of walled states (NaN, +inf and -inf values) and free ones."""
    from redsim.runtime import solver

    restarts: list[Tensor] = []
    restart = solver._restart

    def counted(it: object, rows: Tensor) -> None:
        restarts.append(torch.as_tensor(rows).clone())
        restart(it, rows)

    g = torch.Generator().manual_seed(1)
    batch, d = 7, 3
    c = 1.0 + torch.rand(batch, d, generator=g, dtype=torch.float64)
    z0 = torch.randn(batch, d, generator=g, dtype=torch.float64)
    walled = torch.tensor([True, False, True, True, False, False, True])
    results = []
    for dense in (False, True):
        objective = _Walled(c, z0.clone(), walled)
        solver._restart = counted
        try:
            results.append(
                minimize(
                    objective,
                    z0,
                    torch.ones(batch, dtype=torch.float64),
                    torch.zeros(batch, dtype=torch.float64),
                    tol=1e-10,
                    max_iter=50,
                    hessian="bfgs",
                    warm=torch.eye(d, dtype=torch.float64).expand(batch, d, d),  # not built here: a failure restarts
                    warm_refresh=False,
                    dense=dense,
                )
            )
        finally:
            solver._restart = restart
    rows, dense = results
    assert len(restarts) == 1  # the row loop's one call, every walled state in it (the dense loop restarts by masks)
    assert torch.equal(torch.zeros(batch, dtype=torch.bool).index_fill_(0, restarts[0], True), walled)
    assert torch.equal(rows.stalled, walled) and torch.equal(rows.converged, ~walled)
    assert int(rows.iterations[walled].max()) == 0
    for name in ("z", "value", "energy", "iterations", "converged", "stalled", "finite"):
        torch.testing.assert_close(getattr(rows, name), getattr(dense, name), rtol=0.0, atol=1e-12, msg=name)
    torch.testing.assert_close(rows.model, dense.model, rtol=1e-9, atol=1e-9, equal_nan=True)


def test_host_direction_equals_the_torch_direction() -> None:
    """The row loop's numpy direction (numpy's Cholesky as the test, one LU solve) against torch's Cholesky, on a batch
    of positive definite models and on one with an indefinite and a NaN model in it (torch's per-matrix path then):
    the same steps to round-off, -g where the model is not positive definite."""
    from redsim.runtime.solver import _direction

    g = torch.Generator().manual_seed(2)
    for dtype, tol in ((torch.float32, 1e-4), (torch.float64, 1e-12)):
        a = torch.randn(6, 4, 4, generator=g, dtype=dtype)
        model = a @ a.mT + 0.1 * torch.eye(4, dtype=dtype)
        grad = torch.randn(6, 4, generator=g, dtype=dtype)
        torch.testing.assert_close(torch.from_numpy(_direction(model.numpy(), grad.numpy())), _direction(model, grad))
        mixed = model.clone()
        mixed[1] = -mixed[1]  # indefinite
        mixed[4, 0, 0] = torch.nan
        got = torch.from_numpy(_direction(mixed.numpy(), grad.numpy()))
        want = _direction(mixed, grad)
        torch.testing.assert_close(got, want, rtol=tol, atol=tol)
        assert torch.equal(got[1], -grad[1]) and torch.equal(got[4], -grad[4])
        assert torch.allclose(got[0], -torch.linalg.solve(model[0], grad[0]), rtol=tol, atol=tol)
