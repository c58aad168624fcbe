"""The base latent environment: a scene, a subspace map, the latent stepper and a task.

The state of every copy is the latent pair (z_t, z_{t-1}) of the runtime's two-state implicit
Euler; a step turns the action into loads on the scene's handles (the task), advances all
copies with one batched :meth:`redsim.runtime.LatentStepper.step` per substep, and asks the
task for the observation extras, the reward (each term) and the termination. The same batched
core (:class:`LatentSim`) serves the single env (:class:`LatentEnv`, batch 1) and the native
vector env (:class:`redsim.envs.vector.LatentVectorEnv`, batch N), so they share one code path.

Gymnasium's template-method style: seeding, the step loop, ``info``, rendering and state
access live here; a task (:class:`Task`, e.g. :class:`redsim.envs.reach.HandleReach`) holds
what differs: its reset distribution, action -> load map, observation extras, reward and
termination. Observations are ``concat(z, z_dot, task extras[, condition])``, float32, clipped
into finite bounds; actions are float32 in [-1, 1] (values outside are clipped, non-finite
values raise ValueError).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import importlib.util
import inspect
import logging
import math
import numbers
import os
import re
import sys
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.envs.registration import EnvSpec
from gymnasium.vector import AutoresetMode
from torch import Tensor, nn

from redsim.devices import DTYPES, check_device
from redsim.integrators.tunneling import TunnelTest
from redsim.scene import Scene
from redsim.subspace import CheckpointError, map_fingerprint, periodic_latents
from redsim.threads import check_threads, torch_threads
from redsim.usercache import cache_root, read_arrays, write_arrays
from redsim.version import __version__

logger = logging.getLogger(__name__)

if TYPE_CHECKING:  # imported where used: the runtime and the invariants load only when an env is built
    from redsim.envs.invariants import Invariants
    from redsim.runtime import LatentStepper, StepStats

CAMERA_KEYS = ("azimuth", "elevation", "margin", "merge_px", "track")
"""The ``camera`` keys an env takes: ``azimuth``, ``elevation`` [deg], ``margin`` and ``merge_px`` (keyword arguments
of :class:`redsim.raster.SceneView`; ``merge_px=0`` draws every triangle of a small picture), and ``track`` (bool,
default False: the fixed camera of :meth:`LatentSim.fixed_view`; True: each episode framed anew,
:meth:`LatentSim.view`)."""
FRAME_SAMPLES = 64
"""Fixed draws (seed 0) of a task's targets whose shapes bound the region a fixed camera frames
(:meth:`Task.frame_points`)."""
LOOP_SAMPLES = 64
"""Shapes round the loop of each periodic latent that a fixed camera frames (:meth:`LatentSim.frame_points`)."""

LATENT_BOUND = 10.0
"""Observation bound of each latent coordinate (maps are fitted on z ~ N(0, I)); z_dot gets 2 LATENT_BOUND / h, h the
stepper's step (the env's dt / frame_skip)."""
MAX_FRAME_SKIP = 1000
"""Most stepper steps one env step may take (``frame_skip``): each is an implicit solve, so a larger value makes a
single ``step()`` run for minutes or, mistyped (``10**12``), forever; for a longer env step raise ``dt`` instead."""
MAX_IMAGE_SIDE = 4096
"""Largest rendered width or height [px]: a 4096 x 4096 RGB frame is 48 MiB (and a vector env draws one per copy), so a
larger one is refused when the env is made, not found out as a memory error at the first render."""
LATENT_ENV_ARGUMENTS = (
    '| `dtype` | "float32" | stepper dtype, "float32" or "float64" |',
    '| `device` | "cpu" | torch device |',
    "| `randomize_condition` | False | draw the scene's condition per episode (a conditional map only) |",
    f"| `width`, `height` | 480 | render size [px], 8 to {MAX_IMAGE_SIDE} (`MAX_IMAGE_SIDE`) |",
    "| `camera` | None | `azimuth`, `elevation`, `margin`, `merge_px`, `track` over the env's own camera |",
    "| `stepper_options` | None | :class:`redsim.runtime.LatentStepper` options over the env's `stepper_defaults` |",
    '| `cubature` | None | None: the shipped one where it meets the bar; True: required; False: none; "lean": the '
    "shipped lean one; a path |",
    "| `threads` | 1 | torch intra-op threads while the env computes (None: the caller's setting) |",
)
"""Arguments-table rows of the :class:`LatentEnv` arguments a registered env passes on through ``**kwargs``: a
subclass's docstring row :data:`LATENT_ENV_ROW` is replaced by them (``LatentEnv.__init_subclass__``)."""
LATENT_ENV_ROW = "| `**kwargs` | | the other :class:`LatentEnv` arguments (`LATENT_ENV_ARGUMENTS`) |"
"""Where an env's docstring table takes :data:`LATENT_ENV_ARGUMENTS` (less the rows of those its own table lists)."""


def row_arguments(line: str) -> list[str]:
    """The argument names in the first cell of an Arguments-table row (``| `width`, `height` | ...``), else []."""
    cells = line.strip().split("|")
    if len(cells) < 3 or cells[0] or "`" not in cells[1] or cells[1].strip() == "`**kwargs`":
        return []
    return cells[1].replace(" ", "").replace("`", "").split(",")


ACTION_RESOLUTION_WARNING = 0.05
"""An env whose steps cannot feel actions below this fraction of their range (:attr:`LatentSim.action_resolution`)
warns at its first reset (docs/runtime.md, "Tolerance")."""
USE_RGB_ARRAY = "use render_mode='rgb_array'"
"""What a refused ``render_mode="human"`` advises instead."""
DISPLAY_VARIABLES = ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER")
"""On Linux a window needs one of these set (SDL_VIDEODRIVER=dummy gives a window that shows nothing)."""


def human_unavailable() -> str | None:
    """Why ``render_mode="human"`` cannot open a window on this machine, or None where it can.

    It needs pygame (the ``render`` extra) and, on Linux, a display (:data:`DISPLAY_VARIABLES`).
    """
    if importlib.util.find_spec("pygame") is None:
        return 'pygame is not installed; run `pip install "redsim[render]"` (or `pip install pygame`)'
    if sys.platform.startswith("linux") and not any(os.environ.get(k) for k in DISPLAY_VARIABLES):
        return f"there is no display ({', '.join(DISPLAY_VARIABLES)} are unset); {USE_RGB_ARRAY}"
    return None


HEADLESS_DRIVERS = ("offscreen", "dummy")
"""SDL video drivers that draw into no window: pygame falls back to "offscreen" where ``DISPLAY`` names no reachable
display (a stale variable, a container without the X socket), so a window there is refused unless
``SDL_VIDEODRIVER`` asks for that driver."""


def open_display() -> None:
    """Start pygame's display for ``render_mode="human"``.

    Raises:
        ValueError: pygame opened no display (a driver that ``SDL_VIDEODRIVER`` asks for is not available), or fell
            back to a :data:`HEADLESS_DRIVERS` driver nobody asked for: the window would show nothing.
    """
    import pygame  # present: human_unavailable() was checked first

    try:
        pygame.display.init()
    except pygame.error as err:
        reason = f"pygame opened no display ({err}); {USE_RGB_ARRAY}"
        raise ValueError(f'render_mode="human" needs a window: {reason}') from err
    driver = pygame.display.get_driver()
    if driver in HEADLESS_DRIVERS and driver not in os.environ.get("SDL_VIDEODRIVER", "").lower().split(","):
        pygame.display.quit()
        found = ", ".join(f"{k}={os.environ[k]!r}" for k in DISPLAY_VARIABLES if os.environ.get(k)) or "no display"
        raise ValueError(
            f'render_mode="human" needs a window: pygame reached no display ({found}) and fell back to its {driver!r} '
            f"driver, which shows nothing; {USE_RGB_ARRAY} (or SDL_VIDEODRIVER={driver} to run the window unseen)"
        )


RENDER_MODES = ["rgb_array", "human"]
"""Headless "rgb_array" everywhere; "human", a pygame window, where :func:`human_unavailable` is None.

The class's ``metadata`` declares both, so ``gym.make(..., render_mode="human")`` reaches the env and
its clear error where no window can open (Gymnasium would otherwise wrap the env in its own
HumanRendering); an instance's ``metadata`` lists "human" only where pygame and a display variable exist, so
``check_env`` renders every mode it lists headless (a display variable that names no reachable display is found
by :func:`open_display` when a "human" env is made, not probed for every env)."""

VECTOR_RENDER_MODES = ["rgb_array"]
"""The vector envs (native and sharded) draw one RGB frame per copy; "human", a window, is a single env's."""
NO_HUMAN = (
    'render_mode="human" is a single env\'s window; a vector env draws render_mode="rgb_array" frames (one per '
    "copy, venv.render()), which gymnasium.wrappers.vector.HumanRendering (it needs opencv-python) shows in a window"
)
"""Why a vector env refuses ``render_mode="human"`` (it would draw nothing)."""
NO_RENDER_MODE = "render() called without a render_mode; make the env with render_mode='rgb_array'"
"""The warning of a ``render()`` that draws nothing (single and vector envs, as Gymnasium's and SB3's envs warn)."""


def _unimplemented(task: Task, method: str) -> NotImplementedError:
    """The error of a :class:`Task` method that a task of the user's does not implement, naming it."""
    return NotImplementedError(
        f"{type(task).__name__}.{method} is not implemented: a Task implements action_size, extras_bounds, "
        "observation_structure, loads, extras and reward (controller for scripted actions)"
    )


class Task:
    """What an environment asks of its scene; every method is batched over B copies.

    Per-copy task parameters (a target, ...) are a dict of tensors [B, ...] drawn by
    :meth:`sample` from each copy's own generator, so copy i of a vector env and a single env
    seeded alike draw the same episode. They keep their dtypes through ``get_state``/``set_state`` and
    pickling (a bool flag or an integer counter stays one), and :meth:`loads` may update them in place
    (per-episode state, e.g. a clock).

    A task of your own (``redsim.envs.make(scene, subspace, task=MyTask())``) implements ``action_size``,
    :meth:`extras_bounds` (finite), :meth:`observation_structure` (block sizes adding up to the extras'),
    :meth:`loads`, :meth:`extras` and :meth:`reward`; the others have defaults. ``x`` is the full configuration
    [B, N]; a handle's position is ``sim.scene.handle(name).position(x)`` [B, D]; keep ``sim`` from :meth:`bind`
    for anything else (``sim.x_prev``, ``sim.dt``). Every step checks what the task returns: ``reward`` and each
    reward term (named as ``reward_terms``, summing to the reward) are tensors [B], finite where floating; each
    metric a tensor [B] (it may be NaN where it has no value); ``terminated`` a bool tensor [B]; ``loads`` a
    tensor [B, H, D]; ``extras`` (at every observation, resets too) a tensor [B, k], k = ``len(extras_bounds()[0])``,
    finite; ``start`` a finite latent [d]; ``frame_points`` finite points [P, D]; a ValueError names the method
    otherwise. A vector env and an unpickled env work on a copy of the task object (:meth:`bind` runs again for
    it). :meth:`loads` runs only in steps (the first reset's probe of the action scale works on a copy of the
    parameters).

    Attributes:
        name: Task name (used by :func:`redsim.envs.make`).
        action_size: A, the size of the action vector.
        reward_terms: Names of the reward terms; ``info["reward_<term>"]`` holds each.
        reset_options: Names of the parameters of :meth:`sample` that ``reset(options={name: value})`` sets
            for the episode instead of drawing them (same shape as drawn; integer and bool ones integral).
    """

    name: ClassVar[str] = "task"
    action_size: int
    reward_terms: tuple[str, ...] = ()
    reset_options: tuple[str, ...] = ()

    def bind(self, sim: LatentSim) -> None:
        """Check the task against ``sim.scene`` and precompute what it needs (called once)."""

    def extras_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Finite (low, high) bounds of the observation extras, each shape [k]."""
        raise _unimplemented(self, "extras_bounds")

    def observation_structure(self) -> dict[str, int]:
        """Name -> size of each block of the extras, in order."""
        raise _unimplemented(self, "observation_structure")

    def sample(
        self, rng: np.random.Generator, sim: LatentSim, z_rest: Tensor, cond: Tensor | None
    ) -> dict[str, Tensor]:
        """Parameters of one new episode (each shape [...], no batch dim) drawn from ``rng``."""
        return {}

    def check_options(self, chosen: Mapping[str, Tensor]) -> None:
        """Raise ValueError for ``reset`` option values (named in :attr:`reset_options`) the task cannot start from."""

    def start(self, sim: LatentSim, row: int, z_rest: Tensor) -> Tensor:
        """The latent [d] copy ``row`` starts its episode from, after :meth:`sample` (default: at rest, z_rest)."""
        return z_rest

    def loads(self, action: Tensor, params: Mapping[str, Tensor]) -> Tensor:
        """Loads [B, H, D] [N] from actions [B, A] in [-1, 1]."""
        raise _unimplemented(self, "loads")

    def extras(self, x: Tensor, x_prev: Tensor, params: Mapping[str, Tensor]) -> Tensor:
        """Observation extras [B, k] from full configurations x [B, N] (and the previous ones)."""
        raise _unimplemented(self, "extras")

    def reward(self, x: Tensor, action: Tensor, params: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]]:
        """Reward [B] and its terms {name: [B]} (they sum to the reward). Also called by ``set_state`` on the restored
        x with zero actions and copies of the params, to refuse a state whose reward is not finite."""
        raise _unimplemented(self, "reward")

    def terminated(self, x: Tensor, params: Mapping[str, Tensor]) -> Tensor:
        """Task termination [B] (bool); divergence ends an episode on its own."""
        return torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)

    def metrics(self, x: Tensor, params: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """Extra [B] values for ``info`` (e.g. ``distance``, ``is_success``)."""
        return {}

    def controller(self, sim: LatentSim) -> np.ndarray:
        """A scripted action [B, A] for the current states (demos and the did-it-reach tests)."""
        raise _unimplemented(self, "controller")

    def overlay(self, sim: LatentSim, row: int) -> tuple[list[Any], list[Any]]:
        """(markers, arrows) of :mod:`redsim.raster` to draw on copy ``row``."""
        return [], []

    def frame_points(self, sim: LatentSim) -> np.ndarray | None:
        """Points [P, D] [m] the env's fixed camera must hold besides the reset shapes (:meth:`LatentSim.frame_points`):
        the region targets or goals are drawn from (the corners of a sampling box, or shapes of fixed draws) and the
        handles' reachable extent; None (default): nothing more. Called once per env, at its first render."""
        return None


