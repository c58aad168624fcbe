"""The batched latent stepper against the reference ImplicitEuler(LatentSpace), and its contract.

Reference comparisons run both in float64 on a float64 copy of the shipped map, each converged
tightly (tol 1e-12 relative force balance), so the two solves of one objective agree far below
the motion of a step; both start every step from the same state.
"""

from __future__ import annotations

import copy
import math
import warnings

import pytest
import torch

from redsim import pretrained, scenes
from redsim.cubature import cubature_energy
from redsim.integrators import FullState, ImplicitEuler, LatentSpace
from redsim.runtime import Evaluations, LatentStepper, MapEnergy, StepStats
from redsim.runtime.solver import newton_step
from redsim.runtime.stepper import RESOLUTION_WARNING, _StepObjective, check_compiler

DT = 0.02


def _loads(scene, batch: int, seed: int, size: float, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return size * torch.randn(batch, len(scene.handles), scene.dim, generator=g, dtype=dtype)


@pytest.fixture(scope="module")
def mini_chain():
    scene = scenes.build("mini_chain")
    f = pretrained.load("mini_chain")
    return scene, f


CASES = [("mini_chain", 3, 5.0), ("bistable_bar", 3, 20.0), ("chain", 2, 20.0)]


def _reference_steps(name: str, steps: int, load: float, hessian: str):
    """(stepper, [(z, z_prev, loads, reference z_next, stepper z_next, stats)]) along the reference's path."""
    scene = scenes.build(name)
    f = pretrained.load(name).double()
    stepper = LatentStepper(scene, f, DT, dtype=torch.float64, tol=1e-12, max_iter=60, hessian=hessian)
    reference = ImplicitEuler(LatentSpace(scene, f), DT, tol=1e-12, max_iter=100)
    z = stepper.rest_latent()
    z_prev = z.clone()
    loads = _loads(scene, 1, 0, load)
    out = []
    for _ in range(steps):
        ref_state, info = reference.step(FullState(z[0], z_prev[0], 0.0), loads[0])
        assert info.converged, info.message
        z_next, stats = stepper.step(z, z_prev, loads)
        out.append((z, z_prev, loads, ref_state.q.unsqueeze(0), z_next, stats))
        z_prev, z = z, ref_state.q.unsqueeze(0)
    return stepper, out


@pytest.mark.parametrize(("name", "steps", "load"), CASES)
@pytest.mark.parametrize("hessian", ["exact", "gauss_newton", "bfgs", "lagged", "lagged_fd"])
def test_matches_reference_step_for_step(name: str, steps: int, load: float, hessian: str) -> None:
    """Every step from the reference's own state: "exact" is the reference's Newton and must land on its
    minimizer; the other models must land on it too, or (the mini chain's folded map has several
    minima within one step) on a minimizer with a lower objective."""
    if hessian == "gauss_newton" and name == "mini_chain":
        pytest.skip("Gauss-Newton drops the map's curvature and converges linearly here: no 1e-12 in 60 iterations")
    if hessian in ("gauss_newton", "bfgs") and name == "bistable_bar":
        pytest.skip(  # measured on the mirror-fitted map: residual 8e-9 (Gauss-Newton), 9e-5 (BFGS) after 60
            "the bistable map's rest latent is z = 0, the straight bar (the mirror fixes it), a saddle of its latent "
            "energy: from there the positive-definite models do not reach 1e-12 in 60 iterations"
        )
    stepper, rows = _reference_steps(name, steps, load, hessian)
    for z, z_prev, loads, want, got, stats in rows:
        assert bool(stats.converged[0]), stats
        motion = float((want - z).abs().max())
        assert motion > 1e-4
        if hessian == "exact" or name != "mini_chain":
            torch.testing.assert_close(got, want, rtol=0.0, atol=1e-6 * motion)
        else:
            phi_got, phi_want = (stepper.objective(u, z, z_prev, loads) for u in (got, want))
            same = bool(torch.allclose(got, want, rtol=0.0, atol=1e-6 * motion))
            assert same or float(phi_got) < float(phi_want), (got, want, phi_got, phi_want)


@pytest.mark.parametrize("dense", [False, True])
def test_same_inputs_give_bitwise_equal_outputs(mini_chain, dense: bool) -> None:
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT, dense=dense)
    g = torch.Generator().manual_seed(1)
    z = 0.5 * torch.randn(5, stepper.latent_dim, generator=g)
    z_prev = z + 0.01 * torch.randn(5, stepper.latent_dim, generator=g)
    loads = _loads(scene, 5, 2, 20.0, torch.float32)
    inputs = [u.clone() for u in (z, z_prev, loads)]
    z_next, stats = stepper.step(z, z_prev, loads)
    assert all(torch.equal(u, v) for u, v in zip((z, z_prev, loads), inputs, strict=True))  # none modified (docstring)
    again, stats_again = LatentStepper(scene, f, DT, dense=dense).step(z.clone(), z_prev.clone(), loads.clone())
    assert torch.equal(z_next, again)
    assert all(torch.equal(a, b) for a, b in zip(stats, stats_again, strict=True))
    assert bool(stats.converged.all())


def test_inputs_that_require_grad_step_alike_and_leave_no_graph_in_the_results(mini_chain) -> None:
    """A step is not differentiable: loads that require grad (an agent's action tensor) made stats.carry's force term
    part of the caller's autograd graph (requires_grad, a grad_fn holding the loads), kept alive by every carry handed
    on. Every result is detached, the same numbers, and autograd's mode is as the caller left it."""
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT)
    g = torch.Generator().manual_seed(2)
    z = stepper.rest_latent() + 0.1 * torch.randn(3, stepper.latent_dim, generator=g)
    z_prev = z + 0.01 * torch.randn(3, stepper.latent_dim, generator=g)
    loads = _loads(scene, 3, 3, 5.0, torch.float32)
    plain, plain_stats = stepper.step(z, z_prev, loads)
    tracked = [u.clone().requires_grad_() for u in (z, z_prev, loads)]
    z_next, stats = stepper.step(*tracked, warm=plain_stats.model.requires_grad_(), carry=plain_stats.carry)
    assert torch.is_grad_enabled()
    again, _ = stepper.step(*tracked)
    assert torch.equal(again, plain)
    for name, value in [("z_next", z_next), *stats._asdict().items()]:
        assert not value.requires_grad and value.grad_fn is None, name
    assert not stepper.objective(*tracked[:1], *tracked).requires_grad
    assert not stepper.positions(tracked[0]).requires_grad


def test_batched_equals_single_calls(mini_chain) -> None:
    """Float64, tol 1e-12: one batch and five single calls reach the same minimizers."""
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT, dtype=torch.float64, tol=1e-12, max_iter=60)
    g = torch.Generator().manual_seed(1)
    z = 0.5 * torch.randn(5, stepper.latent_dim, generator=g, dtype=torch.float64)
    z_prev = z + 0.01 * torch.randn(5, stepper.latent_dim, generator=g, dtype=torch.float64)
    loads = _loads(scene, 5, 2, 20.0)
    z_next, stats = stepper.step(z, z_prev, loads)
    assert bool(stats.converged.all())
    for b in range(5):
        single, single_stats = stepper.step(z[b : b + 1], z_prev[b : b + 1], loads[b : b + 1])
        torch.testing.assert_close(single[0], z_next[b], rtol=0.0, atol=1e-9)
        assert bool(single_stats.converged[0])
        assert int(single_stats.iterations[0]) == int(stats.iterations[b])


