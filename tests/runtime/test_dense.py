"""The solver's dense masked iteration (``LatentStepper(dense=True)``) against the row-selected one, and
that it selects no rows by data: no ``nonzero``, no boolean indexing, no host read inside the loop
except the early exit's.

The two loops are compared step for step from the same inputs (the row-selected rollout's states,
warm models carried), in float64 where they agree to round-off, and in float32 to the solve tolerance.
"""

from __future__ import annotations

import contextlib
from collections import Counter
from collections.abc import Iterator

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

import redsim.runtime.solver as solver
import redsim.runtime.stepper as stepper_module
from redsim import pretrained, scenes
from redsim.runtime import LatentStepper

DT = 0.02


def _loads(scene, batch: int, seed: int, size: float, dtype: torch.dtype) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return size * torch.randn(batch, len(scene.handles), scene.dim, generator=g, dtype=torch.float64).to(dtype)


def _step_pairs(name: str, dtype: torch.dtype, steps: int, batch: int = 4, size: float = 10.0, **dense_options):
    """[(row-selected z_next, stats, dense z_next, stats, z)] along the row-selected rollout (warm carried),
    and the two steppers' objective calls."""
    scene = scenes.build(name)
    f = pretrained.load(name).to(dtype)
    rows = LatentStepper(scene, f, DT, dtype=dtype, dense=False)
    dense = LatentStepper(scene, f, DT, dtype=dtype, dense=True, **dense_options)
    z = rows.rest_latent().expand(batch, -1).clone()
    z_prev, model, out = z.clone(), None, []
    for i in range(steps):
        loads = _loads(scene, batch, i, size, dtype)
        want, want_stats = rows.step(z, z_prev, loads, warm=model)
        got, got_stats = dense.step(z, z_prev, loads, warm=model)
        out.append((want, want_stats, got, got_stats, z))
        z_prev, z, model = z, want, want_stats.model
    return out, (rows.evaluations.calls, dense.evaluations.calls)


FLAGS = ("converged", "diverged", "out_of_range", "energy_gain")


@pytest.mark.parametrize("name", ["mini_chain", "chain", "bistable_bar"])
def test_dense_equals_row_selected_step_for_step(name: str) -> None:
    """Float64: the same iterations, calls, flags and minimizers to round-off; float32: the same flags and
    minimizers to the solve tolerance (two float32 solves stopped by tol 1e-6 at different round-off)."""
    for dtype, atol, same_iterations in ((torch.float64, 1e-8, True), (torch.float32, 2e-2, False)):
        pairs, (calls, dense_calls) = _step_pairs(name, dtype, steps=3)
        assert dense_calls == calls or not same_iterations
        for want, want_stats, got, got_stats, z in pairs:
            assert bool(want_stats.converged.all())
            for flag in FLAGS:
                assert torch.equal(getattr(want_stats, flag), getattr(got_stats, flag)), (dtype, flag)
            if same_iterations:
                assert torch.equal(want_stats.iterations, got_stats.iterations)
            motion = float((want - z).abs().max())
            assert motion > 1e-4
            torch.testing.assert_close(got, want, rtol=0.0, atol=atol * motion)


@pytest.mark.parametrize(
    ("options", "size"), [({"sync_every": 3}, 10.0), ({"sync_every": None, "max_iter": 12}, 3.0)], ids=["3", "never"]
)
def test_fewer_early_exit_checks_do_not_change_a_state_s_iterates(options: dict, size: float) -> None:
    """sync_every 3: a state that needs a model between checks waits for the next one, so only the call its
    iterations happen in moves; never checking builds models every call and runs the loop's whole bound (loads of
    3 N take 2-5 iterations, well inside a bound of 12 that keeps the test short)."""
    base, _ = _step_pairs("mini_chain", torch.float64, steps=2, size=size)
    for (_, _, want, want_stats, _), (_, _, got, got_stats, _) in zip(
        base, _step_pairs("mini_chain", torch.float64, steps=2, size=size, **options)[0], strict=True
    ):
        torch.testing.assert_close(got, want, rtol=0.0, atol=1e-12)
        assert torch.equal(got_stats.iterations, want_stats.iterations)
        assert torch.equal(got_stats.converged, want_stats.converged)


SELECTING = frozenset(
    {"aten::nonzero", "aten::masked_select", "aten::_local_scalar_dense", "aten::is_nonzero", "aten::equal"}
)
"""Ops that read a tensor on the host or return a data-dependent shape."""
INDEXING = frozenset({"aten::index", "aten::index_put", "aten::index_put_", "aten::_index_put_impl_"})
"""Ops that select by data when an index is a boolean mask."""


