"""``redsim.tensors.jvp``: torch.func.jvp's answer by reverse mode, without importing torch._dynamo."""

from __future__ import annotations

import subprocess
import sys

import torch

from redsim.tensors import jvp


def test_jvp_equals_forward_mode_and_handles_maps_that_ignore_an_input() -> None:
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(3, 16), torch.nn.ELU(), torch.nn.Linear(16, 5)).double()
    z, tangents = torch.randn(6, 3, dtype=torch.float64), torch.randn(6, 3, dtype=torch.float64)
    with torch.no_grad():  # callers may hold no_grad
        out, column = jvp(net, (z,), (tangents,))
    ref_out, ref_column = torch.func.jvp(net, (z,), (tangents,))
    torch.testing.assert_close(out, ref_out, rtol=0, atol=0)
    torch.testing.assert_close(column, ref_column, rtol=1e-12, atol=1e-14)
    assert not out.requires_grad and not column.requires_grad
    c, c_tangents = torch.randn(6, 2, dtype=torch.float64), torch.randn(6, 2, dtype=torch.float64)
    conditional = lambda u, v: net(u) * v.sum(-1, keepdim=True)  # noqa: E731  (two inputs, as a conditional map)
    out, column = jvp(conditional, (z, c), (tangents, c_tangents))
    _, ref_column = torch.func.jvp(conditional, (z, c), (tangents, c_tangents))
    torch.testing.assert_close(column, ref_column, rtol=1e-12, atol=1e-14)
    for constant in (lambda u: torch.ones(6, 5, dtype=torch.float64), lambda u: torch.floor(net(u))):  # J = 0
        out, column = jvp(constant, (z,), (tangents,))
        assert torch.equal(column, torch.zeros(6, 5, dtype=torch.float64))


def test_an_env_s_first_step_does_not_import_torch_dynamo() -> None:
    """torch.func.jvp imported torch._dynamo (~1.3 s of CPU of a process's first env); a fresh process checks it."""
    code = (
        "import sys, numpy as np, gymnasium as gym, redsim\n"
        "env = gym.make('RedSim/MiniChain-v0'); env.reset(seed=0); env.step(np.zeros(3, np.float32))\n"
        "assert 'torch._dynamo' not in sys.modules, 'torch._dynamo was imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)
