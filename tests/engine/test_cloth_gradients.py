"""The cloth kernels' closed-form gradients (:mod:`redsim.effects.cloth_gradients`: the membrane, the bending hinges)
against autograd through the plain formulas (:func:`membrane_metric`, :func:`hinge_parts`) and against central
differences, to second and third order."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch

import redsim
from redsim.effects import Effect
from redsim.effects.base import edge_vectors, gather_coordinates
from redsim.effects.cloth_gradients import HINGE_CLOSED_FORM_ENTRIES, HingeEnergy, hinge_parts
from redsim.effects.elastic import DiscreteShellBending, membrane_metric

EFFECTS = ("membrane", "bending")
"""The cloth terms with a closed-form gradient (named as the cloth scenes name them)."""


def _plain_energies(effect: Effect, x: torch.Tensor) -> torch.Tensor:
    """Element energies [B, T] by autograd-traceable formulas (the kernels before their closed-form gradients)."""
    coords = gather_coordinates(x, effect.element_dofs)
    if isinstance(effect, DiscreteShellBending):
        return effect.weight * (hinge_parts(coords, effect.length_eps)[0] - effect.rest_angle) ** 2
    caa, cbb, cab = membrane_metric(coords, effect.shape_gradients)
    e00, e11, e01 = 0.5 * (caa - 1.0), 0.5 * (cbb - 1.0), 0.5 * cab
    trace = e00 + e11
    psi = effect.mu * (e00 * e00 + e11 * e11 + 2.0 * e01 * e01) + 0.5 * effect.lam * trace * trace
    return psi * effect.rest_area


def _state(scene: redsim.Scene, batch: int, scale: float, dtype: torch.dtype) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    q = scene.q_seed.to(dtype) + scale * torch.randn(batch, scene.free_dof_count, generator=g, dtype=dtype)
    return scene.to(dtype=dtype).full_positions(q)


def _gradient(energies: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """d(sum of the energies)/dx at x, a plain backward (no create_graph: the kernels' own first-order path)."""
    x = x.detach().requires_grad_(True)
    return torch.autograd.grad(energies(x).sum(), x)[0]


@pytest.mark.parametrize("effect_name", EFFECTS)
@pytest.mark.parametrize("scene_name", ["hanging_sheet", "cloth_ball"])
def test_closed_form_derivatives_equal_autograd_of_the_plain_formulas(
    scene_name: str, effect_name: str, derivatives: Callable[..., list[torch.Tensor]]
) -> None:
    """float64: values, gradients (a plain backward, and under create_graph), Hessian-vector products and third
    derivatives."""
    scene = redsim.scenes.build(scene_name)
    effect = scene.effect(effect_name)
    x = _state(scene, 3, 0.05, torch.float64)
    g = torch.Generator().manual_seed(1)
    u, v = (torch.randn(x.shape, generator=g, dtype=torch.float64) for _ in range(2))
    fast = derivatives(effect.element_energies, x, u, v)
    plain = derivatives(lambda y: _plain_energies(effect, y), x, u, v)
    fast.append(_gradient(effect.element_energies, x))
    plain.append(plain[1])
    for a, b in zip(fast, plain, strict=True):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-12 * float(b.abs().max()))


@pytest.mark.parametrize("scale", [0.01, 0.001])
@pytest.mark.parametrize("effect_name", EFFECTS)
def test_float32_gradients_match_float64_like_autograd(effect_name: str, scale: float) -> None:
    """float32: the closed-form gradient is as close to the float64 one as float32 autograd is (within 5x), also
    near the flat rest (scale 0.001: the hinges' sine and the membrane's strain near zero)."""
    scene = redsim.scenes.build("hanging_sheet")
    effect, effect32 = scene.effect(effect_name), scene.to(dtype=torch.float32).effect(effect_name)
    x = _state(scene, 2, scale, torch.float64)
    reference = _gradient(effect.element_energies, x)
    fast = _gradient(effect32.element_energies, x.float()).double()
    plain = _gradient(lambda y: _plain_energies(effect32, y), x.float()).double()
    scale = float(reference.abs().max())
    assert float((fast - reference).abs().max()) <= 5.0 * float((plain - reference).abs().max()) + 1e-6 * scale


@pytest.mark.parametrize("effect_name", EFFECTS)
def test_closed_form_gradients_pass_gradcheck_and_gradgradcheck(effect_name: str) -> None:
    """Central differences (float64) of the energies and of their gradients, on a few elements read from the slice
    of x they use (as a cubature's)."""
    scene = redsim.scenes.build("cloth_ball")
    subset = scene.effect(effect_name).subset(torch.arange(5))
    kept = torch.unique(subset.element_dofs)
    effect = subset.reindexed(torch.searchsorted(kept, subset.element_dofs))
    x = _state(scene, 2, 0.05, torch.float64)[:, kept].requires_grad_(True)
    assert torch.autograd.gradcheck(effect.element_energies, (x,))
    assert torch.autograd.gradgradcheck(effect.element_energies, (x,))
    xe = x.detach()[:, effect.element_dofs].requires_grad_(True)  # the gathered path (Hessians, cubature fit)
    assert torch.autograd.gradgradcheck(effect.element_energy, (xe,))


