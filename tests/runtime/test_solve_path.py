"""Options that change a step's path to its minimum, not the minimum: the solver's trust radius
(``max_step``), kept warm models (``warm_refresh=False``) and the lower of two starts (``start="lower"``).

Checked against the reference
ImplicitEuler(LatentSpace) in float64 (both converged to 1e-12), with the warm model carried as the envs
carry it, and against the dense loop. On a quadratic toy objective (a solver unit test) the trials are
measured directly: none is longer than ``max_step``, a kept warm model builds no Hessian, and a line search
that fails restarts once from a fresh model before the state stalls.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import redsim.runtime.solver as solver
import redsim.runtime.stepper as stepper_module
from redsim import pretrained, scenes
from redsim.integrators import FullState, ImplicitEuler, LatentSpace
from redsim.runtime import LatentStepper
from redsim.runtime.solver import minimize

DT = 0.02
OPTIONS = {"max_step": 0.5, "warm_refresh": False, "start": "lower"}


def _loads(scene, seed: int, size: float) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return size * torch.randn(1, len(scene.handles), scene.dim, generator=g, dtype=torch.float64)


@pytest.mark.parametrize(("name", "steps", "load"), [("bistable_bar", 4, 20.0), ("chain", 3, 20.0)])
def test_same_minimum_as_the_reference_with_the_warm_model_carried(name: str, steps: int, load: float) -> None:
    scene = scenes.build(name)
    f = pretrained.load(name).double()
    stepper = LatentStepper(scene, f, DT, dtype=torch.float64, tol=1e-12, max_iter=60, **OPTIONS)
    reference = ImplicitEuler(LatentSpace(scene, f), DT, tol=1e-12, max_iter=100)
    z = stepper.rest_latent()
    z_prev, model = z.clone(), None
    for i in range(steps):
        loads = _loads(scene, i, load)
        ref_state, info = reference.step(FullState(z[0], z_prev[0], 0.0), loads[0])
        assert info.converged, info.message
        got, stats = stepper.step(z, z_prev, loads, warm=model)
        want = ref_state.q.unsqueeze(0)
        assert bool(stats.converged[0]), stats
        motion = float((want - z).abs().max())
        assert motion > 1e-4
        torch.testing.assert_close(got, want, rtol=0.0, atol=1e-6 * motion)
        z_prev, z, model = z, want, stats.model


def test_dense_loop_takes_the_same_limited_steps() -> None:
    """Float64: the dense masked loop gives every state the row-selected loop's iterations and minimizer."""
    scene = scenes.build("bistable_bar")
    f = pretrained.load("bistable_bar").double()
    rows = LatentStepper(scene, f, DT, dtype=torch.float64, dense=False, **OPTIONS)
    dense = LatentStepper(scene, f, DT, dtype=torch.float64, dense=True, **OPTIONS)
    g = torch.Generator().manual_seed(4)
    z = rows.rest_latent().expand(4, -1).clone()
    z_prev, model = z.clone(), None
    for _ in range(3):
        loads = 20.0 * torch.randn(4, len(scene.handles), scene.dim, generator=g, dtype=torch.float64)
        want, want_stats = rows.step(z, z_prev, loads, warm=model)
        got, got_stats = dense.step(z, z_prev, loads, warm=model)
        assert bool(want_stats.converged.all())
        assert torch.equal(want_stats.iterations, got_stats.iterations)
        motion = float((want - z).abs().max())
        assert motion > 1e-4
        torch.testing.assert_close(got, want, rtol=0.0, atol=1e-8 * motion)
        z_prev, z, model = z, want, want_stats.model


