"""Implicit Euler in the two-state form of the paper, and static equilibria.

One step solves

    q_{t+1} = argmin_q  1/(2 h^2) |q - qbar|_M^2 + E(q; loads, cond),   qbar = 2 q_t - q_{t-1},

which is backward Euler on M q'' = -dE/dq with the velocity (q_t - q_{t-1}) / h folded into
the state. The objective (:class:`PotentialObjective`) is written once over the coordinates
u of a *space*: q = space.configuration(u). :class:`FullSpace` is the identity (u = q, the
float64 reference); :class:`LatentSpace` solves over the latent z of a subspace map
q = f(z) (paper §3.4), providing only the map, its Newton Hessian, the pull-back of q-space
matrices (J^T A J) and how q-space force scales read in z, so both use the same objective,
minimizers and integrator. In a latent space the state holds z and the inertial target stays in q:
qbar = 2 f(z_t) - f(z_{t-1}).

Static equilibria minimize E(q; loads, cond) - f . q with the same objective, without the
inertia term (:func:`static_equilibrium` over q, :func:`latent_equilibrium` over z).
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from redsim.hessian import energy_hessian
from redsim.scene import LoadsLike, Scene
from redsim.solvers import ConvergenceError, SolveInfo, get_minimizer

logger = logging.getLogger(__name__)

STATIC_MAX_STEP = 0.05
"""Newton trust radius of static full-space solves, as a fraction of the scene's extent."""

NOISE_FACTOR = 100.0 * float(np.finfo(np.float64).eps)
"""Relative round-off of a gradient: gradient_noise = NOISE_FACTOR * |diag(metric)| * L."""
ROUNDOFF_SAFETY = 10.0
"""Margin on the measured gradient change caused by a map's round-off (see :class:`PotentialObjective`)."""
HESSIAN_FLOOR = 1e-8
"""Smallest eigenvalue of a latent Newton Hessian, relative to its largest (see :meth:`LatentSpace.hessian`)."""

LoadSchedule = Callable[[int, "FullState"], LoadsLike]
"""Loads as a function of (step index, state before the step)."""


class Space(Protocol):
    """Coordinates u [m] the integrator solves for, mapped to free configurations q [n].

    The objective's scales are measured in q and read in u through :meth:`gradient_scale`
    (forces) and :meth:`metric_norm` (float64 round-off), plus :attr:`roundoff`.
    """

    @property
    def scene(self) -> Scene:
        """The (float64) scene whose energy is minimized."""
        ...

    @property
    def roundoff(self) -> float:
        """Relative round-off of the configurations q beyond float64's (0; a float32 map's unit round-off)."""
        ...

    @property
    def size(self) -> int:
        """m, the number of coordinates."""
        ...

    @property
    def origin(self) -> Tensor:
        """Default coordinates [m] (float64): where states and static solves start by default."""
        ...

    def configuration(self, u: Tensor) -> Tensor:
        """Free configurations q [B, n] (float64) from coordinates u [B, m] (differentiable)."""
        ...

    def pullback(self, u: Tensor, matrix: Any) -> Any:
        """A q-space matrix A [n, n] seen in coordinates u [m] (J^T A J), shape [m, m]."""
        ...

    def hessian(self, u: Tensor, value: Callable[[Tensor], Tensor], q_hessian: Callable[[Tensor], Any]) -> Any:
        """Positive semi-definite Newton Hessian [m, m] of Phi(u) = value(configuration(u)) at u [m].

        Args:
            u: The coordinates [m].
            value: Phi [B] of configurations q [B, n] (differentiable).
            q_hessian: The projected q-space Hessian [n, n] of Phi at q [n], for spaces that pull it back.
        """
        ...

    def gradient_scale(self, u: Tensor) -> float:
        """|J(u)|_2 = |dq/du|_2 at u [m]: the largest factor by which a q-space force grows in u (1 for u = q)."""
        ...

    def metric_norm(self, u: Tensor, matrix: Any) -> float:
        """Size of a q-space metric A [n, n] acting on round-off of q, seen in u: gradient noise / (NOISE_FACTOR L)."""
        ...


