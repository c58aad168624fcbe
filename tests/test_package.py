"""Packaging: the version is written once, in ``redsim.version`` (``redsim.__version__``), and the metadata agrees."""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

import pytest

import redsim


def test_version_comes_from_one_place() -> None:
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert "version" not in project["project"] and "version" in project["project"]["dynamic"]
    assert project["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "redsim.version.__version__"}
    assert importlib.metadata.version("redsim") == redsim.__version__
