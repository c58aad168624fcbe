"""Each registered env's docstring read the way a user reads MuJoCo's env docs, checked against the running env.

tests/envs/test_envs.py checks the docstrings' form (sections in Gymnasium's order, tables covering every index, the
Arguments table naming every constructor argument, the truncation and the versions); this file checks what the tables
and formulas *say* against what the made env does: the force a unit action puts on which handle along which axis, what
each observation row holds (computed from the env's state, not read back from the observation), the reward's weights
and terms, each argument's stated default, the version list both ways, and README's env table. A review (helper-277,
stop 73) wrote it so that a docstring drifting from its env fails here. Float tolerances: the envs step in float32.
"""

from __future__ import annotations

import ast
import functools
import inspect
import math
import re
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch

import redsim
from redsim.envs.base import LatentEnv
from redsim.envs.reach import ReachEnv

IDS = redsim.envs.ids()
AXES = {"x": 0, "y": 1, "z": 2}
README = Path(__file__).resolve().parents[2] / "README.md"


@functools.cache
def _env(env_id: str) -> gym.Env:
    """One env per id for the whole file (made once: the cloth envs' construction is the slow part)."""
    return gym.make(env_id)


def _table(doc: str, section: str) -> list[dict[str, str]]:
    """The body rows of the markdown tables under ``## section`` as {header: cell} (several tables: each its own
    header)."""
    text = doc.split(f"\n    ## {section}\n", 1)[1].split("\n    ## ", 1)[0]
    rows, header = [], None
    for line in (line.strip() for line in text.splitlines()):
        if not line.startswith("|"):
            header = None
            continue
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        if header is None:
            header = cells
        elif not line.startswith("|---"):
            rows.append(dict(zip(header, cells, strict=True)))
    return rows


def _text(doc: str, section: str) -> str:
    return " ".join(doc.split(f"\n    ## {section}\n", 1)[1].split("\n    ## ", 1)[0].split())


def _span(num: str) -> list[int]:
    first, _, last = num.partition("-")
    return list(range(int(first), int(last or first) + 1))


def _version(env_id: str) -> str:
    return env_id.rsplit("-v", 1)[1]


def _newtons(unit: str, version: str) -> float | None:
    """The force [N] of a unit action a Unit cell states: ``(40 N)``, ``(60 N, 4.8 N m)``, ``(60 N in v0, 40 N in
    v1)``; None where the cell gives none (``max_force N``: the row above's)."""
    per_version = dict((v, float(n)) for n, v in re.findall(r"([\d.]+) N in v(\d+)", unit))
    if per_version:
        return per_version[version]
    found = re.search(r"\(([\d.]+) N\b", unit)
    return None if found is None else float(found[1])


def _digits(value: str) -> float:
    """Half a unit of the last digit a number is stated to (``1.92`` -> 0.005)."""
    return 0.5 * 10.0 ** -len(value.partition(".")[2])


def _check_load_energy(scene: Any, loads: np.ndarray) -> None:
    """The load map is a force [N] on each handle's position [m]: the scene's energy falls by F . p (a perturbed
    seed state, so that no coordinate of p is 0)."""
    q = scene.q_seed.unsqueeze(0)
    q = q + 0.01 * torch.randn(q.shape, generator=torch.Generator().manual_seed(0), dtype=q.dtype)
    load = torch.as_tensor(loads, dtype=q.dtype).unsqueeze(0)
    x = scene.full_positions(q)
    work = sum(float(load[0, h].double() @ handle.position(x)[0].double()) for h, handle in enumerate(scene.handles))
    with torch.no_grad():
        loaded, unloaded = scene.energy_terms(q, load), scene.energy_terms(q)
    change = sum(float(loaded[k][0]) - float(unloaded.get(k, torch.zeros(1))[0]) for k in loaded)
    assert change == pytest.approx(-work, rel=1e-5, abs=1e-6)


