"""The ``tunneled`` test (redsim.integrators.tunneling): a step whose path passed through a contact is reported.

The case is the one the stability bench's ``impact`` regime makes: the two-link chain thrown up at its hook. At
10 m/s a 0.02 s full-space step moves 0.2 m against a wire 0.03 m thick (tube and margins), every step converges,
no energy is gained, and the chain flies off; at 1 m/s the hook catches it.
"""

from __future__ import annotations

import itertools
import math

import gymnasium as gym
import numpy as np
import pytest
import torch

from redsim import scenes
from redsim.benches import stability
from redsim.integrators import FullSpace, FullState, ImplicitEuler
from redsim.integrators.tunneling import TunnelTest
from redsim.scene import Scene


def _thrown(speed: float, **options) -> tuple[Scene, ImplicitEuler, FullState]:
    """The mini chain, its 0.02 s full-space integrator (``options``: ImplicitEuler's) and its state with every link
    thrown up at ``speed`` [m/s]."""
    scene = scenes.build("mini_chain")
    x_dot = torch.zeros(scene.full_dof_count, dtype=torch.float64)
    x_dot[7::12] = speed  # t_y of every link
    sim = ImplicitEuler(FullSpace(scene), 0.02, **options)
    return scene, sim, sim.initial_state(None, scene.dof_map.restrict(x_dot.unsqueeze(0))[0])


def _thrown_up(speed: float, steps: int = 4, **options) -> tuple[torch.Tensor, list]:
    """The mini chain's link centres' heights [steps + 1, 2] [m] and its steps' StepInfo, every link thrown up at
    ``speed`` [m/s] (``options``: ImplicitEuler's)."""
    scene, sim, state = _thrown(speed, **options)
    q, infos = [state.q], []
    for _ in range(steps):
        state, info = sim.step(state)
        q.append(state.q)
        infos.append(info)
    x = scene.full_positions(torch.stack(q)).reshape(steps + 1, -1, 12)
    return x[:, :, 7], infos


def test_a_step_through_the_hook_is_flagged_and_one_the_hook_stops_is_not() -> None:
    heights, infos = _thrown_up(10.0, retry_tunneled=False)
    assert all(info.converged and not info.energy_gain for info in infos)  # nothing else says it
    assert float(heights[-1, 0]) > 0.5  # link 0 (hung at -0.075 m) is far above the hook: it passed through
    assert infos[0].tunneled and not infos[0].tunnel_caught

    heights, infos = _thrown_up(1.0)
    assert not any(info.tunneled or info.tunnel_caught for info in infos)
    assert float(heights[:, 0].max()) < 0.0  # the hook held it


@pytest.mark.parametrize(("speed", "minimizer"), [(10.0, "newton"), (100.0, "newton"), (10.0, "lbfgs")])
def test_a_step_through_the_hook_is_solved_again_and_caught_there(speed: float, minimizer: str) -> None:
    """By default a full-space step that tunneled is solved again from q_t within half the thinnest contact per
    iteration: the hook holds the chain thrown at it (it flew off to +3.1 m at 10 m/s, +39 m at 100 m/s). L-BFGS
    clips its steps too (unclipped, its solve again went through the hook as its first solve did)."""
    heights, infos = _thrown_up(speed, steps=3, minimizer=minimizer)
    assert infos[0].tunnel_caught and not infos[0].tunneled and infos[0].converged
    assert infos[0].iterations > 2  # both solves counted (the first took 1 or 2)
    assert not any(info.tunneled or info.energy_gain for info in infos)
    assert float(heights[:, 0].max()) < 0.1  # link 0 stays hooked (hung at -0.075 m)