def test_warm_start_is_the_same_solve_with_fewer_evaluations() -> None:
    """Carrying stats.model from step to step (as the envs do) lands on the same minimizers as building
    the Hessian every step, for a fraction of the energy evaluations (``stepper.evaluations`` counts them);
    a wrong-shape warm is refused."""
    scene = scenes.build("chain")
    stepper = LatentStepper(scene, pretrained.load("chain").double(), DT, dtype=torch.float64, tol=1e-10)
    rows = [0]
    energy = stepper.energy.energy

    def counted(z, cond):
        rows[0] += z.shape[0]
        return energy(z, cond)

    stepper.energy.energy = counted
    loads = _loads(scene, 2, 3, 20.0)
    runs = {}
    for warm in (False, True):
        rows[0] = 0
        stepper.evaluations = Evaluations()
        z = stepper.rest_latent().expand(2, -1).clone()
        z_prev, model, path = z.clone(), None, [z]
        for _ in range(8):
            z_next, stats = stepper.step(z, z_prev, loads, warm=model)
            assert bool(stats.converged.all())
            model = stats.model if warm else None
            z_prev, z = z, z_next
            path.append(z)
        runs[warm] = (torch.stack(path), rows[0])
        # the stepper's own count: every energy evaluation went through a counted value-and-gradient call
        assert stepper.evaluations.rows == rows[0] and 8 <= stepper.evaluations.calls < rows[0]
    (cold, cold_rows), (hot, hot_rows) = runs[False], runs[True]
    motion = float((cold - cold[0]).abs().max())
    assert motion > 1e-3  # it moved
    assert float((hot - cold).abs().max()) <= 1e-5 * motion  # tol 1e-10 of the force scale, over 8 steps
    assert hot_rows < 0.7 * cold_rows  # measured 150 vs 250 rows
    assert torch.isfinite(stats.model).all() and stats.model.shape == (2, 8, 8)
    with pytest.raises(ValueError, match="warm must have shape"):
        stepper.step(z, z_prev, loads, warm=torch.zeros(2, 3, 3))
    # warm_start=False ignores the model: the cold solve, bitwise
    cold_stepper = LatentStepper(
        scene, pretrained.load("chain").double(), DT, dtype=torch.float64, tol=1e-10, warm_start=False
    )
    a, _ = cold_stepper.step(z, z_prev, loads, warm=stats.model)
    b, _ = cold_stepper.step(z, z_prev, loads)
    assert torch.equal(a, b)


@pytest.mark.parametrize(("name", "cubature"), [("chain", False), ("conditional_bar", True)])
def test_a_carried_start_is_the_same_step_with_fewer_rows(name: str, cubature: bool) -> None:
    """Passing stats.carry on (as the envs do) takes Phi and dPhi/dz at z_t from the last step's E, dPhi/dz and force
    there (E and dE/dz as a fresh evaluation at z_next), the steps land on the same minimizers (float64, tol 1e-10),
    each step's first call evaluates B rows fewer, and rows keyed by another z (or cond) are evaluated; a wrong shape
    is refused."""
    scene = scenes.build(name)
    f = pretrained.load(name).double()
    stepper = LatentStepper(scene, f, DT, dtype=torch.float64, tol=1e-10, energy=cubature_energy if cubature else None)
    assert stepper.reduced == cubature
    B, d = 2, stepper.latent_dim
    cond = stepper._default_cond(B)
    loads = _loads(scene, B, 3, 20.0)
    runs = {}
    for carried in (False, True):
        stepper.evaluations = Evaluations()
        z = stepper.rest_latent().expand(B, -1).clone()
        z_prev, model, carry, path, energies = z.clone(), None, None, [z], []
        for _ in range(6):
            z_next, stats = stepper.step(z, z_prev, loads, warm=model, carry=carry)
            assert bool(stats.converged.all()) and not bool(stats.diverged.any())
            model, carry = stats.model, stats.carry if carried else None
            z_prev, z = z, z_next
            path.append(z)
            energies.append(stats.energy)
        runs[carried] = (torch.stack(path), torch.stack(energies), stepper.evaluations.rows)
    (cold, cold_e, cold_rows), (hot, hot_e, hot_rows) = runs[False], runs[True]
    motion = float((cold - cold[0]).abs().max())
    assert motion > 1e-3  # it moved
    assert float((hot - cold).abs().max()) <= 1e-5 * motion
    torch.testing.assert_close(hot_e, cold_e, rtol=1e-6, atol=1e-9)
    assert hot_rows < cold_rows  # B rows fewer in each carried step's first call (the paths differ in the rest)
    # the carry: (z_next, cond, E, dPhi/dz, the inertia and load force dPhi/dq - dE/dq) at z_next: E and
    # dPhi/dz - dq/dz^T force = dE/dz against autograd through the energy
    key = torch.cat([z, cond], -1) if cond is not None else z
    k = key.shape[1]
    assert stats.carry.shape == (B, stepper.carry_size) and torch.equal(stats.carry[:, :k], key)
    zr = z.clone().requires_grad_(True)
    energy, q = stepper._energy_coords(zr, cond)
    (grad,) = torch.autograd.grad(energy.sum(), zr, retain_graph=True)
    (inertia,) = torch.autograd.grad(q, zr, stats.carry[:, k + 1 + d :])
    torch.testing.assert_close(stats.carry[:, k], energy.detach(), rtol=1e-12, atol=0.0)
    carried_grad = stats.carry[:, k + 1 : k + 1 + d] - inertia
    torch.testing.assert_close(carried_grad, grad, rtol=1e-6, atol=1e-6 * float(grad.abs().max()))
    # a carry keyed by another z (a reset row) or NaN is evaluated: the same rows as no carry at all, bitwise alike
    other = stats.carry.clone()
    other[0, 0] += 1.0
    other[1] = torch.nan
    stepper.evaluations = Evaluations()
    a, _ = stepper.step(z, z_prev, loads, warm=model, carry=other)
    rows_other = stepper.evaluations.rows
    stepper.evaluations = Evaluations()
    b, _ = stepper.step(z, z_prev, loads, warm=model)
    assert torch.equal(a, b) and rows_other == stepper.evaluations.rows
    with pytest.raises(ValueError, match=rf"carry must have shape \[2, {stepper.carry_size}\]"):
        stepper.step(z, z_prev, loads, carry=torch.zeros(2, d))