class _Quartic:
    """Phi(z) = 1/2 z^T A z - b^T z + c/4 |z|^4 per state (a solver unit test), counting what it evaluates."""

    def __init__(self, a: torch.Tensor, b: torch.Tensor, c: float) -> None:
        self.a, self.b, self.c = a, b, c
        self.trials: list[torch.Tensor] = []
        self.builds = 0

    def value_and_grad(self, z, index):
        self.trials.append(z.clone())
        r2 = (z * z).sum(-1)
        value = 0.5 * (z * (z @ self.a)).sum(-1) - (z * self.b[index]).sum(-1) + 0.25 * self.c * r2 * r2
        grad = z @ self.a - self.b[index] + self.c * r2[:, None] * z
        return value, grad, value

    def difference_hessian(self, z, index, grad):
        self.builds += 1
        r2 = (z * z).sum(-1)
        eye = torch.eye(z.shape[1], dtype=z.dtype)
        return self.a + self.c * (r2[:, None, None] * eye + 2.0 * z[:, :, None] * z[:, None, :])


def _solve(objective: _Quartic, z0: torch.Tensor, warm: torch.Tensor | None, **options):
    batch = z0.shape[0]
    ones = torch.ones(batch, dtype=torch.float64)
    return minimize(
        objective, z0, ones, 1e-14 * ones, tol=1e-10, max_iter=200, hessian="lagged_fd", warm=warm, **options
    )


def test_no_step_is_longer_than_max_step_and_the_minimum_is_the_same(monkeypatch) -> None:
    """Every trial is z + alpha * step with alpha <= 1, so the limit holds when every step the solver
    makes (an iteration's first, or a turned one after a rejection) is at most ``max_step`` long."""
    lengths: list[float] = []
    for name in ("_descent", "_relearn"):
        original = getattr(solver, name)

        def recorded(*args, _original=original, **kwargs):
            out = _original(*args, **kwargs)
            step = out[0] if len(out) == 2 else out[1]
            lengths.extend(torch.linalg.vector_norm(torch.as_tensor(step), dim=-1).tolist())
            return out

        monkeypatch.setattr(solver, name, recorded)
    g = torch.Generator().manual_seed(0)
    a = torch.diag(torch.tensor([1e-3, 1.0, 10.0], dtype=torch.float64))  # one soft direction
    b = torch.randn(5, 3, generator=g, dtype=torch.float64)
    z0 = torch.zeros(5, 3, dtype=torch.float64)
    want = _solve(_Quartic(a, b, 0.1), z0, None)
    assert max(lengths) > 1.0  # without the limit the Newton steps run far along the soft direction
    lengths.clear()
    got = _solve(_Quartic(a, b, 0.1), z0, None, max_step=0.25)
    assert 0.25 * (1 - 1e-9) < max(lengths) <= 0.25 * (1 + 1e-12)
    assert bool(want.converged.all()) and bool(got.converged.all())
    torch.testing.assert_close(got.z, want.z, rtol=0.0, atol=1e-8)


def test_a_kept_warm_model_builds_no_hessian() -> None:
    """A poor warm model (10x too soft) backtracks: refreshed, it is rebuilt from differences; kept, the
    BFGS updates repair it and no Hessian is built. Both reach the same minimum."""
    a = torch.diag(torch.tensor([2.0, 1.0, 10.0], dtype=torch.float64))
    b = torch.tensor([[1.0, -2.0, 0.5]], dtype=torch.float64)
    warm = 0.1 * a.unsqueeze(0)
    z0 = torch.zeros(1, 3, dtype=torch.float64)
    results = {}
    for refresh in (True, False):
        objective = _Quartic(a, b, 0.5)
        results[refresh] = (_solve(objective, z0, warm, warm_refresh=refresh), objective.builds)
    (fresh, fresh_builds), (kept, kept_builds) = results[True], results[False]
    assert fresh_builds >= 1 and kept_builds == 0
    assert bool(fresh.converged.all()) and bool(kept.converged.all())
    torch.testing.assert_close(kept.z, fresh.z, rtol=0.0, atol=1e-8)


class _FlatAway(_Quartic):
    """The quartic at its first point, NaN at every other: no line search from there can succeed."""

    def value_and_grad(self, z, index):
        value, grad, energy = super().value_and_grad(z, index)
        if len(self.trials) > 1:
            value = torch.full_like(value, torch.nan)
        return value, grad, energy