class FullSpace:
    """The identity space: u = q over all free DOFs (the full-space reference).

    Args:
        scene: The scene; it is cast to float64 if it is not already.
    """

    def __init__(self, scene: Scene) -> None:
        self._scene = _float64(scene)

    @property
    def roundoff(self) -> float:
        return 0.0

    @property
    def scene(self) -> Scene:
        return self._scene

    @property
    def size(self) -> int:
        """m = n, the number of free DOFs."""
        return self._scene.free_dof_count

    @property
    def origin(self) -> Tensor:
        """The scene's seed q_seed [n]."""
        return self._scene.q_seed

    def configuration(self, u: Tensor) -> Tensor:
        return u

    def pullback(self, u: Tensor, matrix: Any) -> Any:
        return matrix

    def hessian(self, u: Tensor, value: Callable[[Tensor], Tensor], q_hessian: Callable[[Tensor], Any]) -> Any:
        """The projected q-space Hessian q_hessian(u), sparse [n, n]."""
        return q_hessian(u)

    def gradient_scale(self, u: Tensor) -> float:
        return 1.0

    def metric_norm(self, u: Tensor, matrix: Any) -> float:
        """|diag A|_2."""
        return _vector_norm(matrix.diagonal())


class LatentSpace:
    """The latent coordinates z [d] of a subspace map q = f(z[, c]) (paper §3.4).

    The map runs in its own dtype and device (a float32 :class:`redsim.subspace.SubspaceMap`
    stays float32); z is cast to it on the way in and q back to the scene's float64 on the way
    out, differentiably. The Jacobian J = dq/dz [n, d] comes from two reverse-mode passes over a
    batch of d copies of z (J e_k = d/dp_k (e_k . J^T p_k), the double-backward form of a
    Jacobian-vector product, so any map with double-backward support works) and is cached for
    the last z.

    What the shared objective then means in z:

    - Newton's Hessian is the exact d x d Hessian of the objective in z, the map's own curvature
      (second derivatives of f times the q-space gradient) included, from one double-backward
      pass over d copies of z, made positive definite by taking the absolute value of its
      eigenvalues (floored at HESSIAN_FLOOR times the largest; see :meth:`hessian`). It needs no
      per-element Hessians, and unlike Gauss-Newton (J^T H_q J with the per-element projected
      q-space Hessian H_q, linear convergence where f(z*) leaves a large q-space force
      unbalanced) it converges quadratically near a minimum: on the mini_chain, chain and
      bistable_bar presets it took up to 7x fewer iterations per step (never more), each cheaper.
      "lbfgs" (the paper's choice) sees the exact gradient J^T g_q only.
    - Convergence: the q-space force scale F of :class:`PotentialObjective` is multiplied by
      |J(z_ref)|_2, the most a q-space force can grow when read in z (|J^T g| <= |J|_2 |g|), so
      ``tol`` keeps its meaning: a latent residual of tol times the forces acting, as seen
      through the map. Scaling z by a constant leaves the rule unchanged.
    - Round-off: a float32 map rounds q, which moves the gradient; :class:`PotentialObjective`
      measures how much (its ``gradient_noise``), so solves over a float32 map stop at float32
      resolution instead of failing to converge.

    The map must not change (weights, dtype) while the space is in use: the Jacobian is cached.

    Args:
        scene: The scene; it is cast to float64 if it is not already.
        subspace: A callable z [..., d] -> q [..., n] (an ``nn.Module`` such as
            :class:`redsim.subspace.SubspaceMap`) with a ``latent_dim`` attribute; a conditional
            map (``config.condition_dim > 0``) is called as ``subspace(z, c)``.
        cond: Condition c [k] of a conditional map (default: the scene's default condition).
            It only feeds the map: give solves over this space the same c as their energy
            condition (:func:`latent_equilibrium` does so by default).

    Raises:
        ValueError: a map without ``latent_dim``, whose output does not have n entries, a
            condition for an unconditional map, or a conditional map without one.
    """

    def __init__(self, scene: Scene, subspace: Callable[..., Tensor], *, cond: Tensor | None = None) -> None:
        self._scene = _float64(scene)
        latent_dim = getattr(subspace, "latent_dim", None)
        if not isinstance(latent_dim, int) or latent_dim < 1:
            raise ValueError(f"the subspace must have an integer latent_dim >= 1, got {latent_dim!r}")
        self.subspace = subspace
        self.latent_dim = latent_dim
        condition_dim = map_condition_dim(subspace)
        self.condition: Tensor | None = None
        if condition_dim:
            packed = self._scene.pack_condition(cond, 1, self._scene.q_seed)
            if packed is None:
                raise ValueError(
                    f"the subspace is conditional (size {condition_dim}) and scene "
                    f"{self._scene.name!r} has no condition space; give cond"
                )
            self.condition = packed[0].detach().clone()
            if self.condition.shape != (condition_dim,):
                raise ValueError(
                    f"the subspace needs a condition of size {condition_dim}, got {tuple(self.condition.shape)}"
                )
        elif cond is not None:
            raise ValueError("this subspace takes no condition")
        self._origin = torch.zeros(latent_dim, dtype=torch.float64, device=self._scene.device)
        self._jacobian_at: tuple[Tensor, np.ndarray] | None = None
        with torch.no_grad():
            q0 = self.configuration(self._origin.unsqueeze(0))
        if q0.shape != (1, self._scene.free_dof_count):
            raise ValueError(
                f"the subspace maps z [1, {latent_dim}] to {tuple(q0.shape)}; "
                f"scene {self._scene.name!r} needs [1, {self._scene.free_dof_count}]"
            )

    @property
    def scene(self) -> Scene:
        return self._scene

    @property
    def size(self) -> int:
        """m = d, the latent dimension."""
        return self.latent_dim

    @property
    def origin(self) -> Tensor:
        """z = 0 [d]."""
        return self._origin

    @property
    def map_dtype(self) -> torch.dtype:
        """The dtype the map runs in: that of its first floating parameter or buffer (float64 if none)."""
        like = _map_tensor(self.subspace)
        return torch.float64 if like is None else like.dtype

    @property
    def roundoff(self) -> float:
        """The unit round-off of the map's dtype (1.2e-7 for float32); 0 for a float64 map."""
        dtype = self.map_dtype
        return 0.0 if dtype == torch.float64 else float(torch.finfo(dtype).eps)

    def configuration(self, u: Tensor) -> Tensor:
        like = _map_tensor(self.subspace)
        z, cond = (u, self.condition) if like is None else (u.to(like), _to(self.condition, like))
        q = self.subspace(z) if cond is None else self.subspace(z, cond)
        return q.to(device=self._scene.device, dtype=torch.float64)

    def jacobian(self, u: Tensor) -> np.ndarray:
        """J = dq/dz [n, d] at z = u [d] (float64 numpy; the last one is cached)."""
        u = u.detach()
        if self._jacobian_at is not None and torch.equal(self._jacobian_at[0], u):
            return self._jacobian_at[1]
        z = u.expand(self.latent_dim, -1).clone().requires_grad_(True)  # one copy of u per column
        with torch.enable_grad():
            q = self.configuration(z)  # [d, n]
            probe = torch.zeros_like(q, requires_grad=True)
            pulled = None  # stays None for a map that ignores z
            if q.requires_grad:
                (pulled,) = torch.autograd.grad(q, z, probe, create_graph=True, allow_unused=True)  # row k: J^T p_k
            columns = None
            if pulled is not None and pulled.requires_grad:
                (columns,) = torch.autograd.grad(pulled.diagonal().sum(), probe, allow_unused=True)  # row k: J e_k
        jac = torch.zeros_like(q) if columns is None else columns
        matrix = jac.detach().T.cpu().numpy().astype(np.float64)
        self._jacobian_at = (u.clone(), matrix)
        return matrix

    def pullback(self, u: Tensor, matrix: Any) -> np.ndarray:
        """J^T A J [d, d] (dense, symmetrized) for a q-space matrix A [n, n] (dense or scipy sparse)."""
        jac = self.jacobian(u)
        out = jac.T @ np.asarray(matrix @ jac)
        return 0.5 * (out + out.T)

    def hessian(self, u: Tensor, value: Callable[[Tensor], Tensor], q_hessian: Callable[[Tensor], Any]) -> np.ndarray:
        """Newton Hessian [d, d] of Phi(z) = value(f(z)) at z = u [d] (``q_hessian`` is not used).

        The exact Hessian V diag(w) V^T, symmetrized, with each eigenvalue w_k replaced by
        max(|w_k|, HESSIAN_FLOOR max_k |w_k|): positive definite, so a Newton step descends, and
        the plain Newton step where Phi is strictly convex. Along negative curvature (a buckling
        mode, a bend of the map) the step is scaled by the size of that curvature, where a clamp
        at 0 would make it unbounded. An all-zero Hessian (Phi affine in z) stays zero: the
        minimizer then shifts it by its metric.
        """
        z = u.detach().expand(self.latent_dim, -1).clone().requires_grad_(True)  # one copy of u per row
        grad = rows = None
        with torch.enable_grad():
            phi = value(self.configuration(z))  # [d], all equal
            if phi.requires_grad:
                (grad,) = torch.autograd.grad(phi.sum(), z, create_graph=True, allow_unused=True)  # row k: dPhi/dz
            if grad is not None and grad.requires_grad:
                (rows,) = torch.autograd.grad(grad.diagonal().sum(), z, allow_unused=True)  # row k: d^2Phi/dz_k dz
        if rows is None:
            return np.zeros((self.latent_dim, self.latent_dim))
        exact = rows.detach().cpu().numpy().astype(np.float64)
        w, v = np.linalg.eigh(0.5 * (exact + exact.T))
        w = np.maximum(np.abs(w), HESSIAN_FLOOR * float(np.abs(w).max()))
        return (v * w) @ v.T

    def gradient_scale(self, u: Tensor) -> float:
        return float(np.linalg.norm(self.jacobian(u), 2))

    def metric_norm(self, u: Tensor, matrix: Any) -> float:
        """|A J|_F."""
        return float(np.linalg.norm(np.asarray(matrix @ self.jacobian(u))))


