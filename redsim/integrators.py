"""Implicit Euler in the two-state form of the paper, and static equilibria.

One step solves

    q_{t+1} = argmin_q  1/(2 h^2) |q - qbar|_M^2 + E(q; loads, cond),   qbar = 2 q_t - q_{t-1},

which is backward Euler on M q'' = -dE/dq with the velocity (q_t - q_{t-1}) / h folded into
the state. The objective (:class:`PotentialObjective`) is written once over the coordinates
u of a *space*: q = space.configuration(u). :class:`FullSpace` is the identity (u = q, the
float64 reference); a reduced space only has to provide the map and the pull-back of
q-space matrices (J^T A J) to reuse the same objective, minimizers and integrator.

Static equilibria minimize E(q; loads, cond) - f . q with the same objective, without the
inertia term.
"""

from __future__ import annotations

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

NOISE_FACTOR = 100.0 * float(np.finfo(np.float64).eps)
"""Relative round-off of a gradient: gradient_noise = NOISE_FACTOR * |diag(metric)| * L."""

LoadSchedule = Callable[[int, "FullState"], LoadsLike]
"""Loads as a function of (step index, state before the step)."""


class Space(Protocol):
    """Coordinates u [m] the integrator solves for, mapped to free configurations q [n]."""

    @property
    def scene(self) -> Scene:
        """The (float64) scene whose energy is minimized."""
        ...

    def configuration(self, u: Tensor) -> Tensor:
        """Free configurations q [B, n] from coordinates u [B, m] (differentiable)."""
        ...

    def pullback(self, u: Tensor, matrix: Any) -> Any:
        """A q-space matrix A [n, n] seen in coordinates u [m] (J^T A J), shape [m, m]."""
        ...


class FullSpace:
    """The identity space: u = q over all free DOFs (the full-space reference).

    Args:
        scene: The scene; it is cast to float64 if it is not already.
    """

    def __init__(self, scene: Scene) -> None:
        self._scene = scene if scene.dtype == torch.float64 else scene.to(dtype=torch.float64)

    @property
    def scene(self) -> Scene:
        return self._scene

    @property
    def size(self) -> int:
        """m = n, the number of free DOFs."""
        return self._scene.free_dof_count

    def configuration(self, u: Tensor) -> Tensor:
        return u

    def pullback(self, u: Tensor, matrix: Any) -> Any:
        return matrix


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


def _length_scale(scene: Scene) -> float:
    """Size L [m] of the scene: the larger of the seed's extent and magnitude, 1 for an all-zero seed."""
    x = scene.full_positions(scene.q_seed.detach().unsqueeze(0))[0]
    scale = max(float(x.max() - x.min()), float(x.abs().max()))
    return scale if scale > 0.0 else 1.0


def _vector_norm(matrix_diagonal: np.ndarray) -> float:
    return float(np.linalg.norm(matrix_diagonal))