@pytest.mark.parametrize("effect_name", EFFECTS)
def test_edge_entries_give_the_vertex_path_s_energies_and_gradients(effect_name: str) -> None:
    """``edge_energies`` of the edges x_j - x_0 (what a cubature computes from its features) equals
    ``element_energies`` of the vertex coordinates, and its gradient is the vertex gradient's edge part: d/dx_j for
    j >= 1 (float64); central differences of it and of its gradient pass; a wrong entry count is refused."""
    scene = redsim.scenes.build("cloth_ball")
    effect = scene.effect(effect_name).subset(torch.arange(40))
    x = _state(scene, 3, 0.05, torch.float64)
    xe = x[:, effect.element_dofs].requires_grad_(True)  # [B, T, 3 k]: vertex-major x, y, z
    edges = [e.requires_grad_(True) for e in edge_vectors(xe.detach().unbind(-1), 3)]
    by_vertex, by_edges = effect.element_energy(xe), effect.edge_energies(edges)
    assert torch.allclose(by_vertex, effect.element_energies(x), rtol=1e-12, atol=0.0)
    assert torch.allclose(by_edges, by_vertex, rtol=1e-12, atol=0.0)
    (vertex_grads,) = torch.autograd.grad(by_vertex.sum(), xe)
    edge_grads = torch.autograd.grad(by_edges.sum(), edges)
    for a, b in zip(edge_grads, vertex_grads[..., 3:].unbind(-1), strict=True):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12 * float(b.abs().max()))
    few = [e[:, :5].detach().requires_grad_(True) for e in edges]
    assert torch.autograd.gradcheck(lambda *u: effect.subset(torch.arange(5)).edge_energies(u), few)
    assert torch.autograd.gradgradcheck(lambda *u: effect.subset(torch.arange(5)).edge_energies(u), few)
    with pytest.raises(ValueError, match="edge entries"):
        effect.edge_energies(edges[:-1])


@pytest.mark.parametrize(
    ("effect_name", "constant", "message"),
    [("membrane", "mu", "material constants"), ("bending", "weight", "weights and rest angles")],
)
def test_constants_with_gradients_are_refused(effect_name: str, constant: str, message: str) -> None:
    scene = redsim.scenes.build("hanging_sheet")
    effect = scene.effect(effect_name)
    setattr(effect, constant, getattr(effect, constant).clone().requires_grad_(True))
    with pytest.raises(ValueError, match=message):
        effect.element_energies(_state(scene, 1, 0.01, torch.float64))


@pytest.mark.parametrize("rest_apex", [0.0, 0.4])
def test_a_collapsed_hinge_has_the_gradient_autograd_gives(rest_apex: float) -> None:
    """Apexes on the edge line: atan2 at (0, 0), whose derivative torch's atan2 backward takes as 0 (a flat and a
    bent rest hinge); the energy stays finite (element Hessians give such an element a zero block, 1da4fa4)."""
    rest = torch.tensor(
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, 1.0, 0.0], [0.6, -1.0, rest_apex]], dtype=torch.float64
    )
    bending = DiscreteShellBending("b", torch.arange(12).reshape(1, 4, 3), rest[None], 1.0)
    collapsed = torch.tensor([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.7, 0.0, 0.0]], dtype=torch.float64)
    grads = []
    for energies in (bending.element_energies, lambda y: _plain_energies(bending, y)):
        x = collapsed.clone().requires_grad_(True)
        energy = energies(x)
        assert torch.isfinite(energy).all()
        grads.append(torch.autograd.grad(energy.sum(), x)[0])
    assert torch.equal(grads[0], grads[1])


def test_hinges_past_the_closed_form_size_take_autograd() -> None:
    """Above HINGE_CLOSED_FORM_ENTRIES per coordinate the hinges are differentiated by autograd of the same formula
    (the closed form is slower there); below, by HingeEnergy: the same gradients either way (float64)."""
    scene = redsim.scenes.build("hanging_sheet")
    bending = scene.effect("bending")
    for batch, kernel in ((1, "HingeEnergyBackward"), (HINGE_CLOSED_FORM_ENTRIES // bending.element_count + 1, None)):
        x = _state(scene, batch, 0.05, torch.float64).requires_grad_(True)
        energy = bending.element_energies(x)
        assert (type(energy.grad_fn).__name__ == kernel) if kernel else "Hinge" not in type(energy.grad_fn).__name__
        fast = torch.autograd.grad(energy.sum(), x)[0]
        assert torch.allclose(fast, _gradient(lambda y: _plain_energies(bending, y), x), rtol=1e-9, atol=1e-12)


def test_hinge_hessians_with_some_coordinates_fixed() -> None:
    """Under create_graph a coordinate that needs no gradient gets none (a caller holding some vertices fixed)."""
    g = torch.Generator().manual_seed(0)
    coords = [torch.randn(2, 3, generator=g, dtype=torch.float64, requires_grad=i > 0) for i in range(12)]
    energy = HingeEnergy.apply(torch.ones(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), 1e-12, *coords)
    grads = torch.autograd.grad(energy.sum(), coords[1:], create_graph=True)
    plain = torch.autograd.grad(_hinge_plain(coords).sum(), coords[1:], create_graph=True)
    for a, b in zip(grads, plain, strict=True):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-12)
    (second,) = torch.autograd.grad(sum(a.sum() for a in grads), coords[1])
    (second_plain,) = torch.autograd.grad(sum(b.sum() for b in plain), coords[1])
    assert torch.allclose(second, second_plain, rtol=1e-9, atol=1e-12)


def _hinge_plain(coords: list[torch.Tensor]) -> torch.Tensor:
    """Unit-weight, flat-rest hinge energies by autograd-traceable formulas."""
    return hinge_parts(coords, 1e-12)[0] ** 2
