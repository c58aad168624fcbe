"""`RedSim/Klann-v0`: turn the Klann leg's crank at a commanded speed with a bounded crank torque.

The crank angle theta [rad] is the angle of the crank pin about the crank-ground joint in the
x-y plane (counter-clockwise positive); the crank speed omega [rad/s] is its wrapped change
over one env step divided by the env's dt. The action is a tangential force on the crank pin,
``max_force * action`` [N] (a crank torque of ``max_force * r`` [N m], r = 0.05 m the crank
radius), perpendicular to the crank at the state the step starts from.

Reward per step, with omega* the commanded speed of the episode and W = ``speed_scale``:

    reward = -|omega - omega*| / W  -  control_weight * action^2  +  success_bonus * [|omega - omega*| < tol omega*]

reported as ``reward_speed``, ``reward_control`` and ``reward_success``.

Success (``info["is_success"]``) is judged over a window, not one step: the crank speed swings
over each turn (the leg's gravity hump), so "within the tolerance at the last step" is a coin
flip even for a good tracker. A step succeeds when the speed was within the tolerance on at
least ``hold_fraction`` of the last ``hold_steps`` env steps (default: half of the last 100
steps, 2 s, more than one full turn at every commanded speed); steps before the episode's
first count as misses. The window rides in the episode's parameters (``params["held"]``,
[B, hold_steps], newest first), written once per step by :meth:`CrankSpeed.reward`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import torch
from torch import Tensor, nn

from redsim.envs.base import LatentEnv, Task, check_numbers, shipped, shown
from redsim.envs.vector import vector_entry

if TYPE_CHECKING:
    from redsim.envs.base import LatentSim


PIN_RGB = (220, 40, 40)
"""Colour of the ring on the crank pin (where the force acts; the pivot's ring is :data:`redsim.raster.HANDLE_RGB`)."""
MAX_HOLD_STEPS = 10_000
"""Longest success window [env steps] (200 s at the default dt; each copy stores one speed per step of it)."""


class CrankSpeed(Task):
    """Track a commanded crank speed with a tangential force on a crank handle (module doc).

    Args:
        handle: The crank pin's handle.
        pivot: (x, y) [m] of the fixed joint the crank turns about.
        max_force: Tangential force [N] of a unit action.
        speed_range: (low, high) [rad/s] of the commanded speed, drawn uniformly per episode.
        speed_scale: W [rad/s] of the reward (default: the top of ``speed_range``).
        tolerance: Relative speed error under which a step counts as a success.
        control_weight: Weight of the control cost.
        success_bonus: Reward per step within the tolerance.
        controller_gain: Scripted PI controller's gain [N s/rad].
        controller_time: Scripted PI controller's integral time [s].
        hold_steps: Length K [env steps] of the success window (module doc).
        hold_fraction: Fraction of the window's steps within the tolerance that makes a success.

    Raises:
        ValueError: a bad number or range, or (at bind) an unknown handle or a ``speed_range`` whose top is not
            below pi / dt, the fastest speed one env step of dt [s] measures (dt x frame_skip above 0.26 s at the
            default range).
    """

    name = "crank_speed"
    reward_terms = ("speed", "control", "success")
    reset_options = ("speed",)
    action_size = 1

    def __init__(
        self,
        handle: str,
        pivot: tuple[float, float],
        *,
        max_force: float,
        speed_range: tuple[float, float] = (4.0, 12.0),
        speed_scale: float | None = None,
        tolerance: float = 0.2,
        control_weight: float = 0.05,
        success_bonus: float = 0.5,
        controller_gain: float = 2.0,
        controller_time: float = 0.2,
        hold_steps: int = 100,
        hold_fraction: float = 0.5,
    ) -> None:
        pair = np.asarray(speed_range) if not isinstance(speed_range, (str, bytes)) else np.asarray(None)
        if pair.shape != (2,) or pair.dtype.kind not in "iuf":
            raise ValueError(f"speed_range must be a (low, high) pair of numbers [rad/s], got {speed_range!r}")
        low, high = float(pair[0]), float(pair[1])
        if not (np.isfinite(low) and np.isfinite(high) and 0.0 < low <= high):
            raise ValueError(f"speed_range must be finite with 0 < low <= high, got {speed_range!r}")
        check_numbers(
            {
                "max_force": max_force,
                "tolerance": tolerance,
                "controller_gain": controller_gain,
                "controller_time": controller_time,
                "hold_fraction": hold_fraction,
            },
            {"control_weight": control_weight, "success_bonus": success_bonus},
            {"speed_scale": speed_scale},
        )
        if isinstance(hold_steps, bool) or not isinstance(hold_steps, (int, np.integer)) or hold_steps < 1:
            raise ValueError(f"hold_steps must be an integer >= 1, got {hold_steps!r}")
        if hold_steps > MAX_HOLD_STEPS:  # each copy keeps a window of that many speeds
            raise ValueError(f"hold_steps must be <= {MAX_HOLD_STEPS} (a window no episode reaches), got {hold_steps}")
        if hold_fraction > 1.0:
            raise ValueError(f"hold_fraction must be in (0, 1], got {hold_fraction!r}")
        self.handle = handle
        self.pivot = (float(pivot[0]), float(pivot[1]))
        self.max_force = float(max_force)
        self.speed_range = (low, high)
        self.speed_scale = high if speed_scale is None else float(speed_scale)
        self.tolerance = float(tolerance)
        self.control_weight = float(control_weight)
        self.success_bonus = float(success_bonus)
        self.gain = float(controller_gain)
        self.controller_time = float(controller_time)
        self.hold_steps = int(hold_steps)
        self.hold_fraction = float(hold_fraction)

    def __getstate__(self) -> dict[str, Any]:
        # The bound sim is not part of the task: a copy (the vector env's) is bound to its own sim.
        return {k: v for k, v in self.__dict__.items() if k != "_sim"}

    # -- binding --------------------------------------------------------------------------
    def bind(self, sim: LatentSim) -> None:
        names = list(sim.scene.handle_names)
        if self.handle not in names:
            raise ValueError(f"scene {sim.scene.name!r} has no handle {self.handle!r}; valid handles: {names}")
        self._sim = sim
        self._index = names.index(self.handle)
        self._pin = sim.scene.handles[self._index]
        self._handles = len(names)
        self._dim = sim.scene.dim
        self._pivot = torch.tensor(self.pivot, dtype=sim.torch_dtype, device=sim.device)
        self._max_speed = math.pi / sim.dt
        if self.speed_range[1] >= self._max_speed:  # a commanded speed the observation and reward cannot tell
            raise ValueError(
                f"speed_range's top {self.speed_range[1]:g} rad/s must be below pi/dt = {self._max_speed:.3g} rad/s, "
                f"the fastest crank speed one env step of {sim.dt:g} s (dt x frame_skip) measures (a crank turning "
                "faster reads as a slower or backward one): lower dt or frame_skip, or the speed_range"
            )

    def _arm(self, x: Tensor) -> Tensor:
        """Crank vector [B, 2] [m] from the pivot to the pin."""
        return self._pin.position(x)[:, :2] - self._pivot

    def angle(self, x: Tensor) -> Tensor:
        """Crank angle theta [B] [rad] in (-pi, pi]."""
        arm = self._arm(x)
        return torch.atan2(arm[:, 1], arm[:, 0])

    def speed(self, x: Tensor, x_prev: Tensor) -> Tensor:
        """Crank speed omega [B] [rad/s] over one env step."""
        turn = torch.remainder(self.angle(x) - self.angle(x_prev) + math.pi, 2.0 * math.pi) - math.pi
        return turn / self._sim.dt

    # -- episodes -------------------------------------------------------------------------
    def sample(
        self, rng: np.random.Generator, sim: LatentSim, z_rest: Tensor, cond: Tensor | None
    ) -> dict[str, Tensor]:
        low, high = self.speed_range
        speed = torch.tensor(low + (high - low) * rng.random(), dtype=sim.torch_dtype, device=sim.device)
        zero = torch.zeros((), dtype=sim.torch_dtype, device=sim.device)
        held = torch.zeros(self.hold_steps, dtype=sim.torch_dtype, device=sim.device)
        return {"speed": speed, "integral": zero, "held": held}

    def loads(self, action: Tensor, params: Mapping[str, Tensor]) -> Tensor:
        arm = self._arm(self._sim.x).to(action.dtype)
        tangent = torch.stack([-arm[:, 1], arm[:, 0]], dim=1) / arm.norm(dim=1, keepdim=True)
        loads = torch.zeros(action.shape[0], self._handles, self._dim, dtype=action.dtype, device=action.device)
        loads[:, self._index, :2] = self.max_force * action[:, :1] * tangent
        return loads

    def check_options(self, chosen: Mapping[str, Tensor]) -> None:
        # above 0: the tolerance is relative (tol * omega*), so a command of 0 has no step within it, never a success
        if "speed" in chosen and not 0.0 < float(chosen["speed"].reshape(-1)[0]) <= self.speed_range[1]:
            raise ValueError(
                f"options['speed'] must lie in (0, {self.speed_range[1]:g}] rad/s (the observation's range; the "
                f"success tolerance is a fraction of it), got {shown(chosen['speed'])}"
            )

    def extras_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        high = np.array([1.0, 1.0, self._max_speed, self.speed_range[1]])
        return np.array([-1.0, -1.0, -self._max_speed, 0.0]), high

    def observation_structure(self) -> dict[str, int]:
        return {"crank_cos": 1, "crank_sin": 1, "crank_speed": 1, "commanded_speed": 1}

    def extras(self, x: Tensor, x_prev: Tensor, params: Mapping[str, Tensor]) -> Tensor:
        theta = self.angle(x)
        return torch.stack([theta.cos(), theta.sin(), self.speed(x, x_prev), params["speed"]], dim=1)

    def _error(self, x: Tensor, params: Mapping[str, Tensor]) -> Tensor:
        return self.speed(x, self._sim.x_prev) - params["speed"]

    def reward(self, x: Tensor, action: Tensor, params: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]]:
        """Reward [B] and its terms; also pushes this step's in-tolerance flag into ``params["held"]``."""
        error = self._error(x, params).abs()
        within = (error < self.tolerance * params["speed"]).to(error.dtype)
        held = params["held"]
        held.copy_(torch.roll(held, 1, dims=1))
        held[:, 0] = within.to(held.dtype)
        terms = {
            "speed": -error / self.speed_scale,
            "control": -self.control_weight * action.pow(2).mean(dim=1),
            "success": self.success_bonus * within,
        }
        return terms["speed"] + terms["control"] + terms["success"], terms

    def metrics(self, x: Tensor, params: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """``speed_within``: this step within the tolerance; ``held_fraction``: of the window; ``is_success``."""
        error = self._error(x, params)
        held = params["held"].mean(dim=1)
        return {
            "crank_angle": self.angle(x),
            "crank_speed": error + params["speed"],
            "speed_error": error,
            "speed_within": error.abs() < self.tolerance * params["speed"],
            "held_fraction": held,
            "is_success": held >= self.hold_fraction,
        }

    # -- scripted control and drawing -----------------------------------------------------
    def controller(self, sim: LatentSim) -> np.ndarray:
        """A PI controller on the crank speed: F = k (e + I / T), I += e dt, e = omega* - omega.

        Its integral I [rad] (the angle the crank lags the command by) rides in the episode's
        parameters (``params["integral"]``), so it restarts with every episode.
        """
        error = sim.params["speed"] - self.speed(sim.x, sim.x_prev)
        sim.params["integral"] = sim.params["integral"] + error * sim.dt
        force = self.gain * (error + sim.params["integral"] / self.controller_time)
        action = (force / self.max_force).clamp(-1.0, 1.0)
        return action.unsqueeze(1).cpu().numpy().astype(np.float32)

    def overlay(self, sim: LatentSim, row: int) -> tuple[list[Any], list[Any]]:
        from redsim.raster import HANDLE_RGB, Arrow, Marker

        x = sim.x[row : row + 1]
        pin = self._pin.position(x)[0].cpu().numpy()
        pivot = np.array([*self.pivot, float(pin[2])])
        force = sim.loads[row, self._index].cpu().numpy()
        scale = 0.25 * sim.scene.extent() / self.max_force
        return [Marker(pivot, HANDLE_RGB), Marker(pin, PIN_RGB)], [Arrow(pin, force, scale)]


class KlannEnv(LatentEnv):
    """The planar Klann walking linkage driven through its crank; turn the crank at a commanded speed.

    ## Description
    The scene `klann` (n = 60: five affine rigid bars, seven penalty revolute joints, gravity) runs in its
    shipped 1-d periodic neural subspace, whose latent is an angle that takes the linkage once round its
    crank loop (winding 1). A tangential force on the crank pin (handle `crank_pin`), a crank torque, must
    keep the crank turning at the commanded speed omega*, through full turns and over the gravity hump of
    the leg (the pin needs about 16 N to get over it from rest: 15 N held 6 s turns it 0.2 rad).

    ## Action Space
    The action space is a `Box(-1, 1, (1,), float32)`: the tangential force on handle `crank_pin`, scaled to
    ±`max_force` [N] (counter-clockwise positive).
    Values outside [-1, 1] are clipped; non-finite ones raise `ValueError`.

    | Num | Action | Control Min | Control Max | Unit |
    |---|---|---|---|---|
    | 0 | tangential force on the crank pin (a crank torque of F × 0.05 m) | -1 | 1 | `max_force` N (40 N) |

    ## Observation Space
    `obs = concat(z, z_dot, cos theta, sin theta, omega, omega*)`, a `Box(low, high, (6,), float32)` with finite
    bounds (values are clipped into them); the latent angle z is kept in [-pi, pi) (z and z_prev shift together
    by whole turns, which the periodic map does not see):

    | Num | Observation | Min | Max | Unit |
    |---|---|---|---|---|
    | 0 | latent z (an angle) | -10 | 10 | rad |
    | 1 | latent velocity z_dot | -1000 | 1000 | rad/s |
    | 2 | cos theta of the crank angle | -1 | 1 | unitless |
    | 3 | sin theta of the crank angle | -1 | 1 | unitless |
    | 4 | crank speed omega | -pi/dt | pi/dt | rad/s |
    | 5 | commanded speed omega* | 0 | 12 | rad/s |

    ## Rewards
    `reward = -|omega - omega*| / W - 0.05 action^2 + 0.5 [|omega - omega*| < 0.2 omega*]` with W = 12 rad/s (the
    top of the command range), reported as `info["reward_speed"]`, `info["reward_control"]` and
    `info["reward_success"]`. `info` also holds `crank_angle` [rad], `crank_speed` [rad/s], `speed_error`
    [rad/s], `speed_within` (this step within the 20% tolerance), `held_fraction` (of the last 100 steps
    within it) and `is_success`, and the linkage's invariants: `rigid_orthogonality_error`, `joints_max_gap` [m]
    and `joint_axes_max_gap` (:mod:`redsim.envs.invariants`).

    ## Success
    `info["is_success"]`: the crank speed was within the tolerance on at least half of the last 100 env steps
    (2 s: more than one full turn at every commanded speed; steps before the episode's first count as misses).
    The speed swings over each turn (the gravity hump), so one step's error says little about the tracking.

    ## Starting State
    At rest (z: the map's unloaded equilibrium, z_dot = 0, the crank hanging at theta = 2.33 rad). The commanded
    speed omega* is drawn uniformly from `speed_range` (4-12 rad/s, 0.6-1.9 turns/s) by `self.np_random`;
    `reset(options={"speed": omega})` sets it [rad/s] instead, in (0, 12] (the tolerance is 20% of it: a
    command of 0 could never succeed).

    ## Episode End
    Termination: the stepper could not make a step finite (`info["diverged"]`). Truncation: 300 steps
    (6 s at the default `dt` and `frame_skip`).

    ## Arguments
    | Argument | Default | Meaning |
    |---|---|---|
    | `render_mode` | None | None, "rgb_array" or "human" |
    | `max_force` | 40.0 | tangential force [N] of a unit action |
    | `speed_range` | (4.0, 12.0) | range [rad/s] of the commanded speed; its top must be below pi / (dt x frame_skip) |
    | `dt` | 0.02 | stepper time step [s] |
    | `frame_skip` | 1 | stepper steps per env step, 1 to 1000 (`MAX_FRAME_SKIP`) |
    | `hold_steps` | 100 | env steps of the success window |
    | `hold_fraction` | 0.5 | fraction of the window within the tolerance that makes a success |
    | `subspace` | None | the shipped map, a checkpoint path or a map |
    | `scene_params` | None | scene build parameters (the shipped map covers only the defaults) |
    | `fit_if_missing` | False | fit a map for `scene_params` no shipped map covers into the user cache |
    | `fit_options` | None | FitConfig fields over the shipped map's fit options for that fit |
    | `include_q` | False | put q [n] in `info["q"]` |
    | `reset_noise_scale` | 0.0 | s: start at z0 + U(-s, s) with z_dot s N(0, 1) per latent (MuJoCo's convention) |
    | `**kwargs` | | the other :class:`LatentEnv` arguments (`LATENT_ENV_ARGUMENTS`) |

    omega is the wrapped turn of one env step over its dt x frame_skip, so a crank turning faster than
    pi / (dt x frame_skip) would read as a slower or backward one; the env checks `speed_range` against that limit
    when it is made. The push cannot drive the crank that fast: its direction is set where each env step starts
    (perpendicular to the crank there) and held through the step's frame_skip stepper steps while the crank turns,
    so the longer the env step, the less a push drives it. A held full push turns the crank more than twice in
    0.8 s at frame_skip 1, but stays below 12 rad/s, the top of the default `speed_range`, at frame_skip 8 (tests):
    there the fastest commands are out of reach.

    ## Version History
    - v0: first version. Later in v0 (dynamics, observation and reward unchanged): `is_success` is judged over
      the last 100 steps (## Success) instead of at one step, and `info` gained `speed_within` and
      `held_fraction`.
    """

    camera: ClassVar[dict[str, float]] = {"azimuth": 0.0, "elevation": 0.0}

    def __init__(
        self,
        render_mode: str | None = None,
        *,
        max_force: float = 40.0,
        speed_range: tuple[float, float] = (4.0, 12.0),
        dt: float = 0.02,
        frame_skip: int = 1,
        hold_steps: int = 100,
        hold_fraction: float = 0.5,
        subspace: str | nn.Module | None = None,
        scene_params: dict[str, Any] | None = None,
        fit_if_missing: bool = False,
        fit_options: dict[str, Any] | None = None,
        include_q: bool = False,
        **kwargs: Any,
    ) -> None:
        from redsim.scenes.linkages import KLANN_CRANK

        scene, sub = shipped("klann", scene_params, subspace, fit_if_missing=fit_if_missing, fit_options=fit_options)
        task = CrankSpeed(
            KLANN_CRANK.handle,
            KLANN_CRANK.pivot,
            max_force=max_force,
            speed_range=speed_range,
            hold_steps=hold_steps,
            hold_fraction=hold_fraction,
        )
        super().__init__(
            scene, sub, task, render_mode=render_mode, dt=dt, frame_skip=frame_skip, include_q=include_q, **kwargs
        )


make_vec = vector_entry(KlannEnv)

__all__ = ["CrankSpeed", "KlannEnv", "make_vec"]
