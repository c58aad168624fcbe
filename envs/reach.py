"""The reach task: push a handle of the scene to a target point with a bounded force.

Targets are handle positions of the subspace itself: at reset, z_target = z_rest + s * eps with
eps ~ N(0, I) from the env's generator (s = ``target_spread``), and the target is the goal
handle's position in f(z_target[, c]) along the goal axes. Every target is therefore a state the
map contains, at a distance the spread sets, whatever the scene. The action is a force on the
actuated handle along the force axes, ``max_force * action`` [N].

With ``targets="held"`` the targets are instead places a held action brings the goal handle to:
at bind, HELD_SAMPLES actions u ~ U[-s, s]^A (fixed seed 0) are each held on one copy of a batched
stepper with the env's own energy, SETTLE_STEPS implicit-Euler steps of SETTLE_DT (a strongly
damped walk to the static equilibrium under those loads), and the goal handle's positions there
form the table a reset draws from (``rng.integers``). Every such target is reachable by holding
an action no larger than s.

Reward per step, with d the distance [m] from the goal handle to the target along the goal axes
and L = ``distance_scale`` [m]:

    reward = -d / L  -  control_weight * mean(action^2)  +  success_bonus * [d < success_radius]

reported as ``reward_distance``, ``reward_control`` and ``reward_success``.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import torch
from torch import Tensor, nn

from redsim.envs.base import (
    FRAME_SAMPLES,
    LatentEnv,
    Task,
    cached,
    check_numbers,
    map_key,
    row_arguments,
    shipped,
    shown,
)

if TYPE_CHECKING:
    from redsim.envs.base import LatentSim

SCALE_SAMPLES = 64
"""Fixed latent samples (seed 0) that set the default distance scale of a reach task."""
HELD_SAMPLES = 256
"""Held actions (seed 0) whose static goal-handle positions are the targets of ``targets="held"``."""
SETTLE_DT = 1.0
"""Time step [s] of the settling steps that find those positions (implicit Euler: strongly damped)."""
SETTLE_STEPS = 20
"""Settling steps per held action (the hanging sheet moves < 3e-4 m in its 10th step)."""
TARGETS = ("latent", "held")
"""Target distributions of :class:`HandleReach` (module doc)."""
_held_cache: dict[tuple[Any, ...], tuple[Tensor, Tensor]] = {}
"""Held actions and targets settled in this process, by everything they depend on (:meth:`HandleReach._held_key`):
an identical env made again reuses them (HangingCloth-v1 settles for 3-10 s); a later process reads them from the user
cache (:func:`redsim.envs.base.cached`)."""


def _energy_key(energy: Any) -> tuple[str, ...] | None:
    """What a latent energy computes, by value: its class, its scene's content, and its map (every element) or its
    cubature's map and rules (indices and weights); None for an energy of another class (a user's own, whose state
    is not known), which the caller must not cache by."""
    from redsim.cubature.energy import CubatureEnergy
    from redsim.integrators.cache import scene_digest
    from redsim.runtime.energy import MapEnergy

    if type(energy) is MapEnergy and isinstance(energy.map, nn.Module):
        return ("MapEnergy", scene_digest(energy.scene), *map_key(energy.map))
    if type(energy) is CubatureEnergy:
        rules = hashlib.sha256()
        for rule in energy.cubature.rules:
            rules.update(f"{rule.name}:{rule.mode}:".encode())
            rules.update(rule.indices.detach().cpu().to(torch.int64).numpy().tobytes())
            rules.update(rule.weights.detach().cpu().to(torch.float64).numpy().tobytes())
        return (
            "CubatureEnergy",
            scene_digest(energy.scene),
            energy.cubature.map_fingerprint,
            rules.hexdigest(),
            str(energy.slice_all),
        )
    return None


class HandleReach(Task):
    """Bring handle ``goal_handle`` to a target with a force on handle ``actuated`` (module doc).

    Args:
        goal_handle: Handle whose position must reach the target.
        max_force: Force [N] of a unit action on each force axis.
        actuated: Handle the force acts on (default: the goal handle).
        force_axes: Spatial axes of the force (default: all D).
        goal_axes: Spatial axes the distance is measured along (default: all D).
        target_spread: s, the latent spread of targets around the rest state (``targets="latent"``), or the
            largest |entry| of the held actions that set them (``"held"``).
        targets: ``"latent"``: handle positions of latent samples; ``"held"``: where held actions bring the
            handle (module doc).
        distance_scale: L [m] of the reward (default: the RMS target distance over
            SCALE_SAMPLES fixed targets).
        success_radius: Distance [m] under which the task counts as done (default 0.2 L).
        control_weight: Weight of the control cost.
        success_bonus: Reward per step spent within the success radius.
        controller_gain: Scripted controller gain [N/m] (default ``max_force / L``).
        controller_time: Scripted controller integral time [s].

    Raises:
        ValueError: an unknown handle, axis or target distribution, a bad number, or (at bind) held targets
            with a condition drawn per episode.
    """

    name = "reach"
    reward_terms = ("distance", "control", "success")
    reset_options = ("target",)

    def __init__(
        self,
        goal_handle: str,
        *,
        max_force: float,
        actuated: str | None = None,
        force_axes: Sequence[int] | None = None,
        goal_axes: Sequence[int] | None = None,
        target_spread: float = 0.5,
        distance_scale: float | None = None,
        success_radius: float | None = None,
        control_weight: float = 0.05,
        success_bonus: float = 1.0,
        controller_gain: float | None = None,
        controller_time: float = 0.5,
        targets: str = "latent",
    ) -> None:
        if targets not in TARGETS:
            raise ValueError(f"targets must be one of {list(TARGETS)}, got {targets!r}")
        check_numbers(
            {"max_force": max_force, "target_spread": target_spread, "controller_time": controller_time},
            {"control_weight": control_weight, "success_bonus": success_bonus},
            {"distance_scale": distance_scale, "success_radius": success_radius, "controller_gain": controller_gain},
        )
        self.goal_handle = goal_handle
        self.actuated = goal_handle if actuated is None else actuated
        self.max_force = float(max_force)
        self._force_axes = None if force_axes is None else tuple(int(a) for a in force_axes)
        self._goal_axes = None if goal_axes is None else tuple(int(a) for a in goal_axes)
        self.target_spread = float(target_spread)
        self.targets = targets
        self._distance_scale = distance_scale
        self._success_radius = success_radius
        self.control_weight = float(control_weight)
        self.success_bonus = float(success_bonus)
        self._gain = controller_gain
        self.controller_time = float(controller_time)
        self.action_size = 0 if self._force_axes is None else len(self._force_axes)

    # -- binding --------------------------------------------------------------------------
    def bind(self, sim: LatentSim) -> None:
        scene = sim.scene
        names = list(scene.handle_names)
        for handle in (self.goal_handle, self.actuated):
            if handle not in names:
                raise ValueError(f"scene {scene.name!r} has no handle {handle!r}; valid handles: {names}")
        D = scene.dim
        self.force_axes = tuple(range(D)) if self._force_axes is None else self._force_axes
        self.goal_axes = tuple(range(D)) if self._goal_axes is None else self._goal_axes
        for what, axes in (("force_axes", self.force_axes), ("goal_axes", self.goal_axes)):
            if not axes or len(set(axes)) != len(axes) or any(not 0 <= a < D for a in axes):
                raise ValueError(f"{what} must be distinct axes in [0, {D}), got {list(axes)}")
        self.action_size = len(self.force_axes)
        self._goal = scene.handles[names.index(self.goal_handle)]
        self._actuated_index = names.index(self.actuated)
        self._goal_index = torch.tensor(self.goal_axes, device=sim.device)
        self._force_index = torch.tensor(self.force_axes, device=sim.device)
        self._handles = len(names)
        self._dim = D
        rest_x = sim.full_positions(sim._rest_latent(sim.default_cond).unsqueeze(0), sim.default_cond)
        self._rest_goal = self._goal.position(rest_x)[0, self._goal_index]
        self.held_actions, self.held_targets = self._held(sim) if self.targets == "held" else (None, None)
        if self._distance_scale is None:
            if self.held_targets is None:
                generator = torch.Generator().manual_seed(0)
                eps = torch.randn(SCALE_SAMPLES, sim.latent_dim, generator=generator, dtype=torch.float32).to(
                    sim.device, sim.torch_dtype
                )
                z = sim._rest_latent(sim.default_cond).unsqueeze(0) + self.target_spread * eps
                cond = None if sim.default_cond is None else sim.default_cond.expand(SCALE_SAMPLES, -1)
                targets = self._goal.position(sim.full_positions(z, cond))[:, self._goal_index]
            else:
                targets = self.held_targets
            rms = float((targets - self._rest_goal).pow(2).sum(-1).mean().sqrt())
            bound = float(self._rest_goal.abs().max()) + 2.0 * scene.extent()
            if not rms <= bound:  # NaN too: a latent spread far outside the map's range
                raise ValueError(
                    f"target_spread {self.target_spread:g} puts targets {rms:.3g} m from rest (RMS), beyond the "
                    f"observation bound {bound:.3g} m: give a smaller target_spread (the map is fitted on z ~ N(0, I))"
                )
            self.distance_scale = rms if rms > 0.0 else scene.extent()
        else:
            self.distance_scale = float(self._distance_scale)
        self.success_radius = 0.2 * self.distance_scale if self._success_radius is None else self._success_radius
        self.gain = self.max_force / self.distance_scale if self._gain is None else self._gain
        extent = scene.extent()
        self._bound = float(self._rest_goal.abs().max()) + 2.0 * extent

    def _held(self, sim: LatentSim) -> tuple[Tensor, Tensor]:
        """Held actions [HELD_SAMPLES, A] and the goal handle's positions [HELD_SAMPLES, k] [m] at rest under them
        (module doc), settled once per process for each :meth:`_held_key` and kept on disk for the next process
        (:func:`redsim.envs.base.cached`)."""
        if sim.randomize_condition:
            raise ValueError("targets='held' needs one condition for all episodes (randomize_condition is on)")
        shapes = (HELD_SAMPLES, self.action_size), (HELD_SAMPLES, len(self.goal_axes))

        def check(value: Any) -> str:
            got = tuple(tuple(item.shape) for item in value)
            return "" if got == shapes else f"shapes {got}, expected {shapes}"

        key = self._held_key(sim)
        if key is None:  # an energy of the user's own: what it computes is not known by value, so nothing is kept
            held, targets = self._settle(sim)
        else:
            held, targets = cached(_held_cache, key, lambda: self._settle(sim), disk="held targets", check=check)
        return held.clone(), targets.clone()

    def _held_key(self, sim: LatentSim) -> tuple[Any, ...] | None:
        """What the held targets depend on: the scene's content, the map's weights, the energy stepped
        (:func:`_energy_key`), dtype, device, the settling's constants and start (the rest latent) and this task's
        force, spread and handles; None for an energy that is not redsim's own (``stepper_options["energy"]``)."""
        from redsim.integrators.cache import scene_digest

        energy = _energy_key(sim.stepper.energy)
        if energy is None:
            return None
        return (
            scene_digest(sim.source_scene),
            map_key(sim.subspace),
            *energy,
            str(sim.torch_dtype),
            str(sim.device),
            self.target_spread,
            self.max_force,
            self.goal_handle,
            self.actuated,
            self._force_axes,
            self._goal_axes,
            HELD_SAMPLES,
            SETTLE_DT,
            SETTLE_STEPS,
            tuple(sim._rest_latent(sim.default_cond).tolist()),  # where the settling starts
        )

    def _settle(self, sim: LatentSim) -> tuple[Tensor, Tensor]:
        """The held actions and where the goal handle comes to rest under each (the work :meth:`_held` caches)."""
        from redsim.runtime import LatentStepper

        generator = torch.Generator().manual_seed(0)
        # float32 whatever torch's default dtype: the table must not depend on it (it is cached by _held_key)
        uniform = torch.rand(HELD_SAMPLES, self.action_size, generator=generator, dtype=torch.float32)
        held = self.target_spread * (2.0 * uniform - 1.0)
        loads = self.loads(held.to(sim.device, sim.torch_dtype), {})
        stepper = LatentStepper(
            sim.source_scene,
            sim.subspace,
            SETTLE_DT,
            dtype=sim.torch_dtype,
            device=sim.device,
            energy=sim.stepper.energy,
        )
        cond = None if sim.default_cond is None else sim.default_cond.expand(HELD_SAMPLES, -1)
        z = sim._rest_latent(sim.default_cond).expand(HELD_SAMPLES, -1).clone()
        z_prev, model = z.clone(), None
        for _ in range(SETTLE_STEPS):
            z_next, stats = stepper.step(z, z_prev, loads, cond, warm=model)
            if bool(stats.diverged.any()):
                raise ValueError(f"a held action of at most {self.target_spread} diverged while settling")
            z_prev, z, model = z, z_next.detach(), stats.model
        return held, self._goal_position(sim.full_positions(z, cond)).detach()

    # -- episodes -------------------------------------------------------------------------
    def sample(
        self, rng: np.random.Generator, sim: LatentSim, z_rest: Tensor, cond: Tensor | None
    ) -> dict[str, Tensor]:
        if self.held_targets is not None:
            return {"target": self.held_targets[int(rng.integers(HELD_SAMPLES))].clone()}
        eps = torch.as_tensor(rng.standard_normal(sim.latent_dim), dtype=sim.torch_dtype, device=sim.device)
        z = (z_rest + self.target_spread * eps).unsqueeze(0)
        target = self._goal.position(sim.full_positions(z, cond))[0, self._goal_index]
        return {"target": target}

    def frame_points(self, sim: LatentSim) -> np.ndarray:
        """Where targets come from, [P, D] [m]. Held targets: the goal handle's settled positions (the whole table a
        reset draws from), at the rest position along the other axes. Latent targets: the shapes of FRAME_SAMPLES
        fixed draws z_rest + s eps (seed 0) and their goal handle positions, under every condition the camera
        frames (:meth:`LatentSim.frame_conditions`); a draw beyond them all (rare) is clipped at the border."""
        rest_x = sim.full_positions(sim._rest_latent(sim.default_cond).unsqueeze(0), sim.default_cond)
        if self.held_targets is not None:
            points = self._goal.position(rest_x).expand(len(self.held_targets), -1).clone()
            points[:, self._goal_index] = self.held_targets
            return points.detach().cpu().to(torch.float64).numpy()
        generator = torch.Generator().manual_seed(0)
        eps = torch.randn(FRAME_SAMPLES, sim.latent_dim, generator=generator, dtype=torch.float32).to(
            sim.device, sim.torch_dtype
        )
        out = []
        for cond, rest in sim.frame_rests():
            z = rest.unsqueeze(0) + self.target_spread * eps
            conds = None if cond is None else cond.expand(FRAME_SAMPLES, -1)
            goal = self._goal.position(sim.full_positions(z, conds)).detach().cpu().to(torch.float64).numpy()
            out += [sim.surface_points(z, conds), goal]
        return np.concatenate(out)

    def loads(self, action: Tensor, params: Mapping[str, Tensor]) -> Tensor:
        loads = torch.zeros(action.shape[0], self._handles, self._dim, dtype=action.dtype, device=action.device)
        loads[:, self._actuated_index, self._force_index] = self.max_force * action
        return loads

    def _goal_position(self, x: Tensor) -> Tensor:
        return self._goal.position(x)[:, self._goal_index]

    def check_options(self, chosen: Mapping[str, Tensor]) -> None:
        if "target" in chosen and tuple(chosen["target"].shape) != (len(self._goal_index),):
            raise ValueError(
                f"options['target'] must have shape [{len(self._goal_index)}], got {list(chosen['target'].shape)}"
            )
        if "target" in chosen and not bool((chosen["target"].abs() <= self._bound).all()):
            raise ValueError(
                f"options['target'] must lie within the observation bound of {self._bound:.3g} m on each axis, "
                f"got {shown(chosen['target'])}"
            )

    def extras_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        k = len(self.goal_axes)
        high = np.full(2 * k, self._bound)
        return -high, high

    def observation_structure(self) -> dict[str, int]:
        k = len(self.goal_axes)
        return {"handle_position": k, "target_offset": k}

    def extras(self, x: Tensor, x_prev: Tensor, params: Mapping[str, Tensor]) -> Tensor:
        p = self._goal_position(x)
        return torch.cat([p, params["target"] - p], dim=1)

    def _distance(self, x: Tensor, params: Mapping[str, Tensor]) -> Tensor:
        return (self._goal_position(x) - params["target"]).norm(dim=1)

    def reward(self, x: Tensor, action: Tensor, params: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]]:
        distance = self._distance(x, params)
        terms = {
            "distance": -distance / self.distance_scale,
            "control": -self.control_weight * action.pow(2).mean(dim=1),
            "success": self.success_bonus * (distance < self.success_radius).to(distance.dtype),
        }
        return terms["distance"] + terms["control"] + terms["success"], terms

    def metrics(self, x: Tensor, params: Mapping[str, Tensor]) -> dict[str, Tensor]:
        distance = self._distance(x, params)
        return {"distance": distance, "is_success": distance < self.success_radius}

    # -- scripted control and drawing -----------------------------------------------------
    def controller(self, sim: LatentSim) -> np.ndarray:
        """A PI controller on the goal handle, in velocity form (its state is the load last applied).

        F_t = F_{t-1} + k dt / T e_t + k (e_t - e_{t-1}) along the force axes, clipped to ``max_force``,
        with e the offset to the target, k = ``controller_gain`` and T = ``controller_time``.
        """
        p, p_prev = self._goal.position(sim.x), self._goal.position(sim.x_prev)
        error = torch.zeros_like(p)
        error[:, self._goal_index] = sim.params["target"] - p[:, self._goal_index]
        change = torch.zeros_like(p)
        change[:, self._goal_index] = (p_prev - p)[:, self._goal_index]
        force = sim.loads[:, self._actuated_index] + self.gain * (sim.dt / self.controller_time * error + change)
        action = force[:, self._force_index] / self.max_force
        return action.clamp(-1.0, 1.0).cpu().numpy().astype(np.float32)

    def overlay(self, sim: LatentSim, row: int) -> tuple[list[Any], list[Any]]:
        """The target as a ring of the success radius [m] (a sphere's outline; with fewer goal axes than the scene
        has, the success region is a cylinder or slab through it), a ring on the goal handle, the force arrow."""
        from redsim.raster import HANDLE_RGB, TARGET_RGB, Arrow, Marker

        x = sim.x[row : row + 1]
        goal = self._goal.position(x)[0].clone()
        target = goal.clone()
        if "target" in sim.params:
            target[self._goal_index] = sim.params["target"][row]
        pushed = sim.scene.handles[self._actuated_index].position(x)[0]
        force = sim.loads[row, self._actuated_index]
        scale = 0.25 * sim.scene.extent() / self.max_force
        return (
            # the target last, so that the goal handle's ring does not hide it as the handle comes near
            [Marker(goal.cpu().numpy(), HANDLE_RGB), Marker(target.cpu().numpy(), TARGET_RGB, self.success_radius)],
            [Arrow(pushed.cpu().numpy(), force.cpu().numpy(), scale)],
        )


