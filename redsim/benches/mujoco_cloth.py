"""MuJoCo's flex cloth built from a redsim cloth scene: the cloth anchor of ``redsim bench envs``.

:func:`flex_sheet` turns a pure-cloth scene (the catalog's ``hanging_sheet``) into a MuJoCo model with one
``flexcomp`` (``type="direct"``, ``dim=2``): the scene's vertices, triangles and vertex order, the scene's
pinned vertices as flexcomp pins, its lumped vertex masses (set per body through ``MjSpec``; flexcomp's
``mass`` would spread the total evenly), its gravity, and MuJoCo's shell elasticity
(``elastic2d="both"``) with parameters from :func:`matched_shell`:

- stretching: MuJoCo's 2D flex is the same constant-strain StVK membrane with plane-stress Lamé
  parameters as :class:`redsim.effects.StVKMembrane`, so equal ``young * thickness`` and ``poisson`` give
  equal membrane forces (tested to round-off);
- bending: MuJoCo's hinge model has rigidity D = E t^3 / (12 (1 - nu^2)) tied to the membrane's E and t,
  redsim's discrete-shell bending a stiffness per hinge [J]. Both store an energy quadratic in the
  curvature of a flat sheet, so :func:`matched_shell` bends the sheet into a shallow cylinder, measures
  both energies and picks the (E, t) pair that keeps E t and makes MuJoCo's energy equal redsim's.

What differs: MuJoCo's bending is its linear (flat-reference) hinge model against redsim's dihedral
angles (equal energies on the cylinder, forces within 0.2% on a 1 mm bump and 2% on a 1 cm one), its
thickness is a fitted number and no longer the sheet's 1 mm, its elements carry a collision radius
(contacts are switched off here), and MuJoCo integrates flex elasticity only under ``discrete`` (one
linearized implicit solve per step) or explicit ``Euler``.

:func:`timestep_sweep` measures which time steps stay stable, :func:`rest_sag` and :func:`swing_check`
compare the sheet's rest and its swing with redsim's full space, :func:`time_flex_cloth` times the model
as the chain anchor is timed, and :func:`cloth_anchor` / :func:`cloth_ratios` are what ``redsim bench
envs`` prints (``redsim bench mujoco-cloth`` prints the rest).
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from redsim.envs.bench import median_time
from redsim.scene import Scene

CLOTH_SCENE = "hanging_sheet"
"""The catalog scene the anchor is built from (the scene of ``RedSim/HangingCloth-v0``/``-v1``)."""
CLOTH_INTEGRATOR = "discrete"
"""MuJoCo's integrator for the anchor: the one that integrates flex elasticity implicitly in position."""
CLOTH_TIMESTEP = 0.05
"""Time step [s] of the anchor: the largest of :data:`SWEEP_TIMESTEPS` at which every scenario of
:func:`timestep_sweep` passed under :data:`CLOTH_INTEGRATOR` (at 0.1 s MuJoCo's implicit solve fails on the drop;
docs/env-speed.md, "MuJoCo's flex cloth anchor"). It is 2.5x the envs' dt of 0.02 s: the anchor is MuJoCo as fast as it
stays stable, not as accurate as redsim (:func:`swing_check`: at 0.05 s the dropped sheet reaches the vertical 80% late;
0.01 s is as close as redsim's full-space implicit Euler at 0.02 s)."""
SWEEP_TIMESTEPS: dict[str, tuple[float, ...]] = {
    "discrete": (0.1, 0.05, 0.02, 0.01, 0.005),
    "Euler": (1e-3, 5e-4, 2e-4, 1e-4, 5e-5),
}
"""Time steps [s] :func:`timestep_sweep` tries per integrator (MuJoCo 4 integrates flex elasticity under
``discrete`` and, explicitly, ``Euler``; ``implicit``/``implicitfast`` refuse it)."""
SWEEP_SECONDS = 2.0
"""Simulated seconds of each sweep run."""
MAX_EDGE_STRAIN = 0.1
"""A run blew up once an edge is stretched or compressed by more than this fraction (the hanging sheet's
largest strain under its weight is about 0.2%)."""
ENERGY_GROWTH = 0.1
"""A run blew up once its total energy rises above the start by this fraction of m g L (total mass m,
gravity g, sheet size L)."""
CHECK_EVERY = 0.01
"""Simulated seconds between the checks of a sweep run."""
BEND_CURVATURE = 0.5
"""Curvature [1/m] of the cylinder :func:`matched_shell` measures both bending energies on."""
PUSH_EVERY = 0.02
"""Simulated seconds between new random corner forces while the anchor is timed (the envs' dt)."""
PUSH_FORCE = 2.0
"""Largest corner force [N] per axis while the anchor is timed (HangingCloth's ``max_force``)."""
ANCHOR_BUDGET = 20.0
"""Seconds of timing of the anchor in ``redsim bench envs`` at most (its ``--budget``; a step takes 10-50 ms)."""
CLOTH_SCENES = ("cloth_ball", "hanging_sheet")
"""Scenes whose envs :func:`cloth_ratios` sets against MuJoCo's flex cloth."""
CLOTH_GOAL = 10.0
"""The issue's goal for the cloth envs: best-batch simulated s per wall s >= this many times the flex cloth's."""


