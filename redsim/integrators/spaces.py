"""The coordinates an integrator solves for: the full space q, or the latent z of a subspace map.

A *space* maps its coordinates u to free configurations q = space.configuration(u) and says how
q-space quantities read in u (:class:`Space`). :class:`FullSpace` is the identity (u = q, the
float64 reference); :class:`LatentSpace` solves over the latent z of a subspace map q = f(z)
(paper §3.4), providing only the map, its Newton Hessian, the pull-back of q-space matrices
(J^T A J) and how q-space force scales read in z, so both share one objective
(:mod:`redsim.integrators.objective`), minimizers and integrator.
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from redsim.scene import Scene, check_scene_type
from redsim.tensors import jvp

HESSIAN_FLOOR = 1e-8
"""Smallest eigenvalue of a latent Newton Hessian, relative to its largest (see :meth:`LatentSpace.hessian`)."""


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
        self._scene = as_float64(scene)

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
        return float(np.linalg.norm(matrix.diagonal()))


class SceneParametersWarning(UserWarning):
    """A map fitted to a scene of this name with other parameters (another fingerprint) is used on this one: a
    deliberate study (a soft material's map on a stiffer one) or a mistake the caller should see."""


def check_map_scene(subspace: object, scene: Scene) -> None:
    """Refuse a map whose metadata (``subspace.metadata["scene"]``, written by the fit) names a scene other than
    ``scene``: a map of another scene with the same n would be solved on this energy without a word. Warn
    (:class:`SceneParametersWarning`, at the line that called the constructor that calls this) where it names
    this scene with other parameters (``metadata["scene_fingerprint"]`` that ``scene`` does not accept): it is
    solved on this scene's energy. :class:`LatentSpace` and :class:`redsim.runtime.LatentStepper` both check here.

    Raises:
        TypeError: ``scene`` is not a :class:`Scene`.
        ValueError: the map was fitted to another scene.
    """
    check_scene_type(scene)
    metadata = getattr(subspace, "metadata", None) or {}
    if not isinstance(metadata, dict):
        return
    name, fingerprint = metadata.get("scene"), metadata.get("scene_fingerprint")
    if name is not None and name != scene.name:
        raise ValueError(f"the subspace was fitted to scene {name!r}, not to {scene.name!r}")
    if fingerprint is not None and not scene.accepts(fingerprint):
        warnings.warn(
            f"the subspace was fitted to scene {name!r} with other parameters (fingerprint {fingerprint}; this one "
            f"{scene.fingerprint()}): it is solved on this scene's energy",
            SceneParametersWarning,
            stacklevel=3,
        )


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
      bistable_bar shipped maps it took up to 7x fewer iterations per step (never more), each cheaper.
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
        ValueError: a map without ``latent_dim``, whose output does not have n entries, whose metadata names
            another scene (:func:`check_map_scene`), a condition for an unconditional map, or a conditional
            map without one.

    Warns:
        SceneParametersWarning: the map's metadata names this scene with other parameters (:func:`check_map_scene`).
    """

    def __init__(self, scene: Scene, subspace: Callable[..., Tensor], *, cond: Tensor | None = None) -> None:
        check_map_scene(subspace, scene)
        self._scene = as_float64(scene)
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
            if not bool(torch.isfinite(self.condition).all()):
                raise ValueError(f"the condition must be finite, got {self.condition.tolist()}")
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
        like = map_tensor(self.subspace)
        return torch.float64 if like is None else like.dtype

    @property
    def roundoff(self) -> float:
        """The unit round-off of the map's dtype (1.2e-7 for float32); 0 for a float64 map."""
        dtype = self.map_dtype
        return 0.0 if dtype == torch.float64 else float(torch.finfo(dtype).eps)

    def configuration(self, u: Tensor) -> Tensor:
        like = map_tensor(self.subspace)
        z, cond = (u, self.condition) if like is None else (u.to(like), _to(self.condition, like))
        q = self.subspace(z) if cond is None else self.subspace(z, cond)
        return q.to(device=self._scene.device, dtype=torch.float64)

    def jacobian(self, u: Tensor) -> np.ndarray:
        """J = dq/dz [n, d] at z = u [d] (float64 numpy; the last one is cached)."""
        u = u.detach()
        if self._jacobian_at is not None and torch.equal(self._jacobian_at[0], u):
            return self._jacobian_at[1]
        d = self.latent_dim
        _, columns = jvp(self.configuration, (u.expand(d, -1),), (torch.eye(d, dtype=u.dtype, device=u.device),))
        matrix = columns.T.cpu().numpy().astype(np.float64)  # row k of columns: J e_k
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
        """|J|_2 at u; inf where J is not finite (a latent the map overflows at: the step then reports that it did not
        converge, where the SVD of a non-finite J raised LinAlgError)."""
        jacobian = self.jacobian(u)
        return float(np.linalg.norm(jacobian, 2)) if np.isfinite(jacobian).all() else math.inf

    def metric_norm(self, u: Tensor, matrix: Any) -> float:
        """|A J|_F."""
        return float(np.linalg.norm(np.asarray(matrix @ self.jacobian(u))))


def map_condition_dim(subspace: Any) -> int:
    """Size of the condition c a map takes: ``subspace.config.condition_dim`` if it has one, else 0."""
    return int(getattr(getattr(subspace, "config", None), "condition_dim", 0))


def as_float64(scene: Scene) -> Scene:
    """The scene itself if it is float64, else a float64 copy (where reference solves run); a TypeError for what is
    not a :class:`Scene` (a scene's name)."""
    check_scene_type(scene)
    return scene if scene.dtype == torch.float64 else scene.to(dtype=torch.float64)


def map_tensor(subspace: Any) -> Tensor | None:
    """A map's first floating parameter or buffer (its dtype and device), or None (inputs are left as they are)."""
    if isinstance(subspace, torch.nn.Module):
        for tensor in itertools.chain(subspace.parameters(), subspace.buffers()):
            if tensor.is_floating_point():
                return tensor
    return None


def _to(value: Tensor | None, like: Tensor) -> Tensor | None:
    return None if value is None else value.to(like)
