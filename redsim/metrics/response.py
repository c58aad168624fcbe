"""Load response: subspace equilibria under loads against full-space equilibria (figure "modes_comparison")."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch
from torch import Tensor

from redsim.hessian import energy_hessian
from redsim.integrators import latent_equilibrium
from redsim.integrators.reference import FULL_TOL, full_equilibrium
from redsim.metrics.common import DISPLACEMENT_FLOOR, Subspace, check_count, latent_space, m_norm, scene_size
from redsim.scene import LoadsLike, Scene
from redsim.solvers import SHIFT_FLOOR, SolveInfo

RESPONSE_FRACTION = 0.1
"""Default load magnitude: the linear response along the softest handle direction is this fraction of the size L."""


def load_response_error(
    scene: Scene,
    subspace: Subspace,
    *,
    loads: Sequence[LoadsLike] | None = None,
    count: int = 8,
    magnitude: float | None = None,
    response_fraction: float = RESPONSE_FRACTION,
    seed: int = 0,
    cond: Tensor | None = None,
    restarts: int = 2,
    minimizer: str = "lbfgs",
    tol: float = FULL_TOL,
    max_iter: int = 500,
) -> dict[str, Any]:
    """Subspace equilibria against full-space equilibria under the same loads (figure "modes_comparison").

    For each load l: the full-space equilibrium q*_l (from the rest equilibrium q_rest, the
    unloaded equilibrium reached from the seed; both cached, both by Newton with a proximal
    relaxation fallback, to a relative force balance of FULL_TOL, and left again where the
    energy curves down, so saddles do not count as equilibria) and the subspace equilibrium
    f(z*_l) (:func:`redsim.integrators.latent_equilibrium` from z = 0 and from ``restarts``
    seeded z ~ N(0, I), keeping the lowest potential E(f(z); l)). The error is relative to the
    load's own response:

        error_l = |f(z*_l) - q*_l|_M / max(|q*_l - q_rest|_M, DISPLACEMENT_FLOOR * S),

    S = sqrt(sum diag M) L the M-norm size of the scene (L: its largest surface extent at the seed).
    0 means the subspace reproduces the response exactly; 1 is what a subspace that does not
    move at all (f(z*) = q_rest) scores.

    The response error measures the same displacement from the subspace's own unloaded
    equilibrium f(z*_0) instead, so that a fixed offset of f(z*_0) from q_rest does not count:

        response_error_l = |(f(z*_l) - f(z*_0)) - (q*_l - q_rest)|_M / (the same denominator).

    Default loads: ``count`` loads, load i a force on handle i mod H only (handles in scene
    order), in a uniformly random direction (seeded), of magnitude response_fraction * L / c_h,
    where c_h [m/N] is the largest eigenvalue of handle h's linearized compliance G_h^T K^-1 G_h
    at q_rest (K the projected energy Hessian, shifted by SHIFT_FLOOR times its diagonal ratio
    to M so null modes stay finite; G_h [n, D] the generalized forces of unit handle forces):
    the linear response along the handle's softest direction is 10% (by default) of the scene
    size, whatever the units, stiffness or weight. The loads used are returned.

    A load whose full-space solve stops unconverged (``full_converged`` False; e.g. cloth_ball,
    where a push on the ball rolls it off the taut cloth and no static equilibrium exists) is
    still listed per load but left out of the means, median and max (NaN where no solve
    converged); ``averaged_loads`` counts the loads averaged.

    Args:
        scene: The scene; it needs handles.
        subspace: The map (module doc).
        loads: Explicit loads, each as accepted by :meth:`Scene.pack_loads` ([H, D] or a
            {handle: force} mapping) [N]; replaces ``count`` and ``magnitude``.
        count: Number of generated loads (>= 1).
        magnitude: Force per loaded handle [N] instead of the compliance rule.
        response_fraction: Linear response of the compliance rule, as a fraction of L (> 0);
            larger loads probe the nonlinear range.
        seed: Seed of the load directions and of the latent restarts.
        cond: Condition [m] of the energy (and of a conditional map); default: the scene's.
        restarts: Random latent starts besides z = 0 (>= 0).
        minimizer: Minimizer of the latent solves ("lbfgs", the paper's, or "newton").
        tol: Relative gradient tolerance of the latent solves (the full-space ones use FULL_TOL).
        max_iter: Most iterations per latent solve.

    Returns:
        ``errors`` (per load), ``mean_error``, ``median_error``, ``max_error``,
        ``response_errors`` (per load) and ``mean_response_error`` (over the converged loads),
        ``averaged_loads``,
        ``absolute_errors`` and ``displacements`` (|q*_l - q_rest|_M) [kg^1/2 m],
        ``energy_gaps`` E(f(z*_l); l) - E(q*_l; l) [J] (>= 0 when both are in one basin),
        ``full_converged``, ``latent_converged`` (per load), ``rest_converged``, ``rest_error``
        (|f(z*_0) - q_rest|_M [kg^1/2 m] of the unloaded subspace equilibrium: how well the
        subspace holds the rest state itself) and ``rest_latent_converged``,
        ``loads`` ([count, H, D] nested lists [N]), ``handles``, ``magnitudes``
        ({handle: N}, None for explicit loads), ``seed``, ``restarts``, ``minimizer``.

    Raises:
        ValueError: a scene without handles, bad counts, or a bad load.
    """
    if not scene.handles:
        raise ValueError(f"scene {scene.name!r} has no handles to load")
    check_count("restarts", restarts, 0)
    space = latent_space(scene, subspace, cond)
    scene64 = space.scene
    rest, rest_converged, _ = full_equilibrium(scene64, None, cond)
    generator = torch.Generator().manual_seed(seed)
    magnitudes: dict[str, float] | None = None
    if loads is None:
        check_count("count", count, 1)
        if not (math.isfinite(response_fraction) and response_fraction > 0.0):
            raise ValueError(f"response_fraction must be finite and > 0, got {response_fraction!r}")
        per_handle = _handle_magnitudes(scene64, rest, cond, response_fraction) if magnitude is None else None
        if magnitude is not None and not (math.isfinite(magnitude) and magnitude > 0.0):
            raise ValueError(f"magnitude must be finite and > 0 [N], got {magnitude!r}")
        magnitudes = {
            name: float(magnitude) if per_handle is None else float(per_handle[h])
            for h, name in enumerate(scene64.handle_names)
        }
        load_list = _random_loads(scene64, list(magnitudes.values()), count, generator)
    else:
        load_list = [_packed(scene64, load) for load in loads]
        if not load_list:
            raise ValueError("loads must not be empty")
    mass = scene64.mass_matrix_scipy()
    size = scene_size(scene64, mass)
    starts = [
        space.origin,
        *(torch.randn(space.latent_dim, generator=generator, dtype=torch.float64) for _ in range(restarts)),
    ]

    def subspace_equilibrium(load: Tensor | None) -> tuple[Tensor, SolveInfo]:
        """f(z*) [n] of the lowest-energy latent solve over the starts, and its SolveInfo."""
        solutions = [
            latent_equilibrium(space, load, cond, z0=z0, minimizer=minimizer, tol=tol, max_iter=max_iter)
            for z0 in starts
        ]
        z, info = min(solutions, key=lambda s: s[1].energy if math.isfinite(s[1].energy) else math.inf)
        with torch.no_grad():
            return space.configuration(z.unsqueeze(0))[0], info

    q_sub_rest, rest_info = subspace_equilibrium(None)
    rows: list[dict[str, Any]] = []
    for load in load_list:
        target, full_converged, full_energy = full_equilibrium(scene64, load, cond, rest)
        q, info = subspace_equilibrium(load)
        error = m_norm(mass, q - target)
        displacement = m_norm(mass, target - rest)
        scale = max(displacement, DISPLACEMENT_FLOOR * size)
        rows.append(
            {
                "error": error / scale,
                "response": m_norm(mass, (q - q_sub_rest) - (target - rest)) / scale,
                "absolute": error,
                "displacement": displacement,
                "gap": info.energy - full_energy,
                "full": full_converged,
                "latent": info.converged,
            }
        )
    errors = np.array([r["error"] for r in rows])
    responses = np.array([r["response"] for r in rows])
    held = np.array([r["full"] for r in rows])  # loads with a reference: the scene holds them at rest
    return {
        "errors": errors.tolist(),
        "mean_error": _over(errors, held, np.mean),
        "median_error": _over(errors, held, np.median),
        "max_error": _over(errors, held, np.max),
        "response_errors": responses.tolist(),
        "mean_response_error": _over(responses, held, np.mean),
        "averaged_loads": int(held.sum()),
        "absolute_errors": [r["absolute"] for r in rows],
        "displacements": [r["displacement"] for r in rows],
        "energy_gaps": [r["gap"] for r in rows],
        "full_converged": [r["full"] for r in rows],
        "latent_converged": [r["latent"] for r in rows],
        "rest_converged": rest_converged,
        "rest_error": m_norm(mass, q_sub_rest - rest),
        "rest_latent_converged": rest_info.converged,
        "loads": [load.tolist() for load in load_list],
        "handles": list(scene64.handle_names),
        "magnitudes": magnitudes,
        "response_fraction": response_fraction if loads is None and magnitude is None else None,
        "seed": seed,
        "restarts": restarts,
        "minimizer": minimizer,
    }


def _over(values: np.ndarray, held: np.ndarray, reduce: Callable[[np.ndarray], Any]) -> float:
    """``reduce`` of the values of the held loads; NaN where the scene held none."""
    return float(reduce(values[held])) if held.any() else math.nan


def _packed(scene: Scene, load: LoadsLike) -> Tensor:
    """One load as a finite float64 tensor [H, D] [N]."""
    packed = scene.pack_loads(load, 1, scene.q_seed)
    if packed is None or not bool(torch.isfinite(packed).all()):
        raise ValueError(f"each load must be finite and not None, got {load!r}")
    return packed[0]


def _random_loads(scene: Scene, magnitudes: list[float], count: int, generator: torch.Generator) -> list[Tensor]:
    """Load i: magnitudes[h] [N] along a uniformly random unit direction on handle h = i mod H only."""
    out = []
    for i in range(count):
        handle = i % len(magnitudes)
        direction = torch.randn(scene.dim, generator=generator, dtype=torch.float64)
        load = torch.zeros(len(magnitudes), scene.dim, dtype=torch.float64)
        load[handle] = magnitudes[handle] * direction / direction.norm()
        out.append(load)
    return out


def _handle_magnitudes(scene: Scene, rest: Tensor, cond: Tensor | None, fraction: float) -> np.ndarray:
    """fraction * L / c_h [N] per handle (see :func:`load_response_error`), shape [H]."""
    H, D = len(scene.handles), scene.dim
    stiffness = energy_hessian(scene, rest, None, cond, project=True)
    mass = scene.mass_matrix_scipy()
    ratio = float(np.linalg.norm(stiffness.diagonal()) / np.linalg.norm(mass.diagonal()))
    shifted = stiffness + SHIFT_FLOOR * (ratio if ratio > 0.0 else 1.0) * mass
    factor = scipy.sparse.linalg.splu(scipy.sparse.csc_matrix(shifted))
    unit = torch.eye(H * D, dtype=torch.float64).reshape(H * D, H, D)  # every (handle, axis) unit force
    q = rest.detach().unsqueeze(0).expand(H * D, -1).clone().requires_grad_(True)
    work = scene.energy(q, unit, cond) - scene.energy(q, torch.zeros_like(unit), cond)  # -f . p, linear in q
    (grad,) = torch.autograd.grad(work.sum(), q)
    forces = -grad.numpy().T  # [n, H * D]: generalized forces of unit handle forces
    compliance = forces.T @ factor.solve(forces)  # [H * D, H * D] [m/N]
    largest = np.array(
        [
            np.linalg.eigvalsh(0.5 * (block + block.T))[-1]
            for block in (compliance[h * D : (h + 1) * D, h * D : (h + 1) * D] for h in range(H))
        ]
    )
    if not np.all(np.isfinite(largest) & (largest > 0.0)):
        raise ValueError(
            f"scene {scene.name!r}: handle compliances {largest.tolist()} are not finite and > 0; "
            "give the load magnitude"
        )
    return fraction * scene.extent() / largest