@dataclass(frozen=True)
class SheetMesh:
    """The cloth of a scene as MuJoCo needs it (all float64 numpy).

    Attributes:
        vertices: Seed positions [m], shape [V, 3], in the scene's particle order.
        triangles: Vertex ids, shape [T, 3], counter-clockwise about the sheet's normal.
        pinned: Ids of the pinned vertices, shape [P].
        vertex_mass: Lumped mass [kg] of each vertex, shape [V] (0 for pinned ones).
        gravity: Gravitational acceleration [m/s^2], shape [3] (zeros without a gravity effect).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    pinned: np.ndarray
    vertex_mass: np.ndarray
    gravity: np.ndarray

    @property
    def free_mass(self) -> float:
        """Mass of the moving vertices [kg]."""
        return float(self.vertex_mass.sum())

    @property
    def size(self) -> float:
        """Largest side [m] of the bounding box of the vertices."""
        return float(np.ptp(self.vertices, axis=0).max())


@dataclass(frozen=True)
class ShellMatch:
    """MuJoCo ``elasticity`` parameters that reproduce a scene's membrane and bending (:func:`matched_shell`).

    Attributes:
        young: MuJoCo's Young's modulus [Pa].
        poisson: Poisson ratio (the scene's).
        thickness: MuJoCo's shell thickness [m].
        stretch_stiffness: E t [N/m], the scene's and MuJoCo's.
        scene_bending_j: The scene's bending energy [J] on the test cylinder.
        mujoco_bending_j: MuJoCo's bending energy [J] on it with these parameters.
        bending_rigidity: MuJoCo's D = E t^3 / (12 (1 - nu^2)) [J].
    """

    young: float
    poisson: float
    thickness: float
    stretch_stiffness: float
    scene_bending_j: float
    mujoco_bending_j: float
    bending_rigidity: float


def sheet_mesh(scene: Scene) -> SheetMesh:
    """The cloth of a pure-cloth scene (particles only, one surface "cloth", lumped masses).

    Raises:
        ValueError: if the scene has rigid bodies, no "cloth" surface, or a non-lumped mass matrix.
    """
    scene = scene.to(device="cpu", dtype=torch.float64)
    x = scene.full_positions(scene.q_seed[None])[0]
    surfaces = {s.name: s for s in scene.surfaces}
    if scene.dim != 3 or "cloth" not in surfaces:
        raise ValueError(f"scene {scene.name!r} is not a 3D cloth (it needs a 'cloth' surface)")
    count = scene.full_dof_count // 3
    cloth = surfaces["cloth"]
    vertex_dofs = cloth.points.dofs.reshape(-1, 3)
    if cloth.points.count != count or not torch.equal(vertex_dofs, torch.arange(3 * count).reshape(count, 3)):
        raise ValueError(f"scene {scene.name!r} has more than its cloth's vertices (rigid bodies?)")
    mass = scene.mass_matrix.coalesce()
    rows, cols = mass.indices()
    if not torch.equal(rows, cols):
        raise ValueError(f"scene {scene.name!r} has a non-diagonal mass matrix")
    full_mass = torch.zeros(scene.full_dof_count, dtype=torch.float64)
    full_mass[scene.dof_map.free_index[rows]] = mass.values()
    gravity = next((e.acceleration for e in scene.effects if e.kind == "gravity"), torch.zeros(3, dtype=torch.float64))
    return SheetMesh(
        vertices=x.reshape(count, 3).numpy(),
        triangles=cloth.faces.numpy(),
        pinned=np.unique(scene.dof_map.pinned_index.numpy() // 3),
        vertex_mass=full_mass.reshape(count, 3)[:, 0].numpy(),
        gravity=gravity.numpy(),
    )


def _membrane_parameters(scene: Scene) -> tuple[float, float]:
    """(E t [N/m], poisson) of the scene's StVK membrane, read back from its plane-stress Lamé parameters."""
    membrane = next((e for e in scene.effects if e.kind == "stvk_membrane"), None)
    if membrane is None:
        raise ValueError(f"scene {scene.name!r} has no StVK membrane")
    mu_t, lam_t = membrane.mu.to(torch.float64), membrane.lam.to(torch.float64)
    spread = max(float((mu_t / mu_t[0] - 1.0).abs().max()), float((lam_t / lam_t[0] - 1.0).abs().max()))
    if spread > 1e-9:
        raise ValueError(f"scene {scene.name!r} has a non-uniform membrane; MuJoCo's flex takes one material")
    ratio = float(lam_t[0] / mu_t[0])  # plane stress: lambda* / mu = 2 nu / (1 - nu)
    poisson = ratio / (2.0 + ratio)
    return 2.0 * float(mu_t[0]) * (1.0 + poisson), poisson


def bent_cylinder(vertices: np.ndarray, curvature: float) -> np.ndarray:
    """The flat sheet ``vertices`` [V, 3] rolled (isometrically) onto a cylinder of ``curvature`` [1/m].

    The cylinder's axis is the sheet's second in-plane principal direction; the sheet's normal is the
    direction it curls towards.
    """
    centre = vertices.mean(0)
    _, _, basis = np.linalg.svd(vertices - centre)
    s = (vertices - centre) @ basis[0]
    along = np.sin(curvature * s) / curvature - s
    lift = (1.0 - np.cos(curvature * s)) / curvature
    return vertices + along[:, None] * basis[0] + lift[:, None] * basis[2]


def _scene_bending_energy(scene: Scene, positions: np.ndarray) -> float:
    """The scene's bending energy [J] at full positions [V, 3] (0 without a bending term)."""
    x = torch.as_tensor(positions.reshape(1, -1), dtype=torch.float64)
    bending = [e for e in scene.to(dtype=torch.float64).effects if e.kind == "discrete_shell_bending"]
    return float(sum(e.energy(x, None, None)[0] for e in bending))


def matched_shell(scene: Scene) -> ShellMatch:
    """MuJoCo ``young``/``thickness``/``poisson`` that give the scene's membrane and bending (module doc).

    E t and the Poisson ratio come from the scene's membrane. Both bending energies are quadratic in the
    curvature of a flat sheet and MuJoCo's scales with t^2 at fixed E t, so one measurement of each on
    :func:`bent_cylinder` (curvature :data:`BEND_CURVATURE`, pins released in MuJoCo) fixes t.
    """
    scene = scene.to(device="cpu", dtype=torch.float64)  # NumPy probes and MuJoCo run on the CPU
    mesh = sheet_mesh(scene)
    stretch, poisson = _membrane_parameters(scene)
    cylinder = bent_cylinder(mesh.vertices, BEND_CURVATURE)
    target = _scene_bending_energy(scene, cylinder)
    if target <= 0.0:
        raise ValueError(f"scene {scene.name!r} has no bending energy to match")
    probe = 1e-3  # any thickness: MuJoCo's bending energy at fixed E t is probe^2-proportional
    probe_energy = _linear_energy(force_probe(mesh, stretch / probe, poisson, probe), mesh, cylinder)
    thickness = probe * math.sqrt(target / probe_energy)
    young = stretch / thickness
    check = _linear_energy(force_probe(mesh, young, poisson, thickness), mesh, cylinder)
    return ShellMatch(
        young=young,
        poisson=poisson,
        thickness=thickness,
        stretch_stiffness=stretch,
        scene_bending_j=target,
        mujoco_bending_j=check,
        bending_rigidity=young * thickness**3 / (12.0 * (1.0 - poisson**2)),
    )


def force_probe(mesh: SheetMesh, young: float, poisson: float, thickness: float, elastic2d: str = "bend") -> Any:
    """A model of the sheet with its pins released, to read MuJoCo's elastic forces at any positions (Euler:
    its mj_forward solves nothing implicit)."""
    spec = _sheet_spec(mesh, young, poisson, thickness, integrator="Euler", elastic2d=elastic2d, pinned=False)
    return spec.compile()


def _linear_energy(model: Any, mesh: SheetMesh, positions: np.ndarray) -> float:
    """-1/2 f . u [J] of MuJoCo's elastic force f at vertex displacements u: its energy where f is linear in u."""
    sheet = FlexSheet(model, mesh)
    sheet.set_positions(positions)
    force = sheet.elastic_forces()
    return -0.5 * float((force * (positions - mesh.vertices)).sum())


def _sheet_spec(
    mesh: SheetMesh,
    young: float,
    poisson: float,
    thickness: float,
    *,
    integrator: str = CLOTH_INTEGRATOR,
    timestep: float = CLOTH_TIMESTEP,
    elastic2d: str = "both",
    pinned: bool = True,
) -> Any:
    """The MjSpec of the sheet (module doc); ``pinned=False`` releases the pins (for force probes)."""
    import mujoco

    gravity_text = " ".join(repr(float(a)) for a in mesh.gravity)
    points = " ".join(f"{v:.17g}" for v in mesh.vertices.ravel())
    elements = " ".join(str(int(i)) for i in mesh.triangles.ravel())
    pins = f'<pin id="{" ".join(str(int(i)) for i in mesh.pinned)}"/>' if pinned and mesh.pinned.size else ""
    xml = (
        f'<mujoco><option timestep="{float(timestep)!r}" integrator="{integrator}" gravity="{gravity_text}"/>'
        f'<worldbody><flexcomp name="cloth" type="direct" dim="2" radius="0.001" mass="1" '
        f'point="{points}" element="{elements}">'
        '<contact contype="0" conaffinity="0" selfcollide="none"/>'
        f'{pins}<elasticity young="{float(young)!r}" poisson="{float(poisson)!r}" '
        f'thickness="{float(thickness)!r}" elastic2d="{elastic2d}"/>'
        "</flexcomp></worldbody></mujoco>"
    )
    spec = mujoco.MjSpec.from_string(xml)
    floor = 1e-6 * max(float(mesh.vertex_mass.max()), 1e-12)  # released pins need some mass to compile
    for body in spec.bodies:
        if body.name.startswith("cloth_"):
            body.mass = max(float(mesh.vertex_mass[int(body.name.rsplit("_", 1)[1])]), floor)
    return spec


class FlexSheet:
    """A compiled MuJoCo sheet and its state, addressed by the scene's vertex ids.

    Args:
        model: The MjModel of :func:`_sheet_spec`.
        mesh: The :class:`SheetMesh` it was built from.
    """

    def __init__(self, model: Any, mesh: SheetMesh) -> None:
        import mujoco

        self.mujoco = mujoco
        self.model = model
        self.data = mujoco.MjData(model)
        self.mesh = mesh
        body = np.asarray(model.flex_vertbodyid)
        moving = body > 0
        self.moving = np.nonzero(moving)[0]
        """Ids of the vertices with their own body (three slide joints), shape [F]."""
        self.qpos_address = np.asarray(model.jnt_qposadr)[np.asarray(model.body_jntadr)[body[moving]]]
        self.dof_address = np.asarray(model.jnt_dofadr)[np.asarray(model.body_jntadr)[body[moving]]]
        self.body = body
        mujoco.mj_forward(model, self.data)

    @property
    def vertex_count(self) -> int:
        return int(self.model.nflexvert)

    def positions(self) -> np.ndarray:
        """Vertex positions [m], shape [V, 3], of the current qpos (``data.flexvert_xpos`` is one step behind
        after ``mj_step``: it is computed before the step integrates)."""
        out = self.mesh.vertices.copy()
        for k in range(3):
            out[self.moving, k] += self.data.qpos[self.qpos_address + k]
        return out

    def set_positions(self, positions: np.ndarray) -> None:
        """Move the moving vertices to ``positions`` [V, 3] (pinned rows are ignored), at rest, and run mj_forward."""
        for k in range(3):
            self.data.qpos[self.qpos_address + k] = positions[self.moving, k] - self.mesh.vertices[self.moving, k]
        self.data.qvel[:] = 0.0
        self.mujoco.mj_forward(self.model, self.data)

    def velocities(self) -> np.ndarray:
        """Velocities [m/s] of the moving vertices, shape [F, 3]."""
        return np.stack([self.data.qvel[self.dof_address + k] for k in range(3)], 1)

    def elastic_forces(self) -> np.ndarray:
        """MuJoCo's elastic force [N] on each vertex, shape [V, 3] (zero rows for pinned ones)."""
        out = np.zeros((self.vertex_count, 3))
        for k in range(3):
            out[self.moving, k] = self.data.qfrc_spring[self.dof_address + k]
        return out

    def edge_strain(self) -> float:
        """Largest |l / l0 - 1| over the flex's edges at the current qpos."""
        edges = np.asarray(self.model.flex_edge).reshape(-1, 2)
        p = self.positions()
        length = np.linalg.norm(p[edges[:, 1]] - p[edges[:, 0]], axis=1)
        return float(np.abs(length / np.asarray(self.model.flexedge_length0) - 1.0).max())

    def kinetic_energy(self) -> float:
        """1/2 sum m |v|^2 [J] over the moving vertices."""
        return 0.5 * float((self.mesh.vertex_mass[self.moving] * (self.velocities() ** 2).sum(1)).sum())

    def push(self, vertex: int, force: np.ndarray) -> None:
        """Hold ``force`` [N] on ``vertex`` (a moving one) until the next push."""
        self.data.xfrc_applied[self.body[vertex], :3] = force

    def step(self) -> None:
        self.mujoco.mj_step(self.model, self.data)

    def warnings(self) -> int:
        """MuJoCo warnings raised so far (bad accelerations, instabilities, ...)."""
        return sum(int(w.number) for w in self.data.warning)


def flex_sheet(
    scene: Scene,
    *,
    integrator: str = CLOTH_INTEGRATOR,
    timestep: float = CLOTH_TIMESTEP,
    match: ShellMatch | None = None,
) -> FlexSheet:
    """MuJoCo's flex cloth of ``scene`` (module doc), ready to step.

    Args:
        scene: A pure-cloth scene (:func:`sheet_mesh`).
        integrator: MuJoCo integrator (``discrete`` or ``Euler`` for flex elasticity).
        timestep: MuJoCo time step [s].
        match: Elasticity parameters; None: :func:`matched_shell` of the scene.
    """
    if not timestep > 0:
        raise ValueError(f"timestep must be > 0, got {timestep}")
    mesh = sheet_mesh(scene)
    match = matched_shell(scene) if match is None else match
    spec = _sheet_spec(mesh, match.young, match.poisson, match.thickness, integrator=integrator, timestep=timestep)
    return FlexSheet(spec.compile(), mesh)


def whole_steps(seconds: float, timestep: float, what: str = "seconds") -> int:
    """The steps of ``timestep`` [s] in ``seconds`` [s], a whole number >= 1 (float round-off aside).

    Raises:
        ValueError: naming ``what``, where ``seconds`` is not a whole multiple of ``timestep``: the run would last
            another time than asked (``--seconds 0.04`` ran one 0.05 s step, printed as 0.04 s) and runs at other
            time steps would be compared over other times.
    """
    steps = round(seconds / timestep)
    if steps < 1 or not math.isclose(seconds / timestep, steps, rel_tol=1e-9):
        raise ValueError(f"{what} must be a whole multiple of the time step {timestep:g} s, got {seconds:g}")
    return steps


def dropped_positions(mesh: SheetMesh) -> np.ndarray:
    """The seed [V, 3] turned 90 degrees about the line of the pinned vertices, to the side where it is level
    with the ground (normal to gravity) and its centre is higher: released, it falls and swings down."""
    pins = mesh.vertices[mesh.pinned]
    if pins.shape[0] < 2:
        raise ValueError("dropping the sheet needs at least two pinned vertices (the edge it swings about)")
    origin = pins.mean(0)
    axis = np.linalg.svd(pins - origin)[2][0]
    relative = mesh.vertices - origin
    along = relative @ axis
    radial = relative - along[:, None] * axis
    candidates = [origin + along[:, None] * axis + sign * np.cross(axis, radial) for sign in (1.0, -1.0)]
    return max(candidates, key=lambda p: -float(p.mean(0) @ mesh.gravity))


def _total_energy(sheet: FlexSheet, scene: Scene, gravity: np.ndarray) -> float:
    """Kinetic + gravitational + the scene's elastic energy [J] of the sheet's state (redsim's energy terms)."""
    positions = sheet.positions()
    x = torch.as_tensor(positions.reshape(1, -1), dtype=torch.float64)
    elastic = sum(float(e.energy(x, None, None)[0]) for e in scene.effects if e.kind in _ELASTIC_KINDS)
    potential = -float((sheet.mesh.vertex_mass * (positions @ gravity)).sum())
    return sheet.kinetic_energy() + potential + elastic


_ELASTIC_KINDS = ("stvk_membrane", "discrete_shell_bending")


def drop_run(
    scene: Scene,
    *,
    integrator: str,
    timestep: float,
    scenario: str,
    seconds: float = SWEEP_SECONDS,
    match: ShellMatch | None = None,
) -> dict[str, Any]:
    """One stability run of MuJoCo's sheet from rest.

    Scenarios: ``hang`` (from the seed: the sheet hangs in its own plane and stretches under its weight)
    and ``drop`` (from :func:`dropped_positions`: it falls from level and swings down about its pinned
    edge). Every :data:`CHECK_EVERY` s the run is checked for non-finite states, MuJoCo warnings, edge
    strain above :data:`MAX_EDGE_STRAIN` and total energy (kinetic, gravity and the scene's membrane and
    bending energy of MuJoCo's positions) above its start by :data:`ENERGY_GROWTH` m g L.

    Returns:
        ``integrator``, ``timestep``, ``scenario``, ``blew_up``, ``reason`` (None, "nan", "warning",
        "strain", "energy"), ``at_s`` (when), ``max_strain``, ``cpu_s_per_step``.

    Raises:
        ValueError: an unknown scenario, a scene without gravity, or ``seconds`` not a whole multiple of
            ``timestep`` (:func:`whole_steps`).
    """
    import mujoco

    mesh = sheet_mesh(scene)
    if scenario not in ("hang", "drop"):
        raise ValueError(f"scenario must be 'hang' or 'drop', got {scenario!r}")
    gravity = mesh.gravity
    g = float(np.linalg.norm(gravity))
    if g == 0.0:
        raise ValueError(f"scene {scene.name!r} has no gravity to hang or drop under")
    scene64 = scene.to(device="cpu", dtype=torch.float64)
    steps = whole_steps(seconds, timestep)
    every = max(1, round(CHECK_EVERY / timestep))
    reason, at, max_strain, cpu = None, steps, 0.0, 0.0
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda _text: None)  # counted through data.warning instead of printed
    try:
        sheet = flex_sheet(scene64, integrator=integrator, timestep=timestep, match=match)
        if scenario == "drop":
            sheet.set_positions(dropped_positions(mesh))
        ceiling = _total_energy(sheet, scene64, gravity) + ENERGY_GROWTH * mesh.free_mass * g * mesh.size
        for i in range(1, steps + 1):
            start = time.process_time()
            sheet.step()
            cpu += time.process_time() - start
            if i % every and i != steps:
                continue
            if not (np.isfinite(sheet.data.qpos).all() and np.isfinite(sheet.data.qvel).all()):
                reason = "nan"
            elif sheet.warnings():
                reason = "warning"
            else:
                max_strain = max(max_strain, sheet.edge_strain())
                if max_strain > MAX_EDGE_STRAIN:
                    reason = "strain"
                elif _total_energy(sheet, scene64, gravity) > ceiling:
                    reason = "energy"
            if reason:
                at = i
                break
    finally:
        mujoco.set_mju_user_warning(previous)
    return {
        "integrator": integrator,
        "timestep": timestep,
        "scenario": scenario,
        "blew_up": reason is not None,
        "reason": reason,
        "at_s": at * timestep,
        "max_strain": max_strain,
        "cpu_s_per_step": cpu / at,
    }