def test_a_solve_again_that_does_not_converge_keeps_the_first_end_flagged() -> None:
    """Where the solve again ends unconverged, the step is the first solve's, flagged ``tunneled``, with the
    iterations of both solves: L-BFGS (max_iter 50) thrown at 100 m/s spends the whole budget of the solve again.
    With ``escape_saddles`` the 10 m/s catch ends on a saddle of the step (the link pressed on the round wire), and
    the solve that leaves it does not converge: that escape is dropped and the caught saddle kept (it kept the first
    end, through the hook)."""
    from redsim.integrators.implicit_euler import CATCH_ITERATIONS

    first, plain = _thrown_up(100.0, steps=1, minimizer="lbfgs", retry_tunneled=False)
    heights, infos = _thrown_up(100.0, steps=1, minimizer="lbfgs")
    assert infos[0].tunneled and not infos[0].tunnel_caught and infos[0].converged
    assert infos[0].iterations == plain[0].iterations + (1 + CATCH_ITERATIONS) * 50
    assert torch.equal(heights, first) and float(heights[-1, 0]) > 1.0  # the first end: through the hook

    from redsim.integrators.reference import _negative_curvature

    scene, sim, state = _thrown(10.0)
    state, info = sim.step(state)
    assert info.tunnel_caught and _negative_curvature(scene, state.q, None, None, 0.02) is not None  # a saddle
    heights, infos = _thrown_up(10.0, steps=1, escape_saddles=True)
    assert infos[0].tunnel_caught and infos[0].converged and not infos[0].tunneled
    assert (
        float(heights[-1, 0]) < 0.0 and infos[0].iterations > info.iterations
    )  # the saddle at the hook, escapes tried


def test_a_retry_is_refused_in_a_latent_space_and_off_costs_nothing() -> None:
    from redsim import pretrained
    from redsim.integrators import LatentSpace

    scene = scenes.build("mini_chain")
    space = LatentSpace(scene, pretrained.load("mini_chain"))
    with pytest.raises(ValueError, match="retry_tunneled needs the full space"):
        ImplicitEuler(space, 0.02, retry_tunneled=True)
    assert not ImplicitEuler(space, 0.02).retry_tunneled and ImplicitEuler(FullSpace(scene), 0.02).retry_tunneled


def test_the_test_needs_a_move_longer_than_half_the_contact_and_a_deeper_path() -> None:
    scene = scenes.build("mini_chain")
    test = TunnelTest(scene)
    (contact,) = test.contacts
    assert contact.feature_size == pytest.approx(0.03)  # the wire's contact: tube 0.01 m plus two margins of 0.01 m
    x = scene.full_positions(scene.q_seed.to(torch.float64).unsqueeze(0))
    lifted = x.clone()
    lifted[:, 7::12] += 0.2  # every link 0.2 m up: link 0 across the hook
    nudged = x.clone()
    nudged[:, 7::12] += 0.4 * contact.feature_size  # less than half the contact: not sampled
    spun = x.clone()  # link 0 turned 0.6 rad in its own plane about its centre: the hook stays in its hole
    c, s = math.cos(0.6), math.sin(0.6)
    frame = x[0, :12].reshape(3, 4)
    turn = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    spun[0, :12] = torch.cat([turn @ frame[:, :3], frame[:, 3:]], 1).reshape(-1)
    flags = test(torch.cat([x, x, x, x]), torch.cat([lifted, nudged, x, spun]))
    assert flags.tolist() == [True, False, False, False]
    infinite = lifted.clone()
    infinite[:, 7] = math.inf  # not tested (diverged): no OverflowError from its infinite move (a review's finding)
    assert test(torch.cat([x, x]), torch.cat([infinite, lifted]), torch.tensor([True, False])).tolist() == [False] * 2


def test_each_point_is_judged_against_its_own_ends() -> None:
    """A sheet particle whose path cuts through the ball is flagged although another rests inside the contact at both
    ends (comparing the contact's smallest clearance at the ends hid it; a review's finding)."""
    scene = scenes.build("cloth_ball")
    (contact,) = TunnelTest(scene).contacts
    x = scene.full_positions(scene.q_seed.to(torch.float64).unsqueeze(0))
    centre = x[0, contact.frames.dofs[0]].reshape(3, 4)[:, 3]
    reach = contact.shape.radius + contact.margin
    ahead, side = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    x_from, x_to = x.clone(), x.clone()
    through = centre + (reach - 0.09) * ahead  # 0.09 m deep at the middle of its path
    x_from[0, 3000:3003], x_to[0, 3000:3003] = through - 0.3 * side, through + 0.3 * side
    x_from[0, 0:3] = x_to[0, 0:3] = centre - (reach - 0.05) * ahead  # resting 0.05 m inside the margin
    assert contact.clearance(torch.cat([x_from, x_to])).max() < -0.04
    assert TunnelTest(scene)(x_from, x_to).tolist() == [True]


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
    assert row["tunnels_caught"] >= 1 and row["tunneled"] == 0 and row["unreported"] == 0
    assert "tunnels caught" in stability.markdown_rows([row])[0]