@pytest.mark.parametrize("env_id", IDS)
def test_the_action_table_states_the_load_a_unit_action_puts_on_the_handle(env_id: str) -> None:
    """Each action row's force [N] per unit action is the load the env applies, on one handle its docstring names,
    along the row's axis (a tangential one perpendicular to the crank, counter-clockwise); larger actions are clipped
    and non-finite ones refused, as the Action Space section says."""
    env = _env(env_id)
    sim, doc = env.unwrapped.sim, type(env.unwrapped).__doc__
    names = list(sim.scene.handle_names)
    rows, scale = _table(doc, "Action Space"), None
    assert rows and [i for row in rows for i in _span(row["Num"])] == list(range(env.action_space.shape[0]))
    for row in rows:
        scale = _newtons(row["Unit"], _version(env_id)) or scale
        assert scale is not None, row
        for i in _span(row["Num"]):
            loads = []
            for size in (1.0, 3.0):  # 3: clipped to 1
                env.reset(seed=0)
                action = np.zeros(env.action_space.shape, np.float32)
                action[i] = size
                env.step(action)
                loads.append(sim.loads[0].detach().cpu().to(torch.float64).numpy())
            np.testing.assert_array_equal(loads[1], loads[0])
            _check_load_energy(sim.scene, loads[0])
            loaded = np.flatnonzero(np.abs(loads[0]).sum(axis=1))
            assert len(loaded) == 1, (row, loaded)
            force, handle = loads[0][loaded[0]], names[loaded[0]]
            assert np.linalg.norm(force) == pytest.approx(scale, rel=1e-6), (row, force)
            ranges = re.findall(r"`(\w+)_(\d+)`\.\.`\1_(\d+)`", doc)
            named = {f"{stem}_{k}" for stem, a, b in ranges for k in range(int(a), int(b) + 1)}
            assert f"`{handle}`" in doc or handle in named, (row, handle)
            if axis := re.search(r"along ([xyz])\b", row["Action"]):
                assert np.flatnonzero(force).tolist() == [AXES[axis[1]]], (row, force)
            if "tangential" in row["Action"]:
                arm = sim.task._arm(sim.x_prev)[0].detach().cpu().to(torch.float64).numpy()
                assert abs(force[:2] @ arm) < 1e-6 * scale * np.linalg.norm(arm) and force[2] == 0.0
                assert arm[0] * force[1] - arm[1] * force[0] > 0.0  # counter-clockwise positive
                radius = re.search(r"F × ([\d.]+) m", row["Action"])[1]
                assert np.linalg.norm(arm) == pytest.approx(float(radius), abs=_digits(radius))
    env.reset(seed=0)
    with pytest.raises(ValueError):
        env.step(np.full(env.action_space.shape, np.nan, np.float32))


def _latent(env: Any, info: dict[str, Any]) -> np.ndarray:
    return env.sim.z[0]


def _latent_speed(env: Any, info: dict[str, Any]) -> np.ndarray:
    sim = env.sim
    return (sim.z[0] - sim.z_prev[0]) / sim.stepper.dt


def _goal(env: Any, info: dict[str, Any]) -> np.ndarray:
    return env.sim.task._goal_position(env.sim.x)[0]


def _goal_offset(env: Any, info: dict[str, Any]) -> np.ndarray:
    return env.sim.params["target"][0] - _goal(env, info)


def _plate(env: Any, info: dict[str, Any]) -> np.ndarray:
    return env.sim.task.pose(env.sim.x)[0][0]


def _plate_offset(env: Any, info: dict[str, Any]) -> np.ndarray:
    return env.sim.params["target_position"][0] - _plate(env, info)


def _turn(env: Any, info: dict[str, Any]) -> np.ndarray:
    """Axial vector of R* R^T, written out: (m32 - m23, m13 - m31, m21 - m12) / 2."""
    m = env.sim.params["target_rotation"][0] @ env.sim.task.pose(env.sim.x)[1][0].T
    return 0.5 * torch.stack([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])


def _height(env: Any, info: dict[str, Any]) -> float:
    return info["height"]


OBSERVATION_ROWS = {
    r"latent z\b": _latent,
    r"latent velocity z_dot": _latent_speed,
    r"(position p of the|corner position p|tip position p|ball centre \(x, z\))": _goal,
    r"target - (p|ball centre)": _goal_offset,
    r"stiffness ratio c\[0\]": lambda env, info: env.sim.cond[0, 0],
    r"support location c\[1\]": lambda env, info: env.sim.cond[0, 1],
    r"cos theta of the crank angle": lambda env, info: math.cos(info["crank_angle"]),
    r"sin theta of the crank angle": lambda env, info: math.sin(info["crank_angle"]),
    r"crank speed omega\b": lambda env, info: info["crank_speed"],
    r"commanded speed omega\*": lambda env, info: env.sim.params["speed"][0],
    r"plate centre p\b": _plate,
    r"target offset p\* - p": _plate_offset,
    r"orientation error e: axial vector of R\* R\^T": _turn,
    r"height h of the middle column above its straight \(seed\) height": _height,
    r"goal offset h\* - h": lambda env, info: env.sim.params["goal_height"][0] - info["height"],
    r"height speed h_dot": lambda env, info: (info["height"] - env._h_prev) / env.dt,
}
"""What each Observation Space row holds, from the env's state and info (a row no pattern here reads fails: add it)."""