@pytest.mark.parametrize(("name", "cubature"), [("chain", False), ("hanging_sheet", True)])
def test_a_predicted_start_is_the_same_step_with_fewer_rows(name: str, cubature: bool) -> None:
    """With a carry and a warm model (as the envs pass them), ``predict`` starts each solve from the model's Newton
    step from z_t: float64 steps land on the same minimizers as from 2 z_t - z_{t-1}, for fewer rows; without the
    carry or the model it changes nothing, bitwise."""
    scene = scenes.build(name)
    f = pretrained.load(name).double()
    energy = cubature_energy if cubature else None
    steppers = {
        p: LatentStepper(scene, f, DT, dtype=torch.float64, tol=1e-10, energy=energy, predict=p) for p in (False, True)
    }
    B = 2
    loads = _loads(scene, B, 5, 2.0 if cubature else 20.0)
    runs = {}
    for predict, stepper in steppers.items():
        z = stepper.rest_latent().expand(B, -1).clone()
        z_prev, model, carry, path = z.clone(), None, None, [z]
        for _ in range(6):
            z_next, stats = stepper.step(z, z_prev, loads, warm=model, carry=carry)
            assert bool(stats.converged.all()) and not bool(stats.diverged.any())
            model, carry = stats.model, stats.carry
            z_prev, z = z, z_next
            path.append(z)
        runs[predict] = (torch.stack(path), stepper.evaluations.rows)
    (plain, plain_rows), (predicted, predicted_rows) = runs[False], runs[True]
    motion = float((plain - plain[0]).abs().max())
    assert motion > 1e-4  # it moved
    assert float((predicted - plain).abs().max()) <= 1e-5 * motion
    assert predicted_rows < plain_rows
    # without the carry, or without the model, the extrapolated start: bitwise the stepper without predict
    z, z_prev = path[-1], path[-2]
    for kwargs in ({"warm": model}, {"carry": carry}):
        a, _ = steppers[True].step(z, z_prev, loads, **kwargs)
        b, _ = steppers[False].step(z, z_prev, loads, **kwargs)
        assert torch.equal(a, b)
    if not cubature:  # Gauss-Newton (q_energy: not under a cubature) keeps no warm model: no prediction, bitwise
        gauss = {
            p: LatentStepper(scene, f, DT, dtype=torch.float64, hessian="gauss_newton", predict=p)
            for p in (False, True)
        }
        a, _ = gauss[True].step(z, z_prev, loads, warm=model, carry=carry)
        b, _ = gauss[False].step(z, z_prev, loads, warm=model, carry=carry)
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="predict must be True or False"):
        LatentStepper(scene, f, DT, dtype=torch.float64, predict="yes")


def test_newton_step_is_the_model_s_step_where_it_has_one() -> None:
    model = torch.stack([torch.diag(torch.tensor([2.0, 4.0])), torch.full((2, 2), torch.nan), -torch.eye(2)])
    grad = torch.tensor([[2.0, 4.0], [1.0, 1.0], [1.0, 1.0]])
    step, usable = newton_step(model, grad)
    assert usable.tolist() == [True, False, False]  # NaN, not positive definite
    torch.testing.assert_close(step, torch.tensor([[-1.0, -1.0], [0.0, 0.0], [0.0, 0.0]]))
    short, _ = newton_step(model, grad, max_step=0.5)
    torch.testing.assert_close(torch.linalg.vector_norm(short[0]), torch.tensor(0.5))


def test_a_step_that_did_not_converge_carries_nothing(mini_chain) -> None:
    """A load past float32's range (the step proves nothing: not converged, diverged) leaves a NaN carry, so the next
    step evaluates Phi at z_t: a carried force of ~1e20 N would have cancelled dE/dz to exactly 0 there, and the next
    step (a 5 N load, start "lower") would have stopped converged at z_t, 11x the tolerance from its minimum."""
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT, start="lower")
    z = stepper.rest_latent()
    huge = torch.zeros(1, len(scene.handles), scene.dim)
    huge[0, 0, 0] = 1e20
    z1, stats = stepper.step(z, z, huge)
    assert not bool(stats.converged[0]) and bool(stats.diverged[0]) and bool(stats.carry.isnan().all())
    small = torch.zeros(1, len(scene.handles), scene.dim)
    small[0, 0, 1] = 5.0
    carried, carried_stats = stepper.step(z1, z, small, carry=stats.carry)
    fresh, _ = stepper.step(z1, z, small)
    assert torch.equal(carried, fresh) and float((fresh - z1).abs().max()) > 1e-3
    assert bool(carried_stats.converged[0]) and int(carried_stats.iterations[0]) >= 1


def test_stats_shapes_and_types(mini_chain) -> None:
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT)
    z = stepper.rest_latent().expand(3, -1)
    z_next, stats = stepper.step(z, z)
    assert isinstance(stats, StepStats)
    assert z_next.shape == (3, stepper.latent_dim) and z_next.dtype == torch.float32
    assert stats.converged.dtype == torch.bool and stats.out_of_range.dtype == torch.bool
    assert stats.diverged.dtype == torch.bool and stats.iterations.dtype == torch.int64
    assert all(t.shape == (3,) for t in stats[:-2]) and stats.model.shape == (3, stepper.latent_dim, stepper.latent_dim)
    assert stats.carry.shape == (3, stepper.carry_size) == (3, 2 * stepper.latent_dim + 1 + scene.free_dof_count)
    assert stepper.positions(z).shape == (3, scene.free_dof_count)
    # at rest without load nothing moves, nothing is flagged
    torch.testing.assert_close(z_next, z, rtol=0.0, atol=1e-3)
    assert not bool(stats.out_of_range.any()) and not bool(stats.diverged.any())


def test_it_moves_under_load_and_energy_is_the_potential(mini_chain) -> None:
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT)
    z = stepper.rest_latent()
    z_prev = z.clone()
    loads = torch.zeros(1, len(scene.handles), scene.dim)
    loads[0, 0, 0] = 40.0  # [N] sideways on the bottom link
    start = scene.handles[0].position(scene.full_positions(stepper.positions(z).double()))
    for _ in range(10):
        z_next, stats = stepper.step(z, z_prev, loads)
        assert bool(stats.converged.all())
        z_prev, z = z, z_next
    end = scene.handles[0].position(scene.full_positions(stepper.positions(z).double()))
    assert float(end[0, 0] - start[0, 0]) > 0.01  # the handle moved along the pull [m]
    q = stepper.positions(z).double()
    torch.testing.assert_close(stats.energy.double(), scene.energy(q), rtol=1e-4, atol=1e-3)


def test_load_term_matches_the_scene_external_load(mini_chain) -> None:
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT, dtype=torch.float64)
    q = stepper.positions(0.3 * torch.ones(2, stepper.latent_dim, dtype=torch.float64))
    loads = _loads(scene, 2, 3, 5.0)
    work = (loads.reshape(2, -1) * stepper.handle_positions(q)).sum(-1)
    want = scene.energy(q) - scene.energy(q, loads)
    torch.testing.assert_close(work, want, rtol=1e-10, atol=1e-10)


def test_loads_by_handle_name_step_like_the_tensor_form(mini_chain) -> None:
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT)
    z = stepper.rest_latent().expand(2, -1).clone()
    tensor = torch.tensor([[[5.0, 0.0, 0.0]], [[5.0, 0.0, 0.0]]])
    by_name, stats = stepper.step(z, z, {"bottom": [5.0, 0.0, 0.0]})
    want, want_stats = stepper.step(z, z, tensor)
    assert torch.equal(by_name, want) and torch.equal(stats.energy, want_stats.energy)
    assert torch.equal(stepper.step(z, z, tensor[0])[0], want)  # [H, D]: the same loads for every state
    per_row = stepper.step(z, z, {"bottom": torch.tensor([[5.0, 0.0, 0.0], [0.0, 0.0, 0.0]])})[0]
    torch.testing.assert_close(per_row[0], want[0])  # the batch's rows agree to round-off, not bitwise
    assert float((per_row[1] - want[1]).abs().max()) > 1e-3
    with pytest.raises(ValueError, match=r"no handle\(s\) \['nope'\]; valid handles: \['bottom'\]"):
        stepper.step(z, z, {"nope": [5.0, 0.0, 0.0]})
    with pytest.raises(ValueError, match="loads must be finite"):
        stepper.step(z, z, {"bottom": [float("nan"), 0.0, 0.0]})


