"""Implicit Euler in the two-state form of the paper.

One step solves

    q_{t+1} = argmin_q  1/(2 h^2) |q - qbar|_M^2 + E(q; loads, cond),   qbar = 2 q_t - q_{t-1},

which is backward Euler on M q'' = -dE/dq with the velocity (q_t - q_{t-1}) / h folded into
the state, over the coordinates of a space (:mod:`redsim.integrators.spaces`). In a latent space
the state holds z and the inertial target stays in q: qbar = 2 f(z_t) - f(z_{t-1}).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import numbers
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import torch
from torch import Tensor

from redsim.integrators.energy_gain import energy_gain_states
from redsim.integrators.objective import (
    Inertia,
    PotentialObjective,
    SceneConstants,
    check_time_step,
    checked_vector,
    pack_inputs,
)
from redsim.integrators.reference import _lower_along, _negative_curvature
from redsim.integrators.spaces import FullSpace, Space
from redsim.integrators.tunneling import TunnelTest
from redsim.scene import LoadsLike, Scene
from redsim.solvers import ConvergenceError, SolveInfo, check_settings, get_minimizer

logger = logging.getLogger(__name__)

SADDLE_ESCAPES = 3
"""Most escapes from saddles per step of ``ImplicitEuler(..., escape_saddles=True)``."""

CATCH_ITERATIONS = 4
"""A step solved again within the trust radius (``retry_tunneled``) gets this many times ``max_iter`` more iterations
than a step: the mini chain's loaded steps of 0.1 s (the accuracy bench's dt x5) took 48-124 in all where the first
end was 0.1 m through the hook (a budget of ``max_iter`` plus that distance over the radius, 66, was too few)."""

LoadSchedule = Callable[[int, "FullState"], LoadsLike]
"""Loads as a function of (step index, state before the step)."""


@contextlib.contextmanager
def quiet_steps() -> Iterator[None]:
    """Silence the per-step non-convergence warnings inside the block, for a caller that counts
    ``info.converged`` itself and reports it (a benchmark's table)."""
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


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


@dataclass(frozen=True)
class StepInfo(SolveInfo):
    """A step's :class:`SolveInfo` and its energy balance.

    Attributes:
        energy_gain: K + E rose by more than the loads' work, beyond round-off and what the solve's
            leftover gradient allows (:mod:`redsim.integrators.energy_gain`). Reported, never acted on:
            the state is finite and usable, and nothing is logged.
        mechanical_gain: K_{t+1} + E(q_{t+1}) - K_t - E(q_t) - W_t [J], with W_t the loads' work over
            the step; <= 0 on a dissipative step.
        tunneled: The kept end's straight path from q_t passed through a contact that neither end shows (a move
            longer than the contact is thick, which the penalty never felt: :mod:`redsim.integrators.tunneling`):
            in the full space, a step whose first solve did and whose solve again within a trust radius
            (``tunnel_caught``) did not converge or went through a contact on its way (the path through the states
            it accepted), or any such step with ``retry_tunneled=False``; in a latent space, any such step
            (reported only).
        tunnel_caught: The first solve's straight path passed through a contact, and the step was solved again from
            q_t, each iteration moving no contact point more than half the thinnest contact relative to its shape,
            along a path through no contact, ended converged: the end kept (``retry_tunneled``, full space). Converged
            as any step is (a stationary point of the same step objective, which may be a saddle of it without
            ``escape_saddles``). The kept end can be the first solve's own: its chord from q_t crossed a contact
            that the solve again's path went round (a convex shape). ``iterations`` counts both solves,
            ``history`` the second's.
    """

    energy_gain: bool = False
    mechanical_gain: float = 0.0
    tunneled: bool = False
    tunnel_caught: bool = False


def _check_state(state: object) -> None:
    if not isinstance(state, FullState):
        raise TypeError(
            f"state must be a FullState (q and q_prev: sim.initial_state(q, velocity) makes one), got "
            f"{type(state).__name__}"
        )


def _same(a: Tensor | None, b: Tensor | None) -> bool:
    return a is b or (a is not None and b is not None and torch.equal(a, b))


class ImplicitEuler:
    """Two-state implicit Euler over a space (module doc), each step solved by a named minimizer.

    Args:
        space: The coordinates solved for (:class:`FullSpace` for the reference, :class:`LatentSpace`
            for a subspace; the state then holds z).
        dt: Time step h [s], finite and >= :data:`redsim.integrators.objective.MIN_TIME_STEP` (1e-6 s).
        minimizer: A key of :data:`redsim.solvers.MINIMIZERS` ("newton" or "lbfgs").
        tol: Relative gradient tolerance (see :class:`PotentialObjective` for what it bounds).
        max_iter: Most iterations of the minimizer per step.
        strict: Raise :class:`redsim.solvers.ConvergenceError` (a RuntimeError carrying the
            SolveInfo) when a step does not converge; otherwise the step returns the last
            iterate with ``converged=False`` and logs a warning.
        escape_saddles: Full space only. A converged step is a stationary point of the step's objective, and
            projected Newton does not see negative curvature, so from a symmetric state it can end at a saddle
            (the two-link chain's third step of 0.02 s under 2 N on ``bottom``: Hessian eigenvalue -355, 2.8 mJ
            above the minimum the links turn 0.02 rad to; the 24-link chain falling from its seed at 0.02 s: steps
            3 to 6, 3 mJ to 0.4 J above). With True, a converged step whose Hessian K + M/h^2 has negative
            curvature (:func:`redsim.integrators.reference._negative_curvature`) is left along it to lower objective
            and solved again, at most :data:`SADDLE_ESCAPES` times, as
            :func:`redsim.integrators.reference.full_equilibrium` does; at the cost of one more Hessian and
            factorization per step (10-40% of a step's time on the catalog scenes where no step ends at a saddle;
            the chain above then took 5x the time, for the more iterations of the solves that leave them). An escape
            whose solve does not converge is dropped (the converged saddle stands; ``iterations`` counts it).
        retry_tunneled: Solve a step whose end passed through a contact again (``StepInfo.tunnel_caught``): from
            q_t, each iteration moving no contact point more than half the thinnest contact relative to its shape
            (``PotentialObjective.max_step`` and ``move_measure``; what the tunnel test samples), with
            :data:`CATCH_ITERATIONS` x ``max_iter`` more iterations than a step. The first end is kept
            (``tunneled``) where that solve does not converge or its path (q_t, each state it accepted, its end:
            :meth:`TunnelTest.along`) passes through a contact (a penalty contact too soft to stop the body
            before its middle has no minimum on the near side). None (the default): in the full space only; True in
            a latent space is refused (its coordinates have no distance in metres to bound). Costs nothing on a
            step that did not tunnel; the mini chain thrown at its hook at 10 m/s (its first solve: 1 iteration,
            0.2 m up through the hook) is caught 0.06 m up in 12 more.

    Raises:
        ValueError: on a bad dt, tol, max_iter, an unknown minimizer, or ``escape_saddles`` or ``retry_tunneled``
            outside the full space.
        TypeError: ``space`` is a :class:`Scene` (the full space is ``FullSpace(scene)``).
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
        escape_saddles: bool = False,
        retry_tunneled: bool | None = None,
    ) -> None:
        if isinstance(space, Scene):
            raise TypeError(
                "ImplicitEuler takes a space, not a scene: ImplicitEuler(FullSpace(scene), dt) for the full space, "
                "LatentSpace(scene, subspace) for a map's latent one (both in redsim.integrators)"
            )
        dt = check_time_step(dt)
        tol, max_iter = check_settings(tol, max_iter)
        self.space = space
        self.dt = float(dt)
        self.minimizer = minimizer
        self._minimize = get_minimizer(minimizer)
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        self.strict = bool(strict)
        if escape_saddles and not isinstance(space, FullSpace):
            raise ValueError("escape_saddles needs the full space (FullSpace(scene)): the test reads the q Hessian")
        self.escape_saddles = bool(escape_saddles)
        full = isinstance(space, FullSpace)
        if retry_tunneled and not full:
            raise ValueError(
                "retry_tunneled needs the full space (FullSpace(scene)): its trust radius bounds moves in metres"
            )
        self.retry_tunneled = full if retry_tunneled is None else bool(retry_tunneled)
        self._constants = SceneConstants.of(space.scene)
        self._tunnel_test = TunnelTest(space.scene)
        self._last_potential: tuple[Tensor, Tensor | None, Tensor] | None = None

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
        q_t = origin.detach().clone() if q is None else checked_vector(q, size, "q", origin)
        v = torch.zeros_like(q_t) if velocity is None else checked_vector(velocity, size, "velocity", origin)
        return FullState(q_t, q_t - self.dt * v, 0.0)

    def step(self, state: FullState, loads: LoadsLike = None, cond: Tensor | None = None) -> tuple[FullState, StepInfo]:
        """Advance one step of length dt.

        Args:
            state: The current state.
            loads: Loads on the scene's handles [N] (see :meth:`Scene.pack_loads`), held during the step.
            cond: Condition vector [m] for conditional scenes.

        Returns:
            The new state (time + dt) and the minimizer's :class:`SolveInfo` with the step's energy
            balance (:class:`StepInfo`).

        Raises:
            ValueError: on non-finite loads, condition or state.
            TypeError: ``state`` is not a :class:`FullState` (make one with :meth:`initial_state`).
            ConvergenceError: with ``strict=True``, when the step did not converge.
        """
        _check_state(state)
        origin = self.space.origin
        u_t = checked_vector(state.q, self.space.size, "state.q", origin)
        u_prev = checked_vector(state.q_prev, self.space.size, "state.q_prev", origin)
        loads_t, cond_t = pack_inputs(self.scene, loads, cond)
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
        u_next, info = self._solve(objective, 2.0 * u_t - u_prev)
        x_t = self.scene.full_positions(q_t.unsqueeze(0)) if self._tunnel_test.contacts else None
        tunneled, caught = x_t is not None and self._through_contact(x_t, u_next), False
        if tunneled and self.retry_tunneled:
            u_next, info, tunneled, caught = self._catch(objective, u_t, u_next, info)
        if not info.converged:
            if self.strict:
                raise ConvergenceError(info)
            logger.warning("implicit Euler step at t = %.6g s did not converge: %s", state.time, info.message)
        info = self._energy_balance(info, configurations, u_t, u_next, loads_t, cond_t)
        info = dataclasses.replace(info, tunneled=tunneled, tunnel_caught=caught)
        return FullState(u_next.clone(), u_t, state.time + self.dt), info

    def _solve(
        self, objective: PotentialObjective, start: Tensor, max_iter: int | None = None
    ) -> tuple[Tensor, SolveInfo]:
        """The minimizer from ``start`` (and off saddles where ``escape_saddles``): the end [m] and its info."""
        u_next, info = self._minimize(objective, start, tol=self.tol, max_iter=max_iter or self.max_iter)
        if self.escape_saddles and info.converged:
            u_next, info = self._leave_saddles(objective, u_next.detach(), info)
        return u_next.detach(), info

    def _through_contact(self, x_t: Tensor, u_next: Tensor) -> bool:
        """Whether the straight path from x_t [1, N] to the positions of ``u_next`` passed through a contact."""
        with torch.no_grad():
            x_next = self.scene.full_positions(self.space.configuration(u_next.unsqueeze(0)))
        return bool(self._tunnel_test(x_t, x_next)[0])

    def _through_contact_along(self, path: list[Tensor]) -> bool:
        """Whether the path through the coordinates ``path`` (each [m]: a step's start, the states it went through, its
        end) passed through a contact (:meth:`TunnelTest.along`)."""
        with torch.no_grad():
            x = self.scene.full_positions(self.space.configuration(torch.stack(path)))
        return self._tunnel_test.along(x)

    def _contact_move(self, u: Tensor, direction: Tensor) -> float:
        """The largest move [m] of a contact point relative to its shape (in the frame that carries the shape) from u
        to u + direction: what the tunnel test samples along."""
        with torch.no_grad():
            ends = self.space.configuration(torch.stack([u, u + direction]))
            x = self.scene.full_positions(ends)
            largest = 0.0
            for contact in self._tunnel_test.contacts:
                points, valid = contact.frame_points(x)
                move = points[1, valid] - points[0, valid]
                largest = max(largest, float((move * move).sum(-1).max()))
        return math.sqrt(largest)

    def _catch(
        self, objective: PotentialObjective, u_t: Tensor, u_first: Tensor, first: SolveInfo
    ) -> tuple[Tensor, SolveInfo, bool, bool]:
        """The step solved again from u_t, each iteration's contact-point moves within the trust radius
        (``retry_tunneled``): (end, info, tunneled, caught), the first end and info kept (tunneled) where the solve
        again does not converge or its path (u_t, each accepted state, its end) passes through a contact. The path, not
        the chord between the ends, is tested: cloth_ball's dt x5 push wrapped the cloth 160 degrees round the ball in
        one step, whose chord cut 72 mm into the 120 mm ball, while the states of the solve again stayed within 4 mm of
        the surface (an uncaught false tunnel before)."""
        objective.max_step, objective.move_measure = 0.5 * self.scene.feature_size(), self._contact_move
        objective.path = path = [u_t.clone()]
        try:
            u_again, again = self._solve(objective, u_t.clone(), (1 + CATCH_ITERATIONS) * self.max_iter)
        finally:
            objective.max_step, objective.move_measure, objective.path = math.inf, None, None
        iterations = first.iterations + again.iterations
        if not torch.equal(path[-1], u_again):
            path.append(u_again)
        if not again.converged or self._through_contact_along(path):
            return u_first, dataclasses.replace(first, iterations=iterations), True, False
        return u_again, dataclasses.replace(again, iterations=iterations), False, True

    def _leave_saddles(self, objective: PotentialObjective, u: Tensor, info: SolveInfo) -> tuple[Tensor, SolveInfo]:
        """A converged step's end ``u`` moved off saddles of ``objective`` (``escape_saddles``); ``info`` counts the
        iterations of every solve. An escape whose solve does not converge is dropped: the converged saddle it left
        stands (a step solved again after a tunnel, caught on the contact's near side at a saddle, kept that end
        through the hook when the escape stalled at |g| 1.2e-3 against a threshold of 8.9e-5)."""
        iterations = info.iterations
        for _ in range(SADDLE_ESCAPES):
            direction = _negative_curvature(self.scene, u, objective.loads, objective.cond, self.dt)
            lower = None if direction is None else _lower_along(objective, u, info.energy, direction)
            if lower is None:
                break
            mark = None if objective.path is None else len(objective.path)
            u_escaped, escaped = self._minimize(objective, lower, tol=self.tol, max_iter=self.max_iter)
            iterations += escaped.iterations
            if not escaped.converged:
                if mark is not None:  # the states of a dropped escape are not the step's path
                    del objective.path[mark:]
                break
            u, info = u_escaped.detach(), escaped
        return u, dataclasses.replace(info, iterations=iterations)

    def _energy_balance(
        self,
        info: SolveInfo,
        configurations: Tensor,
        u_t: Tensor,
        u_next: Tensor,
        loads: Tensor | None,
        cond: Tensor | None,
    ) -> StepInfo:
        """``info`` with the step's energy balance (:class:`StepInfo`); configurations [2, n]: q_t, q_{t-1}."""
        scene = self.scene
        with torch.no_grad():
            q_next = self.space.configuration(u_next.unsqueeze(0))
            q = torch.cat([configurations[1:], configurations[:1], q_next])  # q_{t-1}, q_t, q_{t+1}
            v = q[1:] - q[:-1]
            kinetic = 0.5 * (v * scene.mass_matvec(v)).sum(-1) / self.dt**2
            last = self._last_potential  # E(q_t) when the last step ended at u_t under this condition
            if last is not None and torch.equal(last[0], u_t) and _same(last[1], cond):
                potential = torch.cat([last[2], scene.energy(q[2:], None, cond)])
            else:
                potential = scene.energy(q[1:], None, None if cond is None else cond.expand(2, -1))
            self._last_potential = (u_next.clone(), cond, potential[1:])
            mechanical = kinetic + potential
            work = torch.zeros((), dtype=q.dtype, device=q.device)
            if loads is not None and scene.handles:
                p = scene.handle_positions(q[1:])
                work = (loads.reshape(-1) * (p[1] - p[0])).sum()
        inexact = info.grad_norm * float(torch.linalg.vector_norm(u_next - u_t))
        eps = max(float(torch.finfo(q.dtype).eps), self.space.roundoff)
        inexact += self._constants.energy_noise  # E's own round-off: near rest far above eps |K + E|
        gained = energy_gain_states(
            mechanical[:1], mechanical[1:], work.reshape(1), torch.tensor([inexact], dtype=q.dtype), eps
        )
        change = float(mechanical[1] - mechanical[0] - work)
        return StepInfo(**dataclasses.asdict(info), energy_gain=bool(gained[0]), mechanical_gain=change)

    def rollout(
        self,
        state: FullState,
        steps: int,
        loads: LoadsLike | LoadSchedule = None,
        cond: Tensor | None = None,
    ) -> tuple[Tensor, list[StepInfo]]:
        """Run ``steps`` steps from ``state``.

        Args:
            state: The initial state.
            steps: Number of steps (>= 0).
            loads: Loads held for every step, or a function (step index, state) -> loads.
            cond: Condition vector, held for every step.

        Returns:
            The coordinates at every time, shape [steps + 1, n] (the initial ones first), and
            one StepInfo per step.

        Raises:
            ValueError: ``steps`` not an integer >= 0; as :meth:`step`.
            TypeError: ``state`` is not a :class:`FullState`.
        """
        if isinstance(steps, bool) or not isinstance(steps, numbers.Real):
            raise ValueError(f"steps must be an integer >= 0, got {steps!r}")
        if not (math.isfinite(steps) and steps >= 0 and int(steps) == steps):
            raise ValueError(f"steps must be an integer >= 0, got {steps!r}")
        _check_state(state)  # before state.q: a tensor read "'Tensor' object has no attribute 'q'"
        schedule: LoadSchedule = loads if callable(loads) else (lambda _i, _s: loads)
        trajectory = [state.q.detach().clone()]
        infos = []
        for index in range(int(steps)):
            state, info = self.step(state, schedule(index, state), cond)
            trajectory.append(state.q)
            infos.append(info)
        return torch.stack(trajectory), infos
