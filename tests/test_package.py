"""Packaging: the version is written once, in ``redsim.version`` (``redsim.__version__``), and the metadata agrees."""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

import pytest

import redsim

ROOT = Path(__file__).resolve().parents[1]
source_checkout = pytest.mark.skipif(
    not (ROOT / "pyproject.toml").is_file(), reason="needs the source checkout (the tests copied beside a wheel)"
)


@source_checkout
def test_version_comes_from_one_place() -> None:
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert "version" not in project["project"] and "version" in project["project"]["dynamic"]
    assert project["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "redsim.version.__version__"}
    assert importlib.metadata.version("redsim") == redsim.__version__


@source_checkout
def test_every_package_folder_is_listed_for_installation() -> None:
    """A wheel holds only the listed packages: a folder missing here works editable and breaks installed."""
    tomllib = pytest.importorskip("tomllib")
    root = Path(__file__).parents[1]
    listed = set(tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    mapped = {"envs": "redsim.envs", "trainers": "redsim.trainers"}
    found = {".".join(p.parent.relative_to(root).parts) for p in (root / "redsim").rglob("__init__.py")}
    found |= {mapped[p.parent.name] for p in root.glob("*/__init__.py") if p.parent.name in mapped}
    assert found <= listed, sorted(found - listed)


@source_checkout
def test_a_source_checkout_imports_its_envs_and_trainers_without_an_editable_install() -> None:
    """A process whose path starts at the clone's root (a Ray worker started there, `python -c` there) imports the
    source folder redsim/: redsim.envs and redsim.trainers still resolve, to the top-level envs/ and trainers/."""
    import subprocess
    import sys

    root = Path(redsim.__file__).resolve().parent.parent
    script = (
        "import sys\n"
        "sys.meta_path = [f for f in sys.meta_path if 'Editable' not in getattr(f, '__name__', type(f).__name__)]\n"
        f"sys.path.insert(0, {str(root)!r})\n"
        "import redsim.envs, redsim.trainers.rllib\n"
        "print(redsim.envs.__file__, redsim.trainers.__file__)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=root, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [str(root / "envs" / "__init__.py"), str(root / "trainers" / "__init__.py")]


def test_an_env_runs_under_python_w_error() -> None:
    """No warning from redsim's import to a vector step (torch's own deprecations on redsim's paths included):
    users whose test suites turn warnings into errors run the envs."""
    import subprocess
    import sys

    script = (
        "import gymnasium as gym, redsim\n"
        "env = gym.make('RedSim/MiniChain-v0'); env.reset(seed=0); env.step(env.action_space.sample())\n"
        "v = gym.make_vec('RedSim/MiniChain-v0', num_envs=2, vectorization_mode='vector_entry_point')\n"
        "v.reset(seed=0); v.step(v.action_space.sample()); print('ok')\n"
    )
    done = subprocess.run([sys.executable, "-W", "error", "-c", script], capture_output=True, text=True, check=False)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-2000:]


def test_import_redsim_does_not_import_trimesh() -> None:
    """trimesh (and the scipy.spatial it pulls in) took about a third of ``import redsim``; the scene builders and
    mesh helpers import it where they use it, so a process that only imports redsim never pays for it."""
    import subprocess
    import sys

    script = "import redsim, sys; assert 'trimesh' not in sys.modules, 'trimesh imported'; print('ok')"
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=False)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-2000:]
