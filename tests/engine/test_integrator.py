"""The full-space reference simulator: Hessian assembly, minimizers, implicit Euler, static equilibria.

Everything runs in float64. Tolerances: exact recursions (linear forces, solved by one
Newton step) hold to round-off (1e-10 on O(1) m positions); physics comparisons are bounded
by the discretization error they name (O(h), O(strain), penalty compliance).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch

from redsim import PointSet, Scene, SceneBuilder
from redsim.effects import FrameSet, NeoHookean, PointPairPenalty, RigidOrthogonality, SDFContact, Sphere
from redsim.hessian import element_hessians, energy_hessian
from redsim.integrators import (
    FullSpace,
    FullState,
    ImplicitEuler,
    Inertia,
    PotentialObjective,
    SceneConstants,
    static_equilibrium,
)
from redsim.solvers import MINIMIZERS, ConvergenceError, newton

G = 9.81  # [m/s^2]
GRAVITY = torch.tensor([0.0, -G, 0.0], dtype=torch.float64)  # float64, so -9.81 is not rounded to float32

# Unit cube, vertex i at (i & 1, (i >> 1) & 1, (i >> 2) & 1), cut into the 6 Kuhn tets around the 0-7 diagonal.
CUBE = torch.tensor([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=torch.float64)
KUHN = [[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]]
TOP = [2, 3, 6, 7]  # y = 1, pinned
BOTTOM = [0, 1, 4, 5]  # y = 0, loaded
# Consistent nodal shares of a uniform traction on the bottom face, triangulated (0, 1, 5) + (0, 4, 5).
BOTTOM_SHARES = [1 / 3, 1 / 6, 1 / 6, 1 / 3]


def _oriented_tets() -> torch.Tensor:
    tets = torch.tensor(KUHN)
    v = CUBE[tets]
    det = torch.linalg.det(v[:, 1:] - v[:, :1])
    return torch.where((det < 0)[:, None], tets[:, [0, 1, 3, 2]], tets)


def _cube(young: float, poisson: float, *, gravity: bool = False, density: float = 1000.0) -> Scene:
    """A 1 m elastic cube hanging from its pinned top face, with a load handle on its bottom face."""
    b = SceneBuilder(dim=3)
    b.add_particles(CUBE, torch.full((8,), density / 8.0))
    tets = _oriented_tets()
    b.add_effect(NeoHookean("elastic", b.particle_dofs(tets), CUBE[tets], young, poisson))
    b.pin_particles(torch.tensor(TOP))
    b.add_handle("bottom", b.particle_points(torch.tensor(BOTTOM)), torch.tensor(BOTTOM_SHARES))
    if gravity:
        b.add_gravity(GRAVITY)
    return b.finalize("cube")


def _mass_block(mass: float, second_moment: tuple[float, float, float]) -> torch.Tensor:
    block = torch.zeros(4, 4, dtype=torch.float64)
    block[:3, :3] = torch.diag(torch.tensor(second_moment, dtype=torch.float64))
    block[3, 3] = mass
    return block


def _rot_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _pendulum(angle: float, *, mass: float, moment: tuple[float, float, float], arm: float, joint: float) -> Scene:
    """A rigid body hanging from the world origin by a joint penalty at body point (0, arm, 0), tilted by angle."""
    b = SceneBuilder(dim=3)
    R = _rot_z(angle)
    pivot_local = torch.tensor([[0.0, arm, 0.0]], dtype=torch.float64)
    t = -(R @ pivot_local[0])
    body = b.add_body(_mass_block(mass, moment), torch.cat([R, t[:, None]], dim=1))
    b.add_effect(RigidOrthogonality("rigid", b.body_dofs(body)[None], 5000.0))
    b.add_effect(
        PointPairPenalty("joint", b.body_points(body, pivot_local), PointSet.world(torch.zeros(1, 3), k=4), joint)
    )
    b.add_gravity(GRAVITY)
    return b.finalize("pendulum")


# -- Hessians -----------------------------------------------------------------------------------
def _mixed_scene() -> Scene:
    """Two tets (one vertex pinned), a rigid body jointed to a vertex, sphere contact on the body, gravity."""
    b = SceneBuilder(dim=3)
    verts = torch.tensor(
        [[0.3, 0.1, 0.0], [1.0, 0.0, 0.0], [0.2, 1.0, 0.1], [0.1, 0.2, 1.0], [1.0, 1.0, 1.0]], dtype=torch.float64
    )
    b.add_particles(verts, torch.ones(5))
    tets = torch.tensor([[0, 1, 2, 3], [1, 2, 3, 4]])
    rest = verts[tets]
    det = torch.linalg.det(rest[:, 1:] - rest[:, :1])
    tets = torch.where((det < 0)[:, None], tets[:, [0, 1, 3, 2]], tets)
    b.add_effect(NeoHookean("elastic", b.particle_dofs(tets), verts[tets], 1e3, 0.3))
    b.pin_particles(torch.tensor([4]))
    body = b.add_body(_mass_block(2.0, (0.1, 0.2, 0.3)))
    b.add_effect(RigidOrthogonality("rigid", b.body_dofs(body)[None], 50.0))
    b.add_effect(
        PointPairPenalty(
            "joint", b.body_points(body, torch.tensor([[0.2, 0.0, 0.0]])), b.particle_points(torch.tensor([0])), 300.0
        )
    )
    b.add_effect(
        SDFContact(
            "contact", b.particle_points(torch.arange(4)), FrameSet.body(b.body_dofs(body), 4), Sphere(0.9), 200.0
        )
    )
    b.add_gravity(GRAVITY)
    return b.finalize("mixed")


def test_assembled_hessian_matches_autograd_and_finite_differences() -> None:
    scene = _mixed_scene()
    g = torch.Generator().manual_seed(0)
    q = scene.q_seed + 0.05 * torch.randn(scene.free_dof_count, generator=g, dtype=torch.float64)
    contact = scene.effect("contact")
    gaps = contact.signed_distance(scene.full_positions(q[None])[:, contact.element_dofs])
    assert bool((gaps < -0.05).any()) and bool((gaps > 0.05).any())  # active and inactive contacts

    H = energy_hessian(scene, q, project=False).toarray()
    reference = torch.autograd.functional.hessian(lambda v: scene.energy(v), q).numpy()
    np.testing.assert_allclose(H, reference, rtol=1e-10, atol=1e-9 * np.abs(reference).max())

    def grad(v: torch.Tensor) -> np.ndarray:
        v = v.clone().requires_grad_(True)
        return torch.autograd.grad(scene.energy(v), v)[0].numpy()

    eps = 1e-6
    eye = torch.eye(q.numel(), dtype=torch.float64)
    fd = np.stack([(grad(q + eps * e) - grad(q - eps * e)) / (2 * eps) for e in eye], axis=1)
    np.testing.assert_allclose(H, fd, atol=1e-5 * np.abs(fd).max())

    projected = energy_hessian(scene, q, project=True).toarray()
    np.testing.assert_allclose(projected, projected.T, atol=1e-12 * np.abs(projected).max())
    assert np.linalg.eigvalsh(projected).min() > -1e-9 * np.abs(projected).max()
    # Affine terms have no Hessian; PSD projection leaves PSD blocks alone.
    x = scene.full_positions(q[None])[0]
    assert not bool(element_hessians(scene.effect("gravity"), x).any())
    joint = element_hessians(scene.effect("joint"), x)
    torch.testing.assert_close(element_hessians(scene.effect("joint"), x, project=True), joint)


def test_a_collapsed_bending_hinge_adds_no_curvature_and_the_step_goes_on() -> None:
    """A cloth vertex moved onto its neighbour collapses the hinges on that edge: their dihedral angle has no second
    derivative (autograd: NaN), and the projected full-space step failed in eigh. Their blocks are zero now, the
    other hinges' as before, and the step converges to a finite state."""
    import redsim

    scene = redsim.scenes.build("toy_small_cloth")
    full_to_free = scene.dof_map.full_to_free()
    hinges = scene.effect("bending").element_dofs  # [E, 12]: edge start, edge end, two apexes
    hinge = next(t for t in range(hinges.shape[0]) if bool((full_to_free[hinges[t]] >= 0).all()))
    q = scene.q_seed.clone()
    x = scene.full_positions(q[None])[0]
    q[full_to_free[hinges[hinge, 3:6]]] = x[hinges[hinge, 0:3]]  # the edge's end onto its start
    x = scene.full_positions(q[None])[0]
    blocks = element_hessians(scene.effect("bending"), x)
    assert bool(blocks.isfinite().all()) and not bool(blocks[hinge].any())
    collapsed = ~blocks.flatten(1).any(1)
    regular = element_hessians(scene.effect("bending"), scene.full_positions(scene.q_seed[None])[0])
    assert bool(regular.flatten(1).any(1)[collapsed].all())  # zeroed only where collapsed
    assert np.isfinite(energy_hessian(scene, q, project=True).data).all()
    integrator = ImplicitEuler(FullSpace(scene), 0.01)
    state, info = integrator.step(integrator.initial_state(q))
    assert info.converged and bool(state.q.isfinite().all())


