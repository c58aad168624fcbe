"""``reset(options=...)`` sets parts of an episode's draw (the task's ``reset_options`` and a per-episode
condition) on the single, native vector and sharded envs; a bad option is refused before anything changes."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import redsim  # noqa: F401  (registers the ids)

ID = "RedSim/MiniChain-v0"
TARGET = [0.05, -0.15, 0.0]


@pytest.fixture(scope="module")
def pair() -> tuple[gym.vector.VectorEnv, gym.vector.VectorEnv]:
    """A native and a 2-shard vector env of two copies, shared by the module's sharded checks (each resets first and
    leaves them open): one worker spawn instead of one per test."""
    make = lambda **kw: gym.make_vec(ID, num_envs=2, vectorization_mode="vector_entry_point", **kw)  # noqa: E731
    native, sharded = make(), make(shards=2)
    yield native, sharded
    native.close()
    sharded.close()


def _target_offset(env: gym.Env, obs: np.ndarray) -> np.ndarray:
    blocks = env.unwrapped.sim.observation_structure()
    start = blocks["z"] + blocks["z_dot"] + blocks["handle_position"]
    return obs[start : start + blocks["target_offset"]]


def test_a_chosen_target_is_the_episode_target_and_leaves_the_random_stream_alone() -> None:
    env, plain = gym.make(ID), gym.make(ID)
    obs, _ = env.reset(seed=3, options={"target": TARGET})
    sim = env.unwrapped.sim
    np.testing.assert_allclose(sim.params["target"][0].numpy(), TARGET, atol=1e-7)
    handle = sim.scene.handle("bottom").position(sim.x)[0].numpy()
    np.testing.assert_allclose(_target_offset(env, obs), np.asarray(TARGET) - handle, atol=1e-6)
    plain.reset(seed=3)
    assert not np.allclose(plain.unwrapped.sim.params["target"][0].numpy(), TARGET)
    # the target is still drawn (and replaced), so the next episodes draw what they would have
    np.testing.assert_array_equal(env.reset()[0], plain.reset()[0])


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"targt": TARGET}, r"unknown reset option\(s\) \['targt'\]; this env accepts 'target'"),
        ({"target": [1.0, 2.0]}, r"options\['target'\] must have shape \[3\], got \[2\]"),
        ({"target": [np.nan, 0.0, 0.0]}, r"options\['target'\] must be finite"),
        ({"target": "up"}, r"options\['target'\] must be a number array"),
        ({"target": ["1", "0", "0"]}, r"options\['target'\] must be a number array"),  # NumPy reads them as numbers
        ({"target": [True, False, False]}, r"options\['target'\] must be a number array"),
        ({"target": [1e30, 0.0, 0.0]}, r"options\['target'\] must lie within the observation bound"),
        ({"target": [10.0, 0.2, 0.0]}, r"got \[10\.0, 0\.2, 0\.0\]$"),  # float32 as given, not 0.2000000029
        ({"reset_mask": np.ones(1, bool)}, r"unknown reset option"),  # a vector env's option
    ],
)
def test_a_bad_option_is_refused_and_the_running_episode_goes_on(options: dict, match: str) -> None:
    env = gym.make(ID)
    env.reset(seed=0)
    state = env.unwrapped.get_state()
    with pytest.raises(ValueError, match=match):
        env.reset(options=options)
    for key in ("z", "params"):
        np.testing.assert_equal(env.unwrapped.get_state()[key], state[key])
    env.step(np.zeros(3, np.float32))


@pytest.mark.parametrize("wrapped", [False, True])
def test_a_shape_refused_at_the_first_draw_needs_a_new_reset(wrapped: bool) -> None:
    """Gymnasium 1.4's passive env checker cannot follow a first reset that raised (README: make the env again, or
    ``disable_env_checker=True``, as here through the other wrappers)."""
    env = gym.make(ID, disable_env_checker=True) if wrapped else gym.make(ID).unwrapped
    with pytest.raises(ValueError, match="must have shape"):
        env.reset(seed=0, options={"target": [1.0]})
    with pytest.raises(gym.error.ResetNeeded):
        env.step(np.zeros(3, np.float32))
    env.reset(seed=0)
    env.step(np.zeros(3, np.float32))


def test_bistable_start_side_starts_in_that_state_with_the_other_as_goal() -> None:
    env = gym.make("RedSim/BistableBar-v0")
    task = env.unwrapped.sim.task
    for side in (0, 1, 1, 0):
        env.reset(options={"start_side": side})
        sim = env.unwrapped.sim
        np.testing.assert_array_equal(sim.z[0].numpy(), task.states[side].numpy())
        assert float(sim.params["start_height"][0]) == float(task.heights[side])
        assert float(sim.params["goal_height"][0]) == float(task.heights[1 - side])
    for bad, match in ((2, "must be 0 .up. or 1 .down."), (0.5, "must be integral")):
        with pytest.raises(ValueError, match=match):
            env.reset(options={"start_side": bad})


def test_a_chosen_condition_is_observed_and_one_outside_its_space_is_refused() -> None:
    env = gym.make("RedSim/ConditionalBar-v0")
    space = env.unwrapped.scene.condition_space
    cond = (0.5 * (space.low + space.high)).tolist()
    obs, _ = env.reset(seed=0, options={"condition": cond, "target": [0.5, 0.0]})
    np.testing.assert_allclose(obs[-len(cond) :], cond, rtol=1e-6)
    with pytest.raises(ValueError, match=r"options\['condition'\] must lie in the condition space .*, got \[[^[]"):
        env.reset(options={"condition": (space.high + 1.0).tolist()})  # shown as given: [m], not [[m]]
    with pytest.raises(ValueError, match=r"this env accepts 'speed'$"):
        gym.make("RedSim/Klann-v0").reset(options={"condition": cond})


def test_the_vector_env_sets_the_option_in_the_copies_it_resets() -> None:
    venv = gym.make_vec(ID, num_envs=3, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    drawn = venv.get_state()["params"]["target"].copy()
    venv.reset(options={"target": TARGET, "reset_mask": np.array([False, True, False])})
    targets = venv.get_state()["params"]["target"]
    np.testing.assert_allclose(targets[1], TARGET, atol=1e-7)
    np.testing.assert_array_equal(targets[[0, 2]], drawn[[0, 2]])
    with pytest.raises(ValueError, match="this env accepts 'target', 'reset_mask'"):
        venv.reset(options={"speed": 1.0})
    # one target per copy, stacked: refused, saying how to set copies apart (a user's first try)
    with pytest.raises(ValueError, match=r"got \[3, 3\]: a vector env's reset option is one value for every copy"):
        venv.reset(options={"target": [TARGET] * 3})
    with pytest.raises(ValueError, match=r"got \[2\]$"):  # a wrong value, not a stacked one: no hint
        venv.reset(options={"target": TARGET[:2]})
    venv.step(np.zeros((3, 3), np.float32))
    single = gym.make(ID)
    obs, _ = single.reset(seed=1, options={"target": TARGET})
    vobs, _ = venv.reset(seed=0, options={"target": TARGET})
    np.testing.assert_allclose(vobs[1], obs, atol=1e-6)


def test_a_refused_option_leaves_the_sharded_env_open(pair: tuple[gym.vector.VectorEnv, ...]) -> None:
    venv = pair[1]
    venv.reset(seed=0, options={"target": TARGET})
    np.testing.assert_allclose(venv.get_state()["params"]["target"], [TARGET, TARGET], atol=1e-7)
    for bad in ({"target": [1.0, 2.0]}, {"bad": 1}):
        with pytest.raises(ValueError):
            venv.reset(options=bad)
    with pytest.raises(gym.error.Error, match="Seed must be greater or equal to zero"):
        venv.reset(seed=[3, -1])  # refused before shard 0 is seeded
    state = venv.get_state()  # and a state with a target no reset would take: refused here, not in a worker
    far = {**state, "params": {**state["params"], "target": np.full((2, 3), 1e6, np.float32)}}
    with pytest.raises(ValueError, match=r"state\['params'\] of copy 0 .*observation bound"):
        venv.set_state(far)
    venv.step(np.zeros((2, 3), np.float32))
    assert not venv.closed


def test_klann_and_stewart_options_outside_what_the_task_observes_are_refused() -> None:
    klann = gym.make("RedSim/Klann-v0")
    klann.reset(seed=0, options={"speed": 6.0})
    for bad in (-1e6, 0.0):  # 0: the tolerance is 20% of the command, so no step could be within it
        with pytest.raises(ValueError, match=r"options\['speed'\] must lie in \(0, 12\] rad/s"):
            klann.reset(options={"speed": bad})
    stewart = gym.make("RedSim/Stewart-v0")
    for bad, match in (
        ({"target_rotation": np.zeros((3, 3))}, "must be a rotation matrix"),
        ({"target_rotation": 5.0 * np.eye(3)}, "must be a rotation matrix"),
        ({"target_position": [10.0, 0.0, 0.0]}, "must lie within the observation bound"),
    ):
        with pytest.raises(ValueError, match=match):
            stewart.reset(seed=0, options=bad)
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    stewart.reset(seed=0, options={"target_rotation": turn})
    np.testing.assert_allclose(stewart.unwrapped.sim.params["target_rotation"][0].numpy(), turn, atol=1e-7)
    stewart.reset(seed=3)  # a drawn target (the map's plate block, orthonormal to ~3e-3) replays as an option
    drawn = {k: v for k, v in stewart.unwrapped.get_state()["params"].items() if k.startswith("target")}
    stewart.reset(seed=3, options=drawn)
    with pytest.raises(ValueError, match="target_spread must be <= 1"):
        gym.make("RedSim/Stewart-v0", target_spread=1.5)


def test_set_state_refuses_what_a_reset_option_would_and_changes_nothing() -> None:
    env = gym.make(ID).unwrapped
    env.reset(seed=0)
    env.step(np.full(3, 0.5, np.float32))
    state = env.get_state()
    far = {**state, "params": {**state["params"], "target": np.array([1e6, 0.0, 0.0], np.float32)}}
    with pytest.raises(ValueError, match=r"state\['params'\] of copy 0 .*options\['target'\] must lie within"):
        env.set_state(far)
    for key in ("z", "z_prev", "model", "params"):
        np.testing.assert_equal(env.get_state()[key], state[key])
    env.set_state(state)  # a state get_state() gave still round-trips
    np.testing.assert_equal(env.get_state(), state)
    klann = gym.make("RedSim/Klann-v0").unwrapped
    klann.reset(seed=0)
    fast = klann.get_state()
    fast["params"]["speed"] = np.float32(-1e6)
    with pytest.raises(ValueError, match=r"options\['speed'\] must lie in \(0, 12\] rad/s"):
        klann.set_state(fast)


def test_the_vector_env_set_state_refuses_a_copy_a_reset_option_would() -> None:
    venv = gym.make_vec(ID, num_envs=2, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    state = venv.get_state()
    targets = state["params"]["target"].copy()
    targets[1, 2] = -1e6
    with pytest.raises(ValueError, match=r"state\['params'\] of copy 1 .*options\['target'\]"):
        venv.set_state({**state, "params": {**state["params"], "target": targets}})
    np.testing.assert_equal(venv.get_state(), state)
    venv.step(np.zeros((2, 3), np.float32))


def test_a_masked_reset_checks_only_the_seeds_of_the_copies_it_resets(pair: tuple[gym.vector.VectorEnv, ...]) -> None:
    """Native and sharded alike: copy 0 is not reset, so its seed (-1, refused if used) is never looked at."""
    mask = np.array([False, True])
    answers = []
    for venv in pair:
        venv.reset(seed=0)
        answers.append(venv.reset(seed=[-1, 5], options={"reset_mask": mask})[0])
        with pytest.raises(gym.error.Error, match="Seed must be greater or equal to zero"):
            venv.reset(seed=[5, -1], options={"reset_mask": mask})
        assert not getattr(venv, "closed", False)
    np.testing.assert_allclose(answers[1], answers[0], atol=1e-6)


def test_the_sharded_set_state_refuses_a_wrong_shape_before_a_refused_target(
    pair: tuple[gym.vector.VectorEnv, ...],
) -> None:
    """A state of the wrong shape gets the shape error (as the native env's set_state), not the target's."""
    for venv in pair:
        venv.reset(seed=0)
        state = venv.get_state()
        far = {**state, "params": {**state["params"], "target": np.full((2, 3), 1e6, np.float32)}}
        d = state["z"].shape[1]
        for bad, match in (
            ({**far, "z_prev": np.zeros((2, d + 1))}, rf"state\['z_prev'\] must have shape \[2, {d}\]"),
            ({**far, "z": np.zeros((3, d))}, rf"state\['z'\] must have shape \[2, {d}\]"),
            ({**far, "params": {"target": np.full((3, 3), 1e6)}}, r"state\['params.target'\] must have shape"),
        ):
            with pytest.raises(ValueError, match=match):
                venv.set_state(bad)
        assert not getattr(venv, "closed", False)
        with pytest.raises(ValueError, match=r"state\['params'\] of copy 0 .*observation bound"):
            venv.set_state(far)
        venv.set_state(state)
        venv.step(np.zeros((2, 3), np.float32))


def test_stewart_takes_the_held_action_with_a_chosen_target_for_its_controller() -> None:
    """Stewart's scripted controller holds the action drawn with the target: a target copied from another episode
    comes with that episode's held_action (an option since stop 44), else the controller steered to the drawn one."""
    env = gym.make("RedSim/Stewart-v0").unwrapped
    env.reset(seed=0)
    chosen = {k: env.sim.params[k][0].cpu().numpy() for k in ("target_position", "target_rotation", "held_action")}
    env.reset(seed=3, options=chosen)
    np.testing.assert_array_equal(env.task.controller(env.sim)[0], chosen["held_action"].astype(np.float32))
    with pytest.raises(ValueError, match=r"options\['held_action'\] must lie in the action space \[-1, 1\]"):
        env.reset(seed=3, options={"held_action": np.full(6, 1.5)})