@pytest.mark.parametrize("dense", [False, True])
def test_a_failed_line_search_restarts_once_from_a_fresh_model_then_stalls(monkeypatch, dense: bool) -> None:
    """With one trial per line search, a poor warm model's first rejection used to stall the state far from its
    minimum; it now restarts from a difference Hessian at the same iterate and converges. Where the restarted
    search fails too, the state stalls at its last accepted iterate after exactly one rebuild."""
    monkeypatch.setattr(solver, "MAX_BACKTRACKS", 1)
    a = torch.diag(torch.tensor([2.0, 1.0, 10.0], dtype=torch.float64))
    b = torch.tensor([[1.0, -2.0, 0.5]], dtype=torch.float64)
    warm = 0.1 * a.unsqueeze(0)  # 10x too soft: its first step overshoots and is rejected
    z0 = torch.zeros(1, 3, dtype=torch.float64)
    objective = _Quartic(a, b, 0.5)
    result = _solve(objective, z0, warm, warm_refresh=False, dense=dense)
    assert objective.builds >= 1 and bool(result.converged.all()) and not bool(result.stalled.any())
    expected = _solve(_Quartic(a, b, 0.5), z0, None)  # the same minimum from scratch
    torch.testing.assert_close(result.z, expected.z, rtol=0.0, atol=1e-8)
    hopeless = _FlatAway(a, b, 0.5)
    result = _solve(hopeless, z0, warm, warm_refresh=False, dense=dense)
    assert hopeless.builds == 1 and bool(result.stalled.all()) and not bool(result.converged.any())
    torch.testing.assert_close(result.z, z0, rtol=0.0, atol=0.0)
    cold = _FlatAway(a, b, 0.5)  # a model built at this iterate: a restart would replay the same trials
    result = _solve(cold, z0, None, warm_refresh=False, dense=dense)
    assert cold.builds == 1 and bool(result.stalled.all())


@pytest.mark.parametrize("dense", [False, True])
def test_every_state_ends_converged_or_stalled_when_each_line_search_fails_twice(dense: bool) -> None:
    """With the real MAX_BACKTRACKS, an iteration whose search fails, restarts and fails again still fits the
    loop's bound of calls: no state comes back neither converged nor stalled."""
    a = torch.diag(torch.tensor([2.0, 1.0, 10.0], dtype=torch.float64))
    b = torch.tensor([[1.0, -2.0, 0.5], [0.5, 1.0, -1.0]], dtype=torch.float64)
    warm = 0.1 * a.expand(2, -1, -1)
    z0 = torch.zeros(2, 3, dtype=torch.float64)
    ones = torch.ones(2, dtype=torch.float64)
    objective = _FlatAway(a, b, 0.5)
    result = minimize(
        objective,
        z0,
        ones,
        1e-14 * ones,
        tol=1e-10,
        max_iter=1,
        hessian="lagged_fd",
        warm=warm,
        warm_refresh=False,
        dense=dense,
    )
    assert bool(result.stalled.all()) and objective.builds == 1


@pytest.mark.parametrize(
    ("settings", "match"),
    [
        ({"tol": math.nan}, "tol must be finite and > 0"),
        ({"tol": -1.0}, "tol must be finite and > 0"),
        ({"max_iter": 0}, "max_iter must be an integer >= 1"),
        ({"max_iter": 2.5}, "max_iter must be an integer >= 1"),
    ],
)
def test_minimize_refuses_a_bad_tol_or_max_iter(settings: dict, match: str) -> None:
    """A NaN tol returned every state at once, neither converged nor stalled; max_iter 2.5 was a TypeError."""
    a = torch.diag(torch.tensor([2.0, 1.0, 10.0], dtype=torch.float64))
    objective = _Quartic(a, torch.tensor([[1.0, -2.0, 0.5]], dtype=torch.float64), 0.5)
    ones = torch.ones(1, dtype=torch.float64)
    with pytest.raises(ValueError, match=match):
        minimize(
            objective, torch.zeros(1, 3, dtype=torch.float64), ones, ones, **{"tol": 1e-10, "max_iter": 5, **settings}
        )


