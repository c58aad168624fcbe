"""How good a subspace map is: the measurements behind the paper's comparison figures.

Every function takes any subspace object (a callable z [..., d] -> q [..., n] with a
``latent_dim``, e.g. :class:`redsim.subspace.SubspaceMap` or a linear basis; a conditional
map with ``config.condition_dim > 0`` is evaluated at ``cond``) and evaluates it through
:class:`redsim.integrators.LatentSpace`: the map runs in its own dtype, everything after it
(energies, norms, solves) in float64. Latent samples are z ~ N(0, I) from a
``torch.Generator`` seeded with ``seed``, so every number is reproducible.

- :func:`energy_stats`: the energy of subspace states, absolute and relative to the drop from
  the seed to the full-space rest equilibrium (the fitting loss's first term).
- :func:`stretch_stats`: the metric stretch |f(z) - f(z')|_M / (sigma |z - z'|) over all pairs
  (supplement A.1; the fitting loss's second term, :func:`pair_log_ratios`).
- :func:`load_response_error`: subspace equilibria under a fixed, seeded set of loads against
  the full-space equilibria (figure "modes_comparison").
- :func:`nonrigid_strain`: the mean Green strain of subspace states of FEM scenes (figure
  "rigidity": linear subspaces shear where they should rotate).
- :func:`evaluate_subspace`: all of the above as one JSON-serializable dict.
- :func:`rest_state`: the full-space rest equilibrium all of them measure around.

Full-space equilibria are the expensive part; they are cached per scene content, condition
and loads (:func:`clear_cache`), in memory and on disk (:func:`cache_directory`: under
``$REDSIM_CACHE``, by default ``~/.cache/redsim``; ``REDSIM_CACHE=0`` turns the disk cache off),
so comparing several subspaces of one scene, in one process or across runs, solves the full
space once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import os
import tempfile
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch
from torch import Tensor

import redsim
from redsim.effects.elastic import NeoHookean, deformation_gradient
from redsim.hessian import energy_hessian
from redsim.integrators import (
    FullSpace,
    Inertia,
    LatentSpace,
    PotentialObjective,
    latent_equilibrium,
    map_condition_dim,
    static_equilibrium,
)
from redsim.scene import LoadsLike, Scene
from redsim.solvers import SHIFT_FLOOR, SolveInfo, convergence_threshold, newton
from redsim.subspace import periodic_latents, sample_latents

logger = logging.getLogger(__name__)

RESPONSE_FRACTION = 0.1
"""Default load magnitude: the linear response along the softest handle direction is this fraction of the size L."""
DISPLACEMENT_FLOOR = 1e-6
"""Smallest load response, relative to the M-norm size of the scene, that relative errors divide by."""
RELATIVE_ENERGY_FLOOR = 1e-9
"""Seed-to-rest energy drop, relative to the energies involved, below which the relative energy is undefined."""
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
CHUNK = 256
"""Latent samples mapped and evaluated per batch (bounds memory on large scenes)."""
CACHE_SIZE = 256
"""Full-space equilibria kept in the in-memory cache (least recently used dropped first)."""
CACHE_ENV = "REDSIM_CACHE"
"""Environment variable naming redsim's cache folder; "0", "off", "false", "no" or "" turn the disk cache off."""
DISK_CACHE_VERSION = 1
"""Part of every disk cache key (with redsim's version): bump it when the full-space solver or an
energy changes what the solves return without changing the scene's data (the digest covers data, not code)."""

Subspace = Callable[..., Tensor]
_CACHE: OrderedDict[tuple[str, ...], tuple[Tensor, bool, float]] = OrderedDict()


def pair_log_ratios(y: Tensor, z: Tensor, scene: Scene, sigma: float, periodic: Sequence[int] = ()) -> Tensor:
    """log(|y_i - y_j|_M / (sigma |z_i - z_j|)) for all pairs i < j, shape [B(B-1)/2].

    M-norm distances come from the B x B Gram matrix of the centred batch (never a B x B x n
    tensor; centring keeps small differences in float32). Periodic latents are angles: their
    difference is wrapped into [-pi, pi) (the distance along the circle), so two samples
    2 pi apart count as the same point.

    Args:
        y: Map outputs, shape [B, n].
        z: Latents, shape [B, d].
        scene: Supplies the mass matrix (in y's dtype).
        sigma: Scale σ [the unit of |q|_M per unit z].
        periodic: Indices of the latents that are angles.
    """
    y = y - y.mean(0, keepdim=True)
    gram = y @ scene.mass_matvec(y).T
    diag = torch.arange(y.shape[0], device=y.device)
    sq = gram[diag, diag]  # not gram.diagonal(): its torch.compile lowering warns in torch 2.13
    i, j = torch.triu_indices(y.shape[0], y.shape[0], offset=1, device=y.device)
    dq2 = (sq[i] + sq[j] - 2.0 * gram[i, j]).clamp_min(torch.finfo(y.dtype).tiny)
    dz = z[i] - z[j]
    if periodic:
        angle = torch.zeros(z.shape[-1], dtype=torch.bool, device=z.device)
        angle[list(periodic)] = True
        dz = torch.where(angle, torch.remainder(dz + math.pi, 2.0 * math.pi) - math.pi, dz)
    dz2 = (dz**2).sum(-1).clamp_min(torch.finfo(z.dtype).tiny)  # equal samples do occur (d = 1, float32)
    return 0.5 * (torch.log(dq2) - torch.log(dz2)) - math.log(sigma)


