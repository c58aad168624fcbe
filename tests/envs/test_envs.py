"""The RedSim Gymnasium suite against the Gymnasium and SB3 contracts, by what users rely on.

The small envs (MiniChain, ConditionalBar) run every check in the default suite; the big ones
(Chain, and the two 6000-DOF cloths, whose construction alone takes seconds on a busy CPU)
run the same checks under ``-m slow``. Float tolerances: the stepper runs in float32.
"""

from __future__ import annotations

import copy
import importlib
import inspect
import json
import logging
import math
import pickle
import re
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.envs.registration import EnvSpec
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

import redsim
from redsim import pretrained, scenes
from redsim.envs.base import ACTION_RESOLUTION_WARNING, MAX_FRAME_SKIP, LatentEnv
from redsim.envs.reach import HandleReach
from redsim.subspace import CheckpointError

FAST = ("RedSim/MiniChain-v0", "RedSim/ConditionalBar-v0")
SLOW = (
    "RedSim/Chain-v0",
    "RedSim/ClothBall-v0",
    "RedSim/ClothBall-v1",
    "RedSim/HangingCloth-v0",
    "RedSim/HangingCloth-v1",
    "RedSim/HangingCloth-v2",
    "RedSim/ConditionalBar-v1",
)
ALL_IDS = [*FAST, *(pytest.param(i, marks=pytest.mark.slow) for i in SLOW)]
LINKAGES = ("RedSim/Klann-v0", "RedSim/Stewart-v0")
"""Not reach tasks: their task checks are in test_linkage_envs.py; the contract checks run here under -m slow."""
SNAP = ("RedSim/BistableBar-v0", "RedSim/BistableBar-v1")
"""Not a reach task either: its task checks are in test_bistable_env.py; the contract checks run here under -m slow."""
CONTRACT_IDS = [*ALL_IDS, *(pytest.param(i, marks=pytest.mark.slow) for i in (*LINKAGES, *SNAP))]


@pytest.fixture(scope="module")
def mini() -> gym.Env:
    return gym.make("RedSim/MiniChain-v0", render_mode="rgb_array")


def _rollout(env: gym.Env, seed: int, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    obs, _ = env.reset(seed=seed)
    observations, rewards = [obs], []
    for a in actions:
        obs, reward, terminated, truncated, _ = env.step(a)
        observations.append(obs)
        rewards.append(reward)
        if terminated or truncated:
            obs, _ = env.reset()
    return np.array(observations), np.array(rewards)


def test_registry_lists_the_suite() -> None:
    assert set(redsim.envs.ids()) == set(FAST) | set(SLOW) | set(LINKAGES) | set(SNAP)
    for env_id in redsim.envs.ids():
        spec = gym.spec(env_id)
        assert spec.max_episode_steps and spec.vector_entry_point
        assert spec.entry_point.startswith("redsim.envs.")


def test_each_env_s_own_docstring_states_its_reward_terms_and_arguments() -> None:
    """help(env.unwrapped) prints the env class's own docstring: the reach envs' carry ReachEnv's formula and table."""
    for env_id in redsim.envs.ids():
        doc = gym.spec(env_id).entry_point
        module, name = doc.split(":")
        text = getattr(__import__(module, fromlist=[name]), name).__doc__
        assert (
            'info["reward_' in text
            and "| `frame_skip` |" in text
            and ":class:`redsim.envs.reach.ReachEnv`)" not in text
        )


SECTIONS = (
    "Description",
    "Action Space",
    "Observation Space",
    "Rewards",
    "Starting State",
    "Episode End",
    "Arguments",
    "Version History",
)
"""Gymnasium's docstring sections, in its order (an env may add its own between them: Klann-v0's Success)."""


def _env_class(env_id: str) -> type[LatentEnv]:
    module, name = gym.spec(env_id).entry_point.split(":")
    return getattr(importlib.import_module(module), name)


def _section(doc: str, name: str) -> str:
    return doc.split(f"\n    ## {name}\n", 1)[1].split("\n    ## ", 1)[0]


def _rows(text: str) -> list[list[str]]:
    """The body rows of the markdown tables in ``text``, as lists of cells (header and rule rows left out)."""
    lines = [line.strip() for line in text.splitlines() if line.strip().startswith("|")]
    rows = [[cell.strip() for cell in line.strip("|").split("|")] for line in lines if not line.startswith("|---")]
    return [row for row in rows if row[0] not in ("Num", "Argument")]


def _indices(num: str) -> list[int]:
    """A table's Num cell (``3`` or ``0-7``) as the indices it covers."""
    first, _, last = num.partition("-")
    return list(range(int(first), int(last or first) + 1))


def _parameters(cls: type[LatentEnv]) -> set[str]:
    """Every keyword argument of an env class: its own ``__init__``'s and those of the LatentEnv classes it passes
    ``**kwargs`` on to (scene, subspace and task are the env's own)."""
    names = set()
    for klass in cls.__mro__:
        if issubclass(klass, LatentEnv) and "__init__" in vars(klass):
            params = inspect.signature(vars(klass)["__init__"]).parameters.values()
            names |= {p.name for p in params if p.kind == p.KEYWORD_ONLY or p.name == "render_mode"}
    return names


@pytest.mark.parametrize("env_id", redsim.envs.ids())
def test_the_env_s_docstring_follows_gymnasium_s_template_and_its_registration(env_id: str) -> None:
    """The docstring is the env's contract (Gymnasium's template): its tables cover every action and observation
    entry its Box literals state, its truncation is the registered one, its Arguments table names every argument the
    env takes and no other, and its Version History every registered version of the id. A review (helper-239) found
    the LatentEnv arguments behind ``**kwargs`` (``randomize_condition``, ``stepper_options``, ``cubature``) missing
    from the tables, ConditionalBar's default of True among them; another (helper-252) found ClothBall's, HangingCloth's
    and ConditionalBar's own rows repeated by the shared ones, each argument is listed once."""
    spec, cls = gym.spec(env_id), _env_class(env_id)
    doc = cls.__doc__
    assert [s for s in re.findall(r"\n    ## (.+)\n", doc) if s in SECTIONS] == list(SECTIONS)
    for name, literal in (
        ("Action Space", r"`Box\(-1, 1, \((\d+),\), float32\)`"),
        ("Observation Space", r"`Box\(low, high, \((\d+),\),\s+float32\)`"),
    ):
        text = _section(doc, name)
        size = int(re.search(literal, text).group(1))
        assert [i for row in _rows(text) for i in _indices(row[0])] == list(range(size)), name
    steps, seconds = re.search(r"Truncation: (\d+) steps\s+\(([\d.]+) s at the default", doc).groups()
    dt = inspect.signature(cls).parameters["dt"].default
    assert int(steps) == spec.max_episode_steps and float(seconds) == pytest.approx(spec.max_episode_steps * dt)
    listed = [name for row in _rows(_section(doc, "Arguments")) for name in re.findall(r"`(\w+)`", row[0])]
    assert sorted({name for name in listed if listed.count(name) > 1}) == []  # ClothBall's `cubature` twice (stop 71)
    named = set(listed)
    assert named == _parameters(cls)
    assert set(spec.kwargs) <= named
    version = env_id.rsplit("-v", 1)[1]
    for key, value in spec.kwargs.items():  # its row gives the id's value: `0.5 (v1, v2: 0.8)`, `(v1 registers 40.0)`
        literal = json.dumps(value) if isinstance(value, str) else repr(value)
        given = rf"\bv{version}\b(?:,\s*v\d+)*(?::| registers)\s*{re.escape(literal)}"
        rows = [" | ".join(row) for row in _rows(_section(doc, "Arguments")) if f"`{key}`" in row[0]]
        assert any(re.search(given, row) for row in rows), (key, value, rows)  # ClothBall-v1's read "v1: a path"
    family = env_id.rsplit("-v", 1)[0]
    versions = [i.rsplit("-v", 1)[1] for i in redsim.envs.ids() if i.rsplit("-v", 1)[0] == family]
    history = _section(doc, "Version History")
    assert [v for v in versions if not re.search(rf"^\s+- (v\d+, )*v{v}[:,]", history, re.M)] == []


@pytest.mark.parametrize("env_id", CONTRACT_IDS)
def test_the_env_s_space_tables_state_its_spaces(env_id: str) -> None:
    """The Box literals are the env's spaces, each observation block (``observation_structure``) starts a table row,
    and every bound the tables give as a number (or in pi and dt) is the space's bound."""
    env = gym.make(env_id).unwrapped
    doc = type(env).__doc__
    actions, observations = _section(doc, "Action Space"), _section(doc, "Observation Space")
    assert f"`Box(-1, 1, ({env.action_space.shape[0]},), float32)`" in actions
    assert env.action_space.dtype == np.float32 and env.observation_space.dtype == np.float32
    assert (env.action_space.low == -1.0).all() and (env.action_space.high == 1.0).all()
    assert re.search(rf"`Box\(low, high, \({env.observation_space.shape[0]},\),\s+float32\)`", observations)
    starts = {_indices(row[0])[0] for row in _rows(observations)}
    assert set(np.cumsum([0, *env.observation_structure.values()])[:-1].tolist()) <= starts
    checked = 0
    for text, space in ((actions, env.action_space), (observations, env.observation_space)):
        for row in _rows(text):
            for cell, bound in ((row[2], space.low), (row[3], space.high)):
                if number := re.fullmatch(r"(-?)(pi/dt|[\d.]+)", cell):
                    value = math.pi / env.dt if number[2] == "pi/dt" else float(number[2])
                    value = -value if number[1] else value
                    assert bound[_indices(row[0])] == pytest.approx(value, rel=1e-6), (row, bound[_indices(row[0])])
                    checked += 1
    assert checked >= 2 * len(_rows(actions))


@pytest.mark.parametrize(
    "env_id",
    [
        *(i for i in redsim.envs.ids() if i in (*FAST, *LINKAGES, "RedSim/BistableBar-v1", "RedSim/ConditionalBar-v1")),
        *(
            pytest.param(i, marks=pytest.mark.slow)
            for i in redsim.envs.ids()
            if i not in (*FAST, *LINKAGES, "RedSim/BistableBar-v1", "RedSim/ConditionalBar-v1")
        ),
    ],
)
def test_the_env_s_docstring_names_every_info_key_of_a_step(env_id: str) -> None:
    """Each key of a step's info is named by the env's own docstring, or by LatentEnv's (the solver's flags).

    A review (helper-213) found Klann-v0's docstring without its linkage invariants and ConditionalBar's without its
    FEM invariants; another (helper-239) ClothBall's without ``membrane_max_strain`` and
    ``rigid_orthogonality_error``."""
    env = gym.make(env_id)
    env.reset(seed=0)
    info = env.step(np.zeros(env.action_space.shape, np.float32))[-1]
    doc, shared = type(env.unwrapped).__doc__, LatentEnv.__doc__
    unnamed = [k for k in info if f"`{k}`" not in doc and f'info["{k}"]' not in doc and f"``{k}``" not in shared]
    assert not unnamed, unnamed


def test_frame_skip_reads_back_as_on_mujoco_envs() -> None:
    env = gym.make("RedSim/MiniChain-v0", frame_skip=2)
    assert env.unwrapped.frame_skip == 2 and env.unwrapped.dt == pytest.approx(0.04)
    venv = gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point", frame_skip=2)
    assert venv.frame_skip == 2 and venv.get_attr("frame_skip") == (2, 2)
    assert gym.make("RedSim/MiniChain-v0", frame_skip=MAX_FRAME_SKIP).unwrapped.frame_skip == MAX_FRAME_SKIP
    refused = rf"frame_skip must be an integer in \[1, {MAX_FRAME_SKIP}\]"
    with pytest.raises(ValueError, match=refused):
        gym.make("RedSim/MiniChain-v0", frame_skip=MAX_FRAME_SKIP + 1)
    for shards in ({}, {"shards": 2}):  # native vector, sharded
        with pytest.raises(ValueError, match=refused):
            gym.make_vec("RedSim/MiniChain-v0", 2, vectorization_mode="vector_entry_point", frame_skip=10**12, **shards)


@pytest.mark.parametrize("env_id", CONTRACT_IDS)
def test_gymnasium_and_sb3_check_env_without_warnings(env_id: str) -> None:
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gym.make(env_id, render_mode="rgb_array")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)  # render check included
        sb3_check_env(env.unwrapped, warn=True)
    assert [str(w.message) for w in caught] == []
    frame = env.unwrapped.render()
    assert frame.shape == (480, 480, 3) and frame.dtype == np.uint8
    drawn = np.any(frame != frame[0, 0], axis=-1).mean()
    assert 0.01 < drawn < 0.9, drawn  # a picture of the shape, not a blank or flooded canvas
    env.close()


