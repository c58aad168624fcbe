"""Material parameter conversions, in one place."""

from __future__ import annotations

from typing import Literal, TypeVar

import torch

Scalar = TypeVar("Scalar", float, torch.Tensor)


def lame_from_young_poisson(
    young: Scalar, poisson: Scalar, *, plane: Literal["strain", "stress"] | None = None
) -> tuple[Scalar, Scalar]:
    """Lamé parameters (mu, lambda) [Pa] from Young's modulus [Pa] and Poisson ratio.

    Works elementwise on floats or tensors (per-element materials).

    Args:
        young: Young's modulus E > 0 [Pa].
        poisson: Poisson ratio nu, -1 < nu < 0.5.
        plane: ``None`` or ``"strain"`` for 3D solids and 2D plane strain (the same formulas),
            ``"stress"`` for thin 2D sheets (lambda becomes 2 mu lambda / (lambda + 2 mu)).

    Raises:
        ValueError: on a non-positive modulus or a Poisson ratio outside (-1, 0.5).
    """
    young_t, poisson_t = torch.as_tensor(young), torch.as_tensor(poisson)
    if not bool(torch.all(young_t > 0)):
        raise ValueError(f"Young's modulus must be > 0, got {young!r}")
    if not bool(torch.all((poisson_t > -1.0) & (poisson_t < 0.5))):
        raise ValueError(f"Poisson ratio must lie in (-1, 0.5), got {poisson!r}")
    if plane not in (None, "strain", "stress"):
        raise ValueError(f"plane must be None, 'strain' or 'stress', got {plane!r}")
    mu = young / (2.0 * (1.0 + poisson))
    lam = young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    if plane == "stress":
        lam = 2.0 * mu * lam / (lam + 2.0 * mu)
    return mu, lam
