"""Batched minimization over latent states: Newton-type directions in z (d x d) and a masked line search.

Every state b of a batch [B, d] is minimized on its own; they share only the calls: each call of the
objective evaluates one trial of every state still active (neither converged nor stalled). The d x d
model Hessian comes from one of :data:`HESSIANS`:

- ``"exact"``: the exact Hessian of Phi in z (map curvature included) by double backward over d
  copies of each state, eigenvalues replaced by their absolute value (floored), as the reference
  :class:`redsim.integrators.LatentSpace` does.
- ``"gauss_newton"``: J^T (M/h^2 + d^2E/dq^2) J with J = dq/dz from :func:`redsim.tensors.jvp`
  and the q-space Hessian applied to J's columns (double backward over q), map curvature dropped.
- ``"bfgs"``: a damped BFGS update of the Hessian, started from J^T M J / h^2.
- ``"lagged"``: the exact Hessian at the first iterate of a step, then BFGS updates of it.
- ``"lagged_fd"``: as "lagged", with the first Hessian from forward differences of the gradient
  (d gradients at z + eps e_k in one call: no double backward, so it also runs compiled).

The quasi-Newton models ("bfgs", "lagged", "lagged_fd") may start from a ``warm`` model, e.g. the
last step's final model (what :class:`redsim.runtime.LatentStepper` carries from step to step, as
MuJoCo's solver carries ``qacc_warmstart``): the step then costs no Hessian evaluation unless a
state is still unconverged after :data:`WARM_ITERATIONS` iterations or backtracks from it, which
recomputes its model at the current iterate once (``warm_refresh=False``: only where its line search fails,
the restart below; otherwise the BFGS updates repair it).
``max_step`` caps the length |dz| of every step the solver tries (a trust radius in latent units): where the map
barely moves along some latent direction a Newton-type step along it can be far too long (docs/env-speed.md,
"ConditionalBar-v0's solve path").

The line search is Armijo backtracking per state: a trial with a non-finite value or gradient is rejected like an
uphill one; a trial whose value change is at round-off level is accepted if it lowers |g|. A quasi-Newton state's
rejected finite trial updates its model (BFGS) and turns the next trial along it, after a trial that rose beyond
round-off no longer than the backtracked trial (so such trials shrink as plain backtracking's do). One whose line
search fails (MAX_BACKTRACKS rejected trials) restarts it once from a model built afresh at the same iterate: a
model that BFGS updates have bent far from the curvature gives directions no step length along which lowers Phi
enough, while the state is far from converged. A state whose restarted line search fails too, or whose model was
built at this iterate already (a restart would replay the same trials), or an "exact" or "gauss_newton" one (its
model is always fresh), keeps its last accepted (finite) iterate and stops (``stalled``). So one iteration takes at
most 2 MAX_BACKTRACKS + 1 calls of the objective, and the loops allow max_iter times that.

Two loops compute the same iterates of every state (to round-off): the row-selected one (the default)
evaluates only the active states in each call, which is what a CPU wants; it keeps the iterates in numpy on the
host, where an op on these few-row arrays costs a third of a torch op's fixed cost, and hands the objective torch
tensors on its device (on a GPU that copies each call's trial states and results across). The dense one
(``dense=True``) evaluates all B states in every call and updates every per-state quantity by
``torch.where`` on masks: nothing in it reads a tensor on the host except the early-exit poll every
``sync_every`` calls (one read of two flags), and a state that needs a model between polls waits for the
next one. Its model builds evaluate every state (kept where one is needed), and what still waits for a
GPU is outside the loop's bookkeeping: the eigenvalue fix of an exact or difference Hessian
(``torch.linalg.eigh`` synchronises on CUDA, torch documents it), once per call that builds models,
and whatever the objective itself does (the effects' eager paths select rows; compiled they are dense).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from types import ModuleType
from typing import Protocol

import numpy as np
import torch
from torch import Tensor

from redsim.solvers import check_settings

ARMIJO_C = 1e-4
"""Sufficient-decrease constant of the line search."""
MAX_BACKTRACKS = 12
"""Rejected trials before a state's line search gives up (each next trial 1/10-1/2 of the last, :func:`_backtrack`)."""
HESSIAN_FLOOR = 1e-8
"""Smallest eigenvalue of an exact Hessian after the absolute-value fix, relative to its largest."""
BFGS_DAMPING = 0.2
"""Powell damping: the update keeps s.y >= BFGS_DAMPING s.H s, so the Hessian stays positive definite."""
NOISE_FACTOR = 100.0
"""Value changes below NOISE_FACTOR * eps * (|Phi| + force_scale * L) count as round-off."""
WARM_ITERATIONS = 8
"""Iterations a state may take from a warm model before its model is recomputed."""
HESSIANS = ("exact", "gauss_newton", "bfgs", "lagged", "lagged_fd")
"""The d x d Hessian models (module doc)."""