def test_make_with_package_prefix_needs_no_import() -> None:
    env = gym.make("redsim:RedSim/MiniChain-v0")
    assert env.spec.id == "RedSim/MiniChain-v0"


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_it_moves_and_the_scripted_controller_gets_closer(env_id: str) -> None:
    """A frozen simulation cannot pass: a held push moves the handle, and PI control shrinks the distance."""
    env = gym.make(env_id).unwrapped
    env.reset(seed=3)
    start = env.sim.task._goal_position(env.sim.x).clone()
    for _ in range(25):
        _, _, terminated, _, info = env.step(np.ones(env.action_space.shape, np.float32))
        assert not terminated
    moved = float((env.sim.task._goal_position(env.sim.x) - start).norm())
    assert moved > 0.2 * env.task.distance_scale, (moved, env.task.distance_scale)
    _, info = env.reset(seed=3)
    first = None
    distances = []
    for _ in range(120):
        _, _, terminated, _, info = env.step(env.task.controller(env.sim)[0])
        first = info["distance"] if first is None else first
        distances.append(info["distance"])
        assert not terminated
    assert min(distances[-20:]) < 0.6 * first, (first, distances[-20:])


def test_vector_env_equals_single_envs_step_for_step() -> None:
    """Same seeds, same actions, same autoresets. Solved in float64 to a tight tolerance, so that what is
    compared is the env logic (seeding, targets, autoreset), not the solver's round-off: a float32 solve stops
    at a relative force balance of 1e-5, and another batch composition lands elsewhere inside it. Even at
    1e-10 the contact-held steps do: copy 1's step 8 stops at residual 6.4e-11 alone and 1.5e-11 in the batch
    (same 17 iterations), and ż = Δz/dt carries that to 7e-7 over the next steps (measured on this CPU; an
    earlier CPU showed none). A wrong seed, target or autoreset differs by 1e-2 or more."""
    n, steps, seed = 3, 12, 7
    tight = {"dtype": "float64", "stepper_options": {"tol": 1e-10, "max_iter": 60}}
    venv = gym.make_vec(
        "RedSim/MiniChain-v0", num_envs=n, vectorization_mode="vector_entry_point", max_episode_steps=5, **tight
    )
    assert venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (steps, n, 3)).astype(np.float32)
    obs, _ = venv.reset(seed=seed)
    vec_obs, vec_rew, vec_done = [obs], [], []
    for a in actions:
        obs, reward, terminated, truncated, _ = venv.step(a)
        vec_obs.append(obs)
        vec_rew.append(reward)
        vec_done.append(terminated | truncated)
    for i in range(n):
        env = gym.make("RedSim/MiniChain-v0", max_episode_steps=5, **tight)
        obs, _ = env.reset(seed=seed + i)
        single_obs, single_rew, autoreset = [obs], [], False
        for a in actions[:, i]:
            if autoreset:  # Gymnasium's NEXT_STEP: this step resets and ignores the action
                obs, _ = env.reset()
                reward, autoreset = 0.0, False
            else:
                obs, reward, terminated, truncated, _ = env.step(a)
                autoreset = terminated or truncated
            single_obs.append(obs)
            single_rew.append(reward)
        np.testing.assert_allclose(np.array(vec_obs)[:, i], np.array(single_obs), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(np.array(vec_rew)[:, i], np.array(single_rew), rtol=1e-5, atol=1e-5)
    assert np.array(vec_done)[4].all()  # truncated at max_episode_steps = 5


def test_a_vector_copys_reset_is_a_single_envs_bit_for_bit_in_float64_and_to_round_off_in_float32() -> None:
    """README: copy i of a vector env seeded s draws what a single env seeded s + i draws; a float32 batch rounds
    the task extras differently (measured 3e-8, 2 ulps of the 0.2 m positions they hold), float64 is bit-equal.
    The bound is a few ulps of the largest entry; another seed's target differs by centimetres."""
    n = 4
    for dtype in ("float64", "float32"):
        venv = gym.make_vec("RedSim/MiniChain-v0", num_envs=n, vectorization_mode="vector_entry_point", dtype=dtype)
        batch, _ = venv.reset(seed=0)
        singles = np.stack([gym.make("RedSim/MiniChain-v0", dtype=dtype).reset(seed=i)[0] for i in range(n)])
        if dtype == "float64":
            assert np.array_equal(batch, singles)
        else:
            np.testing.assert_allclose(batch, singles, rtol=0, atol=4 * np.spacing(np.abs(singles).max()))


def test_reset_noise_scale_perturbs_the_start_reproducibly_and_alike_in_vector_copies() -> None:
    """MuJoCo's convention: z0 + U(-s, s), z_dot s N(0, 1) per latent, from the env's generator; s = 0: at rest."""
    s = 0.05
    plain = gym.make("RedSim/MiniChain-v0", dtype="float64").unwrapped
    noisy = gym.make("RedSim/MiniChain-v0", dtype="float64", reset_noise_scale=s).unwrapped
    rest, _ = plain.reset(seed=3)
    obs, _ = noisy.reset(seed=3)
    d = noisy.sim.latent_dim
    offset, speed = obs[:d] - rest[:d], obs[d : 2 * d]
    assert 0.0 < np.abs(offset).max() <= s and np.abs(offset).min() > 0.0
    assert np.abs(speed).max() > 0.0 and not np.allclose(speed, 0.0)
    for key, value in plain.sim.params.items():  # the same task draw (the target), drawn before the noise
        assert torch.equal(noisy.sim.params[key], value)
    assert np.array_equal(noisy.reset(seed=3)[0], obs)
    assert not np.array_equal(noisy.reset(seed=4)[0][:d], gym.make("RedSim/MiniChain-v0").reset(seed=4)[0][:d])
    venv = gym.make_vec(
        "RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point", dtype="float64", reset_noise_scale=s
    )
    assert np.array_equal(venv.reset(seed=3)[0][0], obs)
    noisy.step(np.zeros(3, np.float32))  # a noisy start steps like any other
    for bad in (-0.1, float("nan"), float("inf"), True, "0.1"):
        with pytest.raises(ValueError, match="reset_noise_scale must be a finite number >= 0"):
            gym.make("RedSim/MiniChain-v0", reset_noise_scale=bad)
    # a start beyond the map's region is flagged in the reset's info, as a step flags it (a review's noise of 100
    # started at |z| 60, its observation clipped to 10, and nothing said so before the first step)
    assert noisy.reset(seed=3)[1]["out_of_range"] is False
    far = gym.make("RedSim/MiniChain-v0", reset_noise_scale=100.0)
    assert far.reset(seed=0)[1]["out_of_range"] is True
    _, infos = venv.reset(seed=3)
    assert infos["out_of_range"].tolist() == [False, False] and infos["_out_of_range"].all()


def test_a_none_seed_in_a_vector_reset_keeps_that_copy_s_generator() -> None:
    """As Gymnasium's sync vector env (and a single env's ``reset(seed=None)``): copy 1 continues its stream."""
    venv = gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point")
    venv.reset(seed=[1, 2])
    obs, _ = venv.reset(seed=[5, None])
    env = gym.make("RedSim/MiniChain-v0")
    env.reset(seed=2)
    np.testing.assert_allclose(obs[1], env.reset()[0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(obs[0], env.reset(seed=5)[0], rtol=0, atol=1e-6)
    assert np.array_equal(venv.reset(seed=np.array([5, 6]))[0], venv.reset(seed=[5, 6])[0])  # NumPy's ints too
    with pytest.raises(ValueError, match="seed must be an int, None or a sequence"):
        venv.reset(seed=2.5)
    generators = venv.get_state()["rngs"]
    for bad in ([3, -1], [3, 1.5]):  # every seed is checked before any copy's generator is replaced
        with pytest.raises(gym.error.Error, match="Seed must be"):
            venv.reset(seed=bad)
        assert venv.get_state()["rngs"] == generators
    with pytest.raises(ValueError, match="num_envs must be an integer"):
        gym.make_vec("RedSim/MiniChain-v0", num_envs=float("nan"), vectorization_mode="vector_entry_point")


def test_same_step_autoreset_reports_the_final_observation() -> None:
    venv = gym.make_vec(
        "RedSim/MiniChain-v0",
        num_envs=2,
        vectorization_mode="vector_entry_point",
        max_episode_steps=2,
        autoreset_mode=AutoresetMode.SAME_STEP,
    )
    venv.reset(seed=0)
    venv.step(np.zeros((2, 3), np.float32))
    obs, _, _, truncated, info = venv.step(np.zeros((2, 3), np.float32))
    assert truncated.all() and info["_final_obs"].all()
    assert not np.array_equal(info["final_obs"][0], obs[0])  # obs is already the next episode's


def test_same_step_infos_have_the_sync_vector_envs_layout() -> None:
    """SAME_STEP, float64 (native and sync equal to round-off): ``final_obs`` an object array (None where no copy
    ended), ``final_info`` a dict of [N] arrays with ``_key`` masks, the ended copies' top-level entries masked out;
    the same keys, masks and values as Gymnasium's sync vector env of the same env."""
    mode = {"autoreset_mode": AutoresetMode.SAME_STEP}
    native = gym.make_vec("RedSim/MiniChain-v0", 3, "vector_entry_point", max_episode_steps=3, dtype="float64", **mode)
    sync = gym.make_vec("RedSim/MiniChain-v0", 3, "sync", vector_kwargs=mode, max_episode_steps=3, dtype="float64")
    actions = np.random.default_rng(0).uniform(-1, 1, (5, 3, 3)).astype(np.float32)
    infos = []
    for venv in (native, sync):
        venv.reset(seed=[0, 1, 2])
        venv.step(actions[0])
        venv.reset(options={"reset_mask": np.array([False, False, True])})  # copy 2 ends a step later
        infos.append([venv.step(a)[4] for a in actions[1:]])
        venv.close()
    for step, (mine, theirs) in enumerate(zip(*infos, strict=True)):
        assert set(mine) == set(theirs), step
        for key, value in theirs.items():
            if key == "final_obs":
                for i, final in enumerate(value):
                    if final is None:
                        assert mine[key][i] is None
                    else:
                        np.testing.assert_allclose(mine[key][i], final, rtol=1e-6, atol=1e-8)
            elif key == "final_info":
                assert set(mine[key]) == set(value)
                ended = value["_is_success"]
                for k, v in value.items():
                    got = mine[key][k]
                    if k.startswith("_"):
                        np.testing.assert_array_equal(got, v)
                    else:
                        np.testing.assert_allclose(got[ended], v[ended], rtol=1e-5, atol=1e-6, err_msg=k)
            elif key.startswith("_"):
                np.testing.assert_array_equal(mine[key], value, err_msg=key)
            else:  # the top-level values, where the masks show them (a review: they were never compared)
                shown = np.asarray(theirs[f"_{key}"], dtype=bool)
                np.testing.assert_allclose(mine[key][shown], value[shown], rtol=1e-5, atol=1e-6, err_msg=key)
    ended = [info["_final_obs"] for info in infos[0] if "_final_obs" in info]
    assert [list(e) for e in ended] == [[True, True, False], [False, False, True]]


@pytest.mark.parametrize("steps", [100, pytest.param(1000, marks=pytest.mark.slow)])
def test_fixed_seed_and_actions_give_bitwise_equal_trajectories(steps: int) -> None:
    actions = np.random.default_rng(1).uniform(-1, 1, (steps, 3)).astype(np.float32)
    a = _rollout(gym.make("RedSim/MiniChain-v0"), 11, actions)
    b = _rollout(gym.make("RedSim/MiniChain-v0"), 11, actions)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    c = _rollout(gym.make("RedSim/MiniChain-v0"), 12, actions[:5])
    assert not np.array_equal(a[0][:6], c[0])  # another seed, another target


def test_an_env_s_stepper_defaults_yield_to_the_user_s_options_key_by_key() -> None:
    """MiniChain-v0 solves cold by default (its ``stepper_defaults``), single and vector; a user's option wins."""
    assert gym.make("RedSim/MiniChain-v0").unwrapped.sim.stepper.warm_start is False
    venv = gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point")
    assert venv.unwrapped.sim.stepper.warm_start is False
    loose = gym.make("RedSim/MiniChain-v0", stepper_options={"tol": 1e-5}).unwrapped.sim.stepper
    assert (loose.warm_start, loose.tol) == (False, 1e-5)
    assert gym.make("RedSim/MiniChain-v0", stepper_options={"warm_start": True}).unwrapped.sim.stepper.warm_start
    assert gym.make("RedSim/ConditionalBar-v0").unwrapped.sim.stepper.warm_start  # the other ids start warm
    # ConditionalBar-v0 limits and keeps its solver models and starts low; one key of the user's replaces one
    bar = gym.make("RedSim/ConditionalBar-v0", stepper_options={"start": "extrapolated"}).unwrapped.sim.stepper
    assert (bar.max_step, bar.warm_refresh, bar.start) == (2.0, False, "extrapolated")


def test_bad_actions_are_clear_errors(mini: gym.Env) -> None:
    mini.reset(seed=0)
    with pytest.raises(ValueError, match="action must be finite"):  # the env's own check, not the stepper's
        mini.step(np.array([np.nan, 0.0, 0.0], np.float32))
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        mini.step(np.zeros(2, np.float32))
    for bad in (["0.1"] * 3, {"a": 1.0}, [[0.1, 0.2], [0.3]]):  # strings are not parsed; ragged is no array
        with pytest.raises(ValueError, match="action must be an array of numbers"):
            mini.step(bad)
    policy_output = torch.zeros(3, requires_grad=True)  # not torch's "Can't call numpy()": the env's own error
    with pytest.raises(ValueError, match=r"torch tensor that requires grad: pass action.detach\(\).cpu\(\).numpy\(\)"):
        mini.step(policy_output)
    with pytest.raises(ValueError, match=r"torch tensor that is on meta"):  # a GPU's, where there is none
        mini.step(torch.zeros(3, device="meta"))
    for nested in (list(torch.zeros(3, requires_grad=True)), (torch.tensor(0.1, requires_grad=True), 0.0, 0.0)):
        with pytest.raises(ValueError, match=r"torch tensor that requires grad: pass action.detach\(\).cpu\(\)"):
            mini.step(nested)  # in a list or tuple too, not torch's RuntimeError from inside np.asarray
    with pytest.raises(ValueError, match=r"torch tensor that is on meta"):
        mini.step([torch.zeros((), device="meta")] * 3)
    mini.step(policy_output.detach())  # a CPU tensor without grad is an array of numbers
    mini.step(list(policy_output.detach()))  # and a list of them
    venv = gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    for bad in (torch.zeros((2, 3), requires_grad=True), [torch.zeros(3, requires_grad=True), torch.zeros(3)]):
        with pytest.raises(ValueError, match=r"torch tensor that requires grad: pass action.detach\(\).cpu\(\)"):
            venv.step(bad)
    with pytest.raises(ValueError, match="options must be a dict"):
        mini.reset(options="target")
    obs, *_ = mini.step(np.array([50.0, -50.0, 0.0], np.float32))  # clipped, not an error
    assert mini.observation_space.contains(obs)
    state = mini.unwrapped.get_state()  # finite but beyond float32's range: clipped too, not "not finite"
    huge = mini.step(np.array([1e39, -1e39, 0.0]))[0]
    mini.unwrapped.set_state(state)
    assert np.array_equal(huge, mini.step(np.array([1.0, -1.0, 0.0], np.float32))[0])


def test_a_subspace_of_another_scene_is_a_clear_error() -> None:
    scene = scenes.build("mini_chain")
    with pytest.raises(CheckpointError, match="fitted to scene 'chain'"):
        LatentEnv(scene, pretrained.load("chain"), HandleReach("bottom", max_force=5.0))
    with pytest.raises(CheckpointError, match="no shipped subspace covers"):
        gym.make("RedSim/MiniChain-v0", scene_params={"density": 1000.0})
    with pytest.raises(ValueError, match="no handle 'tip'"):
        LatentEnv(scene, pretrained.load("mini_chain"), HandleReach("tip", max_force=5.0))


@pytest.mark.parametrize("env_id", [*FAST, *SLOW, *LINKAGES, *SNAP])
def test_every_id_steps_alike_from_a_restored_state(env_id: str) -> None:
    """After a reset and random steps, ``set_state(get_state())`` then a step equals the step from the original
    (same action): obs, reward and flags, and the state after it (about 1 s per id, 15 s in all on one thread)."""
    env = gym.make(env_id).unwrapped
    env.reset(seed=0)
    env.action_space.seed(0)
    for _ in range(3):
        env.step(env.action_space.sample())
    state = env.get_state()
    action = env.action_space.sample()
    obs, reward, terminated, truncated, _ = env.step(action)
    after = env.get_state()
    env.set_state(state)
    obs2, reward2, terminated2, truncated2, _ = env.step(action)
    np.testing.assert_allclose(obs2, obs, rtol=1e-6, atol=1e-6)
    assert np.isclose(reward2, reward, rtol=1e-6, atol=1e-6) and (terminated2, truncated2) == (terminated, truncated)
    again = env.get_state()
    for key in ("z", "z_prev", "model", "carry", "loads", "cond"):
        if after.get(key) is not None:
            np.testing.assert_allclose(again[key], after[key], rtol=1e-6, atol=1e-6, equal_nan=True, err_msg=key)
    assert set(again["params"]) == set(after["params"])
    for key, value in after["params"].items():
        np.testing.assert_allclose(again["params"][key], value, rtol=1e-6, atol=1e-6, err_msg=f"params.{key}")


def test_get_state_set_state_round_trip_exactly(mini: gym.Env) -> None:
    env = mini.unwrapped
    env.reset(seed=5)
    for _ in range(3):
        env.step(np.full(3, 0.5, np.float32))
    state = env.get_state()
    after = [env.step(np.full(3, -0.3, np.float32))[0] for _ in range(3)]
    env.set_state(state)
    again = [env.step(np.full(3, -0.3, np.float32))[0] for _ in range(3)]
    assert np.array_equal(np.array(after), np.array(again))
    env.set_state(state)
    round_trip = env.get_state()
    assert np.array_equal(round_trip["z"], state["z"]) and np.array_equal(round_trip["z_prev"], state["z_prev"])
    with pytest.raises(ValueError, match="shape"):
        env.set_state({**state, "z": state["z"][:2]})
    # the solver's warm start travels with the state; without it the next step builds its own
    assert state["model"].shape == (len(state["z"]),) * 2 and np.isfinite(state["model"]).all()
    with pytest.raises(ValueError, match="model"):
        env.set_state({**state, "model": state["model"][:2]})
    # so does E and dE/dz at z (the stepper's carry), keyed by z: without it the next step evaluates them
    assert state["carry"].shape == (env.sim.stepper.carry_size,) and np.isfinite(state["carry"]).all()
    assert np.array_equal(state["carry"][: len(state["z"])], state["z"])
    with pytest.raises(ValueError, match="carry"):
        env.set_state({**state, "carry": state["carry"][:2]})
    env.set_state({k: v for k, v in state.items() if k not in ("model", "carry")})
    cold = [env.step(np.full(3, -0.3, np.float32))[0] for _ in range(3)]
    d = len(state["z"])  # z within 1e-3, so z_dot = dz / dt within 1e-3 / dt: the float32 solve tolerance
    np.testing.assert_allclose(np.array(cold)[:, :d], np.array(after)[:, :d], rtol=0, atol=1e-3)
    np.testing.assert_allclose(
        np.array(cold)[:, d : 2 * d], np.array(after)[:, d : 2 * d], rtol=0, atol=1e-3 / env.sim.dt
    )


@pytest.mark.parametrize(("env_id", "frame_skip"), [("RedSim/Klann-v0", 2), ("RedSim/MiniChain-v0", 3)])
def test_a_restored_state_reads_the_last_env_step_s_motion_with_frame_skip(env_id: str, frame_skip: int) -> None:
    """x_prev is the shape one env step (frame_skip stepper steps) ago; set_state rebuilt it from z_prev, one stepper
    step ago, so what reads it before the next step (Klann's crank speed, the controllers, a vector env's observation
    of the copies a masked reset leaves) differed from the env that saved the state. A state without z_before (saved
    before stop 44) still loads, as before."""
    saved = gym.make(env_id, frame_skip=frame_skip).unwrapped
    saved.reset(seed=0)
    for _ in range(4):
        saved.step(np.full(saved.action_space.shape, 0.7, np.float32))
    state = saved.get_state()
    restored = gym.make(env_id, frame_skip=frame_skip).unwrapped
    restored.set_state(state)
    assert torch.equal(restored.sim.x_prev, saved.sim.x_prev)
    assert np.array_equal(restored.sim.observe()[0], saved.sim.observe()[0])
    np.testing.assert_array_equal(restored.task.controller(restored.sim), saved.task.controller(saved.sim))
    restored.set_state({k: v for k, v in state.items() if k != "z_before"})
    assert torch.equal(restored.sim.x_prev, restored.sim.full_positions(restored.sim.z_prev))


def test_get_state_needs_a_reset_and_set_state_needs_the_task_s_params_before_one_too() -> None:
    """No state exists before the first reset; a never-reset env (no draw of its own to compare with) still refuses a
    state without the task's parameters, instead of a KeyError at the next step."""
    fresh = gym.make("RedSim/MiniChain-v0").unwrapped
    with pytest.raises(gym.error.ResetNeeded, match=r"before get_state\(\)"):
        fresh.get_state()
    venv = gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point")
    for get in (venv.get_state, lambda: venv.call("get_state")):
        with pytest.raises(gym.error.ResetNeeded, match="call reset"):
            get()
    done = gym.make("RedSim/MiniChain-v0").unwrapped
    done.reset(seed=0)
    state = done.get_state()
    for params in ({}, {"goal": state["params"]["target"]}):
        with pytest.raises(ValueError, match=r"state\['params'\] must have keys \['target'\]"):
            fresh.set_state({**state, "params": params})
    with pytest.raises(ValueError, match=r"state\['params.target'\] must have shape \[1, 3\]"):
        fresh.set_state({**state, "params": {"target": state["params"]["target"][:2]}})
    fresh.set_state(state)
    assert np.array_equal(fresh.step(np.zeros(3, np.float32))[0], done.step(np.zeros(3, np.float32))[0])
    venv.reset(seed=0)
    with pytest.raises(ValueError, match=r"state\['params'\] must have keys \['target'\]"):
        gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point").set_state(
            {**venv.get_state(), "params": {}}
        )


def test_a_state_of_another_env_and_an_unknown_camera_key_are_clear_errors(mini: gym.Env) -> None:
    conditional = gym.make("RedSim/ConditionalBar-v1").unwrapped
    conditional.reset(seed=0)
    mini.unwrapped.reset(seed=0)
    with pytest.raises(ValueError, match=r"the state belongs to another env: scene 'mini_chain'"):
        conditional.set_state(mini.unwrapped.get_state())
    untagged = {k: v for k, v in mini.unwrapped.get_state().items() if k != "setting"}  # a state from before stop 32
    with pytest.raises(ValueError, match=r"state\['cond'\] must be a numeric array .*another env"):
        conditional.set_state(untagged)  # the mini chain has no condition (None)
    with pytest.raises(ValueError, match=r"unknown camera keys \['bogus'\]; valid: \['azimuth'"):
        gym.make("RedSim/MiniChain-v0", render_mode="rgb_array", camera={"bogus": 1, "azimuth": 10})


def test_envs_pickle_and_continue_exactly(mini: gym.Env) -> None:
    env = mini.unwrapped
    env.reset(seed=2)
    env.step(np.full(3, 0.2, np.float32))
    clone = pickle.loads(pickle.dumps(env))
    a = env.step(np.full(3, 0.7, np.float32))[0]
    b = clone.step(np.full(3, 0.7, np.float32))[0]
    assert np.array_equal(a, b)
    assert np.array_equal(env.reset()[0], clone.reset()[0])  # the generator travels too


def test_a_generator_of_another_kind_travels_with_copies_and_states() -> None:
    """Gymnasium's ``np_random`` may be any Generator: a Philox one survives pickle, deepcopy and set_state."""
    env = gym.make("RedSim/MiniChain-v0").unwrapped
    env.reset(seed=0)
    env.np_random = np.random.Generator(np.random.Philox(7))
    state = env.get_state()
    restored = gym.make("RedSim/MiniChain-v0").unwrapped
    restored.reset(seed=1)  # a PCG64 generator
    restored.set_state(state)
    copies = [pickle.loads(pickle.dumps(env)), copy.deepcopy(env), restored]
    next_obs = env.reset()[0]
    for clone in copies:
        assert isinstance(clone.np_random.bit_generator, np.random.Philox)
        assert np.array_equal(clone.reset()[0], next_obs)


def test_vector_generators_of_another_kind_restore_and_a_bad_one_changes_nothing() -> None:
    """The native vector env's ``rngs`` restore by their own kind (as a single env's), and a malformed entry is
    refused before the simulation changes."""
    venv = gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point").unwrapped
    venv.reset(seed=0)
    state = venv.get_state()
    state["rngs"] = [np.random.Generator(np.random.Philox(s)).bit_generator.state for s in (3, 4)]
    other = gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point").unwrapped
    other.reset(seed=1)
    other.set_state(state)
    np.testing.assert_equal(other.get_state()["rngs"], state["rngs"])  # (Philox's state holds arrays)
    mask = np.array([True, False])
    obs = other.reset(options={"reset_mask": mask})[0]
    venv.set_state(state)
    assert np.array_equal(venv.reset(options={"reset_mask": mask})[0], obs)  # the same draws from the Philox streams
    with pytest.raises(AssertionError):  # copy 0's stream moved on, copy 1's did not
        np.testing.assert_equal(other.get_state()["rngs"][0], state["rngs"][0])
    np.testing.assert_equal(other.get_state()["rngs"][1], state["rngs"][1])
    before = other.get_state()
    for bad, message in (
        (None, "must name a NumPy bit generator"),
        ({"bit_generator": "PCG64"}, "not a PCG64 generator state"),  # numpy's KeyError, as a ValueError
        ({"bit_generator": "PCG64", "state": 5}, "not a PCG64 generator state"),  # numpy's TypeError
    ):
        with pytest.raises(ValueError, match=message):
            other.set_state({**venv.get_state(), "z": before["z"] + 1.0, "rngs": [bad, bad]})
        assert np.array_equal(other.get_state()["z"], before["z"])


def test_a_copy_keeps_the_seed_and_spec_so_reading_the_seed_keeps_the_generator() -> None:
    """Gymnasium's ``np_random_seed`` draws a fresh generator where the seed is unset; a copy that dropped it
    would lose its seeded stream on the first read."""
    env = gym.make("RedSim/MiniChain-v0", max_episode_steps=50)
    env.reset(seed=5)
    next_obs = env.unwrapped.reset()[0]
    env.reset(seed=5)
    for clone in (copy.deepcopy(env), pickle.loads(pickle.dumps(env))):
        assert clone.unwrapped.np_random_seed == 5
        assert clone.unwrapped.spec == env.unwrapped.spec
        assert np.array_equal(clone.reset()[0], next_obs)


def test_a_spec_made_with_torch_or_numpy_dtypes_a_device_or_a_path_is_json_and_remakes_the_env() -> None:
    """``dtype=torch.float64`` (or a NumPy dtype, a ``torch.device``, a checkpoint ``Path``) is recorded in the spec
    by its JSON form, so ``spec.to_json()`` (SB3's and RecordVideo's metadata) and ``gym.make(spec)`` work."""
    path = pretrained.path("mini_chain")
    cases = [
        ({"dtype": torch.float64}, {"dtype": "float64"}),
        ({"dtype": np.dtype("float64")}, {"dtype": "float64"}),
        ({"device": torch.device("cpu")}, {"device": "cpu"}),
    ]
    for given, recorded in cases:
        env = gym.make("RedSim/MiniChain-v0", subspace=path, **given)
        spec = EnvSpec.from_json(env.spec.to_json())
        assert spec.kwargs == {"subspace": str(path), **recorded}
        again = gym.make(spec).unwrapped
        assert again.sim.torch_dtype == env.unwrapped.sim.torch_dtype and again.spec == env.unwrapped.spec
    venv = gym.make_vec("RedSim/MiniChain-v0", 2, "vector_entry_point", dtype=torch.float64)
    assert json.loads(venv.spec.to_json())["kwargs"]["dtype"] == "float64"
    from redsim.envs.sb3 import SB3VecEnv  # its vector env is made with AutoresetMode.SAME_STEP

    spec = EnvSpec.from_json(SB3VecEnv.make("RedSim/MiniChain-v0", 2).venv.spec.to_json())
    assert spec.kwargs["autoreset_mode"] == "SameStep"
    assert gym.make_vec(spec, 2, "vector_entry_point").metadata["autoreset_mode"] == AutoresetMode.SAME_STEP


def test_gymnasiums_sync_vector_env_records_a_json_spec_with_dtype_by_name() -> None:
    """``gym.make_vec(id, N, "sync")`` (or ``"async"``) writes its spec in Gymnasium's own code from the kwargs as
    given, where redsim cannot put them in JSON form: ``dtype=torch.float64`` there makes ``spec.to_json()`` a
    TypeError (Gymnasium's), and ``dtype="float64"``, the form the env docs give, is JSON and remakes float64 copies."""
    venv = gym.make_vec("RedSim/MiniChain-v0", 2, "sync", dtype="float64")
    spec = EnvSpec.from_json(venv.spec.to_json())
    assert spec.kwargs["dtype"] == "float64" and spec.kwargs["vectorization_mode"] == "sync"
    again = gym.make_vec(spec)
    assert [env.unwrapped.sim.torch_dtype for env in again.envs] == [torch.float64] * 2
    venv.close()
    again.close()


def test_a_spec_made_with_numpy_scalars_is_json_and_remakes_the_env() -> None:
    """NumPy scalars (a sweep's ``frame_skip=np.int64(2)``, a camera angle of float32) are recorded as the Python
    numbers they hold: ``spec.to_json()`` raised "Object of type int64 is not JSON serializable"."""
    given = {
        "frame_skip": np.int64(2),
        "reset_noise_scale": np.float32(0.1),
        "include_q": np.bool_(True),
        "camera": {"azimuth": np.float32(30.0)},
    }
    env = gym.make("RedSim/MiniChain-v0", **given)
    spec = EnvSpec.from_json(env.spec.to_json())
    assert spec.kwargs == {**given, "camera": {"azimuth": 30.0}} and type(spec.kwargs["frame_skip"]) is int
    again = gym.make(spec)
    np.testing.assert_array_equal(again.reset(seed=3)[0], env.reset(seed=3)[0])
    action = np.full(3, 0.5, np.float32)
    np.testing.assert_array_equal(again.step(action)[0], env.step(action)[0])
    venv = gym.make_vec("RedSim/MiniChain-v0", 2, "vector_entry_point", frame_skip=np.int64(2))
    assert json.loads(venv.spec.to_json())["kwargs"]["frame_skip"] == 2
    venv.close()


def test_info_reports_solver_flags_invariants_rewards_and_q() -> None:
    env = gym.make("RedSim/MiniChain-v0", include_q=True)
    env.reset(seed=0)
    _, reward, _, _, info = env.step(np.zeros(3, np.float32))
    for key in (
        "converged",
        "iterations",
        "residual",
        "energy",
        "out_of_range",
        "diverged",
        "energy_gain",
        "rigid_orthogonality_error",
        "contact_penetration",
        "distance",
        "is_success",
    ):
        assert key in info, key
    terms = [info[f"reward_{t}"] for t in ("distance", "control", "success")]
    assert reward == pytest.approx(sum(terms), rel=1e-5, abs=1e-6)
    assert info["q"].shape == (24,)
    assert info["rigid_orthogonality_error"] < 0.05 and info["contact_penetration"] < 0.01
    assert info["contact_clearance"] == pytest.approx(-info["contact_penetration"]) or info["contact_clearance"] > 0


def test_a_step_s_info_reports_a_stalled_solve_in_every_env() -> None:
    """The stepper's ``StepStats.stalled`` (the line search found no step lowering Phi before max_iter) was in no
    env's info. Float32 asked for a 1e-12 relative residual, below its round-off: the second step's solve stalls
    (measured: 183 of 200 iterations; the first one runs out of them), and the vector env and the SB3 adapter report
    the flag per copy as they report ``diverged``."""
    from redsim.envs.sb3 import SB3VecEnv

    options = {"stepper_options": {"tol": 1e-12, "max_iter": 200}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # tol below float32's round-off, which this test wants
        env = gym.make("RedSim/MiniChain-v0", **options)
        venv = gym.make_vec("RedSim/MiniChain-v0", 2, vectorization_mode="vector_entry_point", **options)
        sb3 = SB3VecEnv.make("RedSim/MiniChain-v0", num_envs=2, **options)
    env.reset(seed=0)
    infos = [env.step(np.ones(3, np.float32))[-1] for _ in range(2)]
    assert [info["stalled"] for info in infos] == [False, True]
    assert not infos[1]["converged"] and infos[1]["iterations"] < 200 and not infos[1]["diverged"]
    venv.reset(seed=0)
    info = venv.step(np.ones((2, 3), np.float32))[-1]
    assert info["stalled"].dtype == bool and info["stalled"].shape == (2,) and info["_stalled"].all()
    sb3.reset()
    rows = sb3.step(np.ones((2, 3), np.float32))[3]
    assert all(row["stalled"].dtype == bool == row["diverged"].dtype for row in rows)


SOLVER_INFO = ("converged", "iterations", "residual", "energy", "diverged", "stalled", "energy_gain", "tunneled")
"""A step's info keys about the solve (and ``energy_gain_tolerance``), which a reset's info has not (it has
``out_of_range``, of the start)."""


def test_reset_info_holds_the_metrics_and_invariants_a_step_reports() -> None:
    """Gymnasium: a reset's info is analogous to a step's. It was empty (``q`` alone with include_q): a user logging
    ``info["distance"]`` or an invariant from the first frame on had nothing at the reset."""
    from redsim.envs.sb3 import SB3VecEnv

    MINI = "RedSim/MiniChain-v0"
    env = gym.make(MINI)
    _, reset_info = env.reset(seed=0)
    step_info = env.step(np.zeros(3, np.float32))[4]
    state = {k for k in step_info if not k.startswith(("reward_", "energy_gain")) and k not in SOLVER_INFO}
    assert set(reset_info) == state and {"distance", "is_success", "rigid_orthogonality_error"} <= state
    assert all(type(reset_info[k]) is type(step_info[k]) for k in state)  # Python numbers, as a step's
    # the vector env: the reset copies only (masks), an autoreset's slot holds the new episode's start as Gymnasium's
    # sync vector env over single envs does, in both modes
    venv = gym.make_vec(MINI, num_envs=3, vectorization_mode="vector_entry_point")
    _, info = venv.reset(seed=0)
    assert set(info) == state | {f"_{k}" for k in state} and info["_distance"].all()
    _, info = venv.reset(options={"reset_mask": np.array([False, True, False])})
    assert info["_distance"].tolist() == [False, True, False] and info["distance"][0] == 0.0
    # (an autoreset's slot, both modes: test_include_q_puts_the_configuration_in_the_reset_info_too)
    # SB3: the new episode's start in reset_infos, the ended step's own values in the step's info
    sb3 = SB3VecEnv.make(MINI, num_envs=2, max_episode_steps=2)
    with pytest.raises(AttributeError, match=r"make it with the setting instead \(SB3VecEnv.make\(ENV_ID"):
        sb3.set_attr("dt", 0.1)
    same = gym.make_vec(
        MINI, num_envs=2, vectorization_mode="vector_entry_point", max_episode_steps=2, autoreset_mode="SameStep"
    )
    same.reset(seed=0)
    sb3.seed(0)
    sb3.reset()
    for _ in range(2):
        rows = sb3.step(np.zeros((2, 3), np.float32))[3]
        info = same.step(np.zeros((2, 3), np.float32))[4]
    assert [row["distance"] for row in rows] == info["final_info"]["distance"].tolist()
    assert [row["distance"] for row in sb3.reset_infos] == info["distance"].tolist()
    # the same where the vector env started without SB3VecEnv.reset (a state restored on it): the adapter learnt the
    # reset info's keys at reset() and, with none learnt, reported the new episode's distance as the ended step's
    restored = SB3VecEnv.make(MINI, num_envs=2, max_episode_steps=2)
    same.reset(seed=0)
    restored.venv.unwrapped.set_state(same.get_state())
    for _ in range(2):
        rows = restored.step(np.zeros((2, 3), np.float32))[3]
        info = same.step(np.zeros((2, 3), np.float32))[4]
    assert [row["distance"] for row in rows] == info["final_info"]["distance"].tolist()
    assert [row["is_success"] for row in rows] == info["final_info"]["is_success"].tolist()
    assert [row["distance"] for row in restored.reset_infos] == info["distance"].tolist()


def test_a_partial_reset_reports_the_metrics_of_a_task_that_reads_the_sims_batch() -> None:
    """The Task doc lets a task read the sim's state (``sim.x_prev``) for the whole batch, as Klann-v0's crank speed
    does: the reset info of some copies evaluated the metrics on those rows' x against every copy's x_prev, and a
    partial reset (reset_mask, an autoreset of some copies) raised a size mismatch."""
    venv = gym.make_vec("RedSim/Klann-v0", num_envs=3, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    venv.step(np.stack([venv.single_action_space.sample() for _ in range(3)]))
    mask = np.array([False, True, False])
    _, info = venv.reset(options={"reset_mask": mask})
    assert info["_crank_speed"].tolist() == mask.tolist() and info["crank_speed"][0] == 0.0
    every = venv.unwrapped.sim.state_info()
    for key in ("crank_speed", "speed_error", "is_success"):
        assert info[key].dtype == every[key].dtype
        np.testing.assert_array_equal(info[key][1], every[key][1], err_msg=key)


def test_include_q_puts_the_configuration_in_the_reset_info_too() -> None:
    from redsim.envs.sb3 import SB3VecEnv

    MINI = "RedSim/MiniChain-v0"
    env = gym.make("RedSim/MiniChain-v0", include_q=True)
    _, info = env.reset(seed=0)
    np.testing.assert_array_equal(info["q"], env.unwrapped.configuration())  # the first frame of an episode's mesh
    assert "q" not in gym.make("RedSim/MiniChain-v0").reset(seed=0)[1]
    venv = gym.make_vec("RedSim/MiniChain-v0", num_envs=3, vectorization_mode="vector_entry_point", include_q=True)
    _, info = venv.reset(seed=0)
    assert info["q"].shape == (3, 24) and info["_q"].all()
    _, info = venv.reset(options={"reset_mask": np.array([False, True, False])})
    assert info["_q"].tolist() == [False, True, False]
    # an autoreset copy's slot holds its new episode's q, metrics and invariants, as in Gymnasium's sync vector env
    # (both modes)
    for mode, steps in ((AutoresetMode.NEXT_STEP, 3), (AutoresetMode.SAME_STEP, 2)):
        options = {"include_q": True, "max_episode_steps": 2}
        native = gym.make_vec(MINI, num_envs=2, vectorization_mode="vector_entry_point", autoreset_mode=mode, **options)
        sync = gym.make_vec(
            MINI, num_envs=2, vectorization_mode="sync", vector_kwargs={"autoreset_mode": mode}, **options
        )
        infos = []
        for env in (native, sync):
            env.reset(seed=0)
            for _ in range(steps):
                info = env.step(np.zeros((2, 3), np.float32))[4]
            infos.append(info)
        for key in ("q", "distance", "is_success", "rigid_orthogonality_error", "contact_clearance"):
            assert infos[0][f"_{key}"].all() and infos[1][f"_{key}"].all()
            np.testing.assert_allclose(infos[0][key], infos[1][key], rtol=1e-5, atol=1e-6, err_msg=key)
    sb3 = SB3VecEnv.make(MINI, num_envs=2, include_q=True, max_episode_steps=2)
    sb3.reset()
    assert all("q" in row and "distance" in row for row in sb3.reset_infos)
    for _ in range(2):
        _, _, done, rows = sb3.step(np.zeros((2, 3), np.float32))
    assert done.all() and all("q" in row and "terminal_observation" in row for row in rows)


def test_bang_bang_soak_stays_finite(mini: gym.Env) -> None:
    env = mini.unwrapped
    env.reset(seed=9)
    rng = np.random.default_rng(9)
    energies = []
    for i in range(150):
        action = np.sign(rng.uniform(-1, 1, 3)).astype(np.float32) if i % 30 < 15 else rng.uniform(-1, 1, 3)
        obs, reward, _terminated, _, info = env.step(action.astype(np.float32))
        assert np.all(np.isfinite(obs)) and np.isfinite(reward) and not info["diverged"]
        energies.append(info["energy"])
    assert np.all(np.isfinite(energies)) and np.ptp(energies) < 100.0  # J; the chain weighs 1.4 kg


@pytest.mark.slow
@pytest.mark.parametrize("env_id", [*FAST, *SLOW, *LINKAGES, *SNAP])
def test_random_and_bang_bang_soak_over_every_env(env_id: str) -> None:
    venv = gym.make_vec(env_id, num_envs=8, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    rng = np.random.default_rng(0)
    stepped = 0
    for i in range(250):  # 2000 env steps
        shape = venv.action_space.shape
        actions = np.sign(rng.uniform(-1, 1, shape)) if i % 50 < 25 else rng.uniform(-1, 1, shape)
        obs, reward, _, _, info = venv.step(actions.astype(np.float32))
        assert np.all(np.isfinite(obs)) and np.all(np.isfinite(reward))
        # a copy's autoreset step (Gymnasium's next-step mode) reports its reset info, without "energy"
        stepped += int(info["_energy"].sum()) if "energy" in info else 0
        assert "energy" not in info or np.all(np.isfinite(info["energy"][info["_energy"]]))
    assert stepped >= 8 * 240


def test_held_targets_are_the_static_positions_under_held_actions() -> None:
    """targets="held" (HangingCloth-v1's targets) on MiniChain: a reset draws from the table, and each entry is the
    handle's position at the float64 latent static equilibrium under its held action (the reference solve)."""
    from redsim.integrators import LatentSpace, latent_equilibrium

    env = gym.make("RedSim/MiniChain-v0", targets="held").unwrapped
    sim, task = env.sim, env.task
    assert task.held_actions.shape == (256, 3) and float(task.held_actions.abs().max()) <= task.target_spread
    env.reset(seed=5)
    assert any(torch.equal(sim.params["target"][0], t) for t in task.held_targets)
    space = LatentSpace(sim.source_scene, sim.subspace)
    for i in range(3):
        loads = task.loads(task.held_actions[i : i + 1].to(torch.float64), {})[0]
        z, info = latent_equilibrium(space, loads, z0=sim._rest_latent(None).to(torch.float64))
        assert info.converged
        reference = task._goal_position(sim.full_positions(z.to(sim.torch_dtype).unsqueeze(0)))[0]
        assert float((reference - task.held_targets[i]).norm()) < 0.1 * task.success_radius
    with pytest.raises(ValueError, match="targets must be one of"):
        gym.make("RedSim/MiniChain-v0", targets="pushed")
    for flag in ("max_force", "target_spread"):  # float() would take "40" and True
        for bad in ("40", True):
            with pytest.raises(ValueError, match=f"{flag} must be a number"):
                gym.make("RedSim/MiniChain-v0", **{flag: bad})
    for flag in ("include_q", "randomize_condition"):
        with pytest.raises(ValueError, match=f"{flag} must be True or False"):
            gym.make("RedSim/ConditionalBar-v0", **{flag: "no"})
    with pytest.raises(ValueError, match="fit_if_missing must be True or False"):  # "no" would have started a fit
        gym.make("RedSim/MiniChain-v0", scene_params={"density": 8000.0}, fit_if_missing="no")
    with pytest.raises(ValueError, match="needs one condition for all episodes"):
        gym.make("RedSim/ConditionalBar-v0", targets="held")


def test_make_builds_an_env_from_any_scene_and_subspace() -> None:
    scene = scenes.build("mini_chain")
    env = redsim.envs.make(scene, pretrained.load("mini_chain", scene), "reach", max_episode_steps=10)
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs) and env.action_space.shape == (3,)
    with pytest.raises(ValueError, match="unknown task"):
        redsim.envs.make("mini_chain", task="balance")


def test_make_takes_minus_one_and_none_as_no_episode_limit_as_gym_make_does() -> None:
    for unlimited in (-1, None):
        env = redsim.envs.make("mini_chain", max_episode_steps=unlimited)
        assert isinstance(env, LatentEnv)  # no TimeLimit
    assert redsim.envs.make("mini_chain", max_episode_steps=np.int64(3))._max_episode_steps == 3
    for bad in (0, -2, 2.5, True, "5"):
        with pytest.raises(ValueError, match=r"max_episode_steps must be None or -1 \(no limit\) or an integer >= 1"):
            redsim.envs.make("mini_chain", max_episode_steps=bad)


def test_conditional_bar_draws_its_condition_per_episode() -> None:
    env = gym.make("RedSim/ConditionalBar-v0").unwrapped
    conditions = {tuple(env.reset(seed=s)[0][-2:].round(4)) for s in range(3)}
    assert len(conditions) == 3
    space = env.sim.scene.condition_space
    for c in conditions:
        assert np.all(np.array(c) >= space.low.numpy() - 1e-6) and np.all(np.array(c) <= space.high.numpy() + 1e-6)


@pytest.mark.parametrize("env_id", CONTRACT_IDS)
def test_sb3_ppo_and_sac_run_a_few_hundred_steps(env_id: str) -> None:
    from stable_baselines3 import PPO, SAC

    from redsim.envs.sb3 import SB3VecEnv

    venv = SB3VecEnv.make(env_id, num_envs=4)
    ppo = PPO("MlpPolicy", venv, n_steps=32, batch_size=64, n_epochs=1, seed=0, policy_kwargs={"net_arch": [16]})
    env = gym.make(env_id)
    sac = SAC("MlpPolicy", env, learning_starts=50, batch_size=32, seed=0, policy_kwargs={"net_arch": [16]})
    for model, steps in ((ppo.learn(256), 256), (sac.learn(150), 150)):  # trained, and its weights stay finite
        assert model.num_timesteps >= steps and model._n_updates > 0
        assert all(bool(torch.isfinite(p).all()) for p in model.policy.parameters())


@pytest.mark.slow
def test_subproc_vec_env_with_spawn_runs_the_envs() -> None:
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    venv = make_vec_env(  # a spawned worker has not imported redsim: the "redsim:" prefix imports it there
        "redsim:RedSim/MiniChain-v0", n_envs=2, vec_env_cls=SubprocVecEnv, vec_env_kwargs={"start_method": "spawn"}
    )
    venv.reset()
    obs, reward, _done, _ = venv.step(np.zeros((2, 3), np.float32))
    assert obs.shape == (2, 14) and np.all(np.isfinite(reward))
    venv.close()


ASYNC_SCRIPT = """
import gymnasium as gym, numpy as np, torch, redsim
torch.set_num_threads(2)
torch.randn(512, 512) @ torch.randn(512, 512)  # the parent has run a parallel region before it forks
venv = gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="async")  # fork on Linux
venv.reset(seed=0)
obs, reward, terminated, truncated, info = venv.step(np.zeros((2, 3), np.float32))
assert obs.shape == (2, 14) and np.all(np.isfinite(reward))
venv.close()
print("ok")
"""


def test_async_vector_env_with_fork_does_not_hang() -> None:
    """Gymnasium's AsyncVectorEnv forks its workers after building an env in the parent; OpenMP's pool does not
    survive fork, so without :mod:`redsim.fork_safety` the workers hung (run in a subprocess: a hang fails here)."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", ASYNC_SCRIPT], capture_output=True, text=True, timeout=240)
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-2000:]


def test_trimesh_export_of_the_current_state(mini: gym.Env) -> None:
    mini.reset(seed=0)
    meshes = mini.unwrapped.trimeshes()
    assert len(meshes) == len(mini.unwrapped.scene.surfaces)
    assert all(m.vertices.shape[1] == 3 and len(m.faces) for m in meshes)


def test_rendering_is_fast_enough_for_video_at_480() -> None:
    """rgb_array stays a real-time rasterizer on the cloth (`redsim bench envs` prints frames/s; README quotes it)."""
    import time

    scene = scenes.build("hanging_sheet")
    from redsim.raster import Marker, SceneView

    q = scene.q_seed
    view = SceneView(scene, q)
    view.draw(q)
    start = time.perf_counter()
    for _ in range(5):
        frame = view.draw(q, markers=[Marker(np.zeros(3))])
    per_frame = (time.perf_counter() - start) / 5
    assert frame.shape == (480, 480, 3)
    assert per_frame < 0.5  # generous: a busy 2-core machine; measured 20-40 ms when idle


def test_frame_skip_observes_the_state_a_step_at_a_time_env_reaches() -> None:
    """frame_skip=2 steps the stepper twice per env step: its observation (z_dot included: the velocity of the
    stepper's last step) equals that of the env stepped twice with the same action (float64)."""
    action = np.array([0.5, -0.3, 0.2], np.float32)
    skipping = gym.make("RedSim/MiniChain-v0", frame_skip=2, dtype="float64")
    single = gym.make("RedSim/MiniChain-v0", dtype="float64")
    skipping.reset(seed=0)
    single.reset(seed=0)
    single.step(action)
    np.testing.assert_allclose(skipping.step(action)[0], single.step(action)[0], rtol=1e-6, atol=1e-6)
    assert skipping.observation_space == single.observation_space


def test_make_names_a_scene_or_task_of_the_wrong_type() -> None:
    with pytest.raises(TypeError, match="scene must be a redsim"):
        redsim.envs.make(None, "x.pt")
    with pytest.raises(TypeError, match="task must be"):
        redsim.envs.make("mini_chain", task=None)
    # a module that is no map was taken for a checkpoint path (TypeError "expected str, bytes or os.PathLike")
    with pytest.raises(ValueError, match="the subspace Linear has no latent_dim"):
        redsim.envs.make(scenes.build("mini_chain"), torch.nn.Linear(2, 24))
    # neither a map nor a path: named (pathlib's "expected str, bytes or os.PathLike" before; a review's finding)
    with pytest.raises(TypeError, match=r"subspace must be a map .* or a checkpoint path, got 42"):
        redsim.envs.make(scenes.build("mini_chain"), 42)
    # fit_subspace's result for its map: the message held the result's repr, the whole training history (35 kB)
    from redsim.trainers.fit import FitResult

    fitted = FitResult(pretrained.load("mini_chain"), [{"loss": 1.0}] * 10_000, 1.0)
    with pytest.raises(TypeError, match=r"got a FitResult: pass its .subspace$") as refused:
        redsim.envs.make(scenes.build("mini_chain"), fitted)
    assert len(str(refused.value)) < 200


def test_make_of_a_catalog_scene_object_takes_its_shipped_subspace() -> None:
    """A catalog scene given as the object (not its name) was refused as 'not a catalog name'; it now takes the
    shipped map, which refuses the scene built with other parameters, and a catalog scene without a shipped map says
    so."""
    env = redsim.envs.make(scenes.build("mini_chain"))
    assert env.unwrapped.sim.scene.name == "mini_chain"
    with pytest.raises(CheckpointError, match="fingerprint"):
        redsim.envs.make(scenes.build("mini_chain", density=1000.0))
    with pytest.raises(ValueError, match="scene 'cantilever' has no shipped subspace: give one"):
        redsim.envs.make(scenes.build("cantilever"))


def test_the_rest_latent_is_solved_once_per_process_and_read_back_by_the_next(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """An env made again with the same scene, map, dtype and device reuses the rest solve (ClothBall-v1's takes
    ~0.6 s; the suite makes hundreds of envs), whatever its task's arguments; another dtype solves its own; a new
    process reads it back from the user cache bit for bit; an env that draws its condition per episode solves the
    default condition's rest once (at construction its task solved it twice)."""
    from redsim.envs import base
    from redsim.runtime import LatentStepper

    solves = []
    solve = LatentStepper._solve_rest
    monkeypatch.setattr(LatentStepper, "_solve_rest", lambda self, *args: solves.append(1) or solve(self, *args))
    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    base._rest_cache.clear()
    first = gym.make("RedSim/MiniChain-v0").unwrapped.sim._rest
    again = gym.make("RedSim/MiniChain-v0", max_force=2.0).unwrapped.sim._rest
    assert len(solves) == 1 and torch.equal(first, again) and first.data_ptr() != again.data_ptr()
    float64 = gym.make("RedSim/MiniChain-v0", dtype="float64").unwrapped.sim._rest
    assert len(solves) == 2 and float64.dtype == torch.float64 and torch.allclose(float64.float(), first)
    base._rest_cache.clear()  # as in a new process
    back = gym.make("RedSim/MiniChain-v0").unwrapped.sim._rest
    assert len(solves) == 2 and torch.equal(back, first) and back.dtype == first.dtype
    assert len(list((tmp_path / "envs").glob("rest-latent-*.npz"))) == 2
    # the map as it computes: a float64 copy of the same weights (one checkpoint fingerprint) solves its own rest
    shipped = gym.make("RedSim/MiniChain-v0").unwrapped.sim.subspace
    double = copy.deepcopy(shipped).double()
    assert base.map_key(double) != base.map_key(shipped)
    layer = torch.nn.Linear(2, 2)
    plain = base.map_key(layer)
    layer.order = 3  # a setting outside the weights (an anchored map's order and radius) is part of the key
    assert base.map_key(layer) != plain
    solves.clear()
    gym.make("RedSim/MiniChain-v0", subspace=double)
    assert len(solves) == 1
    solves.clear()
    envs = [gym.make("RedSim/ConditionalBar-v1") for _ in range(2)]  # the default condition's rest: made it solve 2
    assert len(solves) == 1
    envs[0].reset(seed=0)  # a condition drawn for the episode solves its own
    assert len(solves) == 2
    # the fixed camera frames the rest under each corner of the condition box: solved once (the env's frame and its
    # task's targets solved each twice), and not again for an env made again
    solves.clear()
    frames = []
    for _ in range(2):
        env = gym.make("RedSim/ConditionalBar-v1", render_mode="rgb_array")
        env.reset(seed=0)
        solves.clear()
        frames.append(env.render())
        assert len(solves) == (4 if len(frames) == 1 else 0)
    np.testing.assert_array_equal(frames[0], frames[1])


def test_held_targets_are_settled_once_per_process_for_identical_envs() -> None:
    from redsim.envs import reach

    reach._held_cache.clear()
    first = gym.make("RedSim/MiniChain-v0", targets="held", target_spread=0.5).unwrapped.sim.task.held_targets
    again = gym.make("RedSim/MiniChain-v0", targets="held", target_spread=0.5).unwrapped.sim.task.held_targets
    assert len(reach._held_cache) == 1 and torch.equal(first, again) and first.data_ptr() != again.data_ptr()
    other = gym.make("RedSim/MiniChain-v0", targets="held", target_spread=0.4).unwrapped.sim.task.held_targets
    assert len(reach._held_cache) == 2 and not torch.equal(first, other)
    float64 = gym.make(
        "RedSim/MiniChain-v0", targets="held", target_spread=0.5, dtype="float64"
    ).unwrapped.sim.task.held_targets
    assert len(reach._held_cache) == 3 and float64.dtype == torch.float64


def test_stewart_s_frame_is_solved_once_per_process_and_caches_keep_their_newest_entries(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Stewart-v0's fixed camera solves 64 static equilibria (5-8 s): an identical env made again reuses them."""
    from redsim.envs import base, stewart

    calls = []

    def corners(self, sim):
        calls.append(self.target_spread)
        return np.full((2, 3), float(len(calls)))

    monkeypatch.setattr(stewart.PlatePose, "_corner_points", corners)
    stewart._frame_cache.clear()
    envs = [gym.make("RedSim/Stewart-v0", target_spread=s).unwrapped for s in (0.5, 0.5, 0.4)]
    frames = [env.sim.task.frame_points(env.sim) for env in envs]
    assert calls == [0.5, 0.4] and np.array_equal(frames[0], frames[1]) and not np.array_equal(frames[0], frames[2])
    frames[0][:] = -1.0  # a caller's copy: the cache keeps its own
    assert np.array_equal(envs[1].sim.task.frame_points(envs[1].sim), np.full((2, 3), 1.0))
    cache: dict = {}
    for key in range(base.PROCESS_CACHE_SIZE + 2):
        base.cached(cache, key, lambda key=key: key * 10)
    assert list(cache) == list(range(2, base.PROCESS_CACHE_SIZE + 2))
    assert base.cached(cache, 5, lambda: pytest.fail("computed again")) == 50


@pytest.mark.slow  # 9 s (a second process); their keys and the per-process cache stay in the default suite
def test_held_targets_are_kept_on_disk_for_the_next_process(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A process that finds the held targets on disk reads them back bit for bit instead of settling again; a damaged
    file, or one of another key, is warned about and settled again; REDSIM_CACHE=0 writes nothing."""
    from redsim.envs import reach

    settles = []
    settle = reach.HandleReach._settle

    def counted(self, sim):
        settles.append(self.target_spread)
        return settle(self, sim)

    def task(spread: float = 0.5):
        reach._held_cache.clear()  # as in a new process
        return gym.make("RedSim/MiniChain-v0", targets="held", target_spread=spread).unwrapped.sim.task

    monkeypatch.setattr(reach.HandleReach, "_settle", counted)
    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    first = task()
    (path,) = (tmp_path / "envs").glob("held-targets-*.npz")
    again = task()
    assert settles == [0.5]
    for old, new in ((first.held_actions, again.held_actions), (first.held_targets, again.held_targets)):
        assert torch.equal(old, new) and (old.dtype, old.device) == (new.dtype, new.device)
    good = path.read_bytes()
    task(0.4)
    (other,) = set((tmp_path / "envs").glob("held-targets-*.npz")) - {path}
    for damage in (b"not a zip file", good[:100], other.read_bytes()):
        path.write_bytes(damage)
        with caplog.at_level(logging.WARNING, logger="redsim"):
            assert torch.equal(task().held_targets, first.held_targets)
        assert "ignoring unreadable held targets cache file" in caplog.text
        caplog.clear()
    assert settles == [0.5, 0.4, 0.5, 0.5, 0.5]
    task()  # each settled again rewrote the file
    assert len(settles) == 5
    monkeypatch.setenv("REDSIM_CACHE", "0")
    before = set(tmp_path.rglob("*"))
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)
    task()
    assert len(settles) == 6 and set(tmp_path.rglob("*")) == before | {work} and not any(work.iterdir())


def test_an_unusable_cache_folder_never_stops_an_env(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from redsim.envs import reach

    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path / ("a" * 300)))  # a name too long to check or create
    reach._held_cache.clear()
    with caplog.at_level(logging.WARNING, logger="redsim"):
        env = gym.make("RedSim/MiniChain-v0", targets="held", target_spread=0.5)
    assert env.unwrapped.sim.task.held_targets.shape == (reach.HELD_SAMPLES, 3)
    assert "ignoring unreadable held targets cache file" in caplog.text and "could not write" in caplog.text


def test_held_targets_are_keyed_by_what_the_stepped_energy_computes(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """An energy passed through ``stepper_options`` settles its own targets: one on a stiffer scene gets a key (and
    targets) of its own, and an energy of the user's own class is never cached (it is settled at every make and
    nothing is written), since what it computes is not known by value."""
    from redsim.envs import reach
    from redsim.runtime.energy import MapEnergy

    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    subspace = pretrained.load("mini_chain", scenes.build("mini_chain"))
    settles = []
    settle = reach.HandleReach._settle
    monkeypatch.setattr(reach.HandleReach, "_settle", lambda self, sim: settles.append(1) or settle(self, sim))

    def sim(energy=None):
        options = {} if energy is None else {"stepper_options": {"energy": energy}}
        return gym.make("RedSim/MiniChain-v0", targets="held", target_spread=0.5, **options).unwrapped.sim

    reach._held_cache.clear()
    default = sim()
    stiffer = sim(MapEnergy(scenes.build("mini_chain", rigid_stiffness=20000.0), subspace))
    assert default.task._held_key(default) != stiffer.task._held_key(stiffer) and len(settles) == 2
    assert len(list((tmp_path / "envs").glob("held-targets-*.npz"))) == 2

    class Mine(MapEnergy):  # a user's energy: its state is its own
        pass

    for _ in range(2):
        mine = sim(Mine(scenes.build("mini_chain"), subspace))
        assert mine.task._held_key(mine) is None
    assert len(settles) == 4 and len(list((tmp_path / "envs").glob("held-targets-*.npz"))) == 2
    assert torch.equal(mine.task.held_targets, default.task.held_targets)  # the same physics, settled again


def test_held_targets_and_their_key_do_not_depend_on_torch_s_default_dtype() -> None:
    from redsim.envs import reach

    def held() -> tuple:
        reach._held_cache.clear()
        sim = gym.make("RedSim/MiniChain-v0", targets="held", target_spread=0.5).unwrapped.sim
        return sim.task._held_key(sim), sim.task.held_actions, sim.task.held_targets

    first = held()
    default = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        second = held()
    finally:
        torch.set_default_dtype(default)
    assert first[0] == second[0] and all(torch.equal(a, b) for a, b in zip(first[1:], second[1:], strict=True))


@pytest.mark.parametrize("env_id", ["RedSim/MiniChain-v0", "RedSim/BistableBar-v1"])
def test_an_env_steps_alike_whatever_torch_s_default_dtype(env_id: str) -> None:
    """torch.set_default_dtype(torch.float64) in the user's process changes neither the map's weights (loaded in the
    checkpoint's dtype) nor a task's seeded draws (BistableBar-v1's start search): the same observations,
    bit for bit."""

    def rollout() -> np.ndarray:
        env = gym.make(env_id)
        observations = [env.reset(seed=0)[0]]
        rng = np.random.default_rng(0)
        for _ in range(4):
            observations.append(env.step(rng.uniform(-0.5, 0.5, env.action_space.shape).astype(np.float32))[0])
        return np.array(observations)

    first = rollout()
    default = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        again = rollout()
        loaded = pretrained.load("mini_chain", scenes.build("mini_chain"))
    finally:
        torch.set_default_dtype(default)
    assert np.array_equal(first, again)
    assert {p.dtype for p in loaded.parameters()} == {torch.float32}


def test_the_cache_keys_tell_apart_maps_that_share_their_weights() -> None:
    import dataclasses

    from redsim.envs.base import map_key

    sub = pretrained.load("mini_chain", scenes.build("mini_chain"))
    other = copy.deepcopy(sub)
    other.config = dataclasses.replace(sub.config, activation="tanh")
    assert map_key(sub)[2] == map_key(other)[2] and map_key(sub) != map_key(other)


def test_the_disk_cache_of_settled_work_returns_what_was_computed(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """:func:`redsim.envs.base.cached` with ``disk``: a tensor, an array, or a tuple of them comes back with its type,
    dtype and values; a file with the right key but unusable fields is warned about and computed again."""
    from redsim.envs import base

    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    values = {
        "tuple": (torch.arange(6, dtype=torch.float32).reshape(2, 3), np.array([[1.5, -2.0]])),
        "array": np.linspace(0.0, 1.0, 5),
        "tensor": torch.tensor([1, 2], dtype=torch.int64),
    }
    for name, value in values.items():
        base.cached({}, ("key", name), lambda value=value: value, disk="test")
        back = base.cached({}, ("key", name), lambda: pytest.fail("computed again"), disk="test")
        pairs = zip(value, back, strict=True) if isinstance(value, tuple) else [(value, back)]
        assert isinstance(back, tuple) == isinstance(value, tuple)
        for old, new in pairs:
            assert type(old) is type(new) and old.dtype == new.dtype and old.shape == new.shape
            assert (old == new).all()
    keys = {}
    for file in (tmp_path / "envs").glob("*.npz"):
        assert file.name.startswith("test-")  # named by what it holds
        with np.load(file) as data:
            keys[file] = data["key"]
    (path,) = [file for file, key in keys.items() if "'array'" in str(key)]
    np.savez(path, key=keys[path])  # the right key, no fields
    with caplog.at_level(logging.WARNING, logger="redsim"):
        assert base.cached({}, ("key", "array"), lambda: np.zeros(1), disk="test").shape == (1,)
    assert "ignoring unusable test cache file" in caplog.text
    caplog.clear()

    def check(value: np.ndarray) -> str:
        return "" if value.shape == (2,) else f"shape {value.shape}"

    with caplog.at_level(logging.WARNING, logger="redsim"):  # the file now holds np.zeros(1): refused by the check
        assert base.cached({}, ("key", "array"), lambda: np.ones(2), disk="test", check=check).shape == (2,)
    assert "ignoring unusable test cache file" in caplog.text and "shape (1,)" in caplog.text
    assert base.cached({}, ("key", "array"), lambda: pytest.fail("computed again"), disk="test", check=check)[0] == 1


def test_stewart_s_frame_is_kept_on_disk_for_the_next_process(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from redsim.envs import stewart

    calls = []

    def corners(self, sim):
        calls.append(self.target_spread)
        return np.full((2, 3), 7.0)

    monkeypatch.setattr(stewart.PlatePose, "_corner_points", corners)
    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    for _ in range(2):
        stewart._frame_cache.clear()  # as in a new process
        env = gym.make("RedSim/Stewart-v0").unwrapped
        assert np.array_equal(env.sim.task.frame_points(env.sim), np.full((2, 3), 7.0))
    assert len(calls) == 1


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_an_env_on_cuda_leaves_the_caller_s_map_where_it_was() -> None:
    scene = scenes.build("mini_chain")
    sub = pretrained.load("mini_chain", scene)
    env = redsim.envs.make(scene, sub, device="cuda")
    env.reset(seed=0)
    assert np.isfinite(env.step(env.action_space.sample())[0]).all()
    assert {p.device.type for p in sub.parameters()} == {"cpu"}
    assert {p.device.type for p in env.unwrapped.sim.subspace.parameters()} == {"cuda"}


CUDA_OPTIONS = {"RedSim/Stewart-v0": {"target_rotation": np.eye(3)}, "RedSim/BistableBar-v0": {"start_side": 1}}
"""A reset option per id whose task draws or checks it with tensors (the reach tasks' target is the fallback)."""


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("env_id", [*FAST, *SLOW, *LINKAGES, *SNAP])
def test_every_id_runs_on_cuda(env_id: str) -> None:
    """Reset (its task's draw), an option, steps, a state round trip, a picture and bench envs' full-space step."""
    from redsim.envs.bench import _full_space_step

    env = gym.make(env_id, device="cuda", render_mode="rgb_array")
    env.reset(seed=0)
    for _ in range(3):
        obs, *_ = env.step(env.action_space.sample())
    assert np.isfinite(obs).all() and env.unwrapped.sim.z.device.type == "cuda"
    state = env.unwrapped.get_state()
    after = env.step(np.ones(env.action_space.shape, np.float32))[0]
    env.unwrapped.set_state(state)
    assert np.array_equal(env.step(np.ones(env.action_space.shape, np.float32))[0], after)
    assert env.render().shape == (480, 480, 3)
    sim = env.unwrapped.sim
    reach = {"target": sim.params["target"][0].cpu().numpy()} if "target" in sim.task.reset_options else {}
    env.reset(seed=1, options=CUDA_OPTIONS.get(env_id, reach))
    assert _full_space_step(env.unwrapped, 1, 0.0, np.random.default_rng(0), warmup=1)["step_s"] > 0


def test_an_env_too_coarse_to_feel_its_actions_warns_at_its_first_reset() -> None:
    """float32 at dt 0.005 s on the mini chain cannot feel actions below ~8% of their range: the first reset warns
    (once); float64 resolves 1000x finer (its tol) and the default dt stays under 1%, both silent."""
    with pytest.warns(UserWarning, match=r"cannot feel actions below .* of their range"):
        coarse = gym.make("RedSim/MiniChain-v0", dt=0.005)
        coarse.reset(seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        coarse.reset(seed=1)  # once per env
        fine = gym.make("RedSim/MiniChain-v0", dt=0.005, dtype="float64")
        fine.reset(seed=0)
        default = gym.make("RedSim/MiniChain-v0")
        default.reset(seed=0)
    resolution = coarse.unwrapped.sim.action_resolution
    assert resolution.shape == (3,) and (resolution > ACTION_RESOLUTION_WARNING).all()
    np.testing.assert_allclose(fine.unwrapped.sim.action_resolution, resolution / 1000, rtol=1e-3)
    assert (default.unwrapped.sim.action_resolution < 0.01).all()
    with pytest.warns(UserWarning, match=r"cannot feel any value of an action \(the least it feels is .*x its range"):
        gym.make("RedSim/MiniChain-v0", dt=0.005, max_force=0.01).reset(seed=0)  # was "below 1234.5% of their range"


def test_the_chains_info_counts_links_that_passed_through_each_other() -> None:
    """``contact_unlinked`` (redsim.envs.invariants): 0 at rest and in a chain moved whole; 2 once link 0 is lifted
    through the hook (its ring through the hook's torus and the hook's through its own); 4 where link 0 alone slid
    5.5 cm sideways through the hook's wire and link 1's, its ends resting against the wires' far sides, which the
    tunnel test cannot tell from points resting in contact (helper-219's case)."""
    from redsim.envs.invariants import Invariants
    from redsim.integrators.tunneling import TunnelTest

    scene = scenes.build("mini_chain")
    invariants = Invariants(scene)
    x = scene.full_positions(scene.q_seed.unsqueeze(0))
    moved, lifted, slid = x.clone(), x.clone(), x.clone()
    moved[:, 7::12] -= 0.01  # the chain 1 cm down: still hooked
    lifted[:, 7::12] += 0.2  # link 0 up through the hook (link 1 with it: their pair stays linked)
    slid[:, 3] += 0.055  # link 0 alone slid along x: through the hook's wire and link 1's
    unlinked = invariants(torch.cat([x, moved, lifted, slid]))["contact_unlinked"]
    assert unlinked.tolist() == [0.0, 0.0, 2.0, 4.0]
    assert not bool(TunnelTest(scene)(x, slid)[0])  # the detector misses the slide; the topology does not
    env = gym.make("RedSim/MiniChain-v0").unwrapped
    env.reset(seed=0)
    assert env.step(np.zeros(env.action_space.shape, np.float32))[-1]["contact_unlinked"] == 0.0
