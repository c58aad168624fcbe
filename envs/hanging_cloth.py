"""`RedSim/HangingCloth-v0`: move a free corner of the hanging sheet to a target point."""

from __future__ import annotations

from typing import ClassVar

from redsim.envs.reach import ReachEnv
from redsim.envs.vector import vector_entry


class HangingClothEnv(ReachEnv):
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
    Dense: -d / L_d with d the distance [m] from the corner to the target point,
    a control cost and a bonus within the success radius, each in `info["reward_<term>"]`
    (formula: :class:`redsim.envs.reach.ReachEnv`).

    ## Starting State
    At rest (z: the map's unloaded equilibrium, z_dot = 0). The target is the corner in the subspace state
    z_rest + `target_spread` * N(0, I), drawn from `self.np_random`.

    ## Episode End
    Termination: the stepper could not make a step finite (`info["diverged"]`). Truncation: 200 steps (4 s).

    ## Arguments
    As :class:`redsim.envs.reach.ReachEnv`; `max_force` and `target_spread` default to 2 N, spread 0.5.

    | Argument | Default | Meaning |
    |---|---|---|
    | `cubature` | None: off | `True`: the shipped cubature (force error 3.1%, deviation 4.7-7.2%: not within the bar) |

    ## Version History
    - v0: first version.
    """

    scene_name: ClassVar[str] = "hanging_sheet"
    goal_handle: ClassVar[str] = "bottom_left"
    default_max_force: ClassVar[float] = 2.0
    default_target_spread: ClassVar[float] = 0.5
    camera: ClassVar[dict[str, float]] = {"azimuth": 35.0, "elevation": 15.0, "margin": 0.1}


make_vec = vector_entry(HangingClothEnv)