# -- implicit Euler: exact recursions and physics -----------------------------------------------
def test_falling_particles_match_discrete_and_analytic_solutions() -> None:
    b = SceneBuilder(dim=3)
    b.add_particles(torch.tensor([[0.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 3.0]]), torch.tensor([1.0, 2.0, 0.5]))
    b.add_gravity(GRAVITY)
    scene = b.finalize("falling")
    v0 = torch.tensor([1.0, 2.0, 0.0, -0.5, 0.0, 0.3, 0.0, 4.0, -1.0], dtype=torch.float64)
    gravity = GRAVITY.repeat(3)
    errors = []
    for h in (0.02, 0.01):
        sim = ImplicitEuler(FullSpace(scene), h, strict=True)
        steps = round(0.4 / h)
        traj, infos = sim.rollout(sim.initial_state(velocity=v0), steps)
        n = torch.arange(steps + 1, dtype=torch.float64)[:, None]
        discrete = scene.q_seed + n * h * v0 + h**2 * gravity * n * (n + 1) / 2
        torch.testing.assert_close(traj, discrete, rtol=0.0, atol=1e-10)
        t = n * h
        errors.append(float((traj - (scene.q_seed + v0 * t + 0.5 * gravity * t**2)).abs().max()))
        assert all(i.converged for i in infos)
    assert errors[0] == pytest.approx(G * 0.02 * 0.4 / 2, rel=1e-6)  # the O(h) gap g h t / 2
    assert errors[0] / errors[1] == pytest.approx(2.0, rel=1e-6)


