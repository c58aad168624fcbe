"""The closed-form 2D neo-Hookean gradient (:mod:`redsim.effects.plane_gradients`) against autograd through the
plain formulas (:func:`redsim.effects.elastic._plane_invariants` and psi) and against central differences, to second
and third order, with and without the conditional modulus factor."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch

import redsim
from redsim.effects import NeoHookean
from redsim.effects.base import edge_vectors, gather_coordinates
from redsim.effects.elastic import _plane_invariants


def _plain_energies(fem: NeoHookean, x: torch.Tensor, cond: torch.Tensor | None) -> torch.Tensor:
    """Element energies [B, T] by autograd-traceable formulas (the kernel before its closed-form gradient)."""
    trace, det = _plane_invariants(gather_coordinates(x, fem.element_dofs), fem.shape_gradients)
    mu, lam = fem.mu, fem.lam
    lam_s = lam + mu
    psi = 0.5 * mu * (trace - 2) + 0.5 * lam_s * (det - 1 - mu / lam_s) ** 2 - 0.5 * mu * mu / lam_s
    if fem.condition_scale is not None:
        index, mask = fem.condition_scale
        psi = psi * torch.where(mask, cond[:, index : index + 1], torch.ones_like(mu))
    return psi * fem.rest_volume


def _case(
    name: str, batch: int, scale: float, dtype: torch.dtype
) -> tuple[NeoHookean, torch.Tensor, torch.Tensor | None]:
    """The scene's elastic term, full positions [B, N] near the seed and conditions [B, m] (None without)."""
    scene = redsim.scenes.build(name).to(dtype=dtype)
    g = torch.Generator().manual_seed(0)
    q = scene.q_seed + scale * torch.randn(batch, scene.free_dof_count, generator=g, dtype=dtype)
    x = scene.full_positions(q)
    cond = None
    if scene.condition_space is not None:
        cond = scene.pack_condition(None, batch, x).clone()
        cond[:, 0] = torch.linspace(0.5, 4.0, batch, dtype=dtype)
    return scene.effect("elastic"), x, cond


@pytest.mark.parametrize("name", ["conditional_bar", "bistable_bar"])  # with and without the condition scale
def test_closed_form_derivatives_equal_autograd_of_the_plain_formulas(
    name: str, derivatives: Callable[..., list[torch.Tensor]]
) -> None:
    """float64: values, gradients, Hessian-vector products and third derivatives (backward under create_graph)."""
    fem, x, cond = _case(name, 3, 0.05, torch.float64)
    assert (fem.condition_scale is not None) == (name == "conditional_bar")
    g = torch.Generator().manual_seed(1)
    u, v = (torch.randn(x.shape, generator=g, dtype=torch.float64) for _ in range(2))
    fast = derivatives(lambda y: fem.element_energies(y, cond), x, u, v)
    plain = derivatives(lambda y: _plain_energies(fem, y, cond), x, u, v)
    for a, b in zip(fast, plain, strict=True):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-12 * float(b.abs().max()))


def test_float32_gradients_match_float64_like_autograd(derivatives: Callable[..., list[torch.Tensor]]) -> None:
    """float32: the closed-form gradient is as close to the float64 one as float32 autograd is (within 5x)."""
    fem, x, cond = _case("conditional_bar", 2, 0.01, torch.float64)
    fem32, x32, cond32 = fem.to(dtype=torch.float32), x.float(), cond.float()
    zero = torch.zeros_like(x)

    def gradient(energies, y: torch.Tensor) -> torch.Tensor:
        return derivatives(energies, y, zero.to(y.dtype), zero.to(y.dtype))[1].double()

    reference = gradient(lambda y: fem.element_energies(y, cond), x)
    fast = gradient(lambda y: fem32.element_energies(y, cond32), x32)
    plain = gradient(lambda y: _plain_energies(fem32, y, cond32), x32)
    scale = float(reference.abs().max())
    assert float((fast - reference).abs().max()) <= 5.0 * float((plain - reference).abs().max()) + 1e-6 * scale


