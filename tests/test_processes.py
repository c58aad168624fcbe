"""redsim.processes.alone: a result, an exception or a killed process comes back; none is waited for forever."""

from __future__ import annotations

import math
import os
import warnings

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


def test_the_process_s_warnings_come_back_under_this_process_s_filters() -> None:
    """A spawned process starts with Python's own display: bench scaling printed each size's warnings as
    ``/path/scaling.py:164: UserWarning: ...`` and the source line, not as the command line's one line."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        processes.alone(warnings.warn, "a size's message")
    assert [(str(w.message), w.category) for w in caught] == [("a size's message", UserWarning)]
    assert caught[0].filename == processes.__file__  # where the process issued it (its _send called warn)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("ignore")
        processes.alone(warnings.warn, "a size's message")
    assert caught == []
