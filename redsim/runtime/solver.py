"""Batched minimization over latent states: Newton-type directions in z (d x d) and a masked line search.

Every state b of a batch [B, d] is minimized on its own; they share only the calls. Each iteration
works on the states that are still active (neither converged nor stalled) and gathers them into
one call of the objective. The d x d model Hessian comes from one of :data:`HESSIANS`:

- ``"exact"``: the exact Hessian of Phi in z (map curvature included) by double backward over d
  copies of each state, eigenvalues replaced by their absolute value (floored), as the reference
  :class:`redsim.integrators.LatentSpace` does.
- ``"gauss_newton"``: J^T (M/h^2 + d^2E/dq^2) J with J = dq/dz from forward mode (``torch.func.jvp``)
  and the q-space Hessian applied to J's columns (double backward over q), map curvature dropped.
- ``"bfgs"``: a damped BFGS update of the Hessian, started from J^T M J / h^2 (forward-mode J).
- ``"lagged"``: the exact Hessian at the first iterate of a step, then BFGS updates of it.
- ``"lagged_fd"``: as "lagged", with the first Hessian from forward differences of the gradient
  (d gradients at z + eps e_k in one call: no double backward, so it also runs compiled).

The quasi-Newton models ("bfgs", "lagged", "lagged_fd") may start from a ``warm`` model, e.g. the
last step's final model (what :class:`redsim.runtime.LatentStepper` carries from step to step, as
MuJoCo's solver carries ``qacc_warmstart``): the step then costs no Hessian evaluation unless a
state is still unconverged after :data:`WARM_ITERATIONS` iterations or backtracks from it, which
recomputes its model at the current iterate once.

The line search is Armijo backtracking per state: a trial with a non-finite value or gradient is
rejected like an uphill one; a trial whose value change is at round-off level is accepted if it
lowers |g|. A state whose line search fails keeps its last accepted (finite) iterate and stops
(``stalled``). Only the active states are evaluated, which is what a CPU wants; the price is that choosing
them (``nonzero``, boolean selections of rows) waits for the device once per selection on a GPU, where
a dense masked iteration would not.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

ARMIJO_C = 1e-4
"""Sufficient-decrease constant of the line search."""
MAX_BACKTRACKS = 12
"""Step halvings before a state's line search gives up (the last trial is 2^-11 of the first)."""
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
    grad_norm: Tensor
    iterations: Tensor
    converged: Tensor
    stalled: Tensor
    finite: Tensor
    model: Tensor


def _pd_exact(hessian: Tensor) -> Tensor:
    """V |w| V^T with |w| floored at HESSIAN_FLOOR max|w| (all-zero stays zero)."""
    sym = 0.5 * (hessian + hessian.transpose(-1, -2))
    w, v = torch.linalg.eigh(sym)
    w = w.abs()
    w = torch.maximum(w, HESSIAN_FLOOR * w.amax(-1, keepdim=True))
    return (v * w.unsqueeze(-2)) @ v.transpose(-1, -2)


def _direction(hessian: Tensor, grad: Tensor, fallback: Tensor | None = None) -> Tensor:
    """-H^-1 g by Cholesky; states whose H is not positive definite use ``fallback`` [k, d, d] instead
    (None: none), and -g where that is not positive definite either."""
    chol, info = torch.linalg.cholesky_ex(hessian)
    usable = info == 0
    if fallback is not None:
        bad = ~usable
        chol2, info2 = torch.linalg.cholesky_ex(torch.where(bad[:, None, None], fallback, hessian))
        chol = torch.where(bad[:, None, None], chol2, chol)
        usable = usable | (info2 == 0)
    step = -torch.cholesky_solve(grad.unsqueeze(-1), chol).squeeze(-1)
    return torch.where(usable[:, None] & torch.isfinite(step), step, -grad)


def _bfgs_update(hessian: Tensor, s: Tensor, y: Tensor) -> Tensor:
    """Damped (Powell) BFGS update of Hessians [k, d, d] with steps s [k, d] and gradient changes y [k, d]."""
    hs = (hessian @ s.unsqueeze(-1)).squeeze(-1)
    shs = (s * hs).sum(-1)
    sy = (s * y).sum(-1)
    theta = torch.where(sy >= BFGS_DAMPING * shs, 1.0, (1.0 - BFGS_DAMPING) * shs / (shs - sy))
    r = hs + theta.unsqueeze(-1) * (y - hs)
    sr = (s * r).sum(-1)
    ok = (shs > 0) & (sr > 0) & torch.isfinite(sr) & torch.isfinite(shs)
    # H - hs hs^T / s.Hs + r r^T / s.r as one batched product [k, d, 2] x [k, 2, d] (rows not ok: unused)
    left = torch.stack([hs, r], -1)
    right = torch.stack([hs / -shs.unsqueeze(-1), r / sr.unsqueeze(-1)], -2)
    return torch.where(ok[:, None, None], torch.baddbmm(hessian, left, right), hessian)


