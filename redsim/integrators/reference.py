"""Full-space reference equilibria: the robust, cached static solves the metrics measure against.

:func:`full_equilibrium` finds a *stable* full-space equilibrium under a load: Newton
(:func:`redsim.solvers.newton`, the objective of :func:`redsim.integrators.static_equilibrium`),
a proximal relaxation where Newton stalls, and escapes from saddle points. Results are cached in
memory and on disk by :mod:`redsim.integrators.cache`, keyed by the scene's content, the
condition, the load and the solver settings below. :func:`rest_state` is the unloaded one.
"""

from __future__ import annotations

import logging
import math
import warnings

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch
from torch import Tensor

from redsim.hessian import energy_hessian
from redsim.integrators import cache
from redsim.integrators.objective import Inertia, PotentialObjective, checked_vector
from redsim.integrators.spaces import FullSpace, as_float64
from redsim.scene import Scene
from redsim.solvers import SHIFT_FLOOR, convergence_threshold, newton

logger = logging.getLogger(__name__)

FULL_TOL = 1e-5
"""Relative force-balance tolerance of the full-space equilibria (and the default of the latent ones).

Contact penalties are only C1: the 24-link chain's gradient stalls near 1e-6 of its forces, so
1e-5 is what every catalog scene reaches; error metrics need far less (1e-3).
"""
NEWTON_ITER = 300
"""Newton iterations of the first attempt at a full-space equilibrium (relaxation takes over after them)."""
NEWTON_REUSE = 20
"""Most chord steps per Newton iteration of the full-space solves (``reuse`` of :func:`redsim.solvers.newton`)."""
RELAX_STEPS = 200
"""Most proximal steps of a relaxation."""
ESCAPES = 3
"""Most escapes from saddle points per full-space equilibrium (see :func:`_solve_full`)."""
RELAX_MOVE = 0.01
"""Proximal steps move the fastest DOF about this fraction of the scene size (4x more is rejected)."""


def rest_state(scene: Scene, cond: Tensor | None = None) -> tuple[Tensor, bool]:
    """The unloaded full-space equilibrium that load errors are measured around (cached).

    Newton from the seed, with the relaxation fallback and saddle escapes of
    :func:`full_equilibrium`, in float64. Baselines built here share its reference.

    Returns:
        q_rest [n] (float64) and whether the solve converged.
    """
    q, converged, _ = full_equilibrium(scene, None, cond)
    return q, converged


def rest_or_warn(scene: Scene, user: str, cond: Tensor | None = None) -> Tensor:
    """q_rest [n] (float64) of :func:`rest_state`, with a :class:`RuntimeWarning` naming ``user`` (what is built
    around it) where its solve did not converge: the state is then not an equilibrium, and modes or a polynomial
    map taken there are taken about a state that would move."""
    q, converged = rest_state(scene, cond)
    if not converged:
        warnings.warn(
            f"the full-space rest of scene {scene.name!r} did not converge (Newton with relaxation and saddle "
            f"escapes): {user} uses its last iterate, which is not an equilibrium",
            RuntimeWarning,
            stacklevel=2,
        )
    return q


def full_equilibrium(
    scene: Scene, load: Tensor | None = None, cond: Tensor | None = None, start: Tensor | None = None
) -> tuple[Tensor, bool, float]:
    """Stable full-space static equilibrium under ``load`` [H, D] from ``start`` (None: the seed), cached.

    The cache key is the scene's content, the condition and the load (loaded solves always
    start at the rest equilibrium, itself a function of the scene and condition), plus the
    solver settings for the disk cache (:func:`redsim.integrators.cache.cache_directory`).

    Args:
        scene: The scene (solved in float64: a float32 one is cast, as :func:`rest_state` does).
        load: Loads [N], shape [H, D], or None for the rest equilibrium.
        cond: Condition [m]; default: the scene's.
        start: Where the solve starts, shape [n] (None: the seed).

    Returns:
        q [n] (float64); converged (see :func:`_solve_full`); E(q; load) [J].
    """
    scene = as_float64(scene)
    start = scene.q_seed if start is None else checked_vector(start, scene.free_dof_count, "start", scene.q_seed)
    settings = (FULL_TOL, NEWTON_ITER, NEWTON_REUSE, RELAX_STEPS, RELAX_MOVE, ESCAPES)
    return cache.lookup(scene, load, cond, settings, lambda: _solve_full(scene, load, cond, start))


