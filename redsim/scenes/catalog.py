"""The scene catalog: the eleven systems of the paper's Table 1, plus a heterogeneous beam.

One keyword-only builder per scene, by family: :mod:`~redsim.scenes.cloth`,
:mod:`~redsim.scenes.solids`, :mod:`~redsim.scenes.chains`, :mod:`~redsim.scenes.linkages`.
Every parameter has a default and SI units (m, kg, s, Pa, N, J). Gravity is 9.81 m/s^2 along
-y wherever a ``gravity`` argument is offered, and ``gravity=False`` omits the "gravity"
effect. Each builder passes all its arguments to ``finalize`` so the scene fingerprint
captures them.

Materials are chosen so that implicit Euler with dt = 0.01..0.05 s behaves: rubber-like
solids (E = 1e5..1e7 Pa, density 1000 kg/m^3), cloth with E = 1e6 Pa and 1 mm thickness,
and rigid bodies of 0.01..5 kg held by joint and contact penalties of 1e4..1e5 N/m.
"""

from __future__ import annotations

from redsim.scenes import chains, cloth, linkages, solids
from redsim.scenes.registry import SceneEntry

CATALOG: tuple[SceneEntry, ...] = (
    SceneEntry("cloth_ball", cloth.cloth_ball, tags=("table1", "env", "bench-fit"), full_space_tol=1e-4),
    SceneEntry("klann", linkages.klann, tags=("table1", "env"), crank=linkages.KLANN_CRANK),
    SceneEntry("stewart", linkages.stewart, tags=("table1", "env")),
    SceneEntry(
        "bistable_bar",
        solids.bistable_bar,
        tags=("table1", "env", "bench-fit"),
        reference_states="redsim.metrics:buckled_states",
    ),
    SceneEntry("hanging_sheet", cloth.hanging_sheet, tags=("table1", "env"), full_space_tol=1e-4),
    SceneEntry("conditional_bar", solids.conditional_bar, tags=("table1", "env")),
    SceneEntry("chain", chains.chain, tags=("table1", "env", "bench-fit")),
    SceneEntry("mini_chain", chains.mini_chain, tags=("table1", "env", "bench-fit")),
    SceneEntry("stiff_body", solids.stiff_body, tags=("table1", "bench-fit")),
    SceneEntry("cantilever", solids.cantilever, tags=("table1",)),
    SceneEntry("elephant", solids.elephant, tags=("table1",)),
    SceneEntry("hetero_beam", solids.hetero_beam),
)
"""The catalog scenes in Table 1 order (hetero_beam, not in Table 1, last); tags as in
:data:`redsim.scenes.registry.TAGS`."""
