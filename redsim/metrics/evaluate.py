"""Every metric of one subspace on its scene, as one JSON-serializable dict."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from torch import Tensor

from redsim.effects.elastic import NeoHookean
from redsim.metrics.common import Subspace, check_count
from redsim.metrics.energy import energy_stats, stretch_stats
from redsim.metrics.response import RESPONSE_FRACTION, load_response_error
from redsim.metrics.strain import nonrigid_strain
from redsim.scene import Scene

logger = logging.getLogger(__name__)


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
    check_count("loads_count", loads_count, 0)
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
