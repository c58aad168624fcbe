"""The ``tunneled`` test (redsim.integrators.tunneling): a step whose path passed through a contact is reported.

The case is the one the stability bench's ``impact`` regime makes: the two-link chain thrown up at its hook. At
10 m/s a 0.02 s full-space step moves 0.2 m against a wire 0.03 m thick (tube and margins), every step converges,
no energy is gained, and the chain flies off; at 1 m/s the hook catches it.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch

from redsim import scenes
from redsim.benches import stability
from redsim.integrators import FullSpace, ImplicitEuler
from redsim.integrators.tunneling import TunnelTest


def _thrown_up(speed: float, steps: int = 4) -> tuple[torch.Tensor, list]:
    """The mini chain's link centres' heights [steps + 1, 2] [m] and its steps' StepInfo, every link thrown up at
    ``speed`` [m/s]."""
    scene = scenes.build("mini_chain")
    x_dot = torch.zeros(scene.full_dof_count, dtype=torch.float64)
    x_dot[7::12] = speed  # t_y of every link
    sim = ImplicitEuler(FullSpace(scene), 0.02)
    state = sim.initial_state(None, scene.dof_map.restrict(x_dot.unsqueeze(0))[0])
    q, infos = [state.q], []
    for _ in range(steps):
        state, info = sim.step(state)
        q.append(state.q)
        infos.append(info)
    x = scene.full_positions(torch.stack(q)).reshape(steps + 1, -1, 12)
    return x[:, :, 7], infos


def test_a_step_through_the_hook_is_flagged_and_one_the_hook_stops_is_not() -> None:
    heights, infos = _thrown_up(10.0)
    assert all(info.converged and not info.energy_gain for info in infos)  # nothing else says it
    assert float(heights[-1, 0]) > 0.5  # link 0 (hung at -0.075 m) is far above the hook: it passed through
    assert infos[0].tunneled

    heights, infos = _thrown_up(1.0)
    assert not any(info.tunneled for info in infos)
    assert float(heights[:, 0].max()) < 0.0  # the hook held it


def test_the_test_needs_a_move_longer_than_half_the_contact_and_a_deeper_path() -> None:
    scene = scenes.build("mini_chain")
    test = TunnelTest(scene)
    (contact, _, size), *_ = test.contacts
    assert size == contact.feature_size == 0.03  # the wire: tube 0.01 m plus two margins of 0.01 m
    x = scene.full_positions(scene.q_seed.to(torch.float64).unsqueeze(0))
    lifted = x.clone()
    lifted[:, 7::12] += 0.2  # every link 0.2 m up: link 0 across the hook
    nudged = x.clone()
    nudged[:, 7::12] += 0.4 * size  # less than half the thickness: not sampled
    flags = test(torch.cat([x, x, x]), torch.cat([lifted, nudged, x]))
    assert flags.tolist() == [True, False, False]


def test_env_info_says_tunneled_and_the_impact_rows_count_it() -> None:
    env = gym.make("RedSim/MiniChain-v0")
    env.reset(seed=0)
    info = env.step(np.ones(env.action_space.shape, np.float32))[-1]
    assert info["tunneled"] is False
    env.close()

    scene = scenes.build("mini_chain")
    x_dot = torch.zeros(scene.full_dof_count, dtype=torch.float64)
    x_dot[7::12] = 10.0
    velocity = scene.dof_map.restrict(x_dot.unsqueeze(0))[0]
    full = stability.full_rollout(scene, stability._zero_loads(scene, 4), 0.02, velocity=velocity)
    row = full.row(scene, "mini_chain", "impact_10", "full", stability.FULL_SLACK)
    assert row["tunneled"] >= 1 and row["failures_detected"] >= row["tunneled"] and row["unreported"] == 0
