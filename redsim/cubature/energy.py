"""A cubature: its rules per effect, stored beside the map it belongs to, and the latent energy it gives.

``STEM.cubature.json`` sits beside the map's ``STEM.pt`` + ``STEM.json``. It records the scene's name
and fingerprint and a hash of the map's weights, so it is refused for another scene or another map.

:class:`CubatureEnergy` is a :class:`redsim.runtime.LatentEnergy` whose cost does not grow with n:

    E_cub(z) = sum_effects sum_{e kept} w_e E_e(x_S(z)) + sum_linear (r(z) . c + e0) + offset,

where x_S = r(z) W_S^T + b_S are only the full DOFs the kept elements read (a sliced output layer) and
r(z) the map's last features. The cloth's elements (membrane triangles, bending hinges) read only their edges
x_j - x_0, so they get those straight from r as well, r W_E^T + b_E with the row differences W_E taken once in
float64: no gather of vertex positions, no scatter of their gradients, and no float32 cancellation in x_j - x_0.

It also offers the runtime's reduced-inertia extension (``features``, ``energy_features`` and the output layer),
with which the stepper evaluates 1/(2h^2)|f(z) - qbar|_M^2 exactly as (r - rbar)^T (W^T M W) (r - rbar) / (2h^2),
a w x w form.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from redsim.cubature.fit import LINEAR_KINDS, MODES, CubatureConfig, EffectRule, fit_rules
from redsim.cubature.output import AffineOutput, column_major, sliced_layer
from redsim.devices import check_device
from redsim.effects.base import Effect
from redsim.effects.penalty import FrameSet, SDFContact
from redsim.integrators import map_condition_dim
from redsim.points import PointSet
from redsim.scene import Scene
from redsim.subspace import CheckpointError, checkpoint_path, map_fingerprint, periodic_latents, write_atomically

FORMAT_VERSION = 1
SUFFIX = ".cubature.json"


def cubature_path(path: str | Path) -> Path:
    """``STEM.cubature.json`` for a map given as ``STEM``, ``STEM.pt``, ``STEM.json`` or the cubature itself."""
    path = Path(path)
    if path.name.endswith(SUFFIX):
        return path
    return checkpoint_path(path, SUFFIX)


@dataclass
class Cubature:
    """The rules of every effect of one scene's energy, for one map.

    Attributes:
        scene: Scene name.
        scene_fingerprint: :meth:`redsim.scene.Scene.fingerprint` of the scene it was built for.
        map_fingerprint: :func:`map_fingerprint` of the map.
        rules: One :class:`EffectRule` per effect (load terms excluded).
        summary: State counts and total errors (relative force + energy error on training and held-out states).
        config: The :class:`CubatureConfig` fields.
        command: The ``redsim cubature ...`` command line that made it ("" when built in Python).
    """

    scene: str
    scene_fingerprint: str
    map_fingerprint: str
    rules: list[EffectRule]
    summary: dict[str, Any] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)
    command: str = ""

    @property
    def kept(self) -> int:
        """Elements evaluated per state (subsampled and whole effects)."""
        return sum(int(r.indices.numel()) for r in self.rules)

    def save(self, path: str | Path) -> Path:
        """Write ``STEM.cubature.json`` beside the map ``path`` (``STEM``/``STEM.pt``); returns its path."""
        out = cubature_path(path)
        rules = [
            {
                "name": r.name,
                "mode": r.mode,
                "element_count": r.element_count,
                "indices": r.indices.tolist() if r.mode == "cubature" else None,
                "weights": r.weights.tolist() if r.mode == "cubature" else None,
                "train_error": r.train_error,
                "held_out_error": r.held_out_error,
                "history": r.history,
            }
            for r in self.rules
        ]
        doc = {
            "format_version": FORMAT_VERSION,
            "scene": self.scene,
            "scene_fingerprint": self.scene_fingerprint,
            "map_fingerprint": self.map_fingerprint,
            "summary": self.summary,
            "config": self.config,
            "command": self.command,
            "rules": rules,
        }
        out.parent.mkdir(parents=True, exist_ok=True)
        text = json.dumps(doc, indent=1, sort_keys=True) + "\n"
        write_atomically(out, lambda tmp: tmp.write_text(text))
        return out

    @classmethod
    def load(cls, path: str | Path) -> Cubature:
        """Read ``STEM.cubature.json`` (given as the map's stem or path, or the file itself).

        Raises:
            CheckpointError: a missing or corrupt file (two rules for one effect among the ways), or an unsupported
                format version.
        """
        src = cubature_path(path)
        if not src.is_file():
            raise CheckpointError("no cubature file (make one with `redsim cubature`)", str(src))
        try:
            doc = json.loads(src.read_text())
            if not isinstance(doc, dict):
                raise CheckpointError(f"corrupt cubature file (not a JSON object: {type(doc).__name__})", str(src))
            if doc.get("format_version") != FORMAT_VERSION:
                raise CheckpointError(f"unsupported format_version {doc.get('format_version')!r}", str(src))
            _check_header(doc, str(src))
            names = [r["name"] for r in doc["rules"]]
            if twice := sorted({n for n in names if names.count(n) > 1}):
                counts = ", ".join(f"effect {n!r} has {names.count(n)} rules" for n in twice)
                raise CheckpointError(
                    f"{counts}, not one: the cubature file was edited or damaged; rebuild it with `redsim cubature`",
                    str(src),
                )
            rules = []
            for r in doc["rules"]:
                if r["mode"] not in MODES:
                    raise CheckpointError(f"unknown mode {r['mode']!r}; valid: {list(MODES)}", str(src))
                count = r["element_count"]
                if type(count) is not int or count < 0:  # int() read 18.7 as 18 and "18" as 18, without a word
                    raise CheckpointError(
                        f"effect {r['name']!r}: element_count must be an integer >= 0, got {count!r}", str(src)
                    )
                if r["mode"] == "cubature":
                    # torch.tensor(..., dtype=int64) truncates 0.5 to element 0 and reads true as 1, and a weight
                    # true as 1.0, without a word
                    for what, values, kinds in (
                        ("kept element indices must be integers", r["indices"], (int,)),
                        ("weights must be numbers", r["weights"], (int, float)),
                    ):
                        if odd := [(i, v) for i, v in enumerate(values) if type(v) not in kinds]:
                            i, v = odd[0]
                            raise CheckpointError(f"effect {r['name']!r}: {what}, got {v!r} at position {i}", str(src))
                    index = torch.tensor(r["indices"], dtype=torch.int64)
                    weights = torch.tensor(r["weights"], dtype=torch.float64)
                else:
                    index = torch.arange(count) if r["mode"] == "full" else torch.zeros(0, dtype=torch.int64)
                    weights = torch.ones(index.shape[0], dtype=torch.float64)
                _check_rule(r["name"], count, index, weights, str(src))
                history = [tuple(h) for h in r.get("history", [])]
                rules.append(
                    EffectRule(
                        r["name"], r["mode"], count, index, weights, r["train_error"], r["held_out_error"], history
                    )
                )
            return cls(
                doc["scene"],
                doc["scene_fingerprint"],
                doc["map_fingerprint"],
                rules,
                doc.get("summary", {}),
                doc.get("config", {}),
                doc.get("command", ""),
            )
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
            if isinstance(err, CheckpointError):
                raise
            raise CheckpointError(f"corrupt cubature file ({type(err).__name__}: {err})", str(src)) from None

    def check(self, scene: Scene, subspace: nn.Module, where: str = "") -> None:
        """Refuse another scene or another map (:class:`CheckpointError`)."""
        if self.scene != scene.name or not scene.accepts(self.scene_fingerprint):
            raise CheckpointError(
                f"cubature built for scene {self.scene!r} (fingerprint {self.scene_fingerprint}), "
                f"not for scene {scene.name!r} (fingerprint {scene.fingerprint()})",
                where,
            )
        mine = map_fingerprint(subspace)
        if mine != self.map_fingerprint:
            raise CheckpointError(
                f"cubature built for another map (weights hash {self.map_fingerprint}, this map {mine}); "
                "make one for this map with `redsim cubature CHECKPOINT --elements K` (CHECKPOINT: this map's STEM.pt)",
                where,
            )
        effects = scene.load_free_effects("a cubature")
        names = {e.name: e.element_count for e in effects}
        theirs = {r.name: r.element_count for r in self.rules}
        if names != theirs:
            raise CheckpointError(f"cubature effects {theirs} differ from the scene's {names}", where)
        kinds = {e.name: e.kind for e in effects}
        for rule in self.rules:  # "linear" reduces an effect to its value and gradient at r = 0: exact for these only
            if rule.mode == "linear" and kinds[rule.name] not in LINEAR_KINDS:
                raise CheckpointError(
                    f"effect {rule.name!r} is reduced as linear, but its kind {kinds[rule.name]!r} is not one of "
                    f"{list(LINEAR_KINDS)}: the cubature file was edited or damaged; rebuild it with `redsim cubature`",
                    where,
                )


def _check_header(doc: dict[str, Any], where: str) -> None:
    """Refuse a cubature file whose summary, config or command cannot be a cubature's (:class:`CheckpointError`):
    the bench reads and formats the summary's errors, and failed on a list, or an error given as text, after its
    whole run."""
    for key, kind in (("summary", dict), ("config", dict), ("command", str)):
        if key in doc and not isinstance(doc[key], kind):
            raise CheckpointError(
                f"corrupt cubature file ({key} must be a JSON {'object' if kind is dict else 'string'}, got "
                f"{type(doc[key]).__name__})",
                where,
            )
    for key, value in doc.get("summary", {}).items():
        if key.endswith("error") and (type(value) not in (int, float) or not value >= 0):
            raise CheckpointError(f"corrupt cubature file (summary {key} must be a number >= 0, got {value!r})", where)


def _check_rule(name: str, count: int, index: Tensor, weights: Tensor, where: str) -> None:
    """Refuse a rule read from a file whose kept elements or weights cannot be a cubature's (:class:`CheckpointError`).

    ``index`` [K] must hold distinct element indices in [0, ``count``) and ``weights`` [K] be >= 0 and finite in
    float32 (the runtime casts them to the scene's dtype; NaN, or 1e300, would make every energy NaN or inf).
    """
    if count < 0 or index.ndim != 1 or index.shape != weights.shape:
        raise CheckpointError(
            f"effect {name!r}: one weight per kept element needed, got indices of shape {list(index.shape)} and "
            f"weights of shape {list(weights.shape)} (element_count {count})",
            where,
        )
    for wrong, rule, values in (
        (
            ~(torch.isfinite(weights.to(torch.float32)) & (weights >= 0)),
            "cubature weights must be finite (in float32) and >= 0",
            weights.tolist(),
        ),
        (
            (index < 0) | (index >= count),
            f"kept element indices must lie in [0, {count}) (its element_count)",
            index.tolist(),
        ),
    ):
        if bool(wrong.any()):
            i = int(torch.nonzero(wrong)[0])
            raise CheckpointError(f"effect {name!r}: {rule}, got {values[i]!r} at position {i}", where)
    values, counts = index.unique(return_counts=True)
    if bool((counts > 1).any()):
        twice = int(values[counts > 1][0])
        raise CheckpointError(f"effect {name!r}: kept element indices must be distinct, got {twice} twice", where)


def build_cubature(
    scene: Scene,
    subspace: nn.Module,
    config: CubatureConfig | None = None,
    *,
    progress: bool = False,
    command: str = "",
) -> Cubature:
    """Fit a cubature of ``scene``'s energy for ``subspace`` (see :mod:`redsim.cubature.fit`)."""
    config = CubatureConfig() if config is None else config
    AffineOutput(subspace)  # refuse a map without an affine output layer before any work
    rules, summary = fit_rules(scene, subspace, config, progress=progress)
    fields = {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(config).items()}
    return Cubature(scene.name, scene.fingerprint(), map_fingerprint(subspace), rules, summary, fields, command)


def load_cubature(path: str | Path, scene: Scene, subspace: nn.Module) -> Cubature:
    """Read the cubature beside ``path`` and check it against ``scene`` and ``subspace``."""
    cub = Cubature.load(path)
    cub.check(scene, subspace, str(cubature_path(path)))
    return cub


def cubature_energy(
    scene: Scene,
    subspace: nn.Module,
    source: str | Path | None = None,
    *,
    dtype: torch.dtype = torch.float32,
    device: str | torch.device = "cpu",
) -> CubatureEnergy:
    """The :class:`CubatureEnergy` stored beside ``source`` (a checkpoint or cubature path).

    ``source`` None means the cubature shipped in :mod:`redsim.pretrained` for ``scene.name``, which is
    refused (:class:`CheckpointError`) unless ``subspace`` is the shipped map of that scene.
    """
    if source is None:
        from redsim import pretrained

        try:
            rules = load_cubature(pretrained.FOLDER / scene.name, scene, subspace)
        except CheckpointError as err:  # rebuilding it beside a user's own map would not help: name the way
            raise CheckpointError(
                f"{err} (with no source, cubature_energy reads the cubature shipped for {scene.name!r}; for a map of "
                "your own give its checkpoint: energy=functools.partial(cubature_energy, source='DIR/STEM.pt'))"
            ) from err
    else:
        rules = load_cubature(source, scene, subspace)
    return CubatureEnergy(scene, subspace, rules, dtype=dtype, device=device)


class CubatureEnergy:
    """The latent energy of a cubature (module doc): a :class:`redsim.runtime.LatentEnergy` with reduced inertia.

    Args:
        scene: The scene.
        subspace: The map the cubature was built for (copied).
        cubature: The rules (checked against scene and map).
        dtype: Floating dtype of every evaluation.
        device: Where the evaluations run.
        slice_all: True: the path before stop 36 (docs/cubature.md), kept for comparisons: every DOF a kept or
            whole effect reads through the sliced output layer, whole effects by their own ``energy`` on x with
            the slice scattered in. False (default): a whole single-frame contact (the cloth against its ball) is
            evaluated by its near points only (every point's position without gradients for
            :meth:`SDFContact.near_points`, then a graph only through the rows of W the near points read), an effect
            with ``edge_dim`` (the cloth's, 2D neo-Hookean) reads its elements' edges from the edge layer (since stop
            53), and a whole effect that is its element sum reads the slice directly. Equal to round-off.

    Attributes:
        output_weight: W [n, w] of q = r W^T + b.
        output_bias: b [n].
        kept_dofs: The full DOFs the kept elements read with gradients, [s], int64 (s does not grow with n; a
            near-point contact's points are not among them).
        slice_dofs: Those of them read through the slice x_S (the others' elements read edges), [s'], int64.
        edge_weight: W_E [K, w] of the edge layer (:func:`_edge_layer`); edge_bias: b_E [K].
        screened_dofs: The full DOFs of near-point contacts' points and frames, read without gradients, [c].

    Raises:
        CheckpointError: the cubature belongs to another scene or map.
        ValueError: a map without an affine output layer, or a device redsim cannot run on.
    """

    def __init__(
        self,
        scene: Scene,
        subspace: nn.Module,
        cubature: Cubature,
        *,
        dtype: torch.dtype = torch.float32,
        device: str | torch.device = "cpu",
        slice_all: bool = False,
    ) -> None:
        device = check_device(device)
        cubature.check(scene, subspace)
        self.cubature = cubature
        self.slice_all = bool(slice_all)
        self.latent_dim = int(subspace.latent_dim)
        self.condition_dim = map_condition_dim(subspace)
        self.periodic = periodic_latents(subspace)
        self.scene = scene.to(device=device, dtype=dtype)
        self.output = AffineOutput(subspace).to(device=device, dtype=dtype)
        self.output_weight = self.output.weight
        self.output_bias = self.output.bias
        self._build(scene, subspace, dtype, torch.device(device))

    def _screened(self, effect: Effect) -> bool:
        """True for a whole single-frame contact evaluated by its near points (not ``slice_all``)."""
        rule = {r.name: r for r in self.cubature.rules}.get(effect.name)
        return (
            not self.slice_all
            and rule is not None
            and rule.mode == "full"
            and isinstance(effect, SDFContact)
            and effect.single_frame
            and effect.point_weights is None
        )

    def _by_edges(self, effect: Effect) -> bool:
        """True for an effect whose elements read only their edges x_j - x_0 (``edge_dim``, ``edge_energies``) and
        whose energy is its (weighted) element sum: evaluated on edges computed straight from r (not ``slice_all``)."""
        return not self.slice_all and effect.edge_dim is not None and type(effect).energy is Effect.energy

    def _terms(self, scene: Scene, output: AffineOutput) -> list[tuple[str, Effect, Any]]:
        """Per effect, (how, effect, data) at the slice x_s: ``"edges"`` (its kept elements, or all of a whole effect,
        on their edges, data (its block of the edge layer, its weights or None: the plain sum)), ``"kept"`` (its kept
        elements reindexed into the slice, data their weights), ``"slice"`` (a whole effect whose energy is its element
        sum, reindexed into the slice), ``"near"`` (a near-point contact reindexed into its own screened DOFs, data
        (W_c [c, w], b_c [c], the points' positions in them [P, D*K])), ``"whole"`` (its own ``energy`` on x with the
        slice scattered in)."""
        rules = {r.name: r for r in self.cubature.rules}
        out: list[tuple[str, Effect, Any]] = []
        for effect in scene.effects:
            rule = rules.get(effect.name)
            if rule is None or rule.mode == "linear":
                continue
            if self._by_edges(effect):
                block = len([how for how, _, _ in out if how == "edges"])
                if rule.mode == "full":
                    out.append(("edges", effect, (block, None)))
                else:
                    weights = rule.weights.to(device=scene.device, dtype=scene.dtype)
                    out.append(("edges", effect.subset(rule.indices.to(scene.device)), (block, weights)))
            elif self._screened(effect):
                local = _reindexed_contact(effect, self.screened_dofs)  # type: ignore[arg-type]
                weight, bias = sliced_layer(output, scene, self.screened_dofs)
                out.append(("near", local, _NearContact.build(local, weight, bias)))
            elif rule.mode == "full" and not self.slice_all and type(effect).energy is Effect.energy:
                out.append(("slice", effect.reindexed(torch.searchsorted(self.slice_dofs, effect.element_dofs)), None))
            elif rule.mode == "full":
                out.append(("whole", effect, None))
            else:
                kept = effect.subset(rule.indices.to(scene.device))
                local = kept.reindexed(torch.searchsorted(self.slice_dofs, kept.element_dofs))
                out.append(("kept", local, rule.weights.to(device=scene.device, dtype=scene.dtype)))
        return out

    def _build(self, scene: Scene, subspace: nn.Module, dtype: torch.dtype, device: torch.device) -> None:
        rules = {r.name: r for r in self.cubature.rules}
        sampled = [e for e in self.scene.effects if e.name in rules and rules[e.name].mode != "linear"]
        none = torch.zeros(0, dtype=torch.int64, device=device)
        dofs = {
            e.name: e.element_dofs.index_select(0, rules[e.name].indices.to(device)).reshape(-1)
            for e in sampled
            if not self._screened(e)
        }
        self.kept_dofs = torch.unique(torch.cat(list(dofs.values()))).to(device) if dofs else none
        sliced = [dofs[e.name] for e in sampled if e.name in dofs and not self._by_edges(e)]
        self.slice_dofs = torch.unique(torch.cat(sliced)).to(device) if sliced else none
        screened = [e.element_dofs.reshape(-1) for e in sampled if self._screened(e)]
        self.screened_dofs = torch.unique(torch.cat(screened)).to(device) if screened else none
        self.slice_weight, self.slice_bias = sliced_layer(self.output, self.scene, self.slice_dofs)
        self.slice_weight = column_major(self.slice_weight)
        self.terms = self._terms(self.scene, self.output)
        self._full_values = self.scene.dof_map.full_values
        output64 = AffineOutput(subspace).to(device=device, dtype=torch.float64)
        scene64 = scene.to(device=device, dtype=torch.float64)
        # the edge layer: every edge entry of the edge terms' elements, differences of rows taken in float64
        self.edge_weight, self.edge_bias = _edge_layer(output64, scene64, _edged(self.terms))
        self.edge_weight, self.edge_bias = column_major(self.edge_weight.to(dtype)), self.edge_bias.to(dtype)
        # linear effects: E = r . c + e0 exactly (c, e0 by one backward through the float64 output layer)
        w = output64.feature_dim
        r0 = torch.zeros(1, w, dtype=torch.float64, device=device, requires_grad=True)
        linear = 0.0
        with torch.enable_grad():
            x0 = scene64.full_positions(r0 @ output64.weight.T + output64.bias)
            for effect in scene64.effects:
                if effect.name in rules and rules[effect.name].mode == "linear":
                    linear = linear + effect.energy(x0, self._cond64(scene64, device))
            if isinstance(linear, Tensor):
                (coef,) = torch.autograd.grad(linear.sum(), r0)
            else:
                coef = torch.zeros(1, w, dtype=torch.float64, device=device)
        self.linear_coef = coef[0].to(dtype)
        self.linear_constant = float(linear.detach()) if isinstance(linear, Tensor) else 0.0
        # offset: E_cub = the all-element energy at z = 0
        z0 = torch.zeros(1, self.latent_dim, dtype=torch.float64, device=device)
        cond0 = self._cond64(scene64, device)
        with torch.no_grad():
            q0 = output64(z0, cond0 if self.condition_dim else None)
            full = sum(e.energy(scene64.full_positions(q0), cond0) for e in scene64.effects if e.name in rules)
            approx = self._energy64(output64, scene64, z0, cond0)
        self.offset = float(full) - float(approx)

    def _cond64(self, scene64: Scene, device: torch.device) -> Tensor | None:
        space = scene64.condition_space
        return None if space is None else space.default.to(device=device, dtype=torch.float64)[None]

    def _energy64(self, output64: AffineOutput, scene64: Scene, z: Tensor, cond: Tensor | None) -> Tensor:
        """The cubature energy in float64 (for the offset), without the offset."""
        r = output64.features(z, cond if self.condition_dim else None)
        w_s, b_s = sliced_layer(output64, scene64, self.slice_dofs)
        terms = self._terms(scene64, output64)
        w_e, b_e = _edge_layer(output64, scene64, _edged(terms))
        total = r @ self.linear_coef.to(torch.float64) + self.linear_constant
        return self._sum(total, r, (w_s, b_s), (w_e, b_e), cond, terms, scene64.dof_map.full_values)

    # -- the LatentEnergy protocol ------------------------------------------------------------
    def features(self, z: Tensor, cond: Tensor | None) -> Tensor:
        """r(z[, c]) [B, w], the map's last features (q = r W^T + b)."""
        return self.output.features(z, cond if self.condition_dim else None)

    def energy_features(self, z: Tensor, cond: Tensor | None) -> tuple[Tensor, Tensor]:
        """E_cub [B] [J] of latents z [B, d] and the features r [B, w] it computed."""
        r = self.features(z, cond)
        total = r @ self.linear_coef + (self.linear_constant + self.offset)
        layers = (self.slice_weight, self.slice_bias), (self.edge_weight, self.edge_bias)
        return self._sum(total, r, *layers, cond, self.terms, self._full_values), r

    def _sum(
        self,
        total: Tensor,
        r: Tensor,
        slice_layer: tuple[Tensor, Tensor],
        edge_layer: tuple[Tensor, Tensor],
        cond: Tensor | None,
        terms: list[tuple[str, Effect, Any]],
        full_values: Tensor,
    ) -> Tensor:
        """total + every term (:meth:`_terms`) at the features r [B, w], with the slice layer (W_S [s, w], b_S [s])
        and the edge layer (:func:`_edge_layer`).

        Edge terms read their edges, r W_E^T + b_E (one product for all of them). Kept elements and whole element
        sums read the slice x_S = r W_S^T + b_S directly (their ``element_dofs`` index it). A near-point contact
        screens its points at r without gradients and differentiates only the near ones, each as its rows of W times
        r. Any other whole effect is evaluated by its own ``energy`` on x with the slice scattered in (every DOF it
        reads is in it; the others hold the pinned/seed values). A layer no term reads is not evaluated.
        """
        x_s = torch.addmm(slice_layer[1], r, slice_layer[0].T) if slice_layer[0].shape[0] else None
        blocks = None
        x_full = None
        for how, effect, data in terms:
            if how == "edges":
                if blocks is None:
                    edges = torch.addmm(edge_layer[1], r, edge_layer[0].T)
                    sizes = [(e.element_dofs.shape[1] - int(e.edge_dim)) * e.element_count for e in _edged(terms)]
                    blocks = edges.split(sizes, 1)
                block, weights = data
                width = effect.element_dofs.shape[1] - int(effect.edge_dim)  # type: ignore[arg-type]
                entries = blocks[block].view(r.shape[0], width, effect.element_count).unbind(1)
                energies = effect.edge_energies(entries, cond)
                total = total + (energies.sum(-1) if weights is None else energies @ weights)
            elif how == "kept":
                total = total + effect.element_energies(x_s, cond) @ data
            elif how == "slice":
                total = total + effect.element_energies(x_s, cond).sum(-1)
            elif how == "near":
                total = total + data.energy(effect, r)
            else:
                if x_full is None:
                    x_full = full_values.to(r.dtype).expand(r.shape[0], -1).index_copy(1, self.slice_dofs, x_s)
                total = total + effect.energy(x_full, cond)
        return total

    def energy(self, z: Tensor, cond: Tensor | None) -> tuple[Tensor, None]:
        """E_cub [B] [J] (q is not computed: only the kept DOFs are)."""
        return self.energy_features(z, cond)[0], None

    def positions(self, z: Tensor, cond: Tensor | None) -> Tensor:
        """All of q = f(z[, c]) [B, n] (for drawing and the stepper's constants; not used per iteration)."""
        return self.output(z, cond if self.condition_dim else None)

    def describe(self) -> dict[str, Any]:
        """Kept elements per effect, the DOFs they read (all; those read through the slice), edge entries, n, w."""
        return {
            "kept_elements": {r.name: int(r.indices.numel()) for r in self.cubature.rules},
            "kept_dofs": int(self.kept_dofs.numel()),
            "slice_dofs": int(self.slice_dofs.numel()),
            "edge_entries": int(self.edge_weight.shape[0]),
            "screened_dofs": int(self.screened_dofs.numel()),
            "free_dofs": int(self.output_weight.shape[0]),
            "features": int(self.output_weight.shape[1]),
        }


def _edged(terms: list[tuple[str, Effect, Any]]) -> list[Effect]:
    """The effects of a cubature's edge terms (:meth:`CubatureEnergy._terms`), in order."""
    return [effect for how, effect, _ in terms if how == "edges"]


def _edge_layer(output: AffineOutput, scene: Scene, effects: list[Effect]) -> tuple[Tensor, Tensor]:
    """W_E [K, w] and b_E [K] with r W_E^T + b_E every edge entry x_j - x_0 of ``effects``' elements (each
    ``element_dofs`` [T, D k]: k vertices' D = ``edge_dim`` coordinates), effect by effect, each block ordered (edge,
    coordinate, element): its [B, D (k - 1) T] part viewed as [B, D (k - 1), T] gives the entries as [B, T] rows
    (:func:`redsim.effects.base.edge_vectors`' order). A pinned vertex's rows are zero and its bias its pinned value
    (:func:`sliced_layer`). The row differences are taken in ``output``'s dtype (float64: an edge's entries without
    the cancellation of subtracting two float32 positions)."""
    weights, biases = [], []
    for effect in effects:
        count, width = effect.element_dofs.shape
        dim = int(effect.edge_dim)  # type: ignore[arg-type]
        weight, bias = sliced_layer(output, scene, effect.element_dofs.reshape(-1))
        weight = weight.view(count, width // dim, dim, weight.shape[-1])  # (no -1: a rule may keep no element)
        bias = bias.view(count, width // dim, dim)
        weights.append((weight[:, 1:] - weight[:, :1]).permute(1, 2, 0, 3).reshape(-1, weight.shape[-1]))
        biases.append((bias[:, 1:] - bias[:, :1]).permute(1, 2, 0).reshape(-1))
    if not weights:
        return output.weight.new_zeros(0, output.feature_dim), output.bias.new_zeros(0)
    return torch.cat(weights), torch.cat(biases)


def _reindexed_contact(effect: SDFContact, dofs: Tensor) -> SDFContact:
    """A copy of single-frame contact ``effect`` whose points and frame read x at their positions in ``dofs`` [c]
    (sorted full DOFs holding every entry it reads), its pair tables rebuilt."""
    points = PointSet(torch.searchsorted(dofs, effect.points.dofs), effect.points.weights, effect.points.offset)
    frames = FrameSet(torch.searchsorted(dofs, effect.frames.dofs), effect.frames.weights, effect.frames.offset)
    return SDFContact(effect.name, points, frames, effect.shape, effect.stiffness, margin=effect.margin)


@dataclass
class _NearContact:
    """The output rows a near-point contact reads (reindexed into its screened DOFs, :func:`_reindexed_contact`).

    Attributes:
        weight: W_c [c, w], the rows of the screened DOFs.
        bias: b_c [c].
        points: Each point's entries in them, [P, 3].
        frame_weight: The frame's 12 rows [12, w] (raw entries, before the frame's weights and offset).
        frame_bias: [12].
        offset_weight: Rows [3 P, w] of p - t (point minus frame origin), coordinate-major: affine in r.
        offset_bias: [3 P].
    """

    weight: Tensor
    bias: Tensor
    points: Tensor
    frame_weight: Tensor
    frame_bias: Tensor
    offset_weight: Tensor
    offset_bias: Tensor

    @staticmethod
    def build(effect: SDFContact, weight: Tensor, bias: Tensor) -> _NearContact:
        points = effect.points.dofs[..., 0]  # [P, 3] (plain points: K = 1, weights 1, no offset)
        frame = effect.pair_frame_index[:12]
        origin = frame[3::4]  # t_k = x[frame[4k + 3]] * fw[4k + 3] + fo[4k + 3]
        scale = effect.pair_frame_weights[0, 3::4].to(weight.dtype)
        shift = effect.pair_frame_offset[0, 3::4].to(weight.dtype)
        coords = points.T.reshape(-1)  # coordinate-major [3 P]
        count = points.shape[0]
        offset_weight = weight.index_select(0, coords).view(3, count, -1) - (scale[:, None] * weight[origin])[:, None]
        offset_bias = bias.index_select(0, coords).view(3, count) - (scale * bias[origin] + shift)[:, None]
        return _NearContact(
            weight,
            bias,
            points,
            weight.index_select(0, frame),
            bias.index_select(0, frame),
            column_major(offset_weight.reshape(3 * count, -1)),
            offset_bias.reshape(-1).contiguous(),
        )

    def energy(self, effect: SDFContact, r: Tensor) -> Tensor:
        """The energy [B] of near-point contact ``effect`` at features r [B, w].

        Screen: every point's p - t = r W_o^T + b_o without gradients, against
        :meth:`SDFContact.screen_radius_sq`. With gradients only the frame's 12 entries and the near points'
        own entries, each the dot product of its rows of W_c with its state's r. Under ``torch.compile``, every
        point through W_c and the contact's dense ``energy``.
        """
        if torch.compiler.is_compiling():  # no data-dependent shapes: every point, by the contact's dense path
            return effect.energy(torch.addmm(self.bias, r, self.weight.T))
        frame = torch.addmm(self.frame_bias, r, self.frame_weight.T)  # [B, 12]
        with torch.no_grad():
            frames = (frame * effect.pair_frame_weights[0] + effect.pair_frame_offset[0]).view(-1, 3, 4)
            offsets = torch.addmm(self.offset_bias, r, self.offset_weight.T).view(r.shape[0], 3, -1)
            rows, cols = (offsets.square().sum(1) < effect.screen_radius_sq(frames)[:, None]).nonzero().unbind(1)
        dofs = self.points.index_select(0, cols).reshape(-1)  # [A * 3]
        rows_w = self.weight.index_select(0, dofs).view(cols.shape[0], 3, r.shape[1])  # [A, 3, w]
        entries = torch.bmm(rows_w, r.index_select(0, rows).unsqueeze(-1)).squeeze(-1)
        entries = entries + self.bias.index_select(0, dofs).view(-1, 3)
        return effect.near_point_energy(rows, cols, entries, frame)


__all__ = [
    "FORMAT_VERSION",
    "SUFFIX",
    "Cubature",
    "CubatureEnergy",
    "build_cubature",
    "cubature_energy",
    "cubature_path",
    "load_cubature",
    "map_fingerprint",
]
