"""`RedSim/ClothBall-v0`: push the ball over the pinned cloth to a target spot."""

from __future__ import annotations

from typing import Any

from torch import nn

from redsim.envs.base import LatentEnv, shipped
from redsim.envs.reach import HandleReach
from redsim.envs.vector import vector_entry


class ClothBallEnv(LatentEnv):
    """A 1 kg ball on a 1 m cloth pinned at its corners; roll it to a target spot by pushing it sideways.

    ## Description
    The scene `cloth_ball` (n = 6075: a 45 x 45 StVK cloth with discrete-shell bending, a rigid ball, sphere
    contact, gravity) runs in its shipped 3-d neural subspace. A horizontal force on the ball's centre (handle
    `ball`) must bring the ball above a target spot on the cloth.

    ## Action Space
    The action space is a `Box(-1, 1, (2,), float32)`: the horizontal force on the ball, scaled to ±`max_force` [N].

    | Num | Action | Control Min | Control Max | Unit |
    |---|---|---|---|---|
    | 0 | force along x on the ball | -1 | 1 | `max_force` N (8 N) |
    | 1 | force along z on the ball | -1 | 1 | `max_force` N |

    ## Observation Space
    `obs = concat(z, z_dot, p, target - p)` with p = (x, z) of the ball's centre, a `Box(low, high, (10,),
    float32)` with finite bounds (values are clipped into them):

    | Num | Observation | Min | Max | Unit |
    |---|---|---|---|---|
    | 0-2 | latent z | -10 | 10 | unitless |
    | 3-5 | latent velocity z_dot | -1000 | 1000 | 1/s |
    | 6-7 | ball centre (x, z) | -(r + 2) | r + 2 | m (r: its rest offset, the cloth is 1 m wide) |
    | 8-9 | target - ball centre, (x, z) | -(r + 2) | r + 2 | m |

    ## Rewards
    With d the horizontal distance [m] from the ball to the target and L_d the task's distance scale (the RMS
    distance of targets from the rest spot): `reward = -d / L_d - 0.05 mean(action^2) + 1[d < success_radius]`,
    reported as `info["reward_distance"]`, `info["reward_control"]`, `info["reward_success"]`.

    ## Starting State
    At rest (z: the map's unloaded equilibrium, the ball in the cloth's hollow; z_dot = 0). The target is the
    ball's (x, z) in the subspace state z_rest + `target_spread` * N(0, I), drawn from `self.np_random`.

    ## Episode End
    Termination: the stepper could not make a step finite (`info["diverged"]`). Truncation: 200 steps (4 s).

    ## Arguments
    | Argument | Default | Meaning |
    |---|---|---|
    | `render_mode` | None | None, "rgb_array" or "human" |
    | `max_force` | 8.0 | force [N] of a unit action |
    | `target_spread` | 0.8 | latent spread of the targets |
    | `dt` | 0.02 | stepper time step [s] |
    | `frame_skip` | 1 | stepper steps per env step |
    | `subspace` | None | the shipped map, a checkpoint path or a map |
    | `scene_params` | None | `cloth_ball` build parameters (a shipped map covers only the defaults) |
    | `include_q` | False | put q [6075] in `info["q"]` |
    | `**kwargs` | | more `LatentEnv` arguments (`dtype`, `device`, `width`, `height`, `camera`, ...) |

    ## Version History
    - v0: first version.
    """

    def __init__(
        self,
        render_mode: str | None = None,
        *,
        max_force: float = 8.0,
        target_spread: float = 0.8,
        dt: float = 0.02,
        frame_skip: int = 1,
        subspace: str | nn.Module | None = None,
        scene_params: dict[str, Any] | None = None,
        include_q: bool = False,
        **kwargs: Any,
    ) -> None:
        scene, sub = shipped("cloth_ball", scene_params, subspace)
        task = HandleReach(
            "ball", max_force=max_force, force_axes=(0, 2), goal_axes=(0, 2), target_spread=target_spread
        )
        kwargs.setdefault("camera", {"azimuth": 20.0, "elevation": 40.0, "margin": 0.05})
        super().__init__(
            scene, sub, task, render_mode=render_mode, dt=dt, frame_skip=frame_skip, include_q=include_q, **kwargs
        )


make_vec = vector_entry(ClothBallEnv)
