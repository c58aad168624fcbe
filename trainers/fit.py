"""The data-free subspace fitter of Sharp et al. 2023, "Data-Free Learning of Reduced-Order Kinematics".

Loss (paper eq. "subspace_loss"), estimated on one batch z_1..z_B ~ N(0, I):

    mean_i E_pot(f(z_i)) + lam * mean_{i<j} ( log( |f(z_i) - f(z_j)|_M / (rho sigma |z_i - z_j|) ) )^2

with seeded exploration (§4.1): during fitting f(z) = rho MLP(z) + (1 - rho) q_seed, rho rising
linearly from 0 to 1. Because f(z_i) - f(z_j) = rho (MLP(z_i) - MLP(z_j)), the pair ratio equals
|MLP(z_i) - MLP(z_j)|_M / (sigma |z_i - z_j|) exactly, which is how it is computed (finite at
rho = 0). M-norm distances come from the B x B Gram matrix of the batch (never a B x B x n
tensor), after centring the batch so float32 keeps the small differences.

Speed options (:class:`FitConfig`): ``fused_adam`` (one fused Adam kernel per step) and ``compile``
(the loss, forward and backward, through ``torch.compile``; ``redsim bench fit`` measures both).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import os
import shlex
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch import Tensor

import redsim
from redsim.scene import Scene
from redsim.subspace import (
    CheckpointError,
    SubspaceConfig,
    SubspaceMap,
    checkpoint_path,
    pair_log_ratios,
    sample_latents,
)

log = logging.getLogger(__name__)

DTYPES = {"float32": torch.float32, "float64": torch.float64}


@dataclass(frozen=True)
class FitConfig:
    """Hyperparameters of one fit. Every field has a default; Table 1 values come per scene.

    Attributes:
        latent_dim: d.
        sigma: Target Lipschitz scale of the map [the unit of |q|_M per unit z] (paper σ).
        lam: Weight of the pair term (paper λ).
        steps: Adam steps.
        batch_size: Latent samples per step; the pair term uses all B(B-1)/2 pairs.
        learning_rate: Initial Adam learning rate; halved after each quarter of the steps.
        hidden_width: MLP width.
        hidden_layers: MLP hidden layers.
        periodic: Latent indices treated as angles.
        conditional: Fit f(z, c) over the scene's condition space (else the default condition).
        exploration_fraction: rho reaches 1 after this fraction of the steps (paper: 1.0).
        seed_bias: Start the output layer's bias at q_seed, so the MLP starts near the seed shape
            instead of near 0 (the map still has no seed term). Stiff meshes need it: from a zero
            output they spend their steps rebuilding the shape against a large elastic energy.
        checkpoint_every: Steps between resumable checkpoints (0: only at the end / on interrupt).
        dtype: "float32" (default) or "float64".
        device: Torch device for fitting.
        fused_adam: Use ``torch.optim.Adam(fused=True)`` (one kernel over all parameters per step;
            where the device or dtype has none, a warning is logged and plain Adam is used).
        compile: Run the loss (MLP forward, scene energy, pair term) and its backward through
            ``torch.compile(dynamic=False)``. The first step then compiles (needs a C++ compiler on the
            CPU; compiled code is cached on disk, so a repeat compile is faster). A process reuses the
            compiled code for fits of the same scene and settings; past 8 different ones (torch's
            ``recompile_limit``) torch warns and runs the loss eagerly.

    ``fused_adam`` and ``compile`` change only round-off, so a fit may be resumed with other values.
    The defaults come from ``redsim bench fit`` (1 thread of a shared, loaded 2-core x86_64, batch 32,
    float32, presets; median ms per step eager -> compiled over four runs, cold compile s):
    mini_chain 5-10 -> 2-3 (2.3-3.8x, 28-41 s incl. torch.compile's start-up), chain 34-44 -> 11-17
    (2.6-3.6x, 20-23 s), bistable_bar 12-14 -> 8-10 (1.4x, 19-25 s), cloth_ball 190-206 -> 165-196
    (1.0-1.2x, 38-42 s), stiff_body 510-560 -> 180-320 (1.6-3.1x, 18-24 s); with the on-disk cache
    warm a compile takes 0.4-3 s.
    ``fused_adam=True``: Adam's own step drops from 5-7 to 1.1 ms (cloth_ball) and from 14-19 to 2 ms
    (stiff_body), a few % of a step (below the machine's noise in the bench), and the losses agree
    with plain Adam's to 1e-4 (relative). ``compile=False``: a cold compile pays for itself only
    after about compile / (eager - compiled) steps (~5,000-10,000 mini_chain, ~1,000 chain, ~6,000
    bistable_bar, over 1,000 cloth_ball, ~100 stiff_body), needs a C++ compiler and adds tens of
    seconds to every short fit (tests, examples); turn it on (``redsim fit --compile``) for full
    10,000-step fits of the larger scenes.
    """

    latent_dim: int = 8
    sigma: float = 1.0
    lam: float = 1.0
    steps: int = 10_000
    batch_size: int = 32
    learning_rate: float = 3e-4
    hidden_width: int = 128
    hidden_layers: int = 5
    periodic: tuple[int, ...] = ()
    conditional: bool = False
    exploration_fraction: float = 1.0
    seed_bias: bool = False
    checkpoint_every: int = 1000
    dtype: str = "float32"
    device: str = "cpu"
    fused_adam: bool = True
    compile: bool = False

    def __post_init__(self) -> None:
        bad = [(f, rule) for f, rule, ok in _FIELD_RULES if not ok(self, getattr(self, f))]
        if bad:
            raise FitConfigError(bad, self)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


_FIELD_RULES: tuple[tuple[str, str, Callable[[FitConfig, Any], bool]], ...] = (
    ("latent_dim", "an integer >= 1", lambda c, v: _is_int(v) and v >= 1),
    ("sigma", "a finite number > 0", lambda c, v: _is_number(v) and v > 0),
    ("lam", "a finite number >= 0", lambda c, v: _is_number(v) and v >= 0),
    ("steps", "an integer >= 1", lambda c, v: _is_int(v) and v >= 1),
    ("batch_size", "an integer >= 2", lambda c, v: _is_int(v) and v >= 2),
    ("learning_rate", "a finite number > 0", lambda c, v: _is_number(v) and v > 0),
    ("hidden_width", "an integer >= 1", lambda c, v: _is_int(v) and v >= 1),
    ("hidden_layers", "an integer >= 1", lambda c, v: _is_int(v) and v >= 1),
    (
        "periodic",
        "distinct latent indices in [0, latent_dim)",
        lambda c, v: (
            all(_is_int(i) and 0 <= i < (c.latent_dim if _is_int(c.latent_dim) else 0) for i in v)
            and len(set(v)) == len(v)
        ),
    ),
    ("conditional", "true or false", lambda c, v: isinstance(v, bool)),
    ("exploration_fraction", "a number in (0, 1]", lambda c, v: _is_number(v) and 0 < v <= 1),
    ("seed_bias", "true or false", lambda c, v: isinstance(v, bool)),
    ("checkpoint_every", "an integer >= 0", lambda c, v: _is_int(v) and v >= 0),
    ("dtype", f"one of {', '.join(DTYPES)}", lambda c, v: v in DTYPES),
    ("device", "a torch device such as cpu or cuda", lambda c, v: isinstance(v, str) and _is_device(v)),
    ("fused_adam", "true or false", lambda c, v: isinstance(v, bool)),
    ("compile", "true or false", lambda c, v: isinstance(v, bool)),
)
"""(field, rule, check) for every FitConfig field; the messages state the rule."""


def _is_device(name: str) -> bool:
    try:
        torch.device(name)
    except RuntimeError:
        return False
    return True


class FitConfigError(ValueError):
    """Invalid :class:`FitConfig` fields.

    Attributes:
        problems: (field, rule) per invalid field, e.g. ("steps", "an integer >= 1").
        values: The offending values, by field.
    """

    def __init__(self, problems: list[tuple[str, str]], config: FitConfig) -> None:
        self.problems = problems
        self.values = {f: getattr(config, f) for f, _ in problems}
        super().__init__(self.describe())

    def describe(self, names: dict[str, str] | None = None) -> str:
        """One line naming each field (or its alias in ``names``, e.g. a CLI flag), its rule and its value."""
        names = names or {}
        return "; ".join(f"{names.get(f, f)} must be {rule}, got {self.values[f]!r}" for f, rule in self.problems)


_ROUND_OFF_ONLY = ("fused_adam", "compile")
"""FitConfig fields that change a fit only by round-off: a fit may resume with other values of them."""


class FitResult(NamedTuple):
    """What :func:`fit_subspace` returns."""

    subspace: SubspaceMap
    history: list[dict[str, float]]
    fit_seconds: float


def _loss_tensors(
    scene: Scene,
    model: SubspaceMap,
    z: Tensor,
    cond: Tensor | None,
    rho: Tensor,
    config: FitConfig,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The loss and its terms as 0-dim tensors: total, mean energy [J], pair term, mean metric stretch.

    ``rho`` is a 0-dim tensor, so a compiled copy takes each step's value as an input instead of
    specialising (and recompiling) on it.
    """
    y = model(z, cond if config.conditional else None)
    q = rho * y + (1.0 - rho) * scene.q_seed
    energy = scene.energy(q, cond=cond).mean()
    log_ratio = pair_log_ratios(y, z, scene, config.sigma, config.periodic)
    pair = (log_ratio**2).mean()
    return energy + config.lam * pair, energy, pair, torch.exp(log_ratio.detach()).mean()


def _terms(energy: Tensor, pair: Tensor, stretch: Tensor) -> dict[str, float]:
    return {"energy": float(energy.detach()), "pair": float(pair.detach()), "stretch": float(stretch)}


def subspace_loss(
    scene: Scene, model: SubspaceMap, z: Tensor, cond: Tensor | None, rho: float, config: FitConfig
) -> tuple[Tensor, dict[str, float]]:
    """The fitting loss on one batch, and its terms (mean energy [J], pair term, mean metric stretch)."""
    rho_t = torch.as_tensor(rho, dtype=z.dtype, device=z.device)
    total, energy, pair, stretch = _loss_tensors(scene, model, z, cond, rho_t, config)
    return total, _terms(energy, pair, stretch)


def rho_at(step: int, config: FitConfig, ramp_steps: int | None = None) -> float:
    """Seeded-exploration weight rho after ``step`` completed steps.

    rho rises over ``exploration_fraction * ramp_steps`` steps, ``ramp_steps`` being the length of
    the fit the ramp was planned for (default ``config.steps``; an extended fit keeps its first length).
    """
    return min(1.0, (step + 1) / (config.exploration_fraction * (ramp_steps or config.steps)))


def _lr_step_size(steps: int) -> int:
    """Steps between halvings of the learning rate: a quarter of the run."""
    return max(1, steps // 4)


Callback = Callable[[int, dict[str, float]], None]


def fit_subspace(
    scene: Scene,
    config: FitConfig | None = None,
    *,
    seed: int = 0,
    out: str | Path | None = None,
    resume: bool = False,
    callbacks: Sequence[Callback] = (),
    progress: bool = True,
    command: str | None = None,
    **overrides: Any,
) -> FitResult:
    """Fit a neural subspace to ``scene`` from its energy alone.

    Args:
        scene: The system; its energy is evaluated in ``config.dtype`` on ``config.device``.
        config: Hyperparameters (defaults: :class:`FitConfig`).
        seed: Seeds the MLP initialisation and every latent sample; the same seed reproduces a fit.
        out: Checkpoint stem. With it, ``STEM.fit.pt`` holds resumable training state (written
            every ``checkpoint_every`` steps and on Ctrl-C) and the final map is saved to
            ``STEM.pt`` + ``STEM.json``.
        resume: Continue from ``STEM.fit.pt`` (same scene and config required, except ``steps``:
            a larger value extends a fit, with the learning-rate schedule recomputed for the new
            length from the step reached on; rho keeps the ramp of the first length).
        callbacks: Called as ``cb(step, terms)`` after every step.
        progress: Show a tqdm bar with the energy, pair and stretch terms.
        command: The command line recorded in the metadata (default: a `redsim fit` line).
        **overrides: FitConfig fields replacing those of ``config`` (``dim`` is an alias of
            ``latent_dim``), e.g. ``fit_subspace(scene, dim=8, sigma=1.0, lam=1.0, steps=2000)``.

    Raises:
        ValueError: bad config, a conditional fit on a scene without conditions, or
            ``resume`` with no matching checkpoint.
    """
    if "dim" in overrides:
        overrides["latent_dim"] = overrides.pop("dim")
    unknown = sorted(set(overrides) - {f.name for f in dataclasses.fields(FitConfig)})
    if unknown:
        raise ValueError(f"unknown fit option(s) {unknown}; valid: {[f.name for f in dataclasses.fields(FitConfig)]}")
    config = dataclasses.replace(config or FitConfig(), **overrides)
    if config.conditional and scene.condition_space is None:
        raise ValueError(f"scene {scene.name!r} has no condition space; fit without conditional")
    dtype = DTYPES[config.dtype]
    work = scene.to(device=config.device, dtype=dtype)
    arch = SubspaceConfig(
        latent_dim=config.latent_dim,
        output_dim=scene.free_dof_count,
        condition_dim=scene.condition_dim if config.conditional else 0,
        hidden_width=config.hidden_width,
        hidden_layers=config.hidden_layers,
        periodic=tuple(config.periodic),
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = SubspaceMap(arch).to(device=config.device, dtype=dtype)
    if config.seed_bias:
        with torch.no_grad():
            model.mlp[-1].bias.copy_(work.q_seed)
    fused = config.fused_adam
    if fused and (why := _fused_adam_error(config.device, dtype)) is not None:
        log.warning("fused Adam is unavailable on %s in %s (%s); using plain Adam", config.device, dtype, why)
        fused = False
    optimizer = torch.optim.Adam(model.parameters(), lr=config.learning_rate, fused=fused)
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=_lr_step_size(config.steps), gamma=0.5)
    generator = torch.Generator(device=config.device).manual_seed(seed)
    history: list[dict[str, float]] = []
    start_step, elapsed = 0, 0.0
    command = command or fit_command(scene, config, seed, out)
    ramp_steps, extensions = config.steps, []
    state_path = None if out is None else checkpoint_path(out, ".fit.pt")
    if resume:
        if state_path is None or not state_path.is_file():
            raise ValueError(f"nothing to resume: {state_path} does not exist")
        saved = _load_training_state(state_path, scene, config, model, optimizer, scheduler, generator)
        start_step, elapsed, history = saved["step"], saved["elapsed"], saved["history"]
        ramp_steps, extensions = saved["ramp_steps"], saved["extensions"]
        if saved["steps"] != config.steps:
            _reschedule(optimizer, scheduler, config, start_step)
            extensions.append({"at_step": start_step, "from_steps": saved["steps"], "to_steps": config.steps})
            command = f"{saved['command']} && {command} --resume" if saved["command"] else command
        else:
            command = saved["command"]
        _set_fused(optimizer, fused)
        log.info("resuming %s at step %d of %d", state_path, start_step, config.steps)

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=config.steps, initial=start_step, desc=f"fit {scene.name}", dynamic_ncols=True)
    completed, generator_state = start_step, generator.get_state()
    loss_fn = torch.compile(_loss_tensors, dynamic=False) if config.compile else _loss_tensors
    clock = time.perf_counter()

    def save_state() -> None:
        if state_path is not None:
            _save_training_state(
                state_path,
                {
                    "step": completed,
                    "elapsed": elapsed + time.perf_counter() - clock,
                    "history": history,
                    "scene_fingerprint": scene.fingerprint(),
                    "config": dataclasses.asdict(config),
                    "model": model.state_dict(),
                    "optimizer": optimizer.state_dict(),
                    "scheduler": scheduler.state_dict(),
                    "generator": generator_state,
                    "ramp_steps": ramp_steps,
                    "extensions": extensions,
                    "command": command,
                },
            )

    try:
        for step in range(start_step, config.steps):
            z = sample_latents(
                config.batch_size,
                config.latent_dim,
                config.periodic,
                generator=generator,
                dtype=dtype,
                device=config.device,
            )
            cond = None
            if work.condition_space is not None:
                cond = (
                    work.condition_space.sample(config.batch_size, generator)
                    if config.conditional
                    else work.pack_condition(None, config.batch_size)
                )
            rho = rho_at(step, config, ramp_steps)
            rho_t = torch.tensor(rho, dtype=dtype, device=config.device)
            loss, energy, pair, stretch = loss_fn(work, model, z, cond, rho_t, config)
            terms = _terms(energy, pair, stretch)
            if not torch.isfinite(loss):
                raise FloatingPointError(
                    f"loss became {float(loss)} at step {step} (terms {terms}); lower the learning rate or sigma"
                )
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            scheduler.step()
            terms = {"step": step + 1, "loss": float(loss.detach()), "rho": rho, **terms}
            history.append(terms)
            completed, generator_state = step + 1, generator.get_state()
            for cb in callbacks:
                cb(completed, terms)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(
                    E=f"{terms['energy']:.3g}", pair=f"{terms['pair']:.3g}", stretch=f"{terms['stretch']:.3f}"
                )
            if config.checkpoint_every and completed % config.checkpoint_every == 0:
                save_state()
    except KeyboardInterrupt:
        save_state()
        if state_path is not None:
            log.warning("interrupted after step %d; rerun with --resume to continue (%s)", completed, state_path)
        raise
    finally:
        if bar is not None:
            bar.close()
    save_state()  # the end state too, so that a finished fit can be extended (--resume with more --steps)
    fit_seconds = elapsed + time.perf_counter() - clock
    tail = history[-min(len(history), 100) :]
    model.metadata = {
        "scene": scene.name,
        "scene_fingerprint": scene.fingerprint(),
        "scene_params": scene.params,
        "conditions": _condition_doc(scene) if config.conditional else [],
        "fit": dataclasses.asdict(config),
        "seed": seed,
        "fit_seconds": fit_seconds,
        "final": {k: sum(h[k] for h in tail) / len(tail) for k in ("energy", "pair", "stretch")},
        "redsim_version": redsim.__version__,
        "schedule": {
            "lr_halved_every": _lr_step_size(config.steps),
            "rho_ramp_steps": ramp_steps,
            "extensions": extensions,
        },
        "command": command,
    }
    model = model.cpu()
    if out is not None:
        model.save(out)
    return FitResult(model, history, fit_seconds)


@functools.cache
def _fused_adam_error(device: str, dtype: torch.dtype) -> str | None:
    """Why ``Adam(fused=True)`` cannot step on ``device`` in ``dtype`` (None: it can), from one probe step."""
    probe = torch.zeros(1, device=device, dtype=dtype, requires_grad=True)
    probe.grad = torch.zeros_like(probe)
    try:
        torch.optim.Adam([probe], fused=True).step()
    except RuntimeError as err:
        return str(err)
    return None


def _set_fused(optimizer: torch.optim.Optimizer, fused: bool) -> None:
    """Make a loaded Adam state step fused or not, whichever it was saved with.

    ``load_state_dict`` restores the saved ``fused`` flag; fused Adam keeps its step counts in
    float32 on the parameters' device, plain Adam on the CPU.
    """
    for group in optimizer.param_groups:
        group["fused"] = fused
        for param in group["params"]:
            state = optimizer.state.get(param, {})
            if "step" in state:
                step = state["step"]
                state["step"] = step.to(param.device, torch.float32) if fused else step.cpu()


def _condition_doc(scene: Scene) -> list[dict[str, Any]]:
    space = scene.condition_space
    assert space is not None  # guarded by the caller's config.conditional check
    return [
        {"name": n, "low": float(lo), "high": float(hi)}
        for n, lo, hi in zip(space.names, space.low, space.high, strict=True)
    ]


def fit_command(scene: Scene, config: FitConfig, seed: int, out: str | Path | None) -> str:
    """The `redsim fit` command line that reproduces this fit."""
    from redsim.scenes.spec import scene_arguments

    parts = ["redsim", "fit", *scene_arguments(scene)]
    parts += [
        "--dim",
        str(config.latent_dim),
        "--sigma",
        repr(config.sigma),
        "--lam",
        repr(config.lam),
        "--steps",
        str(config.steps),
        "--batch",
        str(config.batch_size),
        "--lr",
        repr(config.learning_rate),
        "--width",
        str(config.hidden_width),
        "--layers",
        str(config.hidden_layers),
        "--seed",
        str(seed),
    ]
    if config.periodic:
        parts += ["--periodic", ",".join(map(str, config.periodic))]
    if config.conditional:
        parts.append("--cond")
    if config.exploration_fraction != 1.0:
        parts += ["--explore", repr(config.exploration_fraction)]
    if config.seed_bias:
        parts.append("--seed-bias")
    default = FitConfig()
    for field in _ROUND_OFF_ONLY:  # switches, recorded only when not at their defaults
        value, flag = getattr(config, field), field.replace("_", "-")
        if value != getattr(default, field):
            parts.append(f"--{flag}" if value else f"--no-{flag}")
    if out is not None:
        parts += ["--out", os.fspath(out)]
    return shlex.join(parts)


def _save_training_state(path: Path, state: dict[str, Any]) -> None:
    """Write resumable training state atomically (a crash mid-write keeps the previous file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def _load_training_state(
    path: Path,
    scene: Scene,
    config: FitConfig,
    model: SubspaceMap,
    optimizer: torch.optim.Optimizer,
    scheduler: Any,
    generator: torch.Generator,
) -> dict[str, Any]:
    """Restore the training state at ``path`` into the model, optimizer, scheduler and generator.

    Returns:
        ``step``, ``elapsed``, ``history``, the saved ``steps``, ``ramp_steps``, ``extensions`` and ``command``.
    """
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        raise CheckpointError(f"training state is corrupt ({type(err).__name__}: {err})", str(path)) from None
    if state["scene_fingerprint"] != scene.fingerprint():
        raise CheckpointError(
            f"training state is for another scene (fingerprint {state['scene_fingerprint']}, "
            f"this scene {scene.fingerprint()})",
            str(path),
        )
    free = (*_ROUND_OFF_ONLY, "steps")
    mine = {k: v for k, v in dataclasses.asdict(config).items() if k not in free}
    saved = {k: v for k, v in state["config"].items() if k not in free}
    saved["periodic"] = tuple(saved["periodic"])
    saved.setdefault("seed_bias", False)  # states written before the option existed
    if saved != mine:
        diff = sorted(k for k in mine if saved.get(k) != mine[k])
        raise CheckpointError(f"training state was made with different settings {diff}", str(path))
    step = int(state["step"])
    if config.steps < step:
        raise CheckpointError(
            f"steps must be >= the {step} steps already done to resume, got {config.steps}", str(path)
        )
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    scheduler.load_state_dict(state["scheduler"])
    generator.set_state(state["generator"])
    saved_steps = int(state["config"]["steps"])
    return {
        "step": step,
        "elapsed": float(state["elapsed"]),
        "history": list(state["history"]),
        "steps": saved_steps,
        "ramp_steps": int(state.get("ramp_steps", saved_steps)),
        "extensions": list(state.get("extensions", [])),
        "command": state.get("command", ""),
    }


def _reschedule(optimizer: torch.optim.Optimizer, scheduler: Any, config: FitConfig, step: int) -> None:
    """Recompute the step-halving learning rate for a run of ``config.steps`` steps, at ``step`` done."""
    size = _lr_step_size(config.steps)
    scheduler.step_size = size
    scheduler.last_epoch = step
    lr = config.learning_rate * scheduler.gamma ** (step // size)
    for group in optimizer.param_groups:
        group["lr"] = lr
        group["initial_lr"] = config.learning_rate
    scheduler._last_lr = [lr for _ in optimizer.param_groups]
