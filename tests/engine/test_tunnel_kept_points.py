""":class:`redsim.integrators.tunneling.TunnelTest` keeps the points of a call's end for the next call that starts
from that very tensor; a tensor changed in place since (a reset writing the state into the same buffer) must have its
points computed again. Reusing them by identity alone (the ``_version`` check dropped: hand mutation audit,
helper-283) tested the next step from the old state and missed a path through the hook."""

from __future__ import annotations

import torch

from redsim import scenes
from redsim.integrators.tunneling import TunnelTest


def test_an_end_changed_in_place_is_not_read_from_the_kept_points() -> None:
    scene = scenes.build("mini_chain")
    test = TunnelTest(scene)
    x = scene.full_positions(scene.q_seed.to(torch.float64).unsqueeze(0))
    lifted = x.clone()
    lifted[:, 7::12] += 0.2  # every link 0.2 m up: link 0 across the hook (test_tunneling.py's case)
    buffer = x.clone()
    assert test(x.clone(), buffer).tolist() == [False]  # a step that does not move; its end's points are kept
    buffer.copy_(lifted)  # the same tensor now holds the lifted state
    assert test(buffer, x.clone()).tolist() == [True]  # from lifted back down through the hook
    assert test(lifted.clone(), x.clone()).tolist() == [True]  # as from a fresh tensor