class _Watch(TorchDispatchMode):
    """Counts the aten ops that select by data (SELECTING; INDEXING with a mask), except inside :meth:`away`."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: Counter[str] = Counter()
        self.paused = 0

    @contextlib.contextmanager
    def away(self) -> Iterator[None]:
        self.paused += 1
        try:
            yield
        finally:
            self.paused -= 1

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func._schema.name
        if not self.paused:
            if name in SELECTING:
                self.seen[name] += 1
            elif name in INDEXING:
                masks = [t for t in args[1] if isinstance(t, torch.Tensor) and t.dtype == torch.bool]
                self.seen[name + " (bool mask)"] += len(masks) > 0
        return func(*args, **(kwargs or {}))


class _Outside:
    """An objective whose calls run under ``away()`` (the energy's own syncs are not the solver loop's)."""

    def __init__(self, inner, away) -> None:
        self.inner, self.away, self.trials = inner, away, 0

    def __getattr__(self, name: str):
        method = getattr(self.inner, name)

        def call(*args, **kwargs):
            self.trials += name == "value_and_grad"
            with self.away():
                return method(*args, **kwargs)

        return call


def _guarded_steps(monkeypatch, stepper: LatentStepper, away, guard, steps: int) -> list[tuple[int, int]]:
    """Run ``steps`` loaded steps of 4 mini-chain states with every ``minimize`` under ``guard()`` and its
    objective calls, early-exit polls and model builds (the eigensolver syncs on CUDA) under ``away()``;
    (trial calls, polls) per solve."""
    counts, polls = [], [0]
    minimize, poll, model = solver.minimize, solver._poll, solver._model

    def watched_minimize(objective, *args, **kwargs):
        wrapped = _Outside(objective, away)
        polls[0] = 0
        with guard():
            result = minimize(wrapped, *args, **kwargs)
        counts.append((wrapped.trials, polls[0]))
        return result

    def watched_poll(*args):
        polls[0] += 1
        with away():
            return poll(*args)

    def watched_model(*args, **kwargs):
        with away():
            return model(*args, **kwargs)

    monkeypatch.setattr(stepper_module, "minimize", watched_minimize)
    monkeypatch.setattr(solver, "_poll", watched_poll)
    monkeypatch.setattr(solver, "_model", watched_model)
    scene = stepper.source_scene
    z = stepper.rest_latent().expand(4, -1).clone().to(stepper.device)
    z_prev, model_in = z.clone(), None
    for i in range(steps):
        loads = _loads(scene, 4, i, 10.0, stepper.dtype).to(stepper.device)
        z_next, stats = stepper.step(z, z_prev, loads, warm=model_in)
        z_prev, z, model_in = z, z_next, stats.model
    return counts


@pytest.mark.parametrize("hessian", ["lagged_fd", "bfgs", "exact"])
def test_dense_loop_selects_no_rows(monkeypatch, hessian: str) -> None:
    """Under a dispatch mode that sees every aten op: the dense loop makes no data-dependent selection
    (no ``nonzero``, boolean index or ``item``) outside the objective and its one poll per call
    (sync_every 1; with 3, one poll per 3 calls). The watch sees such selections (the row-selected loop makes its
    own on the host, in numpy, where no dispatch mode sees them)."""
    scene, f = scenes.build("mini_chain"), pretrained.load("mini_chain")
    with _Watch() as watch:
        mask = torch.arange(4) > 1
        torch.arange(4)[mask]
        torch.nonzero(mask)
    assert watch.seen["aten::nonzero"] > 0 and watch.seen["aten::index (bool mask)"] > 0
    for sync_every in (1, 3):
        watch = _Watch()
        stepper = LatentStepper(scene, f, DT, hessian=hessian, dense=True, sync_every=sync_every)
        counts = _guarded_steps(monkeypatch, stepper, watch.away, lambda w=watch: w, steps=3)
        assert not +watch.seen, dict(watch.seen)
        for trials, polls in counts:  # the loop ends at a poll that sees no active state
            assert trials % sync_every == 0 and polls == trials // sync_every + 1


@pytest.mark.slow
def test_compiled_dense_equals_eager_dense() -> None:
    scene, f = scenes.build("mini_chain"), pretrained.load("mini_chain")
    eager = LatentStepper(scene, f, DT, dense=True)
    compiled = LatentStepper(scene, f, DT, dense=True, compile=True)
    z = eager.rest_latent().expand(3, -1).clone()
    loads = _loads(scene, 3, 5, 10.0, torch.float32)
    want, want_stats = eager.step(z, z, loads)
    got, got_stats = compiled.step(z, z, loads)
    assert bool(want_stats.converged.all()) and bool(got_stats.converged.all())
    for flag in FLAGS:
        assert torch.equal(getattr(want_stats, flag), getattr(got_stats, flag))
    q_want, q_got = eager.positions(want), eager.positions(got)
    motion = float((q_want - eager.positions(z)).abs().max())
    torch.testing.assert_close(q_got, q_want, rtol=0.0, atol=1e-2 * motion)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("hessian", ["lagged_fd", "bfgs"])
def test_dense_loop_does_not_sync_on_cuda(monkeypatch, hessian: str) -> None:
    """``torch.cuda.set_sync_debug_mode("error")`` around the dense loop: any host synchronisation outside
    the objective, the early-exit poll and the model builds (``eigh`` syncs on CUDA) raises."""

    @contextlib.contextmanager
    def mode(level: str) -> Iterator[None]:
        before = torch.cuda.get_sync_debug_mode()
        torch.cuda.set_sync_debug_mode(level)
        try:
            yield
        finally:
            torch.cuda.set_sync_debug_mode(before)

    scene, f = scenes.build("mini_chain"), pretrained.load("mini_chain")
    stepper = LatentStepper(scene, f, DT, hessian=hessian, device="cuda", dense=True)
    assert stepper.dense  # the default on CUDA
    counts = _guarded_steps(monkeypatch, stepper, lambda: mode("default"), lambda: mode("error"), steps=3)
    assert all(polls == trials + 1 for trials, polls in counts)