def timestep_sweep(
    scene: Scene,
    timesteps: dict[str, tuple[float, ...]] | None = None,
    *,
    seconds: float = SWEEP_SECONDS,
    scenarios: tuple[str, ...] = ("hang", "drop"),
    match: ShellMatch | None = None,
) -> list[dict[str, Any]]:
    """:func:`drop_run` of every scenario at every time step of every integrator (default :data:`SWEEP_TIMESTEPS`);
    ``match`` (default :func:`matched_shell`) saves its two model compiles where the caller has one."""
    match = matched_shell(scene) if match is None else match
    rows = []
    for integrator, steps in (SWEEP_TIMESTEPS if timesteps is None else timesteps).items():
        for dt in steps:
            for scenario in scenarios:
                rows.append(
                    drop_run(scene, integrator=integrator, timestep=dt, scenario=scenario, seconds=seconds, match=match)
                )
    return rows


def largest_stable(rows: list[dict[str, Any]]) -> dict[str, float | None]:
    """Per integrator, the largest time step [s] at which no scenario of ``rows`` blew up (None if none)."""
    out: dict[str, float | None] = {}
    for integrator in dict.fromkeys(r["integrator"] for r in rows):
        mine = [r for r in rows if r["integrator"] == integrator]
        good = [
            dt for dt in {r["timestep"] for r in mine} if not any(r["blew_up"] for r in mine if r["timestep"] == dt)
        ]
        out[integrator] = max(good) if good else None
    return out


