"""``redsim.scenes.toolkit.Joints.align`` on a body seeded in a turned pose: its hinge axis holds at the seed.

A body's direction is stored in its frame as R^T a (``world @ R`` for a row vector). The catalog's linkages seed their
bodies unrotated or in poses where R^T a = R a, so ``world @ R.T`` (R a) passed every engine test (hand mutation audit,
helper-283); for a body turned about a tilted axis the joint_axes penalty was then not zero at the seed, and the hinge
pulled the body off its seed pose.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from redsim import SceneBuilder
from redsim.scenes import shapes, toolkit


def test_a_turned_body_s_hinge_axis_and_pin_hold_at_its_seed() -> None:
    rotation = shapes.rotation_y(0.4) @ np.array(
        [[np.cos(0.7), -np.sin(0.7), 0.0], [np.sin(0.7), np.cos(0.7), 0.0], [0.0, 0.0, 1.0]]
    )
    assert not np.allclose(rotation, rotation.T)
    builder = SceneBuilder(3)
    bar = toolkit.add_rigid_body(
        builder, trimesh.creation.box(extents=(0.2, 0.02, 0.02)), density=1000.0, rotation=rotation,
        translation=(0.1, 0.0, 0.0),
    )  # fmt: skip
    joints = toolkit.Joints(builder)
    joints.pin(bar, None, np.zeros(3))
    joints.align(bar, None, np.array([0.3, 0.4, 1.0]), 50.0)
    joints.finish(1e3)
    scene = builder.finalize("turned_hinge")
    terms = scene.energy_terms(scene.q_seed[None])
    assert float(terms["joints"][0]) == pytest.approx(0.0, abs=1e-20)
    assert float(terms["joint_axes"][0]) == pytest.approx(0.0, abs=1e-20)
    seed = scene.q_seed.reshape(3, 4)  # the seed is the turned pose asked for
    assert torch.allclose(seed[:, :3], torch.as_tensor(rotation))
