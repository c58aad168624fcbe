"""`RedSim/MiniChain-v0`: swing the end of a two-link chain to a target point."""

from __future__ import annotations

from typing import Any, ClassVar

from redsim.envs.reach import ReachEnv
from redsim.envs.vector import vector_entry


class MiniChainEnv(ReachEnv):
    """Two steel torus links hanging from a hook, held together by contact only; push the lower one to a target.

    ## Description
    The scene `mini_chain` (n = 24: two affine rigid bodies) runs in its shipped 4-d neural subspace.
    A force on the centre of the lower link (handle `bottom`) must bring that point to a target.
    The small, fast env of the suite, for quick experiments and tests.

    ## Action Space
    The action space is a `Box(-1, 1, (3,), float32)`: the force on handle `bottom`, scaled to ±`max_force` [N].
    Values outside [-1, 1] are clipped; non-finite ones raise `ValueError`.

    | Num | Action | Control Min | Control Max | Unit |
    |---|---|---|---|---|
    | 0 | force along x on the lower link | -1 | 1 | `max_force` N (15 N) |
    | 1 | force along y (up) on the lower link | -1 | 1 | `max_force` N |
    | 2 | force along z on the lower link | -1 | 1 | `max_force` N |

    ## Observation Space
    `obs = concat(z, z_dot, p, target - p)`, a `Box(low, high, (14,), float32)` with finite bounds (values are
    clipped into them):

    | Num | Observation | Min | Max | Unit |
    |---|---|---|---|---|
    | 0-3 | latent z | -10 | 10 | unitless |
    | 4-7 | latent velocity z_dot | -1000 | 1000 | 1/s |
    | 8-10 | position p of the lower link's centre | -(r + 2L) | r + 2L | m (r: largest rest coordinate, L = 0.27 m) |
    | 11-13 | target - p | -(r + 2L) | r + 2L | m |

    ## Rewards
    Dense: -d / L_d with d the distance [m] from the lower link's centre to the target,
    a control cost and a bonus within the success radius, each in `info["reward_<term>"]`
    (formula: :class:`redsim.envs.reach.ReachEnv`).

    Besides the rewards and the solver's flags, `info` holds `distance` [m], `is_success` and the chain's invariants:
    `rigid_orthogonality_error`, `contact_penetration` [m], `contact_clearance` [m] and `contact_unlinked`, how many
    (link ring, neighbour's torus) pairs, the hook's included, lost the linking number they have at rest: links that
    passed through each other (0 in an intact chain; one joint apart reads 2, once from each link's side).

    ## Starting State
    At rest: z is the map's unloaded equilibrium and z_dot = 0. The target is the lower link's centre in the
    subspace state z_rest + `target_spread` * N(0, I), drawn from `self.np_random`.
    `reset(options={"target": [x, y, z]})` sets the target [m] instead.

    ## Episode End
    Termination: the stepper could not make a step finite (`info["diverged"]`). Truncation: 200 steps
    (4 s at the default `dt` and `frame_skip`).

    ## Arguments
    As :class:`redsim.envs.reach.ReachEnv`; `max_force` and `target_spread` default to 15 N, spread 0.6, and
    `stepper_options` to `{"warm_start": False}` (each step's solve starts from a fresh Hessian model: 1.2x
    faster at 16-64 envs here; `{"warm_start": True}` carries the last step's model, as the other ids do, and with it
    starts each solve at the model's Newton step, `predict`: add `"predict": False` to keep 2 z_t - z_{t-1}).

    ## Version History
    - v0: first version. Its solver starts cold again (`stepper_defaults`), as when v0 was released and its
      shipped policy trained; the runtime's warm start, on for a while in between, lands within the solve's
      tolerance of the same steps (the golden rollout agrees either way).
    """

    stepper_defaults: ClassVar[dict[str, Any]] = {"warm_start": False}

    scene_name: ClassVar[str] = "mini_chain"
    goal_handle: ClassVar[str] = "bottom"
    default_max_force: ClassVar[float] = 15.0
    default_target_spread: ClassVar[float] = 0.6
    camera: ClassVar[dict[str, float]] = {"azimuth": 30.0, "elevation": 15.0}


make_vec = vector_entry(MiniChainEnv)
