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

Full-space equilibria are the expensive part; they are cached per scene content, condition
and loads (:func:`clear_cache`), so comparing several subspaces of one scene solves the full
space once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch
from torch import Tensor

from redsim.effects.elastic import NeoHookean
from redsim.hessian import energy_hessian
from redsim.integrators import (
    FullSpace,
    FullState,
    ImplicitEuler,
    LatentSpace,
    PotentialObjective,
    latent_equilibrium,
    map_condition_dim,
    static_equilibrium,
)
from redsim.scene import LoadsLike, Scene
from redsim.solvers import SHIFT_FLOOR, SolveInfo, convergence_threshold

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
RELAX_STEPS = 200
"""Most proximal steps of a relaxation."""
RELAX_MOVE = 0.01
"""Proximal steps move the fastest DOF about this fraction of the scene size (4x more is rejected)."""
CHUNK = 256
"""Latent samples mapped and evaluated per batch (bounds memory on large scenes)."""
CACHE_SIZE = 256
"""Full-space equilibria kept in the cache (least recently used dropped first)."""

Subspace = Callable[..., Tensor]
_CACHE: OrderedDict[tuple[str, ...], tuple[Tensor, bool, float]] = OrderedDict()


def pair_log_ratios(y: Tensor, z: Tensor, scene: Scene, sigma: float) -> Tensor:
    """log(|y_i - y_j|_M / (sigma |z_i - z_j|)) for all pairs i < j, shape [B(B-1)/2].

    M-norm distances come from the B x B Gram matrix of the centred batch (never a B x B x n
    tensor; centring keeps small differences in float32).

    Args:
        y: Map outputs, shape [B, n].
        z: Latents, shape [B, d].
        scene: Supplies the mass matrix (in y's dtype).
        sigma: Scale σ [the unit of |q|_M per unit z].
    """
    y = y - y.mean(0, keepdim=True)
    gram = y @ scene.mass_matvec(y).T
    sq = gram.diagonal()
    i, j = torch.triu_indices(y.shape[0], y.shape[0], offset=1, device=y.device)
    dq2 = (sq[i] + sq[j] - 2.0 * gram[i, j]).clamp_min(torch.finfo(y.dtype).tiny)
    dz2 = ((z[i] - z[j]) ** 2).sum(-1)
    return 0.5 * (torch.log(dq2) - torch.log(dz2)) - torch.log(torch.as_tensor(sigma, dtype=y.dtype))


def clear_cache() -> None:
    """Forget the cached full-space equilibria."""
    _CACHE.clear()