def map_condition_dim(subspace: Any) -> int:
    """Size of the condition c a map takes: ``subspace.config.condition_dim`` if it has one, else 0."""
    return int(getattr(getattr(subspace, "config", None), "condition_dim", 0))


def _float64(scene: Scene) -> Scene:
    return scene if scene.dtype == torch.float64 else scene.to(dtype=torch.float64)


def _map_tensor(subspace: Any) -> Tensor | None:
    """A map's first floating parameter or buffer (its dtype and device), or None (inputs are left as they are)."""
    if isinstance(subspace, torch.nn.Module):
        for tensor in itertools.chain(subspace.parameters(), subspace.buffers()):
            if tensor.is_floating_point():
                return tensor
    return None


def _to(value: Tensor | None, like: Tensor) -> Tensor | None:
    return None if value is None else value.to(like)


@dataclass(frozen=True)
class Inertia:
    """The inertia term 1/(2 h^2) |q - target|_M^2 of an implicit-Euler step.

    Attributes:
        target: qbar = 2 q_t - q_{t-1} [m], shape [n].
        dt: Time step h [s].
    """

    target: Tensor
    dt: float


@dataclass(frozen=True)
class FullState:
    """A state of the two-state integrator.

    Attributes:
        q: Coordinates of the space at time t (the free configuration q for :class:`FullSpace`), shape [n].
        q_prev: The same at time t - h, shape [n].
        time: t [s].
    """

    q: Tensor
    q_prev: Tensor
    time: float

    def velocity(self, dt: float) -> Tensor:
        """Backward-difference velocity (q - q_prev) / dt [m/s], shape [n]."""
        return (self.q - self.q_prev) / dt


