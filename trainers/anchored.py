"""The anchored-map fit option (``FitConfig.anchor_map``, not in the paper): build the map the fit trains.

Prop. 1 of the paper says the loss's small-sigma limit is linear modes, which hold the small linear
responses to loads; at the sigma a scene needs for its large motions the paper's MLP misses them (issue
12: response errors near 1). Pulling the MLP towards modes or modal derivatives by a penalty did not hold
them (docs/fitting.md, "Small responses"): Adam does not keep a quadratic map's small stiff part, which an MLP can
only express with large, finely cancelling output weights. Here the polynomial map is a fixed part of
:class:`redsim.subspace.AnchoredSubspace` and the MLP enters only through its Taylor remainder at z = 0, so
nothing has to hold it: near z = 0 the map is the polynomial map exactly (to second order for "md", to
first order for "modes"), and the paper's loss trains the MLP's higher-order terms to lower the energy
of the larger samples. It needs no simulation data: the rest state, modes and modal derivatives come from
the energy alone (static equilibrium, Hessian and its directional derivatives).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from redsim.baselines import modal_analysis, modal_derivatives
from redsim.integrators.reference import rest_or_warn
from redsim.scene import Scene
from redsim.subspace import AnchoredSubspace, QuadraticSubspace, SubspaceConfig

if TYPE_CHECKING:
    from redsim.trainers.fit import FitConfig

ANCHOR_MAPS = ("none", "md", "modes")
"""Values of ``FitConfig.anchor_map``: the paper's MLP, modal derivatives (order 2), linear modes (order 1)."""

ANCHOR_MAP_CONDS = ("default", "each")
"""Values of ``FitConfig.anchor_map_cond``: where a conditional map's Taylor polynomial is taken."""

WEIGHT_SCALE = 1e-2
"""The MLP's output weights start scaled by this, so the map starts as the polynomial map (as the modal pull's
flat start, :func:`redsim.trainers.modal.start_at_rest`)."""


def anchor_polynomial(scene: Scene, latent_dim: int, sigma: float, kind: str) -> QuadraticSubspace:
    """The fixed part of an anchored map, float64, at the default condition's rest state
    (:func:`redsim.integrators.reference.rest_state`, the load errors' reference, cached).

    "md": :func:`redsim.baselines.modal_derivatives` of this sigma; "modes": :func:`redsim.baselines.modal_analysis`
    as a quadratic map with Q = 0.
    """
    rest = rest_or_warn(scene, f"the anchored map's {kind!r} polynomial")
    if kind == "md":
        return modal_derivatives(scene, latent_dim, sigma=sigma, rest=rest)
    if kind == "modes":
        linear = modal_analysis(scene, latent_dim, sigma=sigma, rest=rest)
        quadratic = torch.zeros(linear.basis.shape[0], latent_dim * (latent_dim + 1) // 2, dtype=linear.basis.dtype)
        return QuadraticSubspace(linear.basis, linear.offset, quadratic, linear.metadata)
    raise ValueError(f"anchor map must be one of {ANCHOR_MAPS[1:]}, got {kind!r}")


def anchored_map(scene: Scene, arch: SubspaceConfig, config: FitConfig) -> AnchoredSubspace:
    """The untrained anchored map of ``config.anchor_map`` for ``scene`` (float64; the fit casts it).

    Its MLP is initialised from the global torch seed (as a :class:`redsim.subspace.SubspaceMap`), its output
    weights scaled by WEIGHT_SCALE.
    """
    polynomial = anchor_polynomial(scene, arch.latent_dim, config.sigma, config.anchor_map)
    anchor_cond = None
    if config.conditional and config.anchor_map_cond == "default":
        anchor_cond = scene.pack_condition(None, 1)[0].to(torch.float64)
    order = 2 if config.anchor_map == "md" else 1
    model = AnchoredSubspace(arch, polynomial, order, anchor_cond, config.anchor_radius)
    with torch.no_grad():
        model.output_weight.mul_(WEIGHT_SCALE)
    return model