def test_non_finite_inputs_raise_before_stepping(mini_chain) -> None:
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT)
    z = stepper.rest_latent().expand(2, -1).clone()
    loads = torch.zeros(2, len(scene.handles), scene.dim)
    loads[1, 0, 2] = float("nan")
    with pytest.raises(ValueError, match=r"loads must be finite in the stepper's torch.float32 .*: row \[1\] of 2 is"):
        stepper.step(z, z, loads)
    bad = z.clone()
    bad[0, 0] = float("inf")
    with pytest.raises(ValueError, match=r"z must be finite in the stepper's torch.float32: row \[0\] of 2 is not"):
        stepper.step(bad, z)
    with pytest.raises(ValueError, match="z_prev must be finite"):
        stepper.step(z, bad)
    many = z.double().repeat(6, 1)
    many[1:, 0] = 1e39  # past float32's range: inf after the cast
    with pytest.raises(ValueError, match=r"z must be finite .*: rows \[1, 2, 3, 4, 5, 6, 7, 8\] and 3 more of 12 are"):
        stepper.step(many, many)
    with pytest.raises(ValueError, match="shape"):
        stepper.step(z, z, torch.zeros(2, 5, scene.dim))
    with pytest.raises(ValueError, match="no condition space"):
        stepper.step(z, z, cond=torch.zeros(2, 1))


def test_a_condition_past_the_dtype_s_range_is_refused_like_z_and_loads() -> None:
    """cond was checked before its cast to the stepper's dtype: 1e40 in float64 passed, became inf in float32, and
    positions() returned non-finite q and objective() NaN without a word (README: a non-finite condition raises)."""
    scene = scenes.build("conditional_bar")
    stepper = LatentStepper(scene, pretrained.load("conditional_bar", scene), DT)
    z = stepper.rest_latent().expand(2, -1).clone()
    cond = scene.condition_space.default.reshape(1, -1).double().repeat(2, 1)
    cond[1, 0] = 1e40
    message = r"cond must be finite in the stepper's torch.float32: row \[1\] of 2 is not"
    calls = (
        lambda: stepper.step(z, z, cond=cond),
        lambda: stepper.positions(z, cond),
        lambda: stepper.objective(z, z, z, cond=cond),
    )
    for call in calls:
        with pytest.raises(ValueError, match=message):
            call()


def test_inputs_that_are_not_numbers_are_named(mini_chain) -> None:
    """A string, None or a ragged list was torch's conversion error (TypeError "new(): invalid data type 'str'",
    RuntimeError "Could not infer dtype of NoneType"), naming neither the argument nor its shape; a complex z was
    cast with its imaginary part dropped. Each is a ValueError naming both now."""
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT)
    z = stepper.rest_latent()
    for bad in ("abc", None, [[1.0], [1.0, 2.0]]):
        with pytest.raises(ValueError, match=r"z must be an array of numbers of shape \[B, 4\]"):
            stepper.step(bad, z)
    with pytest.raises(ValueError, match=r"z_prev must be an array of real numbers of shape \[B, 4\], got torch.compl"):
        stepper.step(z, z.to(torch.complex64))
    # complex numbers in a list, not an array: their tensor is complex, and was cast to real with a warning
    for bad in ((z.to(torch.complex128) + 5j).tolist(), [[1j, 0.0, 0.0, 0.0]]):
        with pytest.raises(ValueError, match=r"z must be an array of real numbers of shape \[B, 4\], got .*complex"):
            stepper.step(bad, z)
    with pytest.raises(ValueError, match=r"loads must be an array of numbers of shape \[1, 1, 3\] or \[1, 3\]"):
        stepper.step(z, z, "abc")
    with pytest.raises(ValueError, match=r"warm must be an array of numbers of shape \[1, 4, 4\]"):
        stepper.step(z, z, warm="abc")
    z_next, _ = stepper.step(z.numpy(), z.numpy().tolist(), [[0.0, 0.0, 0.0]])  # NumPy arrays and lists still work
    assert torch.equal(z_next, stepper.step(z, z, torch.zeros(1, 1, 3))[0])


def test_an_empty_batch_steps_to_an_empty_batch(mini_chain) -> None:
    """Stepping only the copies still running (``z[~done]``) can leave none: B = 0 returns empty results, as torch
    does. The chains' contact effect inferred a size with reshape(..., -1), which an empty batch cannot (a
    RuntimeError deep inside scene.energy); it also made the chain scenes' energy refuse q [0, n]."""
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT)
    z = stepper.rest_latent()[:0]
    z_next, stats = stepper.step(z, z, torch.zeros(0, len(scene.handles), scene.dim))
    assert z_next.shape == (0, stepper.latent_dim) and stats.model.shape == (0, stepper.latent_dim, stepper.latent_dim)
    assert stats.converged.shape == stats.diverged.shape == stats.energy.shape == (0,)
    for name in ("mini_chain", "chain"):
        built = scenes.build(name)
        assert built.energy(built.q_seed[None][:0]).shape == (0,)
        assert torch.isfinite(built.energy(built.q_seed[None]))
    # the rest of no conditions is none (torch.stack of an empty list raised), and a 1-D condition's error asks for
    # its batch form ([1, m], not [m, m])
    bar = LatentStepper(scenes.build("conditional_bar"), pretrained.load("conditional_bar"), DT)
    assert bar.rest_latent(torch.zeros(0, 2)).shape == (0, bar.latent_dim)
    with pytest.raises(ValueError, match=r"cond must have shape \[1, 2\] .*got \(2,\)"):
        bar.rest_latent(torch.tensor([1.0, 0.65]))


def test_a_warm_model_of_the_wrong_shape_is_refused_also_where_warm_start_ignores_it(mini_chain) -> None:
    scene, f = mini_chain
    cold = LatentStepper(scene, f, DT, warm_start=False)
    z = cold.rest_latent().expand(2, -1)
    with pytest.raises(ValueError, match=r"warm must have shape \[2, 4, 4\]"):
        cold.step(z, z, warm=torch.zeros(7))
    torch.testing.assert_close(cold.step(z, z, warm=torch.eye(4).expand(2, 4, 4))[0], cold.step(z, z)[0])


def test_the_stepper_steps_its_own_copy_of_the_map_and_names_a_scene_of_other_parameters() -> None:
    """The rest solve reads the map the steps use (a copy), whatever the caller does to its own after; a map fitted
    to the scene with other parameters (a soft bar's map on a stiffer bar) is stepped, with a warning that says so."""
    scene, mine = scenes.build("mini_chain"), pretrained.load("mini_chain")
    stepper = LatentStepper(scene, mine, DT, dtype=torch.float64)
    rest = stepper.rest_latent(start=torch.zeros(4))
    with torch.no_grad():
        for p in mine.parameters():
            p.mul_(0.5)
    torch.testing.assert_close(stepper.rest_latent(start=torch.zeros(4)), rest)
    with pytest.raises(ValueError, match=r"start must be finite"):  # it said "z0 must be finite", a name not given
        stepper.rest_latent(start=torch.full((4,), float("nan")))
    with pytest.warns(UserWarning, match="fitted to scene 'mini_chain' with other parameters"):
        LatentStepper(scenes.build("mini_chain", density=2000.0), pretrained.load("mini_chain"), DT)