def test_the_solve_again_bounds_each_iterations_contact_move_by_the_radius(monkeypatch) -> None:
    """The retry's trust radius is on what the tunnel test samples: each iteration moves no contact point more than
    half the thinnest contact relative to its shape (both minimizers clip by ``largest_move``), while a link may turn
    further than the radius in its rotation entries (a per-entry radius of 0.015 held the 24-link chain's links to
    ~0.015 rad per iteration)."""
    from redsim import solvers

    scene, sim, state = _thrown(10.0)
    radius = 0.5 * scene.feature_size()
    seen = []
    search = solvers._line_search

    def watched(objective, point, direction):  # type: ignore[no-untyped-def]
        if objective.move_measure is not None:  # the full step, the longest a line search tries
            seen.append(objective.largest_move(point.u, direction))
        return search(objective, point, direction)

    monkeypatch.setattr(solvers, "_line_search", watched)
    _, info = sim.step(state)
    assert info.tunnel_caught and len(seen) > 5
    assert max(seen) <= 1.01 * radius and max(seen) > 0.5 * radius  # bound, and reached (the map is bilinear)


def test_a_path_across_the_wire_between_coarse_samples_is_flagged() -> None:
    """A point crossing the mini chain's wire (a torus of tube radius 0.01 m) 4.5 mm from its centre circle, 0.053 m
    in one step, goes 5.4 mm into the tube: past its core (5 mm). Sampled a quarter of the contact's 0.03 m apart, its
    samples straddled the wire's middle, the deepest 4.6 mm in, and it was not flagged (the mini chain's bottom link
    left the top one that way at 0.04 s steps under the accuracy bench's actions, no step flagged); sampled a quarter
    of the wire's thinnest part apart, it is."""
    from redsim.integrators.tunneling import _crossed

    scene = scenes.build("mini_chain")
    (contact,) = TunnelTest(scene).contacts
    side = 0.05 + 0.0045  # the centre circle's radius plus the offset, in the circle's plane
    a = torch.tensor([[[side, 0.0, -0.0263]]], dtype=torch.float64)
    b = torch.tensor([[[side, 0.0, 0.0263]]], dtype=torch.float64)
    assert float(contact.shape.distance(a).min()) > contact.margin  # both ends clear of the contact
    assert float(contact.shape.distance((a + b) / 2)) < -0.005  # the middle past the core
    flags = _crossed(contact, 0.005, a, b, torch.tensor([True]), torch.tensor([True]))  # half the wire's radius
    assert flags.tolist() == [True]


@pytest.mark.parametrize("length", [0.053, 8.8, 1e4])
def test_a_path_across_the_wire_is_flagged_however_long(length: float) -> None:
    """The crossing above, the point thrown ``length`` [m] in one step: only the part of its path inside the ball that
    holds the torus is sampled, so a long path is sampled there as finely as a short one (the stiff mini chain's first
    full-space step under 15 kN moved a link 8.8 m through the other's wire: sampled along the whole path at most
    TUNNEL_SAMPLES = 256 times, 3.4 cm apart, it stepped over the 1 cm wire, converged and unflagged, unlinked 2)."""
    from redsim.integrators.tunneling import _crossed

    (contact,) = TunnelTest(scenes.build("mini_chain")).contacts
    side = 0.05 + 0.0045  # 5.4 mm into the tube at the wire, as above
    a = torch.tensor([[[side, 0.0, -0.5 * length]]], dtype=torch.float64)
    b = torch.tensor([[[side, 0.0, 0.5 * length]]], dtype=torch.float64)
    valid = torch.tensor([True])
    assert _crossed(contact, 0.005, a, b, valid, valid).tolist() == [True]
    beside = torch.tensor([[[0.2, 0.0, 0.0]]], dtype=torch.float64)  # the same path 0.2 m off: it misses the ball
    assert _crossed(contact, 0.005, a + beside, b + beside, valid, valid).tolist() == [False]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("length", [8.8, 1e3])