class BatchObjective(Protocol):
    """Phi_b(z) for the states of one step; ``index`` [k] (int64) picks which states z [k, d] belong to."""

    def value_and_grad(self, z: Tensor, index: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Phi [k], dPhi/dz [k, d] and the potential energy E [k] (detached; non-finite where Phi is)."""
        ...

    def exact_hessian(self, z: Tensor, index: Tensor) -> Tensor:
        """The exact d^2 Phi / dz^2 [k, d, d] (symmetric, possibly indefinite)."""
        ...

    def gauss_newton(self, z: Tensor, index: Tensor) -> Tensor:
        """J^T (M/h^2 + d^2E/dq^2) J [k, d, d]."""
        ...

    def metric(self, z: Tensor, index: Tensor) -> Tensor:
        """J^T M J / h^2 [k, d, d], positive definite where J has full rank."""
        ...

    def difference_hessian(self, z: Tensor, index: Tensor, grad: Tensor) -> Tensor:
        """(dPhi/dz(z + eps e_j) - grad) / eps per column j [k, d, d], from the gradient ``grad`` [k, d] at z."""
        ...


@dataclass(frozen=True)
class BatchResult:
    """Per-state outcome of :func:`minimize`, all [B] (``z`` [B, d]).

    Attributes:
        z: Last accepted iterate (finite wherever the start was).
        value: Phi at z [J].
        energy: The potential energy E at z [J] (the objective's third output).
        grad: dPhi/dz at z [B, d] (zero where ``finite`` is false).
        grad_norm: |dPhi/dz| at z.
        iterations: Accepted iterations, int64.
        converged: grad_norm <= tol * scale.
        stalled: The line search found no acceptable step before convergence.
        finite: Phi and its gradient were finite at the start (else z is the start, unchanged).
        model: The final d x d model Hessian [B, d, d] (a warm start for the next solve; NaN where
            none was built).
    """

    z: Tensor
    value: Tensor
    energy: Tensor
    grad: Tensor
    grad_norm: Tensor
    iterations: Tensor
    converged: Tensor
    stalled: Tensor
    finite: Tensor
    model: Tensor


Array = Tensor | np.ndarray
"""The loops' per-state quantities: torch tensors in the dense loop, numpy arrays on the host in the row loop (module
doc); the helpers below take either and return the same kind."""


def _xp(a: Array) -> ModuleType:
    """The array namespace of ``a``: numpy for an ndarray, torch for a tensor."""
    return np if isinstance(a, np.ndarray) else torch


def _finite(t: Array) -> Array:
    """``isfinite(t)`` as |t| < inf (NaN compares false): two ops where torch's ``isfinite`` dispatches four
    (abs, ne, eq, mul); the loops' tensors are small, so each op's fixed cost is what they cost."""
    return abs(t) < math.inf


def _pd_exact(hessian: Tensor) -> Tensor:
    """V |w| V^T with |w| floored at HESSIAN_FLOOR max|w| (all-zero stays zero)."""
    sym = 0.5 * (hessian + hessian.transpose(-1, -2))
    w, v = torch.linalg.eigh(sym)
    w = w.abs()
    w = torch.maximum(w, HESSIAN_FLOOR * w.amax(-1, keepdim=True))
    return (v * w.unsqueeze(-2)) @ v.transpose(-1, -2)


def _direction(hessian: Array, grad: Array, fallback: Array | None = None) -> Array:
    """-H^-1 g by Cholesky; states whose H is not positive definite use ``fallback`` [k, d, d] instead
    (None: none), and -g where that is not positive definite either.

    Host arrays: numpy's Cholesky as the test (it raises for the whole batch where one matrix is not positive
    definite), then one LU solve; where one is not, or with a fallback, torch's per-matrix ``cholesky_ex`` (the
    numpy path takes half the time of torch's on 1-8 rows, development measurement)."""
    if isinstance(hessian, np.ndarray):
        if fallback is None:
            try:
                np.linalg.cholesky(hessian)
                step = -np.linalg.solve(hessian, grad[..., None])[..., 0]
            except np.linalg.LinAlgError:
                pass
            else:
                return np.where(_finite(step), step, -grad)
        fallback = None if fallback is None else torch.from_numpy(fallback)
        return _direction(torch.from_numpy(hessian), torch.from_numpy(grad), fallback).numpy()
    chol, info = torch.linalg.cholesky_ex(hessian)
    usable = info == 0
    if fallback is not None:
        bad = ~usable
        chol2, info2 = torch.linalg.cholesky_ex(torch.where(bad[:, None, None], fallback, hessian))
        chol = torch.where(bad[:, None, None], chol2, chol)
        usable = usable | (info2 == 0)
    step = -torch.cholesky_solve(grad.unsqueeze(-1), chol).squeeze(-1)
    return torch.where(usable[:, None] & _finite(step), step, -grad)