def test_bad_settings_raise(mini_chain) -> None:
    from redsim.cubature import CubatureConfig, CubatureEnergy, build_cubature

    scene, f = mini_chain
    rules = build_cubature(scene, f, CubatureConfig(elements=2, samples=8, episodes=0))
    for kwargs in ({"dt": 0.0}, {"dt": float("nan")}):
        with pytest.raises(ValueError, match="dt"):
            LatentStepper(scene, f, **kwargs)
    with pytest.raises(ValueError, match="tol"):
        LatentStepper(scene, f, DT, tol=-1.0)
    with pytest.raises(ValueError, match="max_iter"):
        LatentStepper(scene, f, DT, max_iter=0)
    with pytest.raises(ValueError, match="hessian"):
        LatentStepper(scene, f, DT, hessian="magic")
    with pytest.raises(ValueError, match="dtype"):
        LatentStepper(scene, f, DT, dtype=torch.float16)
    for sync_every in (0, 1.5, True):
        with pytest.raises(ValueError, match="sync_every"):
            LatentStepper(scene, f, DT, sync_every=sync_every)
    with pytest.raises(ValueError, match="fitted to scene 'mini_chain', not to 'chain'"):
        LatentStepper(scenes.build("chain"), f, DT)
    bare = copy.deepcopy(f)
    bare.metadata = {}  # a map that names no scene: its output size is what is checked
    with pytest.raises(ValueError, match="maps z"):
        LatentStepper(scenes.build("chain"), bare, DT)
    for device in ("bogus", "mps", *(() if torch.cuda.is_available() else ("cuda",))):
        with pytest.raises(ValueError, match="device"):  # the envs' check, not an error from deep inside torch
            LatentStepper(scene, f, DT, device=device)
        with pytest.raises(ValueError, match="device"):
            MapEnergy(scene, f, device=device)
        with pytest.raises(ValueError, match="device"):
            CubatureEnergy(scene, f, rules, device=device)


def test_an_energy_in_another_dtype_is_refused_at_construction(mini_chain) -> None:
    from redsim.cubature import CubatureConfig, CubatureEnergy, build_cubature

    scene, f = mini_chain
    rules = build_cubature(scene, f, CubatureConfig(elements=2, samples=8, episodes=0))
    for energy, name in ((MapEnergy(scene, f), "MapEnergy"), (CubatureEnergy(scene, f, rules), "CubatureEnergy")):
        with pytest.raises(
            ValueError,
            match=rf"energy is a {name} in torch.float32 on cpu, but the stepper runs in torch.float64 on cpu: "
            r"build it with dtype=torch.float64, .* or pass a factory energy\(scene, subspace, \*, dtype, device\)",
        ):
            LatentStepper(scene, f, DT, dtype=torch.float64, energy=energy)
    with pytest.raises(ValueError, match=r"MapEnergy in torch.float64 on cpu, but the stepper runs in torch.float32"):
        LatentStepper(scene, f, DT, energy=MapEnergy(scene, f, dtype=torch.float64))

    def factory(scene, subspace, dtype, device):
        return CubatureEnergy(scene, subspace, rules, dtype=dtype, device=device)

    stepper = LatentStepper(scene, f, DT, dtype=torch.float64, energy=factory)
    z = torch.zeros(1, stepper.latent_dim, dtype=torch.float64)
    assert stepper.step(z, z)[0].dtype == torch.float64
    same = MapEnergy(scene, f, dtype=torch.float64)
    assert LatentStepper(scene, f, DT, dtype=torch.float64, energy=same).energy is same


def test_far_latent_is_out_of_range(mini_chain) -> None:
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT)
    z = torch.zeros(2, stepper.latent_dim)
    z[1] = 30.0  # |z| = 60 >> 4 sqrt(d) = 8
    z_next, stats = stepper.step(z, z)
    assert stats.out_of_range.tolist() == [False, True]
    assert bool(torch.isfinite(z_next).all())


class _Repulsive:
    """The map's energy minus k |q - q0|^2: negative stiffness, so the step flies apart."""

    def __init__(self, inner: MapEnergy, k: float) -> None:
        self.inner, self.k = inner, k
        self.latent_dim, self.condition_dim, self.periodic = inner.latent_dim, inner.condition_dim, inner.periodic
        self.q0 = inner.positions(torch.zeros(1, inner.latent_dim), None).detach()

    def positions(self, z, cond):
        return self.inner.positions(z, cond)

    def energy(self, z, cond):
        e, q = self.inner.energy(z, cond)
        return e - self.k * ((q - self.q0) ** 2).sum(-1), q


class _NaNAway:
    """The map's energy, NaN where |z| > 1: the line search must reject those trials."""

    def __init__(self, inner: MapEnergy) -> None:
        self.inner = inner
        self.latent_dim, self.condition_dim, self.periodic = inner.latent_dim, inner.condition_dim, inner.periodic

    def positions(self, z, cond):
        return self.inner.positions(z, cond)

    def energy(self, z, cond):
        e, q = self.inner.energy(z, cond)
        return torch.where(torch.linalg.vector_norm(z, dim=-1) > 1.0, torch.nan, e), q


@pytest.mark.parametrize("dense", [False, True])
def test_forced_blow_up_is_flagged_diverged_and_stays_finite(mini_chain, dense: bool) -> None:
    scene, f = mini_chain
    inner = MapEnergy(scene, f)
    stepper = LatentStepper(scene, f, DT, energy=_Repulsive(inner, 1e4), dense=dense)
    z = 0.1 * torch.ones(2, stepper.latent_dim)
    z_next, stats = stepper.step(z, z)
    assert bool(stats.diverged.all())
    assert bool(torch.isfinite(z_next).all())
    calm = LatentStepper(scene, f, DT, dense=dense)  # the same start under the real energy is fine
    _, stats = calm.step(z, z)
    assert not bool(stats.diverged.any())