def test_a_long_slanted_path_across_the_wire_is_flagged_in_either_dtype(dtype: torch.dtype, length: float) -> None:
    """The crossing above at 45 degrees, ``length`` [m] long, in an env's float32 too: the part inside the torus's
    ball is found from the line's point nearest the centre (the quadratic's discriminant b^2 - a c cancelled in
    float32 past a few hundred metres and kept that point only, here outside the tube: unflagged)."""
    from redsim.integrators.tunneling import _crossed

    (contact,) = TunnelTest(scenes.build("mini_chain").to(dtype=dtype)).contacts
    at = torch.tensor([0.05 + 0.0045, 0.0, 0.0], dtype=torch.float64)  # in the tube, as above
    way = torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64) / math.sqrt(2.0)
    a, b = ((at + length * s * way).to(dtype)[None, None] for s in (-0.3, 0.7))
    valid = torch.tensor([True])
    assert _crossed(contact, 0.005, a, b, valid, valid).tolist() == [True]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_part_of_a_leg_inside_the_ball_holds_every_point_of_it_there(dtype: torch.dtype) -> None:
    """Random legs of 1 mm to 10 km near a ball of radius 0.06 m (the torus's), ending inside, outside, passing by or
    through it, and of no length: every point of a leg sampled 2001 times that lies inside the ball (computed in
    float64) lies on its clipped part (to the dtype's round-off of the leg's ends, and 1 um), and the clipped ends of
    a leg that enters the ball lie in it."""
    from redsim.integrators.tunneling import _inside_bounding_ball

    radius, legs = 0.06, 400
    g = torch.Generator().manual_seed(0)
    start = torch.randn(legs, 3, generator=g, dtype=torch.float64)
    start = start / start.norm(dim=-1, keepdim=True) * radius * 3 * torch.rand(legs, 1, generator=g).double()
    way = torch.randn(legs, 3, generator=g, dtype=torch.float64)
    way = way / way.norm(dim=-1, keepdim=True)
    length = 10.0 ** (-3 + 7 * torch.rand(legs, 1, generator=g, dtype=torch.float64))
    length[:20] = 0.0
    start[20:100] = start[20:100] - 0.5 * length[20:100] * way[20:100]  # centred on the ball's neighbourhood
    start, end = start.to(dtype), (start + length * way).to(dtype)
    clipped_start, clipped_end = (p.double() for p in _inside_bounding_ball(radius, start, end))
    start, end = start.double(), end.double()
    t = torch.linspace(0.0, 1.0, 2001, dtype=torch.float64)[:, None, None]
    points = start + t * (end - start)  # [2001, legs, 3]
    inside = points.norm(dim=-1) < radius
    tol = 4 * torch.finfo(dtype).eps * torch.maximum(start.norm(dim=-1), end.norm(dim=-1)) + 1e-6  # [legs] [m]
    kept = clipped_end - clipped_start
    along = ((points - clipped_start) * kept).sum(-1) / (kept * kept).sum(-1).clamp_min(1e-300)
    off = (points - (clipped_start + along.clamp(0.0, 1.0)[..., None] * kept)).norm(dim=-1)  # from the clipped part
    assert bool((off[inside] <= tol.expand_as(off)[inside]).all()), float((off - tol)[inside].max())
    missed = ~inside.any(0)
    ends = torch.stack([clipped_start, clipped_end]).norm(dim=-1)
    assert bool((ends[:, ~missed] <= radius + tol[~missed]).all())