def _model(objective: BatchObjective, method: str, z: Tensor, index: Tensor, grad: Tensor) -> Tensor:
    if method in ("exact", "lagged"):
        return _pd_exact(objective.exact_hessian(z, index))
    if method == "lagged_fd":
        return _pd_exact(objective.difference_hessian(z, index, grad))
    if method == "gauss_newton":
        return objective.gauss_newton(z, index)
    return objective.metric(z, index)


def _backtrack(alpha: Tensor, slope: Tensor, rise: Tensor) -> Tensor:
    """Next trial step after a rejected one: the minimizer of the quadratic through Phi(0), Phi'(0) and
    Phi(alpha) (``rise`` = Phi(alpha) - Phi(0)), kept in [alpha / 10, alpha / 2]; alpha / 2 if not finite."""
    curvature = rise - slope * alpha
    guess = -slope * alpha * alpha / (2.0 * curvature)
    guess = torch.where(torch.isfinite(guess) & (curvature > 0), guess, 0.5 * alpha)
    return torch.minimum(torch.maximum(guess, 0.1 * alpha), 0.5 * alpha)


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

    Returns:
        The :class:`BatchResult`.
    """
    if hessian not in HESSIANS:
        raise ValueError(f"unknown hessian {hessian!r}; valid: {list(HESSIANS)}")
    batch = z0.shape[0]
    all_index = torch.arange(batch, device=z0.device)
    z = z0.clone()
    value, grad, energy = objective.value_and_grad(z, all_index) if start is None else start
    finite = torch.isfinite(value) & torch.isfinite(grad).all(-1)
    value = torch.where(finite, value, torch.zeros_like(value))
    grad = torch.where(finite[:, None], grad, torch.zeros_like(grad))
    energy = torch.where(finite, energy, torch.zeros_like(energy))
    threshold = tol * scale
    eps = torch.finfo(z.dtype).eps
    iterations = torch.zeros(batch, dtype=torch.int64, device=z0.device)
    stalled = torch.zeros(batch, dtype=torch.bool, device=z0.device)
    quasi_newton = hessian in ("bfgs", "lagged", "lagged_fd")
    d = z.shape[1]
    model = torch.full((batch, d, d), torch.nan, dtype=z.dtype, device=z.device)
    # built: the model of this row was made in this solve (else it is warm or not there yet)
    built = torch.zeros(batch, dtype=torch.bool, device=z0.device)
    if warm is not None and quasi_newton:
        model = torch.where(torch.isfinite(warm).all(-1).all(-1)[:, None, None], warm.to(z.dtype), model)
        if secant is not None:
            usable = torch.isfinite(secant[1]).all(-1)
            g_s = torch.where(usable[:, None], secant[1], grad)
            model = _bfgs_update(model, z - secant[0], grad - g_s)  # NaN rows stay NaN
    backtracked = torch.zeros(batch, dtype=torch.bool, device=z0.device)
    # the line search of every state runs on its own clock: each call of the objective evaluates one
    # trial of every active state, whether it is the first of an iteration or a backtrack (so a state
    # backtracking does not hold the others' next iterations back)
    searching = torch.zeros(batch, dtype=torch.bool, device=z0.device)  # has a direction and a trial pending
    step = torch.zeros_like(z)
    slope = torch.zeros_like(value)
    alpha = torch.ones_like(value)
    alpha_used = torch.ones_like(value)  # the step length of the last rejected trial
    tries = torch.zeros(batch, dtype=torch.int64, device=z0.device)
    for _ in range(max_iter * (MAX_BACKTRACKS + 1)):
        active = finite & ~stalled & (iterations < max_iter) & (torch.linalg.vector_norm(grad, dim=-1) > threshold)
        index = torch.nonzero(active).squeeze(-1)
        if index.numel() == 0:  # the early exit (one host sync per call of the objective)
            break
        start_rows = index[~searching[index]]  # states starting an iteration: their model and direction
        if start_rows.numel():
            if hessian in ("exact", "gauss_newton"):
                model[start_rows] = _model(objective, hessian, z[start_rows], start_rows, grad[start_rows])
            else:
                missing = ~torch.isfinite(model[start_rows]).all(-1).all(-1)
                stale = ~built[start_rows] & ((iterations[start_rows] >= WARM_ITERATIONS) | backtracked[start_rows])
                rebuild = start_rows[missing | stale]
                if rebuild.numel():
                    fresh = _model(objective, hessian, z[rebuild], rebuild, grad[rebuild])
                    if secant is not None and hessian == "bfgs":  # J^T M J / h^2 built at the start: the secant
                        z_s, g_s = secant[0][rebuild], secant[1][rebuild]
                        usable = torch.isfinite(g_s).all(-1)
                        g_s = torch.where(usable[:, None], g_s, grad[rebuild])
                        fresh = torch.where(
                            (iterations[rebuild] == 0)[:, None, None],
                            _bfgs_update(fresh, z[rebuild] - z_s, grad[rebuild] - g_s),
                            fresh,
                        )
                    model[rebuild] = fresh
                    built[rebuild] = True
            z_r, g_r = z[start_rows], grad[start_rows]
            fallback = objective.metric(z_r, start_rows) if hessian == "gauss_newton" else None
            direction = _direction(model[start_rows], g_r, fallback)
            direction = torch.where(((g_r * direction).sum(-1) < 0)[:, None], direction, -g_r)
            step[start_rows] = direction
            slope[start_rows] = (g_r * direction).sum(-1)
            alpha[start_rows] = 1.0
            alpha_used[start_rows] = 1.0
            tries[start_rows] = 0
            searching[start_rows] = True
        z_a, v_a, g_a = z[index], value[index], grad[index]
        trial = z_a + alpha[index, None] * step[index]
        v_t, g_t, e_t = objective.value_and_grad(trial, index)
        ok_finite = torch.isfinite(v_t) & torch.isfinite(g_t).all(-1)
        armijo = v_t <= v_a + ARMIJO_C * alpha[index] * slope[index]
        noise = (v_t - v_a) <= value_noise[index] + NOISE_FACTOR * eps * v_a.abs()
        lower = torch.linalg.vector_norm(g_t, dim=-1) < torch.linalg.vector_norm(g_a, dim=-1)
        ok = ok_finite & (armijo | (noise & lower))
        take = index[ok]
        if quasi_newton and take.numel():
            model[take] = _bfgs_update(model[take], trial[ok] - z_a[ok], g_t[ok] - g_a[ok])
        z[take], value[take], grad[take], energy[take] = trial[ok], v_t[ok], g_t[ok], e_t[ok]
        iterations[take] += 1
        searching[take] = False
        # rejected trials: back off, or give up after MAX_BACKTRACKS trials of one iteration
        rejected = ~ok
        rows = index[rejected]
        if rows.numel() == 0:
            continue
        tries[rows] += 1
        more = tries[rows] < MAX_BACKTRACKS
        stalled[rows[~more]] = True
        searching[rows[~more]] = False
        rows = rows[more]
        backtracked[rows] = True
        rise = torch.where(ok_finite, v_t - v_a, torch.full_like(v_t, torch.inf))[rejected][more]
        alpha[rows] = _backtrack(alpha[rows], slope[rows], rise)
        # a rejected but finite trial still measured the curvature along its step (quasi-Newton): update
        # the model with it and solve again from the same point (a shorter, turned step)
        learn = (ok_finite & ~ok)[rejected][more] & quasi_newton
        redo = rows[learn]
        if redo.numel():
            change = g_t[rejected][more][learn] - grad[redo]
            h_new = _bfgs_update(model[redo], alpha_used[redo, None] * step[redo], change)
            model[redo] = h_new
            fresh = _direction(h_new, grad[redo])
            fresh_slope = (grad[redo] * fresh).sum(-1)
            good = redo[fresh_slope < 0]
            step[good] = fresh[fresh_slope < 0]
            slope[good] = fresh_slope[fresh_slope < 0]
            alpha[good] = 1.0
        alpha_used[rows] = alpha[rows]
    grad_norm = torch.linalg.vector_norm(grad, dim=-1)
    converged = finite & (grad_norm <= threshold)
    return BatchResult(z, value, energy, grad_norm, iterations, converged, stalled & ~converged, finite, model)


__all__ = ["HESSIANS", "WARM_ITERATIONS", "BatchObjective", "BatchResult", "minimize"]