def clear_cache(*, disk: bool = False) -> None:
    """Forget the cached full-space equilibria: in memory, and with ``disk=True`` also on disk."""
    _CACHE.clear()
    directory = cache_directory() if disk else None
    if directory is not None and directory.is_dir():
        for path in directory.glob("*.npz"):
            path.unlink(missing_ok=True)


def cache_directory() -> Path | None:
    """The folder of the disk cache of full-space equilibria, or None when it is off.

    ``$REDSIM_CACHE/equilibria`` when the variable names a folder; off when it is "0", "off",
    "false", "no" or empty; by default ``$XDG_CACHE_HOME/redsim/equilibria``, else
    ``~/.cache/redsim/equilibria``. Read at every use, so tests can point it elsewhere.

    Entries are keyed like the in-memory cache (scene content digest, condition, load) plus
    redsim's version and the solver settings (DISK_CACHE_VERSION, FULL_TOL, NEWTON_ITER,
    NEWTON_REUSE, RELAX_STEPS, RELAX_MOVE, ESCAPES), one ``.npz`` file each, written atomically;
    unreadable or mismatched files are ignored with a warning and solved again. Non-converged
    results are kept too (they say so). The digest covers the scene's data, not the code of its
    energies: after changing an energy's code, bump DISK_CACHE_VERSION or call
    ``clear_cache(disk=True)``.
    """
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        if value.strip().lower() in ("", "0", "off", "false", "no"):
            return None
        return Path(value).expanduser() / "equilibria"
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "redsim" / "equilibria"


def energy_stats(
    scene: Scene, subspace: Subspace, *, samples: int = 1000, seed: int = 0, cond: Tensor | None = None
) -> dict[str, Any]:
    """Energies E(f(z)) [J] of subspace states, z ~ N(0, I), and how they compare with the seed's.

    Energies carry arbitrary constants (gravity's zero level), so only differences mean
    anything. The reference points are the seed q_seed and the rest equilibrium q_rest, the
    full-space static equilibrium without loads reached from the seed (Newton, with the
    relaxation fallback and saddle escapes of :func:`load_response_error`; cached):

    - ``excess_energy`` = mean E(f(z)) - E(q_rest) [J], >= 0 unless a sample finds a lower basin;
    - ``relative_energy`` = excess_energy / (E(q_seed) - E(q_rest)), unit-free: 0 when the states
      are on average as low as the rest equilibrium, 1 when they are as high as the seed (e.g. a
      cloth held flat), above 1 when higher. It is None (undefined) when the seed already is at
      rest (no gravity or preload: the drop is below ``RELATIVE_ENERGY_FLOOR`` times the
      energies involved); then compare ``excess_energy`` between subspaces of one scene.

    Args:
        scene: The scene (evaluated in float64).
        subspace: The map (module doc).
        samples: Number of latent samples (>= 1).
        seed: Seed of the latent samples.
        cond: Condition [m] of the energy (and of a conditional map); default: the scene's.

    Returns:
        ``mean_energy``, ``median_energy``, ``max_energy``, ``min_energy``, ``seed_energy``,
        ``rest_energy`` [J], ``rest_converged``, ``excess_energy`` [J], ``relative_energy``,
        ``samples``, ``seed``.
    """
    _check_count("samples", samples, 1)
    space = _latent_space(scene, subspace, cond)
    scene64 = space.scene
    z = _latents(samples, space, seed)
    energies = torch.cat([scene64.energy(q, cond=cond) for q in _configurations(space, z)])
    seed_energy = float(scene64.energy(scene64.q_seed.unsqueeze(0), cond=cond)[0])
    rest, rest_converged, _ = _rest_equilibrium(scene64, cond)
    rest_energy = float(scene64.energy(rest.unsqueeze(0), cond=cond)[0])
    mean = float(energies.mean())
    drop = seed_energy - rest_energy
    floor = RELATIVE_ENERGY_FLOOR * max(abs(seed_energy), abs(rest_energy), abs(mean))
    return {
        "samples": samples,
        "seed": seed,
        "mean_energy": mean,
        "median_energy": float(energies.median()),
        "max_energy": float(energies.max()),
        "min_energy": float(energies.min()),
        "seed_energy": seed_energy,
        "rest_energy": rest_energy,
        "rest_converged": rest_converged,
        "excess_energy": mean - rest_energy,
        "relative_energy": (mean - rest_energy) / drop if drop > floor else None,
    }


