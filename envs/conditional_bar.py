"""`RedSim/ConditionalBar-v0`: steer the tip of a bar whose stiffness and support move per episode."""

from __future__ import annotations

from typing import Any

from torch import nn

from redsim.envs.base import LatentEnv, shipped
from redsim.envs.reach import HandleReach
from redsim.envs.vector import vector_entry


class ConditionalBarEnv(LatentEnv):
    """A 2D neo-Hookean cantilever with a random stiffness ratio and support location; steer its tip.

    ## Description
    The scene `conditional_bar` (n = 940: a 1 x 0.1 m plane-strain bar clamped at x = 0, gravity, a support
    along its bottom edge) runs in its shipped 8-d *conditional* subspace f(z, c). Each episode draws the
    condition c (domain randomization through the subspace): c[0] the Young's modulus factor of the right half,
    c[1] the support location [m]; c is part of the observation. A force on the tip column (handle `tip`) must
    bring the tip to a target.

    ## Action Space
    The action space is a `Box(-1, 1, (2,), float32)`: the force on the tip, scaled to ±`max_force` [N].

    | Num | Action | Control Min | Control Max | Unit |
    |---|---|---|---|---|
    | 0 | force along x (along the bar) | -1 | 1 | `max_force` N (300 N) |
    | 1 | force along y (up) | -1 | 1 | `max_force` N |

    ## Observation Space
    `obs = concat(z, z_dot, p, target - p, c)`, a `Box(low, high, (22,), float32)` with finite bounds (values are
    clipped into them):

    | Num | Observation | Min | Max | Unit |
    |---|---|---|---|---|
    | 0-7 | latent z | -10 | 10 | unitless |
    | 8-15 | latent velocity z_dot | -1000 | 1000 | 1/s |
    | 16-17 | tip position p (mean of the tip column) | -3 | 3 | m |
    | 18-19 | target - p | -3 | 3 | m |
    | 20 | stiffness ratio c[0] | 0.2 | 5 | unitless |
    | 21 | support location c[1] | 0.3 | 1.0 | m |

    ## Rewards
    With d the distance [m] from the tip to the target and L_d the task's distance scale (the RMS distance of
    targets from the rest tip at the default condition): `reward = -d / L_d - 0.05 mean(action^2) +
    1[d < success_radius]`, reported as `info["reward_distance"]`, `info["reward_control"]`, `info["reward_success"]`.

    ## Starting State
    c uniform in its box; z the map's unloaded equilibrium under c, z_dot = 0. The target is the tip in the
    subspace state f(z_rest + `target_spread` * N(0, I), c); all draws from `self.np_random`.

    ## Episode End
    Termination: the stepper could not make a step finite (`info["diverged"]`). Truncation: 200 steps (4 s).

    ## Arguments
    | Argument | Default | Meaning |
    |---|---|---|
    | `render_mode` | None | None, "rgb_array" or "human" |
    | `max_force` | 300.0 | force [N] of a unit action |
    | `target_spread` | 0.5 | latent spread of the targets |
    | `dt` | 0.02 | stepper time step [s] |
    | `frame_skip` | 1 | stepper steps per env step |
    | `subspace` | None | the shipped map, a checkpoint path or a map |
    | `scene_params` | None | `conditional_bar` build parameters (a shipped map covers only the defaults) |
    | `include_q` | False | put q [940] in `info["q"]` |
    | `**kwargs` | | more `LatentEnv` arguments (`dtype`, `device`, `width`, `height`, `camera`, ...) |

    ## Version History
    - v0: first version.
    """

    def __init__(
        self,
        render_mode: str | None = None,
        *,
        max_force: float = 300.0,
        target_spread: float = 0.5,
        dt: float = 0.02,
        frame_skip: int = 1,
        subspace: str | nn.Module | None = None,
        scene_params: dict[str, Any] | None = None,
        include_q: bool = False,
        **kwargs: Any,
    ) -> None:
        scene, sub = shipped("conditional_bar", scene_params, subspace)
        task = HandleReach("tip", max_force=max_force, target_spread=target_spread)
        kwargs.setdefault("randomize_condition", True)
        super().__init__(
            scene, sub, task, render_mode=render_mode, dt=dt, frame_skip=frame_skip, include_q=include_q, **kwargs
        )


make_vec = vector_entry(ConditionalBarEnv)
