"""Static equilibria: local minimizers of E(q; loads, cond) - f . q, over q or over a map's latent z.

The objective of :mod:`redsim.integrators.objective` without the inertia term, minimized by a
named minimizer of :mod:`redsim.solvers` (:func:`static_equilibrium` over q,
:func:`latent_equilibrium` over z). The robust, cached full-space equilibria the metrics measure
against are in :mod:`redsim.integrators.reference`.
"""

from __future__ import annotations

from torch import Tensor

from redsim.integrators.objective import PotentialObjective, checked_vector, pack_inputs
from redsim.integrators.spaces import FullSpace, LatentSpace, Space
from redsim.scene import LoadsLike, Scene
from redsim.solvers import SolveInfo, get_minimizer


def static_equilibrium(
    scene: Scene,
    loads: LoadsLike = None,
    cond: Tensor | None = None,
    *,
    q0: Tensor | None = None,
    force: Tensor | None = None,
    minimizer: str = "newton",
    tol: float = 1e-8,
    max_iter: int = 200,
) -> tuple[Tensor, SolveInfo]:
    """A local minimizer of E(q; loads, cond) - force . q, starting from q0.

    Singular Hessians (rigid null modes, free bodies) are handled by the Levenberg shift of
    :func:`redsim.solvers.newton`. Without a minimizer (e.g. an unbalanced load on a free
    body), the result reports ``converged=False``. ``converged`` means stationary: projected Newton does not see
    negative curvature, so from a symmetric start under a symmetric load it can end at a saddle (the bistable
    bar under 30 N: smallest Hessian eigenvalue -0.43); :func:`redsim.integrators.reference.full_equilibrium`
    escapes saddles.

    Args:
        scene: The scene (solved in float64).
        loads: Loads on the handles [N].
        cond: Condition vector [m].
        q0: Initial guess, shape [n] (default: the seed).
        force: Constant generalized force [N], shape [n], or None.
        minimizer: A key of :data:`redsim.solvers.MINIMIZERS`.
        tol: Relative gradient tolerance: converged when |g| <= tol * max(|g(q0)|, F), with F the sum of
            the effects' force norms at q0 plus |force| (or when |g| is at float64 round-off level).
        max_iter: Most iterations.

    Returns:
        The configuration [n] (float64) and the :class:`SolveInfo`.
    """
    return _static_solve(FullSpace(scene), loads, cond, q0, "q0", force, minimizer, tol, max_iter)


def latent_equilibrium(
    space: LatentSpace,
    loads: LoadsLike = None,
    cond: Tensor | None = None,
    *,
    z0: Tensor | None = None,
    force: Tensor | None = None,
    minimizer: str = "newton",
    tol: float = 1e-8,
    max_iter: int = 200,
) -> tuple[Tensor, SolveInfo]:
    """A local minimizer over z of E(f(z); loads, cond) - force . f(z), starting from z0.

    The same objective and minimizers as :func:`static_equilibrium`, over the latent space (see
    :class:`LatentSpace` for what Newton and the convergence rule mean there).

    Args:
        space: The latent space (the map and its condition).
        loads: Loads on the handles [N].
        cond: Condition vector [m] of the energy (default: the space's map condition, else the
            scene's default).
        z0: Initial guess, shape [d] (default: z = 0).
        force: Constant generalized force [N], shape [n], or None.
        minimizer: A key of :data:`redsim.solvers.MINIMIZERS`.
        tol: Relative gradient tolerance (as in :func:`static_equilibrium`, scaled by |J(z0)|_2).
        max_iter: Most iterations.

    Returns:
        The latent coordinates z [d] (float64; q = space.configuration(z[None])[0]) and the
        :class:`SolveInfo`.
    """
    cond = space.condition if cond is None else cond
    return _static_solve(space, loads, cond, z0, "z0", force, minimizer, tol, max_iter)


def _static_solve(
    space: Space,
    loads: LoadsLike,
    cond: Tensor | None,
    u0: Tensor | None,
    name: str,
    force: Tensor | None,
    minimizer: str,
    tol: float,
    max_iter: int,
) -> tuple[Tensor, SolveInfo]:
    """Minimize the static potential over ``space`` from u0 (default: the space's origin)."""
    minimize = get_minimizer(minimizer)
    origin = space.origin
    u_start = origin.detach().clone() if u0 is None else checked_vector(u0, space.size, name, origin)
    seed = space.scene.q_seed
    force_t = None if force is None else checked_vector(force, int(seed.shape[0]), "force", seed)
    loads_t, cond_t = pack_inputs(space.scene, loads, cond)
    objective = PotentialObjective(space, loads=loads_t, cond=cond_t, inertia=None, force=force_t, reference=u_start)
    return minimize(objective, u_start, tol=tol, max_iter=max_iter)