def test_a_float32_path_far_out_is_tested_without_error() -> None:
    """A float32 point 1e20 m out moved 1e19 m (finite, so tested): the product of its position and move overflows
    the dtype, and the part inside the ball came out NaN, so sizing the samples raised ValueError (NaN to integer);
    the whole leg is sampled instead, far from the wire: not flagged."""
    from redsim.integrators.tunneling import _crossed

    (contact,) = TunnelTest(scenes.build("mini_chain").to(dtype=torch.float32)).contacts
    a = torch.tensor([[[1e20, 0.0, 1.0]]], dtype=torch.float32)
    valid = torch.tensor([True])
    assert _crossed(contact, 0.005, a, a + torch.tensor([1e19, 0.0, 0.0]), valid, valid).tolist() == [False]


def test_a_long_thin_plate_is_sampled_finely_across_however_long_the_path() -> None:
    """A 2 x 2 m plate 1 cm thick crossed straight through by a 2.4 m path: its bounding ball's diameter holds ~4,500
    samples an eighth of the plate's half thickness apart, so a sample lies near its middle plane; capped at
    TUNNEL_SAMPLES = 256 (9.5 mm apart across the 10 mm plate) the deepest sample was 0.3 mm in (helper-275 saw a
    plate missed whole on another path)."""
    from types import SimpleNamespace

    from redsim.effects.sdf import Box
    from redsim.integrators.tunneling import _deepest, sample_limit

    plate = SimpleNamespace(shape=Box((1.0, 1.0, 0.005)), feature_size=0.02, margin=0.005)
    assert sample_limit(plate) > 4000
    path = torch.tensor([[[0.5, 0.5, -1.2]], [[0.5, 0.5, 1.2]]], dtype=torch.float64)  # [2, 1, 3]
    assert float(_deepest(plate, path)) < -0.004  # the plate's middle plane is crossed: deeper than 4 of its 5 mm


def test_a_wire_crossing_another_between_two_samples_is_flagged() -> None:
    """The chain's contact points are centre-line samples 13 mm apart, so a link's wire crossing its neighbour's 10 mm
    tube between two samples is only sure to bring one within 6.5 mm of the other's centre line: 3.5 mm into the tube,
    short of half its radius (the 24-link chain came apart at 0.1 s steps under the accuracy bench's actions, its
    deepest sampled path 4.8 mm in, no step flagged). The depth a crossing needs follows the samples' spacing."""
    from redsim.integrators.tunneling import _crossed, core_depth, path_spacing, sample_gap

    scene = scenes.build("chain")
    test = TunnelTest(scene)
    (contact,) = test.contacts
    gap = sample_gap(contact, scene.full_positions(scene.q_seed.unsqueeze(0)))
    assert gap == pytest.approx(2 * 0.05 * math.sin(math.pi / 24), rel=1e-6)  # chords of 24 samples on 0.05 m
    assert test.cores == [core_depth(contact, gap)]
    assert core_depth(contact, gap) == pytest.approx(0.01 - gap / 2 - path_spacing(contact) / 2)
    side = 0.05 + 0.0052  # 4.8 mm into the tube at the path's middle
    a = torch.tensor([[[side, 0.0, -0.06]]], dtype=torch.float64)
    b = torch.tensor([[[side, 0.0, 0.06]]], dtype=torch.float64)
    valid, tested = torch.tensor([True]), torch.tensor([True])
    assert _crossed(contact, test.cores[0], a, b, valid, tested).tolist() == [True]
    assert _crossed(contact, 0.005, a, b, valid, tested).tolist() == [False]  # the core before
    assert core_depth(contact, 0.0) == 0.005 and core_depth(contact, 1.0) == 0.0025  # dense points; the floor