def time_flex_cloth(
    scene: Scene,
    *,
    steps: int,
    budget: float = float("inf"),
    integrator: str = CLOTH_INTEGRATOR,
    timestep: float = CLOTH_TIMESTEP,
    warmup: int = 10,
    seed: int = 0,
    match: ShellMatch | None = None,
) -> dict[str, Any]:
    """Steps/s and simulated seconds per wall second of MuJoCo's sheet (median over timed ``mj_step`` calls).

    From the seed under the scene's gravity, with a random force of up to :data:`PUSH_FORCE` N per axis
    on the bottom-left corner, drawn anew every :data:`PUSH_EVERY` s of simulated time (as
    ``RedSim/HangingCloth`` pushes it), after ``warmup`` untimed steps; at most ``steps`` timed steps, fewer
    once ``budget`` seconds are spent. ``match`` (default :func:`matched_shell`) saves its two model compiles
    where the caller has one.

    Returns:
        ``vertices``, ``pinned``, ``nv``, ``integrator``, ``timestep``, ``steps``, ``steps_per_s``,
        ``sim_s_per_wall_s``, ``young``, ``thickness``, ``finite`` (the state after the timed steps).
    """
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    match = matched_shell(scene) if match is None else match
    sheet = flex_sheet(scene, integrator=integrator, timestep=timestep, match=match)
    corner = (
        int(scene.handle("bottom_left").points.dofs.reshape(-1)[0]) // 3 if "bottom_left" in scene.handle_names else 0
    )
    if corner not in set(sheet.moving.tolist()):
        corner = int(sheet.moving[0])
    rng = np.random.default_rng(seed)
    every = max(1, round(PUSH_EVERY / timestep))
    counter = {"i": 0}

    def call() -> None:
        if counter["i"] % every == 0:
            sheet.push(corner, rng.uniform(-PUSH_FORCE, PUSH_FORCE, 3))
        sheet.step()
        counter["i"] += 1

    for _ in range(warmup):
        call()
    seconds, count = median_time(call, steps, budget)
    return {
        "vertices": sheet.vertex_count,
        "pinned": int(sheet.mesh.pinned.size),
        "nv": int(sheet.model.nv),
        "integrator": integrator,
        "timestep": timestep,
        "steps": count,
        "steps_per_s": 1.0 / seconds,
        "sim_s_per_wall_s": timestep / seconds,
        "young": match.young,
        "thickness": match.thickness,
        "finite": bool(np.isfinite(sheet.data.qpos).all()),
    }


