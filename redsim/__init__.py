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
del _pathlib, _CHECKOUT, _PROJECT

# redsim.envs registers the Gymnasium ids ("RedSim/Chain-v0", ...) with string entry points, and redsim.fork_safety
# makes a process forked from this one run torch on one thread (OpenMP's pool does not survive fork). Neither
# imports torch: the names below are loaded on first use (PEP 562), so ``import redsim`` and ``redsim --help``
# stay quick.
import importlib as _importlib

from redsim import envs, fork_safety
from redsim.version import __version__

_LAZY = {
    "ConditionSpace": "redsim.scene",
    "Handle": "redsim.scene",
    "PointSet": "redsim.points",
    "Scene": "redsim.scene",
    "SceneBuilder": "redsim.scene",
    "SubspaceConfig": "redsim.subspace",
    "SubspaceMap": "redsim.subspace",
    "Surface": "redsim.scene",
    "effects": None,
    "load_subspace": "redsim.subspace",
    "scenes": None,
}
"""Public name -> the module that defines it (None: the name is a subpackage of redsim, as every other submodule
is reached too)."""


def __getattr__(name: str) -> object:
    """Import a public name, or any submodule (``redsim.meshes``), on first use (the engine loads torch)."""
    owner = _LAZY.get(name)
    if owner is None and (name.startswith("_") or _importlib_util.find_spec(f"redsim.{name}") is None):
        raise AttributeError(f"module 'redsim' has no attribute {name!r}")
    module = _importlib.import_module(f"redsim.{name}" if owner is None else owner)
    value = module if owner is None else getattr(module, name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})


__all__ = [*sorted(_LAZY), "__version__", "envs", "fork_safety"]
