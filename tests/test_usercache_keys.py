"""A cache file answers only the key it was written for (hand mutation audit, helper-281: reading any key's file
passed tests/test_usercache.py, tests/engine/test_reference.py and tests/envs/test_envs.py)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from redsim.usercache import read_arrays, write_arrays


def test_a_file_of_another_key_is_not_read(tmp_path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "equilibria" / "x.npz"
    write_arrays(path, "scene a, load 1", {"q": np.arange(3.0)}, "equilibrium")
    back = read_arrays(path, "scene a, load 1", "equilibrium")
    assert back is not None and list(back) == ["q"] and np.array_equal(back["q"], np.arange(3.0))
    with caplog.at_level(logging.WARNING):
        assert read_arrays(path, "scene b, load 1", "equilibrium") is None
    assert "another key" in caplog.text and "equilibrium" in caplog.text
    assert read_arrays(tmp_path / "missing.npz", "scene a, load 1", "equilibrium") is None