@pytest.mark.parametrize("max_step", [0.0, -1.0, math.nan, math.inf, True, "2"])
def test_bad_max_step_raises(max_step) -> None:
    with pytest.raises(ValueError, match="max_step"):
        LatentStepper(scenes.build("mini_chain"), pretrained.load("mini_chain"), DT, max_step=max_step)


def test_lower_start_starts_where_phi_is_lower(monkeypatch) -> None:
    """With ``start="lower"`` each state's solve starts at whichever of 2 z_t - z_{t-1} and z_t has the lower
    Phi (here z_t for the copy whose previous state is far off, the extrapolation for the others); the
    minimizers are the extrapolated start's to the tolerance (float64, 1e-12)."""
    scene = scenes.build("bistable_bar")
    f = pretrained.load("bistable_bar").double()
    starts = []
    original = stepper_module.minimize

    def recorded(objective, z0, *args, **kwargs):
        starts.append(z0.clone())
        return original(objective, z0, *args, **kwargs)

    monkeypatch.setattr(stepper_module, "minimize", recorded)
    steppers = {
        start: LatentStepper(scene, f, DT, dtype=torch.float64, tol=1e-12, max_iter=60, start=start)
        for start in ("extrapolated", "lower")
    }
    z = steppers["lower"].rest_latent().expand(3, -1).clone()
    z_prev = z.clone()
    z_prev[0] += 1.0  # copy 0 extrapolates 1.0 per latent past z_t
    z_prev[1] -= 1e-3  # copy 1 moves slowly: its extrapolated start is the better one
    loads = _loads(scene, 1, 20.0).expand(3, -1, -1)
    results = {}
    for start, stepper in steppers.items():
        starts.clear()
        results[start] = stepper.step(z, z_prev, loads)
        phi_z = stepper.objective(z, z, z_prev, loads)
        phi_extrapolated = stepper.objective(2.0 * z - z_prev, z, z_prev, loads)
        lower = phi_z < phi_extrapolated
        if start == "lower":
            assert bool(lower[0]) and not bool(lower[1])
            want = torch.where(lower[:, None], z, 2.0 * z - z_prev)
        else:
            want = 2.0 * z - z_prev
        assert torch.equal(starts[0], want)
    (got, got_stats), (ref, ref_stats) = results["lower"], results["extrapolated"]
    assert bool(got_stats.converged.all()) and bool(ref_stats.converged.all())
    motion = float((ref - z).abs().max())
    torch.testing.assert_close(got, ref, rtol=0.0, atol=1e-6 * motion)


def test_unknown_start_raises() -> None:
    with pytest.raises(ValueError, match="start"):
        LatentStepper(scenes.build("mini_chain"), pretrained.load("mini_chain"), DT, start="zero")


@pytest.mark.parametrize(
    ("option", "value", "match"),
    [
        ("warm_refresh", "false", "warm_refresh must be True or False"),
        ("warm_refresh", 0, "warm_refresh must be True or False"),
        ("warm_refresh", None, "warm_refresh must be True or False"),
        ("warm_start", "False", "warm_start must be True or False"),
        ("warm_start", None, "warm_start must be True or False"),
        ("dense", "no", "dense must be True, False or None"),
        ("dense", 1, "dense must be True, False or None"),
    ],
)
def test_switches_must_be_bools(option: str, value, match: str) -> None:
    """A JSON string such as "false" would otherwise read as True (warm_start and dense did: a review's finding)."""
    with pytest.raises(ValueError, match=match):
        LatentStepper(scenes.build("mini_chain"), pretrained.load("mini_chain"), DT, **{option: value})


