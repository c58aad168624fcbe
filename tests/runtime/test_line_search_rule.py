"""The latent solver's line-search acceptance (:func:`redsim.runtime.solver._judge`), as its module doc states it.

"A trial with a non-finite value or gradient is rejected like an uphill one; a trial whose value change is at
round-off level is accepted if it lowers |g|" (else Armijo). Accepting every round-off-level trial, whether or not it
lowers |g|, passed tests/runtime/test_solve_path.py, test_row_loop.py, test_dense.py, test_stepper.py and
tests/stability/test_stability.py and test_damping.py (hand mutation audit, helper-276).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from redsim.runtime.solver import _judge


@pytest.mark.parametrize("kind", ["numpy", "torch"])
def test_armijo_or_a_round_off_change_that_lowers_the_gradient_and_nothing_non_finite(kind: str) -> None:
    """Five trials from Phi = 1 J, |g| = 1, slope -1, step 1, value noise 1e-12 J."""
    values = [0.5, 1.0 + 1e-13, 1.0 + 1e-13, 1.1, float("nan")]
    grads = [[0.5, 0.0], [0.5, 0.0], [2.0, 0.0], [0.5, 0.0], [0.5, 0.0]]
    k = len(values)

    def array(x: object) -> object:
        return np.asarray(x, dtype=np.float64) if kind == "numpy" else torch.tensor(x, dtype=torch.float64)

    trial = (array(values), array(grads))
    here = (array([1.0] * k), array([[1.0, 0.0]] * k))
    finite, accepted = _judge(trial, here, array([1.0] * k), array([-1.0] * k), array([1e-12] * k))
    assert [bool(f) for f in finite] == [True, True, True, True, False]
    # Armijo; flat and |g| lower; flat but |g| higher; uphill beyond round-off; NaN
    assert [bool(a) for a in accepted] == [True, True, False, False, False]
    grads[0] = [float("inf"), 0.0]  # a trial with an infinite gradient is no step, however low its value
    finite, accepted = _judge(
        (array(values), array(grads)), here, array([1.0] * k), array([-1.0] * k), array([0.0] * k)
    )
    assert not bool(finite[0]) and not bool(accepted[0])