def _norm(v: Array) -> Array:
    """|v| [k] of vectors v [k, d] (numpy's as sqrt(v . v), half the time of its ``vector_norm`` on a few rows)."""
    if isinstance(v, np.ndarray):
        return np.sqrt((v * v).sum(-1))
    return torch.linalg.vector_norm(v, dim=-1)


def _limit(step: Array, max_step: float | None) -> Array:
    """Steps [k, d] scaled down to length ``max_step`` where longer (None: unchanged)."""
    if max_step is None:
        return step
    length = _norm(step)
    return step * _xp(step).where(length > max_step, max_step / length, 1.0)[:, None]


def newton_step(model: Tensor, grad: Tensor, max_step: float | None = None) -> tuple[Tensor, Tensor]:
    """The model's Newton step -H^-1 g [k, d] of models H [k, d, d] and gradients g [k, d], at most ``max_step`` long
    (None: any length), and where it exists [k] (H positive definite and finite, the step finite; elsewhere 0)."""
    chol, info = torch.linalg.cholesky_ex(torch.nan_to_num(model))
    step = -torch.cholesky_solve(grad.unsqueeze(-1), chol).squeeze(-1)
    usable = (info == 0) & _finite(model).all(-1).all(-1) & _finite(step).all(-1)
    return torch.where(usable[:, None], _limit(step, max_step), torch.zeros_like(step)), usable


def _bfgs_update(hessian: Array, s: Array, y: Array) -> Array:
    """Damped (Powell) BFGS update of Hessians [k, d, d] with steps s [k, d] and gradient changes y [k, d]."""
    xp = _xp(hessian)
    hs = (hessian @ s[..., None])[..., 0]
    shs = (s * hs).sum(-1)
    sy = (s * y).sum(-1)
    theta = xp.where(sy >= BFGS_DAMPING * shs, 1.0, (1.0 - BFGS_DAMPING) * shs / (shs - sy))
    r = hs + theta[:, None] * (y - hs)
    sr = (s * r).sum(-1)
    ok = (shs > 0) & (sr > 0) & (sr < math.inf) & (shs < math.inf)  # positive and finite
    # H - hs hs^T / s.Hs + r r^T / s.r as one batched product [k, d, 2] x [k, 2, d] (rows not ok: unused)
    left = xp.stack([hs, r], -1)
    right = xp.stack([hs / -shs[:, None], r / sr[:, None]], -2)
    return xp.where(ok[:, None, None], hessian + left @ right, hessian)


def _backtrack(alpha: Array, slope: Array, rise: Array) -> Array:
    """Next trial step after a rejected one: the minimizer of the quadratic through Phi(0), Phi'(0) and
    Phi(alpha) (``rise`` = Phi(alpha) - Phi(0)), kept in [alpha / 10, alpha / 2]; alpha / 2 if not finite."""
    curvature = rise - slope * alpha
    guess = -slope * alpha * alpha / (2.0 * curvature)
    xp = _xp(alpha)
    guess = xp.where(_finite(guess) & (curvature > 0), guess, 0.5 * alpha)
    return xp.minimum(xp.maximum(guess, 0.1 * alpha), 0.5 * alpha)


_QUASI_NEWTON = ("bfgs", "lagged", "lagged_fd")


def _model(
    objective: BatchObjective, method: str, z: Tensor, index: Tensor, grad: Tensor, keep: Tensor | None = None
) -> Tensor:
    """The d x d model [k, d, d] of ``method`` at z [k, d] (gradient ``grad`` [k, d]) of the states ``index``.

    ``keep`` [k] (bool, or None: all): the rows that will be used; the others enter the eigenvalue fix as
    the identity (a dense build evaluates every row, and the eigensolver may refuse a non-finite one).
    """
    if method in ("exact", "lagged", "lagged_fd"):
        if method == "lagged_fd":
            raw = objective.difference_hessian(z, index, grad)
        else:
            raw = objective.exact_hessian(z, index)
        if keep is not None:
            raw = torch.where(keep[:, None, None], raw, torch.eye(z.shape[1], dtype=z.dtype, device=z.device))
        return _pd_exact(raw)
    if method == "gauss_newton":
        return objective.gauss_newton(z, index)
    return objective.metric(z, index)


