"""Subspace maps f(z[, c]) -> q and their checkpoints.

A :class:`SubspaceMap` is an ordinary ELU MLP from latent coordinates z [..., d] (and an
optional condition c [..., m]) to free configurations q [..., n] of one scene. The seeded
exploration schedule of the paper lives in the fitter (:mod:`redsim.trainers.fit`), never
here. A saved subspace is ``STEM.pt`` (state dict) plus ``STEM.json`` (config, scene
fingerprint, hyperparameters, metrics and the command that reproduces it); nothing is
pickled.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from redsim.scene import Scene

FORMAT_VERSION = 1
ACTIVATIONS = {"elu": nn.ELU, "tanh": nn.Tanh, "relu": nn.ReLU, "silu": nn.SiLU}


def periodic_latents(subspace: Any) -> tuple[int, ...]:
    """Indices of a map's latents that are angles (``subspace.config.periodic``; () for other maps)."""
    return tuple(getattr(getattr(subspace, "config", None), "periodic", ()))


def sample_latents(
    count: int,
    latent_dim: int,
    periodic: tuple[int, ...] = (),
    *,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> Tensor:
    """Latent samples [count, d]: z ~ N(0, 1) per entry, angles (``periodic``) uniform in [-pi, pi).

    Angles are uniform so that every point of the loop they parameterize is sampled alike (a
    normal angle would leave the far side of the circle, near +-pi, almost unseen).
    """
    z = torch.randn(count, latent_dim, generator=generator, dtype=dtype, device=device)
    if periodic:
        angles = torch.rand(count, len(periodic), generator=generator, dtype=dtype, device=device)
        z[:, list(periodic)] = (2.0 * angles - 1.0) * math.pi
    return z


@dataclass(frozen=True)
class SubspaceConfig:
    """Architecture of a subspace map; every count means what it says.

    Attributes:
        latent_dim: d, the size of z.
        output_dim: n, the scene's free DOF count.
        condition_dim: m, the size of the condition vector (0 for none).
        hidden_width: Units per hidden layer.
        hidden_layers: Number of hidden layers (the output layer is not counted).
        activation: One of ``ACTIVATIONS``.
        periodic: Latent indices entered as (cos z_i, sin z_i), so that z_i is an angle
            (e.g. a crank that turns all the way round).
    """

    latent_dim: int
    output_dim: int
    condition_dim: int = 0
    hidden_width: int = 128
    hidden_layers: int = 5
    activation: str = "elu"
    periodic: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.latent_dim < 1 or self.output_dim < 1 or self.condition_dim < 0:
            raise ValueError(
                f"bad dimensions: latent {self.latent_dim}, output {self.output_dim}, condition {self.condition_dim}"
            )
        if self.hidden_width < 1 or self.hidden_layers < 1:
            raise ValueError(
                f"need hidden_width >= 1 and hidden_layers >= 1, got {self.hidden_width}, {self.hidden_layers}"
            )
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"unknown activation {self.activation!r}; valid: {sorted(ACTIVATIONS)}")
        if any(not 0 <= i < self.latent_dim for i in self.periodic) or len(set(self.periodic)) != len(self.periodic):
            raise ValueError(f"periodic indices {self.periodic} must be distinct and in [0, {self.latent_dim})")