def stretch_stats(
    scene: Scene, subspace: Subspace, sigma: float, *, samples: int = 256, seed: int = 0, cond: Tensor | None = None
) -> dict[str, Any]:
    """The metric stretch s = |f(z) - f(z')|_M / (sigma |z - z'|) over all pairs of samples.

    Supplement A.1: a good fit keeps the mean near 1 (the map spreads its states by sigma per
    unit z in the mass metric) but not within 1e-3 of it everywhere (then it is forced affine).
    An isometric affine map f(z) = b + sigma A z with A^T M A = I has s = 1 for every pair.

    Args:
        scene: The scene (supplies M, float64).
        subspace: The map (module doc).
        sigma: σ [the unit of |q|_M per unit z], > 0.
        samples: Number of latent samples (>= 2); all samples (samples - 1) / 2 pairs are used.
        seed: Seed of the latent samples.
        cond: Condition of a conditional map; default: the scene's.

    Returns:
        ``mean``, ``std``, ``min``, ``max`` of s, ``mean_log`` (mean of log s) and
        ``rms_log`` (the root of the fitting loss's pair term), ``pairs``, ``sigma``, ``samples``, ``seed``.
    """
    _check_count("samples", samples, 2)
    if not (math.isfinite(sigma) and sigma > 0.0):
        raise ValueError(f"sigma must be finite and > 0, got {sigma!r}")
    space = _latent_space(scene, subspace, cond)
    z = _latents(samples, space, seed)
    y = torch.cat(list(_configurations(space, z)))
    log_ratio = pair_log_ratios(y, z, space.scene, sigma, periodic_latents(space.subspace))
    stretch = torch.exp(log_ratio)
    return {
        "samples": samples,
        "seed": seed,
        "sigma": float(sigma),
        "pairs": int(stretch.numel()),
        "mean": float(stretch.mean()),
        "std": float(stretch.std()),
        "min": float(stretch.min()),
        "max": float(stretch.max()),
        "mean_log": float(log_ratio.mean()),
        "rms_log": float(torch.sqrt((log_ratio**2).mean())),
    }


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
        ``response_errors`` (per load) and ``mean_response_error``,
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
    _check_count("restarts", restarts, 0)
    space = _latent_space(scene, subspace, cond)
    scene64 = space.scene
    rest, rest_converged, _ = _rest_equilibrium(scene64, cond)
    generator = torch.Generator().manual_seed(seed)
    magnitudes: dict[str, float] | None = None
    if loads is None:
        _check_count("count", count, 1)
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
    size = _scene_size(scene64, mass)
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
        target, full_converged, full_energy = _full_equilibrium(scene64, load, cond, rest)
        q, info = subspace_equilibrium(load)
        error = _m_norm(mass, q - target)
        displacement = _m_norm(mass, target - rest)
        scale = max(displacement, DISPLACEMENT_FLOOR * size)
        rows.append(
            {
                "error": error / scale,
                "response": _m_norm(mass, (q - q_sub_rest) - (target - rest)) / scale,
                "absolute": error,
                "displacement": displacement,
                "gap": info.energy - full_energy,
                "full": full_converged,
                "latent": info.converged,
            }
        )
    errors = np.array([r["error"] for r in rows])
    return {
        "errors": errors.tolist(),
        "mean_error": float(errors.mean()),
        "median_error": float(np.median(errors)),
        "max_error": float(errors.max()),
        "response_errors": [r["response"] for r in rows],
        "mean_response_error": float(np.mean([r["response"] for r in rows])),
        "absolute_errors": [r["absolute"] for r in rows],
        "displacements": [r["displacement"] for r in rows],
        "energy_gaps": [r["gap"] for r in rows],
        "full_converged": [r["full"] for r in rows],
        "latent_converged": [r["latent"] for r in rows],
        "rest_converged": rest_converged,
        "rest_error": _m_norm(mass, q_sub_rest - rest),
        "rest_latent_converged": rest_info.converged,
        "loads": [load.tolist() for load in load_list],
        "handles": list(scene64.handle_names),
        "magnitudes": magnitudes,
        "response_fraction": response_fraction if loads is None and magnitude is None else None,
        "seed": seed,
        "restarts": restarts,
        "minimizer": minimizer,
    }