_HERE = ":class:`redsim.envs.reach.ReachEnv`"
"""How a reach env's docstring points at :class:`ReachEnv`'s sections (replaced by them, ``__init_subclass__``)."""


def _doc_section(doc: str, name: str) -> str:
    """The lines under ``## name`` in a class docstring, up to the next section."""
    start = doc.index(f"## {name}\n") + len(f"## {name}\n")
    end = doc.find("\n    ## ", start)
    return doc[start : len(doc) if end < 0 else end].rstrip()


class ReachEnv(LatentEnv):
    """A catalog scene in its shipped subspace with a :class:`HandleReach` task: the base of the registered ids.

    A subclass names its scene, goal handle, force and goal axes, default force and target spread,
    and camera (class attributes); everything else is shared.

    ## Rewards
    `reward = -d / L_d - 0.05 mean(action^2) + 1[d < r]` with d the distance [m] from the goal handle to the
    target along the goal axes, L_d the RMS distance of targets from the rest position and r = 0.2 L_d,
    reported as `info["reward_distance"]`, `info["reward_control"]` and `info["reward_success"]`.

    ## Arguments
    | Argument | Default | Meaning |
    |---|---|---|
    | `render_mode` | None | None, "rgb_array" or "human" |
    | `max_force` | the env's | force [N] of a unit action |
    | `target_spread` | the env's | latent spread s of the targets (held targets: largest held action entry) |
    | `targets` | the env's | "latent" or "held" (:class:`HandleReach`) |
    | `dt` | 0.02 | stepper time step [s] |
    | `frame_skip` | 1 | stepper steps per env step, 1 to 1000 (`MAX_FRAME_SKIP`) |
    | `subspace` | None | the shipped map, a checkpoint path or a map |
    | `scene_params` | None | scene build parameters (a shipped map covers only the defaults) |
    | `fit_if_missing` | False | fit a map for `scene_params` no shipped map covers into the user cache |
    | `fit_options` | None | FitConfig fields over the shipped map's fit options for that fit |
    | `include_q` | False | put q [n] in `info["q"]` |
    | `reset_noise_scale` | 0.0 | s: start at z0 + U(-s, s) with z_dot s N(0, 1) per latent (MuJoCo's convention) |
    | `**kwargs` | | the other :class:`LatentEnv` arguments (`LATENT_ENV_ARGUMENTS`) |
    """

    scene_name: ClassVar[str]
    goal_handle: ClassVar[str]
    default_max_force: ClassVar[float]
    default_target_spread: ClassVar[float] = 0.5
    default_targets: ClassVar[str] = "latent"
    force_axes: ClassVar[tuple[int, ...] | None] = None
    goal_axes: ClassVar[tuple[int, ...] | None] = None
    camera: ClassVar[dict[str, float]] = {}
    randomize_condition: ClassVar[bool] = False
    task_class: ClassVar[type[HandleReach]] = HandleReach

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """Write this class's Rewards formula and Arguments table into a subclass's docstring where it points here:
        ``help(env.unwrapped)`` shows the env's own docstring, not its base's."""
        super().__init_subclass__(**kwargs)
        doc, shared = cls.__doc__ or "", ReachEnv.__doc__ or ""
        formula, arguments = _doc_section(shared, "Rewards"), _doc_section(shared, "Arguments")
        own = {name for line in doc.splitlines() for name in row_arguments(line)}  # rows the env's own table gives
        arguments = "\n".join(line for line in arguments.splitlines() if not own & set(row_arguments(line)))
        doc = doc.replace(f"\n    (formula: {_HERE}).", f":\n{formula}")
        cls.__doc__ = doc.replace(f"As {_HERE}; ", f"{arguments.lstrip()}\n\n    In this env, ")

    def __init__(
        self,
        render_mode: str | None = None,
        *,
        max_force: float | None = None,
        target_spread: float | None = None,
        targets: str | None = None,
        dt: float = 0.02,
        frame_skip: int = 1,
        subspace: str | nn.Module | None = None,
        scene_params: dict[str, Any] | None = None,
        fit_if_missing: bool = False,
        fit_options: dict[str, Any] | None = None,
        include_q: bool = False,
        cubature: bool | str | None = None,
        **kwargs: Any,
    ) -> None:
        scene, sub = shipped(
            self.scene_name, scene_params, subspace, fit_if_missing=fit_if_missing, fit_options=fit_options
        )
        task = self.task_class(
            self.goal_handle,
            max_force=self.default_max_force if max_force is None else max_force,
            target_spread=self.default_target_spread if target_spread is None else target_spread,
            targets=self.default_targets if targets is None else targets,
            force_axes=self.force_axes,
            goal_axes=self.goal_axes,
        )
        kwargs.setdefault("randomize_condition", self.randomize_condition)
        super().__init__(
            scene,
            sub,
            task,
            render_mode=render_mode,
            dt=dt,
            frame_skip=frame_skip,
            include_q=include_q,
            cubature=cubature,
            **kwargs,
        )


__all__ = ["HandleReach", "ReachEnv"]
