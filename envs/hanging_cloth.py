"""`RedSim/HangingCloth-v0`: move a free corner of the hanging sheet to a target point."""

from __future__ import annotations

from typing import Any

from torch import nn

from redsim.envs.base import LatentEnv, shipped
from redsim.envs.reach import HandleReach
from redsim.envs.vector import vector_entry


class HangingClothEnv(LatentEnv):
    """A 1 x 1 m sheet hanging from its top edge; pull its bottom-left corner to a target point.

    ## Description
    The scene `hanging_sheet` (n = 6072: a 46 x 45 StVK cloth with bending, the top row pinned, gravity) runs
    in its shipped 8-d neural subspace. A force on the bottom-left corner vertex (handle `bottom_left`) must
    bring that corner to a target.

    ## Action Space
    The action space is a `Box(-1, 1, (3,), float32)`: the force on the corner, scaled to ±`max_force` [N].

    | Num | Action | Control Min | Control Max | Unit |
    |---|---|---|---|---|
    | 0 | force along x (across the sheet) | -1 | 1 | `max_force` N (2 N) |
    | 1 | force along y (up) | -1 | 1 | `max_force` N |
    | 2 | force along z (out of the sheet) | -1 | 1 | `max_force` N |

    ## Observation Space
    `obs = concat(z, z_dot, p, target - p)`, a `Box(low, high, (22,), float32)` with finite bounds (values are
    clipped into them):

    | Num | Observation | Min | Max | Unit |
    |---|---|---|---|---|
    | 0-7 | latent z | -10 | 10 | unitless |
    | 8-15 | latent velocity z_dot | -1000 | 1000 | 1/s |
    | 16-18 | corner position p | -(r + 2) | r + 2 | m (r: its largest rest coordinate) |
    | 19-21 | target - p | -(r + 2) | r + 2 | m |

    ## Rewards
    With d the distance [m] from the corner to the target and L_d the task's distance scale (the RMS distance of
    targets from the rest corner): `reward = -d / L_d - 0.05 mean(action^2) + 1[d < success_radius]`, reported as
    `info["reward_distance"]`, `info["reward_control"]`, `info["reward_success"]`.

    ## Starting State
    At rest (z: the map's unloaded equilibrium, z_dot = 0). The target is the corner in the subspace state
    z_rest + `target_spread` * N(0, I), drawn from `self.np_random`.

    ## Episode End
    Termination: the stepper could not make a step finite (`info["diverged"]`). Truncation: 200 steps (4 s).

    ## Arguments
    | Argument | Default | Meaning |
    |---|---|---|
    | `render_mode` | None | None, "rgb_array" or "human" |
    | `max_force` | 2.0 | force [N] of a unit action |
    | `target_spread` | 0.5 | latent spread of the targets |
    | `dt` | 0.02 | stepper time step [s] |
    | `frame_skip` | 1 | stepper steps per env step |
    | `subspace` | None | the shipped map, a checkpoint path or a map |
    | `scene_params` | None | `hanging_sheet` build parameters (a shipped map covers only the defaults) |
    | `include_q` | False | put q [6072] in `info["q"]` |
    | `**kwargs` | | more `LatentEnv` arguments (`dtype`, `device`, `width`, `height`, `camera`, ...) |

    ## Version History
    - v0: first version.
    """

    def __init__(
        self,
        render_mode: str | None = None,
        *,
        max_force: float = 2.0,
        target_spread: float = 0.5,
        dt: float = 0.02,
        frame_skip: int = 1,
        subspace: str | nn.Module | None = None,
        scene_params: dict[str, Any] | None = None,
        include_q: bool = False,
        **kwargs: Any,
    ) -> None:
        scene, sub = shipped("hanging_sheet", scene_params, subspace)
        task = HandleReach("bottom_left", max_force=max_force, target_spread=target_spread)
        kwargs.setdefault("camera", {"azimuth": 35.0, "elevation": 15.0, "margin": 0.1})
        super().__init__(
            scene, sub, task, render_mode=render_mode, dt=dt, frame_skip=frame_skip, include_q=include_q, **kwargs
        )


make_vec = vector_entry(HangingClothEnv)
