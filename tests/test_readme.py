"""README.md's and docs/*.md's code blocks run as written: every ```python block on its own, top to bottom, in an
empty folder; every `redsim ...` command line of the ```bash blocks parses, and the cheap ones run.

The commands that take minutes (fits with presets, `bench`, `simulate` of real scenes) are only
parsed by default; the slow test runs the `simulate` lines too.
"""

from __future__ import annotations

import re
import shlex
import shutil
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from redsim import pretrained
from redsim.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
if not README.is_file():  # the tests copied beside an installed wheel
    pytest.skip("needs the source checkout (README.md, docs/)", allow_module_level=True)
DOCS = sorted((ROOT / "docs").glob("*.md"))
"""The history and detail moved out of the README; their blocks are held to the same checks."""
FILES = [README, *DOCS]
FENCE = re.compile(r"^( *)```(\w*)\n(.*?)^ *```", re.S | re.M)
"""A fenced block, also one indented in a list item (its body is dedented by the fence's indent)."""
CHEAP = ("scenes", "inspect", "sample", "animate")
"""Commands that run in seconds (`inspect`/`sample`/`animate` on the shipped mini chain map)."""
PIXELS = "CnnPolicy"
"""What marks README's "Learning from pixels" block, which its own test runs (and checks what it built)."""


def name(path: Path) -> str:
    """The file as the test ids show it: README.md, docs/env-speed.md, ..."""
    return path.relative_to(ROOT).as_posix()


def blocks(language: str, path: Path = README) -> list[str]:
    return [
        re.sub(f"(?m)^{indent}", "", body) for indent, lang, body in FENCE.findall(path.read_text()) if lang == language
    ]


def redsim_commands(path: Path = README) -> list[list[str]]:
    """Every `redsim ...` command of the bash blocks (split at `&&`, comments dropped), as argv lists."""
    commands = []
    for block in blocks("bash", path):
        for line in block.splitlines():
            for part in line.split("&&"):
                argv = shlex.split(part, comments=True)
                if argv and argv[0] == "redsim":
                    commands.append(argv[1:])
    return commands


def python_blocks() -> list:
    return [
        pytest.param(path, index, id=f"{name(path)} python block {index}")
        for path in FILES
        for index, code in enumerate(blocks("python", path))
        if not (path == README and PIXELS in code)  # run by test_the_pixels_recipe_trains_a_cnn_policy_on_frame_stacks
    ]


def command_params(kinds: tuple[str, ...] | None = None) -> list:
    """Every `redsim` command of FILES as argv (of `kinds` only, if given), with the file in its test id."""
    return [
        pytest.param(argv, id=f"{name(path)}: {' '.join(argv)}"[:140])
        for path in FILES
        for argv in redsim_commands(path)
        if kinds is None or (argv[0] in kinds and not any(p.startswith("subspaces/part") for p in argv))
    ]


def test_readme_has_the_blocks_this_test_reads() -> None:
    assert len(blocks("python")) >= 2
    commands = [argv[0] for argv in redsim_commands()]
    assert {"scenes", "simulate", "fit", "inspect", "sample", "animate"} <= set(commands)


def test_docs_are_linked_from_the_readme() -> None:
    """Every docs/*.md file is linked from the README, and every docs/ file the README names exists."""
    assert DOCS, "docs/ holds the history moved out of the README"
    readme = README.read_text()
    for path in DOCS:
        assert f"({name(path)})" in readme, f"README.md does not link {name(path)}"
    for named in set(re.findall(r"docs/[\w.-]+\.md", readme)):
        assert (ROOT / named).is_file(), f"README.md names {named}, which does not exist"


@pytest.mark.parametrize(("path", "index"), python_blocks())
def test_python_block_runs_on_its_own(path: Path, index: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    code = blocks("python", path)[index]
    exec(compile(code, f"{name(path)} python block {index}", "exec"), {"__name__": "__main__"})  # as a script runs it


def test_the_pixels_recipe_trains_a_cnn_policy_on_frame_stacks(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """README's "Learning from pixels" block runs as written, what it trains is SB3's CNN policy over stacks of 4
    grey 84 px frames (uint8 [4, 84, 84]) for the steps it asks, and Gymnasium's and SB3's check_env pass on the
    wrapped env (as the README says)."""
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env
    from stable_baselines3.common.policies import ActorCriticCnnPolicy

    (code,) = [block for block in blocks("python") if PIXELS in block and "AddRenderObservation" in block]
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__main__"}
    exec(compile(code, "README.md pixels block", "exec"), namespace)
    model, obs = namespace["model"], namespace["obs"]
    assert isinstance(model.policy, ActorCriticCnnPolicy)
    assert model.observation_space.shape == obs.shape == (4, 84, 84) and obs.dtype == np.uint8
    assert model.num_timesteps >= 256
    assert len(np.unique(obs)) > 2  # a picture, not a blank frame
    env = namespace["env"]
    if tuple(map(int, gym.__version__.split(".")[:2])) >= (1, 4):
        check_env(env, skip_render_check=True)
    else:  # 1.2 (ray[rllib] 2.60's pin) and 1.3: the wrapper records `pixels_only=`, its __init__ takes `render_only=`
        with pytest.raises(TypeError, match="pixels_only"):
            env.spec.make()  # what check_env's close check does
        check_env(env, skip_render_check=True, skip_close_check=True)
    sb3_check_env(env, warn=False)


def test_the_vector_pixels_recipe_trains_a_cnn_policy_on_every_copys_frames(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """README's block of `SB3VecEnv.make(..., pixels=...)` runs as written and trains SB3's CNN policy on 8 copies'
    stacks of 4 grey 84 px frames (SB3 transposes them to [4, 84, 84])."""
    from stable_baselines3.common.policies import ActorCriticCnnPolicy

    (code,) = [block for block in blocks("python") if PIXELS in block and "pixels=" in block]
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__main__"}
    exec(compile(code, "README.md vector pixels block", "exec"), namespace)
    model = namespace["model"]
    assert isinstance(model.policy, ActorCriticCnnPolicy) and model.n_envs == 8
    assert model.observation_space.shape == (4, 84, 84) and model.observation_space.dtype == np.uint8
    assert model.num_timesteps >= 256
    model.get_env().close()


@pytest.mark.parametrize("argv", command_params())
def test_redsim_command_parses(argv: list[str]) -> None:
    args = build_parser().parse_args(argv)
    assert callable(args.func)


def _shipped_mini_chain(folder: Path) -> None:
    """Put the shipped mini chain map where the README's fit writes it (it was made by that command)."""
    target = folder / "subspaces"
    target.mkdir(exist_ok=True)
    for suffix in (".pt", ".json"):
        shutil.copy(pretrained.path("mini_chain").with_suffix(suffix), target / f"mini_chain{suffix}")


@pytest.mark.parametrize("argv", command_params(CHEAP))
def test_cheap_redsim_command_runs(argv: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    _shipped_mini_chain(tmp_path)
    assert main(argv) == 0


@pytest.mark.slow
@pytest.mark.parametrize("argv", command_params(("simulate",)))
def test_simulate_command_runs(argv: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    if "--mesh" in argv:
        pytest.skip("needs the user's own mesh file")
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 0
