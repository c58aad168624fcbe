"""The batched latent stepper: implicit Euler in z for B states at once (the runtime under the envs).

One call advances every state b of a batch by one step of length h:

    z_b' = argmin_z  1/(2 h^2) |f(z) - qbar_b|_M^2 + E(f(z); c_b) - F_b . p(f(z)),   qbar_b = 2 f(z_b) - f(z_b^prev),

the objective of :class:`redsim.integrators.ImplicitEuler` over :class:`redsim.integrators.LatentSpace`
(the reference, which stays the ground truth), solved by :func:`redsim.runtime.solver.minimize` in
the map's dtype and device. Constants (mass operator, handle matrix, force scales) are built once
here; a step only evaluates the energy.
"""

from __future__ import annotations

import copy
import functools
import itertools
import math
import numbers
import types
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from redsim import pretrained
from redsim.devices import check_device, check_dtype
from redsim.integrators import LatentSpace, check_time_step, latent_equilibrium, length_scale
from redsim.integrators.spaces import SceneParametersWarning, check_map_scene
from redsim.runtime.energy import LatentEnergy, MapEnergy, ReducedInertia
from redsim.runtime.flags import diverged_states, energy_gain_states, energy_gain_tolerance, out_of_range_states
from redsim.runtime.solver import HESSIANS, BatchResult, check_max_step, check_sync_every, minimize, newton_step
from redsim.scene import LoadsLike, Scene
from redsim.solvers import check_settings
from redsim.subspace import map_fingerprint
from redsim.tensors import as_numbers, jvp

DEFAULT_TOL = {torch.float32: 1e-6, torch.float64: 1e-9}
"""Default relative gradient tolerance per dtype.

Measured (README, "Latent runtime"): 1e-5 in float32 left one-step errors of 8-16% of the motion
against the reference on chain and bistable_bar, 1e-6 0.2-2.5%."""
DEFAULT_MAX_ITER = 50
"""Default most iterations per step."""
FD_STEP = {torch.float32: 1e-3, torch.float64: 1e-6}
"""Forward-difference step of the "lagged_fd" Hessian, relative to 1 + max|z| (about sqrt(eps) of each dtype)."""
DEFAULT_HESSIAN = "lagged_fd"
"""Default Hessian model of the solver (see the measurements in docs/runtime.md, "Solver: which Hessian model")."""
RESOLUTION_WARNING = 0.01 * 9.81
"""[m/s^2] A stepper whose :attr:`LatentStepper.acceleration_resolution` exceeds this (1% of standard gravity)
warns at construction: forces that small are not felt (README "Latent runtime"; docs/runtime.md, "Tolerance")."""
ROUNDOFF_TOL = 1.0 / 16.0
"""A ``tol`` below this fraction of the dtype's machine epsilon (float32: 7.5e-9) warns at construction: round-off in
the reduced force keeps many solves from reaching it within ``max_iter``. Development runs, float32, the envs'
``max_iter`` 50, 20 random-action steps each: tol 3e-9 converged every step of MiniChain-v0, 95% of Klann-v0's and
none of BistableBar-v1's; 1e-9 35%, 55% and 0%; 1e-10 0%, 5% and 0% (each unconverged step runs ``max_iter``
iterations); 1e-8 converged every step of all three. It is no hard floor: a review's mini chain step at 1e-12 reached
8.2e-10 after 200 iterations."""
ROUNDOFF_PROBE_ULPS = 64.0
"""The latent step of the gradient round-off probe (:attr:`LatentStepper.roundoff_tol`), in units of the dtype's machine
epsilon (float32: 7.6e-6): long enough that the map's layers round differently at each probe point, short enough that
the gradient's curvature over it (of order step^2) stays below its round-off in float32 and float64."""
ROUNDOFF_PROBE_DIRECTIONS = 8
"""Seeded random directions of that probe; the median over them is reported."""
COMPILES = (False, True, "dynamic")
"""The ``compile`` settings of :class:`LatentStepper`: eager, static shapes (every call pads to the batch), and one
graph of value and gradient over any row count."""
STARTS = ("extrapolated", "lower")
"""Where a step's solve starts: 2 z_t - z_{t-1}, or whichever of that and z_t has the lower Phi (both are evaluated)."""


class StepStats(NamedTuple):
    """What one step did, per state; every field has shape [B], except ``model`` [B, d, d] and ``carry`` [B, k].

    Attributes:
        converged: The relative gradient norm met ``tol`` (bool).
        iterations: Accepted solver iterations (int64), those of the solve again from z_t included (:meth:`step`).
        residual: |dPhi/dz| / (|J_0|_2 F_b), the relative gradient norm ``tol`` bounds (see :class:`LatentStepper`);
            inf where the force scale F_b overflows the dtype (loads too large to square; the step is then diverged)
            and where Phi or its gradient was not finite at the start (nothing was solved: z_next is z, diverged).
        energy: Potential energy E(f(z_next)) [J] (the load work not included). Where the start was not finite
            (z_next is then z, and ``diverged`` is set) it is E at z: NaN or inf where E(f(z)) is not finite, never
            a finite stand-in that reads as a state's energy.
        out_of_range: z or z_next (or the condition) is outside the region the map was fitted on (bool).
        diverged: The step is not trustworthy: non-finite (at its end, or Phi at z_t, whose energy balance it is
            checked against), or it added more energy than it could have (bool).
        energy_gain: K + E rose by more than the loads' work, beyond round-off and the solve's
            tolerance (bool): an artefact of the map, reported as information
            (:func:`redsim.runtime.flags.energy_gain_states`).
        energy_gain_tolerance: The rise of K + E beyond the loads' work [J] that ``energy_gain`` allows: what the
            solve's leftover gradient can put in, |dPhi/dz| |z_{t+1} - z_t|, plus round-off (inf where ``residual`` is,
            and where K + E at either end is not finite).
        stalled: The solver stopped unconverged before ``max_iter`` iterations: its line search found no step that
            lowers Phi (a quasi-Newton model's, again from a model built afresh; :mod:`redsim.runtime.solver`) (bool).
            A state neither converged nor stalled ran out of iterations (or its start was not finite: ``diverged``).
        model: The solver's final d x d Hessian model [B, d, d]: pass it as ``warm`` to the next step
            of the same states (NaN rows: none was built).
        carry: What the step knows at z_next, [B, :attr:`LatentStepper.carry_size`]: (z_next, cond) as its key, E,
            dPhi/dz and the inertia and load terms' force dPhi/dq - dE/dq [w] there: pass it as ``carry`` to the next
            step of the same states, which then evaluates Phi at z_t without the energy (NaN rows: the step did not
            converge, and the next one evaluates Phi there).
    """

    converged: Tensor
    iterations: Tensor
    residual: Tensor
    energy: Tensor
    out_of_range: Tensor
    diverged: Tensor
    energy_gain: Tensor
    energy_gain_tolerance: Tensor
    stalled: Tensor
    model: Tensor
    carry: Tensor


@dataclass
class Evaluations:
    """Running count of the objective's value-and-gradient evaluations of a :class:`LatentStepper`.

    The exact and Gauss-Newton Hessians' double backward passes are not counted.

    Attributes:
        calls: Calls (each one batched energy + gradient pass, or several blocks of one with ``row_block``; a
            call's fixed cost is what a small batch pays).
        rows: Latent states evaluated over those calls (a compiled or dense stepper evaluates its whole batch).
    """

    calls: int = 0
    rows: int = 0


