"""Scenes: the static description of a physical system, and the builder that makes them.

A :class:`Scene` holds what never changes during a simulation: the layout of the
configuration (free DOFs; pinned ones are removed and re-inserted by
:meth:`Scene.full_positions`), the mass matrix M, the seed state, the effects whose sum is
the potential energy, the handles where loads act, an optional condition space, the
surfaces to draw, drivers and a mirror (guides that only fitting uses, never part of the energy).
Dynamic data (states, loads, conditions) is passed in per call.

Configuration layout: the full vector x concatenates, in the order they were added,
particle blocks (D numbers per vertex) and rigid bodies (12 numbers each, the row-major
affine map ``[R | t]`` taking body-frame points v to ``R v + t``; body frames are centred on
the centre of mass).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from redsim.devices import check_device, check_dtype
from redsim.dofs import DofMap
from redsim.effects.base import Effect
from redsim.effects.external import ExternalLoad, Gravity
from redsim.points import PointSet
from redsim.tensors import as_numbers, cast_tensors

SOURCE_PARAMS = ("source", "mesh_sha256", "selections")
"""Build parameters that record where a mesh scene was read from and the vertex indices its masks and index lists
were given as, not what it is (left out of its fingerprint: the geometry is in ``mesh_digest``, what a selection
chose in its ``ids:`` label)."""


@dataclass(frozen=True)
class Handle:
    """A place where an external load (later: an action) acts.

    Attributes:
        name: Handle name, unique in the scene.
        points: The points the load is spread over.
        weights: Share of the force on each point, shape [P], summing to 1.
    """

    name: str
    points: PointSet
    weights: Tensor

    def position(self, x: Tensor) -> Tensor:
        """Weighted mean position [m] of the handle, shape [B, D]."""
        return (self.points.positions(x) * self.weights[:, None]).sum(-2)


@dataclass(frozen=True)
class Surface:
    """Something to draw: a triangle mesh whose vertices are points of the configuration.

    Attributes:
        name: Surface name.
        points: Mesh vertices, P of them, 2D or 3D.
        faces: Triangles, shape [F, 3], int64 indices into the points.
    """

    name: str
    points: PointSet
    faces: Tensor


@dataclass(frozen=True)
class ConditionSpace:
    """Named scene parameters c with box ranges, for conditional subspaces (paper §3.5).

    Attributes:
        names: Parameter names, m of them.
        low: Lower bounds, shape [m].
        high: Upper bounds, shape [m].
        default: Value used when no condition is given, shape [m].
    """

    names: tuple[str, ...]
    low: Tensor
    high: Tensor
    default: Tensor

    @property
    def dim(self) -> int:
        return len(self.names)

    def describe(self) -> list[dict[str, Any]]:
        """Each parameter's name, range and default, in order (`redsim scenes`)."""
        rows = zip(self.names, self.low.tolist(), self.high.tolist(), self.default.tolist(), strict=True)
        return [{"name": n, "low": lo, "high": hi, "default": d} for n, lo, hi, d in rows]

    def sample(self, count: int, generator: torch.Generator | None = None) -> Tensor:
        """Uniform samples, shape [count, m]."""
        u = torch.rand(count, self.dim, generator=generator, dtype=self.low.dtype, device=self.low.device)
        return self.low + u * (self.high - self.low)


@dataclass(frozen=True)
class Driver:
    """A guide for fitting only: a handle pulled round a circle as one periodic latent turns.

    A mechanism whose motion is a loop far from its seed (a crank) declares one, so that
    ``FitConfig.drive`` can pull a periodic latent's map onto that loop: at angle ``z[latent]``
    the handle's target is ``center + radius (cos(z + phase) axes[0] + sin(z + phase) axes[1])``.
    It is never part of :meth:`Scene.energy`.

    Attributes:
        name: Driver name, unique in the scene.
        handle: The handle it pulls (one of the scene's).
        latent: Index of the periodic latent that turns it.
        center: Centre of the circle [m], shape [D].
        axes: Two orthonormal directions spanning the circle's plane, shape [2, D].
        radius: Radius [m]: the handle's seed distance from ``center`` in that plane.
        phase: Angle [rad] of the handle's seed position, so z = 0 targets the seed.
    """

    name: str
    handle: str
    latent: int
    center: Tensor
    axes: Tensor
    radius: float
    phase: float

    def target(self, angle: Tensor) -> Tensor:
        """Target positions [m], shape [B, D], for latent angles [rad] of shape [B]."""
        turn = (angle + self.phase).unsqueeze(-1)
        return self.center + self.radius * (torch.cos(turn) * self.axes[0] + torch.sin(turn) * self.axes[1])

    def angle(self, position: Tensor) -> Tensor:
        """Angle [rad] in (-pi, pi] of positions [B, D] about the centre, in the plane of ``axes``."""
        offset = position - self.center
        return torch.atan2(offset @ self.axes[1], offset @ self.axes[0])


@dataclass(frozen=True)
class Mirror:
    """A reflection that maps the scene onto itself, for fitting only: P(q) = sign * q[index] + offset.

    A scene whose energy is (nearly) unchanged by a reflection, E(P q) = E(q), declares one (the
    bistable bar: up-down across its centre line, so its two buckled states are each other's
    image); ``FitConfig.mirror`` then asks the map to be equivariant, f(-z) = P f(z). P is an
    affine involution of the free configuration (P(P(q)) = q, checked when the scene is built).

    Attributes:
        index: Free DOF whose value lands on each free DOF, shape [n], int64.
        sign: +1 or -1 per free DOF, shape [n].
        offset: Added after the sign [m], shape [n].
    """

    index: Tensor
    sign: Tensor
    offset: Tensor

    def apply(self, q: Tensor) -> Tensor:
        """P(q) for free configurations q, shape [B, n] -> [B, n]."""
        return self.sign.to(q.dtype) * q[:, self.index] + self.offset.to(q.dtype)