def nonrigid_strain(
    scene: Scene, subspace: Subspace, *, samples: int = 256, seed: int = 0, cond: Tensor | None = None
) -> dict[str, Any]:
    """Mean Green strain of subspace states of a FEM scene (figure "rigidity").

    Per state: the rest-volume-weighted mean over all neo-Hookean elements of
    |E|_F = |F^T F - I|_F / 2, with F the element's deformation gradient. It is 0 for rigid
    motions of the rest shape, and about |strain| for small deformations; linear subspaces of a
    swinging stiff body shear (strain grows with the rotation angle) where neural ones rotate.

    Args:
        scene: A scene with :class:`redsim.effects.NeoHookean` effects.
        subspace: The map (module doc).
        samples: Number of latent samples z ~ N(0, I) (>= 1).
        seed: Seed of the latent samples.
        cond: Condition of a conditional map; default: the scene's.

    Returns:
        ``mean``, ``median``, ``max`` over the samples, ``seed_strain`` (of q_seed), ``samples``, ``seed``.

    Raises:
        ValueError: for a scene without neo-Hookean elements.
    """
    _check_count("samples", samples, 1)
    space = _latent_space(scene, subspace, cond)
    scene64 = space.scene
    fem = [e for e in scene64.effects if isinstance(e, NeoHookean)]
    if not fem:
        raise ValueError(
            f"scene {scene.name!r} has no neo-Hookean (FEM) effects; its effects are {[e.name for e in scene.effects]}"
        )
    z = _latents(samples, space, seed)
    strain = torch.cat([_mean_strain(scene64, fem, q) for q in _configurations(space, z)])
    seed_strain = float(_mean_strain(scene64, fem, scene64.q_seed.unsqueeze(0))[0])
    return {
        "samples": samples,
        "seed": seed,
        "mean": float(strain.mean()),
        "median": float(strain.median()),
        "max": float(strain.max()),
        "seed_strain": seed_strain,
    }


def reach_error(
    scene: Scene,
    subspace: Subspace,
    targets: Sequence[Tensor],
    *,
    samples: int = 4096,
    refine: int = 4,
    seed: int = 0,
    cond: Tensor | None = None,
) -> dict[str, Any]:
    """How close the subspace comes to given configurations: min_z |f(z) - q_t|_M per target.

    The search samples z ~ N(0, 4 I) (``samples`` of them, wider than the fitting distribution
    so tails count), then refines the ``refine`` nearest by L-BFGS over z. The error is relative
    to the target's distance from the seed, |q_t - q_seed|_M: 0 means the subspace contains
    q_t, 1 is what a subspace that only holds the seed scores.

    Args:
        scene: The scene.
        subspace: The map (module doc).
        targets: Configurations q_t [n] (float64 or castable).
        samples: Latent samples of the coarse search (>= 1).
        refine: Nearest samples refined by L-BFGS (>= 1).
        seed: Seed of the samples.
        cond: Condition of a conditional map; default: the scene's.

    Returns:
        ``errors`` (relative, per target), ``distances`` (|f(z*) - q_t|_M [kg^1/2 m]),
        ``latents`` (z* per target), ``samples``, ``seed``.
    """
    _check_count("samples", samples, 1)
    _check_count("refine", refine, 1)
    space = _latent_space(scene, subspace, cond)
    scene64 = space.scene
    mass = scene64.mass_matrix_scipy()
    z = 2.0 * _latents(samples, space, seed)
    states = torch.cat(_configurations(space, z))
    rows = []
    for target in targets:
        target = target.detach().to(states)
        gaps = (states - target).numpy()
        coarse = np.einsum("bi,bi->b", gaps, (mass @ gaps.T).T)
        best: tuple[float, Tensor] = (math.inf, z[0])
        for start in z[np.argsort(coarse)[:refine]]:
            best = min(best, _nearest_latent(space, mass, target, start), key=lambda pair: pair[0])
        scale = _m_norm(mass, target - scene64.q_seed)
        rows.append((best[0], best[0] / max(scale, DISPLACEMENT_FLOOR * _scene_size(scene64, mass)), best[1]))
    return {
        "errors": [r[1] for r in rows],
        "distances": [r[0] for r in rows],
        "latents": [r[2].tolist() for r in rows],
        "samples": samples,
        "seed": seed,
    }


