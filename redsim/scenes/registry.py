"""One entry per named scene: its builder and what the rest of redsim needs to know about it.

The CLI's scene names, the benches' default scene lists, the scenes the environments run on
(and so ship a subspace) and scene-specific bench knowledge (a crank's pivot, reference
states) all come from these entries; nothing else keeps a list of scene names. Fit presets
stay in :mod:`redsim.trainers.presets`, keyed by these names (the engine does not import
the trainers).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

from torch import Tensor

from redsim.scene import Scene

TAGS: dict[str, str] = {
    "table1": "one of the eleven systems of the paper's Table 1 (`redsim bench subspace` runs them)",
    "env": "a Gymnasium environment runs on it, so a fitted subspace ships in redsim/pretrained",
    "bench-fit": "`redsim bench fit` times its fitting steps by default",
    "toy": "a tiny scene for fast tests (redsim.scenes.testing)",
}
"""The tags a scene entry may carry, with what each means."""


class Crank(NamedTuple):
    """A handle that turns about a fixed pivot as the mechanism's one DOF goes round.

    Attributes:
        handle: Handle name (a single point).
        pivot: The fixed (x, y) [m] it turns about, in the plane of motion z = const.
    """

    handle: str
    pivot: tuple[float, float]


@dataclass(frozen=True)
class SceneEntry:
    """A named scene.

    Attributes:
        name: Catalog name (the scene's ``Scene.name``).
        builder: Keyword-only builder; every argument has a default.
        tags: A subset of :data:`TAGS`.
        crank: For a mechanism driven round by a crank (klann): the crank's handle and pivot,
            used for the loop check (:func:`redsim.metrics.handle_winding`).
        reference_states: ``"module:function"`` of a function ``(scene) -> list[Tensor [n]]``
            of states any good subspace of this scene should contain (the bistable bar's two
            buckled equilibria). A string, imported only when called, because computing the
            states needs the solver stack, which sits above the scenes.
        full_space_tol: Relative gradient tolerance a float64 full-space Newton step of this scene reaches (the
            reference of the accuracy bench, the full-space column of ``bench envs``): 1e-8, or looser where
            Newton stalls above it (the cloths: near 3e-5 of their forces).
    """

    name: str
    builder: Callable[..., Scene]
    tags: tuple[str, ...] = ()
    crank: Crank | None = None
    reference_states: str | None = None
    full_space_tol: float = 1e-8

    def __post_init__(self) -> None:
        unknown = sorted(set(self.tags) - set(TAGS))
        if unknown:
            raise ValueError(f"scene {self.name!r}: unknown tag(s) {unknown}; valid tags: {list(TAGS)}")
        if self.reference_states is not None and ":" not in self.reference_states:
            raise ValueError(f"scene {self.name!r}: reference_states must be 'module:function'")

    def compute_reference_states(self, scene: Scene) -> list[Tensor] | None:
        """The declared reference states of ``scene`` (each [n]), or None where none are declared."""
        if self.reference_states is None:
            return None
        return resolve(self.reference_states)(scene)


def resolve(target: str) -> Callable[..., Any]:
    """The callable named by ``"module:attribute"``.

    Raises:
        ValueError: the module or attribute does not exist, or is not callable.
    """
    module_name, _, attribute = target.partition(":")
    try:
        found = getattr(importlib.import_module(module_name), attribute)
    except (ImportError, AttributeError) as err:
        raise ValueError(f"cannot resolve {target!r}: {err}") from err
    if not callable(found):
        raise ValueError(f"{target!r} is not callable")
    return found