@pytest.mark.parametrize("name", ["mini_chain", "bistable_bar"])
def test_float32_value_noise_is_sized_by_the_round_off_of_phi(name: str) -> None:
    # the line search takes a trial that raises Phi by up to the noise; it sat 7,000x above Phi's float32 round-off
    # on mini_chain (|diag M| L / h^2 counted as a force), so uphill trials of 0.02 J were accepted
    scene, f = scenes.build(name), pretrained.load(name)
    s32 = LatentStepper(scene, f, DT, dtype=torch.float32)
    s64 = LatentStepper(scene, f, DT, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    z = s64.rest_latent() + 0.5 * torch.randn(64, s64.latent_dim, generator=g, dtype=torch.float64)
    z_prev = z - 0.02 * torch.randn(z.shape, generator=g, dtype=torch.float64)
    candidate = z + 0.01 * torch.randn(z.shape, generator=g, dtype=torch.float64)
    exact = s64.objective(candidate, z, z_prev)
    rounded = s32.objective(candidate.float(), z.float(), z_prev.float()).double()
    roundoff = float((rounded - exact).abs().max())
    noise = float(s32._value_noise(torch.zeros(1))[0])
    assert 10.0 * roundoff < noise < 1000.0 * roundoff


@pytest.mark.parametrize("start", ["extrapolated", "lower"])
@pytest.mark.parametrize("dense", [False, True])
def test_non_finite_trials_are_rejected(mini_chain, dense: bool, start: str) -> None:
    """A NaN extrapolated start solves from z_t instead: a finite step, not a diverged one that stays put."""
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT, energy=_NaNAway(MapEnergy(scene, f)), dense=dense, start=start)
    z = torch.zeros(1, stepper.latent_dim)
    z[0, 0] = 0.9
    z_prev = z.clone()
    z_prev[0, 0] = 0.6  # moving outward fast: the extrapolated start (1.2) is NaN
    z_next, stats = stepper.step(z, z_prev)
    assert bool(torch.isfinite(z_next).all())
    assert float(torch.linalg.vector_norm(z_next)) <= 1.0 + 1e-6
    # the minimum lies past the NaN wall, so the solve ends against it unconverged, but it is not flagged
    # diverged and it moved (a non-finite start used to leave z_t in place, flagged diverged)
    assert not bool(stats.diverged.any()), stats
    assert float((z_next - z).abs().max()) > 1e-2


class _Trap:
    """The map's energy, NaN where z_0 > 2, plus k min(|z - p|, r) that its gradient does not see: every step from p
    rises (a solve from p stalls), and from beyond r of p it is a constant."""

    def __init__(self, inner: MapEnergy, p: torch.Tensor, k: float = 1e3, r: float = 0.1) -> None:
        self.inner, self.p, self.k, self.r = inner, p, k, r
        self.latent_dim, self.condition_dim, self.periodic = inner.latent_dim, inner.condition_dim, inner.periodic

    def positions(self, z, cond):
        return self.inner.positions(z, cond)

    def energy(self, z, cond):
        e, q = self.inner.energy(z, cond)
        cone = self.k * torch.linalg.vector_norm(z.detach() - self.p, dim=-1).clamp_max(self.r)
        return torch.where(z[:, 0] > 2.0, torch.nan, e + cone), q


def test_a_step_with_no_finite_start_reports_the_energy_where_it_stays(mini_chain) -> None:
    """Float32, z_{t-1} 1e30 from z_t: Phi overflows at both starts, so nothing is solved (z_next = z_t, diverged).
    ``energy`` is E(f(z_t)), the state's own: it read 0.0 (the solver's zeroed value), a finite energy it never had."""
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT)
    rest = stepper.rest_latent()
    z_prev = rest.clone()
    z_prev[0, 0] -= 1e30
    z_next, stats = stepper.step(rest, z_prev)
    assert bool(stats.diverged[0]) and float(stats.residual[0]) == math.inf and bool(torch.equal(z_next, rest))
    expected = float(scene.energy(stepper.positions(rest).to(torch.float64))[0])
    assert float(stats.energy[0]) == pytest.approx(expected, rel=1e-5) and expected < -1.0


@pytest.mark.parametrize("dense", [False, True])
def test_each_row_s_failure_is_reported_on_that_row_and_leaves_the_others_alone(mini_chain, dense: bool) -> None:
    """Float64, one batch: a row that stalls (``stalled``, not converged, not diverged), a row whose start and z_t have
    no finite energy (z_next = z_t, diverged, residual inf: it was 0, a perfect residual on a row that never
    iterated), a row whose z_t has none but whose extrapolated start has (diverged: the step's energy balance cannot
    be checked; it was unflagged with a NaN energy_gain_tolerance), and a healthy row that steps as it does alone."""
    scene, f = mini_chain
    rest = LatentStepper(scene, f, DT, dtype=torch.float64).rest_latent()
    trap = _Trap(MapEnergy(scene, f, dtype=torch.float64), rest)
    stepper = LatentStepper(scene, f, DT, dtype=torch.float64, energy=trap, dense=dense)
    z = rest.repeat(4, 1)
    z[1, 1] += 0.5  # healthy, beyond the cone
    z[2, 0] = 3.0  # no finite energy at z_t nor at the extrapolated start
    z[3, 0] = 2.05
    z_prev = z.clone()
    z_prev[3, 0] = 3.1  # extrapolated start at z_0 = 1: finite
    loads = torch.zeros(4, len(scene.handles), scene.dim, dtype=torch.float64)
    loads[:, 0, 0] = 5.0
    z_next, stats = stepper.step(z, z_prev, loads)
    assert stats.stalled.tolist() == [True, False, False, False]
    assert stats.converged.tolist() == [False, True, False, True]  # row 3 from its finite start
    assert stats.diverged.tolist() == [False, False, True, True]
    assert bool(torch.equal(z_next[2], z[2])) and float(stats.residual[2]) == math.inf
    assert bool(torch.isfinite(stats.residual[[0, 1, 3]]).all())
    assert math.isnan(float(stats.energy[2])) and bool(torch.isfinite(stats.energy[[0, 1, 3]]).all())  # it read 0
    assert not bool(stats.energy_gain_tolerance.isnan().any())
    assert stats.carry.isnan().all(-1).tolist() == [True, False, True, False]
    alone, alone_stats = stepper.step(z[1:2], z_prev[1:2], loads[1:2])
    torch.testing.assert_close(alone[0], z_next[1], rtol=0.0, atol=1e-12)  # batch round-off only (docs/runtime.md)
    assert int(alone_stats.iterations[0]) == int(stats.iterations[1]) and bool(alone_stats.converged[0])


@pytest.mark.slow
def test_compiled_step_equals_eager_within_float32_round_off(mini_chain) -> None:
    scene, f = mini_chain
    eager = LatentStepper(scene, f, DT)
    compiled = LatentStepper(scene, f, DT, compile=True)
    z = eager.rest_latent().expand(3, -1).clone()
    loads = _loads(scene, 3, 5, 10.0, torch.float32)
    want, want_stats = eager.step(z, z, loads)
    got, got_stats = compiled.step(z, z, loads)
    assert bool(want_stats.converged.all()) and bool(got_stats.converged.all())
    q_want, q_got = eager.positions(want), eager.positions(got)
    motion = float((q_want - eager.positions(z)).abs().max())
    # two float32 solves stopped by tol 1e-6 at different round-off: they agree to the solve tolerance
    # (one-step errors of 0.2-2.5% of the motion against the float64 reference, docs/runtime.md, "Tolerance")
    torch.testing.assert_close(q_got, q_want, rtol=0.0, atol=1e-2 * motion)


def _compiles() -> bool:
    try:
        check_compiler(torch.device("cpu"))
    except RuntimeError:
        return False
    return True