def _fresh_model(
    objective: BatchObjective,
    method: str,
    z: Tensor,
    index: Tensor,
    grad: Tensor,
    iterations: Tensor,
    secant: tuple[Tensor, Tensor] | None,
    keep: Tensor | None = None,
) -> Tensor:
    """:func:`_model` of the states ``index`` at z [k, d]; "bfgs"'s J^T M J / h^2 of a state at its first
    iteration (``iterations`` [k]) also takes the secant update from ``secant`` [B, d] (see :func:`minimize`)."""
    fresh = _model(objective, method, z, index, grad, keep)
    if secant is not None and method == "bfgs":
        z_s, g_s = secant[0][index], secant[1][index]
        usable = torch.isfinite(g_s).all(-1)
        g_s = torch.where(usable[:, None], g_s, grad)
        fresh = torch.where((iterations == 0)[:, None, None], _bfgs_update(fresh, z - z_s, grad - g_s), fresh)
    return fresh


def _stale(model: Array, built: Array, iterations: Array, backtracked: Array, warm_refresh: bool = True) -> Array:
    """Which states [k] need a quasi-Newton model built before their next iteration: none there (a NaN
    model [k, d, d]), or, with ``warm_refresh``, a warm one (not ``built`` in this solve) that has taken
    WARM_ITERATIONS ``iterations`` or ``backtracked``."""
    missing = ~_finite(model).all(-1).all(-1)
    if not warm_refresh:
        return missing
    return missing | (~built & ((iterations >= WARM_ITERATIONS) | backtracked))


def _descent(model: Array, grad: Array, fallback: Array | None, max_step: float | None = None) -> tuple[Array, Array]:
    """The first step [k, d] of an iteration at gradients ``grad`` [k, d] with the model [k, d, d] (where it is not
    positive definite the ``fallback`` model, Gauss-Newton's metric, or None; -grad where that is not downhill either),
    at most ``max_step`` long, and its slope grad . step [k]."""
    direction = _direction(model, grad, fallback)
    direction = _limit(_xp(grad).where(((grad * direction).sum(-1) < 0)[:, None], direction, -grad), max_step)
    return direction, (grad * direction).sum(-1)


def _round_off(value: Array, noise: Array) -> Array:
    """The change [k] of Phi that is round-off at values ``value`` [k] with value noise ``noise`` [k]."""
    return noise + NOISE_FACTOR * float(_xp(value).finfo(value.dtype).eps) * abs(value)


def _judge(
    trial: tuple[Array, Array], here: tuple[Array, Array], alpha: Array, slope: Array, noise: Array
) -> tuple[Array, Array]:
    """(finite, accepted) [k] of trials with (Phi, dPhi/dz) ``trial`` from the iterates ``here``, step
    lengths ``alpha``, slopes and value round-off ``noise`` [k]: Armijo, or a round-off change that lowers |g|."""
    v_t, g_t = trial
    v_a, g_a = here
    finite = _finite(v_t) & _finite(g_t).all(-1)
    armijo = v_t <= v_a + ARMIJO_C * alpha * slope
    flat = (v_t - v_a) <= _round_off(v_a, noise)
    lower = _norm(g_t) < _norm(g_a)
    return finite, finite & (armijo | (flat & lower))


def _relearn(
    model: Array, step: Array, change: Array, grad: Array, bound: Array, max_step: float | None = None
) -> tuple[Array, Array, Array]:
    """A rejected but finite trial still measured the curvature along its ``step`` [k, d] (gradient
    ``change`` [k, d]): the BFGS-updated model [k, d, d], and the direction from it at the iterate's
    gradient ``grad`` [k, d] (a turned step, at most ``max_step`` and ``bound`` [k] long: the backtracked trial's
    length after a trial that rose beyond round-off, so such trials shrink as a backtracking search's do (an updated
    model's step alone could stay as long, every trial rising); inf after one that rose by round-off only, where the
    model's own step moves on and a shrinking one would barely move) with its slope [k]."""
    updated = _bfgs_update(model, step, change)
    fresh = _limit(_direction(updated, grad), max_step)
    length = _norm(fresh)
    fresh = _xp(model).where((length > bound)[:, None], fresh * (bound / length)[:, None], fresh)
    return updated, fresh, (grad * fresh).sum(-1)


@dataclass
class _Iterates:
    """What the solver carries per state; [B] (z, grad, step [B, d], model [B, d, d]).

    ``built``: the model was made in this solve (else it is warm, or not there yet); ``searching``: the
    state has a direction and a trial pending; ``alpha_used``: the step length of the last rejected trial.
    The line search of every state runs on its own clock: each call of the objective evaluates one trial of
    every active state, whether it is the first of an iteration or a backtrack (so a state backtracking
    does not hold the others' next iterations back). ``restarted``: the state's line search from its current
    iterate already failed once and restarted from a fresh model, or its model was built at this iterate
    (a restart would replay the same trials; module doc).
    """

    finite: Tensor
    z: Tensor
    value: Tensor
    grad: Tensor
    energy: Tensor
    iterations: Tensor
    stalled: Tensor
    model: Tensor
    built: Tensor
    backtracked: Tensor
    searching: Tensor
    step: Tensor
    slope: Tensor
    alpha: Tensor
    alpha_used: Tensor
    tries: Tensor
    restarted: Tensor

    def active(self, threshold: Array, max_iter: int) -> Array:
        """The states [B] still iterating: finite, not stalled, under max_iter and above the tolerance."""
        norm = _norm(self.grad)
        return self.finite & ~self.stalled & (self.iterations < max_iter) & (norm > threshold)


