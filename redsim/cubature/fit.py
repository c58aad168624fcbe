"""Optimized cubature for one subspace map (An, Kim & James 2008), per effect, from the subspace itself.

For each effect with elements e = 1..T, the reduced force of a state z is g(z) = J^T grad_x E(f(z)) =
sum_e g_e(z) (J = dx/dz, [N, d]). A cubature keeps a few elements with weights w_e >= 0 such that
sum_e w_e g_e(z) ~ g(z), and sum_e w_e (E_e(z) - E_e(0)) ~ E(z) - E(0), on training states:

- z ~ N(0, I) (angles uniform), the sampler the map was fitted with (no simulation data), and
- the states latent rollouts visit under random piecewise-constant handle loads (the all-element
  :class:`redsim.runtime.LatentStepper`).

Each state's d + 1 rows (its reduced force and its energy) are divided by that state's scale, the norm
sqrt(|g(z)|^2 + (E(z) - E(0))^2) of the total (every effect but the load terms), so that states whose forces
differ by orders of magnitude weigh alike, and the fitted effect's error is relative to the total.
Selection is greedy: each round adds the max(1, K/8) candidates (K kept) whose columns, over their norms,
correlate best (and positively) with the current residual, then non-negative least squares
(``scipy.optimize.nnls``) refits all kept weights and an element it gives no weight leaves for good; it
stops at ``elements`` kept, when the effect's training error is below ``tol`` / sqrt(subsampled effects),
or when no candidate correlates positively. The errors reported are those of held-out states (a share of
the sampled ones, and whole rollouts; :func:`split_states`), which choose no element and no weight,
scaled per state alike: |residual| / |target| over them, ``held_out_force_error`` over the force rows alone. As each
state weighs alike, this reads otherwise than the plain relative force error sqrt(sum_s |residual_s|^2 / sum_s |F_s|^2)
(docs/cubature.md: 6.9% against 12.6% on a small conditional bar build): the summary records that one too,
``held_out_plain_force_error``, with the per-state |residual_s| / |F_s| (median and 90th percentile) and the energy
error (:func:`error_measures`).
Linear effects (gravity) stay exact, effects that switch on rarely (contact) keep all their elements by
default, and the load term belongs to the stepper (exact).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize
import torch
from torch import Tensor, nn

from redsim.cubature.output import AffineOutput
from redsim.effects.base import Effect, gather_elements
from redsim.integrators import map_condition_dim, map_tensor
from redsim.progress import progress_bar
from redsim.scene import Scene
from redsim.subspace import periodic_latents, sample_latents
from redsim.tensors import jvp

MODES = ("cubature", "full", "linear")
"""How a cubature treats an effect: a weighted subset of its elements, all of them, or exactly as a linear term."""
RARE_KINDS = ("sdf_contact",)
"""Effect kinds kept whole by default: penalties that switch on rarely, which a subset would miss."""
CANDIDATE_FLOOR = 1e-3
"""Elements whose column norm is below this fraction of the mean are never selected."""
ROUND_OFF = 1e-12
"""Training error at which the greedy selection stops whatever the budget (the fit is exact)."""
LINEAR_KINDS = ("gravity",)
"""Effect kinds that are linear in x: reduced exactly to r . c + e0."""


@dataclass(frozen=True)
class CubatureConfig:
    """How to build a cubature.

    Attributes:
        elements: Most elements kept per subsampled effect (>= 1).
        tol: Stop an effect earlier once its training error (its reduced forces and energy, relative to the total
            reduced force and energy) is below tol / sqrt(number of subsampled effects); None: keep ``elements``.
        samples: States z ~ N(0, I) (>= 2).
        episodes: Latent rollouts under random loads (>= 0).
        steps: Steps per rollout.
        hold: Steps each rollout load is held.
        load_scale: Std of each load component [N]; None: the scene's weight per handle (trace(M)/D * 9.81 / H).
        dt: Rollout time step [s].
        held_out: Fraction of the sampled states, and of the rollouts (whole ones: a rollout's neighbouring states are
            near-copies of each other), kept out of the fit for the reported error (0 < f < 1; :func:`split_states`).
        full: Effects kept whole, in place of the default; None: those of :data:`RARE_KINDS` (and, without ``tol``,
            any with at most ``elements`` elements).
        subsample: Effects subsampled even if their kind is in :data:`RARE_KINDS`.
        seed: Seeds the samples, loads and split.
    """

    elements: int = 200
    tol: float | None = None
    samples: int = 256
    episodes: int = 4
    steps: int = 40
    hold: int = 8
    load_scale: float | None = None
    dt: float = 0.02
    held_out: float = 0.25
    full: tuple[str, ...] | None = None
    subsample: tuple[str, ...] = ()
    seed: int = 0

    def __post_init__(self) -> None:
        lowest = {"elements": 1, "samples": 2, "episodes": 0, "steps": 1, "hold": 1}
        for name, low in lowest.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        both = sorted(set(self.full or ()) & set(self.subsample))
        if both:
            raise ValueError(f"effect(s) {both} are both in full (kept whole) and in subsample; name each in one")
        if self.tol is not None and not (math.isfinite(self.tol) and 0.0 < self.tol < 1.0):
            raise ValueError(  # a relative error of 1 is what keeping no element gives
                f"tol must be a relative error of the reduced forces and energy in (0, 1), e.g. 0.05, got {self.tol!r}"
            )
        if self.load_scale is not None and not (math.isfinite(self.load_scale) and self.load_scale >= 0.0):
            raise ValueError(f"load_scale must be finite and >= 0 [N], got {self.load_scale!r}")
        if not (math.isfinite(self.dt) and self.dt > 0.0):
            raise ValueError(f"dt must be finite and > 0 [s], got {self.dt!r}")
        if not 0.0 < self.held_out < 1.0:
            raise ValueError(f"held_out must be in (0, 1), got {self.held_out!r}")


@dataclass
class EffectRule:
    """What a cubature does with one effect.

    Attributes:
        name: The effect's name in the scene.
        mode: One of :data:`MODES`.
        element_count: The effect's number of elements T.
        indices: Kept elements (``mode == "cubature"``), shape [K], int64; all for "full"; none for "linear".
        weights: Their weights (>= 0), shape [K].
        train_error: Relative force error on the training states (cubature only; else 0).
        held_out_error: The same on held-out states.
    """

    name: str
    mode: str
    element_count: int
    indices: Tensor
    weights: Tensor
    train_error: float = 0.0
    held_out_error: float = 0.0
    history: list[tuple[int, float, float]] = field(default_factory=list)
    """(kept, train error, held-out error) after each greedy round."""


def default_load_scale(scene: Scene) -> float:
    """Std of each rollout load component [N]: the scene's weight per handle, trace(M)/D * 9.81 / H."""
    if not scene.handles:
        return 0.0
    mass = scene.mass_matrix.coalesce()
    rows, cols = mass.indices()
    trace = float(mass.values()[rows == cols].sum())
    return trace / scene.dim * 9.81 / len(scene.handles)