class SubspaceMap(nn.Module):
    """ELU MLP f(z[, c]) -> q.

    Attributes:
        config: The architecture.
        metadata: Scene fingerprint, hyperparameters, metrics and reproduce command (JSON-able).
    """

    def __init__(self, config: SubspaceConfig, metadata: dict[str, Any] | None = None) -> None:
        super().__init__()
        self.config = config
        self.metadata: dict[str, Any] = dict(metadata or {})
        act = ACTIVATIONS[config.activation]
        width = config.hidden_width
        layers: list[nn.Module] = [
            nn.Linear(config.latent_dim + len(config.periodic) + config.condition_dim, width),
            act(),
        ]
        for _ in range(config.hidden_layers - 1):
            layers += [nn.Linear(width, width), act()]
        layers.append(nn.Linear(width, config.output_dim))
        self.mlp = nn.Sequential(*layers)
        periodic = torch.zeros(config.latent_dim, dtype=torch.bool)
        periodic[list(config.periodic)] = True
        self.register_buffer("periodic_mask", periodic, persistent=False)

    @property
    def latent_dim(self) -> int:
        return self.config.latent_dim

    def features(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """MLP input: z with periodic entries replaced by (cos, sin), then c."""
        if z.shape[-1] != self.config.latent_dim:
            raise ValueError(f"z must have {self.config.latent_dim} entries in its last dim, got {tuple(z.shape)}")
        parts = [z]
        if self.config.periodic:
            angles = z[..., self.periodic_mask]
            parts = [torch.where(self.periodic_mask, torch.cos(z), z), torch.sin(angles)]
        if self.config.condition_dim:
            if cond is None or cond.shape[-1] != self.config.condition_dim:
                raise ValueError(f"this subspace needs a condition of size {self.config.condition_dim}")
            parts.append(cond.expand(*z.shape[:-1], -1))
        elif cond is not None:
            raise ValueError("this subspace takes no condition")
        return torch.cat(parts, dim=-1)

    def forward(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """Configurations q [..., n] from latents z [..., d] (and conditions c [..., m])."""
        return self.mlp(self.features(z, cond))

    def save(self, stem: str | Path) -> tuple[Path, Path]:
        """Write ``stem.pt`` (weights) and ``stem.json`` (config and metadata); returns both paths."""
        return write_checkpoint(self, stem, dataclasses.asdict(self.config))


def checkpoint_path(path: str | Path, suffix: str) -> Path:
    """``STEM + suffix`` for a checkpoint given as ``STEM``, ``STEM.pt`` or ``STEM.json``.

    Suffixes are appended, never swapped, so stems with dots ("bar_sigma0.3") stay whole.
    """
    path = Path(path)
    stem = path.with_suffix("") if path.suffix in (".pt", ".json") else path
    return stem.with_name(stem.name + suffix)


def write_checkpoint(module: nn.Module, stem: str | Path, config: dict[str, Any]) -> tuple[Path, Path]:
    """Write ``stem.pt`` (the module's state dict) and ``stem.json`` (format version, ``config`` and the
    module's ``metadata``); returns both paths. Shared by every kind of subspace."""
    weights, meta = checkpoint_path(stem, ".pt"), checkpoint_path(stem, ".json")
    weights.parent.mkdir(parents=True, exist_ok=True)
    torch.save(module.state_dict(), weights)
    doc = {**getattr(module, "metadata", {}), "format_version": FORMAT_VERSION, "config": config}
    meta.write_text(json.dumps(doc, indent=2, sort_keys=True, default=_json_default))
    return weights, meta


def _json_default(value: Any) -> Any:
    if isinstance(value, Tensor):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON-serializable: {type(value).__name__}")


class CheckpointError(ValueError):
    """A checkpoint that is missing, corrupt, or made for another scene."""

    def __init__(self, message: str, path: str = "") -> None:
        super().__init__(f"{path}: {message}" if path else message)
        self.path = path


def read_metadata(path: str | Path) -> dict[str, Any]:
    """The JSON beside a checkpoint (``X.pt`` or ``X.json`` or the stem ``X``)."""
    meta = checkpoint_path(path, ".json")
    if not meta.is_file():
        raise CheckpointError("no metadata file (expected a .json beside the .pt)", str(meta))
    try:
        doc = json.loads(meta.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise CheckpointError(f"metadata is not valid JSON ({err})", str(meta)) from None
    if doc.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(
            f"unsupported format_version {doc.get('format_version')!r} (this redsim reads {FORMAT_VERSION})",
            str(meta),
        )
    return doc


def check_scene(doc: dict[str, Any], scene: Scene, path: str) -> None:
    """Refuse a checkpoint whose metadata ``doc`` names another scene (name, fingerprint or n)."""
    mine = (doc.get("scene"), doc.get("scene_fingerprint"), (doc.get("config") or {}).get("output_dim"))
    theirs = (scene.name, scene.fingerprint(), scene.free_dof_count)
    if mine != theirs:
        raise CheckpointError(
            f"fitted to scene {mine[0]!r} (fingerprint {mine[1]}, n={mine[2]}), not to scene {theirs[0]!r} "
            f"(fingerprint {theirs[1]}, n={theirs[2]}); build the scene with the parameters in the .json",
            path,
        )


def load_subspace(path: str | Path, scene: Scene | None = None, *, device: str | torch.device = "cpu") -> nn.Module:
    """Load any saved subspace: a neural map, or a baseline of :mod:`redsim.baselines` (by its ``kind``).

    Args:
        path: ``STEM.pt``, ``STEM.json`` or ``STEM``.
        scene: With it, refuse a checkpoint made for another scene.
        device: Where to put the weights.

    Raises:
        CheckpointError: missing or corrupt files, an unknown kind, or a scene whose name,
            fingerprint or n differ.
    """
    weights = checkpoint_path(path, ".pt")
    if not weights.is_file():
        raise CheckpointError("the weights file is missing", str(weights))
    doc = read_metadata(path)
    if scene is not None:
        check_scene(doc, scene, str(weights))
    metadata = {k: v for k, v in doc.items() if k not in ("format_version", "config")}
    kind = doc.get("kind", "neural")
    try:
        if kind == "neural":
            config = SubspaceConfig(**{**doc["config"], "periodic": tuple(doc["config"].get("periodic", ()))})
            model: nn.Module = SubspaceMap(config, metadata)
        else:
            from redsim.baselines import BASELINES

            if kind not in BASELINES:
                raise CheckpointError(
                    f"unknown kind {kind!r}; valid: neural, {', '.join(sorted(BASELINES))}", str(weights)
                )
            model = BASELINES[kind].from_shapes(doc["config"], metadata)
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        if isinstance(err, CheckpointError):
            raise
        raise CheckpointError(f"bad config in metadata ({err!r})", str(weights)) from None
    try:
        state = torch.load(weights, map_location=device, weights_only=True)
    except Exception as err:  # torch raises several types for truncated/corrupt zips
        raise CheckpointError(f"weights are corrupt or truncated ({type(err).__name__}: {err})", str(weights)) from None
    mismatch = _state_mismatch(model.state_dict(), state)
    if mismatch:
        raise CheckpointError(f"the weights do not fit the .json beside them: {mismatch}", str(weights))
    try:
        model.load_state_dict(state)
    except (RuntimeError, KeyError) as err:
        raise CheckpointError(f"weights do not match the config ({err})", str(weights)) from None
    return model.to(device)


def _state_mismatch(expected: dict[str, Tensor], saved: dict[str, Any]) -> str:
    """One line on how a saved state dict differs from the one a config builds ("" when they fit)."""
    missing = sorted(set(expected) - set(saved))
    extra = sorted(set(saved) - set(expected))
    if missing or extra:
        return f"the .pt lacks {missing or 'nothing'} and has extra {extra or 'nothing'}"
    for key, want in expected.items():
        got = saved[key]
        if not isinstance(got, Tensor) or tuple(got.shape) != tuple(want.shape):
            shape = tuple(got.shape) if isinstance(got, Tensor) else type(got).__name__
            return (
                f"{key} has shape {list(shape) if isinstance(shape, tuple) else shape} in the .pt but "
                f"{list(want.shape)} by the .json (weights of another scene or fit?)"
            )
    return ""
