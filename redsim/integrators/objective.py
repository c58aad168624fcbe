"""The one objective every solve minimizes, over the coordinates of any space.

    Phi(u) = [1/(2 h^2) |q - qbar|_M^2] + E(q; loads, cond) - f . q,   q = space.configuration(u),

with the inertia term for an implicit-Euler step (qbar = 2 q_t - q_{t-1}) and without it for a
static equilibrium. :class:`PotentialObjective` also measures the scales the minimizers'
convergence test reads (force scale, round-off, trust radius).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from redsim.hessian import energy_hessian
from redsim.integrators.spaces import FullSpace, Space
from redsim.scene import LoadsLike, Scene
from redsim.tensors import as_numbers

STATIC_MAX_STEP = 0.05
"""Newton trust radius of static full-space solves, as a fraction of the scene's extent."""

NOISE_FACTOR = 100.0 * float(np.finfo(np.float64).eps)
"""Relative round-off of a gradient: gradient_noise = NOISE_FACTOR * |diag(metric)| * L."""
ROUNDOFF_SAFETY = 10.0
"""Margin on the measured gradient change caused by a map's round-off (see :class:`PotentialObjective`)."""


@dataclass(frozen=True)
class Inertia:
    """The inertia term 1/(2 h^2) |q - target|_M^2 of an implicit-Euler step.

    Attributes:
        target: qbar = 2 q_t - q_{t-1} [m], shape [n].
        dt: Time step h [s].
    """

    target: Tensor
    dt: float


MIN_TIME_STEP = 1e-6
"""The smallest time step [s] the integrators take: below it h^2 nears float32's smallest normal numbers (the
inertia term's 1/h^2 overflows at 1e-20 s, h^2 underflows to 0 at 1e-162 s in float64)."""


def check_time_step(dt: Any) -> float:
    """``dt`` [s] as a float: a real number (not a bool) in [:data:`MIN_TIME_STEP`, inf); a ValueError otherwise."""
    if isinstance(dt, bool) or not isinstance(dt, (int, float, np.integer, np.floating)):
        raise ValueError(f"dt must be a number of seconds, got {dt!r}")
    if not (math.isfinite(dt) and dt >= MIN_TIME_STEP):
        raise ValueError(f"dt must be a finite number of seconds >= {MIN_TIME_STEP:g}, got {dt!r}")
    return float(dt)


def length_scale(scene: Scene) -> float:
    """Size L [m] of the scene: the larger of the seed's extent and magnitude, 1 for an all-zero seed."""
    x = scene.full_positions(scene.q_seed.detach().unsqueeze(0))[0]
    scale = max(float(x.max() - x.min()), float(x.abs().max()))
    return scale if scale > 0.0 else 1.0


def _vector_norm(matrix_diagonal: np.ndarray) -> float:
    return float(np.linalg.norm(matrix_diagonal))


def value_roundoff(value: Callable[[Tensor], Tensor], q: Tensor) -> float:
    """ROUNDOFF_SAFETY max_k |value(q + delta_k) - value(q)| [J] over three perturbations delta_k of 4 ulps of
    max(|q_i|, rms q) with seeded random signs: the round-off of an energy ``value`` ([B, n] -> [B]) at q [n].

    Elastic energies are sums of terms of size mu V that cancel (a stable neo-Hookean solid's, at rest), so their
    round-off lies far above eps |E| there; the change the gradient predicts, g . delta, is itself q's rounding.
    """
    generator = torch.Generator().manual_seed(0)
    q = q.detach()
    size = 4.0 * torch.finfo(q.dtype).eps * torch.maximum(q.abs(), q.square().mean().sqrt())
    signs = torch.randint(0, 2, (3, *q.shape), generator=generator).to(q) * 2.0 - 1.0
    with torch.no_grad():
        values = value(torch.cat([q.unsqueeze(0), q + size * signs]))
    return ROUNDOFF_SAFETY * float((values[1:] - values[0]).abs().max())