def length_scale(scene: Scene) -> float:
    """Size L [m] of the scene: the larger of the seed's extent and magnitude, 1 for an all-zero seed."""
    x = scene.full_positions(scene.q_seed.detach().unsqueeze(0))[0]
    scale = max(float(x.max() - x.min()), float(x.abs().max()))
    return scale if scale > 0.0 else 1.0


def _vector_norm(matrix_diagonal: np.ndarray) -> float:
    return float(np.linalg.norm(matrix_diagonal))


@dataclass(frozen=True)
class SceneConstants:
    """What :class:`PotentialObjective` reads from a scene that no state changes: built once per integrator.

    Attributes:
        mass: M [kg], scipy CSR [n, n].
        mass_diagonal_norm: |diag M|_2 [kg].
        length: L [m], :func:`length_scale`.
    """

    mass: Any
    mass_diagonal_norm: float
    length: float

    @classmethod
    def of(cls, scene: Scene) -> SceneConstants:
        """The constants of ``scene``."""
        mass = scene.mass_matrix_scipy().tocsr()
        return cls(mass, _vector_norm(mass.diagonal()), length_scale(scene))


class PotentialObjective:
    """Phi(u) = [1/(2 h^2) |q - qbar|_M^2] + E(q; loads, cond) - f . q with q = space.configuration(u).

    Attributes:
        force_scale: Characteristic force of the problem (see :mod:`redsim.solvers`), in the unit
            of dPhi/du: F |J(u_ref)|_2 (:meth:`Space.gradient_scale`, 1 in the full space), where
            F [N] is the sum over effects of |dE_e/dq| at q_ref, plus |f|, plus for a time step
            |M (qbar - q_ref)| / h^2 and |diag M| L / h^2, the force that moves every DOF by the
            scene size L in one step. With it, tol bounds the per-step position error by about
            tol * L (the Hessian is >= M/h^2), and static solves are converged relative to the
            forces acting (a relative force-balance error of tol, as seen through the map).
        gradient_noise: The gradient round-off: NOISE_FACTOR * :meth:`Space.metric_norm` (|diag
            metric_q|_2 in the full space) * L for float64, plus, for a space with
            :attr:`Space.roundoff` r > 0 (a float32 map), ROUNDOFF_SAFETY times the change of
            dPhi/du when q_ref is perturbed by r max(|q_i|, rms q) with seeded random signs: the
            sensitivity to the map's rounding, stiffness and inertia included.
        value_noise: (NOISE_FACTOR + r) * F * L: the round-off of Phi, a sum of terms of size up to F L [J].
        max_step: Newton trust radius of a static full-space solve [m per entry]: the smaller of
            STATIC_MAX_STEP * scene.extent() and half of scene.feature_size() (the thinnest contact
            shape). A start that feels little restoring force (a chain held only by contact, hanging
            out of contact) would otherwise take one long Levenberg step through its constraints,
            where penalty potentials are bounded. Time steps (the inertia term bounds the move)
            and latent spaces have none.

    Args:
        space: The coordinates to minimize over.
        loads: Packed loads [N], shape [1, H, D], or None.
        cond: Packed condition, shape [1, m], or None.
        inertia: The inertia term of a time step, or None for a static problem.
        force: Constant generalized force f, shape [n], or None.
        reference: Coordinates u_ref [m] where the scales are measured, at q_ref =
            space.configuration(u_ref) (u_t for a step, the initial guess for a static solve).
        constants: ``SceneConstants.of(space.scene)``, passed by callers that build many objectives
            over one scene (default: computed here).
    """

    def __init__(
        self,
        space: Space,
        *,
        loads: Tensor | None,
        cond: Tensor | None,
        inertia: Inertia | None,
        force: Tensor | None,
        reference: Tensor,
        constants: SceneConstants | None = None,
    ) -> None:
        self.space = space
        self.scene = space.scene
        self.loads = loads
        self.cond = cond
        self.inertia = inertia
        self.force = force
        constants = SceneConstants.of(self.scene) if constants is None else constants
        mass, length = constants.mass, constants.length
        with torch.no_grad():
            q_ref = space.configuration(reference.detach().unsqueeze(0))[0]
        if inertia is not None:
            self._metric_q = mass * (1.0 / inertia.dt**2)
        else:
            stiffness = energy_hessian(self.scene, q_ref, loads, cond, project=True)
            ratio = _vector_norm(stiffness.diagonal()) / constants.mass_diagonal_norm
            self._metric_q = mass * (ratio if ratio > 0.0 else 1.0)
        q_force_scale = self._force_scale(q_ref, constants)
        self.force_scale = q_force_scale * space.gradient_scale(reference)
        self.gradient_noise = NOISE_FACTOR * space.metric_norm(reference, self._metric_q) * length
        if space.roundoff > 0.0:
            self.gradient_noise += self._roundoff_noise(reference, q_ref)
        self.value_noise = (NOISE_FACTOR + space.roundoff) * q_force_scale * length
        self.max_step = math.inf
        if inertia is None and isinstance(space, FullSpace):
            self.max_step = min(STATIC_MAX_STEP * self.scene.extent(), 0.5 * self.scene.feature_size())

    def _force_scale(self, reference: Tensor, constants: SceneConstants) -> float:
        q = reference.detach().reshape(1, -1).clone().requires_grad_(True)
        total = 0.0
        with torch.enable_grad():
            terms = self.scene.energy_terms(q, self.loads, self.cond)
            for term in terms.values():
                if term.requires_grad:
                    (grad,) = torch.autograd.grad(term.sum(), q, retain_graph=True, allow_unused=True)
                    total += 0.0 if grad is None else float(torch.linalg.vector_norm(grad))
        if self.force is not None:
            total += float(torch.linalg.vector_norm(self.force))
        if self.inertia is not None:
            drift = (self.inertia.target - reference).detach().cpu().numpy()
            total += float(np.linalg.norm(constants.mass @ drift)) / self.inertia.dt**2
            total += constants.mass_diagonal_norm * constants.length / self.inertia.dt**2
        return total

    def _roundoff_noise(self, reference: Tensor, q_ref: Tensor) -> float:
        """ROUNDOFF_SAFETY |J^T (g_q(q_ref + delta) - g_q(q_ref))| for a round-off-sized delta (see gradient_noise)."""
        generator = torch.Generator().manual_seed(0)
        signs = torch.randint(0, 2, tuple(q_ref.shape), generator=generator).to(q_ref) * 2.0 - 1.0
        size = torch.maximum(q_ref.abs(), q_ref.square().mean().sqrt())
        q = torch.stack([q_ref, q_ref + self.space.roundoff * size * signs]).detach().requires_grad_(True)
        with torch.enable_grad():
            (grads,) = torch.autograd.grad(self._value(q).sum(), q)  # both gradients in one pass
            u = reference.detach().clone().requires_grad_(True)
            (change,) = torch.autograd.grad(self.space.configuration(u.unsqueeze(0))[0] @ (grads[1] - grads[0]), u)
        return ROUNDOFF_SAFETY * float(torch.linalg.vector_norm(change))

    def _value(self, q: Tensor) -> Tensor:
        """Phi [J], shape [B], of configurations q [B, n] (the loads and condition held for all B)."""
        batch = q.shape[0]
        loads = None if self.loads is None else self.loads.expand(batch, -1, -1)
        cond = None if self.cond is None else self.cond.expand(batch, -1)
        value = self.scene.energy(q, loads, cond)
        if self.inertia is not None:
            d = q - self.inertia.target
            value = value + (0.5 / self.inertia.dt**2) * (d * self.scene.mass_matvec(d)).sum(-1)
        if self.force is not None:
            value = value - q @ self.force
        return value

    def value_and_grad(self, u: Tensor) -> tuple[float, Tensor]:
        """Phi [J] and dPhi/du, shape [m], at u [m]."""
        u = u.detach().clone().requires_grad_(True)
        with torch.enable_grad():
            value = self._value(self.space.configuration(u.unsqueeze(0)))[0]
            (grad,) = torch.autograd.grad(value, u)
        return float(value.detach()), grad

    def hessian(self, u: Tensor) -> Any:
        """PSD Newton Hessian [m, m] of Phi at u [m] (:meth:`Space.hessian`): in the full space :meth:`q_hessian`."""
        return self.space.hessian(u, self._value, self.q_hessian)

    def q_hessian(self, q: Tensor) -> Any:
        """Projected-Newton Hessian [n, n] (sparse) of Phi over q at q [n]: M/h^2 (a step) + PSD-projected d^2E/dq^2."""
        matrix = energy_hessian(self.scene, q.detach(), self.loads, self.cond, project=True)
        return matrix + self._metric_q if self.inertia is not None else matrix

    def metric(self, u: Tensor) -> Any:
        """M/h^2 for a step; for a static problem M scaled to the Hessian's diagonal at the reference."""
        return self.space.pullback(u, self._metric_q)


