"""`RedSim/BistableBar-v0` and `-v1`: snap the compressed bar from one buckled state to the other with a bounded force.

The bar (`bistable_bar`, its ends pinned closer than its rest length) has two stable states, arched up
and arched down. Each episode starts at rest in one of them (drawn by the env's generator) and the
other is the goal. The action is a force ``max_force * action`` [N] along y on the middle column
(handle ``middle``); too weak a push only bends the arch, which springs back.

The two states are the map's own: at bind time the lowest-energy latent samples with the handle
above and below its seed height are refined to latent static equilibria (float64, zero load). Let
h be the handle's height [m] above its seed height, h* that of the goal state and h0 that of the
start state. Reward per step, with D = |h* - h0|:

    reward = -|h - h*| / D  -  control_weight * action^2  +  success_bonus * [|h - h*| < tolerance D]

reported as ``reward_height``, ``reward_control`` and ``reward_success``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import torch
from torch import Tensor, nn

from redsim.envs.base import LatentEnv, Task, check_numbers, shipped, shown
from redsim.envs.vector import vector_entry

if TYPE_CHECKING:
    from redsim.envs.base import LatentSim

SEARCH_SAMPLES = 512
"""Latent samples (z ~ N(0, I), fixed seed) searched for the two stable states at bind time."""


class SnapThrough(Task):
    """Move a bistable structure from one of its two stable states to the other with a force on a handle.

    Args:
        handle: The pushed handle; its height along ``axis`` tells the states apart.
        max_force: Force [N] of a unit action, along ``axis``.
        axis: Direction (coordinate index) of the force and of the height (default: the last, y).
        tolerance: Success when |h - h*| < tolerance |h* - h0|.
        control_weight: Weight of the control cost.
        success_bonus: Reward per step within the tolerance.
        release: The scripted controller pushes until the handle is this fraction of the way to the goal.

    Raises:
        ValueError: a bad number, or (at bind) an unknown handle or a subspace without two stable states
            on either side of the handle's seed height.
    """

    name = "snap_through"
    reward_terms = ("height", "control", "success")
    reset_options = ("start_side",)
    action_size = 1

    def __init__(
        self,
        handle: str,
        *,
        max_force: float,
        axis: int = -1,
        tolerance: float = 0.1,
        control_weight: float = 0.05,
        success_bonus: float = 1.0,
        release: float = 0.6,
    ) -> None:
        check_numbers(
            {"max_force": max_force, "tolerance": tolerance, "release": release},
            {"control_weight": control_weight, "success_bonus": success_bonus},
        )
        if not release < 1.0:
            raise ValueError(f"release must be < 1, got {release!r}")
        self.handle = handle
        self.max_force = float(max_force)
        self.axis = int(axis)
        self.tolerance = float(tolerance)
        self.control_weight = float(control_weight)
        self.success_bonus = float(success_bonus)
        self.release = float(release)

    # -- binding --------------------------------------------------------------------------
    def bind(self, sim: LatentSim) -> None:
        scene = sim.scene
        names = list(scene.handle_names)
        if self.handle not in names:
            raise ValueError(f"scene {scene.name!r} has no handle {self.handle!r}; valid handles: {names}")
        self._dt = sim.dt
        self._index = names.index(self.handle)
        self._point = scene.handles[self._index]
        self._handles = len(names)
        self._dim = scene.dim
        self._axis = self.axis % scene.dim
        seed_x = scene.full_positions(scene.q_seed.unsqueeze(0))
        self._seed_height = float(self._point.position(seed_x)[0, self._axis])
        self._bound = 2.0 * scene.extent()
        self.states = self._stable_latents(sim)
        self.heights = self.height(sim.full_positions(self.states))

    def _stable_latents(self, sim: LatentSim) -> Tensor:
        """The two stable latent states [2, d], handle above and below its seed height (module doc)."""
        from redsim.integrators import LatentSpace, latent_equilibrium

        space = LatentSpace(sim.source_scene, sim.subspace)
        z = torch.randn(SEARCH_SAMPLES, sim.latent_dim, generator=torch.Generator().manual_seed(0), dtype=torch.float32)
        z = z.to(torch.float64)
        with torch.no_grad():
            q = space.configuration(z)
            energy = space.scene.energy(q)
            height = self._point.position(space.scene.full_positions(q))[:, self._axis] - self._seed_height
        states = []
        for side in (height > 0.0, height < 0.0):
            if not bool(side.any()):
                raise ValueError(f"the subspace holds no state with handle {self.handle!r} on both sides of its seed")
            start = z[side][int(torch.argmin(energy[side]))]
            found, _ = latent_equilibrium(space, None, z0=start)
            states.append(found)
        out = torch.stack(states).to(sim.device, sim.torch_dtype)
        heights = self.height(sim.full_positions(out))
        if not bool(heights[0] > 0.0 > heights[1]):
            raise ValueError(
                f"the subspace's stable states do not lie on both sides of the seed (handle heights {shown(heights)} m)"
            )
        return out

    def height(self, x: Tensor) -> Tensor:
        """h [B] [m]: the handle's height along the axis above its seed height, in configurations x [B, N]."""
        return self._point.position(x)[:, self._axis] - self._seed_height

    # -- episodes -------------------------------------------------------------------------
    def sample(
        self, rng: np.random.Generator, sim: LatentSim, z_rest: Tensor, cond: Tensor | None
    ) -> dict[str, Tensor]:
        side = int(rng.integers(2))
        return {
            "start_side": torch.tensor(side, device=sim.device),
            "start_height": self.heights[side],
            "goal_height": self.heights[1 - side],
        }

    def check_options(self, chosen: Mapping[str, Tensor]) -> None:
        if "start_side" in chosen and not set(chosen["start_side"].flatten().tolist()) <= {0, 1}:
            raise ValueError(f"options['start_side'] must be 0 (up) or 1 (down), got {chosen['start_side'].tolist()}")

    def start(self, sim: LatentSim, row: int, z_rest: Tensor) -> Tensor:
        """The stable state the episode's draw names (not the rest latent: the map's z = 0 is the straight bar).

        The heights follow ``start_side`` here, so ``reset(options={"start_side": s})`` keeps them consistent.
        """
        side = int(sim.params["start_side"][row])
        sim.params["start_height"][row] = self.heights[side]
        sim.params["goal_height"][row] = self.heights[1 - side]
        return self.states[side]

    def frame_points(self, sim: LatentSim) -> np.ndarray:
        """Both stable states' shapes (an episode starts in one and snaps to the other through the straight bar),
        [P, D] [m]."""
        return sim.surface_points(self.states)

    def loads(self, action: Tensor, params: Mapping[str, Tensor]) -> Tensor:
        loads = torch.zeros(action.shape[0], self._handles, self._dim, dtype=action.dtype, device=action.device)
        loads[:, self._index, self._axis] = self.max_force * action[:, 0]
        return loads

    def extras_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        high = np.array([self._bound, self._bound, 2.0 * self._bound / self._dt])
        return -high, high

    def observation_structure(self) -> dict[str, int]:
        return {"height": 1, "goal_offset": 1, "height_speed": 1}

    def extras(self, x: Tensor, x_prev: Tensor, params: Mapping[str, Tensor]) -> Tensor:
        h = self.height(x)
        return torch.stack([h, params["goal_height"] - h, (h - self.height(x_prev)) / self._dt], dim=1)

    def _error(self, x: Tensor, params: Mapping[str, Tensor]) -> tuple[Tensor, Tensor]:
        """|h - h*| [B] [m] and the success radius tolerance |h* - h0| [B] [m]."""
        span = (params["goal_height"] - params["start_height"]).abs()
        return (self.height(x) - params["goal_height"]).abs(), self.tolerance * span

    def reward(self, x: Tensor, action: Tensor, params: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]]:
        error, radius = self._error(x, params)
        terms = {
            "height": -error * self.tolerance / radius,
            "control": -self.control_weight * action.pow(2).mean(dim=1),
            "success": self.success_bonus * (error < radius).to(error.dtype),
        }
        return terms["height"] + terms["control"] + terms["success"], terms

    def metrics(self, x: Tensor, params: Mapping[str, Tensor]) -> dict[str, Tensor]:
        error, radius = self._error(x, params)
        return {"height": self.height(x), "height_error": error, "is_success": error < radius}

    # -- scripted control and drawing -----------------------------------------------------
    def controller(self, sim: LatentSim) -> np.ndarray:
        """Bang-bang: full force towards the goal until the handle is ``release`` of the way there, then none.

        Past the straight state the goal's own well pulls the bar the rest of the way (and the implicit
        Euler steps' damping settles it), so the push only has to carry it over the barrier.
        """
        start, goal = sim.params["start_height"], sim.params["goal_height"]
        progress = (self.height(sim.x) - start) / (goal - start)
        action = torch.where(progress < self.release, torch.sign(goal - start), torch.zeros_like(goal))
        return action.unsqueeze(1).cpu().numpy().astype(np.float32)

    def overlay(self, sim: LatentSim, row: int) -> tuple[list[Any], list[Any]]:
        """A ring on the pushed point, the goal as a ring of the success tolerance [m] (of height: a band, drawn
        round the goal point) and the force arrow."""
        from redsim.raster import HANDLE_RGB, TARGET_RGB, Arrow, Marker

        x = sim.x[row : row + 1]
        point = self._point.position(x)[0].cpu().numpy()
        markers = [Marker(point, HANDLE_RGB)]
        if "goal_height" in sim.params:
            goal = point.copy()
            goal[self._axis] = self._seed_height + float(sim.params["goal_height"][row])
            _, radius = self._error(x, {k: v[row : row + 1] for k, v in sim.params.items()})
            # the target last, so that the handle's ring does not hide it as the handle comes near (as reach tasks)
            markers.append(Marker(goal, TARGET_RGB, float(radius[0])))
        force = sim.loads[row, self._index].cpu().numpy()
        return markers, [Arrow(point, force, 0.25 * sim.scene.extent() / self.max_force)]


