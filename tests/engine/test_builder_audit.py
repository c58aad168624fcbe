"""Builder contracts no catalog scene exercised (hand mutation audit, helper-283): each test here failed under a
one-line mutation that every other engine test passed.

- A rigid body whose frame origin is not its centre of mass (``SceneBuilder.add_body``'s docstring allows it): gravity
  acts at the centre, block[:3, 3] / block[3, 3] in the body frame. Every catalog body is centred (block[:3, 3] = 0),
  so gravity placed at block[:3, 3] (the division by the mass dropped) passed them all.
- A condition space whose low bound is not 0: its samples (cubature's training states, the modal pull's conditions,
  ``redsim sample``) lie in [low, high]; ``low + u * high`` (the span's low term dropped) passed the catalog tests.
- A tetrahedron of zero rest volume (four coplanar vertices): refused with its index, as an inverted one is; with the
  check reduced to inverted elements it was accepted, and its energy is NaN at every state (D_m has no inverse).
"""

from __future__ import annotations

import pytest
import torch

from redsim import SceneBuilder
from redsim.effects import NeoHookean


def _off_centre_body_scene(mass: float, centre: tuple[float, float, float]):
    """One affine body of ``mass`` [kg] whose centre of mass sits at ``centre`` [m] in its frame, under gravity."""
    c = torch.tensor(centre, dtype=torch.float64)
    block = torch.zeros(4, 4, dtype=torch.float64)
    block[:3, :3] = mass * (torch.outer(c, c) + 0.01 * torch.eye(3, dtype=torch.float64))  # a second moment
    block[:3, 3] = block[3, :3] = mass * c
    block[3, 3] = mass
    builder = SceneBuilder(3)
    builder.add_body(block)
    builder.add_gravity((0.0, 0.0, -9.81))
    return builder.finalize("off_centre_body")


def test_gravity_on_a_body_acts_at_its_centre_of_mass_not_at_the_first_moment() -> None:
    mass, centre = 2.5, (0.4, -0.2, 0.3)
    scene = _off_centre_body_scene(mass, centre)
    angle = 0.7  # a turn about x moves the centre's height: R c + t
    R = torch.tensor(
        [[1.0, 0.0, 0.0], [0.0, torch.cos(torch.tensor(angle)), -torch.sin(torch.tensor(angle))],
         [0.0, torch.sin(torch.tensor(angle)), torch.cos(torch.tensor(angle))]],
        dtype=torch.float64,
    )  # fmt: skip
    t = torch.tensor([0.1, 0.2, 1.5], dtype=torch.float64)
    q = torch.cat([R, t[:, None]], 1).reshape(1, 12)
    height = float((R @ torch.tensor(centre, dtype=torch.float64) + t)[2])
    assert float(scene.energy(q)[0]) == pytest.approx(mass * 9.81 * height, rel=1e-12)


def test_a_condition_space_samples_its_whole_range_and_nothing_outside_it() -> None:
    builder = SceneBuilder(2)
    builder.add_particles(torch.zeros(1, 2), torch.ones(1))
    builder.add_condition("stiffness_ratio", 2.0, 5.0)
    builder.add_condition("offset", -1.0, -0.5)
    scene = builder.finalize("conditioned")
    samples = scene.condition_space.sample(4000, torch.Generator().manual_seed(0))
    low, high = torch.tensor([2.0, -1.0]), torch.tensor([5.0, -0.5])
    assert bool((samples >= low).all()) and bool((samples <= high).all())
    span = high - low  # uniform over the range: it reaches near both ends and its mean is the middle
    assert bool((samples.amin(0) < low + 0.01 * span).all()) and bool((samples.amax(0) > high - 0.01 * span).all())
    assert torch.allclose(samples.mean(0).to(torch.float64), (0.5 * (low + high)).to(torch.float64), atol=0.05)


def test_a_tetrahedron_of_zero_rest_volume_is_refused_and_named() -> None:
    rest = torch.tensor(
        [[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]],  # four coplanar vertices
         [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]],
        dtype=torch.float64,
    )  # fmt: skip
    with pytest.raises(ValueError, match=r"element 0 of 'solid' is degenerate"):
        NeoHookean("solid", torch.arange(24).reshape(2, 4, 3), rest, 1e4, 0.3)


def test_a_driver_targets_its_handle_s_seed_at_zero_and_its_angle_inverts_its_target() -> None:
    """:class:`redsim.scene.Driver`'s contract: z = 0 targets the handle's seed position (the phase is the seed's
    angle), targets go round the circle anticlockwise from axes[0] towards axes[1], and ``angle`` reads back the latent
    angle of a target. The catalog's crank seeds sit where a wrong phase sign or swapped atan2 arguments still passed
    (hand mutation audit, helper-283)."""
    builder = SceneBuilder(3)
    seed = (0.3, 0.4, 0.2)  # 0.5 m from the centre in the plane, at 53.13 degrees from axes[0]
    ids = builder.add_particles(torch.tensor([seed]), torch.ones(1))
    builder.add_handle("tip", builder.particle_points(ids))
    builder.add_driver("turn", "tip", (0.0, 0.0, 0.2), ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)))
    driver = builder.finalize("driven").driver("turn")
    assert driver.radius == pytest.approx(0.5)
    assert torch.allclose(
        driver.target(torch.zeros(1, dtype=torch.float64))[0], torch.tensor(seed, dtype=torch.float64)
    )
    quarter = driver.target(torch.tensor([0.5 * torch.pi], dtype=torch.float64))[0]  # 90 degrees on: (-0.4, 0.3)
    assert torch.allclose(quarter, torch.tensor([-0.4, 0.3, 0.2], dtype=torch.float64), atol=1e-12)
    angles = torch.tensor([-2.5, -1.0, 0.0, 0.3, 1.2, 2.0], dtype=torch.float64)
    back = driver.angle(driver.target(angles))
    assert torch.allclose(
        torch.remainder(back - angles - driver.phase + torch.pi, 2 * torch.pi),
        torch.full_like(angles, torch.pi),
        atol=1e-12,
    )


def test_a_load_given_by_handle_name_lands_on_that_handle() -> None:
    """``scene.pack_loads({name: force})`` puts each force in its handle's row (the tensor form's order): with every
    named load written into the first handle's row the catalog tests still passed, since they load one handle or the
    first (hand mutation audit, helper-283)."""
    builder = SceneBuilder(2)
    ids = builder.add_particles(torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]), torch.ones(3))
    for i, name in enumerate(("left", "middle", "right")):
        builder.add_handle(name, builder.particle_points(ids[i : i + 1]))
    scene = builder.finalize("three_handles")
    packed = scene.pack_loads({"right": [0.5, -2.0], "middle": [1.0, 3.0]}, 2)
    expected = torch.tensor([[0.0, 0.0], [1.0, 3.0], [0.5, -2.0]], dtype=torch.float64).expand(2, 3, 2)
    assert torch.equal(packed, expected)
    q = torch.tensor([[0.1, 0.2, 1.3, 0.4, 2.5, 0.6]], dtype=torch.float64)  # E = -sum F . p over the loaded points
    assert float(scene.energy(q, {"right": [0.5, -2.0]})[0]) == pytest.approx(-(0.5 * 2.5 - 2.0 * 0.6))
