"""Minimizers for the smooth scalar objectives of the integrators (incremental and static potentials).

An :class:`Objective` gives its value and gradient at coordinates u (torch, float64), a
positive semi-definite Hessian approximation (projected Newton) and an SPD ``metric`` with
the units of that Hessian (e.g. M/h^2), which serves as the Levenberg shift and as the
L-BFGS preconditioner. The minimizers are plain functions in :data:`MINIMIZERS`; each
returns the minimizer and a :class:`SolveInfo`, and never reports convergence it did not
reach.

Convergence rule (both minimizers)::

    |g(u)|_2 <= max(tol * max(|g(u_0)|_2, objective.force_scale), objective.gradient_noise)

``force_scale`` [N, or the gradient's unit] is an explicit characteristic force of the
problem that does not depend on how good the initial guess is (a warm start near the
solution must not demand a tighter absolute residual than a cold one), and
``gradient_noise`` is the residual below which float64 round-off dominates; see the
objectives in :mod:`redsim.integrators` for the concrete choices.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch
from torch import Tensor

logger = logging.getLogger(__name__)

ARMIJO_C = 1e-4
"""Sufficient-decrease constant of the backtracking line search."""
MAX_BACKTRACKS = 40
"""Step halvings before a line search gives up (the last step is 2^-39 of the first)."""
MAX_SHIFTS = 30
"""Levenberg shift increases (x10 each) before Newton gives up on an iteration."""
SHIFT_FLOOR = 1e-8
"""First non-zero Levenberg shift, relative to the ratio of the Hessian and metric diagonals."""
ROUNDOFF_DECREASE = 64.0 * float(np.finfo(np.float64).eps)
"""Relative energy change treated as round-off: such a step is accepted if it lowers |g|."""


@dataclass(frozen=True)
class SolveInfo:
    """What a minimization did.

    Attributes:
        converged: True only when the gradient met the convergence rule of this module.
        iterations: Accepted iterations (Newton or L-BFGS steps).
        grad_norm: |g|_2 at the returned point [the gradient's unit, N for positions].
        energy: Objective value at the returned point [J].
        message: Human-readable outcome, with the residual and the threshold.
        history: Objective value [J] at the initial guess and after each accepted iteration.
    """

    converged: bool
    iterations: int
    grad_norm: float
    energy: float
    message: str
    history: tuple[float, ...] = ()


class ConvergenceError(RuntimeError):
    """A strict solve did not converge; ``info`` holds its :class:`SolveInfo`."""

    def __init__(self, info: SolveInfo) -> None:
        super().__init__(f"minimization did not converge: {info.message}")
        self.info = info


class Objective(Protocol):
    """A smooth objective over coordinates u of shape [m] (float64).

    Attributes:
        force_scale: Characteristic gradient magnitude (>= 0) of the problem, see the module doc.
        gradient_noise: Gradient norm (>= 0) at which float64 round-off dominates.
        value_noise: Objective change [J] (>= 0) below which float64 round-off of the value dominates
            (the value is a sum of much larger terms, e.g. load work and elastic energy).
        max_step: Largest move of one step of either minimizer (a trust radius; ``math.inf`` for none): of the
            step's largest entry, or of the objective's ``largest_move(u, direction)`` where it has that method.

    An objective with a method ``visit(u)`` is shown each point the minimizer accepts, in order (not the start).
    """

    force_scale: float
    gradient_noise: float
    value_noise: float
    max_step: float

    def value_and_grad(self, u: Tensor) -> tuple[float, Tensor]:
        """Objective value [J] and gradient, shape [m], at u [m]."""
        ...

    def hessian(self, u: Tensor) -> Any:
        """PSD Hessian (approximation) at u: a scipy sparse matrix or an array, shape [m, m]."""
        ...

    def metric(self, u: Tensor) -> Any:
        """SPD matrix [m, m] with the Hessian's units (Levenberg shift, L-BFGS preconditioner)."""
        ...


Minimizer = Callable[..., tuple[Tensor, SolveInfo]]


@dataclass(frozen=True)
class _Point:
    u: Tensor
    value: float
    grad: Tensor

    @property
    def grad_norm(self) -> float:
        return float(torch.linalg.vector_norm(self.grad))

    @property
    def finite(self) -> bool:
        """Value, gradient and its norm finite (entries near the dtype's limit overflow the norm)."""
        return math.isfinite(self.value) and bool(torch.isfinite(self.grad).all()) and math.isfinite(self.grad_norm)


def convergence_threshold(objective: Objective, tol: float, initial_grad_norm: float) -> float:
    """The gradient norm below which a minimization counts as converged (module doc)."""
    return max(tol * max(initial_grad_norm, objective.force_scale), objective.gradient_noise)


def _evaluate(objective: Objective, u: Tensor) -> _Point:
    value, grad = objective.value_and_grad(u)
    return _Point(u.detach(), float(value), grad.detach())


def _line_search(objective: Objective, point: _Point, direction: Tensor) -> _Point | None:
    """Backtracking (Armijo) from the full step; None if no acceptable step was found.

    Trial points with a non-finite value or gradient are rejected. A step whose energy change
    is at round-off level (where Armijo cannot decide) is accepted if it lowers |g|.
    """
    slope = float(point.grad @ direction)
    if not slope < 0.0:
        return None
    alpha = 1.0
    for _ in range(MAX_BACKTRACKS):
        trial = _evaluate(objective, point.u + alpha * direction)
        if trial.finite:
            if trial.value <= point.value + ARMIJO_C * alpha * slope:
                return trial
            noise = max(ROUNDOFF_DECREASE * max(abs(point.value), abs(trial.value)), objective.value_noise)
            if trial.value - point.value <= noise and trial.grad_norm < point.grad_norm:
                return trial
        alpha *= 0.5
    return None


def _factorize(matrix: Any) -> scipy.sparse.linalg.SuperLU | None:
    """Sparse LU of a symmetric matrix (symmetric ordering, diagonal pivots); None if singular."""
    try:
        return scipy.sparse.linalg.splu(
            scipy.sparse.csc_matrix(matrix),
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
    except RuntimeError:
        return None


def _solve(factor: scipy.sparse.linalg.SuperLU, rhs: Tensor) -> Tensor | None:
    out = factor.solve(rhs.detach().cpu().numpy().astype(np.float64))
    if not np.all(np.isfinite(out)):
        return None
    return torch.from_numpy(out).to(dtype=rhs.dtype, device=rhs.device)


def _accept(objective: Objective, point: _Point, history: list[float]) -> None:
    """Record an accepted point: its value in ``history``; the point to the objective's ``visit(u)``, if it has one."""
    history.append(point.value)
    visit = getattr(objective, "visit", None)
    if visit is not None:
        visit(point.u)


def _result(point: _Point, converged: bool, iterations: int, history: list[float], message: str) -> SolveInfo:
    return SolveInfo(converged, iterations, point.grad_norm, point.value, message, tuple(history))


def check_settings(tol: Any, max_iter: Any) -> tuple[float, int]:
    """``tol`` as a finite float > 0 and ``max_iter`` as an int >= 1, each a real number (not a bool or a string);
    a ValueError otherwise (an inf ``max_iter`` was an OverflowError, a string ``tol`` a TypeError)."""
    real = (int, float, np.integer, np.floating)
    if isinstance(tol, bool) or not isinstance(tol, real) or not (math.isfinite(tol) and tol > 0.0):
        raise ValueError(f"tol must be finite and > 0, got {tol!r}")
    whole = isinstance(max_iter, real) and not isinstance(max_iter, bool) and math.isfinite(max_iter)
    if not (whole and int(max_iter) == max_iter and max_iter >= 1):
        raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")
    return float(tol), int(max_iter)


def _start(objective: Objective, u0: Tensor, tol: float, max_iter: int) -> tuple[_Point, float]:
    check_settings(tol, max_iter)
    if u0.ndim != 1:
        raise ValueError(f"u0 must have shape [m], got {tuple(u0.shape)}")
    point = _evaluate(objective, u0.detach().clone())
    threshold = convergence_threshold(objective, tol, point.grad_norm)
    if not math.isfinite(threshold):  # a force scale past the dtype's range (absurd loads): nothing can converge
        threshold = -math.inf
    return point, threshold


class _Levenberg:
    """Newton directions from H + shift * metric, raising the shift until a step is accepted.

    ``factor`` holds the factorization behind the last accepted step (None before one), for
    chord steps that reuse it.
    """

    def __init__(self) -> None:
        self.shift = 0.0
        self.floor = 0.0
        self.metric: Any = None
        self.factor: scipy.sparse.linalg.SuperLU | None = None

    def step(self, objective: Objective, point: _Point, hessian: Any) -> _Point | None:
        hessian = scipy.sparse.csc_matrix(hessian)
        for _ in range(MAX_SHIFTS):
            matrix = hessian if self.shift == 0.0 else hessian + self.shift * self.metric
            factor = _factorize(matrix)
            direction = None if factor is None else _clipped(objective, _solve(factor, -point.grad), point.u)
            trial = None if direction is None else _line_search(objective, point, direction)
            if trial is not None:
                self.shift = 0.0 if self.shift <= self.floor else max(self.shift / 10.0, self.floor)
                self.factor = factor
                return trial
            self._raise(objective, point, hessian)
        return None

    def _raise(self, objective: Objective, point: _Point, hessian: Any) -> None:
        if self.metric is None:
            self.metric = scipy.sparse.csc_matrix(objective.metric(point.u))
            h_diag = float(np.mean(np.abs(hessian.diagonal())))
            m_diag = float(np.mean(np.abs(self.metric.diagonal())))
            self.floor = SHIFT_FLOOR * (h_diag / m_diag if h_diag > 0.0 and m_diag > 0.0 else 1.0)
        self.shift = self.floor if self.shift == 0.0 else 10.0 * self.shift
        logger.debug("Levenberg shift raised to %.3g", self.shift)


def newton(
    objective: Objective, u0: Tensor, *, tol: float = 1e-8, max_iter: int = 50, reuse: int = 0
) -> tuple[Tensor, SolveInfo]:
    """Projected Newton with Armijo backtracking and Levenberg regularization.

    Each iteration factorizes the objective's PSD Hessian (sparse LU). If that fails (singular),
    the direction is not finite or not a descent direction, or the line search finds no
    acceptable step, the shift ``lambda`` of ``H + lambda * metric`` is raised (first to
    1e-8 x the diagonal ratio, then x10); after an accepted step it is lowered x10 again.

    With ``reuse`` > 0, each Newton step is followed by up to ``reuse`` chord steps: directions
    from the same factorization at the new points (one gradient and one back-substitution each,
    no Hessian), taken while the full step stays within the trust radius ``max_step`` and meets
    the Armijo condition, until the convergence rule is met. Where the Hessian is expensive and
    the convergence linear (soft modes that the projected Hessian over-stiffens, e.g. a chain of
    contact-held links), this cuts the Hessians per solve several-fold; it never changes the
    convergence rule.

    Args:
        objective: The objective.
        u0: Initial guess, shape [m].
        tol: Relative gradient tolerance of the convergence rule (module doc).
        max_iter: Most Newton iterations (Hessian evaluations; chord steps come on top).
        reuse: Most chord steps per Newton iteration (>= 0).

    Returns:
        The last accepted point [m] and its :class:`SolveInfo` (``iterations`` counts Newton
        iterations and chord steps alike; the message gives the number of chord steps).
    """
    if int(reuse) != reuse or reuse < 0:
        raise ValueError(f"reuse must be an integer >= 0, got {reuse}")
    point, threshold = _start(objective, u0, tol, max_iter)
    history = [point.value]
    if not point.finite:
        return point.u, _result(point, False, 0, history, "objective or gradient is not finite at the initial guess")
    regularizer = _Levenberg()
    chords = 0

    def message(text: str) -> str:
        return f"{text} ({chords} chord steps)" if reuse else text

    for _ in range(max_iter):
        if point.grad_norm <= threshold:
            return point.u, _result(
                point,
                True,
                len(history) - 1,
                history,
                message(f"converged: |g| = {point.grad_norm:.3g} <= {threshold:.3g}"),
            )
        trial = regularizer.step(objective, point, objective.hessian(point.u))
        if trial is None:
            return point.u, _result(
                point,
                False,
                len(history) - 1,
                history,
                message(
                    f"no descent step found after {MAX_SHIFTS} Levenberg shifts "
                    f"(|g| = {point.grad_norm:.3g} > {threshold:.3g})"
                ),
            )
        point = trial
        _accept(objective, point, history)
        for _ in range(int(reuse)):
            if point.grad_norm <= threshold or regularizer.factor is None:
                break
            chord = _chord_step(objective, point, regularizer.factor)
            if chord is None:
                break
            point = chord
            chords += 1
            _accept(objective, point, history)
    converged = point.grad_norm <= threshold
    verdict = "converged" if converged else f"not converged after max_iter = {max_iter}"
    return point.u, _result(
        point,
        converged,
        len(history) - 1,
        history,
        message(f"{verdict}: |g| = {point.grad_norm:.3g}, threshold {threshold:.3g}"),
    )


def _largest_move(objective: Objective, u: Tensor, direction: Tensor) -> float:
    """How far the step from u along ``direction`` moves, in the unit of ``objective.max_step``: the objective's own
    measure where it has one (``largest_move(u, direction)``), else the direction's largest entry."""
    measure = getattr(objective, "largest_move", None)
    return float(direction.abs().max()) if measure is None else float(measure(u, direction))


def _clipped(objective: Objective, direction: Tensor | None, u: Tensor) -> Tensor | None:
    """The direction from u scaled down so it moves at most ``objective.max_step`` (:func:`_largest_move`)."""
    if direction is not None and math.isfinite(objective.max_step):
        longest = _largest_move(objective, u, direction)
        if longest > objective.max_step:
            direction = direction * (objective.max_step / longest)
    return direction


def _chord_step(objective: Objective, point: _Point, factor: scipy.sparse.linalg.SuperLU) -> _Point | None:
    """The full step along -A^-1 g (A: a previous iteration's matrix), or None.

    None unless the step is finite, within the trust radius (a chord step that would need
    clipping is outside where the old model holds: a mechanism falling along null modes) and
    meets the Armijo condition.
    """
    direction = _solve(factor, -point.grad)
    if direction is None:
        return None
    if math.isfinite(objective.max_step) and _largest_move(objective, point.u, direction) > objective.max_step:
        return None
    slope = float(point.grad @ direction)
    if not slope < 0.0:
        return None
    trial = _evaluate(objective, point.u + direction)
    if trial.finite and trial.value <= point.value + ARMIJO_C * slope:
        return trial
    return None


def lbfgs(
    objective: Objective, u0: Tensor, *, tol: float = 1e-8, max_iter: int = 50, memory: int = 10
) -> tuple[Tensor, SolveInfo]:
    """L-BFGS with Armijo backtracking, preconditioned by the objective's metric.

    The initial inverse Hessian is gamma * metric^-1 (gamma = s.y / y.metric^-1 y from the
    newest pair, 1 before there is one), so for the incremental potential (metric M/h^2)
    the very first step is already scaled like a Newton step of the inertia. Pairs with
    s.y <= eps |s||y| are skipped; a failed line search clears the memory once and retries
    the preconditioned gradient step.

    Args:
        objective: The objective (its Hessian is never used).
        u0: Initial guess, shape [m].
        tol: Relative gradient tolerance of the convergence rule (module doc).
        max_iter: Most L-BFGS iterations.
        memory: Number of (s, y) pairs kept.

    Returns:
        The last accepted point [m] and its :class:`SolveInfo`.
    """
    point, threshold = _start(objective, u0, tol, max_iter)
    if memory < 1:
        raise ValueError(f"memory must be >= 1, got {memory}")
    history = [point.value]
    if not point.finite:
        return point.u, _result(point, False, 0, history, "objective or gradient is not finite at the initial guess")
    factor = _factorize(objective.metric(point.u))
    if factor is None:  # e.g. a latent metric J^T M J of a map that explodes at u0
        return point.u, _result(point, False, 0, history, "the metric is singular at the initial guess")
    pairs: deque[tuple[Tensor, Tensor, float]] = deque(maxlen=memory)
    for iteration in range(max_iter):
        if point.grad_norm <= threshold:
            return point.u, _result(
                point, True, iteration, history, f"converged: |g| = {point.grad_norm:.3g} <= {threshold:.3g}"
            )
        trial = _line_search(objective, point, _clipped(objective, _two_loop(point.grad, pairs, factor), point.u))
        if trial is None and pairs:
            pairs.clear()
            trial = _line_search(objective, point, _clipped(objective, _two_loop(point.grad, pairs, factor), point.u))
        if trial is None:
            return point.u, _result(
                point, False, iteration, history, f"line search failed (|g| = {point.grad_norm:.3g} > {threshold:.3g})"
            )
        s, y = trial.u - point.u, trial.grad - point.grad
        sy = float(s @ y)
        if sy > float(np.finfo(np.float64).eps) * float(torch.linalg.vector_norm(s) * torch.linalg.vector_norm(y)):
            pairs.append((s, y, 1.0 / sy))
        point = trial
        _accept(objective, point, history)
    converged = point.grad_norm <= threshold
    verdict = "converged" if converged else f"not converged after max_iter = {max_iter}"
    return point.u, _result(
        point, converged, max_iter, history, f"{verdict}: |g| = {point.grad_norm:.3g}, threshold {threshold:.3g}"
    )


def _two_loop(grad: Tensor, pairs: deque[tuple[Tensor, Tensor, float]], factor: scipy.sparse.linalg.SuperLU) -> Tensor:
    """-H_k g by the L-BFGS two-loop recursion with H_0 = gamma * metric^-1."""
    q = grad.clone()
    alphas = []
    for s, y, rho in reversed(pairs):
        a = rho * float(s @ q)
        alphas.append(a)
        q = q - a * y
    r = _solve(factor, q)
    if r is None:
        raise ValueError("the objective's metric solve produced non-finite values")
    if pairs:
        s, y, rho = pairs[-1]
        precond_y = _solve(factor, y)
        if precond_y is None:
            raise ValueError("the objective's metric solve produced non-finite values")
        r = r * (1.0 / (rho * float(y @ precond_y)))
    for (s, y, rho), a in zip(pairs, reversed(alphas), strict=True):
        b = rho * float(y @ r)
        r = r + (a - b) * s
    return -r


MINIMIZERS: dict[str, Minimizer] = {"newton": newton, "lbfgs": lbfgs}
"""Minimizers by name; each is ``f(objective, u0, *, tol, max_iter) -> (u, SolveInfo)``."""


def get_minimizer(name: str) -> Minimizer:
    """The minimizer called ``name``; a ValueError lists the valid names."""
    if name not in MINIMIZERS:
        raise ValueError(f"unknown minimizer {name!r}; valid minimizers: {sorted(MINIMIZERS)}")
    return MINIMIZERS[name]
