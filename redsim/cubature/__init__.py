"""Cubature: a latent energy whose cost does not grow with the mesh (An, Kim & James 2008).

>>> from redsim import pretrained, scenes
>>> from redsim.cubature import CubatureConfig, CubatureEnergy, build_cubature
>>> scene = scenes.build("mini_chain"); f = pretrained.load("mini_chain")
>>> cub = build_cubature(scene, f, CubatureConfig(elements=8, samples=32, episodes=0))
>>> energy = CubatureEnergy(scene, f, cub)   # LatentStepper(scene, f, energy=energy)

The shipped cubatures (``redsim/pretrained/SCENE.cubature.json``) are chosen with one option:
``LatentStepper(scene, pretrained.load(name), energy=cubature_energy)``.

- :mod:`~redsim.cubature.output`: the map's affine output layer and its slice to the kept DOFs.
- :mod:`~redsim.cubature.fit`: training states from the subspace, per-element reduced forces, greedy + NNLS.
- :mod:`~redsim.cubature.energy`: the stored rules (``STEM.cubature.json``) and :class:`CubatureEnergy`.
"""

from __future__ import annotations

from redsim.cubature.energy import (
    Cubature,
    CubatureEnergy,
    build_cubature,
    cubature_energy,
    cubature_path,
    load_cubature,
    map_fingerprint,
)
from redsim.cubature.fit import CubatureConfig, EffectRule
from redsim.cubature.output import AffineOutput

__all__ = [
    "AffineOutput",
    "Cubature",
    "CubatureConfig",
    "CubatureEnergy",
    "EffectRule",
    "build_cubature",
    "cubature_energy",
    "cubature_path",
    "load_cubature",
    "map_fingerprint",
]