def rest_sag(
    scene: Scene,
    *,
    integrator: str = CLOTH_INTEGRATOR,
    timestep: float = CLOTH_TIMESTEP,
    settle_s: float = 20.0,
    match: ShellMatch | None = None,
) -> dict[str, Any]:
    """The sheet's rest under gravity, MuJoCo against redsim's full-space rest (:func:`rest_state`).

    MuJoCo's sheet is stepped from the seed for ``settle_s`` simulated seconds (its implicit steps damp
    the in-plane oscillation); redsim's rest is its float64 Newton equilibrium. Compared: how far each
    handle vertex (e.g. the free bottom corners) moved from the seed, and the largest vertex distance
    between the two rests.

    Returns:
        ``handles``: {name: {"mujoco_m": [3], "redsim_m": [3]}} (displacements from the seed),
        ``max_vertex_gap_m``, ``mujoco_speed_m_s`` (largest vertex speed at the end), ``redsim_converged``.

    Raises:
        ValueError: ``settle_s`` not a whole multiple of ``timestep`` (:func:`whole_steps`).
    """
    from redsim.integrators.reference import rest_state

    scene64 = scene.to(device="cpu", dtype=torch.float64)
    settle_steps = whole_steps(settle_s, timestep, "settle_s")
    sheet = flex_sheet(scene64, integrator=integrator, timestep=timestep, match=match)
    for _ in range(settle_steps):
        sheet.step()
    mujoco_rest = sheet.positions()
    q, converged = rest_state(scene64)
    redsim_rest = scene64.full_positions(q[None])[0].reshape(-1, 3).numpy()
    seed = sheet.mesh.vertices
    handles = {}
    for handle in scene64.handles:
        ids = handle.points.dofs.reshape(handle.points.count, -1)[:, 0].numpy() // 3
        w = handle.weights.numpy()[:, None]
        handles[handle.name] = {
            "mujoco_m": ((mujoco_rest[ids] - seed[ids]) * w).sum(0).tolist(),
            "redsim_m": ((redsim_rest[ids] - seed[ids]) * w).sum(0).tolist(),
        }
    return {
        "handles": handles,
        "max_vertex_gap_m": float(np.linalg.norm(mujoco_rest - redsim_rest, axis=1).max()),
        "mujoco_speed_m_s": float(np.linalg.norm(sheet.velocities(), axis=1).max()),
        "redsim_converged": bool(converged),
    }