@pytest.mark.slow
@pytest.mark.skipif(not _compiles(), reason="torch.compile needs a C++ compiler on the CPU")
def test_dynamic_compile_equals_eager_and_evaluates_only_the_rows_asked() -> None:
    """compile="dynamic" (value and gradient in one graph, any row count) on the cubature HangingCloth-v1 steps on:
    the same Phi, gradient and E as eager at 1, 2 and 5 of 5 states (counted as those rows, not padded to the batch),
    and the same step to the solve's tolerance."""
    scene, f = scenes.build("hanging_sheet"), pretrained.load("hanging_sheet")
    eager = LatentStepper(scene, f, DT, energy=cubature_energy)
    compiled = LatentStepper(scene, f, DT, energy=cubature_energy, compile="dynamic")
    breaks = sum(torch._dynamo.utils.counters["graph_break"].values())
    g = torch.Generator().manual_seed(0)
    z = eager.rest_latent() + 0.3 * torch.randn(5, eager.latent_dim, generator=g)
    with torch.no_grad():
        qbar = eager._energy_coords(z + 0.05 * torch.randn(z.shape, generator=g), None)[1]
    loads = _loads(scene, 5, 1, 1.0, torch.float32).reshape(5, -1)
    for rows in (1, 2, 5):
        index = torch.arange(rows)
        want = _StepObjective(eager, qbar, loads, None, z).value_and_grad(z[:rows], index)
        got = _StepObjective(compiled, qbar, loads, None, z).value_and_grad(z[:rows], index)
        # float32 sums over 1000 kept elements: eager itself moves by up to 2e-4 of a row's gradient norm between
        # batch sizes, Phi by a few 1e-6 of its size, and lies ~2e-5 of it from float64 (a review, stop 53)
        torch.testing.assert_close(got[0], want[0], rtol=5e-5, atol=0.0)
        torch.testing.assert_close(got[2], want[2], rtol=1e-5, atol=1e-5 * float(want[2].abs().max()))
        assert float(((got[1] - want[1]).norm(dim=1) / want[1].norm(dim=1)).max()) < 2e-3
    assert compiled.evaluations == eager.evaluations == Evaluations(calls=3, rows=8)
    # value and gradient in one graph (no break at autograd.grad), and Dynamo's setting restored after each call
    assert sum(torch._dynamo.utils.counters["graph_break"].values()) == breaks
    assert not getattr(torch._dynamo.config, "trace_autograd_ops", False)
    z_prev = z - 0.05 * torch.randn(z.shape, generator=g)
    want, want_stats = eager.step(z, z_prev, loads.reshape(5, -1, scene.dim))
    got, got_stats = compiled.step(z, z_prev, loads.reshape(5, -1, scene.dim))
    assert bool(want_stats.converged.all()) and bool(got_stats.converged.all())
    # Phi is not convex in z: a float32 round-off difference can turn one line-search decision and end a state in
    # another local minimum (since stop 53's edge layer, state 2 here: Phi 0.7746 against 0.7623; both are as close
    # to float64 per call as before, a review). States that end at the same Phi end at the same step.
    phi_want, phi_got = (eager.objective(u, z, z_prev, loads.reshape(5, -1, scene.dim)) for u in (want, got))
    same = (phi_got - phi_want).abs() <= 1e-4 * phi_want.abs().clamp_min(1.0)
    assert int(same.sum()) >= 4
    q_want, q_got = eager.positions(want), eager.positions(got)
    motion = float((q_want - eager.positions(z)).abs().max())
    torch.testing.assert_close(q_got[same], q_want[same], rtol=0.0, atol=1e-2 * motion)  # as the static compile's test


@pytest.mark.skipif(not _compiles(), reason="torch.compile needs a C++ compiler on the CPU")
def test_a_copied_or_pickled_compiled_stepper_evaluates_its_own_map(mini_chain, monkeypatch) -> None:
    """compile="dynamic" (and True) keep callables compiled from the stepper's own ``_phi_eager``: copy.deepcopy
    shared them, so the copy's calls evaluated the original's map (a copy whose map then changed stepped the old
    one), and pickle failed. Dynamo alone (backend "eager", no kernels built): the test is about which map is called."""
    import pickle

    compile_ = torch.compile
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: compile_(fn, **{**kw, "backend": "eager"}))
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT, compile="dynamic")
    copied = copy.deepcopy(stepper)
    with torch.no_grad():
        for p in copied.energy.map.parameters():
            p.mul_(1.05)
    z = stepper.rest_latent().expand(3, -1) + 0.1
    qbar = copied.positions(z).detach()
    want = copied._phi_eager(z, qbar, None, None)[0]
    torch.testing.assert_close(copied._compiled_call(z, qbar, None, None)[0], want, rtol=1e-6, atol=0.0)
    assert not torch.allclose(stepper._compiled_call(z, qbar, None, None)[0], want)  # the original keeps its map
    for mode in (True, "dynamic"):
        z_next, _ = pickle.loads(pickle.dumps(LatentStepper(scene, f, DT, compile=mode))).step(z, z)
        torch.testing.assert_close(z_next, LatentStepper(scene, f, DT).step(z, z)[0], rtol=0.0, atol=1e-4)


@pytest.mark.skipif(not _compiles(), reason="torch.compile needs a C++ compiler on the CPU")
@pytest.mark.parametrize("mode", [True, pytest.param("dynamic", marks=pytest.mark.slow)])
def test_every_compiled_stepper_in_a_process_stays_compiled(mini_chain, monkeypatch, mode) -> None:
    """Dynamo keeps its graphs, and a limit of 8 of them, per code object: every stepper compiled the same function,
    so past ~4 steppers in one process (2 graphs each) the later ones ran uncompiled behind one logged warning. Each
    now compiles a function of its own. Dynamo alone (backend "eager"): the test is about what Dynamo compiles."""
    from torch._dynamo.utils import counters

    compile_ = torch.compile
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: compile_(fn, **{**kw, "backend": "eager"}))
    scene, f = mini_chain
    compiled = counters["frames"]["ok"]
    steppers = 6
    for _ in range(steppers):
        stepper = LatentStepper(scene, f, DT, compile=mode)
        z = stepper.rest_latent().expand(3, -1) + 0.01
        qbar = stepper.positions(z).detach()
        for rows in (1, 3):
            if mode == "dynamic":
                stepper._compiled_call(z[:rows], qbar[:rows], None, None)
            else:
                stepper._phi_fast(z[:rows], qbar[:rows], None, None)
    assert counters["frames"]["ok"] - compiled == 2 * steppers


def test_unknown_compile_is_refused(mini_chain) -> None:
    scene, f = mini_chain
    with pytest.raises(ValueError, match="unknown compile 'static'; valid: \\[False, True, 'dynamic'\\]"):
        LatentStepper(scene, f, DT, compile="static")


def test_compile_without_a_cpp_compiler_is_refused_at_construction(mini_chain, monkeypatch) -> None:
    """torch.compile on the CPU needs a C++ compiler: without one the stepper says so when built, not at its first
    step from inside Inductor."""
    from torch._inductor import cpp_builder, exc

    def missing() -> str:
        raise exc.InvalidCxxCompiler

    monkeypatch.setattr(cpp_builder, "get_cpp_compiler", missing)
    scene, f = mini_chain
    with pytest.raises(RuntimeError, match="compile needs a C\\+\\+ compiler"):
        LatentStepper(scene, f, DT, compile=True)
    LatentStepper(scene, f, DT)  # without compile no compiler is needed


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_runs_on_cuda_like_on_the_cpu(mini_chain) -> None:
    scene, f = mini_chain
    cpu = LatentStepper(scene, f, DT, dtype=torch.float64)
    gpu = LatentStepper(scene, f, DT, dtype=torch.float64, device="cuda")
    z = cpu.rest_latent().expand(4, -1).clone()
    loads = _loads(scene, 4, 6, 10.0)
    want, _ = cpu.step(z, z, loads)
    got, stats = gpu.step(z.cuda(), z.cuda(), loads.cuda())
    assert got.device.type == "cuda" and stats.converged.device.type == "cuda"
    torch.testing.assert_close(got.cpu(), want, rtol=0.0, atol=1e-6)


