"""Benchmarks that sit on top of the engine and the runtime (``redsim bench accuracy | scaling``).

- :mod:`~redsim.benches.accuracy`: trajectory error against a converged full-space reference
  versus per-step wall time, per configuration (full space loosened, subspaces, solver options).
- :mod:`~redsim.benches.scaling`: how fitting, the forward pass and latent and full-space steps
  grow with the mesh (supplement B.3).
"""

from __future__ import annotations
