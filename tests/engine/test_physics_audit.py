"""Physics audit of the energies and the full-space reference, in float64, beside what test_effects.py and
test_integrator.py check already: derivatives where constraints act (inverted elements, a folded cloth, violated
joints, penetrating contact), the elastic constants against uniaxial stress, whole-scene frame indifference, masses
against density x measure, implicit Euler's numerical damping and phase against its linear theory, and a static
cantilever against Timoshenko's beam.

Tolerances: central differences with step h err by O(h^2) plus round-off O(eps |E| / h); small-strain closed forms
by O(strain); the beam by its discretization (linear tets are too stiff, never too soft)."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
import torch

import redsim
from redsim import PointSet, SceneBuilder, meshes
from redsim.effects import (
    DiscreteShellBending,
    Effect,
    FrameSet,
    NeoHookean,
    PointPairPenalty,
    RigidOrthogonality,
    SDFContact,
    Sphere,
    StVKMembrane,
)
from redsim.effects.elastic import hinge_angles
from redsim.hessian import element_hessians
from redsim.integrators import FullSpace, ImplicitEuler, static_equilibrium

G = 9.81  # [m/s^2], the catalog's gravity


def _rotation(dim: int, seed: int) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(dim, dim, generator=torch.Generator().manual_seed(seed), dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    if torch.det(q) < 0:  # a reflection (in 2D, -q is one too): flip one axis
        q[:, 0] = -q[:, 0]
    return q


def _body_dofs(scene: redsim.Scene) -> torch.Tensor:
    """The 12 entries [R | t] of every rigid body, [bodies, 12] (the rows of its orthogonality terms)."""
    rows = [e.element_dofs for e in scene.effects if isinstance(e, RigidOrthogonality)]
    return torch.cat(rows) if rows else torch.zeros(0, 12, dtype=torch.int64)


def _moved(scene: redsim.Scene, x: torch.Tensor, rotation: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """Full configuration x [N] moved rigidly: particles p -> R p + c, bodies [A | t] -> [R A | R t + c]."""
    x = x.clone()
    bodies = _body_dofs(scene)
    particle = torch.ones(x.numel(), dtype=torch.bool)
    particle[bodies.reshape(-1)] = False
    index = particle.nonzero().reshape(-1, scene.dim)
    x[index] = x[index] @ rotation.T + shift
    for row in bodies:
        frame = rotation @ x[row].reshape(3, 4)
        frame[:, 3] += shift
        x[row] = frame.reshape(-1)
    return x


def _noisy(scene: redsim.Scene, scale: float, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    span = float(scene.q_seed.abs().max().clamp_min(1.0))
    return scene.q_seed + scale * span * torch.randn(scene.free_dof_count, generator=g, dtype=torch.float64)


# -- derivatives where the constraints act ---------------------------------------------------------------
def _inverted_tets() -> tuple[redsim.Scene, torch.Tensor]:
    scene = redsim.scenes.build("toy_two_tets")
    q = scene.q_seed.clone()
    q[1] = -0.05  # v3 (0.1 m above the pinned face) pushed 5 cm below it: its tet inverts, the other is squashed
    return scene, q


def _folded_cloth() -> tuple[redsim.Scene, torch.Tensor]:
    """The toy cloth's bottom row folded up by 160 degrees about the row above it (y = -0.2 m)."""
    scene = redsim.scenes.build("toy_small_cloth")
    x = scene.full_positions(scene.q_seed[None])[0].reshape(-1, 3).clone()
    fold = math.radians(160.0)
    row = x[:, 1] < -0.25
    dy, dz = x[row, 1] + 0.2, x[row, 2]
    x[row, 1] = -0.2 + math.cos(fold) * dy - math.sin(fold) * dz
    x[row, 2] = math.sin(fold) * dy + math.cos(fold) * dz
    q = scene.dof_map.restrict(x.reshape(1, -1))[0]
    return scene, q + 1e-3 * torch.randn(q.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)


