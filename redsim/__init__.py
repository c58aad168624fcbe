"""redsim: data-free neural reduced-order simulation and control of physical systems.

Scenes are differentiable potential energies built from declared effects
(:mod:`redsim.scenes`, :mod:`redsim.effects`); a full-space implicit-Euler reference
simulator (:mod:`redsim.integrators`) is the ground truth that reduced models are measured
against.
"""

# ruff: noqa: E402  (the source-checkout path below must be set before redsim.envs is imported)
import importlib.util as _importlib_util
import pathlib as _pathlib

_CHECKOUT = _pathlib.Path(__file__).resolve().parent.parent
_PROJECT = _CHECKOUT / "pyproject.toml"
if (
    _importlib_util.find_spec("redsim.envs") is None
    and (_CHECKOUT / "envs" / "__init__.py").is_file()
    and _PROJECT.is_file()
    and 'name = "redsim"' in _PROJECT.read_text()
):
    # imported from a source checkout that is not installed editable (e.g. a Ray worker whose working directory is
    # the clone's root): redsim.envs and redsim.trainers are its top-level envs/ and trainers/ (pyproject's package-dir)
    __path__.append(str(_CHECKOUT))
del _importlib_util, _pathlib, _CHECKOUT, _PROJECT

# redsim.envs registers the Gymnasium ids ("RedSim/Chain-v0", ...) with string entry points: nothing
# heavy is imported and no checkpoint is loaded until an env is made. redsim.fork_safety: a process forked
# from this one runs torch on one thread (OpenMP's pool does not survive fork).
from redsim import effects, envs, fork_safety, scenes
from redsim.points import PointSet
from redsim.scene import ConditionSpace, Handle, Scene, SceneBuilder, Surface
from redsim.subspace import SubspaceConfig, SubspaceMap, load_subspace
from redsim.version import __version__

__all__ = [
    "ConditionSpace",
    "Handle",
    "PointSet",
    "Scene",
    "SceneBuilder",
    "SubspaceConfig",
    "SubspaceMap",
    "Surface",
    "__version__",
    "effects",
    "envs",
    "fork_safety",
    "load_subspace",
    "scenes",
]
