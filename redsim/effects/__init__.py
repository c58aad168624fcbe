"""Energy terms. A scene's energy is exactly the sum of the effects it declares."""

from redsim.effects.base import Effect
from redsim.effects.elastic import DiscreteShellBending, NeoHookean, StVKMembrane
from redsim.effects.external import ExternalLoad, Gravity
from redsim.effects.penalty import ConditionalPin, FrameSet, PointPairPenalty, SDFContact
from redsim.effects.rigid import RigidOrthogonality
from redsim.effects.sdf import Box, Capsule, Plane, Sphere, Torus

__all__ = [
    "Box",
    "Capsule",
    "ConditionalPin",
    "DiscreteShellBending",
    "Effect",
    "ExternalLoad",
    "FrameSet",
    "Gravity",
    "NeoHookean",
    "Plane",
    "PointPairPenalty",
    "RigidOrthogonality",
    "SDFContact",
    "Sphere",
    "StVKMembrane",
    "Torus",
]