def _numbers(value: Any) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().to(torch.float64).numpy()
    return np.atleast_1d(np.asarray(value, dtype=np.float64))


@pytest.mark.parametrize("env_id", IDS)
def test_each_observation_row_holds_what_its_table_says(env_id: str) -> None:
    """Reset to a chosen-by-seed episode and step once: each row of the Observation Space table, in its order,
    is the quantity its words name (computed from the env's state: the goal handle's position, the target offset,
    the condition, the crank's angle, the plate's pose, the bar's height), and a bound written ``r + 2L`` (or
    ``r + 2``) is the rest coordinate plus twice the extent, with the r and L the Unit cell states."""
    env = _env(env_id)
    unwrapped, doc = env.unwrapped, type(env.unwrapped).__doc__
    env.reset(seed=3)
    sim = unwrapped.sim
    action = np.linspace(-0.7, 0.9, env.action_space.shape[0], dtype=np.float32)
    h_prev = float(sim.task.height(sim.x)[0]) if hasattr(sim.task, "height") else None
    obs, _, _, _, info = env.step(action)
    unwrapped._h_prev = h_prev
    rows = _table(doc, "Observation Space")
    for row in rows:
        matched = [fn for pattern, fn in OBSERVATION_ROWS.items() if re.match(pattern, row["Observation"])]
        assert len(matched) == 1, row
        expected = _numbers(matched[0](unwrapped, info))
        index = _span(row["Num"])
        np.testing.assert_allclose(obs[index], expected, rtol=1e-5, atol=1e-5, err_msg=str(row))
        if row["Max"] in ("r + 2L", "r + 2"):
            assert row["Min"] == f"-({row['Max']})"
            r = float(sim.task._bound - 2.0 * sim.scene.extent())
            stated_r = re.search(r"\br = ([\d.]+) m", row["Unit"])
            if stated_r:
                assert r == pytest.approx(float(stated_r[1]), abs=_digits(stated_r[1])), row
            stated_l = re.search(r"\bL = ([\d.]+) m", row["Unit"])
            extent = sim.scene.extent() if row["Max"] == "r + 2L" else 1.0
            assert extent == pytest.approx(sim.scene.extent(), rel=1e-6), row  # "r + 2": an extent of 1 m
            if stated_l:
                assert extent == pytest.approx(float(stated_l[1]), abs=_digits(stated_l[1])), row
            assert unwrapped.observation_space.high[index] == pytest.approx(r + 2.0 * extent, rel=1e-6)


def _weight(formula: str, pattern: str) -> float:
    found = re.search(pattern, formula)
    assert found, (pattern, formula)
    return float(found[1] or 1.0)


