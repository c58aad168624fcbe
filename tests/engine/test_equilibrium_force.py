"""static_equilibrium's and latent_equilibrium's ``force``: a constant generalized force f, minimizing E - f . q.

No caller in the package and no test passed a ``force``, so its sign in the objective (PotentialObjective's value,
``- q @ force``) was unpinned: flipping it passed tests/engine/test_integrator.py, test_reference.py,
test_latent.py, test_physics_audit.py and test_metrics.py (hand mutation audit, helper-276). A handle load F is the
generalized force f = dp/dq^T F (p the handle positions, linear in q), so both forms give one equilibrium.
"""

from __future__ import annotations

import pytest
import torch

from redsim import pretrained, scenes
from redsim.integrators import LatentSpace, latent_equilibrium, static_equilibrium
from redsim.integrators.objective import pack_inputs


@pytest.fixture(scope="module")
def chain_and_force() -> tuple:
    """mini_chain, a load on its handle, and that load as a generalized force f [N], shape [n]."""
    scene = scenes.build("mini_chain")
    loads = {"bottom": [3.0, 0.0, -2.0]}
    packed, _ = pack_inputs(scene, loads, None)
    q = scene.q_seed.clone().requires_grad_(True)
    (force,) = torch.autograd.grad((packed.reshape(-1) * scene.handle_positions(q[None]).reshape(-1)).sum(), q)
    return scene, loads, force


def test_a_generalized_force_has_the_equilibrium_of_the_handle_load_it_equals(chain_and_force: tuple) -> None:
    scene, loads, force = chain_and_force
    by_load, info = static_equilibrium(scene, loads, tol=1e-10)
    by_force, info_force = static_equilibrium(scene, force=force, tol=1e-10)
    assert info.converged and info_force.converged
    assert float((by_load - scene.q_seed).abs().max()) > 0.1  # the load moved the chain [m]
    torch.testing.assert_close(by_force, by_load, rtol=0.0, atol=1e-8)
    # at the equilibrium the elastic and gravity forces balance f: dE/dq = f
    q = by_force.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(scene.energy(q[None])[0], q)
    assert float((grad - force).norm()) <= 1e-6 * float(force.norm())


def test_a_generalized_force_in_the_latent_space_as_its_handle_load(chain_and_force: tuple) -> None:
    scene, loads, force = chain_and_force
    space = LatentSpace(scene, pretrained.load("mini_chain", scene).double())
    by_load, info = latent_equilibrium(space, loads, tol=1e-10)
    by_force, info_force = latent_equilibrium(space, force=force, tol=1e-10)
    assert info.converged and info_force.converged
    assert float(by_load.abs().max()) > 0.1  # the load moved z
    torch.testing.assert_close(by_force, by_load, rtol=0.0, atol=1e-8)