def training_states(
    scene: Scene, subspace: nn.Module, config: CubatureConfig, *, progress: Callable[[], None] | None = None
) -> tuple[Tensor, Tensor | None, dict[str, int], Tensor]:
    """Latents [S, d] (float64) and conditions [S, m] (or None) of the training and held-out states, how many
    rollout steps were dropped: ``{"diverged": ..., "out_of_range": ...}`` (a copy keeps its last kept state), and
    the rollout each state comes from, [S] int64 (-1: a sampled state).

    ``config.samples`` draws of z ~ N(0, I) (conditions uniform in their ranges), then every state of
    ``config.episodes`` latent rollouts of ``config.steps`` steps from the rest latent under loads redrawn
    from N(0, load_scale^2 I) every ``config.hold`` steps (the scene's default condition), in float64 for a float64
    map and in float32 (the envs' default) otherwise. ``progress`` is called after each rollout step.
    """
    from redsim.runtime import LatentStepper  # the runtime imports nothing of this package

    generator = torch.Generator().manual_seed(config.seed)
    d = int(subspace.latent_dim)
    z = sample_latents(config.samples, d, periodic_latents(subspace), generator=generator, dtype=torch.float64)
    space = scene.condition_space
    cond = space.sample(config.samples, generator).to(torch.float64) if space is not None else None
    dropped = {"diverged": 0, "out_of_range": 0}
    sampled = torch.full((config.samples,), -1, dtype=torch.int64)
    if not config.episodes or not scene.handles:
        return z, cond, dropped, sampled
    scale = default_load_scale(scene) if config.load_scale is None else config.load_scale
    like = map_tensor(subspace)  # a float64 map's rollouts in float64 (float32 would not feel small loads)
    dtype = torch.float64 if like is not None and like.dtype == torch.float64 else torch.float32
    stepper = LatentStepper(scene, subspace, config.dt, dtype=dtype)
    B = int(config.episodes)
    segments = -(-int(config.steps) // int(config.hold))
    loads = scale * torch.randn(segments, B, len(scene.handles), scene.dim, generator=generator, dtype=torch.float32)
    current = stepper.rest_latent().expand(B, -1)
    previous = current
    visited, episode, model, carry = [], [], None, None
    for step in range(int(config.steps)):
        held = loads[step // int(config.hold)].to(stepper.dtype)
        nxt, stats = stepper.step(current, previous, held, warm=model, carry=carry)  # warm and carried as the envs do
        model, carry = stats.model, stats.carry  # (a dropped row's carry no longer matches its z: it is evaluated)
        keep = ~(stats.diverged | stats.out_of_range)
        dropped["diverged"] += int(stats.diverged.sum())
        dropped["out_of_range"] += int((stats.out_of_range & ~stats.diverged).sum())
        previous, current = current, torch.where(keep[:, None], nxt, current)
        visited.append(current[keep].to(torch.float64))
        episode.append(torch.nonzero(keep.cpu()).reshape(-1))
        if progress is not None:
            progress()
    rollout = torch.cat(visited)
    z = torch.cat([z, rollout])
    if space is not None:
        cond = torch.cat([cond, space.default.to(torch.float64).expand(rollout.shape[0], -1)])
    return z, cond, dropped, torch.cat([sampled, *episode])


def split_states(episode: Tensor, config: CubatureConfig) -> tuple[Tensor, Tensor]:
    """Held-out and training state indices for states from rollouts ``episode`` [S] (-1: sampled; see
    :func:`training_states`).

    ``config.held_out`` of the sampled states (at least one on each side), drawn one by one, and as large a share of
    the rollouts, each whole (at least one on each side where there are two or more; a single rollout trains): the
    states of one rollout lie a step apart, so a state held out beside its neighbours in training is not held out.
    Seeded by ``config.seed + 1``; without rollouts it is the split of every state one by one.
    """
    generator = torch.Generator().manual_seed((config.seed + 1) % 2**64)
    sampled = torch.nonzero(episode < 0).reshape(-1)
    order = sampled[torch.randperm(sampled.numel(), generator=generator)]
    n_test = min(sampled.numel() - 1, max(1, round(config.held_out * sampled.numel())))
    test, train = [order[:n_test]], [order[n_test:]]
    rollouts = torch.unique(episode[episode >= 0])
    if rollouts.numel():
        rollouts = rollouts[torch.randperm(rollouts.numel(), generator=generator)]
        held = min(rollouts.numel() - 1, max(1, round(config.held_out * rollouts.numel())))
        chosen = torch.isin(episode, rollouts[:held])
        test.append(torch.nonzero(chosen).reshape(-1))
        train.append(torch.nonzero((episode >= 0) & ~chosen).reshape(-1))
    return torch.cat(test), torch.cat(train)


def element_columns(
    scene: Scene,
    output: AffineOutput,
    effect: Effect,
    z: Tensor,
    cond: Tensor | None,
    chunk: int = 16,
    *,
    progress: Callable[[int], None] | None = None,
) -> tuple[Tensor, Tensor]:
    """Per-element reduced forces and energies of states z [S, d] (float64 scene and output).

    Returns g [S, T, d] = J^T grad_x E_e(f(z_s)) [J per unit z] and E [S, T] [J]. ``progress`` is called with the
    number of states of each chunk done.
    """
    free = scene.dof_map.free_index
    forces, energies = [], []
    d = z.shape[1]
    takes_cond = bool(map_condition_dim(output.map))  # an unconditional map of a conditional scene: the effects' alone
    for start in range(0, z.shape[0], chunk):
        zs = z[start : start + chunk]
        cs = None if cond is None else cond[start : start + chunk]
        k = zs.shape[0]
        tangents = torch.eye(d, dtype=z.dtype).repeat_interleave(k, 0)
        map_cond = cs.repeat(d, 1) if cs is not None and takes_cond else None
        with torch.no_grad():
            q, dq = jvp(lambda u, map_cond=map_cond: output(u, map_cond), (zs.repeat(d, 1),), (tangents,))
        x = scene.full_positions(q[:k])
        jx = torch.zeros(d * k, scene.full_dof_count, dtype=z.dtype).index_copy(1, free, dq)
        xe = gather_elements(x, effect.element_dofs).requires_grad_(True)
        with torch.enable_grad():
            e = effect.element_energy(xe, cs)
            (grad,) = torch.autograd.grad(e.sum(), xe)
        je = gather_elements(jx, effect.element_dofs).reshape(d, k, *effect.element_dofs.shape)
        forces.append(torch.einsum("tek,jtek->tej", grad, je))
        energies.append(e.detach())
        if progress is not None:
            progress(k)
    return torch.cat(forces), torch.cat(energies)


def _columns(forces: Tensor, energies: Tensor, reference: Tensor, scale: Tensor) -> Tensor:
    """Least-squares matrix [S * (d + 1), T]: each state's d force rows and one energy row over ``scale`` [S]."""
    rows = torch.cat([forces, (energies - reference).unsqueeze(-1)], -1) / scale[:, None, None]
    return rows.permute(0, 2, 1).reshape(-1, rows.shape[1])


def _relative_error(a: Tensor, weights: Tensor, index: Tensor, target: Tensor, norm: float) -> float:
    approx = a[:, index] @ weights if index.numel() else torch.zeros_like(target)
    return float(torch.linalg.vector_norm(approx - target)) / norm


def greedy_nnls(
    train: Tensor,
    test: Tensor,
    train_norm: float,
    test_norm: float,
    *,
    elements: int,
    tol: float | None,
    progress: Callable[[int, float], None] | None = None,
) -> tuple[Tensor, Tensor, list[tuple[int, float, float]]]:
    """Greedy element selection + NNLS: columns ``train`` [R, T] must sum (with weights) to their row sum.

    Each round adds the candidates whose normalized columns correlate best with the residual
    (max(1, kept/8) of them), then refits every kept weight by NNLS. Errors are |A w - A 1| / norm.
    ``test`` [R', T] (the held-out states' rows) enters only the held-out errors of the history.

    Returns kept indices [K], weights [K] (>= 0) and the (kept, train, held-out error) history.

    Raises:
        ValueError: an NNLS refit ran out of iterations (saying how many elements it refitted).
    """
    target = train.sum(1, dtype=torch.float64)
    test_target = test.sum(1, dtype=torch.float64)
    norms = torch.linalg.vector_norm(train, dim=0)
    # an element that does (almost) nothing on the training states could only help with a huge weight,
    # which the states between them would pay for: it is never a candidate
    banned = norms < CANDIDATE_FLOOR * norms.mean()
    norms = norms.clamp_min(1e-300)
    kept: list[int] = []
    weights = torch.zeros(0, dtype=torch.float64)
    residual = target.clone()
    history: list[tuple[int, float, float]] = []
    count = train.shape[1]
    rounds = 0
    while len(kept) < min(elements, count) and rounds < 4 * elements:
        rounds += 1
        score = (residual @ train) / norms
        score[banned] = -math.inf
        if kept:
            score[torch.tensor(kept)] = -math.inf
        add = min(max(1, len(kept) // 8), elements - len(kept))
        best = torch.topk(score, add).indices
        best = best[score[best] > 0.0]
        if not best.numel():
            break
        kept += best.tolist()
        index = torch.tensor(kept)
        columns = train[:, index].numpy()
        try:
            solution, _ = scipy.optimize.nnls(columns, target.numpy(), maxiter=50 * len(kept))
        except RuntimeError as err:  # scipy's "Maximum number of iterations reached."
            raise ValueError(
                f"NNLS ran out of iterations refitting the weights of {len(kept)} kept elements (maxiter "
                f"{50 * len(kept)}; scipy: {err}): keep fewer elements (elements, --elements: below {len(kept)}) or "
                "stop earlier (a larger tol, --tol)"
            ) from err
        weights = torch.from_numpy(np.asarray(solution))
        nonzero = weights > 0.0
        banned[index[~nonzero]] = True  # dropped by NNLS: not proposed again
        kept = index[nonzero].tolist()
        weights = weights[nonzero]
        index = torch.tensor(kept, dtype=torch.int64)
        residual = target - train[:, index] @ weights
        error = float(torch.linalg.vector_norm(residual)) / train_norm
        held = _relative_error(test, weights, index, test_target, test_norm)
        history.append((len(kept), error, held))
        if progress is not None:
            progress(len(kept), held)
        if error <= ROUND_OFF or (tol is not None and error <= tol):
            break
    return torch.tensor(kept, dtype=torch.int64), weights, history


def effect_modes(scene: Scene, config: CubatureConfig) -> dict[str, str]:
    """The mode of each effect but the load terms (see :data:`MODES`)."""
    names = {e.name for e in scene.effects}
    unknown = sorted((set(config.full or ()) | set(config.subsample)) - names)
    if unknown:
        raise ValueError(f"scene {scene.name!r} has no effect(s) {unknown}; it has {sorted(names)}")
    effects = scene.load_free_effects("a cubature")
    load_terms = sorted(names - {e.name for e in effects})
    if stray := sorted((set(config.full or ()) | set(config.subsample)) & set(load_terms)):
        raise ValueError(
            f"effect(s) {stray} are the load term, which the latent step adds exactly: a cubature has nothing of "
            "them to keep or subsample (full names the effects to keep whole, in place of the default)"
        )
    linear = sorted(e.name for e in effects if e.kind in LINEAR_KINDS and e.name in (config.full or ()))
    if linear:
        raise ValueError(
            f"effect(s) {linear} are linear: they stay exact, kept whole or not (full names the effects to keep whole, "
            "in place of the default)"
        )
    modes = {}
    for effect in effects:
        rare = effect.kind.split(":")[0] in RARE_KINDS and effect.name not in config.subsample
        whole = effect.name in config.full if config.full is not None else rare
        if effect.kind in LINEAR_KINDS:
            if effect.name in config.subsample:
                raise ValueError(f"effect {effect.name!r} is linear: it stays exact and cannot be subsampled")
            modes[effect.name] = "linear"
        elif whole or (config.tol is None and effect.element_count <= config.elements):
            modes[effect.name] = "full"  # under a tol, the greedy search decides how many of them it needs
        else:
            modes[effect.name] = "cubature"
    return modes


def fit_rules(
    scene: Scene, subspace: nn.Module, config: CubatureConfig, *, progress: bool = False
) -> tuple[list[EffectRule], dict[str, float]]:
    """Build every effect's rule (module doc); also returns the summary (state counts, total errors).

    Args:
        scene: The scene the map was fitted to.
        subspace: The map (neural, linear or quadratic).
        config: Sizes and options.
        progress: Show tqdm bars: the rollout steps, the states whose per-element forces are computed (per effect),
            and per subsampled effect its kept elements and held-out error.

    Raises:
        ValueError: an effect's NNLS refit ran out of iterations (naming the effect, and what to change).
    """
    modes = effect_modes(scene, config)
    bar = None
    if progress and config.episodes and scene.handles:  # the rollouts and the columns come before the greedy's bars
        bar = progress_bar(total=int(config.steps), desc="cubature rollouts", unit="step", dynamic_ncols=True)
    try:  # closed on Ctrl-C too: a bar closed later draws its line below `redsim cubature`'s rerun command
        z, cond, dropped, episode = training_states(
            scene, subspace, config, progress=None if bar is None else lambda: bar.update(1)
        )
    finally:
        if bar is not None:
            bar.close()
    scene64 = scene.to(dtype=torch.float64)
    output = AffineOutput(subspace).to(torch.float64)
    test_index, train_index = split_states(episode, config)
    n_test = int(test_index.numel())
    d1 = z.shape[1] + 1  # rows per state: d force components and the energy
    train_rows = (train_index[:, None] * d1 + torch.arange(d1)).reshape(-1)
    test_rows = (test_index[:, None] * d1 + torch.arange(d1)).reshape(-1)
    z0 = torch.zeros(1, z.shape[1], dtype=torch.float64)
    c0 = None if scene.condition_space is None else scene.condition_space.default.to(torch.float64)[None]
    # the total reduced force and energy per state (all non-load effects), for the per-state scale
    columns = {}
    bar = None
    if progress:
        total = z.shape[0] * sum(e.name in modes for e in scene64.effects)
        bar = progress_bar(total=total, desc="cubature element forces", unit="state", dynamic_ncols=True)
    try:
        for effect in scene64.effects:
            if effect.name in modes:
                forces, energies = element_columns(
                    scene64, output, effect, z, cond, progress=None if bar is None else bar.update
                )
                _, ref = element_columns(scene64, output, effect, z0, c0)
                columns[effect.name] = (forces, energies, ref[0])
    finally:
        if bar is not None:
            bar.close()
    total_force = sum(f.sum(1) for f, _, _ in columns.values())
    total_energy = sum((e - r).sum(1) for _, e, r in columns.values())
    scale = torch.sqrt((total_force**2).sum(-1) + total_energy**2).clamp_min(1e-30)
    whole = torch.cat([total_force, total_energy[:, None]], -1) / scale[:, None]
    train_norm = float(torch.linalg.vector_norm(whole[train_index]))
    test_norm = float(torch.linalg.vector_norm(whole[test_index]))
    subsampled = [name for name, mode in modes.items() if mode == "cubature"]
    per_tol = None if config.tol is None else config.tol / math.sqrt(max(1, len(subsampled)))
    rules = []
    train_residual = torch.zeros_like(whole[train_index])
    test_residual = torch.zeros_like(whole[test_index])
    for effect in scene64.effects:
        if effect.name not in modes:
            continue
        mode = modes[effect.name]
        T = effect.element_count
        if mode != "cubature":
            index = torch.arange(T) if mode == "full" else torch.zeros(0, dtype=torch.int64)
            rules.append(EffectRule(effect.name, mode, T, index, torch.ones(index.shape[0], dtype=torch.float64)))
            continue
        forces, energies, ref = columns[effect.name]
        a = _columns(forces, energies, ref, scale)
        train, test = a[train_rows], a[test_rows]
        bar = None
        if progress:
            bar = progress_bar(total=min(config.elements, T), desc=f"cubature {effect.name}", dynamic_ncols=True)

        def report(kept: int, held: float, bar: object = bar) -> None:
            if bar is not None:
                bar.set_postfix(held_out_error=f"{held:.3g}", refresh=False)  # type: ignore[attr-defined]
                bar.update(kept - bar.n)  # type: ignore[attr-defined]  # redraws as often as the bar allows

        try:
            index, weights, history = greedy_nnls(
                train, test, train_norm, test_norm, elements=config.elements, tol=per_tol, progress=report
            )
        except ValueError as err:
            raise ValueError(f"effect {effect.name!r}: {err}") from err
        finally:
            if bar is not None:
                bar.close()  # type: ignore[attr-defined]
        train_residual += (train[:, index] @ weights - train.sum(1, dtype=torch.float64)).reshape(-1, d1)
        test_residual += (test[:, index].to(torch.float64) @ weights - test.sum(1, dtype=torch.float64)).reshape(-1, d1)
        if history:
            last = history[-1]
        else:  # no element lowers the error (an effect idle on every state, such as a contact never touched)
            last = (0, _relative_error(train, weights, index, train.sum(1, dtype=torch.float64), train_norm))
            last += (_relative_error(test, weights, index, test.sum(1, dtype=torch.float64), test_norm),)
        rules.append(EffectRule(effect.name, mode, T, index, weights, last[1], last[2], history))
    summary = {
        "states": int(z.shape[0]),
        "sampled_states": int(config.samples),
        "rollout_states": int(z.shape[0] - config.samples),
        "rollout_states_dropped": dropped,
        "held_out_states": int(n_test),
        "held_out_rollouts": int(torch.unique(episode[test_index][episode[test_index] >= 0]).numel()),
        "train_error": float(torch.linalg.vector_norm(train_residual)) / train_norm,
        "held_out_error": float(torch.linalg.vector_norm(test_residual)) / test_norm,
    }
    unscaled = test_residual * scale[test_index, None]  # J, J/unit z: the plain errors
    target = whole[test_index] * scale[test_index, None]
    measures = error_measures(unscaled[:, :-1], target[:, :-1], unscaled[:, -1], target[:, -1], scale[test_index])
    summary |= {f"held_out_{key}": value for key, value in measures.items()}
    return rules, summary


def error_measures(
    force_residual: Tensor, force: Tensor, energy_residual: Tensor, energy: Tensor, scale: Tensor | None = None
) -> dict[str, float]:
    """The errors of approximate reduced forces and energies over S states, each a relative error.

    Args:
        force_residual: F_approx - F per state, [S, d].
        force: The reduced force F = J^T grad E the approximation is measured against, [S, d].
        energy_residual: (E_approx(z) - E_approx(0)) - (E(z) - E(0)), [S].
        energy: E(z) - E(0), [S].
        scale: Each state's scale [S]; None: sqrt(|F|^2 + (E - E(0))^2) of ``force`` and ``energy``.

    Returns:
        ``force_error``: the fit's own, over the force rows with each state's residual and force over its scale,
        sqrt(sum_s |r_s / scale_s|^2 / sum_s |F_s / scale_s|^2) (``held_out_force_error``); ``plain_force_error``:
        the same unscaled, sqrt(sum_s |r_s|^2 / sum_s |F_s|^2); ``median_state_force_error`` and
        ``p90_state_force_error``: the median and 90th percentile over states of |r_s| / |F_s|; ``energy_error``:
        sqrt(sum_s (E residual)^2 / sum_s (E - E(0))^2), unscaled.

    Raises:
        ValueError: shapes that do not match.
    """
    if force_residual.ndim != 2 or force_residual.shape != force.shape:
        raise ValueError(
            f"force residual and force must be [S, d] alike, got {list(force_residual.shape)} and {list(force.shape)}"
        )
    count = force.shape[0]
    if energy_residual.shape != (count,) or energy.shape != (count,):
        raise ValueError(
            f"energy residual and energy must be [S] (S = {count}), got {list(energy_residual.shape)} and "
            f"{list(energy.shape)}"
        )
    if scale is None:
        scale = torch.sqrt(force.square().sum(-1) + energy.square())
    if scale.shape != (count,):
        raise ValueError(f"scale must be [S] (S = {count}), got {list(scale.shape)}")
    scale = scale.clamp_min(1e-30)[:, None]

    def ratio(a: Tensor, b: Tensor) -> float:
        return float(torch.linalg.vector_norm(a) / torch.linalg.vector_norm(b).clamp_min(1e-300))

    per_state = torch.linalg.vector_norm(force_residual, dim=-1) / torch.linalg.vector_norm(force, dim=-1).clamp_min(
        1e-300
    )
    per_state = per_state.to(torch.float64)
    return {
        "force_error": ratio(force_residual / scale, force / scale),
        "plain_force_error": ratio(force_residual, force),
        "median_state_force_error": float(per_state.quantile(0.5)),
        "p90_state_force_error": float(per_state.quantile(0.9)),
        "energy_error": ratio(energy_residual, energy),
    }


__all__ = [
    "LINEAR_KINDS",
    "MODES",
    "RARE_KINDS",
    "CubatureConfig",
    "EffectRule",
    "default_load_scale",
    "effect_modes",
    "element_columns",
    "error_measures",
    "fit_rules",
    "greedy_nnls",
    "split_states",
    "training_states",
]