def _start(
    objective: BatchObjective,
    z0: Tensor,
    hessian: str,
    start: tuple[Tensor, Tensor, Tensor] | None,
    secant: tuple[Tensor, Tensor] | None,
    warm: Tensor | None,
) -> _Iterates:
    """The iterates at z0 [B, d] (non-finite starts zeroed, flagged), with the warm model (secant-updated)."""
    batch, d = z0.shape
    z = z0.clone()
    value, grad, energy = objective.value_and_grad(z, torch.arange(batch, device=z0.device)) if start is None else start
    finite = torch.isfinite(value) & torch.isfinite(grad).all(-1)
    value = torch.where(finite, value, torch.zeros_like(value))
    grad = torch.where(finite[:, None], grad, torch.zeros_like(grad))
    model = torch.full((batch, d, d), torch.nan, dtype=z.dtype, device=z.device)
    if warm is not None and hessian in _QUASI_NEWTON:
        model = torch.where(torch.isfinite(warm).all(-1).all(-1)[:, None, None], warm.to(z.dtype), model)
        if secant is not None:
            usable = torch.isfinite(secant[1]).all(-1)
            g_s = torch.where(usable[:, None], secant[1], grad)
            model = _bfgs_update(model, z - secant[0], grad - g_s)  # NaN rows stay NaN
    flags = torch.zeros(batch, dtype=torch.bool, device=z0.device)
    counts = torch.zeros(batch, dtype=torch.int64, device=z0.device)
    return _Iterates(
        finite=finite,
        z=z,
        value=value,
        grad=grad,
        energy=torch.where(finite, energy, torch.zeros_like(energy)),
        iterations=counts.clone(),
        stalled=flags.clone(),
        model=model,
        built=flags.clone(),
        backtracked=flags.clone(),
        searching=flags.clone(),
        step=torch.zeros_like(z),
        slope=torch.zeros_like(value),
        alpha=torch.ones_like(value),
        alpha_used=torch.ones_like(value),
        tries=counts.clone(),
        restarted=flags.clone(),
    )


@dataclass(frozen=True)
class _Problem:
    """What one solve is given (:func:`minimize`'s arguments): ``threshold`` = tol * scale [B], ``noise`` [B]."""

    objective: BatchObjective
    threshold: Tensor
    noise: Tensor
    max_iter: int
    hessian: str
    secant: tuple[Tensor, Tensor] | None
    max_step: float | None = None
    warm_refresh: bool = True


def _host(t: Tensor) -> np.ndarray:
    """``t`` as a numpy array on the host (no copy of a CPU tensor)."""
    return t.detach().cpu().numpy()