PROCESS_CACHE_SIZE = 8
"""Entries each per-process cache of settled work keeps (:func:`cached`), the oldest dropped first."""
SETTLED_CACHE_VERSION = 1
"""Part of every disk key of :func:`cached` (with redsim's version): bump it when code changes what a cached
computation returns for the same key (a task's settling or frame solves, the rest solve, the stepper's defaults)."""

_rest_cache: dict[tuple[Any, ...], Tensor] = {}
"""Rest latents solved in this process, by what they depend on (:meth:`LatentSim._settled_rest`): an identical env
made again reuses them (ClothBall-v1's solve takes ~0.6 s); a later process reads them from the user cache."""

Settled = Tensor | np.ndarray | tuple[Tensor | np.ndarray, ...]
"""What :func:`cached` keeps on disk: a tensor, an array, or a tuple of them."""


def cached(
    cache: dict[Any, Any],
    key: Any,
    compute: Callable[[], Any],
    disk: str | None = None,
    check: Callable[[Any], str] | None = None,
) -> Any:
    """``cache[key]``, computed once by ``compute()`` (work an identical env made again in this process reuses: its
    rest latent, a task's settled targets or frame), keeping the :data:`PROCESS_CACHE_SIZE` newest entries.

    With ``disk`` (a name for what it holds), also kept across processes in ``cache_root()/envs`` (one ``.npz`` per
    key, named by ``disk`` and the key's hash, e.g. ``rest-latent-<sha256>.npz``, written atomically; off with
    ``REDSIM_CACHE=0``, :func:`redsim.usercache.cache_root`): a later process, a vector env's worker, reads it back
    bit for bit instead of solving again. ``compute()`` must then return a
    :data:`Settled` value, and ``key`` name by value everything it depends on (its repr is hashed with redsim's and
    torch's versions and :data:`SETTLED_CACHE_VERSION`). A damaged or foreign file, or a value read back that
    ``check`` refuses (it returns what is wrong with it, "" when nothing), is warned about and computed again; delete
    ``cache_root()/envs`` to forget them all.
    """
    if key not in cache:
        root = None if disk is None else cache_root()
        path = None
        if root is not None:
            text = repr((__version__, torch.__version__, SETTLED_CACHE_VERSION, disk, key))
            kind = re.sub(r"[^a-z0-9]+", "-", disk.lower()).strip("-")
            path = root / "envs" / f"{kind}-{hashlib.sha256(text.encode()).hexdigest()}.npz"
        value = None if path is None else _read_settled(path, text, disk, check)
        if value is None:
            value = compute()
            if path is not None:
                write_arrays(path, text, _settled_arrays(value), disk)
        cache[key] = value
        while len(cache) > PROCESS_CACHE_SIZE:
            cache.pop(next(iter(cache)))
    return cache[key]