def _packed_inputs(scene: Scene, loads: LoadsLike, cond: Tensor | None) -> tuple[Tensor | None, Tensor | None]:
    """Loads [1, H, D] and condition [1, m] for one configuration; non-finite values raise ValueError."""
    loads_t = scene.pack_loads(loads, 1, scene.q_seed)
    if loads_t is not None and not bool(torch.isfinite(loads_t).all()):
        raise ValueError(f"loads must be finite, got {loads_t.tolist()}")
    cond_t = scene.pack_condition(cond, 1, scene.q_seed)
    if cond_t is not None and not bool(torch.isfinite(cond_t).all()):
        raise ValueError(f"condition must be finite, got {cond_t.tolist()}")
    return loads_t, cond_t


def _vector(value: Tensor | Any, size: int, what: str, like: Tensor) -> Tensor:
    out = torch.as_tensor(value, dtype=like.dtype, device=like.device)
    if out.shape != (size,):
        raise ValueError(f"{what} must have shape [{size}], got {tuple(out.shape)}")
    if not bool(torch.isfinite(out).all()):
        raise ValueError(f"{what} must be finite")
    return out.detach().clone()


class ImplicitEuler:
    """Two-state implicit Euler over a space (module doc), each step solved by a named minimizer.

    Args:
        space: The coordinates solved for (:class:`FullSpace` for the reference, :class:`LatentSpace`
            for a subspace; the state then holds z).
        dt: Time step h [s], finite and > 0.
        minimizer: A key of :data:`redsim.solvers.MINIMIZERS` ("newton" or "lbfgs").
        tol: Relative gradient tolerance (see :class:`PotentialObjective` for what it bounds).
        max_iter: Most iterations of the minimizer per step.
        strict: Raise :class:`redsim.solvers.ConvergenceError` (a RuntimeError carrying the
            SolveInfo) when a step does not converge; otherwise the step returns the last
            iterate with ``converged=False`` and logs a warning.

    Raises:
        ValueError: on a bad dt, tol, max_iter or an unknown minimizer.
    """

    def __init__(
        self,
        space: Space,
        dt: float,
        *,
        minimizer: str = "newton",
        tol: float = 1e-8,
        max_iter: int = 50,
        strict: bool = False,
    ) -> None:
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"dt must be a finite number > 0 [s], got {dt!r}")
        if not (math.isfinite(tol) and tol > 0.0):
            raise ValueError(f"tol must be finite and > 0, got {tol!r}")
        if int(max_iter) != max_iter or max_iter < 1:
            raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")
        self.space = space
        self.dt = float(dt)
        self.minimizer = minimizer
        self._minimize = get_minimizer(minimizer)
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        self.strict = bool(strict)
        self._constants = SceneConstants.of(space.scene)

    @property
    def scene(self) -> Scene:
        return self.space.scene

    def initial_state(self, q: Tensor | None = None, velocity: Tensor | None = None) -> FullState:
        """A state at time 0 with coordinates q (default: the space's origin) and velocity (default 0).

        The coordinates are the space's: q [n] (default the seed) for :class:`FullSpace`, z [d]
        (default 0) for :class:`LatentSpace`, with velocity in their unit per second. The
        previous coordinates are q - dt * velocity. Inputs are copied, never aliased.
        """
        origin = self.space.origin
        size = self.space.size
        q_t = origin.detach().clone() if q is None else _vector(q, size, "q", origin)
        v = torch.zeros_like(q_t) if velocity is None else _vector(velocity, size, "velocity", origin)
        return FullState(q_t, q_t - self.dt * v, 0.0)

    def step(
        self, state: FullState, loads: LoadsLike = None, cond: Tensor | None = None
    ) -> tuple[FullState, SolveInfo]:
        """Advance one step of length dt.

        Args:
            state: The current state.
            loads: Loads on the scene's handles [N] (see :meth:`Scene.pack_loads`), held during the step.
            cond: Condition vector [m] for conditional scenes.

        Returns:
            The new state (time + dt) and the minimizer's :class:`SolveInfo`.

        Raises:
            ValueError: on non-finite loads, condition or state.
            ConvergenceError: with ``strict=True``, when the step did not converge.
        """
        origin = self.space.origin
        u_t = _vector(state.q, self.space.size, "state.q", origin)
        u_prev = _vector(state.q_prev, self.space.size, "state.q_prev", origin)
        loads_t, cond_t = _packed_inputs(self.scene, loads, cond)
        with torch.no_grad():
            configurations = self.space.configuration(torch.stack([u_t, u_prev]))
        q_t = configurations[0]
        target = 2.0 * q_t - configurations[1]
        objective = PotentialObjective(
            self.space,
            loads=loads_t,
            cond=cond_t,
            inertia=Inertia(target, self.dt),
            force=None,
            reference=u_t,
            constants=self._constants,
        )
        u_next, info = self._minimize(objective, 2.0 * u_t - u_prev, tol=self.tol, max_iter=self.max_iter)
        if not info.converged:
            if self.strict:
                raise ConvergenceError(info)
            logger.warning("implicit Euler step at t = %.6g s did not converge: %s", state.time, info.message)
        return FullState(u_next.detach().clone(), u_t, state.time + self.dt), info

    def rollout(
        self,
        state: FullState,
        steps: int,
        loads: LoadsLike | LoadSchedule = None,
        cond: Tensor | None = None,
    ) -> tuple[Tensor, list[SolveInfo]]:
        """Run ``steps`` steps from ``state``.

        Args:
            state: The initial state.
            steps: Number of steps (>= 0).
            loads: Loads held for every step, or a function (step index, state) -> loads.
            cond: Condition vector, held for every step.

        Returns:
            The coordinates at every time, shape [steps + 1, n] (the initial ones first), and
            one SolveInfo per step.
        """
        if int(steps) != steps or steps < 0:
            raise ValueError(f"steps must be an integer >= 0, got {steps!r}")
        schedule: LoadSchedule = loads if callable(loads) else (lambda _i, _s: loads)
        trajectory = [state.q.detach().clone()]
        infos = []
        for index in range(int(steps)):
            state, info = self.step(state, schedule(index, state), cond)
            trajectory.append(state.q)
            infos.append(info)
        return torch.stack(trajectory), infos