@dataclass(frozen=True)
class SceneConstants:
    """What :class:`PotentialObjective` reads from a scene that no state changes: built once per integrator.

    Attributes:
        mass: M [kg], scipy CSR [n, n].
        mass_diagonal_norm: |diag M|_2 [kg].
        length: L [m], :func:`length_scale`.
        energy_noise: Round-off [J] of the scene's energy E (no loads), :func:`value_roundoff` at the seed: what
            a step's energy balance cannot resolve (:mod:`redsim.integrators.energy_gain`).
    """

    mass: Any
    mass_diagonal_norm: float
    length: float
    energy_noise: float = 0.0

    @classmethod
    def of(cls, scene: Scene) -> SceneConstants:
        """The constants of ``scene``."""
        mass = scene.mass_matrix_scipy().tocsr()
        noise = value_roundoff(scene.energy, scene.q_seed)
        return cls(mass, _vector_norm(mass.diagonal()), length_scale(scene), noise)


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
        value_noise: (NOISE_FACTOR + r) * F * L: the round-off of Phi, a sum of terms of size up to F L [J]; for a
            static problem at least ROUNDOFF_SAFETY times the largest change of Phi when q_ref moves by a few
            ulps (:func:`value_roundoff`): elastic energies are sums of terms of size mu V that cancel, so at rest
            (F = the loads alone) F L underestimated their round-off and the line search refused the last Newton steps.
        max_step: Trust radius of either minimizer's steps [m per entry, or in ``move_measure``'s unit where set];
            for a static full-space solve, the smaller of
            STATIC_MAX_STEP * scene.extent() and half of scene.feature_size() (the thinnest contact
            shape). A start that feels little restoring force (a chain held only by contact, hanging
            out of contact) would otherwise take one long Levenberg step through its constraints,
            where penalty potentials are bounded. Time steps (the inertia term bounds the move)
            and latent spaces have none (a full-space time step solved again after it tunneled sets one:
            :class:`redsim.integrators.ImplicitEuler`'s ``retry_tunneled``).
        move_measure: None (a step's move is its largest entry), or a function (u, direction) -> the move
            [unit of ``max_step``] that :meth:`largest_move` returns and the minimizers bound by ``max_step``.
        path: None, or a list that :meth:`visit` extends with each point [m] the minimizer accepts (the states a
            step went through: :class:`redsim.integrators.ImplicitEuler`'s ``retry_tunneled`` tests them).

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
        if inertia is None:
            self.value_noise = max(self.value_noise, value_roundoff(self._value, q_ref))
        self.max_step = math.inf
        self.move_measure: Callable[[Tensor, Tensor], float] | None = None
        self.path: list[Tensor] | None = None
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

    def largest_move(self, u: Tensor, direction: Tensor) -> float:
        """How far the step from u [m] along ``direction`` [m] moves, in the unit of ``max_step``: ``move_measure``'s
        where set (e.g. contact points relative to their shapes [m]), else the direction's largest entry."""
        if self.move_measure is None:
            return float(direction.abs().max())
        return self.move_measure(u, direction)

    def visit(self, u: Tensor) -> None:
        """A point u [m] the minimizer accepted: kept in :attr:`path` where that is a list."""
        if self.path is not None:
            self.path.append(u.detach().clone())

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


def pack_inputs(scene: Scene, loads: LoadsLike, cond: Tensor | None) -> tuple[Tensor | None, Tensor | None]:
    """Loads [1, H, D] and condition [1, m] for one configuration; non-finite values raise ValueError."""
    loads_t = scene.pack_loads(loads, 1, scene.q_seed)
    if loads_t is not None and not bool(torch.isfinite(loads_t).all()):
        raise ValueError(f"loads must be finite, got {loads_t.tolist()}")
    cond_t = scene.pack_condition(cond, 1, scene.q_seed)
    if cond_t is not None and not bool(torch.isfinite(cond_t).all()):
        raise ValueError(f"condition must be finite, got {cond_t.tolist()}")
    return loads_t, cond_t


def checked_vector(value: Tensor | Any, size: int, what: str, like: Tensor) -> Tensor:
    """``value`` as a finite vector [size] in ``like``'s dtype and device (a copy); else ValueError naming ``what``."""
    out = as_numbers(value, what, f"[{size}]", like.dtype, like.device)
    if out.shape != (size,):
        raise ValueError(f"{what} must have shape [{size}], got {tuple(out.shape)}")
    if not bool(torch.isfinite(out).all()):
        raise ValueError(f"{what} must be finite")
    return out.detach().clone()