def _penetrating_chain() -> tuple[redsim.Scene, torch.Tensor]:
    scene = redsim.scenes.build("mini_chain")
    q = scene.q_seed.clone()
    q[7] -= 0.015  # link 0 (seed clearance 5 mm) 1 cm into the hook's margin
    q[19] -= 0.030  # link 1 1 cm into link 0's
    return scene, q + 1e-3 * torch.randn(q.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)


def _noisy_scene(name: str, scale: float) -> tuple[redsim.Scene, torch.Tensor]:
    scene = redsim.scenes.build(name)
    return scene, _noisy(scene, scale, 1)


ACTIVE_STATES = {
    "inverted_tets": _inverted_tets,
    "folded_cloth": _folded_cloth,
    "penetrating_chain": _penetrating_chain,
    "inverted_2d_bar": lambda: _noisy_scene("toy_tiny_bar_2d", 0.2),
    "violated_joints": lambda: _noisy_scene("toy_three_link_chain", 0.2),
    "violated_crank": lambda: _noisy_scene("toy_crank", 0.2),
    "violated_klann": lambda: _noisy_scene("klann", 0.2),
    "conditional_pins": lambda: _noisy_scene("conditional_bar", 0.02),
}


def _assert_active(effect: Effect, x: torch.Tensor, state: str) -> None:
    """The state exercises what its name says (a check of the test's setup)."""
    if isinstance(effect, NeoHookean) and state.startswith("inverted"):
        assert bool((effect.invariants(x[None])[1] < 0).any()), state
    if isinstance(effect, SDFContact):
        assert float(effect.penetration(x[None])[0]) > 5e-3, state
    if isinstance(effect, DiscreteShellBending):
        coords = x[effect.element_dofs].T.unbind(0)
        assert float(hinge_angles(coords, effect.length_eps).abs().max()) > 2.5, state
    if isinstance(effect, PointPairPenalty):
        assert float(effect.energy(x[None])[0]) > 1.0, state


@pytest.mark.parametrize("state", sorted(ACTIVE_STATES))
def test_gradients_and_hessians_match_central_differences_where_constraints_act(state: str) -> None:
    """Each effect's autograd gradient of ``energy`` against central differences of its energy, and its element
    Hessians (what the Newton solver assembles, from ``element_energy``) times a direction against central
    differences of that gradient, along random directions of the full configuration."""
    scene, q = ACTIVE_STATES[state]()
    g = torch.Generator().manual_seed(2)
    x = scene.full_positions(q[None])[0]
    cond = None if scene.condition_space is None else scene.pack_condition(scene.condition_space.sample(1, g), 1)
    forces = {h: torch.randn(scene.dim, generator=g, dtype=torch.float64) for h in scene.handle_names}
    loads = scene.pack_loads(forces, 1)
    span = float(x.abs().max().clamp_min(1.0))
    for effect in scene.effects:
        _assert_active(effect, x, state)

        def energy(v: torch.Tensor, effect: Effect = effect) -> torch.Tensor:
            return effect.energy(v[None], cond, loads)[0]

        def gradient(v: torch.Tensor, effect: Effect = effect) -> torch.Tensor:
            v = v.clone().requires_grad_(True)
            value = effect.energy(v[None], cond, loads)[0]
            if not value.requires_grad:
                return torch.zeros_like(v)
            return torch.autograd.grad(value, v)[0]

        blocks = element_hessians(effect, x, cond, loads)
        grad = gradient(x)
        for _ in range(3):
            d = torch.randn(x.shape, generator=g, dtype=torch.float64)
            d /= d.norm()
            h = 1e-6 * span
            fd = float(energy(x + h * d) - energy(x - h * d)) / (2 * h)
            assert fd == pytest.approx(float(grad @ d), rel=1e-6, abs=1e-9 + 1e-13 * abs(float(energy(x))) / h), (
                state,
                effect.name,
            )
            h = 1e-7 * span
            fd_hvp = (gradient(x + h * d) - gradient(x - h * d)) / (2 * h)
            local = (blocks @ d[effect.element_dofs].unsqueeze(-1)).squeeze(-1)
            hvp = torch.zeros_like(x).index_add_(0, effect.element_dofs.reshape(-1), local.reshape(-1))
            bound = 1e-5 * float(fd_hvp.norm()) + 1e-7 * float(grad.norm()) / span
            assert float((hvp - fd_hvp).norm()) <= bound, (state, effect.name, float((hvp - fd_hvp).norm()), bound)