def static_equilibrium(
    scene: Scene,
    loads: LoadsLike = None,
    cond: Tensor | None = None,
    *,
    q0: Tensor | None = None,
    force: Tensor | None = None,
    minimizer: str = "newton",
    tol: float = 1e-8,
    max_iter: int = 200,
) -> tuple[Tensor, SolveInfo]:
    """A local minimizer of E(q; loads, cond) - force . q, starting from q0.

    Singular Hessians (rigid null modes, free bodies) are handled by the Levenberg shift of
    :func:`redsim.solvers.newton`. Without a minimizer (e.g. an unbalanced load on a free
    body), the result reports ``converged=False``.

    Args:
        scene: The scene (solved in float64).
        loads: Loads on the handles [N].
        cond: Condition vector [m].
        q0: Initial guess, shape [n] (default: the seed).
        force: Constant generalized force [N], shape [n], or None.
        minimizer: A key of :data:`redsim.solvers.MINIMIZERS`.
        tol: Relative gradient tolerance: converged when |g| <= tol * max(|g(q0)|, F), with F the sum of
            the effects' force norms at q0 plus |force| (or when |g| is at float64 round-off level).
        max_iter: Most iterations.

    Returns:
        The configuration [n] (float64) and the :class:`SolveInfo`.
    """
    return _static_solve(FullSpace(scene), loads, cond, q0, "q0", force, minimizer, tol, max_iter)