@pytest.mark.parametrize("env_id", IDS)
def test_the_reward_formula_s_terms_and_weights_are_the_env_s(env_id: str) -> None:
    """The Rewards section's formula: its terms are the ``info["reward_<term>"]`` the step reports, they sum to the
    reward, the control weight and success bonus are the ones written, and the main term is the written error over
    the written scale (d / L_d with r = 0.2 L_d; |omega - omega*| / W; d / L_p and theta / L_a; |h - h*| / D)."""
    env = _env(env_id)
    unwrapped = env.unwrapped
    task, doc = unwrapped.sim.task, type(unwrapped).__doc__
    text = _text(doc, "Rewards")
    formula = re.search(r"`reward = ([^`]+)`", text)[1]
    assert set(re.findall(r'info\["reward_(\w+)"\]', text)) == set(task.reward_terms)
    env.reset(seed=5)
    action = np.linspace(-0.8, 0.6, env.action_space.shape[0], dtype=np.float32)
    _, reward, _, _, info = env.step(action)
    terms = {term: float(info[f"reward_{term}"]) for term in task.reward_terms}
    assert sum(terms.values()) == pytest.approx(float(reward), rel=1e-5, abs=1e-6)
    control = _weight(formula, r"- ([\d.]+) (?:mean\()?action\^2")
    bonus = _weight(formula, r"\+ ([\d.]+)? ?(?:1)?\[")
    assert (task.control_weight, task.success_bonus) == (control, bonus)
    assert terms["control"] == pytest.approx(-control * float(np.mean(action.astype(np.float64) ** 2)), rel=1e-5)
    assert terms["success"] in (0.0, bonus)
    if task.name == "reach":
        assert "r = 0.2 L_d" in text
        assert task.success_radius == pytest.approx(0.2 * task.distance_scale, rel=1e-9)
        assert terms["distance"] == pytest.approx(-info["distance"] / task.distance_scale, rel=1e-5)
        assert terms["success"] == bonus * (info["distance"] < task.success_radius)
    elif task.name == "crank_speed":
        scale = re.search(r"W = ([\d.]+) rad/s", text)[1]
        tolerance = re.search(r"< ([\d.]+) omega\*\]", formula)[1]
        assert (task.speed_scale, task.tolerance) == (float(scale), float(tolerance))
        assert terms["speed"] == pytest.approx(-abs(info["speed_error"]) / float(scale), rel=1e-5)
    elif task.name == "plate_pose":
        position, angle = re.search(r"L_p = ([\d.]+) m and L_a = ([\d.]+) rad", text).groups()
        assert (task.position_scale, task.angle_scale) == (float(position), float(angle))
        assert "0.2 L_p and theta < 0.2 L_a" in formula
        assert terms["position"] == pytest.approx(-info["distance"] / float(position), rel=1e-5)
        assert terms["orientation"] == pytest.approx(-info["angle"] / float(angle), rel=1e-5)
    else:
        assert task.name == "snap_through", task.name
        span = float(abs(unwrapped.sim.params["goal_height"][0] - unwrapped.sim.params["start_height"][0]))
        stated = re.search(r"\(about ([\d.]+) m\)", text)[1]
        assert span == pytest.approx(float(stated), abs=_digits(stated))
        assert f"< {task.tolerance:g} D]" in formula
        assert terms["height"] == pytest.approx(-info["height_error"] / span, rel=1e-5)


def _default(cell: str) -> Any:
    """The literal a Default cell starts with: ``0.5 (v1, v2: 0.8)`` -> 0.5, ``None: off (v1: True)`` -> None."""
    for candidate in (cell, cell.split(":")[0], cell.split(" (")[0]):
        try:
            return ast.literal_eval(candidate)
        except (ValueError, SyntaxError):
            continue
    raise AssertionError(f"no literal default in {cell!r}")


def _effective_defaults(cls: type[LatentEnv]) -> dict[str, Any]:
    """Each argument's default as the env applies it: the env's own signature over LatentEnv's (what ``**kwargs``
    reaches), and a reach env's class defaults where its signature says None (``ReachEnv.__init__``)."""
    out = {}
    for klass in reversed(cls.__mro__):
        if issubclass(klass, LatentEnv) and "__init__" in vars(klass):
            for p in inspect.signature(vars(klass)["__init__"]).parameters.values():
                if p.default is not p.empty:
                    out[p.name] = p.default
    if issubclass(cls, ReachEnv):
        out.update(
            max_force=cls.default_max_force,
            target_spread=cls.default_target_spread,
            targets=cls.default_targets,
            randomize_condition=cls.randomize_condition,
        )
    return out