# -- the elastic constants against uniaxial stress --------------------------------------------------------
YOUNG, POISSON, THICKNESS = 2e3, 0.3, 0.01  # [Pa], 1, [m]


def _tet_energy(lateral: float, strain: float) -> float:
    """Energy density [Pa] of a unit tet stretched by diag(1 + strain, 1 + lateral, 1 + lateral)."""
    rest = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    effect = NeoHookean("e", torch.arange(12).reshape(1, 4, 3), rest[None], YOUNG, POISSON)
    stretch = torch.tensor([1 + strain, 1 + lateral, 1 + lateral], dtype=torch.float64)
    return float(effect.energy((rest * stretch).reshape(1, -1))[0]) * 6.0


def _plane_energy(plane: str) -> Callable[[float, float], float]:
    def energy(lateral: float, strain: float) -> float:
        """Energy density [Pa] of a unit triangle stretched by diag(1 + strain, 1 + lateral), per its volume."""
        rest = torch.tensor([[0.0, 0], [1, 0], [0, 1]], dtype=torch.float64)
        effect = NeoHookean(
            "e", torch.arange(6).reshape(1, 3, 2), rest[None], YOUNG, POISSON, thickness=THICKNESS, plane=plane
        )
        stretch = torch.tensor([1 + strain, 1 + lateral], dtype=torch.float64)
        return float(effect.energy((rest * stretch).reshape(1, -1))[0]) / (0.5 * THICKNESS)

    return energy


def _membrane_energy(lateral: float, strain: float) -> float:
    """Energy density [Pa] of a unit cloth triangle (thickness THICKNESS) stretched in its plane."""
    rest = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=torch.float64)
    effect = StVKMembrane("m", torch.arange(9).reshape(1, 3, 3), rest[None], YOUNG, POISSON, thickness=THICKNESS)
    stretch = torch.tensor([1 + strain, 1 + lateral, 1.0], dtype=torch.float64)
    return float(effect.energy((rest * stretch).reshape(1, -1))[0]) / (0.5 * THICKNESS)


PLANE_STRAIN_YOUNG = YOUNG / (1 - POISSON**2)  # uniaxial stress in the plane, no strain out of it
PLANE_STRAIN_POISSON = POISSON / (1 - POISSON)


@pytest.mark.parametrize(
    ("energy", "young", "poisson"),
    [
        (_tet_energy, YOUNG, POISSON),
        (_plane_energy("stress"), YOUNG, POISSON),
        (_plane_energy("strain"), PLANE_STRAIN_YOUNG, PLANE_STRAIN_POISSON),
        (_membrane_energy, YOUNG, POISSON),
    ],
    ids=["neo_hookean_3d", "neo_hookean_plane_stress", "neo_hookean_plane_strain", "stvk_membrane"],
)
def test_uniaxial_stress_gives_young_s_modulus_and_poisson_s_ratio(energy, young: float, poisson: float) -> None:
    """Stretched by a small strain along x with the lateral strain free (minimized: uniaxial stress), every elastic
    model stores E strain^2 / 2 per unit volume and contracts laterally by -nu strain: the Young's modulus and
    Poisson ratio it was given (plane strain: E / (1 - nu^2) and nu / (1 - nu), the in-plane constants)."""
    strain = 1e-4
    guess, step = -poisson * strain, 0.1 * strain
    low, mid, high = (energy(guess + k * step, strain) for k in (-1, 0, 1))
    lateral = guess - step * (high - low) / (2 * (high - 2 * mid + low))  # the parabola's vertex
    assert -lateral / strain == pytest.approx(poisson, rel=1e-3)
    assert energy(lateral, strain) == pytest.approx(0.5 * young * strain**2, rel=1e-3)