def test_a_path_round_the_ball_is_not_flagged_where_its_chord_through_the_ball_is() -> None:
    """A sheet particle carried 160 degrees round the ball 4 mm inside the margin, as cloth_ball's dt x5 push wrapped
    the cloth in one step: the chord between its ends cuts 98 mm into the 0.12 m ball (flagged), the path through the
    states it went through does not (:meth:`TunnelTest.along`); the same ends reached straight through the ball are."""
    scene = scenes.build("cloth_ball")
    test = TunnelTest(scene)
    (contact,) = test.contacts
    x = scene.full_positions(scene.q_seed.to(torch.float64).unsqueeze(0))
    centre = x[0, contact.frames.dofs[0]].reshape(3, 4)[:, 3]
    radius = contact.shape.radius + contact.margin - 0.004
    angles = torch.linspace(-math.radians(80.0), math.radians(80.0), 20, dtype=torch.float64)
    ahead, up = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    arc = centre + radius * (angles.cos()[:, None] * ahead + angles.sin()[:, None] * up)  # [20, 3]
    chord = arc[0] + torch.linspace(0.0, 1.0, 20, dtype=torch.float64)[:, None] * (arc[-1] - arc[0])
    paths = []
    for points in (arc, chord):
        path = x.repeat(20, 1)
        path[:, 3000:3003] = points
        paths.append(path)
    assert float(contact.shape.distance(chord - centre).min()) < -0.09  # the chord's middle 98 mm in
    assert test(paths[0][:1], paths[0][-1:]).tolist() == [True]  # the ends alone: the chord
    assert not test.along(paths[0]) and test.along(paths[1])
    assert not test.along(paths[0][[0, 10, 19]])  # three states: two 80-degree chords, each 26 mm in (core 60 mm)


def _linking_number(a: torch.Tensor, b: torch.Tensor) -> float:
    """Gauss's linking number of two closed polygons a [P, 3] and b [Q, 3] (+-1: interlocked, 0: apart)."""
    da, db = torch.roll(a, -1, 0) - a, torch.roll(b, -1, 0) - b
    r = (a + 0.5 * da)[:, None] - (b + 0.5 * db)[None]
    cross = torch.cross(da[:, None].expand_as(r), db[None].expand_as(r), dim=-1)
    return float(((r * cross).sum(-1) / r.norm(dim=-1) ** 3).sum() / (4.0 * math.pi))


@pytest.mark.slow
def test_the_chain_thrown_at_its_hook_stays_linked() -> None:
    """The 24-link chain thrown up at 10 m/s: every full-space step is caught at the contact and every pair (hook and
    link 0, link k and k + 1) stays interlocked (Gauss linking number). The chord between a solve again's ends read a
    crossing (a link's points swept by its turn) where the states it went through crossed nothing, and the first end
    was kept: three pairs came apart at the fourth step (~30 s)."""
    scene = scenes.build("chain")
    x_dot = torch.zeros(scene.full_dof_count, dtype=torch.float64)
    x_dot[7::12] = 10.0  # t_y of every link
    sim = ImplicitEuler(FullSpace(scene), 0.02)
    state = sim.initial_state(None, scene.dof_map.restrict(x_dot.unsqueeze(0))[0])
    angles = torch.linspace(0.0, 2.0 * math.pi, 97, dtype=torch.float64)[:-1]
    circle = 0.05 * torch.stack([angles.cos(), angles.sin(), torch.zeros_like(angles)], 1)  # a link's centre line
    hook = circle @ torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=torch.float64).T
    for _ in range(4):
        state, info = sim.step(state)
        assert info.converged and not info.tunneled
        frames = scene.full_positions(state.q.unsqueeze(0))[0].reshape(-1, 3, 4)
        lines = [hook, *(circle @ f[:, :3].T + f[:, 3] for f in frames)]
        assert all(abs(_linking_number(a, b)) > 0.5 for a, b in itertools.pairwise(lines))
    assert float(frames[0, 1, 3]) > 0.07  # link 0 pressed up against the hook's top (it hangs at -0.075 m)


