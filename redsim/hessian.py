"""Second derivatives of a scene's energy: per-element Hessians and their sparse assembly.

Every effect is a sum over independent elements (:mod:`redsim.effects.base`), so the
Hessian of the energy with respect to the full configuration x is a sum of small dense
blocks, one [k, k] block per element on the k entries ``element_dofs`` it reads. The blocks
come from autograd, all elements at once: the gathered entries are repeated over the
batch dimension, one copy per Hessian row, so a single double-backward pass yields the
rows of every element (elements are independent, so row j of element t only sees copy j
of element t).

"Projected Newton" replaces each block by its nearest positive semi-definite matrix
(eigenvalues clamped at 0) before assembly, which makes the assembled matrix PSD. The
assembled matrix lives over the free DOFs q: entries on pinned DOFs are dropped, and
entries on repeated indices are summed, which is exactly P^T H_e P for the gather P.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import torch
from torch import Tensor

from redsim.effects.base import Effect
from redsim.scene import LoadsLike, Scene

DEFAULT_PASS_ENTRIES = 1 << 20
"""Largest number of gathered entries (rows x elements x k) differentiated in one pass."""


def project_psd(blocks: Tensor) -> Tensor:
    """The nearest positive semi-definite matrices (in Frobenius norm) of symmetric blocks.

    Args:
        blocks: Symmetric matrices, shape [..., k, k]; only their symmetric part is used.

    Returns:
        V max(w, 0) V^T with (w, V) the eigen-decomposition of each block, shape [..., k, k].
    """
    sym = 0.5 * (blocks + blocks.transpose(-1, -2))
    w, V = torch.linalg.eigh(sym)
    return (V * w.clamp_min(0.0).unsqueeze(-2)) @ V.transpose(-1, -2)


def _local_hessians(
    effect: Effect,
    x: Tensor,
    cond: Tensor | None,
    loads: Tensor | None,
    max_pass_entries: int,
) -> Tensor | None:
    """Per-element Hessians [T, k, k], or None when the effect is affine in x (zero Hessian).

    An element whose second derivatives are not finite at finite coordinates gets a zero block: its energy is not
    twice differentiable there (a collapsed bending hinge, zero-length edge or apex on the edge line, has no
    dihedral angle; autograd's atan2 gives a zero gradient and NaN curvature at (0, 0)), and a Newton model without
    that element's curvature still descends, where a NaN block made the projected step's eigh fail.

    Args:
        effect: The energy term.
        x: One full configuration, shape [N].
        cond: Packed condition, shape [1, m], or None.
        loads: Packed loads, shape [1, H, D], or None.
        max_pass_entries: Bound on rows x T x k per autograd pass.
    """
    xe0 = x.detach()[effect.element_dofs]  # [T, k]
    T, k = xe0.shape
    out = xe0.new_zeros(T, k, k)
    if T == 0:
        return None
    rows_per_pass = max(1, min(k, max_pass_entries // max(1, T * k)))
    for start in range(0, k, rows_per_pass):
        rows = torch.arange(start, min(k, start + rows_per_pass), device=xe0.device)
        count = int(rows.numel())
        xe = xe0.unsqueeze(0).expand(count, T, k).clone().requires_grad_(True)
        cond_b = None if cond is None else cond.expand(count, -1)
        loads_b = None if loads is None else loads.expand(count, -1, -1)
        with torch.enable_grad():
            energy = effect.element_energy(xe, cond_b, loads_b).sum()
            if not energy.requires_grad:
                return None
            (grad,) = torch.autograd.grad(energy, xe, create_graph=True, allow_unused=True)
            if grad is None or not grad.requires_grad:
                return None
            picked = grad[torch.arange(count, device=xe0.device), :, rows]  # [count, T]: d E_t / d xe[t, row]
            (rows_h,) = torch.autograd.grad(picked.sum(), xe, allow_unused=True)
        if rows_h is not None:
            out[:, start : start + count, :] = rows_h.transpose(0, 1)
    undefined = ~out.isfinite().all(dim=(1, 2)) & xe0.isfinite().all(dim=1)
    if bool(undefined.any()):
        out[undefined] = 0.0
    return out


def element_hessians(
    effect: Effect,
    x: Tensor,
    cond: Tensor | None = None,
    loads: Tensor | None = None,
    *,
    project: bool = False,
    max_pass_entries: int = DEFAULT_PASS_ENTRIES,
) -> Tensor:
    """Hessian of each element's energy with respect to its gathered entries.

    Args:
        effect: The energy term; its elements read ``effect.element_dofs`` [T, k].
        x: One full configuration [m, or 1 for affine-body entries], shape [N] or [1, N].
        cond: Packed condition vector, shape [1, m] (see :meth:`Scene.pack_condition`), or None.
        loads: Packed loads [N], shape [1, H, D] (see :meth:`Scene.pack_loads`), or None.
        project: Clamp each block's eigenvalues at 0 (projected Newton).
        max_pass_entries: Memory bound: at most this many gathered entries (Hessian rows x T x k)
            are differentiated in one autograd pass; more rows are done in several passes.

    Returns:
        d^2 E_t / d xe_t^2 [J per unit^2], shape [T, k, k] (zeros for affine terms).
    """
    x = _single_configuration(x)
    if max_pass_entries < 1:
        raise ValueError(f"max_pass_entries must be >= 1, got {max_pass_entries}")
    blocks = _local_hessians(effect, x, cond, loads, max_pass_entries)
    if blocks is None:
        T, k = effect.element_dofs.shape
        return x.new_zeros(T, k, k)
    return project_psd(blocks) if project else blocks


def energy_hessian(
    scene: Scene,
    q: Tensor,
    loads: LoadsLike = None,
    cond: Tensor | None = None,
    *,
    project: bool = True,
    max_pass_entries: int = DEFAULT_PASS_ENTRIES,
) -> scipy.sparse.csr_matrix:
    """The Hessian of ``scene.energy`` over the free DOFs, assembled from element blocks.

    Affine terms (gravity, external loads) are detected by autograd (their gradient does not
    depend on x) and skipped. Exact zeros (e.g. entries of fixed world points, which read
    x[0] with weight 0) are not stored.

    Args:
        scene: The scene.
        q: One free configuration, shape [n] or [1, n].
        loads: Loads as accepted by :meth:`Scene.pack_loads` (batch 1), or None.
        cond: Condition as accepted by :meth:`Scene.pack_condition` (batch 1), or None.
        project: Project every element block to PSD first (projected Newton); then the
            result is positive semi-definite.
        max_pass_entries: Memory bound per autograd pass, see :func:`element_hessians`.

    Returns:
        d^2 E / dq^2, float64 CSR of shape [n, n], duplicates summed.
    """
    n = scene.free_dof_count
    q = q.reshape(1, -1) if q.ndim == 1 else q
    if q.shape != (1, n):
        raise ValueError(
            f"scene {scene.name!r} expects one configuration of shape [{n}] or [1, {n}], got {tuple(q.shape)}"
        )
    if max_pass_entries < 1:
        raise ValueError(f"max_pass_entries must be >= 1, got {max_pass_entries}")
    with torch.no_grad():
        x = scene.full_positions(q.detach())[0]
    loads_t = scene.pack_loads(loads, 1, x)
    cond_t = scene.pack_condition(cond, 1, x)
    full_to_free = scene.dof_map.full_to_free().cpu().numpy()
    rows, cols, values = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], [np.zeros(0)]
    for effect in scene.effects:
        blocks = _local_hessians(effect, x, cond_t, loads_t, max_pass_entries)
        if blocks is None:
            continue
        if project:
            blocks = project_psd(blocks)
        index = full_to_free[effect.element_dofs.cpu().numpy()]  # [T, k]
        block_np = blocks.detach().cpu().to(torch.float64).numpy()
        r = np.broadcast_to(index[:, :, None], block_np.shape)
        c = np.broadcast_to(index[:, None, :], block_np.shape)
        keep = (r >= 0) & (c >= 0) & (block_np != 0.0)
        rows.append(r[keep])
        cols.append(c[keep])
        values.append(block_np[keep])
    coo = scipy.sparse.coo_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    return coo.tocsr()


def _single_configuration(x: Tensor) -> Tensor:
    if x.ndim == 2 and x.shape[0] == 1:
        return x[0]
    if x.ndim != 1:
        raise ValueError(f"expected one configuration of shape [N] or [1, N], got {tuple(x.shape)}")
    return x
