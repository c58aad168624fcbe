"""How good a subspace map is: the measurements behind the paper's comparison figures, by family.

- :mod:`~redsim.metrics.energy`: :func:`energy_stats` (energy of subspace states relative to the
  seed-to-rest drop) and :func:`stretch_stats` (the metric stretch over pairs of samples).
- :mod:`~redsim.metrics.response`: :func:`load_response_error`, subspace against full-space
  equilibria under a seeded set of loads.
- :mod:`~redsim.metrics.reach`: :func:`reach_error` (how close a map comes to given states, such as
  :func:`buckled_states`) and :func:`handle_winding` (does a crank loop close).
- :mod:`~redsim.metrics.strain`: :func:`nonrigid_strain`, the mean Green strain of FEM states.
- :mod:`~redsim.metrics.evaluate`: :func:`evaluate_subspace`, all of them as one JSON dict.
- :mod:`~redsim.metrics.common`: how each of them evaluates a map (module doc there).

No solver code lives here: full-space reference equilibria and their cache are
:mod:`redsim.integrators.reference` and :mod:`redsim.integrators.cache` (:func:`rest_state`,
:func:`clear_cache`, :func:`cache_directory` and ``FULL_TOL`` are re-exported for convenience).
"""

from __future__ import annotations

from redsim.integrators.cache import CACHE_ENV, cache_directory, clear_cache
from redsim.integrators.reference import FULL_TOL, rest_state
from redsim.metrics.common import DISPLACEMENT_FLOOR
from redsim.metrics.energy import RELATIVE_ENERGY_FLOOR, energy_stats, stretch_stats
from redsim.metrics.evaluate import evaluate_subspace
from redsim.metrics.reach import buckled_states, handle_winding, reach_error
from redsim.metrics.response import RESPONSE_FRACTION, load_response_error
from redsim.metrics.strain import nonrigid_strain
from redsim.subspace import pair_log_ratios

__all__ = [
    "CACHE_ENV",
    "DISPLACEMENT_FLOOR",
    "FULL_TOL",
    "RELATIVE_ENERGY_FLOOR",
    "RESPONSE_FRACTION",
    "buckled_states",
    "cache_directory",
    "clear_cache",
    "energy_stats",
    "evaluate_subspace",
    "handle_winding",
    "load_response_error",
    "nonrigid_strain",
    "pair_log_ratios",
    "reach_error",
    "rest_state",
    "stretch_stats",
]