class PotentialObjective:
    """Phi(u) = [1/(2 h^2) |q - qbar|_M^2] + E(q; loads, cond) - f . q with q = space.configuration(u).

    Attributes:
        force_scale: Characteristic force [N] of the problem (see :mod:`redsim.solvers`):
            sum over effects of |dE_e/dq| at the reference configuration, plus |f|, plus for a
            time step |M (qbar - q_ref)| / h^2 and |diag M| L / h^2, the force that moves every
            DOF by the scene size L in one step. With it, tol bounds the per-step position
            error by about tol * L (the Hessian is >= M/h^2), and static solves are converged
            relative to the forces acting (a relative force-balance error of tol).
        gradient_noise: NOISE_FACTOR * |diag(metric)| L: the gradient round-off of float64.
        value_noise: NOISE_FACTOR * force_scale * L: the round-off of Phi, a sum of terms of
            size up to force_scale * L [J].

    Args:
        space: The coordinates to minimize over.
        loads: Packed loads [N], shape [1, H, D], or None.
        cond: Packed condition, shape [1, m], or None.
        inertia: The inertia term of a time step, or None for a static problem.
        force: Constant generalized force f, shape [n], or None.
        reference: Configuration q_ref [n] where the force scale is measured (q_t for a step,
            the initial guess for a static solve).
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
    ) -> None:
        self.space = space
        self.scene = space.scene
        self.loads = loads
        self.cond = cond
        self.inertia = inertia
        self.force = force
        mass = self.scene.mass_matrix_scipy().tocsr()
        if inertia is not None:
            self._metric_q = mass * (1.0 / inertia.dt**2)
        else:
            stiffness = energy_hessian(self.scene, reference, loads, cond, project=True)
            ratio = _vector_norm(stiffness.diagonal()) / _vector_norm(mass.diagonal())
            self._metric_q = mass * (ratio if ratio > 0.0 else 1.0)
        length = _length_scale(self.scene)
        self.force_scale = self._force_scale(reference, mass, length)
        self.gradient_noise = NOISE_FACTOR * _vector_norm(self._metric_q.diagonal()) * length
        self.value_noise = NOISE_FACTOR * self.force_scale * length

    def _force_scale(self, reference: Tensor, mass: Any, length: float) -> float:
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
            total += float(np.linalg.norm(mass @ drift)) / self.inertia.dt**2
            total += _vector_norm(mass.diagonal()) * length / self.inertia.dt**2
        return total

    def _value(self, q: Tensor) -> Tensor:
        """Phi [J], shape [B], of configurations q [B, n]."""
        value = self.scene.energy(q, self.loads, self.cond)
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
        """Projected-Newton Hessian of Phi at u: M/h^2 (for a step) + PSD-projected d^2E/dq^2, pulled back."""
        with torch.no_grad():
            q = self.space.configuration(u.detach().unsqueeze(0))
        matrix = energy_hessian(self.scene, q, self.loads, self.cond, project=True)
        if self.inertia is not None:
            matrix = matrix + self._metric_q
        return self.space.pullback(u, matrix)

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
        space: The coordinates solved for (:class:`FullSpace` for the reference).
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

    @property
    def scene(self) -> Scene:
        return self.space.scene

    def initial_state(self, q: Tensor | None = None, velocity: Tensor | None = None) -> FullState:
        """A state at time 0 with coordinates q (default: the scene's seed) and velocity [m/s] (default 0).

        The previous coordinates are q - dt * velocity. Inputs are copied, never aliased.
        """
        seed = self.scene.q_seed
        size = int(seed.shape[0])
        q_t = seed.detach().clone() if q is None else _vector(q, size, "q", seed)
        v = torch.zeros_like(q_t) if velocity is None else _vector(velocity, size, "velocity", seed)
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
        seed = self.scene.q_seed
        size = int(seed.shape[0])
        u_t = _vector(state.q, size, "state.q", seed)
        u_prev = _vector(state.q_prev, size, "state.q_prev", seed)
        loads_t, cond_t = _packed_inputs(self.scene, loads, cond)
        with torch.no_grad():
            configurations = self.space.configuration(torch.stack([u_t, u_prev]))
        q_t = configurations[0]
        target = 2.0 * q_t - configurations[1]
        objective = PotentialObjective(
            self.space, loads=loads_t, cond=cond_t, inertia=Inertia(target, self.dt), force=None, reference=q_t
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
    minimize = get_minimizer(minimizer)
    space = FullSpace(scene)
    seed = space.scene.q_seed
    n = int(seed.shape[0])
    q_start = seed.detach().clone() if q0 is None else _vector(q0, n, "q0", seed)
    force_t = None if force is None else _vector(force, n, "force", seed)
    loads_t, cond_t = _packed_inputs(space.scene, loads, cond)
    objective = PotentialObjective(space, loads=loads_t, cond=cond_t, inertia=None, force=force_t, reference=q_start)
    return minimize(objective, q_start, tol=tol, max_iter=max_iter)


__all__ = [
    "FullSpace",
    "FullState",
    "ImplicitEuler",
    "Inertia",
    "PotentialObjective",
    "Space",
    "static_equilibrium",
]