def _solve_full(scene: Scene, load: Tensor | None, cond: Tensor | None, start: Tensor) -> tuple[Tensor, bool, float]:
    """A stable full-space equilibrium under ``load`` reached from ``start``: (q [n], converged, E(q; load) [J]).

    Converged means |dE/dq| <= FULL_TOL * max(|g(start)|, F), the rule of
    :func:`static_equilibrium` (F: the summed force norms at ``start``), reached by
    :func:`_descend` (Newton, then relaxation). A force balance can also hold near a saddle: the
    24-link chain falling from its seed came to rest 1 J above its hanging minimum, balanced
    with all links turned 7.5 degrees, where the unprojected Hessian had eigenvalues (over M) of
    -1.7e4 1/s^2; the two-link chain's rest from its seed is such a saddle too. So a converged
    point whose unprojected Hessian K has a direction of negative curvature (K + s M not
    positive definite, s = SHIFT_FLOOR times the ratio of their diagonals, as in the load sizes
    of :func:`redsim.metrics.load_response_error`) is left along that direction, to the side and
    distance (at most the trust radius, halved until the energy drops) of lower energy, and
    solved again; at most
    ESCAPES times. A point that still has negative curvature then is returned as converged
    (the force balance holds) with a warning.
    """
    space = FullSpace(scene)
    loads = scene.pack_loads(load, 1, scene.q_seed)
    packed_cond = scene.pack_condition(cond, 1, scene.q_seed)
    start = start.detach().clone()
    objective = PotentialObjective(space, loads=loads, cond=packed_cond, inertia=None, force=None, reference=start)
    threshold = convergence_threshold(
        objective, FULL_TOL, float(torch.linalg.vector_norm(objective.value_and_grad(start)[1]))
    )
    q = start
    for escape in range(ESCAPES + 1):
        q, converged, energy = _descend(objective, q, threshold)
        if not converged:
            return q, False, energy
        direction = _negative_curvature(scene, q, loads, packed_cond)
        if direction is None:
            return q, True, energy
        if escape == ESCAPES:
            break
        lower = _lower_along(objective, q, energy, direction)
        if lower is None:
            logger.warning(
                "full-space equilibrium of %s has negative curvature but no lower point along it", scene.name
            )
            return q, True, energy
        logger.info("full-space equilibrium of %s is a saddle (E = %.10g J); leaving it", scene.name, energy)
        q = lower
    logger.warning("full-space equilibrium of %s is still a saddle after %d escapes", scene.name, ESCAPES)
    return q, True, energy


def _descend(objective: PotentialObjective, start: Tensor, threshold: float) -> tuple[Tensor, bool, float]:
    """Newton from ``start`` to |g| <= threshold; if it fails, proximal-point relaxation from where Newton stopped.

    Newton is :func:`redsim.solvers.newton` on the static potential (what
    :func:`static_equilibrium` solves) with up to NEWTON_REUSE chord steps per Hessian, and
    tol chosen so that its threshold is ``threshold``. It converges slowly where the projected
    Hessian is much stiffer than the energy along soft modes (a chain's links twisting about
    the vertical) and can stall. The fallback relaxes by proximal steps
    q <- argmin E(q) + |q - q_k|_M^2 / (2 h^2) (implicit Euler with the velocity zeroed; each
    step solved by Newton to 0.01 FULL_TOL), whose move is bounded by h^2 times the net force:
    h starts where the fastest DOF moves RELAX_MOVE L, doubles after a shorter move (near
    equilibrium the steps become Newton steps) and halves, rejecting the step, after a move
    over 4 RELAX_MOVE L. It starts from Newton's last point, which is lower in energy than
    ``start`` (descent only; the trust radius of static full-space solves keeps contact-held
    links from passing through each other).

    Returns:
        q [n]; converged (|dE/dq| <= threshold); E(q; load) [J].
    """
    scene, space = objective.scene, objective.space
    scale = max(float(torch.linalg.vector_norm(objective.value_and_grad(start)[1])), objective.force_scale)
    tol = threshold / scale if scale > 0.0 else FULL_TOL
    q, info = newton(objective, start, tol=tol, max_iter=NEWTON_ITER, reuse=NEWTON_REUSE)
    if info.converged:
        return q.detach().clone(), True, info.energy
    logger.info("full-space Newton on %s did not converge (%s); relaxing", scene.name, info.message)
    q = q.detach().clone()
    energy, grad = objective.value_and_grad(q)
    accel = scipy.sparse.linalg.spsolve(scene.mass_matrix_scipy().tocsc(), grad.numpy())
    limit = RELAX_MOVE * scene.extent()
    dt = math.sqrt(limit / max(float(np.abs(accel).max()), 1e-300))
    for _ in range(RELAX_STEPS):
        step = PotentialObjective(
            space, loads=objective.loads, cond=objective.cond, inertia=Inertia(q, dt), force=None, reference=q
        )
        # solved tighter than the outer test, or that stalls; the step is taken even if not converged
        trial = newton(step, q, tol=0.01 * FULL_TOL, max_iter=50, reuse=NEWTON_REUSE)[0].detach()
        move = float((trial - q).abs().max())
        if move > 4.0 * limit:
            dt *= 0.5
            continue
        q = trial
        energy, grad = objective.value_and_grad(q)
        if float(torch.linalg.vector_norm(grad)) <= threshold:
            return q, True, energy
        if move < limit:
            dt *= 2.0
    logger.warning(
        "full-space equilibrium of %s did not converge: |g| = %.3g > %.3g after relaxing",
        scene.name,
        float(torch.linalg.vector_norm(grad)),
        threshold,
    )
    return q, False, energy