def test_switches_take_numpy_bools() -> None:
    """NumPy's bools pass as the scene builders take them (a review: the stricter check refused np.True_)."""
    import numpy as np

    stepper = LatentStepper(
        scenes.build("mini_chain"), pretrained.load("mini_chain"), DT, warm_start=np.False_, dense=np.True_
    )
    assert stepper.warm_start is False and stepper.dense is True


def test_a_scene_name_for_a_scene_is_a_type_error() -> None:
    """Where a Scene is expected, its name (or None) is a TypeError saying how to build one, not an AttributeError."""
    scene = scenes.build("mini_chain")
    for wrong in ("mini_chain", None):
        with pytest.raises(TypeError, match=r"scene must be a redsim Scene \(redsim.scenes.build\(name\)\)"):
            LatentStepper(wrong, pretrained.load("mini_chain", scene), DT)
    with pytest.raises(TypeError, match="scene must be a redsim Scene"):
        pretrained.load("mini_chain", "mini_chain")


def test_row_blocks_give_the_same_values_gradients_and_steps() -> None:
    """``row_block`` splits a call's rows into blocks: the same Phi, gradient and energy (float64, to round-off), the
    call counted once, and steps that end at the same minimum (the iterates differ by round-off only)."""
    scene = scenes.build("bistable_bar")
    f = pretrained.load("bistable_bar").double()
    g = torch.Generator()
    z = 0.3 * torch.randn(7, 8, generator=g.manual_seed(1), dtype=torch.float64)
    loads = 20.0 * torch.randn(7, len(scene.handles), scene.dim, generator=g.manual_seed(2), dtype=torch.float64)
    calls, steps = {}, {}
    for block in (None, 3):
        stepper = LatentStepper(scene, f, DT, dtype=torch.float64, tol=1e-12, max_iter=60, row_block=block)
        qbar = stepper.positions(z)
        objective = stepper_module._StepObjective(stepper, qbar, loads.reshape(7, -1), None, z)
        calls[block] = objective.value_and_grad(z, torch.arange(7))
        assert (stepper.evaluations.calls, stepper.evaluations.rows) == (1, 7)
        steps[block] = stepper.step(z, z, loads)[0]
    for blocked, whole in zip(calls[3], calls[None], strict=True):
        torch.testing.assert_close(blocked, whole, rtol=1e-13, atol=1e-11)
    torch.testing.assert_close(steps[3], steps[None], rtol=0, atol=1e-8)


@pytest.mark.parametrize("row_block", [0, -4, 2.5, 4.0, math.inf, True, np.bool_(True), "8", [3]])
def test_bad_row_block_raises(row_block) -> None:
    with pytest.raises(ValueError, match="row_block"):
        LatentStepper(scenes.build("mini_chain"), pretrained.load("mini_chain"), DT, row_block=row_block)


def test_row_block_takes_numpy_integers() -> None:
    stepper = LatentStepper(scenes.build("mini_chain"), pretrained.load("mini_chain"), DT, row_block=np.int64(4))
    assert stepper.row_block == 4 and type(stepper.row_block) is int


def test_a_turned_trial_is_no_longer_than_the_backtracked_one() -> None:
    """After a rejected trial the BFGS-updated model's step is capped at the backtracked length (a step as long as
    the rejected one could rise again, and again, until the line search gave up)."""
    g = torch.Generator().manual_seed(0)
    model = torch.eye(3).expand(4, 3, 3).clone()
    grad, step = torch.randn(4, 3, generator=g), torch.randn(4, 3, generator=g)
    change = 0.01 * torch.randn(4, 3, generator=g)  # little curvature measured: the turned step stays long
    bound = torch.tensor([1e-3, 0.1, 1.0, 1e3])
    _, fresh, slope = solver._relearn(model, step, change, grad, bound)
    assert (torch.linalg.vector_norm(fresh, dim=-1) <= bound * (1 + 1e-6)).all()
    assert torch.allclose(slope, (grad * fresh).sum(-1))