@pytest.mark.parametrize("env_id", IDS)
def test_each_argument_s_stated_default_is_the_one_the_env_applies(env_id: str) -> None:
    """Every Default cell of the Arguments tables starts with the default the env applies (``the env's`` rows: the
    numbers of the "In this env" sentence); a ``cubature`` default of ``None: on``/``None: off`` is whether the
    id's env, made without one, steps a cubature."""
    env = _env(env_id)
    cls = type(env.unwrapped)
    doc, defaults = cls.__doc__, _effective_defaults(cls)
    for row in _table(doc, "Arguments"):
        for name in re.findall(r"`(\w+)`", row["Argument"]):
            if row["Default"] == "the env's":
                continue
            assert _default(row["Default"]) == defaults[name], (row, defaults[name])
        state = re.match(r"None: (on|off)\b", row["Default"])
        if row["Argument"] == "`cubature`" and state and "cubature" not in env.spec.kwargs:
            assert env.unwrapped.sim.cubature == (state[1] == "on"), row
    text = _text(doc, "Arguments")
    if issubclass(cls, ReachEnv):
        stated = re.search(
            r"In this env, `max_force` and `target_spread` default to ([\d.]+) N, spread (\d+(?:\.\d+)?)", text
        )
        assert (float(stated[1]), float(stated[2])) == (cls.default_max_force, cls.default_target_spread)
    solver = re.search(r"`stepper_options`(?: \(a :class:`LatentEnv` argument\))? (?:defaults )?to `(\{[^`]*\})`", text)
    assert (ast.literal_eval(solver[1]) if solver else {}) == cls.stepper_defaults


@pytest.mark.parametrize("env_id", IDS)
def test_the_description_states_the_scene_s_size_and_the_map_s_dimension(env_id: str) -> None:
    """``The scene `name` (n = N: ...) runs in its shipped d-d ... subspace``: the scene, its free DOFs and d."""
    sim = _env(env_id).unwrapped.sim
    text = _text(type(_env(env_id).unwrapped).__doc__, "Description")
    name, n, d = re.search(r"The scene `(\w+)` \(n = (\d+)\b.*? shipped (\d+)-d\b", text).groups()
    assert (name, int(n), int(d)) == (sim.scene.name, sim.scene.free_dof_count, sim.latent_dim)


@pytest.mark.parametrize("env_id", IDS)
def test_the_version_history_names_only_registered_versions(env_id: str) -> None:
    """test_envs.py checks each registered version has an entry; here each entry's versions are registered."""
    family = env_id.rsplit("-v", 1)[0]
    history = _text(type(_env(env_id).unwrapped).__doc__, "Version History")
    listed = {v for entry in re.findall(r"- ((?:v\d+, )*v\d+)[:,]", history) for v in re.findall(r"v(\d+)", entry)}
    assert {f"{family}-v{v}" for v in listed} <= set(IDS), listed


def _readme_rows() -> list[dict[str, str]]:
    """The rows of the first table in README's "Gymnasium environments" section (its env table)."""
    section = README.read_text().split("\n## Gymnasium environments\n", 1)[1]
    lines = section.split("\n| id |", 1)[1].split("\n\n", 1)[0].splitlines()[2:]
    header = ["id", "scene", "d", "action", "obs", "task", "steps"]
    return [dict(zip(header, (c.strip() for c in line.strip("|").split("|")), strict=True)) for line in lines]


def test_readme_s_env_table_lists_every_id_once() -> None:
    assert sorted(row["id"].strip("`") for row in _readme_rows()) == sorted(IDS)


@pytest.mark.parametrize("env_id", IDS)
def test_readme_s_env_table_row_is_the_env(env_id: str) -> None:
    """README "Gymnasium environments": scene (n), d, action count and ±force [N], obs size and max steps."""
    env, row = _env(env_id), {row["id"].strip("`"): row for row in _readme_rows()}[env_id]
    sim = env.unwrapped.sim
    scene, n = re.fullmatch(r"(\w+) \((\d+)\)", row["scene"]).groups()
    count, force = re.fullmatch(r"(\d+): .*, ±([\d.]+)", row["action"]).groups()
    assert (scene, int(n)) == (sim.scene.name, sim.scene.free_dof_count)
    assert int(row["d"].split()[0]) == sim.latent_dim
    assert (int(count), float(force)) == (env.action_space.shape[0], sim.task.max_force)
    assert int(row["obs"]) == env.observation_space.shape[0]
    assert int(row["steps"]) == env.spec.max_episode_steps


def _cubature(path: str) -> dict[str, Any]:
    import json

    data = json.loads((README.parent / path).read_text())
    return {"force": data["summary"]["held_out_force_error"], **{r["name"]: r for r in data["rules"]}}


def _kept(rule: dict[str, Any]) -> int:
    return rule["element_count"] if rule["indices"] is None else len(rule["indices"])


def _percent(stated: str, fraction: float) -> None:
    assert 100.0 * fraction == pytest.approx(float(stated), abs=_digits(stated)), (stated, fraction)


