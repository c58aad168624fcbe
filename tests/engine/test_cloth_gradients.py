"""The membrane's closed-form gradient (:mod:`redsim.effects.cloth_gradients`) against autograd through the plain
formula (:func:`membrane_metric`) and against central differences, to second and third order."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch

import redsim
from redsim.effects import Effect
from redsim.effects.base import gather_coordinates
from redsim.effects.elastic import membrane_metric


def _plain_energies(effect: Effect, x: torch.Tensor) -> torch.Tensor:
    """Element energies [B, T] by autograd-traceable formulas (the kernels before their closed-form gradients)."""
    caa, cbb, cab = membrane_metric(gather_coordinates(x, effect.element_dofs), effect.shape_gradients)
    e00, e11, e01 = 0.5 * (caa - 1.0), 0.5 * (cbb - 1.0), 0.5 * cab
    trace = e00 + e11
    psi = effect.mu * (e00 * e00 + e11 * e11 + 2.0 * e01 * e01) + 0.5 * effect.lam * trace * trace
    return psi * effect.rest_area


def _state(scene: redsim.Scene, batch: int, scale: float, dtype: torch.dtype) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    q = scene.q_seed.to(dtype) + scale * torch.randn(batch, scene.free_dof_count, generator=g, dtype=dtype)
    return scene.to(dtype=dtype).full_positions(q)


@pytest.mark.parametrize("scene_name", ["hanging_sheet", "cloth_ball"])
def test_closed_form_derivatives_equal_autograd_of_the_plain_formulas(
    scene_name: str, derivatives: Callable[..., list[torch.Tensor]]
) -> None:
    """float64: values, gradients, Hessian-vector products and third derivatives (backward under create_graph)."""
    scene = redsim.scenes.build(scene_name)
    effect = scene.effect("membrane")
    x = _state(scene, 3, 0.05, torch.float64)
    g = torch.Generator().manual_seed(1)
    u, v = (torch.randn(x.shape, generator=g, dtype=torch.float64) for _ in range(2))
    fast = derivatives(effect.element_energies, x, u, v)
    plain = derivatives(lambda y: _plain_energies(effect, y), x, u, v)
    for a, b in zip(fast, plain, strict=True):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-12 * float(b.abs().max()))


def test_float32_gradients_match_float64_like_autograd(derivatives: Callable[..., list[torch.Tensor]]) -> None:
    """float32: the closed-form gradient is as close to the float64 one as float32 autograd is (within 5x)."""
    scene = redsim.scenes.build("hanging_sheet")
    effect, effect32 = scene.effect("membrane"), scene.to(dtype=torch.float32).effect("membrane")
    x = _state(scene, 2, 0.01, torch.float64)
    zero = torch.zeros_like(x)

    def gradient(energies, y: torch.Tensor) -> torch.Tensor:
        return derivatives(energies, y, zero, zero)[1].double()

    reference = gradient(effect.element_energies, x)
    fast = gradient(effect32.element_energies, x.float())
    plain = gradient(lambda y: _plain_energies(effect32, y), x.float())
    scale = float(reference.abs().max())
    assert float((fast - reference).abs().max()) <= 5.0 * float((plain - reference).abs().max()) + 1e-6 * scale


def test_closed_form_gradients_pass_gradcheck_and_gradgradcheck() -> None:
    """Central differences (float64) of the energies and of their gradients, on a few elements read from the slice
    of x they use (as a cubature's)."""
    scene = redsim.scenes.build("cloth_ball")
    subset = scene.effect("membrane").subset(torch.arange(5))
    kept = torch.unique(subset.element_dofs)
    effect = subset.reindexed(torch.searchsorted(kept, subset.element_dofs))
    x = _state(scene, 2, 0.05, torch.float64)[:, kept].requires_grad_(True)
    assert torch.autograd.gradcheck(effect.element_energies, (x,))
    assert torch.autograd.gradgradcheck(effect.element_energies, (x,))
    xe = x.detach()[:, effect.element_dofs].requires_grad_(True)  # the gathered path (Hessians, cubature fit)
    assert torch.autograd.gradgradcheck(effect.element_energy, (xe,))


def test_constants_with_gradients_are_refused() -> None:
    scene = redsim.scenes.build("hanging_sheet")
    membrane = scene.effect("membrane")
    membrane.mu = membrane.mu.clone().requires_grad_(True)
    with pytest.raises(ValueError, match="material constants"):
        membrane.element_energies(_state(scene, 1, 0.01, torch.float64))
