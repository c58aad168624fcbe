"""2D neo-Hookean solids: the plane model and the thickness reach the energy, by hand.

No catalog scene builds a 2D solid in plane stress or of a thickness other than 1 m, so neither option was pinned:
building the Lamé parameters in plane strain whatever ``plane`` said, dropping the thickness from the rest volume
(the stiffness; the lumped masses kept it) or not passing ``plane`` on from :func:`redsim.scenes.toolkit.add_fem`
passed tests/engine/test_effects.py, test_plane_gradients.py and test_scenes.py (hand mutation audit, helper-276).
"""

from __future__ import annotations

import pytest
import torch

from redsim import SceneBuilder
from redsim.effects import NeoHookean
from redsim.scenes.toolkit import add_fem

TRI = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)  # rest area 0.5 m^2, D_m = I
STRETCH = torch.tensor([1.2, 0.9], dtype=torch.float64)  # F = diag(1.2, 0.9)
# E = 1000 Pa, nu = 0.25: mu = E / (2 (1 + nu)) = 400 Pa; plane strain lam = E nu / ((1 + nu)(1 - 2 nu)) = 400 Pa,
# plane stress lam = 2 mu lam / (lam + 2 mu) = 800/3 Pa
MU = 400.0
LAMBDA = {"strain": 400.0, "stress": 800.0 / 3.0}


def _by_hand(plane: str, thickness: float) -> float:
    """Stable neo-Hookean energy [J] of TRI stretched by STRETCH: thickness * area * psi(F) (NeoHookean's doc)."""
    s, r = (float(v) for v in STRETCH)
    lam_s = LAMBDA[plane] + MU
    alpha = 1.0 + MU / lam_s
    psi = 0.5 * MU * (s * s + r * r - 2.0) + 0.5 * lam_s * (s * r - alpha) ** 2 - 0.5 * MU * MU / lam_s
    return thickness * 0.5 * psi


@pytest.mark.parametrize("plane", ["strain", "stress"])
@pytest.mark.parametrize("thickness", [1.0, 0.02])
def test_a_triangle_s_energy_follows_its_plane_model_and_thickness(plane: str, thickness: float) -> None:
    tri = NeoHookean(
        "elastic", torch.arange(6).reshape(1, 3, 2), TRI[None], 1e3, 0.25, thickness=thickness, plane=plane
    )
    x = (TRI * STRETCH).reshape(1, -1)
    assert float(tri.energy(x)) == pytest.approx(_by_hand(plane, thickness), rel=1e-12)
    # the two models differ by far more than the tolerance: the test tells them apart
    assert abs(_by_hand("stress", thickness) - _by_hand("strain", thickness)) > 1e-2 * _by_hand(plane, thickness)


def test_add_fem_passes_the_plane_model_and_thickness_to_the_solid_and_its_masses() -> None:
    b = SceneBuilder(dim=2)
    add_fem(b, TRI.numpy(), [[0, 1, 2]], young=1e3, poisson=0.25, density=500.0, thickness=0.02, plane="stress")
    scene = b.finalize("one_triangle")
    q = (TRI * STRETCH).reshape(1, -1)
    assert float(scene.energy_terms(q)["elastic"]) == pytest.approx(_by_hand("stress", 0.02), rel=1e-12)
    ones = torch.ones(1, scene.free_dof_count, dtype=torch.float64)
    total = float(scene.mass_matvec(ones).sum()) / 2  # each particle's mass on its x and its y
    assert total == pytest.approx(500.0 * 0.5 * 0.02, rel=1e-12)  # density * area * thickness [kg]
