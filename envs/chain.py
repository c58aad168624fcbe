"""`RedSim/Chain-v0`: bring the free end of the 24-link chain to a target point with a bounded force."""

from __future__ import annotations

from typing import Any, ClassVar

from redsim.envs.reach import ReachEnv
from redsim.envs.vector import vector_entry


class ChainEnv(ReachEnv):
    """A 1.9 m chain of 24 steel torus links, held by contact only; bring its free end to a target.

    ## Description
    The scene `chain` (n = 288: 24 affine rigid bodies, torus signed-distance contact between neighbours)
    runs in its shipped 8-d neural subspace. A force on the centre of the last link (handle `bottom`) must
    bring that point to a target.

    ## Action Space
    The action space is a `Box(-1, 1, (3,), float32)`: the force on handle `bottom`, scaled to ±`max_force` [N].
    Values outside [-1, 1] are clipped; non-finite ones raise `ValueError`.

    | Num | Action | Control Min | Control Max | Unit |
    |---|---|---|---|---|
    | 0 | force along x on the last link | -1 | 1 | `max_force` N (40 N) |
    | 1 | force along y (up) on the last link | -1 | 1 | `max_force` N |
    | 2 | force along z on the last link | -1 | 1 | `max_force` N |

    ## Observation Space
    `obs = concat(z, z_dot, p, target - p)`, a `Box(low, high, (22,), float32)` with finite bounds (values are
    clipped into them):

    | Num | Observation | Min | Max | Unit |
    |---|---|---|---|---|
    | 0-7 | latent z | -10 | 10 | unitless |
    | 8-15 | latent velocity z_dot | -1000 | 1000 | 1/s |
    | 16-18 | position p of the last link's centre | -(r + 2L) | r + 2L | m (r = 1.9 m below the hook, L = 1.92 m) |
    | 19-21 | target - p | -(r + 2L) | r + 2L | m |

    ## Rewards
    Dense: -d / L_d with d the distance [m] from the end link's centre to the target,
    a control cost and a bonus within the success radius, each in `info["reward_<term>"]`
    (formula: :class:`redsim.envs.reach.ReachEnv`).

    Besides the rewards and the solver's flags, `info` holds `distance` [m], `is_success` and the chain's invariants:
    `rigid_orthogonality_error`, `contact_penetration` [m], `contact_clearance` [m] and `contact_unlinked`, how many
    (link ring, neighbour's torus) pairs, the hook's included, lost the linking number they have at rest: links that
    passed through each other (0 in an intact chain; one joint apart reads 2, once from each link's side).

    ## Starting State
    At rest (z: the map's unloaded equilibrium, z_dot = 0). The target is the end link's centre in the subspace
    state z_rest + `target_spread` * N(0, I), drawn from `self.np_random`. `reset(options={"target": [x, y, z]})`
    sets the target [m] instead.

    ## Episode End
    Termination: the stepper could not make a step finite (`info["diverged"]`). Truncation: 300 steps
    (6 s at the default `dt` and `frame_skip`).

    ## Arguments
    As :class:`redsim.envs.reach.ReachEnv`; `max_force` and `target_spread` default to 40 N, spread 0.5, and
    `stepper_options` to `{"max_step": 1.0, "warm_refresh": False, "start": "lower"}`: no solver trial moves z by
    more than 1 latent unit, the warm model is BFGS-updated from step to step and never rebuilt, and each solve
    starts at the lower of the extrapolated state and the current one (1.37x faster at 64 envs here: 18 instead
    of 27 value-and-gradient calls per vector step; docs/env-speed.md, "ConditionalBar-v0's solve path"). `{"max_step":
    None, "warm_refresh": True, "start": "extrapolated"}` gives the solver's general defaults.

    ## Version History
    - v0: first version. Its solver defaults (`stepper_defaults`) later changed the path of each solve, not its
      minimum: one step from the same states moves by as much as a 10x tighter tolerance moves it, the golden
      rollout passes either way, and the shipped policy scores alike (docs/env-speed.md, "ConditionalBar-v0's solve
      path").
    """

    stepper_defaults: ClassVar[dict[str, Any]] = {"max_step": 1.0, "warm_refresh": False, "start": "lower"}

    scene_name: ClassVar[str] = "chain"
    goal_handle: ClassVar[str] = "bottom"
    default_max_force: ClassVar[float] = 40.0
    default_target_spread: ClassVar[float] = 0.5
    camera: ClassVar[dict[str, float]] = {"azimuth": 30.0, "elevation": 15.0}


make_vec = vector_entry(ChainEnv)