@pytest.mark.parametrize("env_id", IDS)
def test_the_cubatures_the_docstring_describes_are_the_shipped_files(env_id: str) -> None:
    """Kept element counts and held-out force errors the docstring gives for a shipped cubature are the file's
    (``N membrane triangles and M bending hinges against the shipped A and B``, ``force error X% against Y%``,
    ``K of E elastic elements (error X%)``, ``the shipped cubature (force error X%)``)."""
    from redsim.cubature import cubature_path
    from redsim.pretrained import path as shipped_path

    scene = _env(env_id).unwrapped.sim.scene.name
    text = " ".join(type(_env(env_id).unwrapped).__doc__.split())
    shipped = cubature_path(shipped_path(scene))
    default = _cubature(str(shipped.relative_to(README.parent))) if shipped.is_file() else {}
    checked = 0
    for lean, membrane, bending, old_membrane, old_bending in re.findall(
        r"`(redsim/pretrained/[\w.]+\.cubature\.json)`: (\d+) membrane triangles and (\d+) bending hinges? "
        r"against the shipped (\d+) and (\d+)",
        text,
    ):
        rules = _cubature(lean)
        assert (_kept(rules["membrane"]), _kept(rules["bending"])) == (int(membrane), int(bending))
        assert (_kept(default["membrane"]), _kept(default["bending"])) == (int(old_membrane), int(old_bending))
        new, old = re.search(r"force error ([\d.]+)% against ([\d.]+)%", text).groups()
        _percent(new, rules["force"])
        _percent(old, default["force"])
        checked += 1
    for kept, total, error in re.findall(r"(\d+) of (\d+) elastic elements \(error ([\d.]+)%\)", text):
        assert (_kept(default["elastic"]), default["elastic"]["element_count"]) == (int(kept), int(total))
        _percent(error, default["force"])
        checked += 1
    for error in re.findall(r"the shipped (?:cubature|one) \((?:force error )?([\d.]+)%(?: force error)?\)", text):
        _percent(error, default["force"])
        checked += 1
    assert checked >= bool(default)  # a scene with a shipped cubature: its env's docstring describes it


@pytest.mark.parametrize("env_id", IDS)
def test_the_starting_state_is_the_stated_draw(env_id: str) -> None:
    """Starting State: z_dot = 0, z the map's rest (or the stated stable state), and the episode's draw is the
    one the section states, replayed from a generator seeded as the env's (``gymnasium.utils.seeding``)."""
    from gymnasium.utils import seeding

    from redsim.envs.reach import HELD_SAMPLES

    env = _env(env_id)
    sim, text = env.unwrapped.sim, _text(type(env.unwrapped).__doc__, "Starting State")
    task, d = sim.task, sim.latent_dim
    obs, _ = env.reset(seed=11)
    rng = seeding.np_random(11)[0]
    assert not obs[d : 2 * d].any()  # z_dot = 0
    if task.name == "reach":
        cond = None
        if sim.randomize_condition:
            assert "c uniform in its box" in text
            u = torch.as_tensor(rng.random(len(sim._cond_low)), dtype=sim.torch_dtype)
            cond = (sim._cond_low + u * (sim._cond_high - sim._cond_low)).unsqueeze(0)
            np.testing.assert_allclose(_numbers(sim.cond[0]), _numbers(cond[0]), rtol=1e-6)
        rest = sim._rest_latent(sim.default_cond if cond is None else cond)
        np.testing.assert_allclose(_numbers(sim.z[0]), _numbers(rest), rtol=1e-6, atol=1e-7)
        if task.targets == "held":
            spread = re.search(r"from (\d+) places .* held action u ~ U\[-([\d.]+), \2\]\^(\d+)", text)
            assert (int(spread[1]), float(spread[2]), int(spread[3])) == (HELD_SAMPLES, task.target_spread, 3)
            assert float(task.held_actions.abs().max()) <= task.target_spread
            expected = task.held_targets[int(rng.integers(HELD_SAMPLES))]
        else:
            assert "z_rest + `target_spread` * N(0, I)" in text
            eps = torch.as_tensor(rng.standard_normal(d), dtype=sim.torch_dtype)
            x = sim.full_positions((rest + task.target_spread * eps).unsqueeze(0), cond)
            expected = task._goal_position(x)[0]
        np.testing.assert_allclose(_numbers(sim.params["target"][0]), _numbers(expected), rtol=1e-5, atol=1e-6)
    elif task.name == "crank_speed":
        low, high = (float(v) for v in re.search(r"`speed_range` \(([\d.]+)-([\d.]+) rad/s", text).groups())
        assert (low, high) == task.speed_range
        assert float(sim.params["speed"][0]) == pytest.approx(low + (high - low) * rng.random(), rel=1e-6)
        theta = re.search(r"the crank hanging at theta = ([\d.]+) rad", text)[1]
        assert float(task.angle(sim.x)[0]) == pytest.approx(float(theta), abs=_digits(theta))
    elif task.name == "plate_pose":
        assert "[-`target_spread`, `target_spread`]^6" in text
        held = task.target_spread * rng.uniform(-1.0, 1.0, 6)
        np.testing.assert_allclose(_numbers(sim.params["held_action"][0]), held, rtol=1e-6)
    else:
        assert "up or down with probability 1/2" in text and '`reset(options={"start_side": 0})` starts up' in text
        assert int(sim.params["start_side"][0]) == int(rng.integers(2))
        assert float(task.heights[0]) > 0.0 > float(task.heights[1])
        np.testing.assert_allclose(_numbers(sim.z[0]), _numbers(task.states[int(sim.params["start_side"][0])]))