def handle_winding(
    scene: Scene,
    subspace: Subspace,
    handle: str,
    center: Sequence[float],
    *,
    latent: int = 0,
    samples: int = 360,
    cond: Tensor | None = None,
) -> dict[str, Any]:
    """How far a handle turns about a point as one periodic latent goes once round the circle.

    Latent ``latent`` sweeps [-pi, pi] in ``samples`` equal steps (the others stay 0); the
    handle's position, projected on the x-y plane, is followed about ``center`` with its angle
    unwrapped. A crank whose map closes the loop turns 360 degrees (winding +-1); a map that
    swings it back and forth turns less and winds 0.

    Args:
        scene: The scene.
        subspace: A map whose latent ``latent`` is periodic (``config.periodic``).
        handle: Handle name.
        center: Pivot (x, y) [m].
        latent: Index of the periodic latent.
        samples: Steps round the circle (>= 8).
        cond: Condition of a conditional map; default: the scene's.

    Returns:
        ``winding`` (whole turns, signed), ``turn_degrees`` (range of the unwrapped angle),
        ``energy_min``/``energy_max`` [J] along the sweep, ``seed_energy`` [J], ``samples``.

    Raises:
        ValueError: an unknown handle, a latent that is not periodic, or too few samples.
    """
    _check_count("samples", samples, 8)
    if latent not in periodic_latents(subspace):
        raise ValueError(f"latent {latent} is not periodic (periodic: {list(periodic_latents(subspace))})")
    if handle not in scene.handle_names:
        raise ValueError(f"scene {scene.name!r} has no handle {handle!r}; valid handles: {list(scene.handle_names)}")
    space = _latent_space(scene, subspace, cond)
    scene64 = space.scene
    z = torch.zeros(samples + 1, space.latent_dim, dtype=torch.float64)
    z[:, latent] = torch.linspace(-math.pi, math.pi, samples + 1, dtype=torch.float64)
    q = torch.cat(_configurations(space, z))
    with torch.no_grad():
        position = scene64.handles[scene64.handle_names.index(handle)].position(scene64.dof_map.expand(q))
        energy = scene64.energy(q, cond=cond)
    offset = (position[:, :2] - torch.as_tensor(center, dtype=torch.float64)[:2]).numpy()
    angle = np.unwrap(np.arctan2(offset[:, 1], offset[:, 0]))
    return {
        "winding": round(float(angle[-1] - angle[0]) / (2.0 * math.pi)),
        "turn_degrees": float(np.degrees(angle.max() - angle.min())),
        "energy_min": float(energy.min()),
        "energy_max": float(energy.max()),
        "seed_energy": float(scene64.energy(scene64.q_seed.unsqueeze(0), cond=cond)[0]),
        "samples": samples,
    }


def buckled_states(scene: Scene, *, bump: float = 0.01, cond: Tensor | None = None) -> list[Tensor]:
    """The two buckled equilibria of a compressed bar (``bistable_bar``): arched up and down.

    Each is the full-space static equilibrium (tolerance FULL_TOL) reached from the seed with
    every free DOF along the scene's last axis (y) moved by +-bump * extent * sin(pi s), s in
    [0, 1] the particle's position along x between the pins.

    Args:
        scene: A 2D or 3D scene whose seed is a straight compressed bar along x.
        bump: Size of the initial arch, relative to the scene's extent.
        cond: Condition of the energy; default: the scene's.

    Returns:
        [q_up, q_down], each [n] float64.

    Raises:
        RuntimeError: a solve did not converge, or both starts reached the same state.
    """
    scene64 = scene if scene.dtype == torch.float64 else scene.to(dtype=torch.float64)
    positions = scene64.full_positions(scene64.q_seed.unsqueeze(0))[0].reshape(-1, scene64.dim)
    x = positions[:, 0]
    s = (x - x.min()) / (x.max() - x.min())
    shape = torch.zeros_like(positions)
    shape[:, -1] = torch.sin(math.pi * s)
    direction = scene64.dof_map.restrict(shape.reshape(1, -1))[0] * bump * scene64.extent()
    states = []
    for sign in (1.0, -1.0):
        q, info = static_equilibrium(scene64, None, cond, q0=scene64.q_seed + sign * direction, tol=FULL_TOL)
        if not info.converged:
            raise RuntimeError(f"buckled state of {scene.name!r} did not converge: {info.message}")
        states.append(q.detach())
    mass = scene64.mass_matrix_scipy()
    if _m_norm(mass, states[0] - states[1]) < _m_norm(mass, direction):  # closer than the two starts were
        raise RuntimeError(f"scene {scene.name!r}: both bumps reached the same equilibrium (not bistable)")
    return states