def _minimize_rows(problem: _Problem, it: _Iterates) -> None:
    """The row-selected iteration (updates ``it``): each call evaluates the active states only.

    The bookkeeping runs on the host in numpy: the iterates are numpy arrays for the solve (copied once each way), rows
    are selected and written back by fancy indexing, and only the objective's calls (and the models' builds) see
    torch tensors, on the iterates' device. The loop runs ~15-25 calls per vector step, most of them on 1-16 rows,
    where each op's fixed cost is what a call of the loop costs: ~0.5-2 us for a numpy op on such arrays against ~2-5
    for a torch op (development measurement: the damped BFGS update of 8 rows, d = 8, 27 against 88 us).
    """
    objective, hessian, secant, max_iter = problem.objective, problem.hessian, problem.secant, problem.max_iter
    max_step, warm_refresh = problem.max_step, problem.warm_refresh
    quasi_newton = hessian in _QUASI_NEWTON
    device = it.z.device

    def tensor(a: np.ndarray) -> Tensor:
        return torch.from_numpy(a).to(device)

    h = _Iterates(**{f.name: _host(getattr(it, f.name)).copy() for f in fields(_Iterates)})
    threshold, noise = _host(problem.threshold), _host(problem.noise)
    with np.errstate(all="ignore"):  # inf and NaN are the loop's values, as in torch
        for _ in range(_call_bound(max_iter)):
            index = np.flatnonzero(h.active(threshold, max_iter))
            if index.size == 0:  # the early exit
                break
            start_rows = index[~h.searching[index]]  # states starting an iteration: their model and direction
            if start_rows.size:
                need = start_rows
                if quasi_newton:
                    rows = start_rows
                    stale = _stale(h.model[rows], h.built[rows], h.iterations[rows], h.backtracked[rows], warm_refresh)
                    need = rows[stale]
                if need.size:
                    z_n, grad_n, iterations_n = tensor(h.z[need]), tensor(h.grad[need]), tensor(h.iterations[need])
                    fresh = _fresh_model(objective, hessian, z_n, tensor(need), grad_n, iterations_n, secant)
                    h.model[need] = _host(fresh)
                    h.built[need] = True
                    h.restarted[need] = True  # built at this iterate: a restart would replay its search
                grad_s = h.grad[start_rows]
                fallback = None
                if hessian == "gauss_newton":
                    fallback = _host(objective.metric(tensor(h.z[start_rows]), tensor(start_rows)))
                h.step[start_rows], h.slope[start_rows] = _descent(h.model[start_rows], grad_s, fallback, max_step)
                h.alpha[start_rows] = 1.0
                h.alpha_used[start_rows] = 1.0
                h.tries[start_rows] = 0
                h.searching[start_rows] = True
            z_a, v_a, g_a, noise_a = h.z[index], h.value[index], h.grad[index], noise[index]
            alpha_a, step_a, slope_a = h.alpha[index], h.step[index], h.slope[index]
            trial = z_a + alpha_a[:, None] * step_a
            v_t, g_t, e_t = (_host(t) for t in objective.value_and_grad(tensor(trial), tensor(index)))
            ok_finite, ok = _judge((v_t, g_t), (v_a, g_a), alpha_a, slope_a, noise_a)
            take = index[ok]
            if take.size:
                if quasi_newton:
                    h.model[take] = _bfgs_update(h.model[take], trial[ok] - z_a[ok], g_t[ok] - g_a[ok])
                h.z[take] = trial[ok]
                h.value[take] = v_t[ok]
                h.grad[take] = g_t[ok]
                h.energy[take] = e_t[ok]
                h.iterations[take] += 1
                h.searching[take] = False
                h.restarted[take] = False
            if take.size == index.size:  # every trial accepted
                continue
            # rejected trials: back off, or after MAX_BACKTRACKS trials of one iteration restart once, then give up
            rejected = ~ok
            rows = index[rejected]
            h.tries[rows] += 1
            more = h.tries[rows] < MAX_BACKTRACKS
            failed = rows[~more]
            if failed.size:
                first = ~h.restarted[failed] & quasi_newton  # a first failure from this iterate restarts
                if first.any():
                    _restart(h, failed[first])
                h.stalled[failed[~first]] = True
                h.searching[failed] = False
            going = rejected.copy()  # positions in index of the rows that back off
            going[rejected] = more
            rows = index[going]
            if rows.size == 0:
                continue
            h.backtracked[rows] = True
            rise = np.where(ok_finite, v_t - v_a, np.inf)
            h.alpha[rows] = _backtrack(h.alpha[rows], h.slope[rows], rise[going])
            if quasi_newton:
                learn = going & ok_finite  # finite trials that were rejected: the model learns from them
                redo = index[learn]
                if redo.size:
                    grad_r, alpha_r, step_r = h.grad[redo], h.alpha[redo], h.step[redo]
                    step = h.alpha_used[redo][:, None] * step_r
                    uphill = rise[learn] > _round_off(v_a[learn], noise_a[learn])
                    bound = np.where(uphill, alpha_r * _norm(step_r), np.inf)
                    updated, fresh, fresh_slope = _relearn(
                        h.model[redo], step, g_t[learn] - grad_r, grad_r, bound, max_step
                    )
                    h.model[redo] = updated
                    turned = fresh_slope < 0
                    good = redo[turned]
                    h.step[good] = fresh[turned]
                    h.slope[good] = fresh_slope[turned]
                    h.alpha[good] = 1.0
            h.alpha_used[rows] = h.alpha[rows]
    for f in fields(_Iterates):
        setattr(it, f.name, tensor(getattr(h, f.name)))


def _call_bound(max_iter: int) -> int:
    """Most objective calls a solve needs: max_iter iterations of a failed line search, its restart's and the
    accepted trial (2 MAX_BACKTRACKS + 1 calls each; module doc)."""
    return max_iter * (2 * MAX_BACKTRACKS + 1)


def _restart(it: _Iterates, rows: Array) -> None:
    """States ``rows`` start their line search again at the same iterate from a model built afresh (module doc)."""
    it.model[rows] = math.nan
    it.tries[rows] = 0
    it.restarted[rows] = True


def _poll(active: Tensor, waiting: Tensor) -> tuple[bool, bool]:
    """The dense loop's one host read: (is any state active, is any waiting for a model) of masks [B]."""
    running, building = torch.stack([active.any(), waiting.any()]).tolist()
    return running, building