LoadsLike = Tensor | Mapping[str, Sequence[float] | Tensor] | None


@dataclass(frozen=True)
class Scene:
    """A static physical system. Build one with :func:`redsim.scenes.build` or :class:`SceneBuilder`.

    Attributes:
        name: Scene name (the catalog key, or a user's name).
        params: Build parameters (JSON-serializable); with ``name`` they define :meth:`fingerprint`, in place of the
            scene's data: give them only where they determine the scene (a builder's arguments), else none.
        dim: Spatial dimension D (2 or 3).
        dof_map: Free/pinned layout; n = ``dof_map.free_dof_count``.
        mass_matrix: M over free DOFs [kg], sparse COO (coalesced), shape [n, n].
        q_seed: Seed (initial) configuration, shape [n].
        effects: The energy terms; the energy is exactly their sum.
        handles: Where loads act, in load order.
        surfaces: What to draw.
        condition_space: Optional condition parameters.
        description: One line on what the scene is, with its units.
        drivers: Fitting-only guides (:class:`Driver`); not part of the energy.
        mirror: Fitting-only reflection symmetry (:class:`Mirror`), or None.
    """

    name: str
    params: dict[str, Any]
    dim: int
    dof_map: DofMap
    mass_matrix: Tensor
    q_seed: Tensor
    effects: tuple[Effect, ...]
    handles: tuple[Handle, ...] = ()
    surfaces: tuple[Surface, ...] = ()
    condition_space: ConditionSpace | None = None
    description: str = ""
    drivers: tuple[Driver, ...] = ()
    mirror: Mirror | None = None
    _effect_index: dict[str, int] = field(default_factory=dict, repr=False, compare=False)
    _mass_entries: tuple[Tensor, Tensor, Tensor] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        names = [e.name for e in self.effects]
        if len(set(names)) != len(names):
            raise ValueError(f"effect names must be unique, got {names}")
        self._effect_index.update({n: i for i, n in enumerate(names)})
        mass = self.mass_matrix.coalesce()
        rows, cols = mass.indices().clone()  # plain copies: torch.compile cannot trace sparse storage
        object.__setattr__(self, "_mass_entries", (rows, cols, mass.values().clone()))

    # -- layout ---------------------------------------------------------------------------
    @property
    def free_dof_count(self) -> int:
        """n, the size of q."""
        return self.dof_map.free_dof_count

    @property
    def full_dof_count(self) -> int:
        """N, the size of x (pinned entries included)."""
        return self.dof_map.full_dof_count

    @property
    def dtype(self) -> torch.dtype:
        return self.q_seed.dtype

    @property
    def device(self) -> torch.device:
        return self.q_seed.device

    @property
    def handle_names(self) -> tuple[str, ...]:
        return tuple(h.name for h in self.handles)

    @property
    def condition_dim(self) -> int:
        return 0 if self.condition_space is None else self.condition_space.dim

    def full_positions(self, q: Tensor) -> Tensor:
        """Full configurations [B, N] from free ones [B, n]."""
        return self.dof_map.expand(q)

    def handle_positions(self, q: Tensor) -> Tensor:
        """Positions [B, H*D] [m] of the handles, in handle order, at free configurations q [B, n]."""
        x = self.full_positions(q)
        return torch.cat([h.position(x) for h in self.handles], -1)

    def extent(self) -> float:
        """Physical size [m]: the largest side of the bounding box of the surfaces at the seed.

        Unlike the spread of raw x entries it ignores the unitless rotation entries of rigid
        bodies. Scenes without surfaces use the spread of all full-configuration entries.
        Computed once per scene (the env overlays ask for it every frame).
        """
        return self._extent

    @functools.cached_property
    def _extent(self) -> float:
        x = self.full_positions(self.q_seed.detach().unsqueeze(0))
        points = torch.cat([s.points.positions(x)[0] for s in self.surfaces]) if self.surfaces else x.reshape(-1, 1)
        size = float((points.max(0).values - points.min(0).values).max())
        return size if size > 0.0 else 1.0

    def feature_size(self) -> float:
        """Thinnest feature [m] any effect resolves (e.g. a contact tube radius); inf without one."""
        return min((e.feature_size for e in self.effects), default=math.inf)

    def driver(self, name: str) -> Driver:
        """The driver called ``name``; a KeyError lists the scene's drivers."""
        for d in self.drivers:
            if d.name == name:
                return d
        raise KeyError(f"scene {self.name!r} has no driver {name!r}; it has {[d.name for d in self.drivers]}")

    def handle(self, name: str) -> Handle:
        """The handle called ``name``; a KeyError lists the scene's handles."""
        if name not in self.handle_names:
            raise KeyError(f"scene {self.name!r} has no handle {name!r}; it has {list(self.handle_names)}")
        return self.handles[self.handle_names.index(name)]

    def effect(self, name: str) -> Effect:
        """The effect called ``name``; a KeyError lists the scene's effects."""
        if name not in self._effect_index:
            raise KeyError(f"scene {self.name!r} has no effect {name!r}; it has {list(self._effect_index)}")
        return self.effects[self._effect_index[name]]

    def load_free_effects(self, user: str) -> tuple[Effect, ...]:
        """The effects but the load term (:class:`ExternalLoad`, whose work a latent step adds in closed form), for
        ``user`` (named in the error): the effects E(q; c) a latent energy or a cubature evaluates.

        Raises:
            ValueError: another effect reads the loads (``uses_loads``): ``user`` evaluates E without them, so it
                would drop that effect; the full-space integrators take it.
        """
        other = [e.name for e in self.effects if e.uses_loads and not isinstance(e, ExternalLoad)]
        if other:
            raise ValueError(
                f"scene {self.name!r}: effect(s) {other} read the loads; {user} handles only the linear load term "
                "(external_load) in closed form and would drop them. Model a load-dependent energy in full space "
                "(redsim.integrators), or as an effect of the configuration (and condition) alone"
            )
        return tuple(e for e in self.effects if not e.uses_loads)

    # -- energy ---------------------------------------------------------------------------
    def energy(self, q: Tensor, loads: LoadsLike = None, cond: Tensor | None = None) -> Tensor:
        """Potential energy [J], shape [B], of free configurations q, shape [B, n] ([n] gives a scalar).

        ``loads``: forces [N] on the handles, a tensor [B, H, D] (or [H, D]) or ``{handle: [D]}``; None: none.
        ``cond``: the condition c [B, m] of a conditional scene (None: its default).
        """
        return sum(self.energy_terms(q, loads, cond).values())  # type: ignore[return-value]

    def energy_terms(self, q: Tensor, loads: LoadsLike = None, cond: Tensor | None = None) -> dict[str, Tensor]:
        """Energy [J] of each declared effect, by name; each shape [B] ([] for q of shape [n]); ``loads`` and
        ``cond`` as in :meth:`energy`."""
        if not isinstance(q, Tensor):  # a numpy array's dtype read as the scene's in the message below
            raise TypeError(f"q must be a torch tensor [B, n], got {type(q).__name__}: torch.as_tensor(q, scene.dtype)")
        single = q.ndim == 1
        if single:
            q = q.unsqueeze(0)
        if q.ndim != 2 or q.shape[1] != self.free_dof_count:
            raise ValueError(f"scene {self.name!r} expects q of shape [B, {self.free_dof_count}], got {tuple(q.shape)}")
        if q.dtype != self.dtype or q.device != self.device:
            raise ValueError(
                f"scene {self.name!r} is {self.dtype} on {self.device}, q is {q.dtype} on {q.device}: convert one "
                f"(q.to(scene.dtype) or scene.to(dtype=q.dtype))"
            )
        x = self.full_positions(q)
        loads_t = self.pack_loads(loads, q.shape[0], q)
        cond_t = self.pack_condition(cond, q.shape[0], q)
        terms = {e.name: e.energy(x, cond_t, loads_t) for e in self.effects}
        for name, value in terms.items():
            if value.shape != (q.shape[0],):
                raise ValueError(
                    f"effect {name!r} of scene {self.name!r} returned an energy of shape {tuple(value.shape)} for "
                    f"{q.shape[0]} configuration(s), not [{q.shape[0]}]: element_energy must return [B, T]"
                )
        return {k: v[0] for k, v in terms.items()} if single else terms

    def pack_loads(self, loads: LoadsLike, batch: int, like: Tensor | None = None) -> Tensor | None:
        """Loads as a tensor [B, H, D] in handle order from a tensor or a {handle: force} mapping.

        Raises:
            ValueError: on an unknown handle name or a wrong shape.
        """
        if loads is None:
            return None
        dtype = like.dtype if like is not None else self.dtype
        device = like.device if like is not None else self.device
        H, D = len(self.handles), self.dim
        if isinstance(loads, Mapping):
            unknown = sorted(set(loads) - set(self.handle_names))
            if unknown:
                raise ValueError(
                    f"scene {self.name!r} has no handle(s) {unknown}; valid handles: {list(self.handle_names)}"
                )
            out = torch.zeros(batch, H, D, dtype=dtype, device=device)
            for i, h in enumerate(self.handle_names):
                if h in loads:
                    f = as_numbers(loads[h], f"load on handle {h!r}", f"[{D}] or [{batch}, {D}]", dtype, device)
                    if f.ndim == 0 or f.shape[-1] != D:
                        raise ValueError(
                            f"load on handle {h!r} must have {D} components (a force [{D}] or [{batch}, {D}]), got "
                            f"shape {tuple(f.shape)}"
                        )
                    try:
                        out[:, i] = f
                    except RuntimeError:
                        raise ValueError(
                            f"load on handle {h!r} must be a force [{D}] or [{batch}, {D}] for {batch} "
                            f"configuration(s), got shape {tuple(f.shape)}"
                        ) from None
            return out
        loads = as_numbers(loads, "loads", f"[{batch}, {H}, {D}] or [{H}, {D}]", dtype, device)
        if loads.ndim == 2:
            loads = loads.unsqueeze(0).expand(batch, -1, -1)
        if loads.shape != (batch, H, D):
            raise ValueError(
                f"loads must have shape [{batch}, {H}, {D}] (handles {list(self.handle_names)}), "
                f"got {tuple(loads.shape)}"
            )
        return loads

    def pack_condition(self, cond: Tensor | None, batch: int, like: Tensor | None = None) -> Tensor | None:
        """Condition vectors [B, m]; the space's default when ``cond`` is None."""
        space = self.condition_space
        if space is None:
            if cond is not None:
                raise ValueError(f"scene {self.name!r} has no condition space, but a condition was given")
            return None
        dtype = like.dtype if like is not None else self.dtype
        device = like.device if like is not None else self.device
        c = space.default if cond is None else as_numbers(cond, "condition", f"[{batch}, {space.dim}]", dtype)
        c = c.to(dtype=dtype, device=device)
        if c.ndim == 1:
            c = c.unsqueeze(0).expand(batch, -1)
        if c.shape != (batch, space.dim):
            raise ValueError(
                f"condition must have shape [{batch}, {space.dim}] ({list(space.names)}), got {tuple(c.shape)}"
            )
        return c

    # -- mass -----------------------------------------------------------------------------
    def mass_matvec(self, v: Tensor) -> Tensor:
        """M v for v of shape [B, n] (or [n]); differentiable in v.

        A gather (``index_select``, whose backward is an ``index_add``, not a sorting ``index_put_``)
        and an ``index_add`` over M's stored entries (in M's dtype): the same sums as a sparse
        product, and traceable by ``torch.compile`` (a fit's compiled loss uses it).
        """
        if v.ndim == 1:
            return self.mass_matvec(v.unsqueeze(0))[0]
        rows, cols, values = self._mass_entries
        out = torch.zeros(v.shape, dtype=values.dtype, device=v.device)
        return out.index_add_(-1, rows, v.to(values.dtype).index_select(-1, cols) * values).to(v.dtype)

    def mass_norm_sq(self, v: Tensor) -> Tensor:
        """|v_s|_M^2 [kg x configuration unit^2] of rows v [S, n], shape [S] (differentiable)."""
        return (v * self.mass_matvec(v)).sum(-1)

    def mass_matrix_scipy(self) -> Any:
        """M as a ``scipy.sparse.csr_matrix`` (float64)."""
        import scipy.sparse

        M = self.mass_matrix.cpu().to(torch.float64).coalesce()
        rows, cols = M.indices().numpy()
        return scipy.sparse.csr_matrix((M.values().numpy(), (rows, cols)), shape=tuple(M.shape))

    # -- bookkeeping ----------------------------------------------------------------------
    def fingerprint(self) -> str:
        """Hash of the scene name and build parameters (checkpoints refuse other scenes). Where a mesh was read
        from (:data:`SOURCE_PARAMS`) is left out: its geometry is in ``mesh_digest``, so a project copied elsewhere
        holds the same scene. A hand-built scene (no builder arguments) is hashed by its data."""
        params = {k: v for k, v in self.params.items() if k not in SOURCE_PARAMS}
        if not params:
            params = {"data": self._data_digest()}
        return _hash({"name": self.name, "params": params})

    def accepts(self, fingerprint: str | None) -> bool:
        """Whether a checkpoint's recorded fingerprint names this scene: this one, or the one written before stop
        29's rule (name and every parameter, a mesh's file path included; a hand-built scene's name alone)."""
        before = {k: v for k, v in self.params.items() if k != "selections"}  # recorded since stop 63
        if fingerprint in (self.fingerprint(), _hash({"name": self.name, "params": before})):
            return True
        params = {k: v for k, v in self.params.items() if k not in SOURCE_PARAMS}
        return not params and fingerprint == _hash({"name": self.name, "params": {"data": self._data_digest(1)}})

    def _data_digest(self, version: int = 2) -> str:
        """Hash of the seed state, the free DOFs, the mass matrix, the condition space and every effect's kind and
        data (tensors, numbers, strings, and the lists, tuples, dicts and arrays that hold them: materials,
        elements, pins); floats as float32, so float32 and float64 copies agree. ``version`` 1: the digest stop 29
        to 30 wrote (no condition space, containers skipped), which :meth:`accepts` still takes."""
        h = hashlib.sha256(_bytes(self.q_seed))
        h.update(str((self.free_dof_count, self.full_dof_count, self.handle_names)).encode())
        h.update(_bytes(self.mass_matrix.to_dense() if self.mass_matrix.is_sparse else self.mass_matrix))
        if version > 1 and self.condition_space is not None:
            _digest_value(h, "condition_space", vars(self.condition_space), depth=2, containers=True)
        for effect in self.effects:
            h.update(f"{effect.name}:{effect.kind}:{effect.element_count}".encode())
            _digest_fields(h, effect, depth=2, containers=version > 1)
        return h.hexdigest()[:16]

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Scene:
        """A copy on ``device`` with floating data in ``dtype``: torch.float32 or torch.float64 (energies in float64
        are the reference), or None to keep the scene's.

        Raises:
            ValueError: any other dtype (an integer one truncated the seed state, float16 overflowed energies), or a
                device redsim cannot run on (:func:`redsim.devices.check_device`).
        """
        if dtype is not None:
            check_dtype(dtype, f"the dtype of scene {self.name!r}")
        if device is not None:
            device = check_device(device)
        mass = self.mass_matrix.to(device=device)
        if dtype is not None:
            mass = mass.to(dtype)
        return dataclasses.replace(
            self,
            dof_map=self.dof_map.to(device, dtype),
            mass_matrix=mass,
            q_seed=self.q_seed.to(device=device, dtype=dtype),
            effects=tuple(e.to(device, dtype) for e in self.effects),
            handles=cast_tensors(self.handles, device, dtype),
            surfaces=cast_tensors(self.surfaces, device, dtype),
            condition_space=cast_tensors(self.condition_space, device, dtype),
            drivers=cast_tensors(self.drivers, device, dtype),
            mirror=cast_tensors(self.mirror, device, dtype),
            _effect_index={},
        )

    def __repr__(self) -> str:
        """One line: name, n, dim, effects, handles and conditions (not the tensors; :meth:`describe` has more)."""
        conditions = "" if self.condition_space is None else f", conditions={list(self.condition_space.names)}"
        return (
            f"Scene({self.name!r}, n={self.free_dof_count}, dim={self.dim}, effects={[e.name for e in self.effects]}, "
            f"handles={list(self.handle_names)}{conditions})"
        )

    def describe(self) -> dict[str, Any]:
        """Summary for `redsim scenes`: n, effects, handles, conditions (names, and with their ranges and defaults)."""
        return {
            "name": self.name,
            "description": self.description,
            "dim": self.dim,
            "n": self.free_dof_count,
            "full_dofs": self.full_dof_count,
            "effects": [e.describe() for e in self.effects],
            "handles": list(self.handle_names),
            "conditions": [] if self.condition_space is None else list(self.condition_space.names),
            "condition_space": None if self.condition_space is None else self.condition_space.describe(),
            "drivers": [d.name for d in self.drivers],
            "mirror": self.mirror is not None,
            "params": self.params,
            "fingerprint": self.fingerprint(),
        }