def evaluate_subspace(
    scene: Scene,
    subspace: Subspace,
    *,
    sigma: float | None = None,
    loads_count: int = 8,
    response_fraction: float = RESPONSE_FRACTION,
    samples: int = 256,
    seed: int = 0,
    cond: Tensor | None = None,
) -> dict[str, Any]:
    """All metrics of one subspace on its scene, as one JSON-serializable dict.

    Args:
        scene: The scene.
        subspace: The map (module doc).
        sigma: σ of the stretch; default: the fitted one in ``subspace.metadata["fit"]["sigma"]``.
        loads_count: Loads of :func:`load_response_error` (0, or a scene without handles, skips it).
        response_fraction: Their size (:func:`load_response_error`).
        samples: Latent samples of the energy, stretch and strain statistics.
        seed: Seed of every sample and load.
        cond: Condition [m] of the energy and of a conditional map; default: the scene's.

    Returns:
        ``scene``, ``scene_fingerprint``, ``latent_dim``, ``energy`` (:func:`energy_stats`),
        ``stretch`` (:func:`stretch_stats`), ``load_response`` (:func:`load_response_error`, when
        run), ``nonrigid_strain`` (:func:`nonrigid_strain`, FEM scenes only) and ``seconds``
        (wall time of each part; full-space solves may come from the cache).

    Raises:
        ValueError: no sigma given and none in the map's metadata.
    """
    if sigma is None:
        sigma = getattr(subspace, "metadata", {}).get("fit", {}).get("sigma")
        if sigma is None:
            raise ValueError("give sigma: the subspace's metadata has no fit sigma")
    _check_count("loads_count", loads_count, 0)
    parts: dict[str, Callable[[], dict[str, Any]]] = {
        "energy": lambda: energy_stats(scene, subspace, samples=samples, seed=seed, cond=cond),
        "stretch": lambda: stretch_stats(scene, subspace, float(sigma), samples=samples, seed=seed, cond=cond),
    }
    if loads_count and scene.handles:
        parts["load_response"] = lambda: load_response_error(
            scene, subspace, count=loads_count, response_fraction=response_fraction, seed=seed, cond=cond
        )
    if any(isinstance(e, NeoHookean) for e in scene.effects):
        parts["nonrigid_strain"] = lambda: nonrigid_strain(scene, subspace, samples=samples, seed=seed, cond=cond)
    out: dict[str, Any] = {
        "scene": scene.name,
        "scene_fingerprint": scene.fingerprint(),
        "latent_dim": int(subspace.latent_dim),  # type: ignore[attr-defined]
    }
    seconds = {}
    for name, part in parts.items():
        start = time.perf_counter()
        out[name] = part()
        seconds[name] = time.perf_counter() - start
        logger.info("%s of %s: %.3g s", name, scene.name, seconds[name])
    out["seconds"] = seconds
    return out


# -- helpers -------------------------------------------------------------------------------------
def _check_count(name: str, value: int, low: int) -> None:
    if int(value) != value or value < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")


def _latent_space(scene: Scene, subspace: Subspace, cond: Tensor | None) -> LatentSpace:
    """The latent space of the map, at condition ``cond`` if the map is conditional."""
    return LatentSpace(scene, subspace, cond=cond if map_condition_dim(subspace) else None)


def _latents(samples: int, space: LatentSpace, seed: int) -> Tensor:
    """Latent samples [samples, d] of the space's map (:func:`redsim.subspace.sample_latents`), float64, seeded."""
    generator = torch.Generator().manual_seed(seed)
    return sample_latents(
        samples, space.latent_dim, periodic_latents(space.subspace), generator=generator, dtype=torch.float64
    )


def _configurations(space: LatentSpace, z: Tensor) -> list[Tensor]:
    """f(z) [B, n] (float64) in chunks of at most CHUNK samples."""
    with torch.no_grad():
        return [space.configuration(chunk) for chunk in z.split(CHUNK)]


def _m_norm(mass: Any, v: Tensor) -> float:
    """|v|_M [kg^1/2 m] of a vector v [n]."""
    x = v.detach().cpu().numpy()
    return math.sqrt(max(float(x @ (mass @ x)), 0.0))


def _mean_strain(scene: Scene, effects: list[NeoHookean], q: Tensor) -> Tensor:
    """Rest-volume-weighted mean |F^T F - I|_F / 2 over the elements of ``effects``, shape [B], for q [B, n]."""
    x = scene.full_positions(q)
    total = q.new_zeros(q.shape[0])
    volume = 0.0
    for effect in effects:
        D = effect.dim
        xe = x[:, effect.element_dofs].reshape(q.shape[0], -1, D + 1, D)
        F = deformation_gradient(xe, effect.shape_gradients)
        strain = torch.linalg.matrix_norm(F.transpose(-1, -2) @ F - torch.eye(D, dtype=F.dtype)) / 2.0
        total = total + strain @ effect.rest_volume
        volume += float(effect.rest_volume.sum())
    return total / volume