# -- frame indifference of whole scenes --------------------------------------------------------------------
def _body_fixed(effect: Effect) -> torch.Tensor | None:
    """Elements of a penalty that read no fixed world point or frame (those are not frame-indifferent), [T] bool;
    None for other effects."""
    if isinstance(effect, PointPairPenalty):
        return (effect.a.weights != 0).any(-1) & (effect.b.weights != 0).any(-1)
    if isinstance(effect, SDFContact):
        return (effect.points.weights != 0).any(-1) & (effect.frames.weights != 0).any(-1)
    return None


FRAME_SCENES = [
    "toy_two_tets",
    "toy_tiny_bar_2d",
    "toy_small_cloth",
    "toy_three_link_chain",
    "mini_chain",
    "klann",
    "stewart",
    "bistable_bar",
    "hanging_sheet",
    "cloth_ball",
]


@pytest.mark.parametrize("name", FRAME_SCENES)
def test_every_internal_energy_of_a_scene_is_unchanged_by_a_rigid_motion_of_the_whole_state(name: str) -> None:
    """The whole deformed state (particles and bodies, pinned entries too) turned and shifted: every elastic,
    orthogonality, joint and contact element between moving parts keeps its energy (frame indifference); 2D scenes
    turn in their plane."""
    scene = redsim.scenes.build(name)
    x = scene.full_positions(_noisy(scene, 0.05, 3)[None])[0]
    g = torch.Generator().manual_seed(4)
    moved = _moved(scene, x, _rotation(scene.dim, 5), torch.randn(scene.dim, generator=g, dtype=torch.float64))
    cond = scene.pack_condition(None, 1)
    checked = 0
    for effect in scene.effects:
        mask = _body_fixed(effect)
        elastic = isinstance(effect, NeoHookean | StVKMembrane | DiscreteShellBending | RigidOrthogonality)
        if mask is None and not elastic:
            continue  # gravity, loads, world pins: not frame-indifferent by design
        before = effect.element_energies(x[None], cond)[0]
        after = effect.element_energies(moved[None], cond)[0]
        keep = torch.ones_like(before, dtype=torch.bool) if mask is None else mask
        torch.testing.assert_close(after[keep], before[keep], rtol=1e-10, atol=1e-12 * float(before.abs().max()))
        checked += int(keep.sum())
    assert checked > 0


# -- masses --------------------------------------------------------------------------------------------
MASSES = {  # [kg]: density x volume (or x area x thickness), from each builder's default parameters
    "cantilever": 1000.0 * 1.0 * 0.2 * 0.2,
    "hetero_beam": 1000.0 * 1.2 * 0.15 * 0.15,
    "bistable_bar": 1000.0 * 1.0 * 0.1 * 0.05,
    "conditional_bar": 1000.0 * 1.0 * 0.1 * 0.05,
    "toy_tiny_bar_2d": 1000.0 * 0.4 * 0.1 * 0.05,
    "toy_two_tets": 1000.0 * 2 * (0.5 * 0.1 * 0.1) * 0.1 / 3,
    "toy_small_cloth": 200.0 * 1e-3 * 0.3 * 0.3,
    "hanging_sheet": 200.0 * 1e-3 * 1.0 * 1.0,
    "cloth_ball": 200.0 * 1e-3 * 1.0 * 1.0 + 1.0,  # the cloth and the 1 kg ball
    "toy_three_link_chain": 3 * 1000.0 * 0.02 * 0.22 * 0.02,
    "toy_crank": 1000.0 * 0.02 * 0.22 * 0.02,
}