def latent_equilibrium(
    space: LatentSpace,
    loads: LoadsLike = None,
    cond: Tensor | None = None,
    *,
    z0: Tensor | None = None,
    force: Tensor | None = None,
    minimizer: str = "newton",
    tol: float = 1e-8,
    max_iter: int = 200,
) -> tuple[Tensor, SolveInfo]:
    """A local minimizer over z of E(f(z); loads, cond) - force . f(z), starting from z0.

    The same objective and minimizers as :func:`static_equilibrium`, over the latent space (see
    :class:`LatentSpace` for what Newton and the convergence rule mean there).

    Args:
        space: The latent space (the map and its condition).
        loads: Loads on the handles [N].
        cond: Condition vector [m] of the energy (default: the space's map condition, else the
            scene's default).
        z0: Initial guess, shape [d] (default: z = 0).
        force: Constant generalized force [N], shape [n], or None.
        minimizer: A key of :data:`redsim.solvers.MINIMIZERS`.
        tol: Relative gradient tolerance (as in :func:`static_equilibrium`, scaled by |J(z0)|_2).
        max_iter: Most iterations.

    Returns:
        The latent coordinates z [d] (float64; q = space.configuration(z[None])[0]) and the
        :class:`SolveInfo`.
    """
    cond = space.condition if cond is None else cond
    return _static_solve(space, loads, cond, z0, "z0", force, minimizer, tol, max_iter)


def _static_solve(
    space: Space,
    loads: LoadsLike,
    cond: Tensor | None,
    u0: Tensor | None,
    name: str,
    force: Tensor | None,
    minimizer: str,
    tol: float,
    max_iter: int,
) -> tuple[Tensor, SolveInfo]:
    """Minimize the static potential over ``space`` from u0 (default: the space's origin)."""
    minimize = get_minimizer(minimizer)
    origin = space.origin
    u_start = origin.detach().clone() if u0 is None else _vector(u0, space.size, name, origin)
    seed = space.scene.q_seed
    force_t = None if force is None else _vector(force, int(seed.shape[0]), "force", seed)
    loads_t, cond_t = _packed_inputs(space.scene, loads, cond)
    objective = PotentialObjective(space, loads=loads_t, cond=cond_t, inertia=None, force=force_t, reference=u_start)
    return minimize(objective, u_start, tol=tol, max_iter=max_iter)


__all__ = [
    "FullSpace",
    "FullState",
    "ImplicitEuler",
    "Inertia",
    "LatentSpace",
    "PotentialObjective",
    "SceneConstants",
    "Space",
    "latent_equilibrium",
    "length_scale",
    "map_condition_dim",
    "static_equilibrium",
]