def flex_cloth_unavailable() -> str | None:
    """Why this Python cannot build the anchor (mujoco missing, or older than 4.0), or None where it can.

    Before 3.13 mujoco has no ``discrete`` integrator or ``MjSpec``; 3.13-3.17 have both, but their 2D flex
    membrane is not the StVK membrane of the module doc (the membrane test fails on each, its forces 60% apart;
    equal to round-off from 4.0.0), so the anchor would be another cloth."""
    import importlib.util

    if importlib.util.find_spec("mujoco") is None:
        return "mujoco is not installed (pip install 'redsim[bench]')"
    import mujoco

    major = int(str(mujoco.__version__).split(".")[0])
    if major < 4 or not hasattr(mujoco.mjtIntegrator, "mjINT_DISCRETE") or not hasattr(mujoco, "MjSpec"):
        return (
            f"mujoco {mujoco.__version__}'s flex cloth is not redsim's StVK sheet (needs mujoco >= 4.0; over a "
            "mujoco 3, `pip uninstall -y mujoco` first: pip's upgrade to MuJoCo 4's split packages leaves `import "
            "mujoco` broken)"
        )
    return None


def cloth_anchor(steps: int, budget: float = ANCHOR_BUDGET) -> dict[str, Any]:
    """The flex cloth anchor of ``redsim bench envs``: :func:`time_flex_cloth` of :data:`CLOTH_SCENE`, or a
    ``reason`` where mujoco is missing or refuses the model (an older one without the ``discrete`` integrator)."""
    reason = flex_cloth_unavailable()
    if reason is not None:
        return {"reason": reason}
    try:
        scene, match = _anchor_sheet()
        return time_flex_cloth(scene, steps=steps, budget=budget, match=match)
    except ValueError as err:
        return {"reason": str(err)}


