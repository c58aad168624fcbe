"""`RedSim/ConditionalBar-v0` and `-v1`: steer the tip of a bar whose stiffness and support move per episode."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from redsim.envs.base import LatentSim
from redsim.envs.reach import HandleReach, ReachEnv
from redsim.envs.vector import vector_entry

SUPPORT_RGB = (150, 150, 150)
"""Colour of the disc that marks the bar's support."""


class SupportedReach(HandleReach):
    """:class:`HandleReach` whose pictures also mark the bar's support (grey) at the episode's location c[1]."""

    def overlay(self, sim: LatentSim, row: int) -> tuple[list[Any], list[Any]]:
        from redsim.raster import Marker

        markers, arrows = super().overlay(sim, row)
        names = list(sim.scene.condition_space.names) if sim.scene.condition_space is not None else []
        if sim.cond is not None and "pin_location" in names:
            location = float(sim.cond[row, names.index("pin_location")])
            # first, under the rings: the target stays the last marker drawn
            markers.insert(0, Marker(np.array([location, 0.0]), SUPPORT_RGB, filled=True))
        return markers, arrows


class ConditionalBarEnv(ReachEnv):
    """A 2D neo-Hookean cantilever with a random stiffness ratio and support location; steer its tip.

    ## Description
    The scene `conditional_bar` (n = 940: a 1 x 0.1 m plane-strain bar clamped at x = 0, gravity, a support
    along its bottom edge) runs in its shipped 8-d *conditional* subspace f(z, c). Each episode draws the
    condition c (domain randomization through the subspace): c[0] the Young's modulus factor of the right half,
    c[1] the support location [m] (a grey dot in the pictures); c is part of the observation. A force on the tip
    column (handle `tip`) must bring the tip to a target.

    ## Action Space
    The action space is a `Box(-1, 1, (2,), float32)`: the force on the tip, scaled to ±`max_force` [N].
    Values outside [-1, 1] are clipped; non-finite ones raise `ValueError`.

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
    | 16-17 | tip position p (mean of the tip column) | -(r + 2L) | r + 2L | m (r = 0.99 m, the rest tip's x; L = 1 m) |
    | 18-19 | target - p | -(r + 2L) | r + 2L | m |
    | 20 | stiffness ratio c[0] | 0.2 | 5 | unitless |
    | 21 | support location c[1] | 0.3 | 1.0 | m |

    ## Rewards
    Dense: -d / L_d with d the distance [m] from the tip to the target (L_d and r are set once, from targets
    under the default condition c = (1, 0.65), not per episode's c), a control cost and a bonus within the success
    radius; `info` also holds `distance` [m], `is_success` (d < r) and the FEM invariants `elastic_min_det_f` and
    `elastic_inverted`. Each term is in `info["reward_<term>"]`
    (formula: :class:`redsim.envs.reach.ReachEnv`).

    ## Starting State
    c uniform in its box; z the map's unloaded equilibrium under c, z_dot = 0. The target is the tip in the
    subspace state f(z_rest + `target_spread` * N(0, I), c); all draws from `self.np_random`.
    `reset(options={"target": [x, y], "condition": [ratio, location]})` sets either instead.

    ## Episode End
    Termination: the stepper could not make a step finite (`info["diverged"]`). Truncation: 200 steps
    (4 s at the default `dt` and `frame_skip`).

    ## Arguments
    As :class:`redsim.envs.reach.ReachEnv`; `max_force` and `target_spread` default to 300 N, spread 0.5, and
    `stepper_options` to `{"max_step": 2.0, "warm_refresh": False, "start": "lower"}`: no solver trial moves z by
    more than 2 latent units, the warm model is BFGS-updated from step to step and never rebuilt, and each solve
    starts at the lower of the extrapolated state and the current one (1.56x faster at 64 envs here: 23 instead
    of 39 value-and-gradient calls per vector step; docs/env-speed.md, "ConditionalBar-v0's solve path"). `{"max_step":
    None, "warm_refresh": True, "start": "extrapolated"}` gives the solver's general defaults.

    | Argument | Default | Meaning |
    |---|---|---|
    | `cubature` | None: off (v1: True) | `True`: the shipped cubature, 200 of 846 elastic elements (error 1.9%) |
    | `randomize_condition` | True | False: c stays (1, 0.65) and the observation leaves it out (20 entries) |

    ## Version History
    - v1: v0 on the shipped cubature (`cubature=True`; held-out force error 1.9%, 100-step trajectory deviation
      1.6%, README "Cubature"): 1.40x faster at 64 envs by CPU time (`redsim bench env-ab`, docs/envs.md) and
      1.6x by wall time (`redsim bench envs`, README "Env speed"); the same task, observation and reward.
    - v0: first version. Its solver defaults (`stepper_defaults`) later limited trial steps, kept the warm
      model and started from the lower of two points: the same steps to the solve's tolerance (its golden rollout
      passes either way), 1.6x faster.
    """

    stepper_defaults: ClassVar[dict[str, Any]] = {"max_step": 2.0, "warm_refresh": False, "start": "lower"}

    scene_name: ClassVar[str] = "conditional_bar"
    goal_handle: ClassVar[str] = "tip"
    default_max_force: ClassVar[float] = 300.0
    default_target_spread: ClassVar[float] = 0.5
    randomize_condition: ClassVar[bool] = True
    task_class: ClassVar[type[HandleReach]] = SupportedReach


make_vec = vector_entry(ConditionalBarEnv)
