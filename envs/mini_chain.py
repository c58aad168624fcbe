"""`RedSim/MiniChain-v0`: swing the end of a two-link chain to a target point."""

from __future__ import annotations

from typing import Any

from torch import nn

from redsim.envs.base import LatentEnv, shipped
from redsim.envs.reach import HandleReach
from redsim.envs.vector import vector_entry


class MiniChainEnv(LatentEnv):
    """Two steel torus links hanging from a hook, held together by contact only; push the lower one to a target.

    ## Description
    The scene `mini_chain` (n = 24: two affine rigid bodies) runs in its shipped 4-d neural subspace.
    A force on the centre of the lower link (handle `bottom`) must bring that point to a target.
    The small, fast env of the suite, for quick experiments and tests.

    ## Action Space
    The action space is a `Box(-1, 1, (3,), float32)`: the force on handle `bottom`, scaled to ±`max_force` [N].

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
    With d the distance [m] from p to the target and L_d the task's distance scale (the RMS distance of targets
    from the rest position, about 0.05 m): `reward = -d / L_d - 0.05 mean(action^2) + 1[d < success_radius]`,
    reported as `info["reward_distance"]`, `info["reward_control"]`, `info["reward_success"]`.

    ## Starting State
    At rest: z is the map's unloaded equilibrium and z_dot = 0. The target is the lower link's centre in the
    subspace state z_rest + `target_spread` * N(0, I), drawn from `self.np_random`.

    ## Episode End
    Termination: the stepper could not make a step finite (`info["diverged"]`). Truncation: 200 steps (4 s).

    ## Arguments
    | Argument | Default | Meaning |
    |---|---|---|
    | `render_mode` | None | None, "rgb_array" or "human" |
    | `max_force` | 15.0 | force [N] of a unit action |
    | `target_spread` | 0.6 | latent spread of the targets |
    | `dt` | 0.02 | stepper time step [s] |
    | `frame_skip` | 1 | stepper steps per env step |
    | `subspace` | None | the shipped map, a checkpoint path or a map |
    | `scene_params` | None | `mini_chain` build parameters (a shipped map covers only the defaults) |
    | `include_q` | False | put q [24] in `info["q"]` |
    | `**kwargs` | | more `LatentEnv` arguments (`dtype`, `device`, `width`, `height`, `camera`, ...) |

    ## Version History
    - v0: first version.
    """

    def __init__(
        self,
        render_mode: str | None = None,
        *,
        max_force: float = 15.0,
        target_spread: float = 0.6,
        dt: float = 0.02,
        frame_skip: int = 1,
        subspace: str | nn.Module | None = None,
        scene_params: dict[str, Any] | None = None,
        include_q: bool = False,
        **kwargs: Any,
    ) -> None:
        scene, sub = shipped("mini_chain", scene_params, subspace)
        task = HandleReach("bottom", max_force=max_force, target_spread=target_spread)
        kwargs.setdefault("camera", {"azimuth": 30.0, "elevation": 15.0})
        super().__init__(
            scene, sub, task, render_mode=render_mode, dt=dt, frame_skip=frame_skip, include_q=include_q, **kwargs
        )


make_vec = vector_entry(MiniChainEnv)