def test_falling_rigid_body_matches_discrete_recursion() -> None:
    b = SceneBuilder(dim=3)
    body = b.add_body(_mass_block(3.0, (0.2, 0.1, 0.3)), torch.eye(3, 4, dtype=torch.float64))
    b.add_effect(RigidOrthogonality("rigid", b.body_dofs(body)[None], 5000.0))
    b.add_gravity(GRAVITY)
    scene = b.finalize("falling_body")
    h, steps = 0.01, 30
    v0 = torch.zeros(12, dtype=torch.float64)
    v0[[3, 7, 11]] = torch.tensor([0.5, 3.0, -1.0], dtype=torch.float64)  # t_x, t_y, t_z
    accel = torch.zeros(12, dtype=torch.float64)
    accel[7] = -G
    sim = ImplicitEuler(FullSpace(scene), h, strict=True)
    traj, _ = sim.rollout(sim.initial_state(velocity=v0), steps)
    n = torch.arange(steps + 1, dtype=torch.float64)[:, None]
    torch.testing.assert_close(traj, scene.q_seed + n * h * v0 + h**2 * accel * n * (n + 1) / 2, rtol=0.0, atol=1e-10)


def test_gravity_acts_at_a_bodys_centre_of_mass_where_its_frame_is_off_centre() -> None:
    """A body whose frame origin is not its centre of mass (mass block with block[:3, 3] != 0): turning it 90 degrees
    about z lifts the centre of mass by 1 m, and gravity's energy rises by m g (it stayed 0: gravity acted at the
    frame origin)."""
    points = CUBE - 0.5 + torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)  # 8 x 0.25 kg around (1, 0, 0)
    homogeneous = torch.cat([points, torch.ones(8, 1, dtype=torch.float64)], dim=1)
    block = 0.25 * homogeneous.T @ homogeneous
    b = SceneBuilder(dim=3)
    b.add_body(block)
    b.add_gravity(GRAVITY)
    scene = b.finalize("off_centre_body")
    turned = torch.tensor([[0.0, -1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]], dtype=torch.float64)
    lift = scene.energy_terms(turned.reshape(1, 12))["gravity"] - scene.energy_terms(scene.q_seed[None])["gravity"]
    torch.testing.assert_close(lift, torch.tensor([2.0 * G], dtype=torch.float64))