@pytest.mark.parametrize("name", sorted(MASSES))
def test_masses_are_density_times_measure_and_inertia_agrees_with_gravity(name: str) -> None:
    """Gravity's masses sum to the scene's density x volume; and translating every free entry by a gives
    |u|_M^2 = m_free |a|^2 with the same m_free gravity's energy changes by (-m_free g . a): the inertia and the
    weight are one mass, so a free part falls at g."""
    scene = redsim.scenes.build(name, **({"gravity": True} if name in ("bistable_bar", "toy_crank") else {}))
    gravity = scene.effect("gravity")
    assert float(gravity.masses.sum()) == pytest.approx(MASSES[name], rel=1e-12)
    up = torch.zeros(scene.dim, dtype=torch.float64)
    up[1] = 1.0
    x = scene.full_positions(scene.q_seed[None])
    u = scene.dof_map.restrict(_moved(scene, x[0], torch.eye(scene.dim, dtype=torch.float64), up)[None] - x)
    inertial = float(scene.mass_norm_sq(u)[0])
    lift = float(gravity.energy(scene.full_positions(scene.q_seed[None] + u))[0] - gravity.energy(x)[0])
    assert inertial > 0.0
    assert lift / G == pytest.approx(inertial, rel=1e-10)


def test_a_spinning_bar_s_kinetic_energy_is_half_omega_inertia_omega() -> None:
    """A link of the toy chain (a 0.02 x 0.22 x 0.02 m box of 0.088 kg) spinning at omega about its centre: the
    affine body's [R | t] moves at [[omega]_x R | 0], and |v|_M^2 / 2 is the rigid body's omega . I omega / 2 with
    the box's inertia tensor m (b^2 + c^2) / 12, ... (the 4x4 mass block holds the second moments, not I)."""
    scene = redsim.scenes.build("toy_three_link_chain")
    mass, sides = 0.088, torch.tensor([0.02, 0.22, 0.02], dtype=torch.float64)
    inertia = torch.diag(mass * (sides.square().sum() - sides.square()) / 12)
    omega = torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64)
    cross = torch.tensor([[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]])
    velocity = torch.zeros(scene.free_dof_count, dtype=torch.float64)
    frame = scene.q_seed[:12].reshape(3, 4)  # body 0, unrotated
    velocity[:12] = torch.cat([cross @ frame[:, :3], torch.zeros(3, 1, dtype=torch.float64)], 1).reshape(-1)
    kinetic = 0.5 * float(scene.mass_norm_sq(velocity[None])[0])
    assert kinetic == pytest.approx(0.5 * float(omega @ inertia @ omega), rel=1e-12)


# -- implicit Euler against its linear theory --------------------------------------------------------------
def test_implicit_euler_damps_and_slows_a_pendulum_as_its_linear_theory_says() -> None:
    """The crank (a rigid bar hinged by penalties) swinging under gravity: implicit Euler's recursion
    (1 + w^2 h^2) x_{n+1} = 2 x_n - x_{n-1} turns each step's exact rotation by w h into an amplitude factor
    1 / sqrt(1 + (w h)^2) and a phase atan(w h). Both, fitted from the swing, match that of the compound pendulum's
    w^2 = m g d / I_pivot at w h = 0.25 (a 3% loss per step)."""
    scene = redsim.scenes.build("toy_crank", gravity=True)
    block = scene.mass_matrix.to_dense()[:4, :4]  # [[S, 0], [0, m]] about the centre of mass (row 0 of [R | t])
    mass, second_moment = float(block[3, 3]), block[:3, :3]
    arm = float(scene.q_seed[3])  # the hinge is at the origin, the centre of mass at (arm, 0, 0)
    inertia = float(second_moment[0, 0] + second_moment[1, 1]) + mass * arm**2  # about the hinge's z axis
    omega = math.sqrt(mass * G * arm / inertia)
    h = 0.25 / omega
    angle = -math.pi / 2 + 0.05  # 0.05 rad from hanging straight down
    c, s = math.cos(angle), math.sin(angle)
    turn = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    q0 = _moved(scene, scene.q_seed, turn, torch.zeros(3, dtype=torch.float64))
    sim = ImplicitEuler(FullSpace(scene), h, tol=1e-10, strict=True)
    trajectory, _ = sim.rollout(sim.initial_state(q0), 60)
    swing = torch.atan2(trajectory[:, 3], -trajectory[:, 7]).numpy()[10:]  # after the stiff penalty modes died out
    # x_{n+1} = a x_n + b x_{n-1} with a = 2 r cos(phase), b = -r^2, by least squares
    (a, b), *_ = np.linalg.lstsq(np.stack([swing[1:-1], swing[:-2]], 1), swing[2:], rcond=None)
    factor, phase = math.sqrt(-b), math.acos(a / (2 * math.sqrt(-b)))
    assert 1 - factor == pytest.approx(1 - 1 / math.sqrt(1 + (omega * h) ** 2), rel=2e-3)  # 1e-4 measured
    assert phase == pytest.approx(math.atan(omega * h), rel=2e-3)  # 3e-4 measured (the joints' give)


