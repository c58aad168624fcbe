"""The cloth envs' cubature option (``cubature=None/True/False/"lean"/PATH``) and their fast contract checks.

The full contract (check_env, the PI controller) of the cloth ids also runs under ``-m slow`` in
test_envs.py; here a few steps each, on the stepper the env chooses by default. Float tolerances:
the stepper runs in float32 unless a test says float64.
"""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.envs.registration import EnvSpec
from gymnasium.utils.env_checker import check_env
from torch import Tensor

import redsim
from redsim.cubature import CubatureEnergy
from redsim.envs.base import CUBATURE_DEFAULT, SHIPPED_CUBATURES
from redsim.subspace import CheckpointError

CLOTH_BALL = "RedSim/ClothBall-v0"


def _rollout(env: gym.Env, actions: np.ndarray, seed: int) -> np.ndarray:
    env.reset(seed=seed)
    ball = []
    for a in actions:
        _, _, terminated, _, info = env.step(a)
        assert not terminated and not info["diverged"]
        ball.append(env.unwrapped.sim.task._goal_position(env.unwrapped.sim.x)[0].numpy().copy())
    return np.array(ball)


def test_cloth_ball_steps_its_shipped_cubature_by_default_and_follows_the_all_element_step() -> None:
    """Default on where CUBATURE_DEFAULT says the shipped cubature meets the bar; the ball's path under the
    same pushes stays within 5% of its travel of the all-element step's over 25 steps."""
    assert CUBATURE_DEFAULT["cloth_ball"] and not CUBATURE_DEFAULT["hanging_sheet"]
    env = gym.make(CLOTH_BALL)
    assert env.unwrapped.sim.cubature and isinstance(env.unwrapped.sim.stepper.energy, CubatureEnergy)
    full = gym.make(CLOTH_BALL, cubature=False)
    assert not full.unwrapped.sim.cubature
    actions = np.tile(np.array([[1.0, -0.6]], np.float32), (25, 1))
    actions[12:] *= -1.0
    cub_path, full_path = _rollout(env, actions, 4), _rollout(full, actions, 4)
    travel = np.linalg.norm(full_path - full_path[0], axis=1).max()
    assert travel > 0.05  # m: the pushes moved the ball
    assert np.linalg.norm(cub_path - full_path, axis=1).max() < 0.05 * travel


def test_cubature_true_loads_the_shipped_one_and_refuses_where_none_exists() -> None:
    assert not gym.make("RedSim/HangingCloth-v0").unwrapped.sim.cubature  # shipped, not within the bar: off
    assert gym.make("RedSim/HangingCloth-v0", cubature=True).unwrapped.sim.cubature
    with pytest.raises(CheckpointError, match="redsim cubature"):
        gym.make("RedSim/MiniChain-v0", cubature=True)
    # with subspace=PATH, True means the cubature beside that checkpoint, on every env alike
    sheet = gym.make("RedSim/HangingCloth-v0", subspace=str(redsim.pretrained.FOLDER / "hanging_sheet"), cubature=True)
    assert sheet.unwrapped.sim.cubature
    with pytest.raises(CheckpointError, match="no cubature file"):
        gym.make("RedSim/Klann-v0", subspace=str(redsim.pretrained.FOLDER / "klann"), cubature=True)
    own = redsim.envs.make(
        redsim.scenes.build("hanging_sheet"), redsim.pretrained.FOLDER / "hanging_sheet", cubature=True
    )
    assert own.unwrapped.sim.cubature  # redsim.envs.make with a checkpoint path alike
    with pytest.raises(ValueError, match="cubature must be"):
        gym.make(CLOTH_BALL, cubature=3)
    with pytest.raises(ValueError, match="not both"):
        gym.make(CLOTH_BALL, cubature=True, stepper_options={"energy": None})


def test_the_lean_ids_name_their_cubature_so_their_specs_hold_on_another_install() -> None:
    """ClothBall-v1 and HangingCloth-v2 register ``cubature="lean"`` (SHIPPED_CUBATURES), not this install's
    absolute path of the file: their spec JSON names no path, and the name loads the lean file beside the map."""
    for env_id, scene in (("RedSim/ClothBall-v1", "cloth_ball"), ("RedSim/HangingCloth-v2", "hanging_sheet")):
        spec = gym.spec(env_id)
        assert spec.kwargs["cubature"] == "lean" and "lean" in SHIPPED_CUBATURES
        assert str(redsim.pretrained.FOLDER) not in spec.to_json()
        energy = gym.make(env_id).unwrapped.sim.stepper.energy
        lean = redsim.cubature.load_cubature(
            redsim.pretrained.FOLDER / f"{scene}.lean.cubature.json",
            redsim.scenes.build(scene),
            redsim.pretrained.load(scene),
        )
        kept = {rule.name: int(rule.indices.numel()) for rule in lean.rules}
        assert energy.describe()["kept_elements"] == kept
    # the same name on the v0 id of that map: the lean cubature; on a scene with none shipped: an error naming the CLI
    assert gym.make("RedSim/HangingCloth-v0", cubature="lean").unwrapped.sim.stepper.energy.describe()[
        "kept_elements"
    ] == {"membrane": 728, "bending": 76, "gravity": 0}
    with pytest.raises(CheckpointError, match=r"no 'lean' cubature is shipped for scene 'klann'.*redsim cubature"):
        gym.make("RedSim/Klann-v0", cubature="lean")
    with pytest.raises(CheckpointError, match=r"no 'lean' cubature.*conditional_bar\.cubature\.json"):
        gym.make("RedSim/ConditionalBar-v0", cubature="lean")