def _zero_crossings(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    i = np.nonzero(np.sign(x[:-1]) != np.sign(x[1:]))[0]
    return t[i] - x[i] * (t[i + 1] - t[i]) / (x[i + 1] - x[i])


def test_compound_pendulum_small_amplitude_period() -> None:
    mass, moment, arm = 1.0, (0.004, 0.03, 0.004), 0.3
    i_pivot = moment[0] + moment[1] + mass * arm**2  # about z: S_xx + S_yy + m d^2 [kg m^2]
    period = 2 * math.pi * math.sqrt(i_pivot / (mass * G * arm))
    scene = _pendulum(0.05, mass=mass, moment=moment, arm=arm, joint=1e5)
    h = 0.005
    sim = ImplicitEuler(FullSpace(scene), h, strict=True)
    traj, _ = sim.rollout(sim.initial_state(), math.ceil(1.7 * period / h))
    x = traj[:, 3].numpy()  # t_x, the centre of mass's horizontal position
    crossings = _zero_crossings(h * np.arange(x.size), x)
    assert crossings.size >= 3
    measured = 2 * float(np.mean(np.diff(crossings)))
    assert measured == pytest.approx(period, rel=0.02)
    assert 0.5 * abs(x[0]) < np.abs(x[-x.size // 3 :]).max() < abs(x[0])  # implicit Euler damps, but mildly here


# -- static equilibria -----------------------------------------------------------------------------
def test_static_stretch_matches_linear_elasticity() -> None:
    young, load = 1e6, 100.0  # [Pa], [N]: strain 1e-4 on a 1 m^2 x 1 m cube
    scene = _cube(young, 0.0)
    q, info = static_equilibrium(scene, {"bottom": [0.0, -load, 0.0]}, tol=1e-10)
    assert info.converged, info.message
    v = q.clone().requires_grad_(True)
    grad = torch.autograd.grad(scene.energy(v, {"bottom": [0.0, -load, 0.0]}), v)[0]
    assert float(grad.norm()) < 1e-8 * load
    x = scene.full_positions(q[None])[0].reshape(8, 3)
    stretch = -x[BOTTOM, 1]  # the bottom face started at y = 0
    expected = load * 1.0 / (young * 1.0)  # F L / (E A)
    torch.testing.assert_close(stretch, torch.full_like(stretch, expected), rtol=1e-2, atol=0.0)


def test_static_pendulum_hangs_straight_despite_rigid_null_modes() -> None:
    arm, mass, joint = 0.3, 1.0, 1e5
    scene = _pendulum(0.4, mass=mass, moment=(0.004, 0.03, 0.004), arm=arm, joint=joint)
    q, info = static_equilibrium(scene)
    assert info.converged, info.message
    # The joint stretches by m g / k_joint, and the affine body by e = m g d / (8 k_orth), the minimizer of
    # k_orth (2e + e^2)^2 - m g d e (penalty compliance, both ~1e-4 here).
    drop = arm * (1.0 + mass * G * arm / (8 * 5000.0)) + mass * G / joint
    torch.testing.assert_close(q[[3, 7, 11]], torch.tensor([0.0, -drop, 0.0], dtype=torch.float64), rtol=0.0, atol=1e-7)
    R = q.reshape(3, 4)[:, :3]
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=torch.float64), rtol=0.0, atol=1e-3)


# -- solver behaviour --------------------------------------------------------------------------------
def _hard_step(max_iter: int, strict: bool) -> tuple[ImplicitEuler, FullState]:
    sim = ImplicitEuler(FullSpace(_cube(1e5, 0.45, gravity=True)), 0.1, max_iter=max_iter, strict=strict)
    return sim, sim.initial_state()


def test_nonconvergence_is_reported_and_strict_raises() -> None:
    loads = {"bottom": [3e4, -5e4, 0.0]}
    sim, state = _hard_step(1, strict=False)
    new_state, info = sim.step(state, loads)
    assert not info.converged and info.iterations == 1
    assert "not converged" in info.message
    assert bool(torch.isfinite(new_state.q).all())
    sim, state = _hard_step(1, strict=True)
    with pytest.raises(RuntimeError) as error:
        sim.step(state, loads)
    assert isinstance(error.value, ConvergenceError) and not error.value.info.converged
    sim, state = _hard_step(50, strict=True)
    _, info = sim.step(state, loads)
    assert info.converged and info.iterations > 1


def test_newton_energy_decreases_and_large_steps_stay_finite() -> None:
    scene = _cube(1e7, 0.45, gravity=True)
    sim = ImplicitEuler(FullSpace(scene), 1 / 30, strict=True)
    _, info = sim.step(sim.initial_state(), {"bottom": [2e6, -4e6, 1e6]})
    history = np.array(info.history)
    assert info.iterations >= 3
    assert np.all(np.diff(history) <= 1e-12 * np.abs(history[:-1]))
    big = ImplicitEuler(FullSpace(scene), 1.0)
    traj, infos = big.rollout(big.initial_state(), 4, {"bottom": [0.0, -1e5, 0.0]})
    assert bool(torch.isfinite(traj).all())
    assert all(i.converged for i in infos), [i.message for i in infos]


def test_step_info_holds_the_energy_balance_and_a_dissipative_run_flags_no_gain() -> None:
    """mechanical_gain is K + E - W's change, as the stability bench's float64 ledger counts it; backward Euler on
    a loaded, kicked elastic cube only loses energy, so no step is flagged (the firing case, the cloth hit by its
    ball at 10 m/s, is the slow impact regime of tests/stability/test_bench_stability.py)."""
    from redsim.benches.stability import ledger

    scene = _cube(1e4, 0.45, gravity=True)
    sim = ImplicitEuler(FullSpace(scene), 0.02)
    kick = torch.linspace(-2.0, 2.0, scene.free_dof_count, dtype=torch.float64)
    start = sim.initial_state(velocity=kick)
    loads = torch.tensor([[[50.0 * (-1) ** t, -80.0, 20.0]] for t in range(12)], dtype=torch.float64)
    traj, infos = sim.rollout(start, 12, lambda t, _s: loads[t])
    h = ledger(scene, traj, loads, 0.02, start.q_prev)
    gains = torch.tensor([i.mechanical_gain for i in infos], dtype=torch.float64)
    assert torch.allclose(gains, h[1:] - h[:-1], rtol=1e-9, atol=1e-9 * float(h.abs().max()))
    assert bool((gains < 0).all()) and not any(i.energy_gain for i in infos)
    assert all(i.converged for i in infos)


def test_newton_and_lbfgs_agree_on_a_step() -> None:
    scene = _cube(1e4, 0.3, gravity=True)
    loads = {"bottom": [50.0, -200.0, 0.0]}
    results = {}
    for name, max_iter in (("newton", 50), ("lbfgs", 500)):
        sim = ImplicitEuler(FullSpace(scene), 0.05, minimizer=name, tol=1e-10, max_iter=max_iter, strict=True)
        state = sim.initial_state(velocity=torch.full((scene.free_dof_count,), 0.1))
        results[name] = sim.step(state, loads)[0].q
    displacement = float((results["newton"] - scene.q_seed).abs().max())
    assert displacement > 1e-3
    torch.testing.assert_close(results["lbfgs"], results["newton"], rtol=0.0, atol=1e-6 * displacement)


@pytest.mark.parametrize(("name", "options"), [("newton", {}), ("newton", {"reuse": 2}), ("lbfgs", {})])
def test_the_minimizers_show_each_accepted_point_to_the_objective(name: str, options: dict) -> None:
    """``visit(u)`` sees every accepted point in order (chord steps too), the last the returned end, one per entry of
    the history after the start's (what ImplicitEuler's ``retry_tunneled`` tests the path of a step through)."""
    from redsim.solvers import get_minimizer

    scene = _cube(1e4, 0.3, gravity=True)
    space = FullSpace(scene)
    q = scene.q_seed.to(torch.float64)
    packed = scene.pack_loads({"bottom": [50.0, -200.0, 0.0]}, 1, q)
    objective = PotentialObjective(
        space, loads=packed, cond=None, inertia=Inertia(q + 0.005, 0.05), force=None, reference=q
    )
    objective.path = []
    minimize = functools.partial(get_minimizer(name), **options)
    end, info = minimize(objective, q.clone(), tol=1e-10, max_iter=200)
    assert info.converged and len(objective.path) == len(info.history) - 1 >= 2
    assert torch.equal(objective.path[-1], end)
    assert [objective.value_and_grad(u)[0] for u in objective.path] == pytest.approx(info.history[1:], rel=1e-12)


def test_steps_with_cached_scene_constants_match_fresh_objectives() -> None:
    """ImplicitEuler builds the scene's constants once; every step's objective and result stay those of a fresh one."""
    scene = _cube(1e4, 0.3, gravity=True)
    space = FullSpace(scene)
    loads = {"bottom": [50.0, -200.0, 0.0]}
    sim = ImplicitEuler(space, 0.05, strict=True)
    state = sim.initial_state(velocity=torch.full((scene.free_dof_count,), 0.1))
    trajectory, _ = sim.rollout(state, 5, loads)
    packed = scene.pack_loads(loads, 1, scene.q_seed)
    q, q_prev = state.q, state.q_prev
    for step in range(5):
        inertia = Inertia(2.0 * q - q_prev, 0.05)
        fresh = PotentialObjective(space, loads=packed, cond=None, inertia=inertia, force=None, reference=q)
        cached = PotentialObjective(
            space,
            loads=packed,
            cond=None,
            inertia=inertia,
            force=None,
            reference=q,
            constants=SceneConstants.of(scene),
        )
        for name in ("force_scale", "gradient_noise", "value_noise", "max_step"):
            assert getattr(cached, name) == getattr(fresh, name), name
        q, q_prev = newton(fresh, 2.0 * q - q_prev, tol=sim.tol, max_iter=sim.max_iter)[0], q
        torch.testing.assert_close(trajectory[step + 1], q, rtol=0.0, atol=1e-14)


def test_bad_inputs_raise_value_error() -> None:
    space = FullSpace(_cube(1e4, 0.3))
    for dt in (0.0, -0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="dt"):
            ImplicitEuler(space, dt)
    with pytest.raises(ValueError, match="newton") as error:
        ImplicitEuler(space, 0.01, minimizer="gradient_descent")
    assert all(name in str(error.value) for name in MINIMIZERS)
    with pytest.raises(ValueError, match="minimizer"):
        static_equilibrium(space.scene, minimizer="bfgs")
    sim = ImplicitEuler(space, 0.01)
    with pytest.raises(ValueError, match="finite"):
        sim.step(sim.initial_state(), {"bottom": [float("nan"), 0.0, 0.0]})
    with pytest.raises(ValueError, match="finite"):
        sim.step(sim.initial_state(), torch.tensor([[0.0, float("inf"), 0.0]]))
    with pytest.raises(ValueError, match="finite"):
        static_equilibrium(space.scene, {"bottom": [0.0, float("nan"), 0.0]})


def test_a_scene_name_a_scene_for_a_space_or_a_tensor_for_a_state_is_a_clear_type_error() -> None:
    """These were AttributeErrors ("'str' object has no attribute 'dtype'", "'Scene' object has no attribute
    'scene'", "'Tensor' object has no attribute 'q'"), a review's finding."""
    scene = _cube(1e4, 0.3)
    with pytest.raises(TypeError, match=r"scene must be a redsim Scene \(redsim.scenes.build\(name\)\), got 'cube'"):
        FullSpace("cube")
    with pytest.raises(TypeError, match="scene must be a redsim Scene"):
        static_equilibrium("cube")
    with pytest.raises(TypeError, match=r"not a scene: ImplicitEuler\(FullSpace\(scene\), dt\)"):
        ImplicitEuler(scene, 0.01)
    sim = ImplicitEuler(FullSpace(scene), 0.01)
    with pytest.raises(TypeError, match=r"state must be a FullState .*, got Tensor"):
        sim.step(scene.q_seed)
    with pytest.raises(TypeError, match=r"state must be a FullState .*, got Tensor"):  # rollout read state.q first
        sim.rollout(scene.q_seed, 3)
    for steps in (2.5, -1, float("nan"), float("inf"), True, None, "3"):  # int(nan), int(None): torch-free crashes
        with pytest.raises(ValueError, match="steps must be an integer >= 0"):
            sim.rollout(sim.initial_state(), steps)


def test_a_step_that_converged_at_a_saddle_is_left_with_escape_saddles() -> None:
    """The two-link chain's third step under 2 N ends at a saddle of the step's objective (|g| within the
    tolerance, Hessian eigenvalue -355): projected Newton sees no negative curvature (a review's finding).
    ``escape_saddles=True`` leaves it to the minimum."""
    import redsim

    scene = redsim.scenes.build("mini_chain")
    loads = {"bottom": [2.0, 0.0, 0.0]}

    def third_step(**options: bool) -> tuple[FullState, FullState, object]:
        sim = ImplicitEuler(FullSpace(scene), 0.02, **options)
        state = sim.initial_state()
        for _ in range(2):
            state, _ = sim.step(state, loads)
        return (state, *sim.step(state, loads))

    def lowest_curvature_and_value(before: FullState, after: FullState) -> tuple[float, float]:
        inertia = Inertia(2.0 * before.q - before.q_prev, 0.02)
        objective = PotentialObjective(
            FullSpace(scene),
            loads=scene.pack_loads(loads, 1),
            cond=None,
            inertia=inertia,
            force=None,
            reference=before.q,
        )
        hessian = torch.autograd.functional.hessian(lambda q: objective._value(q[None])[0], after.q)
        return float(torch.linalg.eigvalsh(0.5 * (hessian + hessian.T))[0]), objective.value_and_grad(after.q)[0]

    before, plain, info = third_step()
    assert info.converged
    saddle, value = lowest_curvature_and_value(before, plain)
    assert saddle < -100.0
    before_escaped, escaped, info = third_step(escape_saddles=True)
    assert info.converged and torch.equal(before_escaped.q, before.q)  # the first two steps are minima as they were
    curvature, lower = lowest_curvature_and_value(before, escaped)
    assert curvature > 0.0 and lower < value - 1e-3
    with pytest.raises(ValueError, match="escape_saddles needs the full space"):
        ImplicitEuler(_NotFull(FullSpace(scene)), 0.02, escape_saddles=True)


class _NotFull:
    """A space that is not :class:`FullSpace` (its attributes those of the one it wraps)."""

    def __init__(self, space: FullSpace) -> None:
        self._space = space

    def __getattr__(self, name: str) -> object:
        return getattr(self._space, name)


def test_static_equilibrium_of_a_contact_held_chain_does_not_fall_through() -> None:
    """The links start out of contact: Newton's trust radius (half the contact tube) keeps the
    first steps from passing through the hook, where the bounded penalty would let them fall."""
    import redsim

    scene = redsim.scenes.build("mini_chain")
    q, info = static_equilibrium(scene)
    assert info.converged, info.message
    terms = scene.energy_terms(q)
    drop = float(scene.energy_terms(scene.q_seed)["gravity"] - terms["gravity"])
    assert 0.0 < drop < 0.5  # settles by millimetres into contact instead of falling away
    assert float(terms["contact"]) < 0.01


def test_a_latent_space_refuses_a_map_fitted_to_another_scene() -> None:
    """LatentStepper refused a map whose metadata names another scene, LatentSpace (ImplicitEuler's latent space, the
    benches' converged latent solve) took it wherever n matched (helper-233's lead)."""
    import copy

    from redsim import pretrained, scenes
    from redsim.integrators import LatentSpace

    scene = scenes.build("mini_chain")
    own = pretrained.load("mini_chain", scene)
    LatentSpace(scene, own)  # its own scene: accepted
    other = copy.deepcopy(own)
    other.metadata = {**own.metadata, "scene": "klann"}
    with pytest.raises(ValueError, match="fitted to scene 'klann', not to 'mini_chain'"):
        LatentSpace(scene, other)


def test_a_latent_space_warns_of_a_map_fitted_to_its_scene_with_other_parameters() -> None:
    """LatentStepper warned where a map's metadata names this scene with other parameters (its fingerprint), LatentSpace
    took it without a word; both check in check_map_scene now: one warning from the constructor the caller called
    (a stepper's own rest solve, which builds a LatentSpace, adds none)."""
    import warnings

    from redsim import pretrained, scenes
    from redsim.integrators import LatentSpace
    from redsim.integrators.spaces import SceneParametersWarning
    from redsim.runtime import LatentStepper

    dense = scenes.build("mini_chain", density=2000.0)
    match = "fitted to scene 'mini_chain' with other parameters"
    with pytest.warns(SceneParametersWarning, match=match) as caught:
        LatentSpace(dense, pretrained.load("mini_chain"))
    assert [w.filename for w in caught] == [__file__]  # the caller's line, not the helper's
    with warnings.catch_warnings():
        warnings.simplefilter("error", SceneParametersWarning)
        LatentSpace(scenes.build("mini_chain"), pretrained.load("mini_chain"))  # its own scene: no warning
    with pytest.warns(SceneParametersWarning, match=match) as caught:
        LatentStepper(dense, pretrained.load("mini_chain"), 0.02).rest_latent()
    assert [w.filename for w in caught] == [__file__]