def test_objective_is_what_the_step_minimizes(mini_chain) -> None:
    """stepper.objective at the step's answer is below its value at the start and at nearby latents."""
    scene, f = mini_chain
    stepper = LatentStepper(scene, f, DT, dtype=torch.float64, tol=1e-10)
    z = stepper.rest_latent()
    loads = _loads(scene, 1, 4, 5.0)
    z_next, stats = stepper.step(z, z, loads)
    assert bool(stats.converged.all())
    best = stepper.objective(z_next, z, z, loads)
    g = torch.Generator().manual_seed(0)
    nearby = z_next + 1e-3 * torch.randn(8, stepper.latent_dim, generator=g, dtype=torch.float64)
    others = stepper.objective(nearby, z.expand(8, -1), z.expand(8, -1), loads.expand(8, -1, -1))
    assert float(best) < float(stepper.objective(z, z, z, loads)) and bool((best < others).all())
    # one candidate or one z_prev for 8 states was broadcast to 8 values without a word (3 of 8: a torch error)
    for args in ((z, z.expand(8, -1), z.expand(8, -1)), (nearby, nearby, z), (nearby[:3], nearby, nearby)):
        with pytest.raises(ValueError, match="candidate, z and z_prev must have the same batch size"):
            stepper.objective(*args)


@pytest.mark.parametrize(("name", "cubature"), [("mini_chain", False), ("conditional_bar", True)])
def test_closed_form_inertia_gradient_equals_autograd(name: str, cubature: bool) -> None:
    """The solver's value and gradient (autograd through E and q, the inertia and load terms in closed form)
    equal autograd through the whole objective, in the free DOFs and in a cubature's features (float64)."""
    scene = scenes.build(name)
    f = pretrained.load(name)
    stepper = LatentStepper(scene, f, DT, dtype=torch.float64, energy=cubature_energy if cubature else None)
    assert stepper.reduced == cubature
    g = torch.Generator().manual_seed(0)
    z = 0.5 * torch.randn(3, stepper.latent_dim, generator=g, dtype=torch.float64)
    cond = stepper._default_cond(3)
    with torch.no_grad():
        qbar = stepper._energy_coords(z + 0.2 * torch.randn(z.shape, generator=g, dtype=torch.float64), cond)[1]
    loads = _loads(scene, 3, 1, 5.0).reshape(3, -1)
    objective = _StepObjective(stepper, qbar, loads, cond, z)
    value, grad, energy = objective._value_and_grad(z, qbar, loads, cond)
    zr = z.clone().requires_grad_(True)
    expected, expected_energy = stepper._phi_eager(zr, qbar, loads, cond)
    (expected_grad,) = torch.autograd.grad(expected.sum(), zr)
    torch.testing.assert_close(value, expected.detach(), rtol=1e-12, atol=0.0)
    torch.testing.assert_close(energy, expected_energy.detach(), rtol=0.0, atol=0.0)
    torch.testing.assert_close(grad, expected_grad, rtol=1e-9, atol=1e-9 * float(expected_grad.abs().max()))


def test_an_effect_that_reads_the_loads_besides_the_load_term_is_refused(mini_chain) -> None:
    """The runtime and the cubature add the loads' work in closed form (the linear external_load term); another
    load-reading effect would be dropped, so they refuse the scene where the full-space integrators take it."""
    import dataclasses

    from redsim.cubature import CubatureConfig, build_cubature
    from redsim.effects import Effect

    class Wind(Effect):
        kind = "wind"
        uses_loads = True

        def __init__(self, dofs: torch.Tensor) -> None:
            self.name, self.element_dofs = "wind", dofs

        def element_energy(self, xe, cond=None, loads=None):
            return xe.new_zeros(xe.shape[:2]) if loads is None else -(xe * loads[:, :1, :1]).sum(-1)

    scene, f = mini_chain
    dofs = scene.effect("external_load").element_dofs[:, :1]
    windy = dataclasses.replace(scene, effects=(*scene.effects, Wind(dofs)), _effect_index={})
    assert "wind" in windy.energy_terms(windy.q_seed)  # the scene itself keeps it (full space evaluates it)
    with pytest.raises(ValueError, match=r"effect\(s\) \['wind'\] read the loads; the latent runtime"):
        LatentStepper(windy, f, DT)
    with pytest.raises(ValueError, match=r"effect\(s\) \['wind'\] read the loads; a cubature"):
        build_cubature(windy, f, CubatureConfig(samples=8))


def test_a_tolerance_below_float32_round_off_warns_and_its_steps_end_unconverged(mini_chain) -> None:
    """tol 1e-12 in float32 (a review's setting: every step ran max_iter and nothing said why) warns at construction;
    its steps under a load end unconverged where the default converges; float64 takes 1e-12 without a warning."""
    scene, f = mini_chain
    with pytest.warns(UserWarning, match=r"tol 1e-12 is below what torch.float32's round-off .* larger tol"):
        tight = LatentStepper(scene, f, DT, dtype=torch.float32, tol=1e-12, max_iter=20)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        LatentStepper(scene, f, DT, dtype=torch.float64, tol=1e-12)
        default = LatentStepper(scene, f, DT, dtype=torch.float32)
    for stepper, converges in ((tight, False), (default, True)):
        z = stepper.rest_latent()
        loads = torch.zeros(1, len(scene.handles), scene.dim, dtype=stepper.dtype)
        loads[..., 0] = 10.0
        _, stats = stepper.step(z, z.clone(), loads)
        assert bool(stats.converged[0]) == converges
        assert (int(stats.iterations[0]) == 20) != converges


def test_a_stepper_too_coarse_to_feel_its_forces_warns(mini_chain) -> None:
    """float32 at dt 1 ms resolves only ~2 m/s^2 on the mini chain: it warns, and a 10 N load is not felt (the step
    ends at its start with no iteration) where float64 moves; the envs' dt 0.02 s does not warn."""
    scene, f = mini_chain
    with pytest.warns(UserWarning, match=r"resolves accelerations only to .* use dtype=torch.float64"):
        coarse = LatentStepper(scene, f, 0.001, dtype=torch.float32)
    fine = LatentStepper(scene, f, 0.001, dtype=torch.float64)
    assert coarse.acceleration_resolution == pytest.approx(1000 * fine.acceleration_resolution, rel=1e-4)
    assert coarse.load_resolution.shape == (len(scene.handles),) and bool((coarse.load_resolution > 0).all())
    torch.testing.assert_close(coarse.load_resolution, 1000 * fine.load_resolution, rtol=1e-3, atol=0.0)
    for stepper, felt in ((coarse, False), (fine, True)):
        z = stepper.rest_latent()
        loads = torch.zeros(1, len(scene.handles), scene.dim, dtype=stepper.dtype)
        loads[..., 0] = 10.0
        z_next, stats = stepper.step(z, z.clone(), loads)
        assert bool(stats.converged[0])
        assert (int(stats.iterations[0]) > 0) == felt and bool((z_next != z).any()) == felt
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        default = LatentStepper(scene, f, DT)
    assert default.acceleration_resolution < RESOLUTION_WARNING