def test_a_point_pushed_through_the_wire_in_short_legs_is_flagged_along_its_path() -> None:
    """The mini chain lifted 0.2 m, link 0 up through the hook's wire, in 80 legs of 2.5 mm (each far shorter than a
    solve again's iteration, 15 mm at most): the path through its states is flagged as the chord between its ends is.
    Lifted so, then carried 0.2 m aside, down beside the hook and back to where it started, neither is: the end is
    its start (the ends' net move, not the path's length, picks the points tested)."""
    scene = scenes.build("mini_chain")
    test = TunnelTest(scene)
    x = scene.full_positions(scene.q_seed.to(torch.float64).unsqueeze(0))

    def moved(d: tuple[float, float, float]) -> torch.Tensor:
        y = x.clone()
        for axis, by in enumerate(d):
            y[0, 3 + 4 * axis :: 12] += by  # every link's t_x, t_y, t_z
        return y

    up = [(0.0, 0.2 * k / 80, 0.0) for k in range(81)]
    lifted = torch.cat([moved(d) for d in up])
    assert test(lifted[:1], lifted[-1:]).tolist() == [True] and test.along(lifted)
    back = [(0.0, 0.2, 0.2 * k / 40) for k in range(1, 41)] + [(0.0, 0.2 - 0.2 * k / 40, 0.2) for k in range(1, 41)]
    back += [(0.0, 0.0, 0.2 - 0.2 * k / 40) for k in range(1, 41)]
    loop = torch.cat([lifted, *(moved(d) for d in back)])
    assert torch.equal(loop[-1:], x) and not test.along(loop) and not test(loop[:1], loop[-1:])[0]


def test_a_solve_again_is_judged_along_its_start_its_kept_states_and_its_end(monkeypatch) -> None:
    """The path :meth:`TunnelTest.along` reads: q_t, each state the solve again accepted, its end; a saddle escape's
    states where it is kept (here one from 1 cm above the caught saddle), not where it is dropped (the real escape
    at 10 m/s stalls after 50 iterations); the objective's path and trust radius are reset where the solve raises."""
    from redsim.integrators import implicit_euler

    def judged(speed: float) -> tuple[list[torch.Tensor], FullState, FullState, list]:
        _, sim, state = _thrown(speed, escape_saddles=True)
        seen, solves = [], []
        along, minimize = sim._through_contact_along, sim._minimize

        def spied_along(path: list[torch.Tensor]) -> bool:
            seen.append([u.clone() for u in path])
            return along(path)

        def spied_minimize(objective, start, **kw):  # type: ignore[no-untyped-def]
            end, info = minimize(objective, start, **kw)
            solves.append(info)
            return end, info

        sim._through_contact_along, sim._minimize = spied_along, spied_minimize
        end, info = sim.step(state)
        assert info.tunnel_caught and len(seen) == 1
        return seen[0], state, end, solves

    path, start, end, solves = judged(10.0)
    assert [s.converged for s in solves] == [True, True, False]  # first solve, solve again, dropped escape
    assert torch.equal(path[0], start.q) and torch.equal(path[-1], end.q) and len(path) == 1 + solves[1].iterations

    scene = scenes.build("mini_chain")
    lift = torch.zeros(scene.full_dof_count, dtype=torch.float64)
    lift[7::12] = 0.01  # every link 1 cm up
    lift, escapes = scene.dof_map.restrict(lift.unsqueeze(0))[0], []

    def beside(objective, u, energy, direction):  # type: ignore[no-untyped-def]
        if objective.path is None or escapes:
            return None
        escapes.append(u)  # the caught saddle
        return u + lift

    monkeypatch.setattr(implicit_euler, "_negative_curvature", lambda scene, u, *_: torch.ones_like(u))
    monkeypatch.setattr(implicit_euler, "_lower_along", beside)
    path, start, end, solves = judged(10.0)
    assert [s.converged for s in solves] == [True, True, True] and solves[2].iterations >= 1  # escape kept
    assert len(path) == 1 + solves[1].iterations + solves[2].iterations
    assert torch.equal(path[solves[1].iterations], escapes[0]) and torch.equal(path[-1], end.q)  # the saddle, kept

    _, sim, state = _thrown(10.0)
    minimize, objectives = sim._minimize, []

    def raising(objective, start, **kw):  # type: ignore[no-untyped-def]
        objectives.append(objective)
        if objective.path is not None:
            minimize(objective, start, max_iter=3, tol=kw["tol"])
            raise RuntimeError("solver failed")
        return minimize(objective, start, **kw)

    sim._minimize = raising
    with pytest.raises(RuntimeError, match="solver failed"):
        sim.step(state)
    assert objectives[-1].path is None and objectives[-1].max_step == math.inf