def _floating_scene() -> redsim.Scene:
    """Two tets, a rigid body jointed to one of their vertices and a sphere on the body that they touch; nothing
    pinned, no gravity: every force is internal."""
    b = SceneBuilder(dim=3)
    verts = torch.tensor([[0.3, 0.1, 0], [1, 0, 0], [0.2, 1, 0.1], [0.1, 0.2, 1], [1, 1, 1]], dtype=torch.float64)
    ids = b.add_particles(verts, torch.tensor([1.0, 2.0, 0.5, 1.5, 1.0]))
    tets = torch.as_tensor(meshes.orient_tets(verts.numpy(), np.array([[0, 1, 2, 3], [1, 2, 3, 4]])))
    b.add_effect(NeoHookean("elastic", b.particle_dofs(ids[tets]), verts[tets], 1e3, 0.3))
    frame = torch.tensor([[1.0, 0, 0, 1.4], [0, 1, 0, 1.2], [0, 0, 1, 1.1]], dtype=torch.float64)
    body = b.add_body(torch.diag(torch.tensor([0.1, 0.2, 0.3, 2.0], dtype=torch.float64)), frame)
    b.add_effect(RigidOrthogonality("rigid", b.body_dofs(body)[None], 50.0))
    pivot = b.body_points(body, torch.tensor([[-0.4, 0.0, 0.0]]))
    b.add_effect(PointPairPenalty("joint", pivot, b.particle_points(ids[1:2]), 300.0))
    sphere = FrameSet.body(b.body_dofs(body), 5)
    b.add_effect(SDFContact("contact", b.particle_points(ids), sphere, Sphere(0.5), 200.0))
    return b.finalize("floating")


