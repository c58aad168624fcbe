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


def test_every_package_folder_is_listed_for_installation() -> None:
    """A wheel holds only the listed packages: a folder missing here works editable and breaks installed."""
    tomllib = pytest.importorskip("tomllib")
    root = Path(__file__).parents[1]
    listed = set(tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    mapped = {"envs": "redsim.envs", "trainers": "redsim.trainers"}
    found = {".".join(p.parent.relative_to(root).parts) for p in (root / "redsim").rglob("__init__.py")}
    found |= {mapped[p.parent.name] for p in root.glob("*/__init__.py") if p.parent.name in mapped}
    assert found <= listed, sorted(found - listed)