@functools.cache
def _anchor_sheet() -> tuple[Scene, ShellMatch]:
    """:data:`CLOTH_SCENE` and its :func:`matched_shell`, made once per process: every round of ``redsim bench envs
    --rounds N`` times the same model (the match, ~2 s of MuJoCo compiles, is a pure function of the scene)."""
    import redsim

    scene = redsim.scenes.build(CLOTH_SCENE)
    return scene, matched_shell(scene)


def cloth_anchor_line(cloth: dict[str, Any]) -> str:
    """:func:`cloth_anchor` as one printed line (``failed`` where it raised: :func:`redsim.envs.bench.attempt`)."""
    if "failed" in cloth:
        return f"MuJoCo flex cloth failed: {cloth['failed']}"
    if "reason" in cloth:
        return f"MuJoCo flex cloth skipped: {cloth['reason']}"
    return (
        f"MuJoCo flex cloth ({cloth['vertices']} vertices, {cloth['pinned']} pinned, nv {cloth['nv']}, "
        f"{cloth['integrator']} dt {cloth['timestep']} s): {cloth['steps_per_s']:.1f} steps/s, "
        f"{cloth['sim_s_per_wall_s']:.2f} sim s per wall s"
        + ("" if cloth["finite"] else " (NOT FINITE at the end: no ratio is taken against it)")
    )


def cloth_ratios(rows: list[dict[str, Any]], cloth: dict[str, Any]) -> dict[str, float]:
    """Per cloth env row of :func:`redsim.envs.bench.bench_env` (with vector batches): its best batch's simulated
    s per wall s over the flex cloth's (:func:`cloth_anchor`), of the batches timed (a failed part, ``{"failed":
    ...}``, is left out, an id that failed as a whole too); empty where the flex cloth was not timed, failed or its
    state ended not finite (a blown-up run's speed is no anchor)."""
    if "reason" in cloth or "failed" in cloth or not cloth["finite"]:
        return {}
    timed = {row["id"]: [v for v in row["vector"].values() if "failed" not in v] for row in rows if "failed" not in row}
    return {
        row["id"]: max(v["sim_s_per_wall_s"] for v in timed[row["id"]]) / cloth["sim_s_per_wall_s"]
        for row in rows
        if row["id"] in timed and row["scene"] in CLOTH_SCENES and timed[row["id"]]
    }


def cloth_ratio_lines(ratios: dict[str, float]) -> list[str]:
    """:func:`cloth_ratios` as printed lines (none without any)."""
    if not ratios:
        return []
    cells = ", ".join(f"{env_id} {ratio:.1f}x" for env_id, ratio in ratios.items())
    return [f"cloth envs' best batch over MuJoCo's flex cloth, sim s per wall s (goal >= {CLOTH_GOAL:g}x): {cells}"]


SWING_RUNS: tuple[tuple[str, float], ...] = (
    ("discrete", CLOTH_TIMESTEP),
    ("discrete", 0.02),
    ("discrete", 0.01),
    ("discrete", 0.005),
    ("Euler", 1e-4),
)
"""MuJoCo runs of :func:`swing_check`: the anchor, ``discrete`` at the envs' dt and below, and explicit Euler at a
small step (MuJoCo's most accurate run of the sweep)."""
SWING_REDSIM_DT = 0.02
"""Time step [s] of redsim's full-space reference in :func:`swing_check` (the envs' dt)."""
SWING_HANDLE = "bottom_middle"
"""The handle whose path :func:`swing_check` compares (the middle of the free edge)."""


def _swing_metrics(times: np.ndarray, path: np.ndarray, pivot: np.ndarray, gravity: np.ndarray) -> dict[str, Any]:
    """Passes of a path [K, 3] (at ``times`` [K] s) through the vertical below ``pivot``, its lowest point and how far
    it swings out on the far side after the first pass."""
    down = gravity / np.linalg.norm(gravity)
    side = path[0] - pivot - ((path[0] - pivot) @ down) * down  # where the swing starts, across the vertical
    side /= np.linalg.norm(side)
    across = (path - pivot) @ side
    passes = [
        float(times[k] - across[k] * (times[k + 1] - times[k]) / (across[k + 1] - across[k]))
        for k in range(len(times) - 1)
        if across[k] > 0 >= across[k + 1] or across[k] < 0 <= across[k + 1]
    ]
    after = times > passes[0] if passes else np.zeros(len(times), dtype=bool)
    return {
        "passes_s": passes,
        "lowest_m": float(((path - pivot) @ down).max()),
        "far_side_m": float(-across[after].min()) if after.any() else 0.0,
    }