def test_implicit_euler_keeps_the_momentum_of_a_free_system_and_loses_its_energy() -> None:
    """Tets, a jointed body and contact between them, thrown with random velocities: every term is translation
    invariant, so M (q_{n+1} - 2 q_n + q_{n-1}) / h^2 = -grad E sums to zero along a translation and the linear
    momentum T_a^T M v (T_a: the free entries of a translation by a) is conserved to the solver's tolerance; the
    energy |v|_M^2 / 2 + E falls every step (here the potential is convex enough; implicit Euler dissipates)."""
    scene = _floating_scene()
    h = 0.01
    sim = ImplicitEuler(FullSpace(scene), h, tol=1e-10, strict=True)
    velocity = torch.randn(scene.free_dof_count, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    trajectory, _ = sim.rollout(sim.initial_state(velocity=velocity), 100)
    contact = scene.effect("contact")
    assert max(float(contact.penetration(scene.full_positions(q[None]))[0]) for q in trajectory) > 0.1
    x = scene.full_positions(scene.q_seed[None])
    eye = torch.eye(3, dtype=torch.float64)
    translations = torch.cat([scene.dof_map.restrict(_moved(scene, x[0], eye, a)[None] - x) for a in eye])
    velocities = (trajectory[1:] - trajectory[:-1]) / h
    momentum = scene.mass_matvec(velocities) @ translations.T  # [steps, 3]
    torch.testing.assert_close(momentum, momentum[:1].expand_as(momentum), rtol=0.0, atol=1e-10)
    energy = 0.5 * scene.mass_norm_sq(velocities) + scene.energy(trajectory[1:])
    assert bool((energy[1:] < energy[:-1]).all())


def test_a_step_s_energy_balance_is_implicit_euler_s_exact_dissipation_for_a_spring() -> None:
    """Two particles on zero-length springs to world points, under gravity and a constant load: the energy is
    quadratic (springs) plus linear (gravity), so each step's reported mechanical_gain, K + E after minus before
    minus the load's work, is exactly -(|v_{t+1} - v_t|_M^2 + |q_{t+1} - q_t|_K^2) / 2 (the Bregman divergence of
    a quadratic), never positive."""
    b = SceneBuilder(dim=3)
    ids = b.add_particles(torch.tensor([[0.0, 0, 0], [1.0, 0, 0]]), torch.tensor([2.0, 0.5]))
    anchors = torch.tensor([[0.1, 0.2, -0.1], [1.0, 0.3, 0.2]], dtype=torch.float64)
    stiffness = torch.tensor([50.0, 80.0], dtype=torch.float64)
    b.add_effect(PointPairPenalty("springs", b.particle_points(ids), PointSet.world(anchors), stiffness))
    b.add_gravity([0.0, -G, 0.0])
    b.add_handle("end", b.particle_points(ids[1:]))
    scene = b.finalize("springs")
    h = 0.05
    sim = ImplicitEuler(FullSpace(scene), h, tol=1e-12, strict=True)
    velocity = torch.tensor([1.0, -2.0, 0.5, 0.0, 3.0, -1.0], dtype=torch.float64)
    trajectory, infos = sim.rollout(sim.initial_state(velocity=velocity), 20, {"end": [4.0, -1.0, 2.0]})
    q = torch.cat([(trajectory[:1] - h * velocity), trajectory])  # q_{-1} = q_0 - h v_0, as initial_state sets it
    v = (q[1:] - q[:-1]) / h
    dv, dq = (v[1:] - v[:-1]).reshape(-1, 2, 3), (q[2:] - q[1:-1]).reshape(-1, 2, 3)
    masses = torch.tensor([2.0, 0.5], dtype=torch.float64)
    dissipated = 0.5 * ((masses * dv.square().sum(-1)) + (stiffness * dq.square().sum(-1))).sum(-1)
    gains = torch.tensor([info.mechanical_gain for info in infos], dtype=torch.float64)
    torch.testing.assert_close(gains, -dissipated, rtol=1e-8, atol=1e-12)
    assert not any(info.energy_gain for info in infos)


# -- a static cantilever against beam theory -----------------------------------------------------------------
def test_a_cantilever_bends_less_than_timoshenko_s_beam_and_more_when_refined() -> None:
    """A 1 N load on the free end of the 1 m x 0.2 m x 0.2 m beam (E = 1e6 Pa, nu = 0.3, no gravity): the tip
    deflection of linear tets lies below Timoshenko's P L^3 / (3 E I) + P L / (k G A) (a conforming mesh is too
    stiff), rises under refinement (the Kuhn meshes are nested), and the equilibrium's energy is -P delta / 2
    (Clapeyron: the load's potential and the stored energy in the units they claim)."""
    load, length, width, young, poisson = 1.0, 1.0, 0.2, 1e6, 0.3
    shear_factor = 10 * (1 + poisson) / (12 + 11 * poisson)  # square section
    shear = young / (2 * (1 + poisson))
    timoshenko = load * length**3 / (3 * young * width**4 / 12) + load * length / (shear_factor * shear * width**2)
    deflections = []
    for cells_x, cells_yz in ((10, 2), (20, 4)):
        scene = redsim.scenes.build(
            "cantilever", cells_x=cells_x, cells_yz=cells_yz, poisson=poisson, young=young, gravity=False
        )
        loads = {"tip": [0.0, -load, 0.0]}
        q, info = static_equilibrium(scene, loads, tol=1e-9)
        assert info.converged, info.message
        drop = float(scene.handle_positions(scene.q_seed[None])[0, 1] - scene.handle_positions(q[None])[0, 1])
        assert info.energy == pytest.approx(-0.5 * load * drop, rel=1e-4)
        deflections.append(drop)
    assert deflections[0] < deflections[1] < timoshenko
    assert deflections[1] > 0.7 * timoshenko


def test_a_static_solve_at_rest_converges_where_the_elastic_energy_s_round_off_hides_the_last_newton_steps() -> None:
    """A 10 x 2 cell cantilever of nu = 0 under a 1 N tip load: the stable neo-Hookean energy is a sum of terms of
    size mu V that cancel, so its round-off (1e-13 J) exceeded the value noise the line search allowed (F L with
    F = the load alone, 1e-15 J), and the full Newton steps that cut |g| a hundredfold were refused as rises:
    not converged after 10 iterations (200 took minutes). Now 3."""
    scene = redsim.scenes.build("cantilever", cells_x=10, cells_yz=2, poisson=0.0, gravity=False)
    _, info = static_equilibrium(scene, {"tip": [0.0, -1.0, 0.0]}, max_iter=10)
    assert info.converged, info.message
    assert info.iterations <= 5


def _hinge(fold: float) -> torch.Tensor:
    """Two unit right triangles sharing the x axis edge, the second turned by ``fold`` [rad] about it, [4, 3]."""
    apex = [0.5, -math.cos(fold), math.sin(fold)]
    return torch.tensor([[0.0, 0, 0], [1, 0, 0], [0.5, 1, 0], apex], dtype=torch.float64)


@pytest.mark.parametrize("size", [1, 10**6])  # the closed-form gradient's path, and autograd's past its size
def test_a_bent_rest_hinge_is_pushed_away_from_folding_flat_from_either_side(size: int) -> None:
    """A hinge whose rest is bent by 0.7 rad: its energy k (theta - rest)^2 rises toward the flat fold (theta = +-pi,
    the triangles through each other) from both sides, so no shape near the fold is pushed into it. The value jumps
    at the fold itself (44.3 J from one side, 17.9 J from the other: stiffness 1 J, weight 3), where self-contact
    must stop a cloth anyway; wrapping theta - rest into [-pi, pi) removed that jump but moved the kink to
    theta = rest + pi, an ordinary shape, and from there the energy fell toward the fold (29.6 J at ``fold`` -2.44 rad,
    18.5 J at -3.1): reverted."""
    bend = DiscreteShellBending("b", torch.arange(12).reshape(1, 4, 3), _hinge(0.7)[None], stiffness=1.0)
    rows = size // 12 + 1

    def energy(fold: float) -> float:
        x = _hinge(fold).reshape(1, 12).repeat(rows, 1)
        return float(bend.element_energy(x.reshape(rows, 1, 12)).sum()) / rows

    near = [energy(f) for f in (2.44, 2.6, 3.1, math.pi - 1e-7)]
    assert near == sorted(near) and near[-1] == pytest.approx(3.0 * (math.pi - 0.7) ** 2, rel=1e-6)
    other = [energy(f) for f in (-2.0, -2.6, -3.1, -math.pi + 1e-7)]
    assert other == sorted(other) and other[-1] == pytest.approx(3.0 * (math.pi + 0.7) ** 2, rel=1e-6)


def test_a_solid_barely_moving_near_rest_reports_no_energy_gain_from_the_round_off_of_its_energy() -> None:
    """The two tets (no gravity) pushed at 1e-9 m/s: K + E is below 1e-16 J, but E sums stable neo-Hookean terms
    of size mu V that cancel, whose round-off (steps of 6e-17 J) read as gains on 4 of 10 steps against
    eps |K + E|; the balance now allows the energy's measured round-off (SceneConstants.energy_noise, 6e-16 J)."""
    scene = redsim.scenes.build("toy_two_tets", gravity=False)
    sim = ImplicitEuler(FullSpace(scene), 0.01)
    push = 1e-9 * torch.randn(scene.free_dof_count, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    _, infos = sim.rollout(sim.initial_state(velocity=push), 10)
    assert all(info.converged for info in infos)
    assert not any(info.energy_gain for info in infos), [info.mechanical_gain for info in infos]