def test_a_cubature_path_that_reads_as_a_shipped_name_stays_a_path_in_the_spec(tmp_path, monkeypatch) -> None:
    """``cubature=Path("lean")`` is the user's ``./lean.cubature.json``; its spec JSON recorded "lean", which
    ``gym.make(spec)`` read as the shipped lean cubature: the remade env stepped another energy."""
    shutil.copy(redsim.pretrained.FOLDER / "cloth_ball.cubature.json", tmp_path / "lean.cubature.json")  # v0's
    monkeypatch.chdir(tmp_path)
    kept = {"membrane": 200, "bending": 200, "rigid": 1, "contact": 2025, "gravity": 0}  # the lean one's: 366, 1
    env = gym.make(CLOTH_BALL, cubature=Path("lean"))
    assert env.unwrapped.sim.stepper.energy.describe()["kept_elements"] == kept
    again = gym.make(EnvSpec.from_json(env.spec.to_json()))
    assert again.unwrapped.sim.stepper.energy.describe()["kept_elements"] == kept


def test_a_cubature_of_another_map_is_refused(tmp_path) -> None:
    """A map refitted or perturbed is another map: the shipped cubature does not follow it (None falls back to
    every element; True and a path are errors)."""
    scene = redsim.scenes.build("cloth_ball")
    sub = redsim.pretrained.load("cloth_ball", scene)
    with torch.no_grad():
        sub.mlp[-1].bias.add_(1e-3)
    assert not redsim.envs.make(scene, sub, cubature=None).unwrapped.sim.cubature
    with pytest.raises(CheckpointError, match="another map"):
        redsim.envs.make(scene, sub, cubature=True)
    with pytest.raises(CheckpointError, match="another map"):
        redsim.envs.make(scene, sub, cubature=str(redsim.pretrained.FOLDER / "cloth_ball"))
    with pytest.raises(CheckpointError, match="no cubature file"):
        redsim.envs.make(scene, sub, cubature=str(tmp_path / "missing"))


def test_cloth_ball_check_env_vector_equals_single_and_state_round_trip() -> None:
    env = gym.make(CLOTH_BALL, render_mode="rgb_array")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    assert [str(w.message) for w in caught] == []
    n, steps, seed = 3, 6, 11
    rng = np.random.default_rng(1)
    actions = rng.uniform(-1, 1, (steps, n, 2)).astype(np.float32)
    tight = {"dtype": "float64", "stepper_options": {"tol": 1e-10, "max_iter": 60}}
    venv = gym.make_vec(CLOTH_BALL, num_envs=n, vectorization_mode="vector_entry_point", **tight)
    assert venv.sim.cubature
    obs, _ = venv.reset(seed=seed)
    vec = [obs] + [venv.step(a)[0] for a in actions]
    for i in range(n):
        single = gym.make(CLOTH_BALL, **tight)
        obs, _ = single.reset(seed=seed + i)
        one = [obs] + [single.step(a)[0] for a in actions[:, i]]
        np.testing.assert_allclose(np.array(vec)[:, i], np.array(one), rtol=1e-6, atol=1e-7)
    single.reset(seed=2)
    single.step(actions[0, 0])
    state = single.unwrapped.get_state()
    after = [single.step(a)[0] for a in actions[1:, 0]]
    single.unwrapped.set_state(state)
    again = [single.step(a)[0] for a in actions[1:, 0]]
    assert np.array_equal(np.array(after), np.array(again))


def test_cloth_strain_invariant_is_the_largest_principal_stretch() -> None:
    from redsim.effects.base import gather_elements
    from redsim.effects.elastic import deformation_gradient
    from redsim.envs.invariants import Invariants

    scene = redsim.scenes.build("hanging_sheet")
    g = torch.Generator().manual_seed(0)
    q = scene.q_seed + 0.01 * torch.randn(3, scene.free_dof_count, generator=g, dtype=scene.q_seed.dtype)
    x = scene.full_positions(q)
    membrane = scene.effect("membrane")
    F = deformation_gradient(gather_elements(x, membrane.element_dofs).reshape(3, -1, 3, 3), membrane.shape_gradients)
    expected = torch.linalg.eigvalsh(F.transpose(-1, -2) @ F)[..., -1].sqrt().amax(-1) - 1.0
    got = Invariants(scene)(x)["membrane_max_strain"]
    assert float(expected.min()) > 0.01  # stretched
    torch.testing.assert_close(got, expected, rtol=1e-10, atol=1e-12)