def _negative_curvature(
    scene: Scene, q: Tensor, loads: Tensor | None, cond: Tensor | None, dt: float | None = None
) -> Tensor | None:
    """A direction v [n] (largest entry 1) with v^T K v < -s v^T M v, or None if K + s M is positive definite.

    K is the unprojected energy Hessian at q and s = SHIFT_FLOOR * |diag K| / |diag M| (round-off
    and exact null modes stay above -s); for an implicit-Euler step of ``dt`` [s], s = 1 / dt^2 (K + M / dt^2 is
    the Hessian of the step's objective). The test is the inertia of a symmetric sparse LU with
    diagonal pivots (K + s M = P^T U^T D^-1 U P): a negative pivot d_i gives v = P^T U^-1 e_i
    with v^T (K + s M) v = 1 / d_i < 0. None also when the factorization is singular or not
    symmetric (no verdict).
    """
    stiffness = energy_hessian(scene, q, loads, cond, project=False)
    mass = scene.mass_matrix_scipy()
    ratio = float(np.linalg.norm(stiffness.diagonal()) / np.linalg.norm(mass.diagonal()))
    shift = SHIFT_FLOOR * (ratio if ratio > 0.0 else 1.0) if dt is None else 1.0 / dt**2
    matrix = scipy.sparse.csc_matrix(0.5 * (stiffness + stiffness.T) + shift * mass)
    try:
        factor = scipy.sparse.linalg.splu(
            matrix, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
    except RuntimeError:
        return None
    pivots = factor.U.diagonal()
    negative = np.flatnonzero(pivots < 0.0)
    if not np.array_equal(factor.perm_r, factor.perm_c) or negative.size == 0:
        return None
    upper = factor.U.tocsr()
    for i in negative[np.argsort(pivots[negative])][:8]:
        unit = np.zeros(matrix.shape[0])
        unit[i] = 1.0
        v = scipy.sparse.linalg.spsolve_triangular(upper, unit, lower=False)[factor.perm_c]
        if np.all(np.isfinite(v)) and v @ (matrix @ v) < 0.0:
            return torch.from_numpy(v / np.abs(v).max())
    return None


def _lower_along(objective: PotentialObjective, q: Tensor, energy: float, direction: Tensor) -> Tensor | None:
    """The lowest q + t direction below ``energy`` over both signs of t (from the trust radius, halved), or None."""
    best: tuple[float, Tensor] | None = None
    for sign in (1.0, -1.0):
        t = objective.max_step if math.isfinite(objective.max_step) else RELAX_MOVE * objective.scene.extent()
        for _ in range(40):
            trial = q + sign * t * direction
            value = objective.value_and_grad(trial)[0]
            if value < energy - objective.value_noise:
                if best is None or value < best[0]:
                    best = (value, trial)
                break
            t *= 0.5
    return None if best is None else best[1].detach().clone()
