"""redsim.processes.alone: a result, an exception or a killed process comes back; none is waited for forever."""

from __future__ import annotations

import math
import os

import pytest

from redsim import processes


def test_a_process_that_dies_is_reported_and_an_exception_raised_as_it_is() -> None:
    """A ``multiprocessing.Pool`` waited forever for a worker the kernel killed (bench scaling's size out of memory)."""
    with pytest.raises(ChildProcessError, match="exit code 9"):
        processes.alone(os._exit, 9)
    with pytest.raises(ValueError, match="math domain error") as raised:
        processes.alone(math.sqrt, -1.0)
    assert "Traceback" in raised.value.__notes__[0]
    assert processes.alone(math.sqrt, 4.0) == 2.0
