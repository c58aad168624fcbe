"""The batched latent runtime: implicit-Euler steps in z for B states at once (see :mod:`redsim.runtime.stepper`).

>>> from redsim import pretrained, scenes
>>> from redsim.runtime import LatentStepper
>>> stepper = LatentStepper(scenes.build("mini_chain"), pretrained.load("mini_chain"), dt=0.02)
>>> z = stepper.rest_latent().expand(4, -1)
>>> z_next, stats = stepper.step(z, z)
"""

from __future__ import annotations

from redsim.runtime.energy import LatentEnergy, MapEnergy, ReducedInertia
from redsim.runtime.stepper import Evaluations, LatentStepper, StepStats

__all__ = ["Evaluations", "LatentEnergy", "LatentStepper", "MapEnergy", "ReducedInertia", "StepStats"]