def test_cloth_strain_invariant_leaves_x_alone_and_float32_agrees() -> None:
    """The membrane check works in place on its gathered coordinates: x is unchanged, and in float32 it equals the
    float64 value to float32 round-off."""
    from redsim.envs.invariants import Invariants

    scene = redsim.scenes.build("hanging_sheet")
    g = torch.Generator().manual_seed(1)
    q = scene.q_seed + 0.01 * torch.randn(5, scene.free_dof_count, generator=g, dtype=scene.q_seed.dtype)
    x64 = scene.full_positions(q)
    x32 = x64.float()
    kept = x32.clone()
    got = Invariants(scene.to(dtype=torch.float32))(x32)["membrane_max_strain"]
    assert torch.equal(x32, kept)
    expected = Invariants(scene)(x64)["membrane_max_strain"]
    assert got.dtype == torch.float32 and float(expected.min()) > 0.01
    torch.testing.assert_close(got.double(), expected, rtol=2e-6, atol=1e-6)


@pytest.mark.parametrize("name", ["cloth_ball", "chain"])
def test_invariants_in_row_blocks_equal_one_pass(name: str) -> None:
    """Every invariant, computed over blocks of rows (the last one short), equals the one-pass value row for row (to
    float64 round-off: the contact's batched matmuls may sum in another order)."""
    from redsim.envs.invariants import Invariants

    scene = redsim.scenes.build(name)
    g = torch.Generator().manual_seed(0)
    q = scene.q_seed + 0.01 * torch.randn(7, scene.free_dof_count, generator=g, dtype=scene.q_seed.dtype)
    x = scene.full_positions(q)
    invariants = Invariants(scene)
    one_pass = invariants(x)
    invariants.block_rows = 3
    blocks = invariants(x)
    assert set(blocks) == set(one_pass) and len(one_pass) >= 2
    for key, value in one_pass.items():
        assert blocks[key].shape == (7,)
        torch.testing.assert_close(blocks[key], value, rtol=1e-12, atol=1e-14)


def _triangle_strains(scene: redsim.Scene, x: Tensor) -> Tensor:
    """The largest principal stretch - 1 of every membrane triangle [T] of one configuration x [1, N]."""
    caa, cbb, cab = scene.effect("membrane").metric(x)
    return ((0.5 * (caa + cbb) + torch.hypot(0.5 * (caa - cbb), cab)).sqrt() - 1.0)[0]


def _pinned_triangles(scene: redsim.Scene) -> Tensor:
    """Which membrane triangles [T] have a pinned vertex."""
    vertices = scene.effect("membrane").element_dofs[:, ::3] // 3
    return torch.isin(vertices, scene.dof_map.pinned_index // 3).any(-1)


@pytest.mark.slow
def test_cloth_ball_rest_strain_is_the_corner_pins_and_the_map_adds_to_it() -> None:
    """ClothBall's docstring on `membrane_max_strain` (stop 70): the float64 full-space rest reads 0.30 (median
    0.021) in the triangles at the pinned corners, which carry the ball's weight; on a coarser mesh (22 cells) 0.18: a
    point pin's concentration, larger the finer the mesh. The shipped map's rest reads 0.44 (median 0.035), in the same
    triangles. The measure is the invariant's (checked against eigvalsh above). ~20 s: two full-space solves."""
    from redsim.envs.invariants import Invariants
    from redsim.integrators.reference import rest_state

    strains = {}
    for cells in (44, 22):
        scene = redsim.scenes.build("cloth_ball", cells=cells)
        q, converged = rest_state(scene)
        assert converged
        x = scene.full_positions(q.unsqueeze(0))
        strains[cells] = _triangle_strains(scene, x)
        torch.testing.assert_close(Invariants(scene)(x)["membrane_max_strain"][0], strains[cells].max())
        assert bool(_pinned_triangles(scene)[strains[cells].argmax()])
    assert 0.28 < float(strains[44].max()) < 0.32 and 0.019 < float(strains[44].median()) < 0.023
    assert 0.16 < float(strains[22].max()) < 0.20
    env = gym.make(CLOTH_BALL).unwrapped
    _, info = env.reset(seed=0)
    scene = redsim.scenes.build("cloth_ball")
    mapped = _triangle_strains(scene, scene.full_positions(env.sim.positions(env.sim.z[:1]).double()))
    reported = float(info["membrane_max_strain"])
    assert 0.42 < reported < 0.45 and abs(float(mapped.max()) - reported) < 1e-4
    assert bool(_pinned_triangles(scene)[mapped.argmax()]) and 0.033 < float(mapped.median()) < 0.037


@pytest.mark.slow
def test_hanging_cloth_v1_targets_are_reached_by_the_pi_controller_within_the_episode() -> None:
    """v1's targets are places a held push of at most 1.6 N per axis brings the corner to; its PI controller (forces
    within the 2 N bound) ends every one of 8 seeded episodes within the success radius, on the cubature v1 steps."""
    from redsim.trainers.agents import evaluate

    env = gym.make("RedSim/HangingCloth-v1").unwrapped
    assert env.sim.cubature and env.task.targets == "held"
    scripted = evaluate("RedSim/HangingCloth-v1", "scripted", episodes=8, seed=0)
    assert scripted.successes.all(), scripted.successes