@pytest.mark.parametrize("name", ["conditional_bar", "bistable_bar"])
def test_closed_form_gradients_pass_gradcheck_and_gradgradcheck(name: str) -> None:
    """Central differences (float64) of the energies and of their gradients, on a few elements read from the slice
    of x they use (as a cubature's), and on the gathered path (Hessians, cubature fit)."""
    fem, x, cond = _case(name, 2, 0.05, torch.float64)
    subset = fem.subset(torch.arange(0, fem.element_count, fem.element_count // 5))
    kept = torch.unique(subset.element_dofs)
    local = subset.reindexed(torch.searchsorted(kept, subset.element_dofs))
    xs = x[:, kept].requires_grad_(True)
    assert torch.autograd.gradcheck(lambda y: local.element_energies(y, cond), (xs,))
    assert torch.autograd.gradgradcheck(lambda y: local.element_energies(y, cond), (xs,))
    xe = xs.detach()[:, local.element_dofs].requires_grad_(True)
    assert torch.autograd.gradgradcheck(lambda y: local.element_energy(y, cond), (xe,))


def test_gradient_with_respect_to_the_condition() -> None:
    """The modulus factor is differentiable (first and second order) like the plain formulas."""
    fem, x, cond = _case("conditional_bar", 3, 0.05, torch.float64)
    x = x.requires_grad_(True)
    subset = fem.subset(torch.arange(0, fem.element_count, 50))
    kept = torch.unique(subset.element_dofs)  # central differences of the positions the elements read, not all of x
    local = subset.reindexed(torch.searchsorted(kept, subset.element_dofs))
    xs = x.detach()[:, kept].requires_grad_(True)
    c = cond.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda y, k: local.element_energies(y, k), (xs, c))
    assert torch.autograd.gradgradcheck(lambda y, k: local.element_energies(y, k), (xs, c))
    (fast,) = torch.autograd.grad(fem.element_energies(x, c).sum(), c)
    (plain,) = torch.autograd.grad(_plain_energies(fem, x, c).sum(), c)
    assert torch.allclose(fast, plain, rtol=1e-10, atol=1e-12 * float(plain.abs().max()))


def test_constants_with_gradients_are_refused() -> None:
    fem, x, cond = _case("conditional_bar", 1, 0.01, torch.float64)
    fem.plane_constants = tuple(c.clone().requires_grad_(True) for c in fem.plane_constants)
    with pytest.raises(ValueError, match="material constants"):
        fem.element_energies(x, cond)


@pytest.mark.parametrize("name", ["conditional_bar", "bistable_bar"])
def test_edge_entries_give_the_vertex_path_s_energies_and_gradients(name: str) -> None:
    """``edge_energies`` of the edges (x1 - x0, y1 - y0, x2 - x0, y2 - y0) equals the vertex path and its gradient is
    the vertex gradient's edge part (float64); central differences of it and of its gradient pass (the condition
    scale included); a wrong entry count and a 3D element are refused."""
    fem, x, cond = _case(name, 3, 0.05, torch.float64)
    assert fem.edge_dim == 2
    xe = x[:, fem.element_dofs].requires_grad_(True)
    edges = [e.requires_grad_(True) for e in edge_vectors(xe.detach().unbind(-1), 2)]
    by_vertex, by_edges = fem.element_energy(xe, cond), fem.edge_energies(edges, cond)
    assert torch.allclose(by_edges, by_vertex, rtol=1e-12, atol=0.0)
    (vertex_grads,) = torch.autograd.grad(by_vertex.sum(), xe)
    for a, b in zip(torch.autograd.grad(by_edges.sum(), edges), vertex_grads[..., 2:].unbind(-1), strict=True):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12 * float(b.abs().max()))
    few = fem.subset(torch.arange(4))
    entries = [e[:, :4].detach().requires_grad_(True) for e in edges]
    assert torch.autograd.gradcheck(lambda *u: few.edge_energies(u, cond), entries)
    assert torch.autograd.gradgradcheck(lambda *u: few.edge_energies(u, cond), entries)
    with pytest.raises(ValueError, match="edge entries"):
        fem.edge_energies(edges[:-1], cond)
    solid = redsim.scenes.build("stiff_body").effect("elastic")
    assert solid.edge_dim is None
    with pytest.raises(NotImplementedError, match="by their edges"):
        solid.edge_energies(edges, None)