def _scene_size(scene: Scene, mass: Any) -> float:
    """S = sqrt(sum diag M) L [kg^1/2 m], the M-norm size of the scene (L its largest extent)."""
    return math.sqrt(float(mass.diagonal().sum())) * scene.extent()


def _nearest_latent(space: LatentSpace, mass: Any, target: Tensor, start: Tensor) -> tuple[float, Tensor]:
    """Local minimum of |f(z) - target|_M over z from ``start``: (distance [kg^1/2 m], z [d])."""
    z = start.detach().clone().requires_grad_(True)
    optimizer = torch.optim.LBFGS([z], max_iter=200, line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        optimizer.zero_grad()
        gap = space.configuration(z.unsqueeze(0)) - target
        value = (gap * space.scene.mass_matvec(gap)).sum()
        value.backward()
        return value

    optimizer.step(closure)
    with torch.no_grad():
        q = space.configuration(z.unsqueeze(0))[0]
    return _m_norm(mass, q - target), z.detach()


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


def rest_state(scene: Scene, cond: Tensor | None = None) -> tuple[Tensor, bool]:
    """The unloaded full-space equilibrium that load errors are measured around (cached).

    Newton from the seed, with the relaxation fallback and saddle escapes of
    :func:`load_response_error`, in float64. Baselines built here share its reference.

    Returns:
        q_rest [n] (float64) and whether the solve converged.
    """
    q, converged, _ = _rest_equilibrium(scene.to(dtype=torch.float64), cond)
    return q, converged


def _rest_equilibrium(scene: Scene, cond: Tensor | None) -> tuple[Tensor, bool, float]:
    """The unloaded full-space equilibrium reached by Newton from the seed (cached): q [n], converged, energy [J]."""
    return _full_equilibrium(scene, None, cond, None)


def _full_equilibrium(
    scene: Scene, load: Tensor | None, cond: Tensor | None, start: Tensor | None
) -> tuple[Tensor, bool, float]:
    """Full-space static equilibrium under ``load`` [H, D] from ``start`` (None: the seed), cached.

    The key is the scene's content, the condition and the load (loaded solves always start at
    the rest equilibrium, itself a function of the scene and condition). Misses of the
    in-memory cache look in the disk cache (:func:`cache_directory`) before solving.
    """
    packed_cond = scene.pack_condition(cond, 1, scene.q_seed)
    key = (
        _scene_digest(scene),
        "" if packed_cond is None else packed_cond.numpy().tobytes().hex(),
        "" if load is None else load.numpy().tobytes().hex(),
    )
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    settings = (
        redsim.__version__,
        DISK_CACHE_VERSION,
        FULL_TOL,
        NEWTON_ITER,
        NEWTON_REUSE,
        RELAX_STEPS,
        RELAX_MOVE,
        ESCAPES,
    )
    disk_key = "|".join([*map(repr, settings), *key])
    directory = cache_directory()
    path = None if directory is None else directory / f"{hashlib.sha256(disk_key.encode()).hexdigest()}.npz"
    result = None if path is None else _read_entry(path, disk_key, scene.free_dof_count)
    if result is None:
        result = _solve_full(scene, load, cond, scene.q_seed if start is None else start)
        if path is not None:
            _write_entry(path, disk_key, result)
    _CACHE[key] = result
    while len(_CACHE) > CACHE_SIZE:
        _CACHE.popitem(last=False)
    return result


def _read_entry(path: Path, key: str, n: int) -> tuple[Tensor, bool, float] | None:
    """A disk cache entry (q [n], converged, energy), or None if there is none or it is unusable (warned)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            stored_key, q = str(data["key"]), np.array(data["q"], dtype=np.float64)
            converged, energy = bool(data["converged"]), float(data["energy"])
        if stored_key != key:
            raise ValueError("the file belongs to another key")
        if q.shape != (n,) or not np.all(np.isfinite(q)):
            raise ValueError(f"q has shape {q.shape} or is not finite; expected [{n}]")
    except Exception as error:  # any damage (truncated, not a zip, missing fields) means: solve again
        logger.warning("ignoring unreadable equilibrium cache file %s (%s); solving again", path, error)
        return None
    logger.debug("full-space equilibrium from the disk cache %s", path)
    return torch.from_numpy(q), converged, energy


def _write_entry(path: Path, key: str, result: tuple[Tensor, bool, float]) -> None:
    """Store a result atomically (temporary file, then rename); failures are warned, never raised."""
    q, converged, energy = result
    temporary: Path | None = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=".", suffix=".npz.tmp", delete=False) as file:
            temporary = Path(file.name)
            np.savez(
                file,
                key=np.array(key),
                q=q.detach().cpu().numpy().astype(np.float64),
                converged=np.array(bool(converged)),
                energy=np.array(float(energy)),
            )
        temporary.chmod(0o644)  # a temporary file is private; the cache is not
        os.replace(temporary, path)
    except OSError as error:
        logger.warning("could not write the equilibrium cache file %s (%s)", path, error)
        if temporary is not None:
            temporary.unlink(missing_ok=True)


def _solve_full(scene: Scene, load: Tensor | None, cond: Tensor | None, start: Tensor) -> tuple[Tensor, bool, float]:
    """A stable full-space equilibrium under ``load`` reached from ``start``: (q [n], converged, E(q; load) [J]).

    Converged means |dE/dq| <= FULL_TOL * max(|g(start)|, F), the rule of
    :func:`static_equilibrium` (F: the summed force norms at ``start``), reached by
    :func:`_descend` (Newton, then relaxation). A force balance can also hold near a saddle: the
    24-link chain falling from its seed came to rest 1 J above its hanging minimum, balanced
    with all links turned 7.5 degrees, where the unprojected Hessian had eigenvalues (over M) of
    -1.7e4 1/s^2; the two-link chain's rest from its seed is such a saddle too. So a converged
    point whose unprojected Hessian K has a direction of negative curvature (K + s M not
    positive definite, s = SHIFT_FLOOR times the ratio of their diagonals, the shift of
    :func:`_handle_magnitudes`) is left along that direction, to the side and distance (at most
    the trust radius, halved until the energy drops) of lower energy, and solved again; at most
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


def _negative_curvature(scene: Scene, q: Tensor, loads: Tensor | None, cond: Tensor | None) -> Tensor | None:
    """A direction v [n] (largest entry 1) with v^T K v < -s v^T M v, or None if K + s M is positive definite.

    K is the unprojected energy Hessian at q and s = SHIFT_FLOOR * |diag K| / |diag M| (round-off
    and exact null modes stay above -s). The test is the inertia of a symmetric sparse LU with
    diagonal pivots (K + s M = P^T U^T D^-1 U P): a negative pivot d_i gives v = P^T U^-1 e_i
    with v^T (K + s M) v = 1 / d_i < 0. None also when the factorization is singular or not
    symmetric (no verdict).
    """
    stiffness = energy_hessian(scene, q, loads, cond, project=False)
    mass = scene.mass_matrix_scipy()
    ratio = float(np.linalg.norm(stiffness.diagonal()) / np.linalg.norm(mass.diagonal()))
    shift = SHIFT_FLOOR * (ratio if ratio > 0.0 else 1.0)
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


def _scene_digest(scene: Scene) -> str:
    """Hash of everything a scene holds (its fingerprint alone does not tell apart scenes built by hand)."""
    digest = hashlib.sha256(scene.fingerprint().encode())
    _feed(digest, [scene.dof_map, scene.mass_matrix, scene.q_seed, scene.effects, scene.handles, scene.condition_space])
    return digest.hexdigest()


def _feed(digest: Any, value: Any) -> None:
    if isinstance(value, Tensor):
        if value.is_sparse:
            value = value.coalesce()
            _feed(digest, [value.indices(), value.values()])
            return
        digest.update(f"{value.dtype}{tuple(value.shape)}".encode())
        digest.update(value.detach().cpu().contiguous().numpy().tobytes())
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        digest.update(type(value).__name__.encode())
        _feed(digest, [getattr(value, f.name) for f in dataclasses.fields(value)])
    elif isinstance(value, Mapping):
        for key in sorted(value, key=str):
            digest.update(str(key).encode())
            _feed(digest, value[key])
    elif isinstance(value, (list, tuple)):
        digest.update(f"[{len(value)}".encode())
        for item in value:
            _feed(digest, item)
    elif hasattr(value, "__dict__") and not isinstance(value, type):
        digest.update(type(value).__name__.encode())
        _feed(digest, vars(value))
    else:
        digest.update(repr(value).encode())


__all__ = [
    "cache_directory",
    "clear_cache",
    "energy_stats",
    "evaluate_subspace",
    "handle_winding",
    "load_response_error",
    "nonrigid_strain",
    "pair_log_ratios",
    "rest_state",
    "stretch_stats",
]