def _minimize_dense(problem: _Problem, it: _Iterates, sync_every: int | None) -> None:
    """The dense masked iteration (updates ``it``): every call evaluates all B states and every update
    is a ``torch.where`` on masks, so nothing waits for the device except :func:`_poll` every
    ``sync_every`` calls (None: never; the loop then runs its whole bound).

    Models are built (for every state, kept where one is needed) in the calls after a poll that saw a
    state needing one: every such call for "exact" and "gauss_newton", the first for the quasi-Newton
    models (every call without polls). A state that comes to need one when no call builds waits for the
    next poll (its own sequence of iterates is unchanged: only the call it happens in moves). With
    ``sync_every`` 1 the calls are the row-selected loop's.
    """
    objective, hessian, secant, max_iter = problem.objective, problem.hessian, problem.secant, problem.max_iter
    max_step, warm_refresh = problem.max_step, problem.warm_refresh
    quasi_newton = hessian in _QUASI_NEWTON
    index = torch.arange(it.z.shape[0], device=it.z.device)
    building = True
    for call in range(_call_bound(max_iter) * (sync_every or 1)):
        active = it.active(problem.threshold, max_iter)
        starting = active & ~it.searching
        need = starting
        if quasi_newton:
            need = starting & _stale(it.model, it.built, it.iterations, it.backtracked, warm_refresh)
        if sync_every is not None and call % sync_every == 0:
            running, building = _poll(active, need)
            if not running:  # the early exit
                break
        build = building
        if build:
            fresh = _fresh_model(objective, hessian, it.z, index, it.grad, it.iterations, secant, keep=need)
            it.model = torch.where(need[:, None, None], fresh, it.model)
            it.built = it.built | need
            it.restarted = it.restarted | need  # built at this iterate: a restart would replay its search
            # exact and Gauss-Newton need a model every iteration; a quasi-Newton state rarely (a cold
            # start, a warm model gone stale), so until the next poll asks again, the calls build none
            building = sync_every is None or not quasi_newton
        go = starting if build else starting & ~need
        if build or quasi_newton:  # (exact, Gauss-Newton: no state goes without a model)
            fallback = objective.metric(it.z, index) if hessian == "gauss_newton" else None
            direction, slope = _descent(it.model, it.grad, fallback, max_step)
            it.step = torch.where(go[:, None], direction, it.step)
            it.slope = torch.where(go, slope, it.slope)
            it.alpha = torch.where(go, 1.0, it.alpha)
            it.alpha_used = torch.where(go, 1.0, it.alpha_used)
            it.tries = torch.where(go, 0, it.tries)
            it.searching = it.searching | go
        trying = active & it.searching
        trial = torch.where(trying[:, None], it.z + it.alpha[:, None] * it.step, it.z)
        v_t, g_t, e_t = objective.value_and_grad(trial, index)
        ok_finite, ok = _judge((v_t, g_t), (it.value, it.grad), it.alpha, it.slope, problem.noise)
        take = trying & ok
        if quasi_newton:
            updated = _bfgs_update(it.model, trial - it.z, g_t - it.grad)
            it.model = torch.where(take[:, None, None], updated, it.model)
        rise = torch.where(ok_finite, v_t - it.value, torch.full_like(v_t, torch.inf))
        change = g_t - it.grad
        it.z = torch.where(take[:, None], trial, it.z)
        it.value = torch.where(take, v_t, it.value)
        it.grad = torch.where(take[:, None], g_t, it.grad)
        it.energy = torch.where(take, e_t, it.energy)
        it.iterations = it.iterations + take
        it.searching = it.searching & ~take
        it.restarted = it.restarted & ~take
        # rejected trials: back off, or after MAX_BACKTRACKS trials of one iteration restart once, then give up
        rejected = trying & ~ok
        it.tries = it.tries + rejected
        give_up = rejected & (it.tries >= MAX_BACKTRACKS)
        again = give_up & ~it.restarted & quasi_newton
        it.model = torch.where(again[:, None, None], torch.nan, it.model)
        it.tries = torch.where(again, 0, it.tries)
        it.restarted = it.restarted | again
        it.stalled = it.stalled | (give_up & ~again)
        it.searching = it.searching & ~give_up
        back = rejected & ~give_up
        it.backtracked = it.backtracked | back
        it.alpha = torch.where(back, _backtrack(it.alpha, it.slope, rise), it.alpha)
        if quasi_newton:
            learn = back & ok_finite
            step = it.alpha_used[:, None] * it.step
            uphill = rise > _round_off(it.value, problem.noise)
            bound = torch.where(uphill, it.alpha * torch.linalg.vector_norm(it.step, dim=-1), torch.inf)
            updated, fresh, fresh_slope = _relearn(it.model, step, change, it.grad, bound, max_step)
            it.model = torch.where(learn[:, None, None], updated, it.model)
            good = learn & (fresh_slope < 0)
            it.step = torch.where(good[:, None], fresh, it.step)
            it.slope = torch.where(good, fresh_slope, it.slope)
            it.alpha = torch.where(good, 1.0, it.alpha)
        it.alpha_used = torch.where(back, it.alpha, it.alpha_used)