@pytest.mark.parametrize("env_id", IDS)
def test_the_episode_ends_where_the_docstring_says(env_id: str) -> None:
    """Episode End: ``gym.make``'s env truncates at the stated step count, not one step earlier, and a step that
    terminates is one whose ``info["diverged"]`` is set (an ordinary step neither terminates nor diverges)."""
    env = _env(env_id)
    steps = int(re.search(r"Truncation: (\d+) steps", _text(type(env.unwrapped).__doc__, "Episode End"))[1])
    limit = env
    while not isinstance(limit, gym.wrappers.TimeLimit):
        limit = limit.env
    zero = np.zeros(env.action_space.shape, np.float32)
    for elapsed, ends in ((steps - 2, False), (steps - 1, True)):
        env.reset(seed=0)
        limit._elapsed_steps = elapsed  # as after that many steps: the limit alone decides the next step's end
        _, _, terminated, truncated, info = env.step(zero)
        assert (truncated, terminated, bool(info["diverged"])) == (ends, False, False), elapsed


def _speed_table() -> dict[str, list[str]]:
    """README "Env speed": each id's row of its first table (env, n, d, act, obs, single, N=16, N=64, N=256, ...)."""
    section = README.read_text().split("\n### Env speed", 1)[1].split("\n## ", 1)[0]
    header = next(line for line in section.splitlines() if line.startswith("env ") and "N=64" in line)
    table = section.split(header, 1)[1]
    rows = {}
    for line in table.splitlines()[1:]:
        if not line.startswith("RedSim/"):
            break
        rows[line.split()[0]] = line.split()
    assert header.split()[:9] == ["env", "n", "d", "act", "obs", "single", "N=16", "N=64", "N=256"], header
    return rows


@pytest.mark.parametrize("env_id", IDS)
def test_the_docstring_s_env_rates_are_readme_s_latest_run(env_id: str) -> None:
    """A rate [env steps/s] a docstring quotes is README "Env speed"'s (the latest run), named as such: ``v1's A
    against v0's B env steps/s at N envs in README "Env speed"``; and that table's n, d, act and obs columns are the
    env's. A review (helper-277) found HangingCloth-v1's "545 against 118 env steps/s at 64 envs in the latest quiet
    run", an older run's (docs/env-speed.md) where README's latest read 1,537 against 388."""
    env, table = _env(env_id), _speed_table()
    sim = env.unwrapped.sim
    n, d, act, obs = (int(v) for v in table[env_id][1:5])
    assert (n, d, act, obs) == (
        sim.scene.free_dof_count,
        sim.latent_dim,
        env.action_space.shape[0],
        env.observation_space.shape[0],
    )
    text = " ".join(type(env.unwrapped).__doc__.split())
    quoted = r"(v\d+)'s ([\d,]+) against (v\d+)'s ([\d,]+) env steps/s at (16|64|256) envs in README \"Env speed\""
    column, family = {"16": 6, "64": 7, "256": 8}, env_id.rsplit("-v", 1)[0]
    for version, rate, other, other_rate, batch in re.findall(quoted, text):
        for v, r in ((version, rate), (other, other_rate)):
            assert int(r.replace(",", "")) == int(table[f"{family}-{v}"][column[batch]]), (v, r, batch)
    assert len(re.findall(r"env steps/s\b", text)) == len(re.findall(quoted, text)), "a rate without its run"