class SceneBuilder:
    """Collects particles, rigid bodies, pins, effects, handles and surfaces; :meth:`finalize` makes a Scene.

    Example::

        b = SceneBuilder(dim=3)
        ids = b.add_particles(vertices, masses)
        b.pin_particles(ids[:4])
        b.add_effect(NeoHookean("elastic", b.particle_dofs(tets), vertices[tets], young=1e5, poisson=0.4))
        b.add_gravity((0.0, -9.81, 0.0))
        scene = b.finalize("my_scene")  # fingerprinted by its data; params=... only if they determine it
    """

    default_rigid_stiffness = 5000.0

    def __init__(self, dim: int) -> None:
        if dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {dim}")
        self.dim = dim
        self._dof_count = 0
        self._seed: list[Tensor] = []
        self._particle_first_dof: list[Tensor] = []
        self._particle_mass: list[Tensor] = []
        self._body_first_dof: list[int] = []
        self._body_mass_block: list[Tensor] = []
        self._pinned: list[Tensor] = []
        self._pinned_values: list[Tensor] = []
        self._effects: list[Effect] = []
        self._handles: list[tuple[str, PointSet, Tensor]] = []
        self._surfaces: list[Surface] = []
        self._conditions: list[tuple[str, float, float, float]] = []
        self._drivers: list[tuple[str, str, int, Tensor, Tensor]] = []
        self._mirror: tuple[Tensor, int, float] | None = None

    # -- content --------------------------------------------------------------------------
    @property
    def particle_count(self) -> int:
        return sum(int(t.numel()) for t in self._particle_first_dof)

    @property
    def body_count(self) -> int:
        return len(self._body_first_dof)

    def add_particles(self, positions: Tensor, masses: Tensor) -> Tensor:
        """Add V particles at ``positions`` [m] ([V, D], the seed state) with lumped ``masses`` [kg] ([V]).

        Returns:
            Their particle ids, shape [V], int64.
        """
        positions = torch.as_tensor(positions, dtype=torch.float64)
        masses = torch.as_tensor(masses, dtype=torch.float64).reshape(-1)
        if positions.ndim != 2 or positions.shape[1] != self.dim or masses.shape[0] != positions.shape[0]:
            raise ValueError(
                f"positions must be [V, {self.dim}] and masses [V]; got {tuple(positions.shape)}, {tuple(masses.shape)}"
            )
        if (
            not bool(torch.isfinite(positions).all())
            or bool((masses < 0).any())
            or not bool(torch.isfinite(masses).all())
        ):
            raise ValueError("particle positions must be finite and masses finite and >= 0")
        first = self.particle_count
        V = positions.shape[0]
        self._particle_first_dof.append(self._dof_count + self.dim * torch.arange(V))
        self._particle_mass.append(masses)
        self._seed.append(positions.reshape(-1))
        self._dof_count += V * self.dim
        return torch.arange(first, first + V)

    def particle_dofs(self, ids: Tensor) -> Tensor:
        """Full-configuration index of each coordinate of particles ``ids`` (integers, any shape S) -> [*S, D].

        Raises:
            ValueError: ids that are not integers (a bool mask would otherwise index particles 0 and 1) or out of
                range.
        """
        ids = torch.as_tensor(ids)
        if ids.numel() and (ids.dtype == torch.bool or ids.is_floating_point() or ids.is_complex()):
            hint = ": a mask? pass mask.nonzero().reshape(-1)" if ids.dtype == torch.bool else ""
            raise ValueError(f"particle ids must be integers, got {ids.dtype}{hint}")
        ids = ids.to(torch.int64)
        first = torch.cat(self._particle_first_dof) if self._particle_first_dof else torch.zeros(0, dtype=torch.int64)
        if ids.numel() and (int(ids.min()) < 0 or int(ids.max()) >= first.numel()):
            raise ValueError(f"particle id out of range [0, {first.numel()})")
        return first[ids].unsqueeze(-1) + torch.arange(self.dim)

    def particle_points(self, ids: Tensor) -> PointSet:
        """The particles ``ids`` (any shape, flattened) as points, e.g. for a handle or a surface."""
        return PointSet.particles(self.particle_dofs(torch.as_tensor(ids).reshape(-1)))

    def particle_positions(self, ids: Tensor) -> Tensor:
        """Seed positions [m] of particles ``ids``, shape [*S, D]."""
        seed = torch.cat(self._seed)
        return seed[self.particle_dofs(ids)]

    def add_body(self, mass_block: Tensor, transform: Tensor | None = None) -> int:
        """Add an affine rigid body (3D only).

        Args:
            mass_block: The 4x4 matrix sum_v m_v [v;1][v;1]^T over the body-frame mass
                distribution [kg, kg m, kg m^2] (see :func:`redsim.meshes.affine_mass_block`); the frame's origin
                need not be the centre of mass (block[:3, 3] / block[3, 3]), where gravity acts.
            transform: Seed 3x4 ``[R | t]``; identity rotation at the origin by default.

        Returns:
            The body id.
        """
        if self.dim != 3:
            raise ValueError("rigid bodies need a 3D scene")
        mass_block = torch.as_tensor(mass_block, dtype=torch.float64)
        if mass_block.shape != (4, 4) or not bool(torch.isfinite(mass_block).all()) or not mass_block[3, 3] > 0:
            raise ValueError("mass_block must be a finite 4x4 matrix with positive mass at [3, 3]")
        transform = (
            torch.eye(3, 4, dtype=torch.float64)
            if transform is None
            else torch.as_tensor(transform, dtype=torch.float64)
        )
        if transform.shape != (3, 4):
            raise ValueError(f"transform must be 3x4, got {tuple(transform.shape)}")
        self._body_first_dof.append(self._dof_count)
        self._body_mass_block.append(mass_block)
        self._seed.append(transform.reshape(-1))
        self._dof_count += 12
        return self.body_count - 1

    def body_dofs(self, body: int) -> Tensor:
        """The 12 full-configuration indices of body ``body`` (row-major ``[R | t]``)."""
        if not 0 <= body < self.body_count:
            raise ValueError(f"body id {body} out of range [0, {self.body_count})")
        return self._body_first_dof[body] + torch.arange(12)

    def body_points(self, body: int, local: Tensor, *, direction: bool = False) -> PointSet:
        """Points fixed in body ``body`` at ``local`` [P, 3] [m] in its frame (``direction``: vectors, which ignore
        the body's translation)."""
        return PointSet.body_points(self.body_dofs(body), local, direction=direction)

    def pin_particles(self, ids: Tensor, positions: Tensor | None = None) -> None:
        """Remove particles ``ids`` (P of them) from q, holding them at ``positions`` [m], shape [P, D], finite
        (default: their seed)."""
        dofs = self.particle_dofs(torch.as_tensor(ids).reshape(-1))
        if positions is None:
            values = self.particle_positions(torch.as_tensor(ids).reshape(-1))
        else:
            values = torch.as_tensor(positions, dtype=torch.float64)
            if values.shape != dofs.shape:
                raise ValueError(
                    f"pin_particles: positions must have shape [{dofs.shape[0]}, {self.dim}] (one row per pinned "
                    f"particle), got {list(values.shape)}"
                )
            if not bool(torch.isfinite(values).all()):
                i = int(torch.nonzero(~torch.isfinite(values).all(-1))[0, 0])
                raise ValueError(f"pin_particles: positions must be finite, got {values[i].tolist()} in row {i}")
        self._pinned.append(dofs.reshape(-1))
        self._pinned_values.append(values.reshape(-1))

    def add_effect(self, effect: Effect) -> Effect:
        """Declare ``effect``: the scene's energy is the sum of the declared effects (its ``element_dofs`` are
        checked at :meth:`finalize`). Returns the effect."""
        self._effects.append(effect)
        return effect

    def add_gravity(self, acceleration: Sequence[float]) -> Gravity:
        """Gravity on every particle and on every body's centre of mass."""
        sets, masses = [], []
        if self._particle_first_dof:
            sets.append(self.particle_points(torch.arange(self.particle_count)))
            masses.append(torch.cat(self._particle_mass))
        if self._body_first_dof:  # at the centre of mass, in the body frame block[:3, 3] / m (0 where centred)
            centres = [(m[:3, 3] / m[3, 3]).reshape(1, 3) for m in self._body_mass_block]
            sets.extend(self.body_points(b, centre) for b, centre in enumerate(centres))
            masses.append(torch.stack([m[3, 3] for m in self._body_mass_block]))
        if not sets:
            raise ValueError("add particles or bodies before gravity")
        gravity = Gravity(
            "gravity", PointSet.cat(sets), torch.cat(masses), torch.as_tensor(acceleration, dtype=torch.float64)
        )
        self.add_effect(gravity)
        return gravity

    def add_handle(self, name: str, points: PointSet, weights: Tensor | None = None) -> None:
        """A named place where loads act; ``weights`` [P] (default uniform), each finite and > 0, are normalised to
        sum to 1."""
        if any(h[0] == name for h in self._handles):
            raise ValueError(f"handle {name!r} already exists")
        w = (
            torch.ones(points.count, dtype=torch.float64)
            if weights is None
            else torch.as_tensor(weights, dtype=torch.float64)
        )
        if not points.count:
            raise ValueError(f"handle {name!r} has no points")
        rule = f"handle {name!r} needs {points.count} finite positive weights"
        if w.shape != (points.count,):
            raise ValueError(f"{rule}, got weights of shape {list(w.shape)}")
        bad = torch.nonzero(~((w > 0) & torch.isfinite(w))).reshape(-1)
        if bad.numel():
            raise ValueError(f"{rule}, got {float(w[bad[0]])!r} at point {int(bad[0])}")
        self._handles.append((name, points, w / w.sum()))

    def add_surface(self, name: str, points: PointSet, faces: Tensor) -> None:
        """A triangle surface for rendering and mesh export: ``faces`` [F, 3] index ``points``.

        Raises:
            ValueError: a name used before, or faces not of shape [F, 3] or indexing past ``points``.
        """
        if any(surface.name == name for surface in self._surfaces):
            raise ValueError(f"surface {name!r} already exists")
        faces = torch.as_tensor(faces, dtype=torch.int64)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"surface {name!r}: faces must have shape [F, 3], got {list(faces.shape)}")
        if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= points.count):
            raise ValueError(
                f"surface {name!r}: face indices must lie in [0, {points.count}) (its points), got "
                f"{int(faces.min())}..{int(faces.max())}"
            )
        self._surfaces.append(Surface(name, points, faces))

    def add_driver(
        self, name: str, handle: str, center: Sequence[float], axes: Sequence[Sequence[float]], *, latent: int = 0
    ) -> None:
        """Declare a fitting-only :class:`Driver` pulling handle ``handle`` round ``center`` [m].

        ``axes`` (two non-parallel directions, orthonormalized here) span the circle's plane; the
        radius and phase come from the handle's seed position at :meth:`finalize`.
        """
        if any(d[0] == name for d in self._drivers):
            raise ValueError(f"driver {name!r} already exists")
        if not any(h[0] == handle for h in self._handles):
            raise ValueError(f"driver {name!r}: no handle {handle!r} (add the handle first)")
        if latent < 0:
            raise ValueError(f"driver {name!r}: latent must be >= 0, got {latent}")
        c = torch.as_tensor(center, dtype=torch.float64)
        a = torch.as_tensor(axes, dtype=torch.float64)
        if c.shape != (self.dim,) or a.shape != (2, self.dim):
            raise ValueError(f"driver {name!r}: center must be [{self.dim}] and axes [2, {self.dim}]")
        u = a[0] / a[0].norm()
        v = a[1] - (a[1] @ u) * u
        if not float(v.norm()) > 1e-9 * float(a[1].norm()) or not float(a[0].norm()) > 0:
            raise ValueError(f"driver {name!r}: axes must be two non-parallel, non-zero directions")
        self._drivers.append((name, handle, latent, c, torch.stack([u, v / v.norm()])))

    def mirror_particles(self, partner: Tensor, axis: int, plane: float) -> None:
        """Declare a fitting-only :class:`Mirror`: reflect coordinate ``axis`` about ``plane`` [m] and swap particles.

        Particle i lands on particle ``partner[i]`` with x_axis -> 2 plane - x_axis (the other
        coordinates unchanged). ``partner`` [particle_count] must be an involution; pinned
        particles must map to pinned ones at mirrored positions (checked at :meth:`finalize`).
        Scenes with rigid bodies cannot declare one.
        """
        partner = torch.as_tensor(partner, dtype=torch.int64)
        if self._body_first_dof:
            raise ValueError("mirror_particles: the scene has rigid bodies (only particle scenes can be mirrored)")
        if partner.shape != (self.particle_count,):
            raise ValueError(
                f"mirror_particles: partner must have shape [{self.particle_count}], got {list(partner.shape)}"
            )
        if not 0 <= axis < self.dim:
            raise ValueError(f"mirror_particles: axis must be in [0, {self.dim}), got {axis}")
        if bool((partner < 0).any() or (partner >= self.particle_count).any()) or not torch.equal(
            partner[partner], torch.arange(self.particle_count)
        ):
            raise ValueError("mirror_particles: partner must be an involution of the particle ids")
        self._mirror = (partner, int(axis), float(plane))

    def add_condition(self, name: str, low: float, high: float, default: float | None = None) -> int:
        """Declare a condition parameter with finite bounds low < high and a default in [low, high] (None: the
        middle); returns its index in c.

        Raises:
            ValueError: a name declared before, bounds that are not finite with low < high, or a default outside them.
        """
        if any(c[0] == name for c in self._conditions):
            raise ValueError(f"condition {name!r} already exists")
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise ValueError(f"condition {name!r} needs finite low < high, got [{low}, {high}]")
        default = 0.5 * (low + high) if default is None else default
        if not low <= default <= high:
            raise ValueError(f"condition {name!r}: default {default} lies outside [{low}, {high}]")
        self._conditions.append((name, float(low), float(high), float(default)))
        return len(self._conditions) - 1

    # -- finalize -------------------------------------------------------------------------
    def finalize(
        self,
        name: str,
        params: dict[str, Any] | None = None,
        *,
        description: str = "",
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> Scene:
        """Freeze everything into a :class:`Scene` (adds the ``external_load`` term when there are handles)."""
        N = self._dof_count
        if N == 0:
            raise ValueError("the scene is empty")
        seed = torch.cat(self._seed)
        pinned = torch.cat(self._pinned) if self._pinned else torch.zeros(0, dtype=torch.int64)
        if pinned.numel():
            values = torch.cat(self._pinned_values)
            order = torch.argsort(pinned, stable=True)
            same = pinned[order][1:] == pinned[order][:-1]
            clash = same & (values[order][1:] != values[order][:-1])
            if bool(clash.any()):  # which position would win is not defined
                dof = int(pinned[order][1:][clash][0])
                raise ValueError(f"DOF {dof} is pinned twice at different positions; pin each particle once")
            seed[pinned] = values
        free_mask = torch.ones(N, dtype=torch.bool)
        free_mask[pinned] = False
        free_index = torch.nonzero(free_mask).reshape(-1)
        if free_index.numel() == 0:
            raise ValueError("every DOF is pinned")
        dof_map = DofMap(free_index, seed)

        effects = list(self._effects)
        for effect in effects:
            _check_element_dofs(effect, N)
        for handle_name, points, _ in self._handles:  # a load on a handle no free DOF moves would do nothing
            if not bool((free_mask[points.dofs] & (points.weights != 0).unsqueeze(1)).any()):
                raise ValueError(f"handle {handle_name!r} has no point a free DOF moves (all pinned or fixed)")
        if self._handles:
            points = PointSet.cat([h[1] for h in self._handles])
            index = torch.cat([torch.full((h[1].count,), i, dtype=torch.int64) for i, h in enumerate(self._handles)])
            weights = torch.cat([h[2] for h in self._handles])
            effects.append(ExternalLoad("external_load", points, index, weights, len(self._handles)))
        handles = tuple(Handle(n, p, w) for n, p, w in self._handles)
        space = None
        if self._conditions:
            names, low, high, default = zip(*self._conditions, strict=True)
            space = ConditionSpace(
                tuple(names),
                torch.tensor(low, dtype=torch.float64),
                torch.tensor(high, dtype=torch.float64),
                torch.tensor(default, dtype=torch.float64),
            )
        drivers = []
        seed_x = dof_map.expand(seed[free_index].unsqueeze(0))
        for driver, handle, latent, center, axes in self._drivers:
            points, weights = next((p, w) for n, p, w in self._handles if n == handle)
            offset = (points.positions(seed_x)[0] * weights[:, None]).sum(0) - center
            radius = float((offset @ axes.T).norm())
            if not radius > 0.0:
                raise ValueError(f"driver {driver!r}: handle {handle!r} sits on the centre (radius 0)")
            phase = math.atan2(float(offset @ axes[1]), float(offset @ axes[0]))
            drivers.append(Driver(driver, handle, latent, center, axes, radius, phase))
        mirror = self._finalize_mirror(dof_map, seed, free_mask)
        scene = Scene(
            name=name,
            params=dict(params or {}),
            dim=self.dim,
            dof_map=dof_map,
            mass_matrix=self._mass_matrix(dof_map),
            q_seed=seed[free_index].clone(),
            effects=tuple(effects),
            handles=handles,
            surfaces=tuple(self._surfaces),
            condition_space=space,
            description=description,
            drivers=tuple(drivers),
            mirror=mirror,
        )
        return scene.to(device, dtype) if (device is not None or dtype != torch.float64) else scene

    def _finalize_mirror(self, dof_map: DofMap, seed: Tensor, free_mask: Tensor) -> Mirror | None:
        """The free-DOF :class:`Mirror` of :meth:`mirror_particles` (None without one)."""
        if self._mirror is None:
            return None
        partner, axis, plane = self._mirror
        ids = torch.arange(self.particle_count)
        index = torch.empty(self._dof_count, dtype=torch.int64)
        index[self.particle_dofs(ids).reshape(-1)] = self.particle_dofs(partner).reshape(-1)
        sign = torch.ones(self._dof_count, dtype=torch.float64)
        offset = torch.zeros(self._dof_count, dtype=torch.float64)
        flipped = self.particle_dofs(ids)[:, axis]
        sign[flipped], offset[flipped] = -1.0, 2.0 * plane
        mirrored = sign * seed[index] + offset
        if not torch.equal(free_mask[index], free_mask) or not torch.allclose(
            mirrored[~free_mask], seed[~free_mask], atol=1e-9
        ):
            raise ValueError("mirror_particles: pinned particles must map to pinned particles at mirrored positions")
        free_index = dof_map.free_index
        position = torch.full((self._dof_count,), -1, dtype=torch.int64)
        position[free_index] = torch.arange(free_index.numel())
        return Mirror(position[index[free_index]], sign[free_index], offset[free_index])

    def _mass_matrix(self, dof_map: DofMap) -> Tensor:
        rows, cols, vals = [], [], []
        if self._particle_first_dof:
            first = torch.cat(self._particle_first_dof)
            mass = torch.cat(self._particle_mass)
            dofs = (first.unsqueeze(-1) + torch.arange(self.dim)).reshape(-1)
            rows.append(dofs)
            cols.append(dofs)
            vals.append(mass.repeat_interleave(self.dim))
        for first, block in zip(self._body_first_dof, self._body_mass_block, strict=True):
            base = first + 4 * torch.arange(3).reshape(3, 1, 1)
            r = (base + torch.arange(4).reshape(1, 4, 1)).expand(3, 4, 4)
            c = (base + torch.arange(4).reshape(1, 1, 4)).expand(3, 4, 4)
            rows.append(r.reshape(-1))
            cols.append(c.reshape(-1))
            vals.append(block.expand(3, 4, 4).reshape(-1))
        full_to_free = dof_map.full_to_free()
        r, c, v = full_to_free[torch.cat(rows)], full_to_free[torch.cat(cols)], torch.cat(vals)
        keep = (r >= 0) & (c >= 0)
        n = dof_map.free_dof_count
        M = torch.sparse_coo_tensor(torch.stack([r[keep], c[keep]]), v[keep], (n, n), check_invariants=True).coalesce()
        diag = torch.zeros(n, dtype=torch.float64).index_add_(
            0, r[keep][r[keep] == c[keep]], v[keep][r[keep] == c[keep]]
        )
        if bool((diag <= 0).any()):
            raise ValueError(f"{int((diag <= 0).sum())} free DOF(s) have no mass (massless particles must be pinned)")
        return M


def check_scene_type(scene: object) -> None:
    """Refuse what is not a :class:`Scene` (e.g. a scene's name) with a TypeError that says how to build one."""
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a redsim Scene (redsim.scenes.build(name)), got {scene!r}")


def _check_element_dofs(effect: Effect, count: int) -> None:
    """Refuse an effect whose ``element_dofs`` are not [T, k] int64 indices into a full configuration of ``count``."""
    dofs = getattr(effect, "element_dofs", None)
    if not isinstance(dofs, Tensor) or dofs.ndim != 2 or dofs.dtype != torch.int64:
        shown = (tuple(dofs.shape), dofs.dtype) if isinstance(dofs, Tensor) else type(dofs).__name__
        raise ValueError(f"effect {effect.name!r}: element_dofs must be an int64 tensor [T, k], got {shown}")
    if dofs.numel() and (int(dofs.min()) < 0 or int(dofs.max()) >= count):
        raise ValueError(
            f"effect {effect.name!r}: element_dofs hold indices {int(dofs.min())}..{int(dofs.max())}, outside the "
            f"scene's {count} full DOFs"
        )


def _hash(doc: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _bytes(t: Tensor) -> bytes:
    t = t.detach().to("cpu")
    return (t.to(torch.float32) if t.is_floating_point() else t).contiguous().numpy().tobytes()


def _digest_fields(h: Any, obj: Any, depth: int, containers: bool = True) -> None:
    """Feed ``h`` an object's tensors, numbers and strings, and those of the objects it holds (``depth`` levels);
    with ``containers``, also those inside its lists, tuples, dicts and arrays."""
    for key, value in sorted(vars(obj).items()):
        _digest_value(h, key, value, depth, containers)


def _digest_value(h: Any, key: str, value: Any, depth: int, containers: bool) -> None:
    """Feed ``h`` one field (:func:`_digest_fields`)."""
    if isinstance(value, Tensor):
        h.update(key.encode() + _bytes(value))
    elif isinstance(value, bool | int | float | str) or value is None:
        h.update(f"{key}={value!r}".encode())
    elif containers and isinstance(value, np.ndarray):
        h.update(key.encode() + _bytes(torch.as_tensor(value)))
    elif containers and isinstance(value, list | tuple):
        h.update(f"{key}:{type(value).__name__}{len(value)}".encode())
        for i, item in enumerate(value):
            _digest_value(h, f"{key}[{i}]", item, depth, containers)
    elif containers and isinstance(value, dict):
        h.update(f"{key}:dict{len(value)}".encode())
        for name, item in sorted(value.items(), key=lambda pair: str(pair[0])):
            _digest_value(h, f"{key}[{name!r}]", item, depth, containers)
    elif depth > 0 and hasattr(value, "__dict__") and not callable(value):
        h.update(f"{key}:{type(value).__name__}".encode())
        _digest_fields(h, value, depth - 1, containers)