def check_sync_every(sync_every: int | None) -> None:
    """Raise ValueError unless ``sync_every`` (the dense loop's calls between early exits) is None or an int >= 1."""
    if sync_every is not None and (isinstance(sync_every, bool) or int(sync_every) != sync_every or sync_every < 1):
        raise ValueError(f"sync_every must be None or an integer >= 1, got {sync_every!r}")


def check_max_step(max_step: float | None) -> None:
    """Raise ValueError unless ``max_step`` (the longest latent step of a trial) is None or a finite number > 0."""
    if max_step is None:
        return
    number = isinstance(max_step, (int, float)) and not isinstance(max_step, bool)
    if not (number and math.isfinite(max_step) and max_step > 0):
        raise ValueError(f"max_step must be None or a finite number > 0 (latent units), got {max_step!r}")


def minimize(
    objective: BatchObjective,
    z0: Tensor,
    scale: Tensor,
    value_noise: Tensor,
    *,
    tol: float,
    max_iter: int,
    hessian: str = "bfgs",
    start: tuple[Tensor, Tensor, Tensor] | None = None,
    secant: tuple[Tensor, Tensor] | None = None,
    warm: Tensor | None = None,
    dense: bool = False,
    sync_every: int | None = 1,
    max_step: float | None = None,
    warm_refresh: bool = True,
) -> BatchResult:
    """Minimize Phi_b over z_b for every state b from z0 [B, d].

    Args:
        objective: The per-state objective.
        z0: Starting latents [B, d].
        scale: Per-state gradient scale [B]: converged when |dPhi/dz| <= tol * scale.
        value_noise: Per-state value round-off [B] (the line search's noise level) [J].
        tol: Relative gradient tolerance.
        max_iter: Most accepted iterations per state.
        hessian: One of :data:`HESSIANS`.
        start: (Phi, dPhi/dz, E) at z0 if the caller has them (else they are evaluated).
        secant: (z_s, dPhi/dz at z_s) [B, d] of another point: the quasi-Newton models take one BFGS
            update from it (s = z0 - z_s) before the first step, of a warm model or of "bfgs"'s J^T M J / h^2.
        warm: A starting model [B, d, d] for the quasi-Newton models (rows with a non-finite entry
            build their own); ignored by "exact" and "gauss_newton".
        dense: Iterate densely (module doc): every call evaluates all B states, no per-call row
            selection; the same per-state iterates as the row-selected loop, to round-off.
        sync_every: With ``dense``: check for the early exit (one host read) every this many calls;
            None: never (every call also builds the models of the states that need one, and the loop
            runs all max_iter * (2 * MAX_BACKTRACKS + 1) calls). Ignored without ``dense``.
        max_step: The longest step |dz| an iteration's first trial (and a turned one after a rejection)
            may take: longer directions are scaled down to it (a trust radius in latent units; None: no limit).
        warm_refresh: Rebuild a ``warm`` model after WARM_ITERATIONS iterations or a backtrack (default);
            False keeps BFGS-updating it (a model is still built where none is given, and where a line search
            fails: the restart, module doc).

    Returns:
        The :class:`BatchResult`.

    Raises:
        ValueError: an unknown ``hessian``, a ``tol`` that is not a finite number > 0 or a ``max_iter`` that is not
            an integer >= 1 (a NaN tol stopped every state at once, neither converged nor stalled), a ``sync_every``
            that is not None or an integer >= 1, or a ``max_step`` that is not None or a finite number > 0.
    """
    if hessian not in HESSIANS:
        raise ValueError(f"unknown hessian {hessian!r}; valid: {list(HESSIANS)}")
    tol, max_iter = check_settings(tol, max_iter)
    check_sync_every(sync_every)
    check_max_step(max_step)
    it = _start(objective, z0, hessian, start, secant, warm)
    problem = _Problem(objective, tol * scale, value_noise, max_iter, hessian, secant, max_step, bool(warm_refresh))
    if dense:
        _minimize_dense(problem, it, sync_every)
    else:
        _minimize_rows(problem, it)
    grad_norm = torch.linalg.vector_norm(it.grad, dim=-1)
    converged = it.finite & (grad_norm <= problem.threshold)
    stalled = it.stalled & ~converged
    return BatchResult(
        it.z, it.value, it.energy, it.grad, grad_norm, it.iterations, converged, stalled, it.finite, it.model
    )


__all__ = [
    "HESSIANS",
    "WARM_ITERATIONS",
    "BatchObjective",
    "BatchResult",
    "check_max_step",
    "check_sync_every",
    "minimize",
    "newton_step",
]
