"""The data-free subspace fitter of Sharp et al. 2023, "Data-Free Learning of Reduced-Order Kinematics".

Loss (paper eq. "subspace_loss"), estimated on one batch z_1..z_B ~ N(0, I):

    mean_i E_pot(f(z_i)) + lam * mean_{i<j} ( log( |f(z_i) - f(z_j)|_M / (rho sigma |z_i - z_j|) ) )^2

with seeded exploration (§4.1): during fitting f(z) = rho MLP(z) + (1 - rho) q_seed, rho rising
linearly from 0 to 1. Because f(z_i) - f(z_j) = rho (MLP(z_i) - MLP(z_j)), the pair ratio equals
|MLP(z_i) - MLP(z_j)|_M / (sigma |z_i - z_j|) exactly, which is how it is computed (finite at
rho = 0). M-norm distances come from the B x B Gram matrix of the batch (never a B x B x n
tensor), after centring the batch so float32 keeps the small differences.

Drivers (``FitConfig.drive``, not in the paper): a mechanism whose motion is a loop far from its
seed (the Klann crank) declares a :class:`redsim.scene.Driver`, a handle to be pulled round a
circle by a periodic latent. With ``drive > 0`` the loss gains the penalty

    mean_i  k(t)/2 |h(MLP(z_i)) - target(z_i)|^2

on the MLP's own output (like the pair term, so it acts from the first step whatever rho is);
k(t) is ``drive`` for the first half of ``drive_fraction`` of the steps, then falls linearly to 0
at ``drive_fraction``. It needs no simulation data: it only says where the handle goes round.

Softening (``FitConfig.soften``, not in the paper): the energies of the named effects are
weighted by w(t) = soften_from^(1 - t / (soften_fraction T)) (geometric, up to 1 at
``soften_fraction``). An affine body whose orthogonality penalty ("rigid") is soft can shear its
way round while the joints hold; as w reaches 1 it turns into the rotation (a driven map of
a rigid crank otherwise translates the bar off its hinge, a local minimum it does not leave).
The reported ``energy`` term is always the true, unweighted energy. It needs no simulation data: it
only says which way round the loop goes; the rest of the fit (rho at 1, driver off) is the paper's
loss, which keeps a map that is on the loop there.

Mirror (``FitConfig.mirror``, not in the paper): a scene whose energy a reflection P leaves
(nearly) unchanged declares it (:class:`redsim.scene.Mirror`; the bistable bar's up-down flip,
which swaps its two buckled states). With ``mirror > 0`` each batch is antithetic (z and -z) and
the loss gains

    mirror * mean_i |MLP(-z_i) - P(MLP(z_i))|^2_M

so the map becomes equivariant, f(-z) = P f(z): whatever state it reaches, it reaches the mirror
image too, at -z (the loss alone fills one well and leaves the other out). The origin maps to a
symmetric state (the straight seed of the bar), and exploration grows from it both ways. It needs
no simulation data: only the symmetry.

Anchors (``FitConfig.anchor``, not in the paper): a scene whose registry entry declares reference
states (:attr:`redsim.scenes.registry.SceneEntry.reference_states`: states found from its energy
alone, the bistable bar's two buckled equilibria) can have the fit pull the map through them. State
k gets the latent a_k = (-1)^k (|q_k - q_seed|_M / sigma) e_{k // 2} (a pair of states on opposite
ends of one axis, as far out as the pair term's scale puts them), and the loss gains

    mean_k  k(t)/2 |MLP(a_k) - q_k|^2_M

on the MLP's own output, with k(t) held at ``anchor`` for half of ``anchor_fraction`` of the steps,
then falling linearly to 0 (the driver's schedule). The paper's loss alone fills one well and
leaves the other out; the anchors only decide the topology (a map through both wells), and once
they are off the energy keeps each well in the map. It needs no simulation data: the states are
static equilibria of the energy.

Modal pull (``FitConfig.modal``, not in the paper): the map's value and Jacobian at z = 0 are pulled to
the static equilibrium and sigma times the lowest modes there, Prop. 1's small-sigma limit, so that the
map holds the small linear responses to loads (:mod:`redsim.trainers.modal`).

Anchored map (``FitConfig.anchor_map``, not in the paper): instead of an MLP the fit trains
:class:`redsim.subspace.AnchoredSubspace`, a fixed polynomial map (modal derivatives, ``"md"``, or linear
modes, ``"modes"``, of the fit's sigma at the rest state) plus the MLP stripped of its Taylor polynomial at
z = 0, so the map holds the small responses by construction and the paper's loss shapes only what lies
further out (:mod:`redsim.trainers.anchored`).

Speed options (:class:`FitConfig`): ``fused_adam`` (one fused Adam kernel per step) and ``compile``
(the loss, forward and backward, through ``torch.compile``; ``redsim bench fit`` measures both).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import logging
import math
import numbers
import os
import shlex
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch import Tensor

from redsim.devices import DTYPES, check_device
from redsim.interrupts import ForcedInterrupt, deferred_interrupts
from redsim.progress import progress_bar
from redsim.scene import Scene
from redsim.subspace import (
    AnchoredSubspace,
    CheckpointError,
    SubspaceConfig,
    SubspaceMap,
    checkpoint_path,
    map_fingerprint,
    pair_log_ratios,
    sample_latents,
    write_atomically,
)
from redsim.subspace.checkpoint import scene_mismatch, scene_record
from redsim.trainers.anchored import ANCHOR_MAP_CONDS, ANCHOR_MAPS, anchored_map
from redsim.trainers.modal import ModalTargets, modal_gap, modal_targets, start_at_rest
from redsim.trainers.presets import preset
from redsim.version import __version__

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FitConfig:
    """Hyperparameters of one fit. Every field has a default; Table 1 values come per scene.

    Numeric fields also take NumPy scalars (``numbers.Integral`` / ``numbers.Real``), kept as Python int / float.

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
            output they spend their steps rebuilding the shape against a large elastic energy. No effect with
            ``modal``, whose pull starts the map at the rest state (over this bias; the stiff body's and Klann's
            presets set it, so ``--modal`` on them fits as without it).
        drive: Initial stiffness [N/m] of the scene's drivers (:class:`redsim.scene.Driver`), a
            fitting-only pull of a handle round a circle by a periodic latent (0: off). Needs a
            scene that declares drivers, each turned by a latent in ``periodic``.
        drive_fraction: The driver is held at ``drive`` for half of this fraction of the steps,
            then falls linearly to 0 at it.
        soften: Names of scene effects (e.g. "rigid") whose energy is weighted by a factor rising
            from ``soften_from`` to 1 during fitting (empty: off).
        soften_from: Initial weight of the ``soften`` effects.
        soften_fraction: Their weight rises geometrically to 1 over this fraction of the steps.
        anchor: Initial stiffness [1/s^2] of the pull of the map through the scene's reference states
            (module doc; 0: off). Needs a catalog scene whose registry entry declares them.
        anchor_fraction: The anchor pull is held for half of this fraction of the steps, then falls
            linearly to 0 at it.
        modal: Initial weight (unitless) of the modal pull (:mod:`redsim.trainers.modal`; 0: off): the map's
            value and Jacobian at z = 0 towards the static equilibrium and sigma times the lowest modes, in
            the energy norm (w/2 |x|^2_H is w times the elastic energy an error x costs).
        modal_fraction: The modal pull is held for half of this fraction of the steps, then falls
            linearly to 0 at it (the anchor schedule; 2: held to the end).
        anchor_map: "none" (the paper's MLP), "md" or "modes": fit an :class:`redsim.subspace.AnchoredSubspace`
            that equals modal derivatives to second order (or linear modes to first order) at z = 0
            (:mod:`redsim.trainers.anchored`). Not with ``modal``, ``seed_bias`` or ``periodic``.
        anchor_map_cond: For a conditional ``anchor_map`` fit: "each" takes the MLP's Taylor polynomial at
            (0, c) for every condition c (f(0, c) is the default condition's rest state for every c), "default"
            only at the default condition (elsewhere the MLP moves the map freely).
        anchor_radius: R > 0 fades the ``anchor_map`` polynomial out beyond |z| ~ R (the factor exp(-|z|^2 / 2R^2),
            which keeps the map's Taylor polynomial to second order at z = 0); 0: no taper.
        mirror: Weight [1/s^2] of the equivariance penalty mean |MLP(-z) - P MLP(z)|^2_M [kg m^2]
            for the scene's mirror P (:class:`redsim.scene.Mirror`; 0: off). Needs a scene that
            declares one and an even ``batch_size`` (the batch is z and -z).
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
    drive: float = 0.0
    drive_fraction: float = 0.5
    soften: tuple[str, ...] = ()
    soften_from: float = 1e-3
    soften_fraction: float = 0.5
    anchor: float = 0.0
    anchor_fraction: float = 0.5
    modal: float = 0.0
    modal_fraction: float = 0.5
    anchor_map: str = "none"
    anchor_map_cond: str = "default"
    anchor_radius: float = 0.0
    mirror: float = 0.0
    checkpoint_every: int = 1000
    dtype: str = "float32"
    device: str = "cpu"
    fused_adam: bool = True
    compile: bool = False

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):  # NumPy scalars (np.float32(0.1), np.int64(10)) as Python numbers
            value = getattr(self, field.name)
            if field.name == "periodic" and isinstance(value, tuple):
                object.__setattr__(self, field.name, tuple(_python_number(i, int) for i in value))
            elif type(field.default) in (int, float):
                object.__setattr__(self, field.name, _python_number(value, type(field.default)))
        bad = [(f, rule) for f, rule, ok in _FIELD_RULES if not ok(self, getattr(self, f))]
        if bad:
            raise FitConfigError(bad, self)


def _python_number(value: Any, kind: type) -> Any:
    """A non-bool ``numbers.Integral`` as int, a ``numbers.Real`` as float where ``kind`` is float (a float field takes
    both, as Python numbers); anything else, Python ints and floats included, unchanged (the rules judge it)."""
    if type(value) in (int, float) or isinstance(value, bool):
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if kind is float and isinstance(value, numbers.Real):
        return float(value)
    return value


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
    ("drive", "a finite number >= 0", lambda c, v: _is_number(v) and v >= 0),
    ("drive_fraction", "a number in (0, 1]", lambda c, v: _is_number(v) and 0 < v <= 1),
    ("soften", "effect names", lambda c, v: isinstance(v, tuple) and all(isinstance(n, str) and n for n in v)),
    ("soften_from", "a number in (0, 1]", lambda c, v: _is_number(v) and 0 < v <= 1),
    ("soften_fraction", "a number in (0, 1]", lambda c, v: _is_number(v) and 0 < v <= 1),
    ("anchor", "a finite number >= 0", lambda c, v: _is_number(v) and v >= 0),
    ("anchor_fraction", "a number in (0, 1]", lambda c, v: _is_number(v) and 0 < v <= 1),
    ("modal", "a finite number >= 0", lambda c, v: _is_number(v) and v >= 0),
    ("modal_fraction", "a number in (0, 2]", lambda c, v: _is_number(v) and 0 < v <= 2),
    (
        "anchor_map",
        f"one of {', '.join(ANCHOR_MAPS)} (not with modal, seed_bias or periodic latents)",
        lambda c, v: v in ANCHOR_MAPS and (v == "none" or not (c.modal or c.seed_bias or c.periodic)),
    ),
    (
        "anchor_map_cond",
        f"one of {', '.join(ANCHOR_MAP_CONDS)} ('default' without anchor_map)",
        lambda c, v: v in ANCHOR_MAP_CONDS and (v == "default" or c.anchor_map != "none"),
    ),
    (
        "anchor_radius",
        "a finite number >= 0 (0: no taper; 0 without anchor_map)",
        lambda c, v: _is_number(v) and v >= 0 and (v == 0 or c.anchor_map != "none"),
    ),
    (
        "mirror",
        "a finite number >= 0 (> 0 needs an even batch_size)",
        lambda c, v: _is_number(v) and v >= 0 and (v == 0 or (_is_int(c.batch_size) and c.batch_size % 2 == 0)),
    ),
    ("checkpoint_every", "an integer >= 0", lambda c, v: _is_int(v) and v >= 0),
    ("dtype", f"one of {', '.join(DTYPES)}", lambda c, v: v in DTYPES),
    (
        "device",
        "cpu or cuda[:N], a GPU this machine has",
        lambda c, v: isinstance(v, str) and _is_device(v),
    ),
    ("fused_adam", "true or false", lambda c, v: isinstance(v, bool)),
    ("compile", "true or false", lambda c, v: isinstance(v, bool)),
)
"""(field, rule, check) for every FitConfig field; the messages state the rule."""


def _is_device(name: str) -> bool:
    """A device redsim runs on and this torch can use (:func:`redsim.devices.check_device`)."""
    try:
        check_device(name)
    except ValueError:
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
        """One line naming each field (or its alias in ``names``, e.g. a CLI flag), its rule and its value (a tuple
        as the flag takes it, comma-separated, where ``names`` is given)."""

        def shown(value: Any) -> str:
            return ",".join(map(str, value)) if names and isinstance(value, tuple) else repr(value)

        aliases = names or {}
        return "; ".join(f"{aliases.get(f, f)} must be {why}, got {shown(self.values[f])}" for f, why in self.problems)


FIT_ALIASES = {"dim": "latent_dim"}
"""Keyword aliases :func:`fit_subspace` takes for FitConfig fields (alias -> field)."""

_ROUND_OFF_ONLY = ("fused_adam", "compile")
"""FitConfig fields that change a fit only by round-off: a fit may resume with other values of them."""


class FitStopped(Exception):
    """A fit stopped at ``stop_at``, before its last step; its training state is saved for ``resume``.

    Attributes:
        step: Steps done.
        state: The training state, ``STEM.fit.pt``.
    """

    def __init__(self, step: int, state: Path) -> None:
        super().__init__(f"stopped after step {step}; the training state is in {state}")
        self.step = step
        self.state = state


class ResumeSettingsError(CheckpointError):
    """A resume with settings other than those the training state was made with.

    Attributes:
        differences: (field, saved value, value now) per FitConfig field that differs.
        command: The fit's recorded command ("" in a state written before it was recorded).
    """

    def __init__(self, differences: list[tuple[str, Any, Any]], command: str, path: str) -> None:
        self.differences, self.command = differences, command
        super().__init__(self.describe(), path)

    def describe(self, names: dict[str, str] | None = None) -> str:
        """The message, naming each field by its alias in ``names`` (e.g. a CLI flag) where it has one."""
        aliases = names or {}
        values = ", ".join(f"{aliases.get(k, k)}: saved {was!r}, now {now!r}" for k, was, now in self.differences)
        where = f": {self.command}" if self.command else ""
        return (
            f"training state was made with different settings ({values}); resume with the saved ones (the fit's "
            f"recorded command has them{where})"
        )


LOW_STRETCH = 0.1  # a fit whose mean metric stretch ends below this is warned about (sigma too large, or collapsed)


def low_stretch_warning(stretch: float, sigma: float, *, flags: bool = False) -> str | None:
    """What to say of a fit whose mean metric ``stretch`` ended below :data:`LOW_STRETCH` at ``sigma`` (None:
    nothing), naming the settings as FitConfig's fields or, with ``flags``, as ``redsim fit``'s options."""
    if not stretch < LOW_STRETCH:
        return None
    name = {"sigma": "--sigma", "seed_bias": "--seed-bias", "lam": "--lam", "explore": "--explore 0.5"}
    if not flags:
        name = {"sigma": "sigma", "seed_bias": "seed_bias=True", "lam": "lam", "explore": "exploration_fraction=0.5"}
    return (
        f"the map spreads its samples {100 * stretch:.2g}% as far as sigma ({sigma:g}) asks (mean metric stretch "
        f"{stretch:.3g}): its states sit near one configuration. Either sigma is large for this scene's energy (try "
        f"{name['sigma']} near {sigma * stretch:.2g}, sigma times the stretch), or the map collapsed onto the seed "
        f"against a stiff energy (start the output at the seed with {name['seed_bias']}, raise {name['lam']}, or "
        f"{name['explore']}, as the stiff body's preset does: README 'Fitting a subspace')"
    )


HIGH_STRETCH = 10.0
"""A fit whose mean metric stretch ends above this is warned about: its samples spread far beyond sigma (a runaway;
the modal baselines reach ~1-7, a fit 0.5-0.95)."""


def high_stretch_warning(stretch: float, sigma: float, energy: float, *, flags: bool = False) -> str | None:
    """What to say of a fit whose mean metric ``stretch`` ended above :data:`HIGH_STRETCH` at ``sigma``, its final
    ``energy`` [J] (None: nothing), naming the settings as FitConfig's fields or, with ``flags``, as ``redsim fit``'s
    options."""
    if not stretch > HIGH_STRETCH:
        return None
    lr, sigma_name = ("--lr", "--sigma") if flags else ("learning_rate", "sigma")
    return (
        f"the map spreads its samples {stretch:.3g}x as far as sigma ({sigma:g}) asks, at a final energy of "
        f"{energy:.3g} J: the fit ran away from the low-energy set; try a smaller {lr} (or {sigma_name})"
    )


@contextlib.contextmanager
def quiet_low_stretch() -> Iterator[None]:
    """Silence :func:`fit_subspace`'s low- and high-stretch warnings inside: for the benches' timing fits, and the
    CLI, which says them in its own words."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="the map spreads its samples", category=UserWarning)
        yield


class FitResult(NamedTuple):
    """What :func:`fit_subspace` returns."""

    subspace: SubspaceMap | AnchoredSubspace
    history: list[dict[str, float]]
    fit_seconds: float


def _loss_tensors(
    scene: Scene,
    model: SubspaceMap,
    z: Tensor,
    cond: Tensor | None,
    rho: Tensor,
    drive: Tensor,
    soften: Tensor,
    config: FitConfig,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The loss and its terms as 0-dim tensors: total, mean energy [J], pair term, mean metric stretch, driver [J],
    mirror penalty [J].

    ``rho``, ``drive`` (the driver stiffness now [N/m]) and ``soften`` (the weight of the
    ``config.soften`` effects now) are 0-dim tensors, so a compiled copy takes each step's values
    as inputs instead of specialising (and recompiling) on them.
    """
    y = model(z, cond if config.conditional else None)
    q = rho * y + (1.0 - rho) * scene.q_seed
    if config.soften:
        terms = scene.energy_terms(q, cond=cond)
        energy = sum(terms.values()).mean()
        weighted = energy - (1.0 - soften) * sum(terms[name] for name in config.soften).mean()
    else:
        energy = weighted = scene.energy(q, cond=cond).mean()
    log_ratio = pair_log_ratios(y, z, scene, config.sigma, config.periodic)
    pair = (log_ratio**2).mean()
    total = weighted + config.lam * pair
    pull = drive_energy(scene, y, z, drive) if config.drive > 0 else torch.zeros_like(energy)
    flip = config.mirror * mirror_gap(scene, y) if config.mirror > 0 else torch.zeros_like(energy)
    return total + pull + flip, energy, pair, torch.exp(log_ratio.detach()).mean(), pull, flip


def mirror_gap(scene: Scene, y: Tensor) -> Tensor:
    """Mean over pairs of |y(-z_i) - P y(z_i)|^2_M [kg m^2] for an antithetic batch y = [y(z); y(-z)], shape [2B, n].

    P is the scene's :class:`redsim.scene.Mirror`; 0 for a map with f(-z) = P f(z).
    """
    assert scene.mirror is not None  # checked by fit_subspace
    half = y.shape[0] // 2
    gap = y[half:] - scene.mirror.apply(y[:half])
    return (gap * scene.mass_matvec(gap)).sum(-1).mean()


def anchor_states(scene: Scene, config: FitConfig) -> tuple[Tensor, Tensor]:
    """The anchors of ``scene``: latents a_k [K, d] and reference states q_k [K, n] (module doc), in the scene's dtype.

    Raises:
        ValueError: the scene is not in the catalog, or its entry declares no reference states, or it
            declares more than 2 d of them.
    """
    from redsim import scenes

    declared = scenes.entry(scene.name).reference_states if scene.name in scenes.names() else None
    if declared is None:
        raise ValueError(f"scene {scene.name!r} declares no reference states; fit without anchor (--anchor)")
    states = [q.to(scene.q_seed) for q in scenes.entry(scene.name).compute_reference_states(scene)]
    if len(states) > 2 * config.latent_dim:
        raise ValueError(f"{len(states)} reference states need latent_dim >= {(len(states) + 1) // 2}")
    latents = torch.zeros(len(states), config.latent_dim, dtype=scene.q_seed.dtype)
    for k, q in enumerate(states):
        gap = (q - scene.q_seed).unsqueeze(0)
        distance = float((gap * scene.mass_matvec(gap)).sum().sqrt())
        latents[k, k // 2] = (-1.0) ** k * distance / config.sigma
    return latents, torch.stack(states)


def anchor_energy(scene: Scene, model: SubspaceMap, anchors: tuple[Tensor, Tensor], stiffness: float) -> Tensor:
    """mean_k stiffness/2 |MLP(a_k) - q_k|^2_M [J] for anchors (a [K, d], q [K, n]) (:func:`anchor_states`)."""
    latents, states = anchors
    gap = model(latents) - states
    return 0.5 * stiffness * (gap * scene.mass_matvec(gap)).sum(-1).mean()


def anchor_at(step: int, config: FitConfig, ramp_steps: int | None = None) -> float:
    """Anchor stiffness [1/s^2] in step ``step`` (0-based): ``anchor``, then falling linearly to 0 (as the driver)."""
    return _held_then_falling(config.anchor, config.anchor_fraction, step, ramp_steps or config.steps)


def modal_at(step: int, config: FitConfig, ramp_steps: int | None = None) -> float:
    """Modal pull weight in step ``step`` (0-based): ``modal``, then falling linearly to 0 (as the anchor)."""
    return _held_then_falling(config.modal, config.modal_fraction, step, ramp_steps or config.steps)


def _held_then_falling(value: float, fraction: float, step: int, steps: int) -> float:
    """``value`` for the first half of ``fraction`` of ``steps`` steps, then linearly down to 0 at ``fraction``."""
    progress = step / (fraction * steps)
    return value * min(1.0, max(0.0, 2.0 * (1.0 - progress)))


def batch_latents(config: FitConfig, generator: torch.Generator, dtype: torch.dtype) -> Tensor:
    """One step's latents [B, d]: :func:`redsim.subspace.sample_latents`, antithetic ([z; -z]) with ``mirror``."""
    antithetic = config.mirror > 0
    count = config.batch_size // 2 if antithetic else config.batch_size
    z = sample_latents(
        count, config.latent_dim, config.periodic, generator=generator, dtype=dtype, device=config.device
    )
    return torch.cat([z, -z]) if antithetic else z


def drive_energy(scene: Scene, q: Tensor, z: Tensor, stiffness: Tensor | float) -> Tensor:
    """Mean over the batch of the drivers' penalty stiffness/2 sum_d |h_d(q) - target_d(z)|^2 [J].

    Args:
        scene: Declares the drivers (:class:`redsim.scene.Driver`).
        q: Free configurations, shape [B, n].
        z: Latents, shape [B, d]; driver k turns with ``z[:, driver.latent]``.
        stiffness: Penalty stiffness [N/m].
    """
    x = scene.full_positions(q)
    gap2 = torch.zeros_like(q[:, 0])
    for driver in scene.drivers:
        gap = scene.handle(driver.handle).position(x) - driver.target(z[:, driver.latent])
        gap2 = gap2 + (gap**2).sum(-1)
    return 0.5 * stiffness * gap2.mean()


def _terms(energy: Tensor, pair: Tensor, stretch: Tensor, pull: Tensor, flip: Tensor) -> dict[str, float]:
    return {
        "energy": float(energy.detach()),
        "pair": float(pair.detach()),
        "stretch": float(stretch),
        "drive": float(pull.detach()),
        "mirror": float(flip.detach()),
    }


def subspace_loss(
    scene: Scene,
    model: SubspaceMap,
    z: Tensor,
    cond: Tensor | None,
    rho: float,
    config: FitConfig,
    step: int = 0,
    anchors: tuple[Tensor, Tensor] | None = None,
    modal: ModalTargets | None = None,
    ramp_steps: int | None = None,
    core: Callable[..., tuple[Tensor, ...]] | None = None,
) -> tuple[Tensor, dict[str, float]]:
    """The fitting loss on one batch, as :func:`fit_subspace` takes its steps, and its terms (mean energy [J],
    pair term, mean metric stretch, driver [J], mirror penalty [J]; anchor pull [J] and modal pull [J] where those
    terms are on); ``z`` must be antithetic, [z; -z], when ``config.mirror > 0``.

    ``step`` (0-based) sets the driver stiffness (:func:`drive_at`), softening (:func:`soften_at`), the
    anchor stiffness (:func:`anchor_at`; ``anchors`` from :func:`anchor_states`, needed when ``config.anchor > 0``)
    and the modal pull's (:func:`modal_at`; ``modal`` from :func:`redsim.trainers.modal.modal_targets`, needed
    when ``config.modal > 0``), over a fit planned for ``ramp_steps`` steps (default ``config.steps``). ``core``:
    the paper's terms (default the eager ones; the fit passes them compiled with ``config.compile``).
    """
    if config.mirror > 0 and scene.mirror is None:
        raise ValueError(f"scene {scene.name!r} declares no mirror; fit without mirror (--mirror)")
    rho_t, drive_t, soften_t = (
        torch.as_tensor(v, dtype=z.dtype, device=z.device)
        for v in (rho, drive_at(step, config, ramp_steps), soften_at(step, config, ramp_steps))
    )
    total, *parts = (core or _loss_tensors)(scene, model, z, cond, rho_t, drive_t, soften_t, config)
    terms = _terms(*parts)
    if config.anchor > 0:
        if anchors is None:
            raise ValueError("config.anchor > 0 needs the anchors (anchor_states)")
        pull = anchor_energy(scene, model, anchors, anchor_at(step, config, ramp_steps))
        total = total + pull
        terms["anchor"] = float(pull.detach())
    if config.modal > 0:
        if modal is None:
            raise ValueError("config.modal > 0 needs the modal targets (redsim.trainers.modal.modal_targets)")
        hold = 0.5 * modal_at(step, config, ramp_steps) * modal_gap(scene, model, modal, config.sigma)
        total = total + hold
        terms["modal"] = float(hold.detach())
    return total, terms


def rho_at(step: int, config: FitConfig, ramp_steps: int | None = None) -> float:
    """Seeded-exploration weight rho after ``step`` completed steps.

    rho rises over ``exploration_fraction * ramp_steps`` steps, ``ramp_steps`` being the length of
    the fit the ramp was planned for (default ``config.steps``; an extended fit keeps its first length).
    """
    return min(1.0, (step + 1) / (config.exploration_fraction * (ramp_steps or config.steps)))


def ramp_end(config: FitConfig, ramp_steps: int) -> int:
    """The fewest steps after which rho is 1 (:func:`rho_at`) for a ramp planned over ``ramp_steps`` steps."""
    return math.ceil(config.exploration_fraction * ramp_steps)


def _lr_step_size(steps: int) -> int:
    """Steps between halvings of the learning rate: a quarter of the run."""
    return max(1, steps // 4)


def drive_at(step: int, config: FitConfig, ramp_steps: int | None = None) -> float:
    """Driver stiffness [N/m] in step ``step`` (0-based): ``drive``, then falling linearly to 0.

    Like rho, it follows the length ``ramp_steps`` the fit was planned for (default ``config.steps``).
    """
    return _held_then_falling(config.drive, config.drive_fraction, step, ramp_steps or config.steps)


def soften_at(step: int, config: FitConfig, ramp_steps: int | None = None) -> float:
    """Weight of the ``soften`` effects in step ``step`` (0-based): geometric from ``soften_from`` to 1 (planned
    over ``ramp_steps``, default ``config.steps``, as rho)."""
    progress = min(1.0, step / (config.soften_fraction * (ramp_steps or config.steps)))
    return config.soften_from ** (1.0 - progress) if config.soften else 1.0


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
    stop_at: int | None = None,
    overwrite: bool = False,
    **overrides: Any,
) -> FitResult:
    """Fit a neural subspace to ``scene`` from its energy alone.

    Args:
        scene: The system; its energy is evaluated in ``config.dtype`` on ``config.device``.
        config: Hyperparameters (defaults: :class:`FitConfig`).
        seed: Seeds the MLP initialisation and every latent sample; the same seed reproduces a fit. An integer in
            [0, 2**64 - 1] (as `redsim fit --seed`; a NumPy integer too).
        out: Checkpoint stem. With it, ``STEM.fit.pt`` holds resumable training state (written
            every ``checkpoint_every`` steps and on Ctrl-C) and the final map is saved to
            ``STEM.pt`` + ``STEM.json``.
        resume: Continue from ``STEM.fit.pt`` (same scene and config required, except ``steps``:
            a larger value extends a fit, with the learning-rate schedule recomputed for the new
            length from the step reached on; rho keeps the ramp of the first length, so ``steps``
            may not end the fit before rho reaches 1 (:func:`ramp_end`), nor before the steps done).
        callbacks: Called as ``cb(step, terms)`` after every step.
        progress: Show a tqdm bar with the energy, pair and stretch terms.
        command: The command line recorded in the metadata (default: a `redsim fit` line).
        stop_at: Stop when this many steps are done, before ``config.steps``, as Ctrl-C does: the training state is
            saved (``resume`` continues it), no map is written, and :class:`FitStopped` is raised. Needs ``out``.
        overwrite: Replace a fit already at ``out`` (its map, metadata and training state); without it (or
            ``resume``) one there is refused, so that a finished or interrupted fit is never replaced silently.
        **overrides: FitConfig fields replacing those of ``config`` (``dim`` is an alias of
            ``latent_dim``), e.g. ``fit_subspace(scene, dim=8, sigma=1.0, lam=1.0, steps=2000)``.

    Raises:
        ValueError: bad config or seed, an alias given with its field at another value (``dim=3, latent_dim=4``), a
            conditional fit on a scene without conditions, ``resume`` without ``out``, with no matching checkpoint or
            with ``overwrite``, ``stop_at`` outside [steps done, ``config.steps``) or without ``out``, or a folder
            where one of the fit's files goes (:func:`check_fit_files`).
        FileExistsError: a fit at ``out`` and neither ``resume`` nor ``overwrite``.
        RuntimeError: ``compile`` on the CPU where no C++ compiler runs (nothing is written).
        FitStopped: the fit stopped at ``stop_at``.
    """
    seed = _fit_seed(seed)
    if stop_at is not None and (isinstance(stop_at, bool) or not isinstance(stop_at, numbers.Integral)):
        raise ValueError(f"stop_at must be an integer, got {stop_at!r}")
    if stop_at is not None and out is None:
        raise ValueError("stop_at needs out (the training state is saved there)")
    if resume and out is None:
        raise ValueError("resume needs out: the checkpoint stem whose STEM.fit.pt it continues")
    if resume and overwrite:
        raise ValueError("resume continues the fit at out, overwrite replaces it: give one")
    if out is not None:
        check_fit_files(out)
    if out is not None and not (resume or overwrite) and (found := existing_fit(out)) is not None:
        if (why := other_scene_fit(out, scene)) is not None:
            raise FileExistsError(
                f"a fit of another scene is at {found} ({why}): give another out for this one, or replace that one "
                "with overwrite=True"
            )
        raise FileExistsError(
            f"a fit exists at {found}: continue it with resume=True (a larger steps extends it), or replace it with "
            "overwrite=True"
        )
    for alias, field in FIT_ALIASES.items():
        if alias in overrides:
            if field in overrides and overrides[field] != overrides[alias]:
                raise ValueError(
                    f"{alias} is an alias of {field}, and they differ: {alias}={overrides[alias]!r}, "
                    f"{field}={overrides[field]!r}; give one"
                )
            overrides[field] = overrides.pop(alias)
    unknown = sorted(set(overrides) - {f.name for f in dataclasses.fields(FitConfig)})
    if unknown:
        raise ValueError(f"unknown fit option(s) {unknown}; valid: {[f.name for f in dataclasses.fields(FitConfig)]}")
    config = dataclasses.replace(config or FitConfig(), **overrides)
    if config.conditional and scene.condition_space is None:
        raise ValueError(f"scene {scene.name!r} has no condition space; fit without conditional (--cond)")
    if config.drive > 0:
        _check_drivers(scene, config)
    if config.mirror > 0 and scene.mirror is None:
        raise ValueError(f"scene {scene.name!r} declares no mirror; fit without mirror (--mirror)")
    if config.anchor > 0 and config.conditional:
        raise ValueError("anchor: conditional fits cannot be anchored (the reference states are for one condition)")
    unknown_effects = sorted(set(config.soften) - {e.name for e in scene.effects})
    if unknown_effects:
        raise ValueError(
            f"soften: scene {scene.name!r} has no effect(s) {unknown_effects}; it has {[e.name for e in scene.effects]}"
        )
    dtype = DTYPES[config.dtype]
    work = scene.to(device=config.device, dtype=dtype)
    anchors = None
    if config.anchor > 0:
        anchors = tuple(t.to(device=config.device, dtype=dtype) for t in anchor_states(scene, config))
    targets = None
    if config.modal > 0:
        found = modal_targets(scene, config.latent_dim, config.conditional, seed)
        targets = found.to(config.device, dtype)
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
        model = SubspaceMap(arch) if config.anchor_map == "none" else anchored_map(scene, arch, config)
        model = model.to(device=config.device, dtype=dtype)
    if config.seed_bias:
        with torch.no_grad():
            model.mlp[-1].bias.copy_(work.q_seed)
    if targets is not None:
        start_at_rest(model, targets)
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
    recorded = config  # what the metadata records: a resume that runs no step keeps the saved fit's own settings
    state_path = None if out is None else checkpoint_path(out, ".fit.pt")
    if resume:
        if state_path is None or not state_path.is_file():
            raise ValueError(f"nothing to resume: {state_path} does not exist")
        saved = _load_training_state(state_path, scene, config, model, optimizer, scheduler, generator)
        if saved["seed"] is not None and saved["seed"] != seed:  # the seed set its samples: another seed is another fit
            raise CheckpointError(f"training state was made with seed {saved['seed']}, not {seed}", str(state_path))
        start_step, elapsed, history = saved["step"], saved["elapsed"], saved["history"]
        ramp_steps, extensions = saved["ramp_steps"], saved["extensions"]
        if start_step == config.steps:  # nothing to run: fused_adam or compile given now changed nothing
            recorded = dataclasses.replace(config, **{k: saved["config"][k] for k in _ROUND_OFF_ONLY})
        if saved["steps"] != config.steps:
            _reschedule(optimizer, scheduler, config, start_step)
            extensions.append({"at_step": start_step, "from_steps": saved["steps"], "to_steps": config.steps})
            if saved["command"]:  # the stop too where it came before the first length's end: the rescheduling step
                stop = f" --stop-at {start_step}" if start_step < saved["steps"] else ""
                command = f"{saved['command']}{stop} && {command} --resume"
        else:
            command = saved["command"]
        _set_fused(optimizer, fused)
        log.info("resuming %s at step %d of %d", state_path, start_step, config.steps)
    if stop_at is not None and not start_step <= stop_at < config.steps:
        raise ValueError(f"stop_at must be < steps ({config.steps}) and >= the {start_step} steps done, got {stop_at}")
    if config.compile:  # Inductor builds its CPU kernels with a C++ compiler: refused here, not deep in torch later
        from redsim.runtime.stepper import check_compiler

        check_compiler(torch.device(config.device))
    if state_path is not None and overwrite:  # the old training state must not be taken for the new fit's; removed
        state_path.unlink(missing_ok=True)  # only here, after every refusal: a refused call keeps it

    bar = None
    if progress:
        bar = progress_bar(total=config.steps, initial=start_step, desc=f"fit {scene.name}", dynamic_ncols=True)
    completed, generator_state = start_step, generator.get_state()
    loss_fn = torch.compile(_loss_tensors, dynamic=False) if config.compile else _loss_tensors
    record = scene_record(scene)  # names the parameters that differ when another scene would resume it
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
                    "scene_record": record,
                    "config": dataclasses.asdict(recorded),
                    "model": model.state_dict(),
                    "optimizer": optimizer.state_dict(),
                    "scheduler": scheduler.state_dict(),
                    "generator": generator_state,
                    "ramp_steps": ramp_steps,
                    "extensions": extensions,
                    "command": command,
                    "seed": seed,
                },
            )

    with deferred_interrupts() as interrupt_point:
        try:
            for step in range(start_step, config.steps if stop_at is None else stop_at):
                z = batch_latents(config, generator, dtype)
                cond = None
                if work.condition_space is not None and not config.conditional:
                    cond = work.pack_condition(None, config.batch_size)
                elif work.condition_space is not None and config.mirror > 0:  # z_i and -z_i under one condition
                    cond = work.condition_space.sample(config.batch_size // 2, generator).repeat(2, 1)
                elif work.condition_space is not None:
                    cond = work.condition_space.sample(config.batch_size, generator)
                rho = rho_at(step, config, ramp_steps)
                loss, terms = subspace_loss(
                    work, model, z, cond, rho, config, step, anchors, targets, ramp_steps, loss_fn
                )
                if not torch.isfinite(loss):
                    raise FloatingPointError(
                        f"loss became {float(loss.detach())} at step {step} (terms {terms}); lower the learning rate "
                        "or sigma"
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
                    bar.set_postfix(
                        E=f"{terms['energy']:.3g}",
                        pair=f"{terms['pair']:.3g}",
                        stretch=f"{terms['stretch']:.3f}",
                        refresh=False,  # drawn by update(), as often as the bar allows
                    )
                    bar.update(1)
                if config.checkpoint_every and completed % config.checkpoint_every == 0:
                    save_state()
                interrupt_point()  # a Ctrl-C during the step stops here, between steps
        except ForcedInterrupt:  # a second Ctrl-C inside a step: the weights may be part of an update, not saved
            if state_path is not None:
                log.warning("interrupted inside step %d; not saved: the last saved state is resumable", step + 1)
            raise
        except KeyboardInterrupt:
            save_state()
            if state_path is not None:
                log.warning("interrupted after step %d; rerun with --resume to continue (%s)", completed, state_path)
            raise
        finally:
            if bar is not None:
                bar.close()
        # the end state too, so that a finished fit can be extended (--resume with more --steps); inside the block,
        # so a Ctrl-C after the last step's check is raised at its end with this state saved
        save_state()
    if completed < config.steps:
        assert state_path is not None  # stop_at needs out
        raise FitStopped(completed, state_path)
    fit_seconds = elapsed + time.perf_counter() - clock
    tail = history[-min(len(history), 100) :]
    model.metadata = {
        "scene": scene.name,
        "scene_fingerprint": scene.fingerprint(),
        "scene_params": scene.params,
        "conditions": _condition_doc(scene) if config.conditional else [],
        "fit": dataclasses.asdict(recorded),
        "seed": seed,
        "fit_seconds": fit_seconds,
        "final": {k: sum(h[k] for h in tail) / len(tail) for k in ("energy", "pair", "stretch")},
        "redsim_version": __version__,
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
        _remove_stale_cubature(out, model)
    final = model.metadata["final"]
    message = low_stretch_warning(final["stretch"], config.sigma) or high_stretch_warning(
        final["stretch"], config.sigma, final["energy"]
    )
    if message is not None:
        warnings.warn(message, UserWarning, stacklevel=2)
    return FitResult(model, history, fit_seconds)


def _fit_seed(seed: Any) -> int:
    """``seed`` as a Python int: an integer (a NumPy one too) in [0, 2**64 - 1], what torch's generators and
    ``redsim fit --seed`` take (a negative one fitted, but the recorded command did not run)."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or not 0 <= seed < 2**64:
        raise ValueError(f"seed must be an integer in [0, 2**64 - 1] (as redsim fit --seed), got {seed!r}")
    return int(seed)


def _remove_stale_cubature(stem: str | Path, model: torch.nn.Module) -> None:
    """Delete (saying so) the cubature beside ``stem`` unless it records ``model``'s weights hash: one made for the map
    this fit replaced would be refused (a resume that ran no step keeps the map, and its cubature)."""
    from redsim.cubature.energy import Cubature, cubature_path

    stale = cubature_path(stem)
    if not stale.is_file():
        return
    try:
        if Cubature.load(stale).map_fingerprint == map_fingerprint(model):
            return
    except CheckpointError:  # unreadable: no use to any map
        pass
    stale.unlink()
    warnings.warn(
        f"removed {stale}: it was built for the map this fit replaced (rebuild it: redsim cubature {stem})",
        stacklevel=3,
    )


def _check_drivers(scene: Scene, config: FitConfig) -> None:
    """Raise ValueError unless ``scene`` declares drivers, each turned by a periodic latent of ``config``."""
    if not scene.drivers:
        raise ValueError(f"scene {scene.name!r} declares no driver; fit without drive (--drive)")
    for driver in scene.drivers:
        if driver.latent not in config.periodic:
            raise ValueError(
                f"driver {driver.name!r} of scene {scene.name!r} turns with latent {driver.latent}, which is not "
                f"periodic (periodic {list(config.periodic)}; --periodic)"
            )


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
    """The `redsim fit` command line that reproduces this fit (for a scene built in Python, the fit's settings: no
    command rebuilds that scene, and `redsim inspect` says so)."""
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
    # `redsim fit` starts from the scene's preset: a setting turned off there is written too (--drive 0, ...)
    base = FitConfig(**preset(scene.name))
    if config.exploration_fraction != 1.0 or base.exploration_fraction != 1.0:
        parts += ["--explore", repr(config.exploration_fraction)]
    if config.seed_bias or base.seed_bias:
        parts.append("--seed-bias" if config.seed_bias else "--no-seed-bias")
    if config.drive > 0:
        parts += ["--drive", repr(config.drive), "--drive-fraction", repr(config.drive_fraction)]
    elif base.drive > 0:
        parts += ["--drive", "0"]
    if config.soften:
        parts += ["--soften", ",".join(config.soften), "--soften-from", repr(config.soften_from)]
        parts += ["--soften-fraction", repr(config.soften_fraction)]
    for field, flag in (("anchor", "--anchor"), ("modal", "--modal")):
        if getattr(config, field) > 0:
            parts += [
                flag,
                repr(getattr(config, field)),
                f"{flag}-fraction",
                repr(getattr(config, f"{field}_fraction")),
            ]
        elif getattr(base, field) > 0:
            parts += [flag, "0"]
    if config.anchor_map != "none" or preset(scene.name).get("anchor_map", "none") != "none":
        parts += ["--anchor-map", config.anchor_map]  # "none" too where the scene's preset anchors its map
    if config.anchor_map != "none":
        if config.conditional:
            parts += ["--anchor-map-cond", config.anchor_map_cond]
        if config.anchor_radius > 0:
            parts += ["--anchor-radius", repr(config.anchor_radius)]
    if config.mirror > 0 or base.mirror > 0:
        parts += ["--mirror", repr(config.mirror)]
    default = FitConfig()
    for field in ("dtype", "device"):  # the precision and the random stream (a CUDA generator draws its own)
        if getattr(config, field) != getattr(default, field):
            parts += [f"--{field}", str(getattr(config, field))]
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
    write_atomically(path, lambda tmp: torch.save(state, tmp))


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
        ``step``, ``elapsed``, ``history``, the saved ``steps``, ``ramp_steps``, ``extensions``, ``command``,
        ``seed`` (None in states written before it was recorded) and the saved ``config`` (a dict).
    """
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        raise CheckpointError(f"training state is corrupt ({type(err).__name__}: {err})", str(path)) from None
    needed = ("scene_fingerprint", "config", "step", "elapsed", "history", "model", "optimizer", "scheduler")
    if not isinstance(state, dict) or (lacking := [key for key in (*needed, "generator") if key not in state]):
        what = f"it lacks {lacking}" if isinstance(state, dict) else f"it holds a {type(state).__name__}"
        raise CheckpointError(
            f"not a fit's training state ({what}): a map saved at a stem ending in .fit takes this name; move it",
            str(path),
        )
    if not scene.accepts(state["scene_fingerprint"]):
        why = _state_scene_mismatch(state, scene) or (
            f"fingerprint {state['scene_fingerprint']}, this scene's {scene.fingerprint()}"
        )
        raise CheckpointError(f"training state is for another scene: {why}", str(path))
    free = (*_ROUND_OFF_ONLY, "steps", "checkpoint_every")  # checkpoint_every: how often it saves, not what
    mine = {k: v for k, v in dataclasses.asdict(config).items() if k not in free}
    saved = {k: v for k, v in state["config"].items() if k not in free}
    saved["periodic"] = tuple(saved["periodic"])
    added = ("seed_bias", "drive", "drive_fraction", "soften", "soften_from", "soften_fraction")
    for key in (
        *added,
        "anchor",
        "anchor_fraction",
        "modal",
        "modal_fraction",
        "anchor_map",
        "anchor_map_cond",
        "anchor_radius",
        "mirror",
    ):
        saved.setdefault(key, getattr(FitConfig(), key))  # states written before the options existed
    saved["soften"] = tuple(saved["soften"])
    if saved != mine:
        diff = [(k, saved.get(k), mine[k]) for k in sorted(mine) if saved.get(k) != mine[k]]
        raise ResumeSettingsError(diff, str(state.get("command") or ""), str(path))
    step, saved_steps = int(state["step"]), int(state["config"]["steps"])
    ramp_steps = int(state.get("ramp_steps", saved_steps))
    minimum = max(step, ramp_end(config, ramp_steps))
    if config.steps < minimum:
        why = (
            f"{step} steps are done"
            if minimum == step
            else f"rho, ramped for {ramp_steps} steps, reaches 1 at step {minimum} (the saved map is the one at rho 1)"
        )
        raise CheckpointError(f"steps must be >= {minimum} to resume, got {config.steps}: {why}", str(path))
    try:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        generator.set_state(state["generator"])
    except (KeyError, RuntimeError, TypeError, ValueError) as err:
        raise CheckpointError(f"training state is corrupt ({type(err).__name__}: {err})", str(path)) from None
    return {
        "step": step,
        "elapsed": float(state["elapsed"]),
        "history": list(state["history"]),
        "steps": saved_steps,
        "ramp_steps": ramp_steps,
        "extensions": list(state.get("extensions", [])),
        "command": state.get("command", ""),
        "seed": state.get("seed"),
        "config": state["config"],
    }


def check_fit_files(stem: str | Path) -> None:
    """Refuse a stem where ``STEM.pt``, ``STEM.json`` or ``STEM.fit.pt`` is something other than a file (a folder):
    a fit would run all its steps and then fail to save (its training state too, so all of it lost).

    Also refuse a stem ending in ``.fit``: its map ``STEM.fit.pt`` would take the name of a training state.

    Raises:
        ValueError: naming the path that is in the way.
    """
    weights = checkpoint_path(stem, ".pt")
    if weights.name.endswith(".fit.pt"):
        raise ValueError(
            f"a stem ending in .fit would save the map as {weights}, the name of a fit's training state (the commands "
            "would take it for one): choose another out"
        )
    for suffix in (".pt", ".json", ".fit.pt"):
        path = checkpoint_path(stem, suffix)
        if path.exists() and not path.is_file():
            raise ValueError(
                f"{path} is a folder, not a file, so a fit at {stem} could not be saved: remove it or "
                "choose another out"
            )


def existing_fit(stem: str | Path) -> Path | None:
    """The first file of a fit at ``stem`` (``STEM.pt``, ``STEM.json`` or ``STEM.fit.pt``); None where there is none."""
    return next((p for p in (checkpoint_path(stem, s) for s in (".pt", ".json", ".fit.pt")) if p.is_file()), None)


def recorded_fit_command(stem: str | Path) -> str | None:
    """The ``redsim fit ...`` command the fit at ``stem`` records (its training state's, else its ``.json``'s), its
    ``--out`` made ``stem`` (the files may have moved, or the command was run from another folder), which ``--resume``
    appended to continues it on its own scene; None where neither says."""
    from redsim.subspace.checkpoint import read_metadata

    try:
        command = torch.load(checkpoint_path(stem, ".fit.pt"), map_location="cpu", weights_only=True)["command"]
    except Exception:  # none, or unreadable: the record may say
        try:
            command = read_metadata(stem).get("command")
        except CheckpointError:
            return None
    try:
        parts = shlex.split(command) if isinstance(command, str) and command.startswith("redsim fit ") else None
    except ValueError:  # unbalanced quotes: not a command this module wrote
        parts = None
    if parts is None:
        return None
    out = parts.index("--out") if "--out" in parts[:-1] else len(parts)
    return shlex.join([*parts[:out], "--out", os.fspath(stem), *parts[out + 2 :]])


def other_scene_fit(stem: str | Path, scene: Scene) -> str | None:
    """Why the fit at ``stem`` is of another scene than ``scene``, or None: the same scene, no fit there, or files
    that do not say (resuming says why). Its training state ``STEM.fit.pt`` decides where there is a readable one
    (what a resume continues: an interrupted ``--overwrite`` leaves the replaced fit's ``.pt`` and ``.json`` beside
    it), else the ``STEM.json`` record."""
    from redsim.subspace.checkpoint import read_metadata, scene_mismatch

    try:
        state = torch.load(checkpoint_path(stem, ".fit.pt"), map_location="cpu", weights_only=True)
        fingerprint = state["scene_fingerprint"]
    except Exception:  # none, or unreadable: the record may say
        fingerprint = None
    if fingerprint is not None and scene.accepts(fingerprint):
        return None
    try:
        doc = read_metadata(stem)
    except CheckpointError:
        doc = None
    if doc is not None and fingerprint in (None, doc.get("scene_fingerprint")):  # the record of that same fit
        return scene_mismatch(doc, scene)  # (names the parameters that differ)
    if fingerprint is not None:
        return _state_scene_mismatch(state, scene) or (
            f"its training state is of scene fingerprint {fingerprint}, not this scene's {scene.fingerprint()}"
        )
    return None


def _state_scene_mismatch(state: dict[str, Any], scene: Scene) -> str | None:
    """How the scene a training state was made for differs from ``scene``, which does not accept its fingerprint: the
    name and the parameters that differ (:func:`redsim.subspace.checkpoint.scene_mismatch`); None for a state written
    before it recorded them (the callers name the two fingerprints)."""
    try:
        return scene_mismatch(json.loads(state["scene_record"]), scene)
    except (KeyError, TypeError, ValueError, AttributeError):  # an older state, or a record that does not read
        return None


def planned_steps(stem: str | Path) -> int | None:
    """The length (``steps``) of the fit whose training state is at ``STEM.fit.pt``; None without a readable one
    (resuming it says why)."""
    try:
        state = torch.load(checkpoint_path(stem, ".fit.pt"), map_location="cpu", weights_only=True)
        return int(state["config"]["steps"])
    except Exception:
        return None


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
