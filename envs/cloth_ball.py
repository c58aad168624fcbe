"""`RedSim/ClothBall-v0` and `-v1`: push the ball over the pinned cloth to a target spot."""

from __future__ import annotations

from typing import Any, ClassVar

from redsim.envs.reach import ReachEnv
from redsim.envs.vector import vector_entry


class ClothBallEnv(ReachEnv):
    """A 1 kg ball on a 1 m cloth pinned at its corners; roll it to a target spot by pushing it sideways.

    ## Description
    The scene `cloth_ball` (n = 6075: a 45 x 45 StVK cloth with discrete-shell bending, a rigid ball, sphere
    contact, gravity) runs in its shipped 3-d neural subspace, stepped with its shipped cubature energy
    (README "Cubature"). A horizontal force on the ball's centre (handle `ball`) must bring the ball above a
    target spot on the cloth.

    ## Action Space
    The action space is a `Box(-1, 1, (2,), float32)`: the horizontal force on the ball, scaled to ±`max_force` [N].
    Values outside [-1, 1] are clipped; non-finite ones raise `ValueError`.

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
    Dense: -d / L_d with d the distance [m] from the ball to the target spot, horizontally,
    a control cost and a bonus within the success radius, each in `info["reward_<term>"]`
    (formula: :class:`redsim.envs.reach.ReachEnv`).

    Besides the rewards and the solver's flags, `info` holds `distance` [m], `is_success` and the scene's invariants
    (:mod:`redsim.envs.invariants`): `membrane_max_strain` (the largest principal stretch - 1 over the cloth's
    triangles; 0.44 at rest in the shipped map, in the triangles at the pinned corners, where the median triangle's
    is 0.035: the four point pins carry the ball's and cloth's 11.8 N, so the float64 full-space rest reads 0.30 there
    too (median 0.021; 0.18 on a 22-cell mesh, 0.39 on a 66-cell one: a point pin's peak grows as the mesh is
    refined), and the map's rest, 1.0 J above that one, adds the other 0.14), `rigid_orthogonality_error` (the ball's
    |R^T R - I|_F), `contact_penetration` [m] and `contact_clearance` [m] (Starting State).

    ## Starting State
    At rest (z: the map's unloaded equilibrium, the ball in the cloth's hollow; z_dot = 0). In the shipped d = 3 map
    the ball does not touch the cloth: its nearest cloth point stays ~2 cm beyond the contact margin
    (`info["contact_clearance"]` 0.019 m at rest and 0.0085-0.064 m over 100 random steps at seeds 0 and 1 in stop
    44's review, `contact_penetration` 0), the map carrying ball and
    cloth together where contact forces would; a full-space step from there closes the gap to the margin. The target is
    the ball's (x, z) in the subspace state z_rest + `target_spread` * N(0, I), drawn from `self.np_random`.
    `reset(options={"target": [x, z]})` sets it [m] instead.

    ## Episode End
    Termination: the stepper could not make a step finite (`info["diverged"]`). Truncation: 200 steps
    (4 s at the default `dt` and `frame_skip`).

    ## Arguments
    As :class:`redsim.envs.reach.ReachEnv`; `max_force` and `target_spread` default to 8 N, spread 0.8.

    | Argument | Default | Meaning |
    |---|---|---|
    | `cubature` | None: on (v1: "lean") | the shipped cubature (force error 2.9%); "lean": v1's leaner one; a path |

    `stepper_options` (a :class:`LatentEnv` argument) defaults to `{"row_block": 256}`: a solver call of more than
    256 rows (a step's first call above 128 envs, a difference Hessian's d x k rows above 85 copies to build) is
    evaluated in blocks of 256 rows, the same values to round-off and 1.16x faster at 256 envs
    (:class:`redsim.runtime.LatentStepper`); `{"row_block": None}` evaluates every call in one pass.

    ## Version History
    - v1: v0 on a leaner, more accurate cubature of the same map (`redsim/pretrained/cloth_ball.lean.cubature.json`:
      366 membrane triangles and 1 bending hinge against the shipped 200 and 200, chosen by `--tol 0.015` on more
      training states): held-out force error 1.4% against 2.9%, trajectory deviation from the all-element step 3.1%
      against 6.3% (median of 32 rollouts, `redsim bench cubature --states 32`), as fast (1.01x at 64 envs, `redsim
      bench env-ab`; docs/envs.md, "ClothBall-v1"; docs/cubature.md, "Stop 56"). Its dynamics differ from v0's by what
      the two cubatures differ by; the task, observation and reward are v0's.
    - v0: first version; stepped with the shipped cubature by default since it was added (`cubature=False`
      gives the all-element step of the first release). Its solver default `row_block` came later: the same
      solves to float32 round-off.
    """

    stepper_defaults: ClassVar[dict[str, Any]] = {"row_block": 256}

    scene_name: ClassVar[str] = "cloth_ball"
    goal_handle: ClassVar[str] = "ball"
    default_max_force: ClassVar[float] = 8.0
    default_target_spread: ClassVar[float] = 0.8
    force_axes: ClassVar[tuple[int, ...] | None] = (0, 2)
    goal_axes: ClassVar[tuple[int, ...] | None] = (0, 2)
    camera: ClassVar[dict[str, float]] = {"azimuth": 20.0, "elevation": 40.0, "margin": 0.05}


make_vec = vector_entry(ClothBallEnv)