class BistableBarEnv(LatentEnv):
    """A compressed elastic bar with two buckled states; snap it from one to the other with a push on its middle.

    ## Description
    The scene `bistable_bar` (n = 820: a 1 x 0.1 m plane-strain neo-Hookean bar, E = 1e5 Pa, its ends clamped
    0.8 m apart, no gravity) runs in its shipped 8-d neural subspace, which holds both buckled states (the fit's
    mirror option makes the map equivariant under the up-down flip). The bar starts at rest arched up or down;
    a vertical force on its middle column (handle `middle`) must snap it over into the other arch. The force is
    bounded: a push only just above the snap-through load carries it over, a weaker one bends it and it springs
    back: in this env (the shipped map, stop 44) a push held for 1.2 s snaps it from the down arch at 36-40 N and
    from the up arch at 40-44 N. (The full-space bar buckles sideways under a static middle load of 24-26 N, an
    asymmetric mode the mirror-equivariant map does not hold; along the symmetric path its limit is 40.0-40.25 N.)
    v0 allows 60 N, so a push towards the goal (the scripted controller) snaps it in every episode; v1 allows 40 N,
    below the up arch's held-push snap load: the same push snaps it from the down arch (``start_side`` 1; 27 steps
    at seed 1) and never from the up arch (200 steps), while pushing along the middle's motion pumps in energy and
    snaps it every time (tests), so a policy must learn to swing the bar over from the up arch.

    ## Action Space
    The action space is a `Box(-1, 1, (1,), float32)`: the force along y on the middle column, scaled to
    ±`max_force` [N].
    Values outside [-1, 1] are clipped; non-finite ones raise `ValueError`.

    | Num | Action | Control Min | Control Max | Unit |
    |---|---|---|---|---|
    | 0 | force along y (up) on the middle column | -1 | 1 | `max_force` N (60 N in v0, 40 N in v1) |

    ## Observation Space
    `obs = concat(z, z_dot, h, h* - h, h_dot)`, a `Box(low, high, (19,), float32)` with finite bounds (values are
    clipped into them):

    | Num | Observation | Min | Max | Unit |
    |---|---|---|---|---|
    | 0-7 | latent z | -10 | 10 | unitless |
    | 8-15 | latent velocity z_dot | -1000 | 1000 | 1/s |
    | 16 | height h of the middle column above its straight (seed) height | -1.6 | 1.6 | m |
    | 17 | goal offset h* - h | -1.6 | 1.6 | m |
    | 18 | height speed h_dot | -160 | 160 | m/s |

    ## Rewards
    `reward = -|h - h*| / D - 0.05 action^2 + 1[|h - h*| < 0.1 D]` with D = |h* - h0| the height difference of
    the two states (about 0.50 m), reported as `info["reward_height"]`, `info["reward_control"]` and
    `info["reward_success"]`; `info` also holds `height` [m], `height_error` [m], `is_success` and the FEM
    invariants `elastic_min_det_f` and `elastic_inverted`.

    ## Starting State
    At rest in one of the two stable states of the map (up or down with probability 1/2, from `self.np_random`;
    `reset(options={"start_side": 0})` starts up, 1 down), z_dot = 0; the goal is the other one.

    ## Episode End
    Termination: the stepper could not make a step finite (`info["diverged"]`). Truncation: 200 steps
    (4 s at the default `dt` and `frame_skip`).

    ## Arguments
    | Argument | Default | Meaning |
    |---|---|---|
    | `render_mode` | None | None, "rgb_array" or "human" |
    | `max_force` | 60.0 | force [N] of a unit action on the middle column (v1 registers 40.0) |
    | `dt` | 0.02 | stepper time step [s] |
    | `frame_skip` | 1 | stepper steps per env step, 1 to 1000 (`MAX_FRAME_SKIP`) |
    | `subspace` | None | the shipped map, a checkpoint path or a map (it must hold both states) |
    | `scene_params` | None | scene build parameters (the shipped map covers only the defaults) |
    | `fit_if_missing` | False | fit a map for `scene_params` no shipped map covers into the user cache |
    | `fit_options` | None | FitConfig fields over the shipped map's fit options for that fit |
    | `include_q` | False | put q [n] in `info["q"]` |
    | `reset_noise_scale` | 0.0 | s: start at z0 + U(-s, s) with z_dot s N(0, 1) per latent (MuJoCo's convention) |
    | `**kwargs` | | the other :class:`LatentEnv` arguments (`LATENT_ENV_ARGUMENTS`) |

    `stepper_options` (a :class:`LatentEnv` argument) defaults to `{"max_step": 2.0, "warm_refresh": False,
    "start": "lower"}`: no solver trial moves z by more than 2 latent units, the warm model is BFGS-updated from
    step to step and never rebuilt, and each solve starts at the lower of the extrapolated state and the current
    one (1.36x less CPU time for v0 and 1.18x for v1 at 64 envs here; docs/env-speed.md, "ConditionalBar-v0's solve
    path"). `{"max_step": None, "warm_refresh": True, "start": "extrapolated"}` gives the solver's general defaults.

    ## Version History
    - v1: `max_force` 40 N (v0: 60 N), below the load a held push needs to snap the env's bar from its up arch
      (not from its down arch); nothing else changed.
    - v0: first version.
    - v0, v1: their solver defaults (`stepper_defaults`) later changed the path of each solve, not its minimum:
      the golden rollouts pass either way and v1's shipped policy scores alike (docs/env-speed.md, "ConditionalBar-v0's
      solve path").
    """

    stepper_defaults: ClassVar[dict[str, Any]] = {"max_step": 2.0, "warm_refresh": False, "start": "lower"}

    def __init__(
        self,
        render_mode: str | None = None,
        *,
        max_force: float = 60.0,
        dt: float = 0.02,
        frame_skip: int = 1,
        subspace: str | nn.Module | None = None,
        scene_params: dict[str, Any] | None = None,
        fit_if_missing: bool = False,
        fit_options: dict[str, Any] | None = None,
        include_q: bool = False,
        **kwargs: Any,
    ) -> None:
        scene, sub = shipped(
            "bistable_bar", scene_params, subspace, fit_if_missing=fit_if_missing, fit_options=fit_options
        )
        task = SnapThrough("middle", max_force=max_force)
        super().__init__(
            scene, sub, task, render_mode=render_mode, dt=dt, frame_skip=frame_skip, include_q=include_q, **kwargs
        )


make_vec = vector_entry(BistableBarEnv)

__all__ = ["BistableBarEnv", "SnapThrough", "make_vec"]