class _StepObjective:
    """Phi_b(z) of one step for the solver (:class:`redsim.runtime.solver.BatchObjective`)."""

    def __init__(
        self, stepper: LatentStepper, qbar: Tensor, loads: Tensor | None, cond: Tensor | None, pad: Tensor
    ) -> None:
        self.s = stepper
        self.qbar = qbar
        self.loads = loads
        self.cond = cond
        self.pad = pad  # [B, d]: finite latents for the rows a compiled call does not need

    def _cond(self, index: Tensor, repeat: int = 1) -> Tensor | None:
        if self.cond is None:
            return None
        c = self.cond[index]
        return c.repeat(repeat, 1) if repeat > 1 else c

    def phi(self, z: Tensor, index: Tensor, repeat: int = 1) -> tuple[Tensor, Tensor]:
        """Phi [k * repeat] of z [k * repeat, d] (``repeat`` copies of the states ``index``) and E."""
        qbar = self.qbar[index]
        loads = None if self.loads is None else self.loads[index]
        cond = self._cond(index)
        if repeat > 1:
            qbar = qbar.repeat(repeat, 1)
            loads = None if loads is None else loads.repeat(repeat, 1)
            cond = None if cond is None else cond.repeat(repeat, 1)
        return self.s._phi(z, qbar, loads, cond)

    def value_and_grad(self, z: Tensor, index: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        if self.s.compiled:  # one static shape [B]: the other rows are evaluated at the start and dropped
            full = self.pad.index_copy(0, index, z)
            value, grad, energy = self._value_and_grad(full, self.qbar, self.loads, self.cond)
            return value[index], grad[index], energy[index]
        loads = None if self.loads is None else self.loads[index]
        return self._value_and_grad(z, self.qbar[index], loads, self._cond(index))

    def start(self, z0: Tensor, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Phi, dPhi/dz and E at the start z0 and at z_t (both [B, d]) of every state, in one call: [2B], [2B, d], [2B].

        Compiled, this is its own static shape [2B] (one more graph, one call fewer per step than two [B] calls).
        """
        both = torch.cat([z0, z])
        if not self.s.compiled:
            index = torch.arange(z.shape[0], device=z.device)
            return self.value_and_grad(both, torch.cat([index, index]))
        loads = None if self.loads is None else self.loads.repeat(2, 1)
        cond = None if self.cond is None else self.cond.repeat(2, 1)
        return self._value_and_grad(both, self.qbar.repeat(2, 1), loads, cond)

    def _value_and_grad(
        self, z: Tensor, qbar: Tensor, loads: Tensor | None, cond: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor]:
        self.s.evaluations.calls += 1
        self.s.evaluations.rows += z.shape[0]
        block = self.s.row_block
        if not self.s.compiled and block is not None and z.shape[0] > block:
            parts = [
                self._block_value_and_grad(
                    z[i : i + block],
                    qbar[i : i + block],
                    None if loads is None else loads[i : i + block],
                    None if cond is None else cond[i : i + block],
                )
                for i in range(0, z.shape[0], block)
            ]
            return tuple(torch.cat(columns) for columns in zip(*parts, strict=True))  # type: ignore[return-value]
        return self._block_value_and_grad(z, qbar, loads, cond)

    def _block_value_and_grad(
        self, z: Tensor, qbar: Tensor, loads: Tensor | None, cond: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Phi, dPhi/dz and E of one block of rows (uncounted: :meth:`_value_and_grad` counts the call)."""
        if self.s._compiled_call is not None:  # compile="dynamic": value and gradient in one graph, these rows only
            return self.s._compiled_call(z, qbar, loads, cond)
        if self.s.compiled:
            z = z.detach().requires_grad_(True)
            with torch.enable_grad():
                value, energy = self.s._phi_fast(z, qbar, loads, cond)
                (grad,) = torch.autograd.grad(value.sum(), z)
            return value.detach(), grad, energy.detach()
        return self.s._eager_value_and_grad(z, qbar, loads, cond)

    def exact_hessian(self, z: Tensor, index: Tensor) -> Tensor:
        k, d = z.shape
        eye = torch.eye(d, dtype=z.dtype, device=z.device)
        tangents = eye.repeat_interleave(k, 0)  # copy j of every state probes direction e_j
        zr = z.detach().repeat(d, 1).requires_grad_(True)
        with torch.enable_grad():
            value, _ = self.phi(zr, index, d)
            (grad,) = torch.autograd.grad(value.sum(), zr, create_graph=True)
            (rows,) = torch.autograd.grad((grad * tangents).sum(), zr)
        return rows.reshape(d, k, d).transpose(0, 1)

    def difference_hessian(self, z: Tensor, index: Tensor, grad: Tensor) -> Tensor:
        k, d = z.shape
        step = FD_STEP[z.dtype] * (1.0 + z.abs().amax(-1, keepdim=True))  # [k, 1]
        eye = torch.eye(d, dtype=z.dtype, device=z.device)
        shifted = (z.unsqueeze(0) + step.unsqueeze(0) * eye.unsqueeze(1)).reshape(d * k, d)  # copy j: z + h e_j
        _, grads, _ = (
            self.value_and_grad(shifted, index.repeat(d)) if not self.s.compiled else self._shifted(shifted, index)
        )
        columns = (grads.reshape(d, k, d) - grad.unsqueeze(0)) / step.unsqueeze(0)  # [j, k, :] = H e_j
        return columns.transpose(0, 1)

    def _shifted(self, shifted: Tensor, index: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Gradients at the d shifted copies [d * k, d] of states ``index`` with one static-shape call [d * B]."""
        d = shifted.shape[0] // index.numel()
        batch = self.qbar.shape[0]
        full = self.pad.repeat(d, 1)
        rows = (index.unsqueeze(0) + batch * torch.arange(d, device=index.device).unsqueeze(1)).reshape(-1)
        full = full.index_copy(0, rows, shifted)
        loads = None if self.loads is None else self.loads.repeat(d, 1)
        cond = None if self.cond is None else self.cond.repeat(d, 1)
        value, grads, energy = self._value_and_grad(full, self.qbar.repeat(d, 1), loads, cond)
        return value[rows], grads[rows], energy[rows]

    def _jacobian(
        self, z: Tensor, index: Tensor, coords: Callable[[Tensor, Tensor | None], Tensor] | None = None
    ) -> Tensor:
        """J^T as [d, k, n]: dy/dz_j of every state (y = the stepper's coordinates), by :func:`redsim.tensors.jvp`."""
        k, d = z.shape
        tangents = torch.eye(d, dtype=z.dtype, device=z.device).repeat_interleave(k, 0)
        cond = self._cond(index, d)
        coords = self.s._coords if coords is None else coords
        _, columns = jvp(lambda u: coords(u, cond), (z.detach().repeat(d, 1),), (tangents,))
        return columns.reshape(d, k, -1)

    def metric(self, z: Tensor, index: Tensor) -> Tensor:
        columns = self._jacobian(z, index)
        d, k, n = columns.shape
        mj = self.s._mass(columns.reshape(d * k, n)).reshape(d, k, n)
        return torch.einsum("akn,bkn->kab", columns, mj) / self.s.dt**2

    def gauss_newton(self, z: Tensor, index: Tensor) -> Tensor:
        q_energy = getattr(self.s.energy, "q_energy", None)
        if q_energy is None:
            raise ValueError("the gauss_newton Hessian needs an energy with q_energy(q, cond) (e.g. MapEnergy)")
        columns = self._jacobian(z, index)
        d, k, n = columns.shape
        with torch.no_grad():
            q = self.s.energy.positions(z, self._cond(index))
        qr = q.repeat(d, 1).requires_grad_(True)
        flat = columns.reshape(d * k, n)
        with torch.enable_grad():
            (grad,) = torch.autograd.grad(q_energy(qr, self._cond(index, d)).sum(), qr, create_graph=True)
            (hv,) = torch.autograd.grad((grad * flat).sum(), qr)
        hv = hv + self.s.scene.mass_matvec(flat) / self.s.dt**2
        out = torch.einsum("akn,bkn->kab", columns, hv.reshape(d, k, n))
        return 0.5 * (out + out.transpose(-1, -2))


class LatentStepper:
    """Implicit Euler over the latent z of a subspace map, B states per call (module doc).

    Convergence: a state is converged when |dPhi/dz| <= tol * |J_0|_2 * F_b, where |J_0|_2 is the
    spectral norm of dq/dz at z = 0 and F_b [N] = the effects' force norms at f(0) (summed) + |diag M| L / h^2
    + |M (q_t - q_{t-1})| / h^2 + |F_b loads|: the reference's rule (:class:`redsim.integrators.PotentialObjective`)
    with its scales measured once per scene and map instead of per step. ``residual`` is that ratio.

    Args:
        scene: The scene.
        subspace: The map f(z[, c]) -> q (a :class:`redsim.subspace.SubspaceMap` or a baseline); copied.
        dt: Time step h [s].
        dtype: Floating dtype of the solve (float32 by default; float64 on request).
        device: Where it runs ("cpu", "cuda", ...).
        energy: A :class:`redsim.runtime.energy.LatentEnergy`; None means :class:`MapEnergy` (scene.energy o f).
            One that also implements :class:`redsim.runtime.energy.ReducedInertia` (e.g. a cubature energy)
            has the inertia and load terms evaluated in its features r (q = r W^T + b) with the
            precomputed W^T M W: exact, and no per-iteration cost that grows with n. A callable is a
            factory ``energy(scene, subspace, dtype=, device=)``, e.g. :func:`redsim.cubature.cubature_energy`
            (the cubature shipped for the scene's map).
        max_iter: Most solver iterations per step.
        tol: Relative gradient tolerance (default :data:`DEFAULT_TOL` of the dtype).
        hessian: The solver's Hessian model, one of :data:`redsim.runtime.solver.HESSIANS`.
        compile: Evaluate the objective's value and gradient through ``torch.compile`` (:data:`COMPILES`): True,
            with static shapes (every call evaluates the whole batch, its other rows dropped; one graph per batch
            size); "dynamic", the value and its gradient in one graph for any number of rows (a call evaluates only
            the rows it needs, as eager does; two graphs, one row and several; HangingCloth-v1 at 64 envs 1.18-1.25x
            by CPU time, static 0.62x). The first steps pay the compilation (tens of seconds; 90 s cold on a loaded
            2-core CPU); results equal eager within dtype round-off; on the CPU it needs a C++ compiler. The exact
            and Gauss-Newton Hessians' double backward passes stay eager.
        warm_start: Use the ``warm`` model :meth:`step` is given (default). False ignores it: every
            step builds its own model, as the reference does. Where a step's objective has several
            nearby minima (the mini chain's folded map under full-range actions) the two can
            converge to different ones, and a chaotic rollout then splits (docs/runtime.md, "Warm start across steps").
        dense: Solve with the dense masked iteration (:func:`redsim.runtime.solver.minimize`): every
            call evaluates all B states, and the solver's loop waits for the device only at the early
            exit every ``sync_every`` calls (the energy's own eager paths and the eigenvalue fix of the
            exact and difference Hessians still synchronise). None (default): dense exactly on a CUDA
            device; on the CPU the row-selected iteration, which evaluates only the active states, is
            as fast or faster (docs/runtime.md, "Two solver iterations").
        sync_every: With ``dense``, calls between early-exit checks (None: never, so every step runs the loop's
            whole bound of max_iter (2 MAX_BACKTRACKS + 1) calls however soon it converges: for a graph that must
            not read the device, not for speed; see ``minimize``).
        max_step: The longest latent step |dz| a solver trial takes (longer directions are scaled down to it);
            None (default): no limit. Guards against Newton-type steps along a direction the map barely
            moves, which overshoot (docs/env-speed.md, "ConditionalBar-v0's solve path").
        warm_refresh: Rebuild a ``warm`` model when a step backtracks from it or is still unconverged after
            :data:`redsim.runtime.solver.WARM_ITERATIONS` iterations (default); False keeps BFGS-updating it
            (rebuilt only where a line search fails: the solver's restart).
        start: Where each solve starts (:data:`STARTS`): "extrapolated" (default), 2 z_t - z_{t-1}; "lower",
            whichever of that and z_t has the lower Phi (the step evaluates both anyway). The same minimum
            where the step's objective has one (docs/env-speed.md, "ConditionalBar-v0's solve path"). Either way a copy
            whose extrapolated start has a non-finite Phi or gradient starts from z_t.
        row_block: Most rows one value-and-gradient pass evaluates (ignored with ``compile=True``, whose one graph
            evaluates the whole batch: ClothBall-v0's default stays harmless there); a call with more is
            evaluated in blocks of this many rows, the same values to round-off (counted as one call). None
            (default): one pass. Where one pass's per-element tensors outgrow the CPU's cache it pays: ClothBall-v0 at
            256 envs (its whole contact, 2025 points a row, in a step's first call of 512 rows and its d x k-row
            difference-Hessian calls) 1.16x by CPU time with 256; HangingCloth-v1 and Chain-v0 gain nothing
            (docs/env-speed.md, "Stop 28's measurements"). The exact and Gauss-Newton Hessians' passes are not split.
        predict: Where a step is given both a ``carry`` and a ``warm`` model of a state (the envs pass both), start
            its solve from the model's Newton step from z_t, z_t - H^-1 dPhi/dz(z_t) (at most ``max_step`` long;
            the carry gives dPhi/dz there without a call), instead of 2 z_t - z_{t-1}: the same minimum where the
            step's objective has one near z_t (where it has two, either start may pick the higher: docs/runtime.md),
            ~1 iteration fewer per copy on the cloths and the chain (docs/env-speed.md, "Stop 51"). Skipped with
            ``hessian="gauss_newton"`` (no warm model: 31% more calls on the chain). False: the extrapolated start
            always. ``start="lower"`` compares Phi there with Phi(z_t).

    Raises:
        ValueError: a bad dt, tol, max_iter, hessian, compile, sync_every, max_step, warm_refresh, warm_start, dense,
            start, row_block or predict, a device redsim cannot run on (:func:`redsim.devices.check_device`), or a map
            that does not fit the scene (another output size, or fitted to a scene of another name; one fitted to this
            scene with other parameters, e.g. a soft map driven on a stiffer material, is stepped with a warning).
        TypeError: a scene that is not a :class:`redsim.scene.Scene` (e.g. its name).
        RuntimeError: ``compile`` on the CPU without a C++ compiler (:func:`check_compiler`).
    """

    def __init__(
        self,
        scene: Scene,
        subspace: nn.Module,
        dt: float = 0.02,
        *,
        dtype: torch.dtype = torch.float32,
        device: str | torch.device = "cpu",
        energy: LatentEnergy | Callable[..., LatentEnergy] | None = None,
        max_iter: int = DEFAULT_MAX_ITER,
        tol: float | None = None,
        hessian: str = DEFAULT_HESSIAN,
        compile: bool | str = False,
        warm_start: bool = True,
        dense: bool | None = None,
        sync_every: int | None = 1,
        max_step: float | None = None,
        warm_refresh: bool = True,
        start: str = "extrapolated",
        row_block: int | None = None,
        predict: bool = True,
    ) -> None:
        dt = check_time_step(dt)
        check_dtype(dtype)
        tol = DEFAULT_TOL[dtype] if tol is None else tol
        tol, max_iter = check_settings(tol, max_iter)
        if hessian not in HESSIANS:
            raise ValueError(f"unknown hessian {hessian!r}; valid: {list(HESSIANS)}")
        check_sync_every(sync_every)
        check_max_step(max_step)
        if start not in STARTS:
            raise ValueError(f"unknown start {start!r}; valid: {list(STARTS)}")
        if row_block is not None and (
            isinstance(row_block, bool) or not isinstance(row_block, numbers.Integral) or row_block < 1
        ):
            raise ValueError(f"row_block must be an integer >= 1 or None, got {row_block!r}")
        self.row_block = None if row_block is None else int(row_block)
        if not isinstance(predict, bool | np.bool_):
            raise ValueError(f"predict must be True or False, got {predict!r}")
        self.predict = bool(predict)
        self.start = start
        self.max_step = None if max_step is None else float(max_step)
        if not isinstance(warm_refresh, bool | np.bool_):
            raise ValueError(f"warm_refresh must be True or False, got {warm_refresh!r}")
        self.warm_refresh = bool(warm_refresh)
        self.dt = float(dt)
        self.dtype = dtype
        self.device = torch.device(check_device(device))
        if not (isinstance(compile, bool) or compile == "dynamic"):
            raise ValueError(f"unknown compile {compile!r}; valid: {list(COMPILES)}")
        if compile:
            check_compiler(self.device)
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        self.hessian = hessian
        if not (dense is None or isinstance(dense, bool | np.bool_)):
            raise ValueError(f"dense must be True, False or None, got {dense!r}")
        if not isinstance(warm_start, bool | np.bool_):  # NumPy's bools too, as the scene builders take them
            raise ValueError(f"warm_start must be True or False, got {warm_start!r}")
        self.dense = self.device.type == "cuda" if dense is None else bool(dense)
        self.sync_every = sync_every
        check_map_scene(subspace, scene)
        self.source_scene = scene
        # a snapshot: the rest solve reads the map the steps use, whatever the caller does to its own afterwards
        self.subspace = copy.deepcopy(subspace) if isinstance(subspace, nn.Module) else subspace
        self.scene = scene.to(device=self.device, dtype=dtype)
        factory = callable(energy) and not isinstance(energy, LatentEnergy)
        if factory:  # e.g. cubature_energy
            energy = energy(scene, subspace, dtype=dtype, device=self.device)
        if energy is not None and not isinstance(energy, LatentEnergy):
            raise ValueError(f"energy must be a LatentEnergy, a factory of one, or None; got {energy!r}")
        if energy is not None:
            self._check_energy_placement(energy, factory)
        self.energy: LatentEnergy = (
            MapEnergy(scene, subspace, dtype=dtype, device=self.device) if energy is None else energy
        )
        if hessian == "gauss_newton" and getattr(self.energy, "q_energy", None) is None:
            raise ValueError(
                f"hessian='gauss_newton' needs an energy with q_energy(q, cond) (e.g. MapEnergy); "
                f"{type(self.energy).__name__} has none: choose another hessian (e.g. {DEFAULT_HESSIAN!r})"
            )
        self.latent_dim = int(self.energy.latent_dim)
        self.reduced = isinstance(self.energy, ReducedInertia)
        self._rest: Tensor | None = None
        self._build_constants()
        self._phi = self._phi_eager
        self.compiled = compile is True  # static shapes: a call pads to the whole batch
        self._compile(compile == "dynamic")
        self.warm_start = bool(warm_start)
        self.evaluations = Evaluations()
        """Value-and-gradient calls and rows so far (:class:`Evaluations`; assign a new one to restart the count)."""
        self.roundoff_tol = self._gradient_roundoff() / (self.jacobian_norm * self.base_force)
        """The relative gradient norm |dPhi/dz| / (|J_0|_2 F_b) that the dtype's round-off alone gives at the map's
        origin (measured, not estimated: :meth:`_gradient_roundoff`); a ``tol`` below it is met only where the
        round-off happens to be small, and the stepper warns at construction. NaN where the probe was not finite."""
        if self.tol < self.roundoff_tol:
            warnings.warn(
                f"{self.dtype}'s round-off in the reduced force, measured at the map's origin, is "
                f"{self.roundoff_tol:.3g} of the force scale, {self.roundoff_tol / self.tol:.3g}x tol {self.tol:g}: "
                "solves cannot resolve their gradient to tol, so steps take many iterations and may end unconverged "
                f"at max_iter={self.max_iter} (StepStats.converged, an env's info['converged'], False); use "
                "dtype=torch.float64 (envs: dtype='float64') or a tol a few times that (docs/runtime.md, 'Tolerance')",
                stacklevel=2,
            )

    def __getstate__(self) -> dict[str, object]:
        """The attributes less the compiled callables: closures over this stepper's own ``_phi_eager``, so a
        ``copy.deepcopy`` kept calling the original's (its map and scene, not the copy's) and a pickle failed;
        :meth:`__setstate__` compiles the copy's own (the eager stepper's state is unchanged)."""
        state = dict(self.__dict__)
        state["_compiled_call"] = self._compiled_call is not None  # compile="dynamic"
        state["_phi_fast"] = None
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        self.__dict__.update(state)
        self._compile(bool(state["_compiled_call"]))

    def _compile(self, dynamic: bool) -> None:
        """This stepper's own compiled callables of ``_phi_eager``: ``_phi_fast`` (static shapes, ``compiled``; the
        value and gradient through torch.compile, AOTAutograd compiling the backward, the exact Hessian's double
        backward eager, as compiled graphs do not support it) and ``_compiled_call`` (``dynamic``)."""
        self._phi_fast = torch.compile(_own_frame(self._phi_eager), dynamic=False) if self.compiled else self._phi_eager
        self._compiled_call = _compiled_value_and_grad(self._phi_eager) if dynamic else None

    def _check_energy_placement(self, energy: LatentEnergy, factory: bool) -> None:
        """Refuse an energy that evaluates in another dtype or on another device than the stepper (where it says:
        its own ``dtype``/``device`` or its scene's); its first step would fail in a matmul."""
        source = energy if hasattr(energy, "dtype") else getattr(energy, "scene", None)
        their_dtype, their_device = getattr(source, "dtype", None), getattr(source, "device", None)
        if not isinstance(their_dtype, torch.dtype):
            their_dtype = None
        theirs = their_device if isinstance(their_device, torch.device) else None
        same_device = (
            theirs is None
            or theirs == self.device
            or (theirs.type == self.device.type and None in (theirs.index, self.device.index))  # "cuda" is "cuda:0"
        )
        if (their_dtype is None or their_dtype == self.dtype) and same_device:
            return
        given = "the energy factory returned" if factory else "energy is"
        raise ValueError(
            f"{given} a {type(energy).__name__} in {their_dtype} on {their_device}, but the stepper runs in "
            f"{self.dtype} on {self.device}: build it with dtype={self.dtype}, device={str(self.device)!r}, or pass "
            "a factory energy(scene, subspace, *, dtype, device) -> LatentEnergy (e.g. redsim.cubature.cubature_energy,"
            " or lambda scene, subspace, dtype, device: CubatureEnergy(scene, subspace, cubature, dtype=dtype, "
            "device=device)), which the stepper calls with its own"
        )

    # -- constants, once per scene and map --------------------------------------------------
    def _build_constants(self) -> None:
        scene, dtype, device = self.scene, self.dtype, self.device
        n = scene.free_dof_count
        # handle positions p = A q + p0 (linear in q): rows of A by one backward each
        q0 = torch.zeros(1, n, dtype=dtype, device=device, requires_grad=True)
        rows = []
        with torch.enable_grad():
            p = torch.cat([h.position(scene.full_positions(q0)) for h in scene.handles], -1) if scene.handles else None
            if p is not None:
                for j in range(p.shape[1]):
                    (row,) = torch.autograd.grad(p[0, j], q0, retain_graph=True)
                    rows.append(row[0])
        self._handle_matrix = torch.stack(rows) if rows else torch.zeros(0, n, dtype=dtype, device=device)
        self._handle_offset = p[0].detach() if p is not None else torch.zeros(0, dtype=dtype, device=device)
        self._coords = self.energy.positions
        self._coords_size = n  # the width w of the stepper's coordinates q (a reduced energy's features: theirs)
        self._mass = scene.mass_matvec
        self._handles = self.handle_positions
        self._handle_rows = self._handle_matrix
        if self.reduced:
            self._reduce_inertia()
        # force scale pieces, measured at f(0) in float64
        scene64 = self.source_scene.to(device=device, dtype=torch.float64)
        cond0 = self._default_cond(1, torch.float64)
        with torch.no_grad():
            q_ref = self.energy.positions(
                torch.zeros(1, self.latent_dim, dtype=dtype, device=device), None if cond0 is None else cond0.to(dtype)
            ).to(torch.float64)
        q_ref.requires_grad_(True)
        force = 0.0
        with torch.enable_grad():
            for term in scene64.energy_terms(q_ref, None, cond0).values():
                if term.requires_grad:
                    (g,) = torch.autograd.grad(term.sum(), q_ref, retain_graph=True, allow_unused=True)
                    force += 0.0 if g is None else float(torch.linalg.vector_norm(g))
        self.length = length_scale(scene64)
        mass = scene64.mass_matrix.coalesce()
        rows_m, cols_m = mass.indices()
        mass_diagonal = torch.linalg.vector_norm(mass.values()[rows_m == cols_m])
        self.base_force = force + float(mass_diagonal) * self.length / self.dt**2
        self._terms_force = force  # [N] the energy terms' part of base_force: their round-off scale (_value_noise)
        z0 = torch.zeros(1, self.latent_dim, dtype=dtype, device=device)
        objective = _StepObjective(self, torch.zeros(1, n, dtype=dtype, device=device), None, self._default_cond(1), z0)
        index0 = torch.zeros(1, dtype=torch.int64, device=device)
        columns = objective._jacobian(z0, index0, self.energy.positions)[:, 0].to(torch.float64)
        self.jacobian_norm = float(torch.linalg.matrix_norm(columns, 2)) or 1.0
        self._eps = float(torch.finfo(dtype).eps)
        self.acceleration_resolution = self.tol * self.base_force / float(mass_diagonal)
        """[m/s^2] tol F / |diag M|_2: an acceleration the same at every node that is smaller is not felt (a step
        ends at its start); one the map projects weakly needs more. Grows as 1 / dt^2
        (docs/runtime.md, "Tolerance")."""
        handle_jacobian = self._handle_matrix.to(torch.float64) @ columns.T  # dp/dz at z = 0 [H D, d]
        D, F = scene.dim, self.tol * self.jacobian_norm * self.base_force
        blocks = [handle_jacobian[h * D : (h + 1) * D] for h in range(len(scene.handles))]
        gains = [float(torch.linalg.matrix_norm(block, 2)) for block in blocks]
        self.load_resolution = torch.tensor([F / g if g > 0.0 else math.inf for g in gains], dtype=torch.float64)
        """[N] per handle [H]: tol |J_0|_2 F / |dp_h/dz|_2 at z = 0, the smallest load on handle h (along the direction
        the map moves it most) that a step can feel; a smaller one ends the step where it starts."""
        if self.acceleration_resolution > RESOLUTION_WARNING:
            warnings.warn(
                f"{self.dtype} at dt={self.dt:g} s resolves accelerations only to "
                f"{self.acceleration_resolution:.3g} m/s^2 (tol {self.tol:g}) at best: smaller forces are not felt, a "
                "step ends where it starts, and a load on one handle needs more; use dtype=torch.float64 (envs: "
                "dtype='float64') or a longer dt (docs/runtime.md, 'Tolerance')",
                stacklevel=3,
            )
        if self.tol < ROUNDOFF_TOL * self._eps:
            warnings.warn(
                f"tol {self.tol:g} is below what {self.dtype}'s round-off lets a solve reach on some scenes "
                f"(~{ROUNDOFF_TOL * self._eps:.2g}): steps may run max_iter={self.max_iter} iterations and end "
                "unconverged (StepStats.converged, an env's info['converged'], False); use a larger tol or "
                "dtype=torch.float64 (envs: dtype='float64') (docs/runtime.md, 'Tolerance')",
                stacklevel=3,
            )

    def _gradient_roundoff(self) -> float:
        """The round-off of dPhi/dz [unit of dPhi/dz] at z = 0 (qbar = the coordinates there, no loads, the default
        condition), measured in the stepper's dtype by the eager gradient: the median over
        :data:`ROUNDOFF_PROBE_DIRECTIONS` seeded unit directions u of |g(z + s u) + g(z - s u) - 2 g(z)| / sqrt(6),
        s = :data:`ROUNDOFF_PROBE_ULPS` eps, in one call. The exact gradient's change is odd in s (cancels) up to a
        term of order s^2; round-off at the three points is independent (the map's layers round differently), so
        this is its size at one point (a batched call's: a one-row call may round worse). It is what limits a solve.
        The barely fitted cantilever map of ``redsim bench scaling`` at k = 6 (float32, tol 1e-6) reads 2.6e-6 here,
        6.5e-6 with its 144-element cubature; against the float64 gradient at the same z the error is 2-3 times tol
        (cubature: 5-10 times in a batch, 21 in one-row calls), its float32 steps take 4-10 and 19-50 iterations
        (2 of 6 cubature steps end unconverged at 50) where float64 takes 1. The shipped envs read 0.004-0.04 times
        their tol in float32 (each id at gym.make; tests/runtime/test_gradient_roundoff.py). NaN where the gradient
        there is not finite.

        The elastic forces' round-off is not eps |forces| (at rest they are zero): f's rounding of q, felt through
        the elements' stiffness, dominates it (the cantilever map at k = 6, all elements: 3.0 times tol of the 3.3),
        then the energy's own evaluation at the same q (0.9 times tol); the float32 backward through the map adds
        1e-4 times tol. Against the inertia scale |diag M|_2 L / h^2 of F_b it grows with mesh refinement and h^2.
        """
        d, count = self.latent_dim, ROUNDOFF_PROBE_DIRECTIONS
        generator = torch.Generator().manual_seed(0)
        u = torch.randn(count, d, generator=generator, dtype=torch.float64)
        u = (u / torch.linalg.vector_norm(u, dim=-1, keepdim=True).clamp_min(1e-300)).to(self.dtype).to(self.device)
        step = ROUNDOFF_PROBE_ULPS * self._eps
        z = torch.cat([torch.zeros(1, d, dtype=self.dtype, device=self.device), step * u, -step * u])
        cond = self._default_cond(z.shape[0])
        with torch.no_grad():
            qbar = self._coords(z[:1], None if cond is None else cond[:1]).expand(z.shape[0], -1)
        _, grad, _ = self._eager_value_and_grad(z, qbar, None, cond)
        grad = grad.detach().to(torch.float64)
        second = grad[1 : 1 + count] + grad[1 + count :] - 2.0 * grad[:1]
        noise = float(torch.linalg.vector_norm(second, dim=-1).median()) / math.sqrt(6.0)
        return noise if math.isfinite(noise) else math.nan

    def _reduce_inertia(self) -> None:
        """Coordinates r with q = r W^T + b: mass W^T M W, |M v| by W^T M^2 W, handles A W r + (A b + p0)."""
        energy: ReducedInertia = self.energy  # type: ignore[assignment]
        weight = energy.output_weight.to(device=self.device, dtype=torch.float64)
        bias = energy.output_bias.to(device=self.device, dtype=torch.float64)
        mass_w = self.source_scene.to(device=self.device, dtype=torch.float64).mass_matvec(weight.T)  # (M W)^T [w, n]
        gram = (mass_w @ weight).to(self.dtype)
        gram_sq = (mass_w @ mass_w.T).to(self.dtype)
        handles = self._handle_matrix.to(torch.float64)
        handle_matrix = (handles @ weight).to(self.dtype)
        handle_offset = (handles @ bias).to(self.dtype) + self._handle_offset
        self._coords = energy.features
        self._coords_size = weight.shape[1]
        # partials of module functions, not lambdas: a local lambda does not pickle (the envs rebuild their stepper
        # from their arguments, but a user's pickle or multiprocessing of a stepper does not), and deepcopy shared it
        self._mass = functools.partial(_times, matrix=gram)
        self._mass_norm = functools.partial(_gram_norm, gram_sq=gram_sq)
        self._handles = functools.partial(_affine, matrix=handle_matrix, offset=handle_offset)
        self._handle_rows = handle_matrix

    def _value_noise(self, moving: Tensor) -> Tensor:
        """Phi's round-off [J] [B] for the inertia and loads' force scale ``moving`` [B] [N]: 100 eps (F_E + moving) L,
        F_E the energy terms' forces at f(0) (``base_force`` less |diag M| L / h^2: the inertia force of a whole scene
        length per step is a scale for the gradient's threshold, not a term of Phi, and made this 2,000-7,000x the
        float32 round-off of Phi on the chains, the cloth and Stewart, so the line search took uphill trials)."""
        return 100.0 * self._eps * (self._terms_force + moving) * self.length

    def _kinetic_roundoff(self, q: Tensor, kinetic_now: Tensor, kinetic_next: Tensor) -> Tensor:
        """Round-off [B] [J] of K_t + K_{t+1} (each [B] [J]): each q carries eps |q|_M of it, and K = |dq|_M^2 /
        (2 h^2) divides it by h^2 (at a tiny h, the size of any energy change)."""
        delta = 2.0 * self._eps * torch.sqrt((q * self._mass(q)).sum(-1).clamp_min(0.0))  # |dq|_M's round-off
        moved = (torch.sqrt(2.0 * kinetic_now.clamp_min(0.0)) + torch.sqrt(2.0 * kinetic_next.clamp_min(0.0))) * self.dt
        return delta * (moved + delta) / self.dt**2

    def _mass_norm(self, v: Tensor, mv: Tensor) -> Tensor:
        """|M v| [B] of coordinate velocities v [B, n], given mv = self._mass(v)."""
        return torch.linalg.vector_norm(mv, dim=-1)

    def _default_cond(self, batch: int, dtype: torch.dtype | None = None) -> Tensor | None:
        space = self.scene.condition_space
        if space is None:
            return None
        return space.default.to(device=self.device, dtype=dtype or self.dtype).unsqueeze(0).expand(batch, -1)

    def _energy_coords(self, z: Tensor, cond: Tensor | None) -> tuple[Tensor, Tensor]:
        """E [k] and the stepper's coordinates q [k, n] of z [k, d]: the free DOFs, or an energy's features r
        (reduced inertia)."""
        if self.reduced:
            return self.energy.energy_features(z, cond)  # type: ignore[attr-defined]
        energy, q = self.energy.energy(z, cond)
        return energy, self.energy.positions(z, cond) if q is None else q

    def _inertia_loads(self, energy: Tensor, q: Tensor, qbar: Tensor, loads: Tensor | None) -> tuple[Tensor, Tensor]:
        """Phi [k] = E + |q - qbar|^2_M / (2 h^2) - loads . p(q) from E [k] and q [k, n], and dPhi/dq - dE/dq
        [k, n] = M (q - qbar) / h^2 - A^T loads in closed form (M symmetric, the handles p = A q + p0 affine)."""
        d = q - qbar
        md = self._mass(d)
        value = energy + (0.5 / self.dt**2) * (d * md).sum(-1)
        force = md * (1.0 / self.dt**2)
        if loads is not None:
            value = value - (loads * self._handles(q)).sum(-1)
            force = force - loads @ self._handle_rows
        return value, force

    def _phi_eager(self, z: Tensor, qbar: Tensor, loads: Tensor | None, cond: Tensor | None) -> tuple[Tensor, Tensor]:
        """Phi [k] and E [k] of z [k, d] with inertial targets qbar [k, n], loads [k, H*D] and cond [k, m]
        (differentiable in z to any order; :meth:`_StepObjective._value_and_grad` takes a shorter way)."""
        energy, q = self._energy_coords(z, cond)
        return self._inertia_loads(energy, q, qbar, loads)[0], energy

    def _eager_value_and_grad(
        self, z: Tensor, qbar: Tensor, loads: Tensor | None, cond: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Phi [k], dPhi/dz [k, d] and E [k] of z [k, d], eager: autograd through E and q only; the inertia and load
        terms' gradient in q is closed form (fewer graph nodes per call: 1.03-1.12x per call on Klann, Chain, Stewart
        and ConditionalBar-v1, docs/env-speed.md, "Stop 24's per-call changes")."""
        z = z.detach().requires_grad_(True)
        with torch.enable_grad():
            energy, q = self._energy_coords(z, cond)
        value, force = self._inertia_loads(energy.detach(), q.detach(), qbar, loads)
        pairs = [(t, g) for t, g in ((energy, torch.ones_like(energy)), (q, force)) if t.requires_grad]
        if not pairs:  # neither depends on z
            return value, torch.zeros_like(z), energy.detach()
        outputs, seeds = zip(*pairs, strict=True)
        (grad,) = torch.autograd.grad(outputs, z, seeds, allow_unused=True)
        return value, torch.zeros_like(z) if grad is None else grad, energy.detach()

    def handle_positions(self, q: Tensor) -> Tensor:
        """Handle positions [B, H*D] [m] of free configurations q [B, n] (linear in q)."""
        return q @ self._handle_matrix.T + self._handle_offset

    # -- inputs -----------------------------------------------------------------------------
    def _latents(self, z: Tensor, what: str) -> Tensor:
        z = as_numbers(z, what, f"[B, {self.latent_dim}]", device=self.device)
        if z.ndim != 2 or z.shape[1] != self.latent_dim:
            raise ValueError(f"{what} must have shape [B, {self.latent_dim}], got {tuple(z.shape)}")
        z = z.to(self.dtype).detach()  # checked after the cast; never part of the caller's autograd graph
        if not bool(torch.isfinite(z).all()):
            raise ValueError(f"{what} must be finite in the stepper's {self.dtype}{_bad_rows(z)}")
        return z

    def _cond(self, cond: Tensor | None, batch: int) -> Tensor | None:
        space = self.scene.condition_space
        if space is None:
            if cond is not None:
                raise ValueError(f"scene {self.scene.name!r} has no condition space, but a condition was given")
            return None
        if cond is None:
            return self._default_cond(batch)
        cond = as_numbers(cond, "cond", f"[{batch}, {space.dim}]", device=self.device)
        if cond.shape != (batch, space.dim):
            raise ValueError(
                f"cond must have shape [{batch}, {space.dim}] ({list(space.names)}), got {tuple(cond.shape)}"
            )
        cond = cond.to(self.dtype).detach()  # checked after the cast, as z and loads: 1e40 is inf in float32
        if not bool(torch.isfinite(cond).all()):
            raise ValueError(f"cond must be finite in the stepper's {self.dtype}{_bad_rows(cond)}")
        return cond

    def _loads(self, loads: LoadsLike, batch: int) -> Tensor | None:
        if loads is None:
            return None
        H, D = len(self.scene.handles), self.scene.dim
        if isinstance(loads, Mapping):  # {handle: force}, as scene.energy takes it
            loads = self.scene.pack_loads(loads, batch)
        loads = as_numbers(loads, "loads", f"[{batch}, {H}, {D}] or [{H}, {D}]", device=self.device)
        if loads.shape == (H, D):  # one set of loads for every state
            loads = loads.expand(batch, H, D)
        if loads.shape != (batch, H, D):
            raise ValueError(
                f"loads must have shape [{batch}, {H}, {D}] or [{H}, {D}] (handles {list(self.scene.handle_names)}), "
                f"got {tuple(loads.shape)}"
            )
        # checked after the cast (1e100 is inf in float32); detached: a carry's force made from a loads tensor that
        # requires grad kept the caller's autograd graph alive in every step's stats.carry
        loads = loads.to(self.dtype).detach()
        if not bool(torch.isfinite(loads).all()):
            raise ValueError(f"loads must be finite in the stepper's {self.dtype} [N]{_bad_rows(loads)}")
        return loads.reshape(batch, H * D)

    # -- public -----------------------------------------------------------------------------
    @property
    def carry_size(self) -> int:
        """Columns k of :attr:`StepStats.carry`: 2 d + m + 1 + w (m the scene's condition size, 0 without one; w the
        stepper's coordinates: the free DOFs n, or a reduced energy's features)."""
        space = self.scene.condition_space
        return 2 * self.latent_dim + 1 + (0 if space is None else space.dim) + self._coords_size

    def positions(self, z: Tensor, cond: Tensor | None = None) -> Tensor:
        """Free DOFs q = f(z) [B, n] of latents z [B, d] (``scene.full_positions(q)`` draws them)."""
        z = self._latents(z, "z")
        with torch.no_grad():
            return self.energy.positions(z, self._cond(cond, z.shape[0]))

    def step(
        self,
        z: Tensor,
        z_prev: Tensor,
        loads: LoadsLike = None,
        cond: Tensor | None = None,
        *,
        warm: Tensor | None = None,
        carry: Tensor | None = None,
    ) -> tuple[Tensor, StepStats]:
        """One implicit-Euler step of every state.

        Every input may be a tensor of any real dtype on any device, a NumPy array or a nested list: it is read in the
        stepper's dtype and device (float64 numbers rounded to float32 by a float32 stepper), and none is modified.

        Args:
            z: Latents at time t, [B, d] (a batch of one is [1, d]; an unbatched [d] is refused).
            z_prev: Latents at time t - h, [B, d].
            loads: Forces [N] on the scene's handles (held during the step): a tensor [B, H, D] in handle order (or
                [H, D], the same loads for every state, as ``scene.energy`` broadcasts them), a mapping
                ``{handle: force}`` with each force [D] or [B, D] (absent handles get none; as
                :meth:`redsim.scene.Scene.pack_loads` and ``scene.energy`` take it), or None.
            cond: Scene conditions [B, m] (default: the scene's default condition), or None.
            warm: The previous step's ``stats.model`` [B, d, d] of the same states, or None. With it
                the quasi-Newton models start from it instead of building a Hessian (the default
                "lagged_fd" saves d gradient evaluations a step; rows with a NaN build their own).
                The result is the same solve, to the tolerance.
            carry: The previous step's ``stats.carry`` of the same states, or None. A row whose key (that step's
                z_next and condition) equals this step's z and cond bitwise has Phi and dPhi/dz at z_t from it (E,
                and the last dPhi/dz plus dq/dz^T times the change of the inertia and load force: one backward pass
                through the map's coordinates), so the step's first call evaluates the energy at the extrapolated
                start only; other rows (NaN, another z: a reset, a periodic latent turned by 2 pi) are evaluated. The
                same step, to round-off.

        Returns:
            z_next [B, d] (never NaN: a state that failed keeps its best finite iterate) and the
            :class:`StepStats`.

        Raises:
            ValueError: a z, z_prev, loads, cond, warm or carry that is not an array of real numbers, a wrong shape
                or a non-finite z, z_prev, loads or cond, or an unknown handle in a loads mapping (nothing is
                stepped).
        """
        z = self._latents(z, "z")
        z_prev = self._latents(z_prev, "z_prev")
        batch = z.shape[0]
        if z_prev.shape[0] != batch:
            raise ValueError(f"z and z_prev must have the same batch size, got {batch} and {z_prev.shape[0]}")
        loads_t = self._loads(loads, batch)
        cond_t = self._cond(cond, batch)
        d = self.latent_dim
        if warm is not None:  # checked even where warm_start=False ignores it: a wrong one is a caller's mistake
            warm = as_numbers(warm, "warm", f"[{batch}, {d}, {d}]", device=self.device)
            if warm.shape != (batch, d, d):
                raise ValueError(
                    f"warm must have shape [{batch}, {d}, {d}] (a step's stats.model), got {tuple(warm.shape)}"
                )
            warm = warm.to(self.dtype) if self.warm_start else None
        known = self._reusable(carry, z, cond_t)
        z_grad = z.detach().requires_grad_(known is not None)  # a carry's Phi(z_t) takes dq/dz^T there
        with torch.no_grad():
            with torch.set_grad_enabled(known is not None):
                both = self._coords(torch.cat([z_grad, z_prev]), None if cond_t is None else cond_t.repeat(2, 1))
                q_graph = both[:batch]
            q_t, q_prev = q_graph.detach(), both[batch:].detach()
            velocity = q_t - q_prev
            qbar = q_t + velocity
            m_v = self._mass(velocity)
            moving = self._mass_norm(velocity, m_v) / self.dt**2  # [N] the inertia and loads' force scale [B]
            if loads_t is not None:
                moving = moving + torch.linalg.vector_norm(loads_t, dim=-1)
            force = self.base_force + moving
            z0 = 2.0 * z - z_prev
            objective = _StepObjective(self, qbar, loads_t, cond_t, z0)
            # Phi at the extrapolated start and at z_t: the start of the solve, a secant pair for
            # the quasi-Newton models, and Phi(z_t) for the diverged flag (one call; at z_t from the carry where
            # it holds the last step's E, dPhi/dz and force there)
            first, at_z, z0 = self._start(objective, z0, z, known, (z_grad, q_graph), warm)
            noise = self._value_noise(moving)
            # from z_t where the extrapolated start is not finite (a finite step may still exist), and with
            # start "lower" where Phi(z_t) is lower (from z_t the secant pair is empty: the solver skips its update)
            lower = ~(torch.isfinite(first[0]) & torch.isfinite(first[1]).all(-1))
            if self.start == "lower":
                lower = lower | (at_z[0] < first[0])
            z0 = torch.where(lower[:, None], z, z0)
            first = (
                torch.where(lower, at_z[0], first[0]),
                torch.where(lower[:, None], at_z[1], first[1]),
                torch.where(lower, at_z[2], first[2]),
            )
            result = minimize(
                objective,
                z0,
                self.jacobian_norm * force,
                noise,
                tol=self.tol,
                max_iter=self.max_iter,
                hessian=self.hessian,
                dense=self.dense,
                sync_every=self.sync_every,
                max_step=self.max_step,
                warm_refresh=self.warm_refresh,
                start=first,
                secant=(z, at_z[1]),
                warm=warm,
            )
            result = self._restart_worse(objective, result, z, at_z, force, noise)
            z_next = torch.where(result.finite[:, None], result.z, z)
            q_next = self._coords(z_next, cond_t)
            step_velocity = q_next - q_t
            kinetic_next = 0.5 * (step_velocity * self._mass(step_velocity)).sum(-1) / self.dt**2
            offset = q_next - qbar
            kinetic_now = 0.5 * (velocity * m_v).sum(-1) / self.dt**2
            diverged = ~result.finite | diverged_states(
                at_z[0],
                result.value,
                kinetic_now,
                kinetic_next,
                0.5 * (offset * self._mass(offset)).sum(-1) / self.dt**2,
                force * self.length,
                noise + self.tol * force * self.length,
            )
            work = torch.zeros_like(kinetic_now)  # of the loads over the step [J]
            if loads_t is not None:
                work = (loads_t * (self._handles(q_next) - self._handles(q_t))).sum(-1)
            mechanical_now = kinetic_now + at_z[2]
            energy_next = torch.where(result.finite, result.energy, at_z[2])  # the solver zeroes a non-finite one
            mechanical_next = kinetic_next + energy_next
            balance = (
                mechanical_now,
                mechanical_next,
                work,
                result.grad_norm * torch.linalg.vector_norm(z_next - z, dim=-1)
                + self._kinetic_roundoff(q_t, kinetic_now, kinetic_next),
                self._eps,
            )
            energy_gain = energy_gain_states(*balance)
            gain_tolerance = energy_gain_tolerance(*balance)
        # a force scale past the dtype's range (finite loads too large to square) makes every threshold inf:
        # such a step proves nothing, so it is reported as not converged and diverged
        # (its residual and energy-gain tolerance inf, not the 0 or NaN that dividing by an inf scale gives)
        unbounded = ~torch.isfinite(force)
        converged = result.converged & ~unbounded
        unsolved = unbounded | ~result.finite  # no residual to report: inf, not the 0 of the zeroed gradient
        stats = StepStats(
            converged=converged,
            iterations=result.iterations,
            residual=(result.grad_norm / (self.jacobian_norm * force)).masked_fill(unsolved, math.inf),
            energy=energy_next,
            out_of_range=out_of_range_states(
                torch.stack([z, z_next], 1), self.energy.periodic, cond_t, self.scene.condition_space
            ),
            diverged=diverged | unbounded,
            energy_gain=energy_gain,
            model=result.model,
            energy_gain_tolerance=gain_tolerance.masked_fill(unbounded | ~torch.isfinite(gain_tolerance), math.inf),
            stalled=result.stalled & ~unbounded,
            carry=self._carry(
                z_next, cond_t, result, self._inertia_loads(result.energy, q_next, qbar, loads_t)[1], converged
            ),
        )
        return z_next, stats

    def _reusable(self, carry: Tensor | None, z: Tensor, cond: Tensor | None) -> Tensor | None:
        """The last step's (E, dPhi/dz, force) at z_t [B, 1 + d + w] from a ``carry`` of :meth:`step` whose rows are
        keyed by z [B, d] and cond [B, m] (NaN rows: evaluate them), or None where no row is (or the stepper is
        compiled with static shapes, whose first call evaluates every row at both points anyway).

        Raises:
            ValueError: a carry that is not an array of real numbers of shape [B, :attr:`carry_size`].
        """
        if carry is None:
            return None
        key = z if cond is None else torch.cat([z, cond], -1)
        batch, width = z.shape[0], self.carry_size
        carry = as_numbers(carry, "carry", f"[{batch}, {width}]", device=self.device)
        if carry.shape != (batch, width):
            raise ValueError(f"carry must have shape [{batch}, {width}] (a step's carry), got {list(carry.shape)}")
        carry = carry.to(self.dtype)
        if self.compiled:
            return None
        known = carry[:, key.shape[1] :]
        holds = (carry[:, : key.shape[1]] == key).all(-1) & torch.isfinite(known).all(-1)
        if not bool(holds.any()):
            return None
        return known.masked_fill(~holds[:, None], torch.nan)

    def _start(
        self,
        objective: _StepObjective,
        z0: Tensor,
        z: Tensor,
        known: Tensor | None,
        coords: tuple[Tensor, Tensor],
        warm: Tensor | None,
    ) -> tuple[tuple[Tensor, Tensor, Tensor], tuple[Tensor, Tensor, Tensor], Tensor]:
        """(Phi, dPhi/dz, E) at the starts [B], [B, d], [B], the same at z_t (both [B, d]), and the starts [B, d].

        At z_t from ``known`` (:meth:`_reusable`) where it holds the last step's E, dPhi/dz and force dPhi/dq - dE/dq
        there: Phi = E + this step's inertia and load terms, dPhi/dz = the last one's + dq/dz^T (this force - the
        last), through ``coords`` (z_t [B, d] and its coordinates q [B, w] in autograd); the other rows with the
        starts in one call. With :attr:`predict`, a state with both that and a ``warm`` model [B, d, d] starts from
        the model's Newton step from z_t (:func:`redsim.runtime.solver.newton_step`, at most ``max_step`` long),
        the others from z0 [B, d] (2 z_t - z_{t-1})."""
        batch, d = z.shape
        if known is None:
            value, grad, energy = objective.start(z0, z)
            return (value[:batch], grad[:batch], energy[:batch]), (value[batch:], grad[batch:], energy[batch:]), z0
        rows = torch.arange(batch, device=z.device)
        have = torch.isfinite(known[:, 0])
        fresh, kept = rows[~have], rows[have]
        z_grad, q = coords
        loads = None if objective.loads is None else objective.loads[kept]
        kept_energy = known[kept, 0]
        kept_value, force = self._inertia_loads(kept_energy, q[kept].detach(), objective.qbar[kept], loads)
        change = torch.zeros_like(q).index_copy_(0, kept, force - known[kept, 1 + d :])
        (moved,) = torch.autograd.grad(q, z_grad, change, allow_unused=True)  # None: q does not depend on z
        kept_grad = known[kept, 1 : 1 + d] + (0.0 if moved is None else moved[kept])
        if self.predict and warm is not None and self.hessian != "gauss_newton":
            step, usable = newton_step(warm[kept], kept_grad, self.max_step)
            z0 = z0.index_copy(0, kept, torch.where(usable[:, None], z[kept] + step, z0[kept]))
        value, grad, energy = objective.value_and_grad(torch.cat([z0, z[fresh]]), torch.cat([rows, fresh]))
        at_z = (
            value.new_empty(batch).index_copy_(0, fresh, value[batch:]).index_copy_(0, kept, kept_value),
            grad.new_empty(batch, d).index_copy_(0, fresh, grad[batch:]).index_copy_(0, kept, kept_grad),
            energy.new_empty(batch).index_copy_(0, fresh, energy[batch:]).index_copy_(0, kept, kept_energy),
        )
        return (value[:batch], grad[:batch], energy[:batch]), at_z, z0

    def _carry(
        self, z_next: Tensor, cond: Tensor | None, result: BatchResult, force: Tensor, converged: Tensor
    ) -> Tensor:
        """:attr:`StepStats.carry` [B, :attr:`carry_size`]: (z_next, cond, E, dPhi/dz, the inertia and load terms'
        force dPhi/dq - dE/dq [B, w]) per state at the solve's end; NaN where the step did not converge (``converged``
        [B]). There the force need not balance E's, and the next step's dPhi/dz = this one + dq/dz^T (its force - this
        force) would carry the round-off of a force far above its own (a load past the dtype's range: all of it)."""
        key = z_next if cond is None else torch.cat([z_next, cond], -1)
        carry = torch.cat([key, result.energy[:, None], result.grad, force], -1)
        return carry.masked_fill(~converged[:, None], torch.nan)

    def _restart_worse(
        self,
        objective: _StepObjective,
        result: BatchResult,
        z: Tensor,
        at_z: tuple[Tensor, Tensor, Tensor],
        force: Tensor,
        noise: Tensor,
    ) -> BatchResult:
        """Solve again from z_t [B, d] the states whose solve ended above Phi(z_t); each keeps the lower minimum.

        Phi is not convex in z (a neural map, contact), so the extrapolated start 2 z_t - z_{t-1} can
        lie in a basin whose minimum is above Phi(z_t), a point every step can reach; a descent from
        z_t ends at or below it. ``at_z`` is (Phi, dPhi/dz, E) at z_t [B], [B, d], [B].
        """
        value, grad, energy = at_z
        worse = result.finite & (result.value > value + noise + self.tol * force * self.length)
        if not bool(worse.any()):
            return result
        rows = worse[:, None]
        retry = minimize(
            objective,
            torch.where(rows, z, result.z),
            self.jacobian_norm * force,
            noise,
            tol=self.tol,
            max_iter=self.max_iter,
            hessian=self.hessian,
            dense=self.dense,
            sync_every=self.sync_every,
            max_step=self.max_step,
            warm_refresh=self.warm_refresh,
            # the other states start with a zero gradient: converged at once, their result is kept below
            start=(
                torch.where(worse, value, result.value),
                torch.where(rows, grad, torch.zeros_like(grad)),
                torch.where(worse, energy, result.energy),
            ),
        )
        take = worse & retry.finite & (retry.value < result.value)
        fields = {
            name: torch.where(take.view(-1, *[1] * (old.ndim - 1)), getattr(retry, name), old)
            for name, old in vars(result).items()
        }
        fields["iterations"] = result.iterations + torch.where(worse, retry.iterations, 0)
        return BatchResult(**fields)

    def objective(
        self, candidate: Tensor, z: Tensor, z_prev: Tensor, loads: LoadsLike = None, cond: Tensor | None = None
    ) -> Tensor:
        """Phi_b [J] of candidate next latents [B, d] for the step from (z, z_prev) [B, d] under ``loads``
        ([B, H, D] or ``{handle: force}``, as :meth:`step`; what :meth:`step` minimizes, module doc): compare two
        answers to one step.

        Raises:
            ValueError: as :meth:`step`.
        """
        candidate, z, z_prev = (
            self._latents(u, what) for u, what in ((candidate, "candidate"), (z, "z"), (z_prev, "z_prev"))
        )
        batch = z.shape[0]
        if candidate.shape[0] != batch or z_prev.shape[0] != batch:  # a batch of 1 broadcast without a word
            raise ValueError(
                f"candidate, z and z_prev must have the same batch size, got {candidate.shape[0]}, {batch} and "
                f"{z_prev.shape[0]}"
            )
        loads_t, cond_t = self._loads(loads, batch), self._cond(cond, batch)
        with torch.no_grad():
            q_t = self._coords(z, cond_t)
            qbar = 2.0 * q_t - self._coords(z_prev, cond_t)
            value, _ = self._phi(candidate, qbar, loads_t, cond_t)
        return value

    def rest_latent(self, cond: Tensor | None = None, start: Tensor | None = None) -> Tensor:
        """The latent static equilibrium under zero load near z = 0: [1, d] (cond None) or [B, d] (cond [B, m]).

        Solved once per condition by the reference :func:`redsim.integrators.latent_equilibrium`: float64 Newton
        from ``start`` [d]; without one, under the default condition (``cond`` None) from the shipped map's rest
        start where it has one (:func:`redsim.pretrained.rest_start`: the same minimum on every CPU where the map's
        latent energy has near-degenerate ones), else from z = 0. Cached for the default condition without ``start``.
        A ``cond`` given, even the default one, solves from z = 0 (no conditional map ships a rest start).
        """
        if start is not None and not bool(torch.isfinite(torch.as_tensor(start, dtype=torch.float64)).all()):
            raise ValueError("start must be finite (a latent [d], [1, d] or [B, d])")
        if cond is not None or start is not None:
            return self._solve_rest(cond, start)
        if self._rest is None:
            shipped = None  # a map that is not a module (any callable) has no weights to match a shipped start
            if isinstance(self.subspace, nn.Module):
                shipped = pretrained.rest_start(self.source_scene.name, map_fingerprint(self.subspace))
            self._rest = self._solve_rest(None, shipped)
        return self._rest.clone()

    def _solve_rest(self, cond: Tensor | None, start: Tensor | None) -> Tensor:
        """:meth:`rest_latent` solved from ``start`` [d] (None: z = 0), [1, d] or [B, d]."""
        conds: list[Tensor | None] = [None]
        if cond is not None:
            try:
                shape = tuple(cond.shape) if isinstance(cond, Tensor) else np.shape(cond)
            except ValueError:  # ragged: _cond names it
                shape = ()
            conds = list(self._cond(cond, shape[0] if len(shape) == 2 else 1).to(torch.float64))  # B = 0 gives none
        out = []
        for c in conds:
            with warnings.catch_warnings():  # the constructor warned of a scene of other parameters already
                warnings.simplefilter("ignore", SceneParametersWarning)
                space = LatentSpace(
                    self.source_scene, self.subspace, cond=None if c is None or not self.energy.condition_dim else c
                )
            z, _ = latent_equilibrium(space, None, c, z0=start)
            out.append(z.to(device=self.device, dtype=self.dtype))
        return torch.stack(out) if out else torch.zeros(0, self.latent_dim, dtype=self.dtype, device=self.device)


def _times(y: Tensor, matrix: Tensor) -> Tensor:
    """y [k, w] @ matrix [w, w] (a reduced stepper's mass W^T M W)."""
    return y @ matrix


def _gram_norm(v: Tensor, _mv: Tensor, gram_sq: Tensor) -> Tensor:
    """|M v| [k] of feature velocities v [k, w] from W^T M^2 W [w, w] (``_mv`` unused: the full-space form's)."""
    return (v * (v @ gram_sq)).sum(-1).clamp_min(0.0).sqrt()


def _affine(y: Tensor, matrix: Tensor, offset: Tensor) -> Tensor:
    """Handle positions [k, H*D] of features y [k, w]: y (A W)^T + (A b + p0)."""
    return y @ matrix.T + offset


def _bad_rows(t: Tensor, shown: int = 8) -> str:
    """``": rows [i, j, ...] are not"``: the states [B, ...] of ``t`` with a non-finite entry (the first ``shown``), for
    an error message: a batch's whole step is refused for them, so name them."""
    rows = (~torch.isfinite(t.reshape(t.shape[0], -1))).any(-1).nonzero().flatten().tolist()
    more = f" and {len(rows) - shown} more" if len(rows) > shown else ""
    plural = len(rows) > 1
    return f": row{'s' if plural else ''} {rows[:shown]}{more} of {t.shape[0]} {'are' if plural else 'is'} not"


_FRAMES = itertools.count()


def _own_frame(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` behind a function whose code object is its own, for ``torch.compile``: Dynamo keeps its graphs and its
    limit of ``recompile_limit`` (8) per code object, so every stepper compiling the same function shared them, and
    past ~4 steppers in one process (2 graphs each: one row, several) the later ones silently ran uncompiled."""

    def frame(*args: Any) -> Any:
        return fn(*args)

    code = frame.__code__.replace(co_name=f"{getattr(fn, '__name__', 'fn')}_{next(_FRAMES)}")
    return types.FunctionType(code, frame.__globals__, code.co_name, None, frame.__closure__)


def _compiled_value_and_grad(
    phi: Callable[[Tensor, Tensor, Tensor | None, Tensor | None], tuple[Tensor, Tensor]],
) -> Callable[[Tensor, Tensor, Tensor | None, Tensor | None], tuple[Tensor, Tensor, Tensor]]:
    """``(z, qbar, loads, cond) -> (Phi [k], dPhi/dz [k, d], E [k])`` (detached) as one compiled graph of ``phi``
    (:meth:`LatentStepper._phi_eager`) and its gradient, the row count k dynamic.

    ``torch.autograd.grad`` is traced into the graph (Dynamo's ``trace_autograd_ops``, where this torch has it;
    elsewhere the graph breaks there and the call runs as a compiled forward and backward, 1.3-1.9x slower at 1-4 rows).
    One row is its own graph (Dynamo specialises sizes 0 and 1); every k >= 2 shares the other.
    """

    def value_and_grad(
        z: Tensor, qbar: Tensor, loads: Tensor | None, cond: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor]:
        value, energy = phi(z, qbar, loads, cond)
        if not value.requires_grad:  # Phi does not depend on z
            return value.detach(), torch.zeros_like(z), energy.detach()
        (grad,) = torch.autograd.grad(value.sum(), z)
        return value.detach(), grad, energy.detach()

    compiled = torch.compile(_own_frame(value_and_grad))
    config = torch._dynamo.config
    trace = hasattr(config, "trace_autograd_ops")

    def call(z: Tensor, qbar: Tensor, loads: Tensor | None, cond: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        z = z.detach().requires_grad_(True)
        if z.shape[0] > 1:
            for t in (z, qbar, loads, cond):
                if t is not None:
                    torch._dynamo.maybe_mark_dynamic(t, 0)
        # set around every call (read only when Dynamo traces, which any call may), the caller's value restored;
        # set directly: config.patch costs ~17 us a call, 2-3% of a compiled one-row call
        before = config.trace_autograd_ops if trace else None
        if trace:
            config.trace_autograd_ops = True
        try:
            with torch.enable_grad():
                return compiled(z, qbar, loads, cond)
        finally:
            if trace:
                config.trace_autograd_ops = before

    return call


def check_compiler(device: torch.device) -> None:
    """Refuse ``torch.compile`` on the CPU where no C++ compiler is found (Inductor builds its CPU kernels with one).

    Without this, a compiled stepper fails at its first step, deep inside torch. Other devices are not checked.

    Raises:
        RuntimeError: no compiler found (the ``CXX`` environment variable, else ``g++``, as Inductor looks).
    """
    if device.type != "cpu":
        return
    try:
        from torch._inductor.cpp_builder import get_cpp_compiler
    except ImportError:  # a torch without this helper: torch.compile reports it at the first step
        return
    try:
        get_cpp_compiler()
    except Exception as err:  # InvalidCxxCompiler, or a compiler that does not run
        raise RuntimeError(
            f"compile needs a C++ compiler on the CPU (torch.compile builds its kernels with one), and none runs "
            f"({type(err).__name__}); install g++ (or set CXX to a C++ compiler), or step without compile"
        ) from None


__all__ = [
    "COMPILES",
    "DEFAULT_HESSIAN",
    "DEFAULT_MAX_ITER",
    "DEFAULT_TOL",
    "STARTS",
    "Evaluations",
    "LatentStepper",
    "StepStats",
    "check_compiler",
]