def energy_stats(
    scene: Scene, subspace: Subspace, *, samples: int = 1000, seed: int = 0, cond: Tensor | None = None
) -> dict[str, Any]:
    """Energies E(f(z)) [J] of subspace states, z ~ N(0, I), and how they compare with the seed's.

    Energies carry arbitrary constants (gravity's zero level), so only differences mean
    anything. The reference points are the seed q_seed and the rest equilibrium q_rest, the
    full-space static equilibrium without loads reached from the seed (Newton, with the
    relaxation fallback of :func:`load_response_error`; cached):

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
    z = _latents(samples, space.latent_dim, seed)
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
    z = _latents(samples, space.latent_dim, seed)
    y = torch.cat(list(_configurations(space, z)))
    log_ratio = pair_log_ratios(y, z, space.scene, sigma)
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
    relaxation fallback, to a relative force balance of FULL_TOL) and the subspace equilibrium
    f(z*_l) (:func:`redsim.integrators.latent_equilibrium` from z = 0 and from ``restarts``
    seeded z ~ N(0, I), keeping the lowest potential E(f(z); l)). The error is relative to the
    load's own response:

        error_l = |f(z*_l) - q*_l|_M / max(|q*_l - q_rest|_M, DISPLACEMENT_FLOOR * S),

    S = sqrt(sum diag M) L the M-norm size of the scene (L: its largest surface extent at the seed).
    0 means the subspace reproduces the response exactly; 1 is what a subspace that does not
    move at all (f(z*) = q_rest) scores.

    Default loads: ``count`` loads, load i a force on handle i mod H only (handles in scene
    order), in a uniformly random direction (seeded), of magnitude RESPONSE_FRACTION * L / c_h,
    where c_h [m/N] is the largest eigenvalue of handle h's linearized compliance G_h^T K^-1 G_h
    at q_rest (K the projected energy Hessian, shifted by SHIFT_FLOOR times its diagonal ratio
    to M so null modes stay finite; G_h [n, D] the generalized forces of unit handle forces):
    the linear response along the handle's softest direction is 10% of the scene size,
    whatever the units, stiffness or weight. The loads used are returned.

    Args:
        scene: The scene; it needs handles.
        subspace: The map (module doc).
        loads: Explicit loads, each as accepted by :meth:`Scene.pack_loads` ([H, D] or a
            {handle: force} mapping) [N]; replaces ``count`` and ``magnitude``.
        count: Number of generated loads (>= 1).
        magnitude: Force per loaded handle [N] instead of the compliance rule.
        seed: Seed of the load directions and of the latent restarts.
        cond: Condition [m] of the energy (and of a conditional map); default: the scene's.
        restarts: Random latent starts besides z = 0 (>= 0).
        minimizer: Minimizer of the latent solves ("lbfgs", the paper's, or "newton", Gauss-Newton there).
        tol: Relative gradient tolerance of the latent solves (the full-space ones use FULL_TOL).
        max_iter: Most iterations per latent solve.

    Returns:
        ``errors`` (per load), ``mean_error``, ``median_error``, ``max_error``,
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
        per_handle = _handle_magnitudes(scene64, rest, cond) if magnitude is None else None
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
    size = math.sqrt(float(mass.diagonal().sum())) * scene64.extent()
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
        rows.append(
            {
                "error": error / max(displacement, DISPLACEMENT_FLOOR * size),
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
    z = _latents(samples, space.latent_dim, seed)
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


def evaluate_subspace(
    scene: Scene,
    subspace: Subspace,
    *,
    sigma: float | None = None,
    loads_count: int = 8,
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
        parts["load_response"] = lambda: load_response_error(scene, subspace, count=loads_count, seed=seed, cond=cond)
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


def _latents(samples: int, latent_dim: int, seed: int) -> Tensor:
    """z ~ N(0, I), shape [samples, d], float64, from a generator seeded with ``seed``."""
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(samples, latent_dim, generator=generator, dtype=torch.float64)


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
        F = torch.einsum("btvi,tvj->btij", xe, effect.shape_gradients)  # F = sum_v x_v (x) G_v
        strain = torch.linalg.matrix_norm(F.transpose(-1, -2) @ F - torch.eye(D, dtype=F.dtype)) / 2.0
        total = total + strain @ effect.rest_volume
        volume += float(effect.rest_volume.sum())
    return total / volume


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


def _handle_magnitudes(scene: Scene, rest: Tensor, cond: Tensor | None) -> np.ndarray:
    """RESPONSE_FRACTION * L / c_h [N] per handle (see :func:`load_response_error`), shape [H]."""
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
    return RESPONSE_FRACTION * scene.extent() / largest


def _rest_equilibrium(scene: Scene, cond: Tensor | None) -> tuple[Tensor, bool, float]:
    """The unloaded full-space equilibrium reached by Newton from the seed (cached): q [n], converged, energy [J]."""
    return _full_equilibrium(scene, None, cond, None)


def _full_equilibrium(
    scene: Scene, load: Tensor | None, cond: Tensor | None, start: Tensor | None
) -> tuple[Tensor, bool, float]:
    """Full-space static equilibrium under ``load`` [H, D] from ``start`` (None: the seed), cached.

    The key is the scene's content, the condition and the load (loaded solves always start at
    the rest equilibrium, itself a function of the scene and condition).
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
    _CACHE[key] = _solve_full(scene, load, cond, scene.q_seed if start is None else start)
    while len(_CACHE) > CACHE_SIZE:
        _CACHE.popitem(last=False)
    return _CACHE[key]


def _solve_full(scene: Scene, load: Tensor | None, cond: Tensor | None, start: Tensor) -> tuple[Tensor, bool, float]:
    """Newton from ``start``; if it fails, proximal-point relaxation from ``start``.

    Newton can run away where the start feels little restoring force: a chain held only by
    contact starts out of contact (or swings under a load), a Levenberg step is long, and the
    links pass through each other and fall. The fallback relaxes by proximal steps
    q <- argmin E(q) + |q - q_k|_M^2 / (2 h^2) (implicit Euler with the velocity zeroed), whose
    move is bounded by h^2 times the net force: h starts where the fastest DOF moves
    RELAX_MOVE L, doubles after a shorter move (near equilibrium the steps become Newton
    steps) and halves, rejecting the step, after a move over 4 RELAX_MOVE L.

    Returns:
        q [n]; converged (|dE/dq| <= FULL_TOL * F, the rule of :func:`static_equilibrium`); E(q; load) [J].
    """
    q, info = static_equilibrium(scene, load, cond, q0=start, tol=FULL_TOL, max_iter=NEWTON_ITER)
    if info.converged:
        return q.detach().clone(), True, info.energy
    logger.info("full-space Newton on %s did not converge (%s); relaxing", scene.name, info.message)
    space = FullSpace(scene)
    objective = PotentialObjective(
        space,
        loads=scene.pack_loads(load, 1, scene.q_seed),
        cond=scene.pack_condition(cond, 1, scene.q_seed),
        inertia=None,
        force=None,
        reference=start,
    )
    energy, grad = objective.value_and_grad(start)
    threshold = convergence_threshold(objective, FULL_TOL, float(torch.linalg.vector_norm(grad)))
    accel = scipy.sparse.linalg.spsolve(scene.mass_matrix_scipy().tocsc(), grad.numpy())
    limit = RELAX_MOVE * scene.extent()
    dt = math.sqrt(limit / max(float(np.abs(accel).max()), 1e-300))
    q = start.detach().clone()
    for _ in range(RELAX_STEPS):
        step = ImplicitEuler(space, dt, tol=0.01 * FULL_TOL)  # tighter than the outer test, or that stalls
        trial = step.step(FullState(q, q, 0.0), load, cond)[0].q
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
    "clear_cache",
    "energy_stats",
    "evaluate_subspace",
    "load_response_error",
    "nonrigid_strain",
    "pair_log_ratios",
    "stretch_stats",
]