def test_hanging_cloth_s_rest_shape_is_the_one_its_docstring_describes() -> None:
    """HangingCloth's Starting State: the shipped map's rest is folded, its lowest point at the stated y and its upper
    left corner folded up to the stated height above the pinned edge. A review (helper-277) found "its top row ~6 cm
    above the pinned edge": the top free row reaches 2.2 cm; the 6 cm is the left edge's fourth row, folded up."""
    env = _env("RedSim/HangingCloth-v0")
    text = _text(type(env.unwrapped).__doc__, "Starting State")
    low, high = re.search(
        r"its lowest point at y = (-[\d.]+) m, its upper left corner folded up to (\d+) cm above", text
    ).groups()
    env.reset(seed=0)
    sim = env.unwrapped.sim
    seed = sim.scene.full_positions(sim.scene.q_seed.unsqueeze(0))[0].reshape(-1, 3).double().numpy()
    rest = sim.x[0].reshape(-1, 3).detach().double().numpy()
    edge = seed[:, 1].max()  # the pinned top row
    assert rest[:, 1].min() == pytest.approx(float(low), abs=_digits(low))
    assert 100.0 * (rest[:, 1].max() - edge) == pytest.approx(float(high), abs=0.5)
    top = rest[:, 1].argmax()
    assert seed[top, 0] == seed[:, 0].min() and seed[top, 1] > edge - 0.1 * np.ptp(seed[:, 1])


def test_readme_s_env_table_states_each_torque_arm_as_the_docstring() -> None:
    """A README action cell that gives a torque arm says it as the docstring's action table does (``a hinge torque of
    F × 0.08 m``); the review (helper-277) found Stewart's "(hinge torque × 0.08 m)", a torque times a length."""
    checked = 0
    for row in _readme_rows():
        env_id = row["id"].strip("`")
        for arm in re.findall(r"× ([\d.]+) m", row["action"]):
            assert f"of F × {arm} m" in row["action"], row["action"]
            assert f"F × {arm} m" in _text(type(_env(env_id).unwrapped).__doc__, "Action Space")
            checked += 1
    assert checked >= 1


def test_readme_s_rates_and_cubature_envs_are_the_envs() -> None:
    """README "Gymnasium environments": a task cell's ``N× at 64 envs in "Env speed": A against B env steps/s`` is
    that table's (the row's id against its v0), and "**K envs step a cubature.** (ids) evaluate a cubature" names
    exactly the ids whose env steps one (``env.unwrapped.sim.cubature``) and ``(ids) step every element`` some that
    do not."""
    table, checked = _speed_table(), 0
    for row in _readme_rows():
        env_id = row["id"].strip("`")
        quoted = re.search(r"([\d.]+)× at 64 envs in \"Env speed\": ([\d,]+) against ([\d,]+) env steps/s", row["task"])
        if quoted:
            rate, base = (int(v.replace(",", "")) for v in quoted.groups()[1:])
            assert (rate, base) == (int(table[env_id][7]), int(table[f"{env_id.rsplit('-v', 1)[0]}-v0"][7])), row
            assert rate / base == pytest.approx(float(quoted[1]), abs=_digits(quoted[1]))
            checked += 1
    assert checked >= 1
    section = README.read_text().split("\n## Gymnasium environments\n", 1)[1]
    count, listed, exact = re.search(
        r"\*\*(\w+) envs step a cubature\.\*\* (.+?) evaluate\s.*?; (.+?) step every element", section, re.S
    ).groups()

    def ids(text: str) -> set[str]:
        out, family = set(), None
        for name, version in re.findall(r"(?:(\w+)-)?v(\d+)\b", " ".join(text.split())):
            family = name or family
            out.add(f"RedSim/{family}-v{version}")
        return out

    stepping = {i for i in IDS if _env(i).unwrapped.sim.cubature}
    numbers = {"Four": 4, "Five": 5, "Six": 6, "Seven": 7}
    assert ids(listed) == stepping and numbers[count] == len(stepping), (listed, sorted(stepping))
    assert ids(exact) and not ids(exact) & stepping, exact