def swing_check(
    scene: Scene,
    *,
    seconds: float = SWEEP_SECONDS,
    redsim_dt: float = SWING_REDSIM_DT,
    runs: tuple[tuple[str, float], ...] = SWING_RUNS,
    match: ShellMatch | None = None,
) -> dict[str, Any]:
    """The dropped sheet's swing (:func:`dropped_positions`), MuJoCo's ``runs`` (integrator, dt [s]) against redsim.

    redsim's reference is the float64 full-space implicit Euler (Newton, tol 1e-8) at ``redsim_dt`` from the
    same start. Compared per run: the path of :data:`SWING_HANDLE`, sampled at every step: when it passes the
    vertical below the pinned edge (the first pass is a quarter swing), how far below the edge it reaches, how
    far it swings out on the far side after the first pass (what an integrator's damping takes away), and its
    RMS distance [m] from redsim's path at redsim's sample times (linear interpolation).

    Returns:
        ``runs``: list of ``{"name", "timestep", "passes_s", "lowest_m", "far_side_m", "rms_gap_m", "cpu_s",
        "steps"}`` (redsim's first), with redsim's ``unconverged_steps`` (its Newton steps that did not converge)
        and each MuJoCo run's ``warnings`` (:meth:`FlexSheet.warnings`).

    Raises:
        ValueError: ``seconds`` not a whole multiple of ``redsim_dt`` and of every run's time step
            (:func:`whole_steps`): the paths would be compared over other times.
    """
    from redsim.integrators import FullSpace, ImplicitEuler
    from redsim.integrators.implicit_euler import quiet_steps

    steps = whole_steps(seconds, redsim_dt)
    counts = [whole_steps(seconds, dt) for _, dt in runs]
    scene64 = scene.to(device="cpu", dtype=torch.float64)
    mesh = sheet_mesh(scene64)
    start = dropped_positions(mesh)
    handle = scene64.handle(SWING_HANDLE)
    ids = handle.points.dofs.reshape(handle.points.count, -1)[:, 0].numpy() // 3
    weights = handle.weights.numpy()
    pivot = mesh.vertices[mesh.pinned].mean(0)

    def point(positions: np.ndarray) -> np.ndarray:
        return weights @ positions[ids]

    integrator = ImplicitEuler(FullSpace(scene64), redsim_dt, minimizer="newton", tol=1e-8, max_iter=50)
    state = integrator.initial_state(scene64.dof_map.restrict(torch.as_tensor(start.reshape(1, -1)))[0])
    clock = time.process_time()
    path, unconverged = [point(start)], 0
    with quiet_steps():  # counted in the result
        for _ in range(steps):
            state, info = integrator.step(state)
            unconverged += not info.converged
            path.append(point(scene64.full_positions(state.q[None])[0].reshape(-1, 3).numpy()))
    reference_times = redsim_dt * np.arange(steps + 1)
    reference = np.array(path)
    results = [
        {
            "name": f"redsim full space, implicit Euler dt {redsim_dt:g} s",
            "timestep": redsim_dt,
            **_swing_metrics(reference_times, reference, pivot, mesh.gravity),
            "rms_gap_m": 0.0,
            "cpu_s": time.process_time() - clock,
            "steps": steps,
            "unconverged_steps": unconverged,
        }
    ]
    match = matched_shell(scene64) if match is None else match
    for (name, dt), count in zip(runs, counts, strict=True):
        sheet = flex_sheet(scene64, integrator=name, timestep=dt, match=match)
        sheet.set_positions(start)
        clock = time.process_time()
        path = [point(start)]
        for _ in range(count):
            sheet.step()
            path.append(point(sheet.positions()))
        times, mine = dt * np.arange(count + 1), np.array(path)
        sampled = np.stack([np.interp(reference_times, times, mine[:, k]) for k in range(3)], 1)
        results.append(
            {
                "name": f"MuJoCo {name} dt {dt:g} s",
                "timestep": dt,
                **_swing_metrics(times, mine, pivot, mesh.gravity),
                "rms_gap_m": float(np.sqrt(((sampled - reference) ** 2).sum(1).mean())),
                "cpu_s": time.process_time() - clock,
                "steps": count,
                "warnings": sheet.warnings(),
            }
        )
    return {"handle": SWING_HANDLE, "seconds": seconds, "runs": results}


__all__ = [
    "ANCHOR_BUDGET",
    "CLOTH_GOAL",
    "CLOTH_INTEGRATOR",
    "CLOTH_SCENE",
    "CLOTH_SCENES",
    "CLOTH_TIMESTEP",
    "MAX_EDGE_STRAIN",
    "SWEEP_TIMESTEPS",
    "SWING_REDSIM_DT",
    "FlexSheet",
    "SheetMesh",
    "ShellMatch",
    "bent_cylinder",
    "cloth_anchor",
    "cloth_anchor_line",
    "cloth_ratio_lines",
    "cloth_ratios",
    "drop_run",
    "dropped_positions",
    "flex_cloth_unavailable",
    "flex_sheet",
    "force_probe",
    "largest_stable",
    "matched_shell",
    "rest_sag",
    "sheet_mesh",
    "swing_check",
    "time_flex_cloth",
    "timestep_sweep",
    "whole_steps",
]
