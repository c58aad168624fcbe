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
    # a folder of data files (redsim/pretrained/policies) is a namespace package to Python: setuptools warns that
    # it "would be ignored" unless listed, and its files then ship only while setuptools still reads them as data
    folders = {".".join(d.relative_to(root).parts) for d in (root / "redsim").rglob("*") if d.is_dir()}
    folders = {f for f in folders if "__pycache__" not in f.split(".")}
    assert folders <= listed, sorted(folders - listed)


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


def _run(script: str) -> str:
    """stdout of ``python -c script`` in a fresh process (its stderr where it fails)."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def test_import_redsim_imports_neither_torch_nor_trimesh() -> None:
    """torch took ~2 s of ``import redsim`` (and of ``redsim --help``), trimesh with its scipy.spatial a third of the
    rest: the package's names are loaded on first use, the ids are registered without either, and a forked child of
    a process that never loaded torch does not load it."""
    script = (
        "import os, sys, gymnasium as gym, redsim\n"
        "assert 'RedSim/Chain-v0' in gym.registry\n"
        "redsim.fork_safety.one_thread_in_child()\n"
        "print(sorted(m for m in ('torch', 'trimesh') if m in sys.modules))\n"
    )
    assert _run(script).strip() == "[]"


def test_the_package_names_load_on_first_use() -> None:
    from redsim import effects, scene, subspace

    assert redsim.Scene is scene.Scene and redsim.SceneBuilder is scene.SceneBuilder
    assert redsim.load_subspace is subspace.load_subspace and redsim.effects is effects
    assert set(redsim.__all__) <= set(dir(redsim))
    assert redsim.meshes.cloth_grid is not None  # any submodule, as when redsim's import loaded them all
    with pytest.raises(AttributeError, match="no attribute 'Scenes'"):
        redsim.Scenes  # noqa: B018 (the attribute access is the test)


def test_the_command_line_loads_torch_only_for_a_command_that_needs_it() -> None:
    """``redsim --help`` and ``redsim cache info`` run without torch (2.4 s before, ~0.3 s after); the options of
    ``fit`` and ``train-agent``, whose help needs torch-importing modules, are added when those commands are used."""
    script = (
        "import contextlib, io, sys\n"
        "from redsim.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()) as text:\n"
        "    codes = [main(['--help']), main(['cache', 'info'])]\n"
        "print(codes, 'torch' in sys.modules)\n"
        "with contextlib.redirect_stdout(io.StringIO()) as text:\n"
        "    codes = [main(['fit', '--help']), main(['train-agent', '--help'])]\n"
        "print(codes, '--anchor-radius' in text.getvalue() and '{ppo,sac,td3}' in text.getvalue())\n"
    )
    assert _run(script).split("\n")[:2] == ["[0, 0] False", "[0, 0] True"]


@pytest.mark.parametrize("argv", [["simulate", "mini_chain", "--steps", "1"], ["fit", "mini_chain", "--steps", "1"]])
def test_ctrl_c_while_a_command_loads_torch_exits_130_with_one_line(argv: list[str]) -> None:
    """Ctrl-C in a command's first seconds (torch loading) was a KeyboardInterrupt traceback from the imports; fit
    loads it while parsing (its options' defaults), before the command runs (helper-194's finding)."""
    script = (
        "import sys\n"
        "class CtrlC:\n"
        "    def find_spec(self, name, path, target=None):\n"
        "        if name == 'torch':\n"
        "            raise KeyboardInterrupt\n"
        "sys.meta_path.insert(0, CtrlC())\n"
        "from redsim.cli import main\n"
        f"print(main({argv!r}))\n"
    )
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=False)
    assert (done.returncode, done.stdout, done.stderr) == (0, "130\n", "redsim: warning: interrupted\n")