def map_key(subspace: nn.Module) -> tuple[str, str, str, str]:
    """What a map computes, for the keys of :func:`cached`: its class, its configuration (activation, periodic
    latents, sizes: not in its weights), a hash of its weights exactly as they are (dtype included: the checkpoint's
    :func:`redsim.subspace.map_fingerprint` reads them as float32, so a float64 copy shares it, but its solves differ)
    and its modules' plain settings (an anchored map's order and radius)."""
    weights = hashlib.sha256()
    for name, value in sorted(subspace.state_dict().items()):
        weights.update(f"{name}:{value.dtype}:{tuple(value.shape)}:".encode())
        weights.update(value.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    settings = [
        (name, key, value)
        for name, module in subspace.named_modules()
        for key, value in sorted(vars(module).items())
        if not key.startswith("_") and isinstance(value, (bool, int, float, str))
    ]
    return type(subspace).__name__, repr(getattr(subspace, "config", None)), weights.hexdigest(), repr(settings)


def _settled_arrays(value: Settled) -> dict[str, np.ndarray]:
    """The arrays of a :data:`Settled` value, each tensor's device beside it (a single value: ``single``)."""
    items = value if isinstance(value, tuple) else (value,)
    arrays: dict[str, np.ndarray] = {"single": np.array(not isinstance(value, tuple))}
    for i, item in enumerate(items):
        tensor = isinstance(item, Tensor)
        arrays[f"item{i}"] = item.detach().cpu().numpy() if tensor else np.asarray(item)
        arrays[f"device{i}"] = np.array(str(item.device) if tensor else "")
    return arrays


def _read_settled(path: Path, key: str, what: str, check: Callable[[Any], str] | None = None) -> Settled | None:
    """The :data:`Settled` value stored at ``path`` for ``key``, or None (no file, or an unusable one: warned)."""
    arrays = read_arrays(path, key, what)
    if arrays is None:
        return None
    try:
        items: list[Tensor | np.ndarray] = []
        for i in range(sum(name.startswith("item") for name in arrays)):
            device = str(arrays[f"device{i}"])
            items.append(torch.from_numpy(arrays[f"item{i}"]).to(device) if device else arrays[f"item{i}"])
        value = items[0] if bool(arrays["single"]) else tuple(items)
        wrong = "" if check is None else check(value)
        if wrong:
            raise ValueError(wrong)
        return value
    except Exception as error:  # fields missing or unusable: compute again
        logger.warning("ignoring unusable %s cache file %s (%s); computing again", what, path, error)
        return None


def check_subspace(scene: Scene, subspace: nn.Module) -> None:
    """Refuse a map fitted to another scene (by its metadata) or with the wrong output size.

    Raises:
        CheckpointError: the map's metadata names another scene or fingerprint.
        ValueError: the map has no ``latent_dim`` or does not map to q [n].
    """
    meta = getattr(subspace, "metadata", None) or {}
    fitted = (meta.get("scene"), meta.get("scene_fingerprint"))
    if fitted[1] is not None and (fitted[0] != scene.name or not scene.accepts(fitted[1])):
        raise CheckpointError(
            f"the subspace was fitted to scene {fitted[0]!r} (fingerprint {fitted[1]}), not to scene "
            f"{scene.name!r} (fingerprint {scene.fingerprint()}); build the scene with the parameters it was fitted to"
        )
    d = getattr(subspace, "latent_dim", None)
    if not isinstance(d, int) or d < 1:
        raise ValueError(f"the subspace must have an integer latent_dim >= 1, got {d!r}")
    out = getattr(getattr(subspace, "config", None), "output_dim", None)
    if out is not None and out != scene.free_dof_count:
        raise ValueError(f"the subspace maps to {out} DOFs; scene {scene.name!r} has n = {scene.free_dof_count}")


CUBATURE_DEFAULT: dict[str, bool] = {"cloth_ball": True, "hanging_sheet": False}
"""Catalog scenes whose shipped cubature (``redsim/pretrained/SCENE.cubature.json``) an env uses by default:
those that meet the accuracy bar (held-out force error and 100-step trajectory deviation <= 5%,
``redsim bench cubature``, README "Cubature"). hanging_sheet's deviation is 9.3% from the envs' rest, so it stays
off. The others step every element unless ``cubature=True``."""


SHIPPED_CUBATURES = ("lean",)
"""Names ``cubature`` takes for another cubature shipped beside a scene's shipped map
(``redsim/pretrained/SCENE.NAME.cubature.json``): a name, unlike a path, holds on every machine, so the registered
ids that step one (ClothBall-v1, HangingCloth-v2) have specs and pickles that another install can make."""


CHECKPOINT_ATTRIBUTE = "redsim_checkpoint"
"""Attribute :func:`shipped` sets on a map it loads from a path: that path, where ``cubature=True`` looks."""


def _on_device(module: nn.Module, device: torch.device) -> bool:
    """Whether every parameter and buffer of ``module`` is on ``device`` (``cuda`` means the current index)."""
    wanted = torch.device(device.type, torch.cuda.current_device()) if device == torch.device("cuda") else device
    tensors = [*module.parameters(), *module.buffers()]
    return all(t.device == wanted or t.device == device for t in tensors)


def env_energy(
    scene: Scene,
    subspace: nn.Module,
    cubature: bool | str | os.PathLike[str] | None,
    *,
    dtype: torch.dtype,
    device: str | torch.device,
) -> Any:
    """The latent energy an env steps: a :class:`redsim.cubature.CubatureEnergy`, or None (every element).

    Args:
        scene: The scene.
        subspace: Its map.
        cubature: None: the shipped cubature of the scene where :data:`CUBATURE_DEFAULT` turns it on and it
            belongs to this very map, else every element. True: the cubature beside the checkpoint the map was
            loaded from (:func:`shipped`), else the shipped one; either must belong to this map. False: every
            element. A name of :data:`SHIPPED_CUBATURES` ("lean"): that cubature shipped beside the scene's shipped
            map, which must be this map. A path: the cubature beside that checkpoint (or the ``.cubature.json``
            itself).
        dtype: The stepper's dtype.
        device: The stepper's device.

    Raises:
        redsim.subspace.CheckpointError: a cubature was asked for and none exists for this scene and map.
        ValueError: ``cubature`` of another type.
    """
    from redsim import pretrained
    from redsim.cubature import CubatureEnergy, cubature_path, load_cubature
    from redsim.cubature.energy import SUFFIX

    if cubature is False:
        return None
    if cubature is True and getattr(subspace, CHECKPOINT_ATTRIBUTE, None) is not None:
        cubature = getattr(subspace, CHECKPOINT_ATTRIBUTE)
    if cubature is None or cubature is True:
        source = pretrained.FOLDER / scene.name
        if cubature is None:
            if not CUBATURE_DEFAULT.get(scene.name, False) or not cubature_path(source).is_file():
                return None
            try:
                cub = load_cubature(source, scene, subspace)
            except CheckpointError:  # another map or scene parameters: the shipped cubature is not this map's
                return None
            return CubatureEnergy(scene, subspace, cub, dtype=dtype, device=device)
        if not cubature_path(source).is_file():
            raise CheckpointError(
                f"no cubature is shipped for scene {scene.name!r}; make one for your map with "
                "`redsim cubature CHECKPOINT --elements K` (a hand-built scene: redsim.cubature.build_cubature(scene, "
                "map).save(STEM)) and pass cubature=CHECKPOINT"
            )
    elif isinstance(cubature, str) and cubature in SHIPPED_CUBATURES:
        source = pretrained.FOLDER / f"{scene.name}.{cubature}{SUFFIX}"
        if not source.is_file():
            shipped = sorted(path.name for path in pretrained.FOLDER.glob(f"{scene.name}*{SUFFIX}"))
            instead = (
                f"shipped for it: {', '.join(shipped)} (cubature=True takes {scene.name}{SUFFIX})"
                if shipped
                else "make one with `redsim cubature CHECKPOINT --elements K` and pass cubature=CHECKPOINT"
            )
            raise CheckpointError(f"no {cubature!r} cubature is shipped for scene {scene.name!r}; {instead}")
    elif isinstance(cubature, (str, os.PathLike)):
        source = cubature
    else:
        raise ValueError(
            f"cubature must be None, True, False, a shipped name {list(SHIPPED_CUBATURES)} or a checkpoint path, "
            f"got {cubature!r}"
        )
    return CubatureEnergy(scene, subspace, load_cubature(source, scene, subspace), dtype=dtype, device=device)


class LatentSim:
    """B copies of one scene in latent space: the batched core of the single and vector envs.

    Args:
        scene: The scene (any dtype; a copy in ``dtype`` is used for positions and invariants).
        subspace: Its map f(z[, c]) -> q.
        task: The task (bound to this sim here).
        batch: B, the number of copies.
        dt: Stepper time step [s].
        frame_skip: Stepper steps per env step, in [1, :data:`MAX_FRAME_SKIP`] (the env's dt is ``dt * frame_skip``).
        dtype: "float32" or "float64", the stepper's dtype.
        device: Torch device of the stepper.
        randomize_condition: Draw the condition c uniformly from the scene's condition space per
            episode (a conditional map is needed) and append it to the observation.
        include_q: Put the full free configuration q [n] in ``info["q"]`` (steps and resets, :meth:`state_info`).
        reset_noise_scale: s >= 0: each episode starts at the task's start z0 + U(-s, s) with z_dot s N(0, 1)
            [latent units, per s], per latent, from the copy's generator (MuJoCo's convention; 0: exactly z0 at rest);
            periodic latents then move by whole turns into [-pi, pi), z_prev with them, as after a step; x_prev (the
            configuration one env step before, which a task's velocity extras read) is that of z - frame_skip (z -
            z_prev), the start's velocity held one env step back.
        stepper_options: Extra keyword arguments of :class:`redsim.runtime.LatentStepper`.
        cubature: Step a cubature energy instead of every element (:func:`env_energy`): None (default)
            the shipped one where :data:`CUBATURE_DEFAULT` turns it on, True, False, "lean" (the lean one shipped
            beside the shipped map: :data:`SHIPPED_CUBATURES`) or a checkpoint path.

    Raises:
        ValueError: a bad number or option, or both ``cubature`` and ``stepper_options["energy"]``.
        redsim.subspace.CheckpointError: another scene's map, or a cubature asked for that does not exist.
    """

    # declared for type checkers (set in __init__): the state [B, d] and what users read
    source_scene: Scene
    scene: Scene  # the copy in the stepper's dtype and device
    subspace: nn.Module
    task: Task
    if TYPE_CHECKING:  # annotations typing.get_type_hints could not resolve at run time
        stepper: LatentStepper
        invariants: Invariants
    torch_dtype: torch.dtype
    device: torch.device
    batch: int
    frame_skip: int
    dt: float  # the env's step [s]: the stepper's dt times frame_skip
    latent_dim: int
    periodic: list[int]
    cubature: bool
    conditional: bool
    randomize_condition: bool
    include_q: bool
    reset_noise_scale: float
    z: Tensor
    z_prev: Tensor
    x: Tensor
    x_prev: Tensor
    loads: Tensor
    model: Tensor
    carry: Tensor

    def __init__(
        self,
        scene: Scene,
        subspace: nn.Module,
        task: Task,
        *,
        batch: int = 1,
        dt: float = 0.02,
        frame_skip: int = 1,
        dtype: str = "float32",
        device: str = "cpu",
        randomize_condition: bool = False,
        include_q: bool = False,
        reset_noise_scale: float = 0.0,
        stepper_options: Mapping[str, Any] | None = None,
        cubature: bool | str | os.PathLike[str] | None = None,
    ) -> None:
        from redsim.cubature import CubatureEnergy
        from redsim.envs.invariants import Invariants
        from redsim.runtime import LatentStepper

        if int(batch) != batch or batch < 1:
            raise ValueError(f"batch must be an integer >= 1, got {batch!r}")
        from redsim.integrators import check_time_step

        dt = check_time_step(dt)
        if (
            isinstance(frame_skip, bool)
            or not isinstance(frame_skip, numbers.Integral)
            or not 1 <= frame_skip <= MAX_FRAME_SKIP
        ):
            raise ValueError(
                f"frame_skip must be an integer in [1, {MAX_FRAME_SKIP}] (MAX_FRAME_SKIP; for longer env steps raise "
                f"dt), got {frame_skip!r}"
            )
        for flag, value in (("include_q", include_q), ("randomize_condition", randomize_condition)):
            if not isinstance(value, (bool, np.bool_)):
                raise ValueError(f"{flag} must be True or False, got {value!r}")
        noise = reset_noise_scale
        if isinstance(noise, bool) or not isinstance(noise, numbers.Real) or not 0.0 <= noise < math.inf:
            raise ValueError(f"reset_noise_scale must be a finite number >= 0 [latent units], got {noise!r}")
        dtype = _dtype_name(dtype)
        device = check_device(device)
        check_subspace(scene, subspace)
        conditional = int(getattr(getattr(subspace, "config", None), "condition_dim", 0)) > 0
        if randomize_condition and not (conditional and scene.condition_space is not None):
            raise ValueError("randomize_condition needs a scene with a condition space and a conditional subspace")
        self.options = {
            "dt": float(dt),
            "frame_skip": int(frame_skip),
            "dtype": dtype,
            "device": device,
            "randomize_condition": bool(randomize_condition),
            "include_q": bool(include_q),
            "reset_noise_scale": float(reset_noise_scale),
            "stepper_options": dict(stepper_options or {}),
            "cubature": cubature,
        }
        self.source_scene = scene
        self.torch_dtype = DTYPES[dtype]
        self.device = torch.device(device)
        self.scene = scene.to(self.device, self.torch_dtype)
        self.tunnel_test = TunnelTest(self.scene)
        # nn.Module.to moves a module in place: the caller's map stays where it is
        self.subspace = subspace if _on_device(subspace, self.device) else copy.deepcopy(subspace).to(self.device)
        self.batch = int(batch)
        self.frame_skip = int(frame_skip)
        self.randomize_condition = bool(randomize_condition)
        self.conditional = conditional
        self.include_q = bool(include_q)
        self.reset_noise_scale = float(reset_noise_scale)
        if stepper_options is not None and not isinstance(stepper_options, Mapping):
            raise ValueError(f"stepper_options must be a dict, got {stepper_options!r:.80}")
        options = dict(stepper_options or {})
        valid = set(inspect.signature(LatentStepper).parameters) - {"scene", "subspace", "dt", "dtype", "device"}
        if set(options) - valid:
            raise ValueError(f"unknown stepper_options {sorted(set(options) - valid)}; valid: {sorted(valid)}")
        if "energy" in options and cubature:
            raise ValueError("give either cubature or stepper_options['energy'], not both")
        if "energy" not in options:
            options["energy"] = env_energy(scene, self.subspace, cubature, dtype=self.torch_dtype, device=self.device)
        self.stepper = LatentStepper(scene, self.subspace, dt, dtype=self.torch_dtype, device=self.device, **options)
        self.cubature = isinstance(self.stepper.energy, CubatureEnergy)
        """Whether the stepper evaluates a cubature energy (else every element)."""
        self.latent_dim = int(self.stepper.latent_dim)
        self.periodic = list(periodic_latents(subspace))
        self.dt = float(dt) * self.frame_skip
        self.invariants = Invariants(self.scene)
        self.task = task
        space = scene.condition_space
        self._cond_low = None if space is None else space.low.to(self.device, self.torch_dtype)
        self._cond_high = None if space is None else space.high.to(self.device, self.torch_dtype)
        self.default_cond = self.scene.pack_condition(None, 1, self.scene.q_seed) if conditional else None
        self._default_rest = self._settled_rest()
        """[d] the rest latent under the default condition (the only one where it is not drawn per episode)."""
        self._rest: Tensor | None = None if self.randomize_condition else self._default_rest
        d, B = self.latent_dim, self.batch
        zeros = torch.zeros(B, d, dtype=self.torch_dtype, device=self.device)
        self.z, self.z_prev = zeros.clone(), zeros.clone()
        self.z_before = zeros.clone()
        """[B, d] z at the start of the last env step (frame_skip stepper steps before z; z_prev's with 1): x_prev's."""
        self.cond: Tensor | None = None if not conditional else self.default_cond.expand(B, -1).clone()
        self.params: dict[str, Tensor] = {}
        self.action_resolution: np.ndarray | None = None
        """[A] after the first reset: :meth:`_action_resolution` (actions below this fraction go unfelt)."""
        self.loads = torch.zeros(B, len(scene.handles), scene.dim, dtype=self.torch_dtype, device=self.device)
        # the solver's d x d model of each copy, carried from step to step (NaN: build one)
        self.model = torch.full((B, d, d), torch.nan, dtype=self.torch_dtype, device=self.device)
        # E and dE/dz at z of each copy, from its last step (the stepper's carry; NaN: evaluate them)
        self.carry = torch.full((B, self.stepper.carry_size), torch.nan, dtype=self.torch_dtype, device=self.device)
        self._frame_points: np.ndarray | None = None  # the fixed camera's frame, at the first render (frame_points)
        task.bind(self)
        self.x = self.x_prev = self.full_positions(self.z)

    def clone(self, batch: int, task: Task | None = None) -> LatentSim:
        """A new sim of ``batch`` copies with this scene, map and settings (and ``task``, default this one)."""
        return LatentSim(
            self.source_scene, self.subspace, self.task if task is None else task, batch=batch, **self.options
        )

    # -- configurations -------------------------------------------------------------------
    def _settled_rest(self) -> Tensor:
        """The rest latent [d] under the default condition (:meth:`_settled_rests`)."""
        return self._settled_rests([self.default_cond])[0]

    def _settled_rests(self, conds: Sequence[Tensor | None]) -> tuple[Tensor, ...]:
        """The rest latents [d] under ``conds`` (:meth:`_rest_latent`), solved once per process for each scene
        content, map, dtype, device, shipped start (:func:`redsim.pretrained.rest_start`) and conditions and kept on
        disk for the next process (:func:`cached`); solved every time for a map that is not a module (its weights are
        not known by value)."""

        def solve() -> tuple[Tensor, ...]:
            return tuple(self._rest_latent(cond) for cond in conds)

        if not isinstance(self.subspace, nn.Module):
            return solve()
        from redsim import pretrained
        from redsim.integrators.cache import scene_digest

        d = self.latent_dim
        start = pretrained.rest_start(self.source_scene.name, map_fingerprint(self.subspace))  # a shipped map's
        where = None if start is None else tuple(start.tolist())
        values = tuple(None if cond is None else tuple(cond.flatten().tolist()) for cond in conds)
        key = (scene_digest(self.source_scene), map_key(self.subspace), str(self.torch_dtype), str(self.device))
        key += (where, values)

        def check(value: Any) -> str:
            shapes = [(tuple(v.shape), v.dtype) if isinstance(v, Tensor) else type(v) for v in value]
            ok = isinstance(value, tuple) and shapes == [((d,), self.torch_dtype)] * len(conds)
            return "" if ok else f"not {len(conds)} {self.torch_dtype} tensors of shape ({d},): {shapes}"

        rests = cached(_rest_cache, key, solve, disk="rest latent", check=check)
        return tuple(rest.to(self.device).clone() for rest in rests)

    def _rest_latent(self, cond: Tensor | None) -> Tensor:
        """The rest latent [d] under ``cond`` (None: the scene has none; :meth:`LatentStepper.rest_latent`: from the
        shipped map's rest start where it has one, else from z = 0); under ``default_cond`` itself the one solved at
        construction."""
        if cond is self.default_cond and getattr(self, "_default_rest", None) is not None:
            return self._default_rest.clone()
        return self.stepper.rest_latent(cond).reshape(-1, self.latent_dim)[0].detach().clone()

    def positions(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """Free configurations q [B, n] of latents z [B, d] (the copies' conditions by default)."""
        return self.stepper.positions(z, cond if cond is not None or not self.conditional else self.cond)

    def full_positions(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """Full configurations x [B, N] of latents z [B, d]."""
        return self.scene.full_positions(self.positions(z, cond).to(self.torch_dtype))

    # -- episodes -------------------------------------------------------------------------
    def episode_options(self, options: Mapping[str, Any] | None, vector: bool = False) -> dict[str, Tensor]:
        """What ``reset(options=...)`` sets for the new episodes, checked before anything is reset.

        Accepted keys: the task's :attr:`Task.reset_options`, ``"condition"`` (values [m] inside the condition
        space) where the condition is drawn per episode, and ``"reset_mask"`` for a vector env (its own).

        Raises:
            ValueError: another key, a value that is not a finite number array (of the parameter's shape), one the
                task refuses (:meth:`Task.check_options`), or a condition outside its space.
        """
        if options is not None and not isinstance(options, Mapping):
            raise ValueError(f"options must be a dict (or None), got {options!r:.80}")
        accepted = (*self.task.reset_options, *(("condition",) if self.randomize_condition else ()))
        chosen = {k: v for k, v in (options or {}).items() if not (vector and k == "reset_mask")}
        unknown = sorted(set(chosen) - set(accepted))
        if unknown:
            allowed = ", ".join(repr(k) for k in (*accepted, *(("reset_mask",) if vector else ()))) or "none"
            raise ValueError(f"unknown reset option(s) {unknown}; this env accepts {allowed}")
        try:
            return self._checked_options(chosen)
        except ValueError as err:
            if vector and self._stacked(chosen):  # one value per copy, stacked: a natural first try
                raise ValueError(
                    f"{err}: a vector env's reset option is one value for every copy the reset starts; give copies "
                    "values of their own in separate resets, each with options['reset_mask'] naming its copies"
                ) from None
            raise

    def _stacked(self, chosen: Mapping[str, Any]) -> bool:
        """Whether the first row of every value in ``chosen`` passes :meth:`_checked_options` (values stacked one per
        copy)."""
        try:
            self._checked_options({key: np.asarray(value)[0] for key, value in chosen.items()})
        except (ValueError, TypeError, IndexError):
            return False
        return True

    def _checked_options(self, chosen: Mapping[str, Any]) -> dict[str, Tensor]:
        """:meth:`episode_options`' checks of the values of known keys ``chosen``."""
        out = {}
        for key, value in chosen.items():
            try:
                array = np.asarray(value)  # numbers only: NumPy would read "5" as 5.0 and True as 1.0
                if array.dtype.kind not in "iuf":
                    raise TypeError
                array = array.astype(np.float64)
            except (TypeError, ValueError):
                raise ValueError(
                    f"options[{key!r}] must be a number array (not a bool or a string), got {value!r:.80}"
                ) from None
            if not np.isfinite(array).all():
                raise ValueError(f"options[{key!r}] must be finite, got {array.tolist()}")
            out[key] = torch.as_tensor(array, device=self.device)
            if key in self.params:  # the shape and dtype of an earlier draw (else checked at the draw)
                out[key] = _chosen_param(key, out[key], self.params[key][0])
        self.task.check_options({k: v for k, v in out.items() if k != "condition"})
        if "condition" in out:
            m = self._cond_low.shape[0]
            if tuple(out["condition"].shape) != (m,):
                raise ValueError(f"options['condition'] must have shape [{m}], got {list(out['condition'].shape)}")
            cond = out["condition"].to(self.torch_dtype)[None]
            out["condition"] = self.check_cond(cond, "options['condition']", single=True)[0]
        return out

    def reset_rows(
        self, rows: list[int], rngs: list[np.random.Generator], chosen: Mapping[str, Tensor] | None = None
    ) -> None:
        """Start a new episode in copies ``rows`` (at rest, or where the task starts it), each drawing from its own
        generator; ``chosen`` (from :meth:`episode_options`) replaces the drawn parameters it names in every row."""
        chosen = dict(chosen or {})
        for row, rng in zip(rows, rngs, strict=True):
            cond = None
            if self.randomize_condition:
                u = torch.as_tensor(rng.random(self._cond_low.shape[0]), dtype=self.torch_dtype, device=self.device)
                cond = (self._cond_low + u * (self._cond_high - self._cond_low)).unsqueeze(0)
                if "condition" in chosen:
                    cond = chosen["condition"].unsqueeze(0)
                self.cond[row] = cond[0]
                z_rest = self._rest_latent(cond)
            else:
                cond = None if self.cond is None else self.cond[row : row + 1]
                z_rest = self._rest
            drawn = self.task.sample(rng, self, z_rest, cond)
            drawn.update({k: _chosen_param(k, v, drawn.get(k)) for k, v in chosen.items() if k != "condition"})
            if self.params and set(drawn) != set(self.params):
                raise ValueError(f"Task.sample returned keys {sorted(drawn)}, another episode {sorted(self.params)}")
            for key, value in drawn.items():
                if not isinstance(value, Tensor):
                    raise ValueError(f"Task.sample must return torch tensors, got {type(value).__name__} for {key!r}")
                if key not in self.params:
                    self.params[key] = torch.zeros((self.batch, *value.shape), dtype=value.dtype, device=self.device)
                self.params[key][row] = value
            start = self.task.start(self, row, z_rest)
            if not isinstance(start, Tensor) or tuple(start.shape) != (self.latent_dim,):
                got = list(start.shape) if isinstance(start, Tensor) else type(start).__name__
                raise ValueError(f"Task.start must return a torch tensor of shape [d] = [{self.latent_dim}], got {got}")
            if not bool(torch.isfinite(start).all()):
                raise ValueError(f"Task.start returned a latent that is not finite: {shown(start)}")
            self.z[row] = start
            self.z_prev[row] = start
            if self.reset_noise_scale > 0.0:  # drawn last: with s = 0 the streams are those of an env without it
                s, d = self.reset_noise_scale, self.latent_dim
                offset = torch.as_tensor(rng.uniform(-s, s, d), dtype=self.torch_dtype, device=self.device)
                speed = torch.as_tensor(s * rng.standard_normal(d), dtype=self.torch_dtype, device=self.device)
                self.z[row] = start + offset
                self.z_prev[row] = self.z[row] - speed * self.stepper.dt
        self.z[rows], self.z_prev[rows] = self._first_turn(self.z[rows], self.z_prev[rows])  # as after a step
        # x_prev's latent: one env step back at the start's velocity (z itself at rest), so that a task's extras that
        # read x_prev (Klann-v0's crank speed, BistableBar's height speed) see the start's velocity as z_dot does
        self.z_before[rows] = self.z[rows] - self.frame_skip * (self.z[rows] - self.z_prev[rows])
        self.loads[rows] = 0.0
        self.model[rows] = torch.nan
        self.carry[rows] = torch.nan
        cond = None if self.cond is None else self.cond[rows]
        x = self.full_positions(self.z[rows], cond)
        self.x = self.x.clone()
        self.x_prev = self.x_prev.clone()
        self.x[rows] = x
        self.x_prev[rows] = x if self.reset_noise_scale == 0.0 else self.full_positions(self.z_before[rows], cond)
        if self.action_resolution is None:
            self.action_resolution = self._action_resolution(rows[0])

    def task_loads(self, action: Tensor, params: Mapping[str, Tensor]) -> Tensor:
        """:meth:`Task.loads` of actions [B, A], refused (a ValueError naming it) unless a tensor [B, H, D]."""
        loads = self.task.loads(action, params)
        want = (self.batch, len(self.scene.handles), self.scene.dim)
        if not isinstance(loads, Tensor) or tuple(loads.shape) != want:
            got = list(loads.shape) if isinstance(loads, Tensor) else type(loads).__name__
            raise ValueError(f"Task.loads must return a torch tensor of shape [B, H, D] = {list(want)}, got {got}")
        return loads

    def _action_resolution(self, row: int) -> np.ndarray:
        """[A] The fraction of each action's range whose load a step from the map's origin can feel at best
        (:attr:`redsim.runtime.LatentStepper.load_resolution` over the load a full action puts on each handle); warns
        where it exceeds :data:`ACTION_RESOLUTION_WARNING`."""
        resolution = self.stepper.load_resolution
        size = self.task.action_size
        fractions = np.zeros(size)
        for i in range(size):
            action = torch.zeros(self.batch, size, dtype=self.torch_dtype, device=self.device)
            action[:, i] = 1.0
            # on a copy: loads may advance per-episode parameters in place (a clock), and this is no step
            params = {k: v.clone() for k, v in self.params.items()}
            load = self.task_loads(action, params)[row].detach().to("cpu", torch.float64).norm(dim=-1)  # [H]
            if bool((load > 0.0).any()):
                fractions[i] = float((resolution[load > 0.0] / load[load > 0.0]).min())
        if fractions.max() > ACTION_RESOLUTION_WARNING:
            worst = fractions.max()
            felt = (
                f"cannot feel actions below {worst:.1%} of their range"
                if worst <= 1.0
                else f"cannot feel any value of an action (the least it feels is {worst:.3g}x its range)"
            )
            warnings.warn(
                f"{self.torch_dtype} at dt={self.stepper.dt:g} s {felt} (action {int(fractions.argmax())}): such a "
                "step ends where it started (at best: from the map's origin, along the direction it moves a handle "
                "most); use dtype='float64' or a longer dt (docs/runtime.md, 'Tolerance')",
                stacklevel=2,
            )
        return fractions

    def observe(self) -> np.ndarray:
        """Observations [B, obs] (float32, clipped to :meth:`observation_bounds`)."""
        # z_dot of the state the stepper carries: z_prev is the last stepper step's, h (not the env's dt) before
        extras = self.task.extras(self.x, self.x_prev, self.params)
        k = len(self.task.extras_bounds()[0])
        # a copy whose x is not finite may report non-finite extras: which copies, only where some extras are not
        # finite (the check then passes on every copy alike; the scan of x costs ~1 ms at 64 cloth copies)
        finite = isinstance(extras, Tensor) and extras.is_floating_point() and bool(torch.isfinite(extras).all())
        valid = None if finite else torch.isfinite(self.x).all(dim=1)
        _check_task_output("extras", extras, self.batch, valid=valid, width=k)
        parts = [self.z, (self.z - self.z_prev) / self.stepper.dt, extras]
        if self.randomize_condition:
            parts.append(self.cond)
        obs = torch.cat([p.to(self.torch_dtype) for p in parts], dim=1).cpu().numpy().astype(np.float32)
        low, high = self.observation_bounds()
        return np.clip(obs, low, high)

    def observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) of one observation, float32 [obs]."""
        d = self.latent_dim
        low_e, high_e = self.task.extras_bounds()
        if np.shape(low_e) != np.shape(high_e) or np.ndim(low_e) != 1:
            raise ValueError(
                f"Task.extras_bounds must return (low, high), two 1-D arrays of one length, got shapes "
                f"{list(np.shape(low_e))} and {list(np.shape(high_e))}"
            )
        low = [np.full(d, -LATENT_BOUND), np.full(d, -2.0 * LATENT_BOUND / self.stepper.dt), low_e]
        high = [np.full(d, LATENT_BOUND), np.full(d, 2.0 * LATENT_BOUND / self.stepper.dt), high_e]
        if self.randomize_condition:
            low.append(self._cond_low.cpu().numpy())
            high.append(self._cond_high.cpu().numpy())
        return np.concatenate(low).astype(np.float32), np.concatenate(high).astype(np.float32)

    def observation_structure(self) -> dict[str, int]:
        """Name -> size of each observation block, in order."""
        d = self.latent_dim
        out = {"z": d, "z_dot": d, **self.task.observation_structure()}
        if self.randomize_condition:
            out["condition"] = self.cond.shape[1]
        return out

    # -- stepping -------------------------------------------------------------------------
    def _nearest_turn(self, z: Tensor, near: Tensor) -> Tensor:
        """z [B, d] with its periodic latents moved by whole turns to within pi of ``near`` [B, d].

        The map does not see whole turns, and the solve may land any number of them away (a
        quasi-Newton step on an angle), which would read as a huge z_dot.
        """
        if not self.periodic:
            return z
        turns = torch.zeros_like(z)
        gap = z[:, self.periodic] - near[:, self.periodic]
        turns[:, self.periodic] = 2.0 * math.pi * torch.round(gap / (2.0 * math.pi))
        return z - turns

    def _first_turn(self, z: Tensor, z_prev: Tensor) -> tuple[Tensor, Tensor]:
        """z, z_prev [B, d] shifted by the same whole turns that bring z's periodic latents into [-pi, pi) (z_dot
        unchanged; a no-op without periodic latents)."""
        if not self.periodic:
            return z, z_prev
        turns = z - self._nearest_turn(z, torch.zeros_like(z))
        return z - turns, z_prev - turns

    def _beyond_bound(self, z: Tensor, z_prev: Tensor) -> Tensor:
        """Copies [B] (bool) with a non-periodic latent of z or z_prev [B, d] beyond :data:`LATENT_BOUND`, which the
        observation clips (z, and z_dot past its bound): flagged ``out_of_range`` even where |z| is inside the map's
        radius (:data:`redsim.runtime.flags.LATENT_RANGE`, 11.3 at d = 8), so a clipped observation is never silent."""
        beyond = torch.stack([z, z_prev], 1).abs() > LATENT_BOUND  # [B, 2, d]
        if self.periodic:
            beyond[..., self.periodic] = False
        return beyond.any(-1).any(-1)

    def _stepper_step(self, rows: Tensor | None) -> StepStats:
        """One stepper step of the copies ``rows`` (indices; None: every copy) from z, z_prev under the loads, which
        updates their z, z_prev, model and carry; the other copies keep theirs and get zeros (False) in the
        returned [B] fields (its ``model`` and ``carry`` are the sim's)."""
        if rows is None:
            z_next, stats = self.stepper.step(
                self.z, self.z_prev, self.loads, self.cond, warm=self.model, carry=self.carry
            )
            self.model, self.carry = stats.model, stats.carry
            self.z_prev, self.z = self.z, self._nearest_turn(z_next.detach(), self.z)
            return stats
        cond = None if self.cond is None else self.cond[rows]
        z, z_prev = self.z[rows], self.z_prev[rows]
        z_next, stats = self.stepper.step(
            z, z_prev, self.loads[rows], cond, warm=self.model[rows], carry=self.carry[rows]
        )
        self.model, self.carry = self.model.clone(), self.carry.clone()
        self.model[rows], self.carry[rows] = stats.model, stats.carry
        self.z_prev, self.z = self.z_prev.clone(), self.z.clone()
        self.z_prev[rows], self.z[rows] = z, self._nearest_turn(z_next.detach(), z)
        from redsim.runtime import StepStats

        spread = {}
        for field, value in stats._asdict().items():
            if field not in ("model", "carry"):
                spread[field] = value.new_zeros(self.batch).index_copy(0, rows.to(value.device), value)
        return StepStats(**spread, model=self.model, carry=self.carry)

    def step(
        self, action: np.ndarray, active: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Advance every copy by one env step with actions [B, A] (already checked and clipped). The step is
        atomic: an exception or a KeyboardInterrupt inside it leaves every copy as it was before the call.

        ``active`` (bool [B], default all) names the copies the solver steps; the others keep their state and get
        zeros in the solver's entries of ``info`` (a vector env's copies that the step resets: their step would be
        discarded). Their reward, termination, metrics and ``out_of_range`` (a latent beyond the observation's bound)
        are of the state they keep, for the caller to drop. A stepper compiled with static shapes (``compile=True``:
        one graph per batch size) steps every copy, as before.

        Returns:
            reward [B] (float64), terminated [B] (bool), info {key: [B] array} (see :class:`LatentEnv`; floats
            float64, integers int64, as Gymnasium's sync vector env batches the single env's numbers).
        """
        saved = self.snapshot()
        try:
            return self._step(action, active)
        except BaseException:
            self.restore(saved)
            raise

    def snapshot(self) -> tuple[Any, ...]:
        """Copies of what a step or a reset of some rows changes (z, z_prev, z_before, loads, the solver's model and
        carry, the task params, which a task's loads may update in place, and cond); x and x_prev are replaced, never
        written in place, so they are kept by reference. :meth:`restore` puts them back: an env step that fails after
        the simulation step (its observation, an autoreset) leaves every copy as it was."""
        params = {k: v.clone() for k, v in self.params.items()}
        cond = None if self.cond is None else self.cond.clone()
        return (
            self.z.clone(),
            self.z_prev.clone(),
            self.z_before.clone(),
            self.x,
            self.x_prev,
            self.loads.clone(),
            self.model.clone(),
            self.carry.clone(),
            params,
            cond,
        )

    def restore(self, saved: tuple[Any, ...]) -> None:
        """Return to a :meth:`snapshot`."""
        z, z_prev, z_before, x, x_prev, loads, model, carry, params, cond = saved
        self.z, self.z_prev, self.z_before, self.x, self.x_prev, self.loads = z, z_prev, z_before, x, x_prev, loads
        self.model, self.carry, self.params, self.cond = model, carry, params, cond

    def _step(
        self, action: np.ndarray, active: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        from redsim.runtime.flags import out_of_range_states

        act = torch.as_tensor(action, dtype=self.torch_dtype, device=self.device)
        self.loads = self.task_loads(act, self.params).to(self.torch_dtype)
        moving = torch.ones(self.batch, dtype=torch.bool, device=self.device)
        if active is not None and np.shape(active) != (self.batch,):
            raise ValueError(f"active must be a bool mask of shape ({self.batch},), got shape {np.shape(active)}")
        if active is not None and not self.stepper.compiled:  # a static graph per batch size: a subset recompiles
            moving = torch.as_tensor(np.asarray(active, dtype=bool), device=self.device)
        every = bool(moving.all())
        rows = None if every else torch.nonzero(moving).flatten()
        diverged = torch.zeros(self.batch, dtype=torch.bool, device=self.device)
        # the step's own start too: a z_prev set beyond the map's region (a velocity no step of it made) is flagged
        out_of_range = out_of_range_states(self.z_prev[:, None], tuple(self.periodic), None, None).to(self.device)
        out_of_range &= moving
        energy_gain = torch.zeros_like(diverged)
        stalled = torch.zeros_like(diverged)
        gain_tolerance = torch.zeros(self.batch, dtype=self.torch_dtype, device=self.device)
        iterations = torch.zeros(self.batch, dtype=torch.int64, device=self.device)
        converged = moving.clone()
        residual = energy = torch.zeros(self.batch, dtype=self.torch_dtype, device=self.device)
        z_before = self.z.clone()  # x's latent, x_prev's after this step
        for _ in range(self.frame_skip if rows is None or len(rows) else 0):
            stats = self._stepper_step(rows)
            diverged |= stats.diverged.to(self.device)
            out_of_range |= stats.out_of_range.to(self.device)
            energy_gain |= stats.energy_gain.to(self.device)
            stalled |= stats.stalled.to(self.device)
            gain_tolerance += stats.energy_gain_tolerance.to(self.device, self.torch_dtype)
            converged &= stats.converged.to(self.device)
            iterations += stats.iterations.to(self.device).to(torch.int64)
            residual, energy = stats.residual, stats.energy
        diverged |= ~torch.isfinite(self.z).all(dim=1)
        self.z, self.z_prev = self._first_turn(self.z, self.z_prev)
        out_of_range |= self._beyond_bound(self.z, self.z_prev)
        self.x_prev, self.x, self.z_before = self.x, self.full_positions(self.z), z_before
        tunneled = self.tunnel_test(self.x_prev, self.x, ~diverged)  # over the env step (frame_skip stepper steps)
        reward, terms = self.task.reward(self.x, act, self.params)
        valid = moving & ~diverged
        _check_task_output("reward", reward, self.batch, valid=valid)
        for key, value in terms.items():
            _check_task_output(f"reward term {key!r}", value, self.batch, valid=valid)
        if self.task.reward_terms and set(terms) != set(self.task.reward_terms):
            raise ValueError(f"Task reward terms {sorted(terms)} are not reward_terms {list(self.task.reward_terms)}")
        total = sum(terms.values())
        if terms and not torch.allclose(total.to(reward.dtype)[valid], reward[valid], rtol=1e-4, atol=1e-5):
            raise ValueError("Task reward terms must sum to the reward (each is reported as info['reward_<term>'])")
        ended = self.task.terminated(self.x, self.params)
        _check_task_output("terminated", ended, self.batch, dtype=torch.bool)
        terminated = ended | diverged
        info: dict[str, Tensor] = {
            "converged": converged,
            "iterations": iterations,
            "residual": residual,
            "energy": energy,
            "out_of_range": out_of_range,
            "diverged": diverged,
            "stalled": stalled,
            "energy_gain": energy_gain,
            "energy_gain_tolerance": gain_tolerance,
            "tunneled": tunneled,
            **{f"reward_{k}": v for k, v in terms.items()},
        }
        out = {k: _info_array(v.detach().cpu().numpy()) for k, v in info.items()}
        return reward.detach().cpu().numpy().astype(np.float64), terminated.cpu().numpy(), {**out, **self.state_info()}

    def state_info(self, rows: np.ndarray | None = None, *, start: bool = False) -> dict[str, np.ndarray]:
        """What ``info`` says about the current states, at a step and at a reset alike (Gymnasium: a reset's info is
        analogous to a step's): the task's metrics, the scene's invariants and, with ``include_q``, ``q`` [B, n]; each
        [B, ...], the [B] ones float64 or int64 as a step's numbers. With ``rows`` (bool [B]) only those copies'
        entries are kept (the ones a reset just started; the others' are zeros), and the invariants and q are evaluated
        for them only; none: an empty dict. The task's metrics are evaluated for every copy: a task may read the whole
        batch's state through the sim :meth:`Task.bind` gave it (Klann-v0's crank speed reads ``sim.x_prev``).
        ``start`` (a reset's info) adds ``out_of_range``, as a step flags it, for a start beyond the map's region or
        the observation's bounds (a large ``reset_noise_scale``: a review's started at |z| 60, clipped to 10)."""
        every = rows is None or bool(np.all(rows))
        if rows is not None and not np.any(rows):
            return {}
        index = None if every else torch.as_tensor(np.nonzero(rows)[0], device=self.device)
        metrics = self.task.metrics(self.x, self.params)
        for key, value in metrics.items():
            _check_task_output(f"metric {key!r}", value, self.batch, finite=False)
        if index is not None:
            metrics = {key: value[index] for key, value in metrics.items()}
        x = self.x if index is None else self.x[index]
        values = {**metrics, **self.invariants(x)}
        if start:
            from redsim.runtime.flags import out_of_range_states

            z, z_prev = (self.z, self.z_prev) if index is None else (self.z[index], self.z_prev[index])
            cond = None if self.cond is None else (self.cond if index is None else self.cond[index])
            pair = torch.stack([z, z_prev], 1)
            space = self.scene.condition_space
            values["out_of_range"] = out_of_range_states(pair, tuple(self.periodic), cond, space) | self._beyond_bound(
                z, z_prev
            )
        if self.include_q:
            z = self.z if index is None else self.z[index]
            cond = None if self.cond is None or index is None else self.cond[index]
            values["q"] = self.positions(z, cond)
        out: dict[str, np.ndarray] = {}
        for key, value in values.items():
            part = value.detach().cpu().numpy()
            if index is not None:
                full = np.zeros((self.batch, *part.shape[1:]), dtype=part.dtype)
                full[rows] = part
                part = full
            out[key] = _info_array(part)
        return out

    # -- state ----------------------------------------------------------------------------
    def setting(self) -> dict[str, Any]:
        """What a state means only under: the scene, the task, the step dt [s] and its substeps (z_prev encodes
        the velocity (z - z_prev) / dt)."""
        kind = type(self.task)
        return {
            "scene": self.source_scene.name,
            "task": f"{kind.__module__}.{kind.__qualname__}",
            "dt": self.dt,
            "frame_skip": self.frame_skip,
        }

    def get_state(self) -> dict[str, Any]:
        """Copies of the dynamic state: z, z_prev [B, d], ``z_before`` [B, d] (z one env step ago: x_prev's, which
        Klann's crank speed reads), cond [B, m] or None, task params {k: [B, ...]},
        the solver's warm start ``model`` [B, d, d] and ``carry`` [B, k] (so a restored state steps bitwise alike;
        :attr:`redsim.runtime.stepper.StepStats`), the loads of the last
        step ``loads`` [B, H, D] [N] (what the force arrows draw and a task's controller reads) and the
        :meth:`setting` it belongs to."""
        return {
            "z": self.z.cpu().numpy().copy(),
            "z_prev": self.z_prev.cpu().numpy().copy(),
            "z_before": self.z_before.cpu().numpy().copy(),
            "model": self.model.cpu().numpy().copy(),
            "carry": self.carry.cpu().numpy().copy(),
            "loads": self.loads.cpu().numpy().copy(),
            "cond": None if self.cond is None else self.cond.cpu().numpy().copy(),
            "params": {k: v.cpu().numpy().copy() for k, v in self.params.items()},
            "setting": self.setting(),
        }

    def set_state(self, state: Mapping[str, Any]) -> None:
        """Restore a state from :meth:`get_state` (shapes are checked; without ``model`` the next step
        builds its solver model afresh and without ``carry`` evaluates E at z itself: the same solve to the
        tolerance, from which float32 trajectories then drift apart as they do between batch sizes; without
        ``loads`` (a state saved before states held them) the last loads are zero, as after a reset: no force arrow
        is drawn until the next step).

        The state is checked as ``reset(options=...)`` checks its options (a task parameter named in
        :attr:`Task.reset_options`, e.g. a target beyond the observation bound, is refused by
        :meth:`Task.check_options`; a condition outside its space too) before anything changes.

        Raises:
            ValueError: on a missing key, task parameters other than the task draws (their keys, shapes; before
                any reset: of :meth:`drawn_params`), a wrong shape, non-finite values, latents too far out for the
                map (their positions or reward not finite), a condition outside the scene's condition space, a task
                parameter that ``reset(options=...)`` would refuse, or a state of another
                scene, task, dt or frame_skip (``state["setting"]``; a state without it, from before stop 32, is
                taken as it is).
        """
        d, B = self.latent_dim, self.batch
        theirs, mine = state.get("setting"), self.setting()
        if theirs is not None and not isinstance(theirs, Mapping):
            raise ValueError(f"state['setting'] must be the dict get_state() wrote, got {theirs!r:.80}")
        if theirs is not None and dict(theirs) != mine:
            differ = ", ".join(f"{k} {theirs.get(k)!r} (here {v!r})" for k, v in mine.items() if theirs.get(k) != v)
            raise ValueError(f"the state belongs to another env: {differ}")

        def tensor(
            value: Any, shape: tuple[int, ...], what: str, dtype: torch.dtype | None = None, finite: bool = True
        ) -> Tensor:
            try:
                if value is None:
                    raise TypeError
                exact = dtype in (torch.bool, torch.int64)  # integers and flags without a round trip through floats
                array = np.asarray(value) if exact else np.asarray(value, dtype=np.float64)
                t = torch.as_tensor(array, dtype=dtype or self.torch_dtype, device=self.device)
            except (TypeError, ValueError):
                raise ValueError(
                    f"state[{what!r}] must be a numeric array of shape {list(shape)}, got {value!r:.80} "
                    "(a state of another env?)"
                ) from None
            if tuple(t.shape) != shape:
                raise ValueError(f"state[{what!r}] must have shape {list(shape)}, got {list(t.shape)}")
            if finite and not bool(torch.isfinite(t).all()):
                raise ValueError(f"state[{what!r}] must be finite")
            return t.clone()

        missing = {"z", "z_prev", "cond", "params"} - set(state)
        if missing:
            raise ValueError(f"state is missing {sorted(missing)}")
        cond = None if self.cond is None else self.check_cond(tensor(state["cond"], tuple(self.cond.shape), "cond"))
        z = tensor(state["z"], (B, d), "z")
        z_prev = tensor(state["z_prev"], (B, d), "z_prev")
        # a state saved before stop 44 holds no z_before: z_prev, which is it with frame_skip 1
        z_before = z_prev.clone() if state.get("z_before") is None else tensor(state["z_before"], (B, d), "z_before")
        model = torch.full((B, d, d), torch.nan, dtype=self.torch_dtype, device=self.device)
        if state.get("model") is not None:  # NaN rows: none built yet (the next step builds its own)
            model = tensor(state["model"], (B, d, d), "model", finite=False)
        carry = torch.full_like(self.carry, torch.nan)
        if state.get("carry") is not None:  # NaN rows: the next step evaluates them
            carry = tensor(state["carry"], tuple(carry.shape), "carry", finite=False)
        H, D = self.loads.shape[1:]
        loads = torch.zeros_like(self.loads)
        if state.get("loads") is not None:
            loads = tensor(state["loads"], (B, H, D), "loads")
        params, like = state["params"], self.params or self.drawn_params()
        if not isinstance(params, Mapping):
            raise ValueError(f"state['params'] must be the task parameters' dict get_state() wrote, got {params!r:.60}")
        if set(params) != set(like):
            raise ValueError(f"state['params'] must have keys {sorted(like)} (the task's draw), got {sorted(params)}")
        # each keeps its dtype (a task's counters and flags stay integers and bools)
        params = {k: tensor(v, tuple(like[k].shape), f"params.{k}", like[k].dtype) for k, v in params.items()}
        self.check_state_params(params)
        decoded = self.decode_state_latents({"z": z, "z_before": z_before, "z_prev": z_prev}, cond, params)
        self.z, self.z_prev, self.z_before, self.model, self.carry, self.params, self.loads = (
            z,
            z_prev,
            z_before,
            model,
            carry,
            params,
            loads,
        )
        if cond is not None:
            self.cond = cond
        self.x_prev, self.x = decoded["z_before"], decoded["z"]

    def decode_state_latents(
        self, latents: Mapping[str, Tensor], cond: Tensor | None, params: Mapping[str, Tensor]
    ) -> dict[str, Tensor]:
        """Full positions {name: x [B, N]} of a state's latents {"z", "z_before", "z_prev": [B, d]} under its
        conditions cond [B, m] (None: the copies' own) and task parameters; changes nothing.

        Raises:
            ValueError: copies too far out for the map: positions not finite, or a reward at z (zero action, copies
                of the params; float32 distances past 1e19 m overflow) that is not; the next step's would be too.
        """
        cond = cond if cond is not None else self.cond
        decoded = {}
        for what, latent in latents.items():
            x = self.full_positions(latent, cond)
            far = ~torch.isfinite(x).all(dim=1)
            if bool(far.any()):
                raise ValueError(
                    f"state[{what!r}] of copies {torch.nonzero(far).flatten().tolist()} decodes to non-finite "
                    f"positions (|z| up to {float(latent[far].abs().max()):.3g}): latents too far out for the map"
                )
            decoded[what] = x
        z, x = latents["z"], decoded["z"]
        idle = torch.zeros(x.shape[0], self.task.action_size, dtype=self.torch_dtype, device=self.device)
        reward, _ = self.task.reward(x, idle, {k: v.clone() for k, v in params.items()})
        far = ~torch.isfinite(reward)
        if bool(far.any()):
            raise ValueError(
                f"state['z'] of copies {torch.nonzero(far).flatten().tolist()} is too far out for the map: its reward "
                f"is not finite (|z| up to {float(z[far].abs().max()):.3g})"
            )
        return decoded

    def drawn_params(self) -> dict[str, Tensor]:
        """Zeros {name: [B, ...]} shaped and typed as the task's parameters, from one throwaway draw (seed 0, the
        default condition; the copies' generators untouched): what a state must hold before any reset."""
        z_rest = self._default_rest.clone()
        drawn = self.task.sample(np.random.default_rng(0), self, z_rest, self.default_cond)
        return {k: torch.zeros((self.batch, *v.shape), dtype=v.dtype, device=self.device) for k, v in drawn.items()}

    def check_state_params(self, params: Mapping[str, Any]) -> None:
        """Refuse a state's task parameters {name: [B, ...]} where ``reset(options=...)`` would refuse them as
        options: those named in :attr:`Task.reset_options`, copy by copy, by :meth:`Task.check_options`.

        Raises:
            ValueError: naming the copy and the task's reason.
        """
        chosen = {}
        for key in set(params) & set(self.task.reset_options):
            try:
                value = params[key]
                chosen[key] = value if isinstance(value, Tensor) else torch.as_tensor(np.asarray(value, np.float64))
            except (TypeError, ValueError):
                continue  # not a number array: set_state refuses it by its shape, and says so
        for row in range(min((v.shape[0] if v.ndim else 0 for v in chosen.values()), default=0)):
            try:
                self.task.check_options({k: v[row] for k, v in chosen.items()})
            except ValueError as error:
                raise ValueError(f"state['params'] of copy {row} is one a reset would refuse: {error}") from None

    def check_cond(self, cond: Tensor, what: str = "state['cond']", single: bool = False) -> Tensor:
        """``cond`` [B, m], refused (ValueError naming ``what`` and the ranges) where it leaves the condition space;
        ``single``: ``what`` is one condition [m] (B = 1), shown as such."""
        if bool(((cond < self._cond_low) | (cond > self._cond_high)).any()):
            space = self.scene.condition_space
            ranges = ", ".join(
                f"{name} in [{lo:g}, {hi:g}]"
                for name, lo, hi in zip(space.names, space.low.tolist(), space.high.tolist(), strict=True)
            )
            got = shown(cond[0] if single else cond)
            raise ValueError(f"{what} must lie in the condition space ({ranges}), got {got}")
        return cond

    # -- drawing --------------------------------------------------------------------------
    def surface_points(self, z: Tensor, cond: Tensor | None = None) -> np.ndarray:
        """Vertex positions [P, D] [m] of every surface in the shapes of latents z [B, d] (conditions cond [B, m],
        default: the default condition), float64."""
        if cond is None and self.conditional:
            cond = self.default_cond.expand(len(z), -1)
        x = self.full_positions(z, cond)
        points = [s.points.positions(x).reshape(-1, self.scene.dim) for s in self.scene.surfaces]
        return torch.cat(points).detach().cpu().to(torch.float64).numpy()

    def frame_conditions(self) -> list[Tensor | None]:
        """The conditions [1, m] whose reset shapes a fixed camera frames: the default, and where the condition is
        drawn per episode the corners of the condition box too ([None] for an unconditional map)."""
        if not self.conditional:
            return [None]
        conds = [self.default_cond]
        if self.randomize_condition:
            m = self._cond_low.shape[0]
            for corner in range(2**m):
                pick = torch.tensor([(corner >> i) & 1 for i in range(m)], dtype=torch.bool, device=self.device)
                conds.append(torch.where(pick, self._cond_high, self._cond_low).unsqueeze(0))
        return conds

    def frame_rests(self) -> list[tuple[Tensor | None, Tensor]]:
        """Each of :meth:`frame_conditions` with its rest latent [d] (solved once: :meth:`_settled_rests`)."""
        conds = self.frame_conditions()
        return list(zip(conds, self._settled_rests(conds), strict=True))

    def frame_points(self) -> np.ndarray:
        """Points [P, D] [m] a fixed camera frames (computed once, then kept): the reset shapes (at rest under each
        of :meth:`frame_conditions`), every shape round the loop of each periodic latent (:data:`LOOP_SAMPLES`
        angles) and the task's :meth:`Task.frame_points` (its target region, its handles' reach)."""
        if self._frame_points is None:
            points = []
            angles = torch.linspace(-math.pi, math.pi, LOOP_SAMPLES + 1, dtype=self.torch_dtype)[:-1]
            for cond, rest in self.frame_rests():
                rest = rest.unsqueeze(0)
                shapes = [rest]
                for latent in self.periodic:  # each loop on its own, the other latents at rest
                    loop = rest.repeat(LOOP_SAMPLES, 1)
                    loop[:, latent] = angles.to(self.device)
                    shapes.append(loop)
                z = torch.cat(shapes)
                points.append(self.surface_points(z, None if cond is None else cond.expand(len(z), -1)))
            extra = self.task.frame_points(self)
            if extra is not None and len(extra):
                extra = np.asarray(extra, dtype=np.float64)
                if extra.ndim != 2 or extra.shape[1] != self.scene.dim or not np.isfinite(extra).all():
                    raise ValueError(
                        f"Task.frame_points must return finite points [P, D] = [P, {self.scene.dim}] [m], got "
                        f"shape {list(extra.shape)}{'' if np.isfinite(extra).all() else ' with non-finite values'}"
                    )
                points.append(extra)
            self._frame_points = np.concatenate(points)
        return self._frame_points

    def fixed_view(self, width: int, height: int, camera: Mapping[str, Any] | None) -> Any:
        """The env's fixed camera: a :class:`redsim.raster.SceneView` framed on :meth:`frame_points`, so the same
        world point lands on the same pixel in every episode and every copy (DeepMind Control's fixed cameras); a
        shape that leaves the frame is clipped at the picture's border."""
        from redsim.raster import SceneView

        rest = self._rest_latent(self.default_cond).unsqueeze(0)
        q = self.positions(rest, self.default_cond)[0]
        settings = {k: v for k, v in dict(camera or {}).items() if k != "track"}
        return SceneView(self.scene, q, width=width, height=height, extra_points=self.frame_points(), **settings)

    def view(self, width: int, height: int, camera: Mapping[str, Any] | None, rows: Sequence[int] = (0,)) -> Any:
        """A tracking camera (``camera={"track": True}``): a :class:`redsim.raster.SceneView` framed on copy 0's
        current shape and the overlay markers (targets, handles) of copies ``rows``."""
        return self.view_on(width, height, camera, self.first_shape(), self.marker_points(rows))

    def first_shape(self) -> Tensor:
        """Copy 0's configuration q [n], what a tracking camera frames (:meth:`view`)."""
        return self.positions(self.z[:1], None if self.cond is None else self.cond[:1])[0]

    def view_on(
        self, width: int, height: int, camera: Mapping[str, Any] | None, q: Tensor, extra: np.ndarray | None
    ) -> Any:
        """A :class:`redsim.raster.SceneView` framed on q [n] and the points ``extra`` [P, D] (None: none)."""
        from redsim.raster import SceneView

        settings = {k: v for k, v in dict(camera or {}).items() if k != "track"}
        return SceneView(self.scene, q, width=width, height=height, extra_points=extra, **settings)

    def marker_points(self, rows: Sequence[int]) -> np.ndarray | None:
        """Positions [P, D] of the overlay markers of copies ``rows`` (None: no marker)."""
        points = [m.position for row in rows for m in self.task.overlay(self, row)[0]]
        return np.array(points, dtype=np.float64).reshape(len(points), -1) if points else None

    def framed_view(
        self, view: Any, width: int, height: int, camera: Mapping[str, Any] | None, rows: Sequence[int]
    ) -> Any:
        """The view to draw copies ``rows`` with. The fixed camera (default): ``view``, or :meth:`fixed_view` for a
        first one (None). A tracking camera (``camera["track"]``): ``view`` while it shows every overlay marker of
        copies ``rows``, else a new :meth:`view` framed on them all (a target drawn or chosen outside the frame, or a
        handle that left it; None: a first view)."""
        if not (camera or {}).get("track", False):
            return view if view is not None else self.fixed_view(width, height, camera)
        if view is not None:
            points = self.marker_points(rows)
            if points is None or view.contains(points):
                return view
        return self.view(width, height, camera, rows)

    def trimeshes(self, row: int) -> list[Any]:
        """Copy ``row``'s surfaces as ``trimesh.Trimesh`` objects (:func:`redsim.render.surface_meshes`), decoded on
        their own (as :meth:`draw_rows` decodes), so a vector copy's meshes are the single env's for the same state."""
        from redsim.render import surface_meshes

        cond = None if self.cond is None else self.cond[row : row + 1]
        q = self.positions(self.z[row : row + 1], cond)[0].detach().to(self.scene.dtype)
        return surface_meshes(self.scene, q)

    def draw(self, view: Any, row: int) -> np.ndarray:
        """RGB picture [H, W, 3] of copy ``row``."""
        return self.draw_rows(view, [row])[0]

    def draw_rows(self, view: Any, rows: Sequence[int]) -> np.ndarray:
        """RGB pictures [len(rows), H, W, 3] of copies ``rows``, in one :meth:`redsim.raster.SceneView.draw_batch`.

        Each copy's configuration is decoded on its own (as a single env decodes its one copy: a batched decode
        differs in the last bits, which moves a vertex across a pixel boundary now and then), so copy i's picture is
        pixel for pixel the single env's for the same state."""
        q = torch.cat(
            [self.positions(self.z[i : i + 1], None if self.cond is None else self.cond[i : i + 1]) for i in rows]
        )
        overlays = [self.task.overlay(self, i) for i in rows]
        return view.draw_batch(q, markers=[m for m, _ in overlays], arrows=[a for _, a in overlays])


def shipped(
    scene_name: str,
    scene_params: Mapping[str, Any] | None = None,
    subspace: str | nn.Module | None = None,
    *,
    fit_if_missing: bool = False,
    fit_options: Mapping[str, Any] | None = None,
) -> tuple[Scene, nn.Module]:
    """A catalog scene and its subspace: the shipped one (default), a checkpoint path, or a map.

    Args:
        scene_name: Catalog name.
        scene_params: Build parameters (the shipped map covers only the defaults).
        subspace: None (shipped), a checkpoint path or a map.
        fit_if_missing: With ``subspace=None`` and parameters no shipped map covers, fit one into
            the user cache (or load it from there): :func:`redsim.envs.fitted.cached_subspace`.
        fit_options: FitConfig fields over the shipped map's fit options for that fit (e.g. ``{"steps": 2000}``).

    Raises:
        ValueError: an unknown scene or parameter, a bad fit option, or fit options beside a given ``subspace``.
        redsim.subspace.CheckpointError: no shipped subspace covers ``scene_params`` (and
            ``fit_if_missing`` is False), or the checkpoint is missing or corrupt.
    """
    from redsim import pretrained, scenes

    if scene_params is not None and not isinstance(scene_params, Mapping):
        raise ValueError(f"scene_params must be a dict of build parameters, got {scene_params!r:.80}")
    if not isinstance(fit_if_missing, (bool, np.bool_)):  # "no" is truthy: it would start a fit
        raise ValueError(f"fit_if_missing must be True or False, got {fit_if_missing!r}")
    scene = scenes.build(scene_name, **dict(scene_params or {}))
    if fit_options is not None and not fit_if_missing:
        raise ValueError("fit_options only apply with fit_if_missing=True")
    if fit_options is not None and subspace is not None:  # no fit is made: the options would be dropped unsaid
        raise ValueError(
            "fit_options apply to a fit into the user cache (subspace=None); with subspace given that map is used "
            "as it is and nothing is fitted"
        )
    if subspace is None:
        if scene_params and scenes.build(scene_name).fingerprint() != scene.fingerprint():
            if fit_if_missing:
                from redsim.envs.fitted import cached_subspace

                return scene, cached_subspace(scene_name, scene, fit_options)
            raise CheckpointError(
                f"no shipped subspace covers scene {scene_name!r} with parameters {dict(scene_params)}; the "
                "shipped one is fitted to the defaults. Pass fit_if_missing=True to fit one into the user cache "
                f"(minutes), or fit one yourself (`redsim fit {scene_name} --param ...`) and pass subspace=PATH"
            )
        return scene, pretrained.load(scene_name, scene)
    if isinstance(subspace, nn.Module):
        return scene, subspace
    return scene, checkpoint_subspace(subspace, scene)


def with_fitted_map(kwargs: Mapping[str, Any], subspace: nn.Module) -> dict[str, Any]:
    """An env's constructor arguments ``kwargs`` to make it again with the map a fit made in memory: ``subspace`` given
    and no ``fit_options`` (nothing is fitted beside a given map: :func:`shipped` refuses them)."""
    return {**{k: v for k, v in kwargs.items() if k != "fit_options"}, "subspace": subspace}


def checkpoint_subspace(path: str | os.PathLike[str], scene: Scene) -> nn.Module:
    """The map saved at ``path`` for ``scene``, marked with its path (:data:`CHECKPOINT_ATTRIBUTE`): an env's
    ``cubature=True`` then takes the cubature beside it.

    Raises:
        redsim.subspace.CheckpointError: a missing or corrupt checkpoint, or one of another scene.
    """
    from redsim.subspace import load_subspace

    loaded = load_subspace(path, scene=scene)
    setattr(loaded, CHECKPOINT_ATTRIBUTE, os.fspath(path))
    return loaded


def on_env_threads(method: Callable[..., Any]) -> Callable[..., Any]:
    """``method`` of an env run on the env's ``threads`` torch threads, the caller's setting restored after it
    (:func:`redsim.threads.torch_threads`)."""

    @functools.wraps(method)
    def run(self: Any, *args: Any, **kwargs: Any) -> Any:
        with torch_threads(self.threads):
            return method(self, *args, **kwargs)

    return run


class LatentEnv(gym.Env[np.ndarray, np.ndarray]):
    """A Gymnasium env whose state is the latent (z, z_dot) of a subspace, advanced by the latent stepper.

    The registered ``RedSim/...-v0`` envs subclass it with a scene, its shipped subspace and a
    task; :func:`redsim.envs.make` builds one from any scene, subspace and task.

    ``info`` after each step: ``converged``, ``iterations``, ``residual`` (the stepper's solver
    statistics), ``energy`` [J] (the energy the stepper minimized: a cubature's estimate where the env steps one),
    ``out_of_range`` (z left the region the map was fitted on, or a latent of z lies beyond the observation's
    :data:`LATENT_BOUND`, where the observation clips it), ``diverged``, ``stalled`` (a solve, of any of the
    ``frame_skip`` stepper steps, stopped unconverged before ``max_iter``: its line search found no step lowering the
    objective; :class:`redsim.runtime.StepStats`), ``energy_gain`` (a step raised K + E by
    more than the action's work: an artefact of the map or the solve, reported like MuJoCo's warnings and never
    ending the episode; see
    :func:`redsim.runtime.flags.energy_gain_states`), ``energy_gain_tolerance`` [J] (the rise that flag allows: what
    the solve's leftover gradient can put in, plus round-off), ``tunneled`` (the step's straight path passed through
    a contact that neither end shows: a move longer than the contact is thick, which the penalty never felt;
    :mod:`redsim.integrators.tunneling`; reported, the episode goes on), ``reward_<term>`` for each reward term, the
    task's metrics (``distance``, ``is_success``), the scene's invariants (:mod:`redsim.envs.invariants`) and, with
    ``include_q=True``, ``q`` [n]. ``info`` after a reset: the same metrics, invariants and ``q`` of the new
    episode's start (:meth:`LatentSim.state_info`). A step the stepper cannot make finite ends the episode
    (``terminated=True``, ``info["diverged"]=True``).

    Args:
        scene: The scene.
        subspace: Its map (fitted to this scene: another scene's map raises CheckpointError).
        task: The task.
        render_mode: None, "rgb_array" (headless) or "human" (a pygame window; listed in ``metadata``
            where pygame and a display exist, else a clear error: :func:`human_unavailable`, and
            :func:`open_display` where pygame reaches no display).
        dt: Stepper time step [s].
        frame_skip: Stepper steps per env step, in [1, :data:`MAX_FRAME_SKIP`].
        dtype: Stepper dtype, "float32" or "float64" (or the torch/NumPy dtype; the spec records its name).
        device: Torch device (a ``torch.device`` is recorded in the spec as its string).
        randomize_condition: Draw the scene's condition per episode (conditional maps).
        include_q: Put q in the ``info`` of every step and reset.
        reset_noise_scale: Start noise s [latent units] (:class:`LatentSim`; 0: every episode starts at rest).
        width: Render width [px], 8 to :data:`MAX_IMAGE_SIDE` (4096).
        height: Render height [px], the same range.
        camera: ``azimuth``/``elevation``/``margin``/``merge_px`` of :class:`redsim.raster.SceneView`, over the
            env's own :attr:`camera` key by key. The camera is fixed (framed once, at the first render, on the reset
            shapes and the task's target region: :meth:`LatentSim.fixed_view`); ``track=True`` frames each episode
            anew on its shape and markers instead.
        stepper_options: Extra keyword arguments of :class:`redsim.runtime.LatentStepper`.
        cubature: Step a cubature energy (:func:`env_energy`): None (the shipped one where
            :data:`CUBATURE_DEFAULT` turns it on), True (required), False (every element), "lean" (the lean one
            shipped beside the shipped map: :data:`SHIPPED_CUBATURES`) or a checkpoint path.
        threads: torch intra-op threads while the env computes (made, reset, stepped, rendered; default 1, what its
            small tensor ops run fastest on), the caller's own setting restored after each call; None: the caller's
            setting (:mod:`redsim.threads`).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": RENDER_MODES, "render_fps": 50}
    stepper_defaults: ClassVar[dict[str, Any]] = {}
    """The env's own defaults of ``stepper_options`` (a user's options override them key by key)."""
    camera: ClassVar[dict[str, float]] = {}
    """The env's own camera (a user's ``camera`` overrides it key by key)."""
    _spec: EnvSpec | None = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """Put :data:`LATENT_ENV_ARGUMENTS` in place of a :data:`LATENT_ENV_ROW` row of the subclass's docstring (at
        that row's indent): ``help(env.unwrapped)`` shows every argument the env takes."""
        super().__init_subclass__(**kwargs)
        doc = cls.__doc__ or ""
        if LATENT_ENV_ROW in doc:
            indent = doc[: doc.index(LATENT_ENV_ROW)].rsplit("\n", 1)[-1]
            own = {name for line in doc.splitlines() for name in row_arguments(line)}
            rows = [row for row in LATENT_ENV_ARGUMENTS if not own & set(row_arguments(row))]
            cls.__doc__ = doc.replace(LATENT_ENV_ROW, f"\n{indent}".join(rows))

    @property
    def spec(self) -> EnvSpec | None:
        """The spec ``gym.make`` gave the env, its kwargs in JSON form (:func:`json_spec`: ``spec.to_json()`` works)."""
        return self._spec

    @spec.setter
    def spec(self, spec: EnvSpec | None) -> None:
        self._spec = json_spec(spec)

    def __new__(cls, *args: Any, **kwargs: Any) -> LatentEnv:
        check_threads(kwargs.get("threads", 1))  # before a subclass builds its scene or fits a map
        env = super().__new__(cls)
        env._init_args = (args, dict(kwargs))  # for pickling: rebuilt from the same arguments
        return env

    def __init__(
        self,
        scene: Scene,
        subspace: nn.Module,
        task: Task,
        *,
        render_mode: str | None = None,
        dt: float = 0.02,
        frame_skip: int = 1,
        dtype: str = "float32",
        device: str = "cpu",
        randomize_condition: bool = False,
        include_q: bool = False,
        reset_noise_scale: float = 0.0,
        width: int = 480,
        height: int = 480,
        camera: Mapping[str, float] | None = None,
        stepper_options: Mapping[str, Any] | None = None,
        cubature: bool | str | os.PathLike[str] | None = None,
        threads: int | None = 1,
    ) -> None:
        self.threads = check_threads(threads)
        """torch intra-op threads the env computes on (None: the caller's setting; :mod:`redsim.threads`)."""
        if render_mode not in (None, "rgb_array", "human"):
            raise ValueError(f"render_mode must be None, 'rgb_array' or 'human', got {render_mode!r}")
        if render_mode == "human" and (reason := human_unavailable()) is not None:
            error = ValueError if importlib.util.find_spec("pygame") else gym.error.DependencyNotInstalled
            raise error(f'render_mode="human" needs a window: {reason}')
        if render_mode == "human":
            open_display()  # here, not at the first frame: a display that shows nothing is refused as none is
        with torch_threads(self.threads):  # the rest solve, a task's settling
            self.sim = LatentSim(
                scene,
                subspace,
                task,
                batch=1,
                dt=dt,
                frame_skip=frame_skip,
                dtype=dtype,
                device=device,
                randomize_condition=randomize_condition,
                include_q=include_q,
                reset_noise_scale=reset_noise_scale,
                stepper_options={**self.stepper_defaults, **(stepper_options or {})},
                cubature=cubature,
            )
        self.task = task
        self.render_mode = render_mode
        self.dt = self.sim.dt  # [s] of an env step, as MuJoCo envs' dt
        self.frame_skip = self.sim.frame_skip  # stepper steps per env step (the stepper's dt = dt / frame_skip)
        modes = [m for m in RENDER_MODES if m != "human" or human_unavailable() is None]
        fps = 1.0 / self.dt  # frames per simulated second; a float where 1/dt is not whole (Gymnasium allows it)
        fps = int(fps) if fps.is_integer() else fps
        self.metadata = {**type(self).metadata, "render_modes": modes, "render_fps": fps}
        self.action_space = spaces.Box(-1.0, 1.0, (task.action_size,), np.float32)
        low, high = self.sim.observation_bounds()
        self.observation_space = spaces.Box(low, high, dtype=np.float32)
        self.observation_structure = self.sim.observation_structure()
        if not (np.isfinite(low).all() and np.isfinite(high).all()):
            raise ValueError("Task.extras_bounds must be finite (observation bounds, as Gymnasium users expect)")
        blocks, extras = task.observation_structure(), len(task.extras_bounds()[0])
        if sum(blocks.values()) != extras:
            raise ValueError(f"Task.observation_structure {blocks} does not add up to Task.extras_bounds' {extras}")
        self._render_size = _image_size(width, height)
        self._camera = {**self.camera, **_camera(camera)}
        self._view: Any = None
        self._window: Any = None
        self._display = render_mode == "human"  # pygame's display, started above; quit by close()
        self._reset_done = False

    @property
    def scene(self) -> Scene:
        return self.sim.scene

    # -- Gymnasium API --------------------------------------------------------------------
    @on_env_threads
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start at the rest state (z = the map's unloaded equilibrium, z_dot = 0; or where the task starts, plus
        ``reset_noise_scale`` noise) with a new task draw.

        ``options`` sets parts of the draw for this episode: the task's ``reset_options`` (e.g. ``{"target": [x, y,
        z]}``, see the env's "Starting State") and ``"condition"`` where it is drawn per episode; another key is a
        ValueError.
        """
        chosen = self.sim.episode_options(options)
        super().reset(seed=seed)
        self._reset_done = False  # until the draw succeeds (a task may refuse an option's value)
        self.sim.reset_rows([0], [self.np_random], chosen)
        self._reset_done = True
        if self._camera.get("track", False):
            self._view = None  # framed anew on this episode: a picture never depends on earlier episodes
        if self.render_mode == "human":
            self.render()
        return self.sim.observe()[0], _first_row(self.sim.state_info(start=True))

    @on_env_threads
    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """One env step (``frame_skip`` stepper steps) with the action held; entries outside the action space's
        [-1, 1] are clipped to it (as the loads the subspace was fitted for bound them).

        Raises:
            ValueError: a wrong action shape (both shapes are named) or non-finite entries.
        """
        if not self._reset_done:
            raise gym.error.ResetNeeded("call reset() before step()")
        act = check_action(action, self.action_space.shape)
        saved = self.sim.snapshot()  # atomic up to the return: an interrupt in the observation or the window too
        try:
            reward, terminated, info = self.sim.step(act[None])
            info_row = _first_row(info)
            obs = self.sim.observe()[0]
            if self.render_mode == "human":
                self.render()
        except BaseException:
            self.sim.restore(saved)
            raise
        return obs, float(reward[0]), bool(terminated[0]), False, info_row

    @on_env_threads
    def render(self) -> np.ndarray | None:
        """The current picture: an RGB array [H, W, 3] ("rgb_array"), or a window update ("human")."""
        if self.render_mode is None:
            gym.logger.warn(NO_RENDER_MODE)
            return None
        self._view = self.sim.framed_view(self._view, *self._render_size, self._camera, (0,))
        frame = self.sim.draw(self._view, 0)
        if self.render_mode == "rgb_array":
            return frame
        self._show(frame)
        return None

    def _show(self, frame: np.ndarray) -> None:
        import pygame  # present: checked with the render mode in __init__

        if self._window is None:
            open_display()  # again after close()
            self._display = True
            self._window = pygame.display.set_mode(frame.shape[1::-1])
            self._clock = pygame.time.Clock()
        pygame.event.pump()
        self._window.blit(pygame.surfarray.make_surface(frame.swapaxes(0, 1)), (0, 0))
        pygame.display.flip()
        self._clock.tick(self.metadata["render_fps"])

    def close(self) -> None:
        if self._display:
            import pygame

            pygame.display.quit()
            pygame.quit()
            self._window, self._display = None, False

    # -- state and export -----------------------------------------------------------------
    def get_state(self) -> dict[str, Any]:
        """The dynamic state (numpy copies): z, z_prev [d], cond [m] or None, task params, the solver's warm start,
        the last step's loads [H, D] [N] (a restored env draws the same force arrow), the setting it belongs to, and
        ``rng``, the state of the env's generator (``np_random``: what the next unseeded reset draws).

        Raises:
            gymnasium.error.ResetNeeded: before the first reset (or :meth:`set_state`): there is no episode yet.
        """
        if not self._reset_done:
            raise gym.error.ResetNeeded("call reset() (or set_state()) before get_state(): there is no episode yet")
        return {**state_row(self.sim.get_state()), "rng": self.np_random.bit_generator.state}

    @on_env_threads
    def set_state(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`get_state`'s state; the next step continues exactly from it, and with ``rng`` so does the
        next unseeded reset."""
        self.sim.set_state(_batch(state))
        if state.get("rng") is not None:
            self._np_random = restored_generator(self.np_random, state["rng"])
        self._reset_done = True
        if self._camera.get("track", False):
            self._view = None  # framed anew on the restored state, as after a reset

    @on_env_threads
    def configuration(self) -> np.ndarray:
        """The free configuration q [n] of the current state (float of the stepper's dtype)."""
        return self.sim.positions(self.sim.z)[0].detach().cpu().numpy()

    @on_env_threads
    def trimeshes(self) -> list[Any]:
        """The scene's surfaces at the current state as ``trimesh.Trimesh`` objects (2D scenes at z = 0; a vector
        env's ``call("trimeshes")`` gives each copy's: :meth:`LatentSim.trimeshes`)."""
        return self.sim.trimeshes(0)

    def __getstate__(self) -> dict[str, Any]:
        """The constructor arguments (the copy is rebuilt from them), the state, the spec and the generator; and
        the map itself where no checkpoint file backs it (:data:`redsim.envs.fitted.IN_MEMORY_ATTRIBUTE`): a
        rebuild would fit it again. A map loaded from a file (a shipped one) is not pickled: the copy loads it."""
        state = {"init": self._init_args, "sim": self.get_state() if self._reset_done else None, "spec": self.spec}
        state["rng"] = None if self._np_random is None else self._np_random.bit_generator.state
        state["seed"] = self._np_random_seed  # without it, reading np_random_seed would replace the generator
        state["subspace"] = self.unbacked_subspace()
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        args, kwargs = state["init"]
        self._init_args = (args, kwargs)
        carried = state.get("subspace")
        self.__init__(*args, **(kwargs if carried is None else with_fitted_map(kwargs, carried)))  # type: ignore[misc]
        self.spec = state["spec"]
        if state["rng"] is not None:
            self._np_random = restored_generator(None, state["rng"])
            self._np_random_seed = state["seed"]
        if state["sim"] is not None:
            self.set_state(state["sim"])

    def unbacked_subspace(self) -> nn.Module | None:
        """The map where it was fitted in memory (:data:`redsim.envs.fitted.IN_MEMORY_ATTRIBUTE`), the constructor
        arguments do not hold it (a rebuild from them would fit it again) and the constructor takes a ``subspace``,
        else None."""
        from redsim.envs.fitted import IN_MEMORY_ATTRIBUTE

        subspace = self.sim.subspace
        if not getattr(subspace, IN_MEMORY_ATTRIBUTE, False):
            return None
        args, kwargs = self._init_args
        if any(value is subspace for value in (*args, *kwargs.values())):
            return None  # pickled with the arguments already
        if "subspace" not in inspect.signature(type(self).__init__).parameters:
            return None  # an env class that cannot take it: rebuilt (and fitted) from its arguments
        return subspace


def check_numbers(
    positive: Mapping[str, Any],
    nonnegative: Mapping[str, Any] | None = None,
    optional: Mapping[str, Any] | None = None,
) -> None:
    """Check task arguments by name: ``positive`` finite and > 0, ``nonnegative`` finite and >= 0,
    ``optional`` None or finite and > 0 (:func:`redsim.scenes.toolkit.check_positive` for each).

    Raises:
        ValueError: naming the first bad argument and its value (a non-number included).
    """
    from redsim.scenes.toolkit import check_positive

    for key, value in positive.items():
        check_positive(key, value)
    for key, value in dict(nonnegative or {}).items():
        check_positive(key, value, allow_zero=True)
    for key, value in dict(optional or {}).items():
        if value is not None:
            check_positive(key, value)


def check_action(action: Any, shape: tuple[int, ...]) -> np.ndarray:
    """The action as float32 of ``shape``, clipped to [-1, 1] (checked and clipped in float64, so a finite
    value beyond float32's range is clipped too, not refused as infinite).

    A torch tensor (or a list or tuple of them) is taken as NumPy takes it: on the CPU and without grad (a
    policy's output that requires grad or lives on a GPU is refused, naming the fix, instead of torch's error from
    inside NumPy).

    Raises:
        ValueError: not an array of numbers (strings are refused, not parsed), a torch tensor that requires grad
            or is not on the CPU (alone or in a list or tuple), a wrong shape (both named) or non-finite entries.
    """
    why = _tensor_refusal(action)
    if why is not None:
        raise ValueError(
            f"action must be a NumPy array (actions are not differentiated through), got a torch tensor that {why}: "
            "pass action.detach().cpu().numpy()"
        )
    try:
        raw = np.asarray(action)
    except (TypeError, ValueError):
        raw = np.asarray(None)  # ragged nesting: refused below
    if raw.dtype.kind not in "biuf":
        raise ValueError(f"action must be an array of numbers, got {action!r:.80}")
    act = raw.astype(np.float64)
    if act.shape != tuple(shape):
        raise ValueError(f"action must have shape {tuple(shape)}, got {act.shape}")
    if not np.all(np.isfinite(act)):
        raise ValueError(f"action must be finite, got {act.tolist()}")
    return np.clip(act, -1.0, 1.0).astype(np.float32)


def _tensor_refusal(action: Any) -> str | None:
    """Why NumPy cannot take a torch tensor in ``action`` (itself, or nested in lists and tuples): it requires grad
    or is not on the CPU; None where there is none."""
    if isinstance(action, Tensor):
        if action.requires_grad:
            return "requires grad"
        return None if action.device.type == "cpu" else f"is on {action.device}"
    if isinstance(action, list | tuple):
        return next((why for why in map(_tensor_refusal, action) if why is not None), None)
    return None


def _chosen_param(key: str, value: Tensor, drawn: Tensor | None) -> Tensor:
    """A reset option's value in the shape, dtype and device of the parameter ``drawn`` it replaces."""
    if drawn is None:
        raise ValueError(f"Task.reset_options names {key!r}, which Task.sample does not return")
    if tuple(value.shape) != tuple(drawn.shape):
        raise ValueError(f"options[{key!r}] must have shape {list(drawn.shape)}, got {list(value.shape)}")
    if not drawn.is_floating_point() and not bool((value == value.round()).all()):
        raise ValueError(f"options[{key!r}] must be integral (the task's is {drawn.dtype}), got {value.tolist()}")
    return value.to(drawn.dtype).to(drawn.device)


def _first_row(info: dict[str, np.ndarray]) -> dict[str, Any]:
    """The single env's ``info`` from the batch of one: an entry [1] becomes a Python number, [1, ...] its row."""
    return {k: (v[0].item() if v.ndim == 1 else v[0]) for k, v in info.items()}


def _info_array(value: np.ndarray) -> np.ndarray:
    """A step's info value with the dtype Gymnasium's sync vector env gives it: an entry [B] is a Python number in
    the single env's info, so floats become float64 and integers int64 (bools, and arrays [B, ...], stay)."""
    if value.ndim != 1:
        return value
    kind = value.dtype.kind
    return value.astype(np.float64) if kind == "f" else value.astype(np.int64) if kind in "iu" else value


def _check_task_output(
    what: str,
    value: Any,
    batch: int,
    *,
    dtype: torch.dtype | None = None,
    finite: bool = True,
    valid: Tensor | None = None,
    width: int | None = None,
) -> None:
    """Refuse a task's step output that is not a tensor of shape [B] (with ``width`` k: [B, k]; of ``dtype``; finite
    where asked, in the ``valid`` copies [B] (bool): a diverged copy's state may not be): a bug in a user's task would
    otherwise be broadcast over the copies silently (one copy's reward for all).

    Raises:
        ValueError: naming the Task method and the shape it returned.
    """
    want, names = ((batch,), "[B]") if width is None else ((batch, width), "[B, k]")
    if not isinstance(value, Tensor) or tuple(value.shape) != want:
        shape = list(value.shape) if isinstance(value, Tensor) else type(value).__name__
        raise ValueError(f"Task {what} must be a torch tensor of shape {names} = {list(want)}, got {shape}")
    if dtype is not None and value.dtype != dtype:
        raise ValueError(f"Task {what} must be a {dtype} tensor, got {value.dtype}")
    checked = value if valid is None else value[valid]
    if finite and value.is_floating_point() and not bool(torch.isfinite(checked).all()):
        raise ValueError(f"Task {what} is not finite: {shown(value)}")


def _dtype_name(dtype: Any) -> str:
    """``dtype`` ("float32"/"float64", or the torch or NumPy dtype) as its name in :data:`DTYPES`; a ValueError
    otherwise."""
    name = str(dtype).removeprefix("torch.")
    if not isinstance(dtype, (str, torch.dtype)):
        try:
            name = np.dtype(dtype).name
        except TypeError:
            name = ""
    if name not in DTYPES:
        raise ValueError(f"dtype must be one of {sorted(DTYPES)} (or the torch/NumPy dtype), got {dtype!r}")
    return name


def shown(value: Tensor) -> Any:
    """``value`` as (nested) lists for an error message, each entry to 7 significant digits: a float32 0.2 reads 0.2,
    not 0.20000000298023224."""
    array = value.detach().cpu().to(torch.float64).numpy()
    return np.vectorize(lambda v: float(f"{v:.7g}"), otypes=[float])(array).tolist()


def json_spec(spec: EnvSpec | None) -> EnvSpec | None:
    """``spec`` with the env arguments given in a non-JSON form redsim accepts in their JSON one, so that
    ``spec.to_json()`` works and ``gym.make(spec)`` makes the same env: ``dtype`` by name (``torch.float64`` or
    ``np.float64`` as "float64"), a ``torch.device`` as its string, a path (``subspace``, ``cubature``) as a string
    (``cubature=Path("lean")`` as "./lean": "lean" names the shipped one, :data:`SHIPPED_CUBATURES`),
    a vector env's ``AutoresetMode`` as its value ("SameStep"), a NumPy scalar (``frame_skip=np.int64(2)``,
    ``camera={"azimuth": np.float32(30)}``) as the Python number or bool it holds. Other values are kept (a map given
    as ``subspace`` is not JSON: its spec cannot be)."""
    if spec is None:
        return None
    kwargs = {key: _python_scalars(value) for key, value in spec.kwargs.items()}
    if "dtype" in kwargs and not isinstance(kwargs["dtype"], str):
        kwargs["dtype"] = _dtype_name(kwargs["dtype"])
    if isinstance(kwargs.get("device"), torch.device):
        kwargs["device"] = str(kwargs["device"])
    if isinstance(kwargs.get("autoreset_mode"), AutoresetMode):
        kwargs["autoreset_mode"] = kwargs["autoreset_mode"].value
    for key in ("subspace", "cubature"):
        if isinstance(kwargs.get(key), os.PathLike):
            path = os.fspath(kwargs[key])  # Path("lean") stays a path: "./lean"
            kwargs[key] = os.path.join(os.curdir, path) if key == "cubature" and path in SHIPPED_CUBATURES else path
    return dataclasses.replace(spec, kwargs=kwargs)


def _python_scalars(value: Any) -> Any:
    """``value`` with each NumPy scalar in it (itself, or in a dict, list or tuple) as the Python scalar it holds."""
    if isinstance(value, np.generic):
        return value.item()
    if type(value) is dict:
        return {key: _python_scalars(item) for key, item in value.items()}
    if type(value) in (list, tuple):
        return type(value)(_python_scalars(item) for item in value)
    return value


def _image_size(width: Any, height: Any) -> tuple[int, int]:
    """(width, height) [px], checked here rather than at the first ``render()`` (8 to :data:`MAX_IMAGE_SIDE`)."""
    sizes = (width, height)
    if any(isinstance(v, bool) or not isinstance(v, numbers.Integral) or not 8 <= v <= MAX_IMAGE_SIDE for v in sizes):
        raise ValueError(f"width and height must be integers in [8, {MAX_IMAGE_SIDE}] [px], got {width!r} x {height!r}")
    return int(width), int(height)


def _camera(camera: Mapping[str, Any] | None) -> dict[str, Any]:
    """The ``camera`` settings, checked (:data:`CAMERA_KEYS`: finite numbers [deg], a margin and merge_px >= 0, track a
    bool)."""
    if camera is not None and not isinstance(camera, Mapping):
        raise ValueError(f"camera must be a dict of {list(CAMERA_KEYS)}, got {camera!r:.80}")
    camera = dict(camera or {})
    unknown = sorted(set(camera) - set(CAMERA_KEYS))
    if unknown:
        raise ValueError(f"unknown camera keys {unknown}; valid: {list(CAMERA_KEYS)}")
    if not isinstance(camera.get("track", False), bool | np.bool_):
        raise ValueError(f"camera['track'] must be True or False, got {camera['track']!r}")
    track = {"track": bool(camera.pop("track"))} if "track" in camera else {}
    for key, value in camera.items():
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
            raise ValueError(f"camera[{key!r}] must be a finite number, got {value!r}")
    if camera.get("margin", 0.0) < 0.0:
        raise ValueError(f"camera['margin'] must be >= 0 (a fraction of the frame), got {camera['margin']!r}")
    if camera.get("merge_px", 0.0) < 0.0:
        raise ValueError(f"camera['merge_px'] must be >= 0 [px], got {camera['merge_px']!r}")
    return {**{k: float(v) for k, v in camera.items()}, **track}


def copy_seeds(seed: int | Sequence[int | None] | None, count: int) -> tuple[int | None, list[Any] | None]:
    """A vector env's reset seed: (its own seed, or None; the seed of each of ``count`` copies, or None).

    An int (NumPy's too) seeds copy i with ``seed + i``; a sequence gives each copy its own (None: the copy keeps
    its generator, as Gymnasium's sync and async vector envs do).

    Raises:
        ValueError: not an int, None or a sequence of them, or a sequence of another length.
    """
    if isinstance(seed, np.ndarray) and seed.ndim == 0:
        seed = seed.item()
    if isinstance(seed, np.integer):
        seed = int(seed)
    if seed is None:
        return None, None
    if isinstance(seed, int) and not isinstance(seed, bool):
        return seed, [seed + i for i in range(count)]
    if isinstance(seed, (str, bytes)) or not isinstance(seed, Sequence | np.ndarray):
        raise ValueError(f"seed must be an int, None or a sequence of them (one per copy), got {seed!r:.80}")
    seeds = [int(s) if isinstance(s, np.integer) else s for s in seed]
    if len(seeds) != count:
        raise ValueError(f"need {count} seeds, got {len(seeds)}")
    return None, seeds


def restored_generator(generator: np.random.Generator | None, state: Mapping[str, Any]) -> np.random.Generator:
    """A NumPy generator in ``state`` (a ``bit_generator.state`` dict): ``generator`` set in place where its bit
    generator is of the kind ``state["bit_generator"]`` names, else a new one of that kind (PCG64, Philox, SFC64, ...:
    Gymnasium's ``np_random`` may be any ``Generator``).

    Raises:
        ValueError: ``state`` names no NumPy bit generator, or is not a state of the one it names.
    """
    name = state.get("bit_generator") if isinstance(state, Mapping) else None
    kind = getattr(np.random, str(name), None)
    if not (isinstance(kind, type) and issubclass(kind, np.random.BitGenerator)):
        raise ValueError(f"a generator state must name a NumPy bit generator in 'bit_generator', got {name!r}")
    fresh = np.random.Generator(kind())
    try:  # on a fresh generator first: a malformed state leaves ``generator`` as it was
        fresh.bit_generator.state = state
    except (KeyError, TypeError, ValueError) as error:
        raise ValueError(f"not a {name} generator state ({type(error).__name__}: {error})") from None
    if generator is None or type(generator.bit_generator) is not kind:
        return fresh
    generator.bit_generator.state = state
    return generator


def state_row(state: Mapping[str, Any], i: int = 0) -> dict[str, Any]:
    """Copy i's state (as a single env's ``get_state``) from a batched :meth:`LatentSim.get_state`."""
    return {
        "z": state["z"][i],
        "z_prev": state["z_prev"][i],
        "z_before": None if state.get("z_before") is None else state["z_before"][i],
        "model": state["model"][i],
        "carry": None if state.get("carry") is None else state["carry"][i],
        "loads": None if state.get("loads") is None else state["loads"][i],
        "cond": None if state["cond"] is None else state["cond"][i],
        "params": {k: v[i] for k, v in state["params"].items()},
        "setting": state.get("setting"),
    }


def _batch(state: Mapping[str, Any]) -> dict[str, Any]:
    def row(value: Any) -> Any:
        if value is None:
            return None
        try:
            return np.asarray(value)[None]
        except ValueError:  # ragged: the batched set_state refuses it, naming the key and the shape it needs
            return [value]

    missing = {"z", "z_prev", "cond", "params"} - set(state)
    if missing:
        raise ValueError(f"state is missing {sorted(missing)}")
    return {
        "z": row(state["z"]),
        "z_prev": row(state["z_prev"]),
        "z_before": row(state.get("z_before")),
        "model": row(state.get("model")),
        "carry": row(state.get("carry")),
        "loads": row(state.get("loads")),
        "cond": row(state["cond"]),
        # not a dict: as given, for the batched set_state to name
        "params": {k: row(v) for k, v in params.items()} if isinstance(params := state["params"], Mapping) else params,
        "setting": state.get("setting"),
    }


__all__ = [
    "LATENT_BOUND",
    "LATENT_ENV_ARGUMENTS",
    "LATENT_ENV_ROW",
    "MAX_FRAME_SKIP",
    "NO_HUMAN",
    "VECTOR_RENDER_MODES",
    "LatentEnv",
    "LatentSim",
    "Task",
    "check_action",
    "check_numbers",
    "check_subspace",
    "human_unavailable",
    "json_spec",
    "shipped",
]
