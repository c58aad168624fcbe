"""GoalObservation: the reach envs as goal-conditioned envs (Gymnasium-Robotics' dict convention, SB3's HER)."""

from __future__ import annotations

import copy
import functools
import warnings
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

import redsim  # noqa: F401  (registers the ids)
from redsim.envs.goal import GoalObservation, GoalVectorObservation
from redsim.envs.sb3 import SB3VecEnv

REACH = ("RedSim/MiniChain-v0", "RedSim/ConditionalBar-v0")
"""Small reach envs; ConditionalBar's observation has a block (the condition) after the goal's."""


@pytest.fixture(scope="module", params=REACH)
def pair(request: pytest.FixtureRequest) -> tuple[gym.Env, GoalObservation]:
    """The same id plain and wrapped."""
    return gym.make(request.param), GoalObservation(gym.make(request.param))


def _blocks(env: gym.Env) -> dict[str, slice]:
    out, start = {}, 0
    for name, size in env.unwrapped.observation_structure.items():
        out[name] = slice(start, start + size)
        start += size
    return out


def test_the_dict_observation_is_the_flat_one_split_at_the_goal(pair: tuple[gym.Env, GoalObservation]) -> None:
    plain, goal = pair
    flat, _ = plain.reset(seed=3)
    obs, _ = goal.reset(seed=3)
    action = np.full(plain.action_space.shape, 0.7, dtype=np.float32)
    for _ in range(3):
        flat, *_ = plain.step(action)
        obs, *_ = goal.step(action)
    assert goal.observation_space.contains(obs)
    blocks = _blocks(plain)
    kept = np.concatenate([flat[s] for name, s in blocks.items() if name != "target_offset"])
    np.testing.assert_array_equal(obs["observation"], kept)
    np.testing.assert_array_equal(obs["achieved_goal"], flat[blocks["handle_position"]])
    target = flat[blocks["handle_position"]] + flat[blocks["target_offset"]]
    np.testing.assert_allclose(obs["desired_goal"], target, atol=1e-6)
    assert obs["observation"].size == flat.size - obs["desired_goal"].size


@pytest.mark.parametrize("control_cost", [False, True])
def test_compute_reward_is_the_step_reward_for_its_own_goals_and_relabels_others(control_cost: bool) -> None:
    env = GoalObservation(gym.make("RedSim/MiniChain-v0"), control_cost=control_cost)
    env.reset(seed=1)
    rng = np.random.default_rng(0)
    rewards, achieved, desired, infos = [], [], [], []
    for _ in range(20):
        obs, reward, *_, info = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        rewards.append(reward)
        achieved.append(obs["achieved_goal"])
        desired.append(obs["desired_goal"])
        infos.append(info)
    terms = np.array([[i["reward_distance"], i["reward_control"], i["reward_success"]] for i in infos])
    task_reward = terms.sum(1) if control_cost else terms[:, 0] + terms[:, 2]  # the env's own terms
    np.testing.assert_allclose(rewards, task_reward, atol=1e-6)
    for a, d, info, reward in zip(achieved, desired, infos, rewards, strict=True):
        assert env.compute_reward(a, d, info) == pytest.approx(reward, abs=1e-6)
    batched = env.compute_reward(np.stack(achieved), np.stack(desired), np.array(infos))
    assert batched.shape == (20,) and batched.dtype == np.float32
    np.testing.assert_allclose(batched, rewards, atol=1e-6)
    # HER's relabelling: the goal it reached earns the success bonus and no distance cost
    hit = env.compute_reward(np.stack(achieved), np.stack(achieved), infos)
    np.testing.assert_allclose(hit, env.unwrapped.task.success_bonus + (terms[:, 1] if control_cost else 0), atol=1e-6)
    empty = [{} for _ in infos]  # what SB3's HerReplayBuffer passes unless copy_info_dict=True
    if control_cost:
        with pytest.raises(KeyError, match="copy_info_dict"):
            env.compute_reward(np.stack(achieved), np.stack(desired), empty)
    else:
        np.testing.assert_array_equal(env.compute_reward(np.stack(achieved), np.stack(desired), empty), batched)
    assert env.compute_terminated(np.stack(achieved), np.stack(desired), infos).shape == (20,)
    assert not env.compute_truncated(np.stack(achieved), np.stack(desired), infos).any()
    # goals numpy would broadcast into other transitions' rewards (a column, the batch transposed, flattened)
    a, d = np.stack(achieved), np.stack(desired)
    for bad in ((a[:, :1], d), (a.T, d.T), (a.ravel(), d.ravel()), (a[0, 0], d[0, 0])):
        with pytest.raises(ValueError, match=r"must share a shape \[\.\.\., 3\] \(k = 3: the goal axes\)"):
            env.compute_reward(*bad, infos)


def test_the_wrapped_env_passes_both_checkers_and_remakes_from_its_spec() -> None:
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = GoalObservation(gym.make("RedSim/MiniChain-v0"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
        sb3_check_env(env, warn=True)
    # Gymnasium's checker only remarks that it was given a wrapped env, which is the point here
    assert [str(w.message) for w in caught if "different from the unwrapped" not in str(w.message)] == []
    again = gym.make(env.spec)
    assert isinstance(again, GoalObservation) and again.observation_space == env.observation_space


def test_an_env_without_a_goal_or_with_a_changed_observation_is_a_clear_error() -> None:
    with pytest.raises(TypeError, match="needs a reach env"):
        GoalObservation(gym.make("RedSim/Klann-v0"))
    with pytest.raises(TypeError, match="outside GoalObservation"):  # the goals would be in other units
        GoalObservation(gym.wrappers.NormalizeObservation(gym.make("RedSim/MiniChain-v0")))
    outside = gym.wrappers.FlattenObservation(GoalObservation(gym.make("RedSim/MiniChain-v0")))
    obs, _ = outside.reset(seed=0)
    assert outside.observation_space.contains(obs)


def test_one_info_for_a_batch_of_goals_and_the_task_is_the_env_s() -> None:
    env = GoalObservation(gym.make("RedSim/MiniChain-v0"), control_cost=True)
    obs, _ = env.reset(seed=2)
    obs, reward, *_, info = env.step(env.action_space.sample())
    goals = np.stack([obs["achieved_goal"]] * 4)
    batched = env.compute_reward(goals, np.stack([obs["desired_goal"]] * 4), info)
    np.testing.assert_allclose(batched, np.full(4, reward), atol=1e-6)
    clone = copy.deepcopy(env)
    assert clone.task is clone.unwrapped.task


def test_her_learns_from_the_step_that_ends_every_copys_first_episode() -> None:
    """``her_wait``: learning_starts such that SB3 (which learns once its step count exceeds it) learns at copies x
    episode steps, where every copy has ended an episode (the bound was one episode step per copy later)."""
    from stable_baselines3 import SAC, HerReplayBuffer

    from redsim.envs.sb3 import SB3VecEnv
    from redsim.trainers.agents import her_wait

    copies, episode = 2, 4
    venv = SB3VecEnv.make("RedSim/MiniChain-v0", copies, goal=True, max_episode_steps=episode)
    model = SAC("MultiInputPolicy", venv, replay_buffer_class=HerReplayBuffer, batch_size=4, seed=0)
    model.learning_starts = her_wait(copies, episode)
    model.learn(copies * episode)  # HER samples only ended episodes: before every copy ended one, it would raise
    assert model.num_timesteps == copies * episode and model._n_updates == 1
    venv.close()


def test_sb3_sac_with_hindsight_replay_learns_on_it() -> None:
    from stable_baselines3 import SAC, HerReplayBuffer
    from stable_baselines3.common.env_util import make_vec_env

    venv = make_vec_env(
        "RedSim/MiniChain-v0", n_envs=1, seed=0, wrapper_class=GoalObservation, env_kwargs={"max_episode_steps": 40}
    )
    model = SAC(
        "MultiInputPolicy",
        venv,
        replay_buffer_class=HerReplayBuffer,
        replay_buffer_kwargs={"n_sampled_goal": 4, "goal_selection_strategy": "future"},
        learning_starts=50,
        batch_size=32,
        seed=0,
    )
    model.learn(120)
    batch = model.replay_buffer.sample(64, env=None)  # half of the goals relabelled, rewards from compute_reward
    rewards = batch.rewards.numpy().ravel()
    assert np.isfinite(rewards).all() and (rewards > 0.5).any()  # some relabelled goals earn the success bonus
    obs = venv.reset()
    action, _ = model.predict(obs, deterministic=True)
    assert venv.action_space.contains(action[0])


TIGHT = {"dtype": "float64", "stepper_options": {"tol": 1e-10, "max_iter": 60}}
"""A tight float64 solve, so that vector and single envs agree to round-off (test_envs.py's vector test)."""


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_the_vector_goal_env_equals_single_goal_envs_in_both_autoreset_modes(mode: AutoresetMode) -> None:
    n, seed = 3, 7
    venv = GoalVectorObservation(
        gym.make_vec(
            "RedSim/MiniChain-v0",
            num_envs=n,
            vectorization_mode="vector_entry_point",
            max_episode_steps=4,
            autoreset_mode=mode,
            **TIGHT,
        )
    )
    singles = [GoalObservation(gym.make("RedSim/MiniChain-v0", max_episode_steps=4, **TIGHT)) for _ in range(n)]
    obs, _ = venv.reset(seed=seed)
    expected = [env.reset(seed=seed + i)[0] for i, env in enumerate(singles)]
    rng = np.random.default_rng(0)
    autoreset, ended = np.zeros(n, dtype=bool), 0
    for _ in range(10):
        actions = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
        obs, reward, *_, info = venv.step(actions)
        assert venv.observation_space.contains(obs)
        for i, env in enumerate(singles):
            if autoreset[i]:  # NEXT_STEP: this step resets the copy and earns 0
                expected[i], _ = env.reset()
                single_reward, autoreset[i] = 0.0, False
            else:
                expected[i], single_reward, term, trunc, _ = env.step(actions[i])
                if (term or trunc) and mode == AutoresetMode.SAME_STEP:
                    ended += 1
                    assert info["_final_obs"][i]
                    for key, value in expected[i].items():  # the ended episode's last observation and goal
                        np.testing.assert_allclose(info["final_obs"][i][key], value, rtol=1e-5, atol=1e-5)
                    expected[i], _ = env.reset()
                else:
                    autoreset[i] = term or trunc
            assert reward[i] == pytest.approx(single_reward, abs=1e-5)
            for key, value in expected[i].items():
                np.testing.assert_allclose(obs[key][i], value, rtol=1e-5, atol=1e-5)
    assert ended == (2 * n if mode == AutoresetMode.SAME_STEP else 0)  # truncated after steps 4 and 8
    goals = (obs["achieved_goal"], obs["desired_goal"], {})
    np.testing.assert_array_equal(venv.compute_reward(*goals), singles[0].compute_reward(*goals))


def test_the_vector_goal_env_with_control_cost_keeps_the_env_s_reward() -> None:
    make = functools.partial(
        gym.make_vec, "RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point", max_episode_steps=3
    )
    plain, goal = make(), GoalVectorObservation(make(), control_cost=True)
    plain.reset(seed=1)
    goal.reset(seed=1)
    for _ in range(5):
        action = np.full((2, 3), 0.5, dtype=np.float32)
        _, expected, *_ = plain.step(action)
        obs, reward, *_, info = goal.step(action)
        np.testing.assert_array_equal(reward, expected)
        if "_reward_control" not in info:  # every copy restarted this step: no keys, as SyncVectorEnv's
            assert (reward == 0.0).all()
            continue
        infos = [{k: v[i] for k, v in info.items()} for i in range(2)]
        stepped = info["_reward_control"]  # not the copies this step reset (reward 0)
        relabel = goal.compute_reward(obs["achieved_goal"], obs["desired_goal"], infos)
        np.testing.assert_allclose(relabel[stepped], reward[stepped], atol=1e-6)
        assert (reward[~stepped] == 0.0).all()


def test_the_vector_goal_env_refuses_what_it_cannot_split() -> None:
    def make(env_id: str = "RedSim/MiniChain-v0", **kwargs: Any) -> gym.vector.VectorEnv:
        return gym.make_vec(env_id, num_envs=2, vectorization_mode="vector_entry_point", **kwargs)

    with pytest.raises(TypeError, match="needs a reach env"):
        GoalVectorObservation(make("RedSim/Klann-v0"))
    with pytest.raises(TypeError, match="outside GoalVectorObservation"):
        GoalVectorObservation(gym.wrappers.vector.NormalizeObservation(make()))
    with pytest.raises(TypeError, match="native vector env"):
        GoalVectorObservation(gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="sync"))


def test_sb3_her_trains_on_the_native_vector_env_through_env_method() -> None:
    from stable_baselines3 import SAC, HerReplayBuffer

    venv = SB3VecEnv.make("RedSim/MiniChain-v0", 4, goal=True, max_episode_steps=20)
    obs = venv.reset()
    goals = (obs["achieved_goal"], obs["desired_goal"], [{}] * 4)
    rewards = venv.env_method("compute_reward", *goals, indices=[0, 2])
    assert len(rewards) == 2 and rewards[0].shape == (4,)
    with pytest.raises(AttributeError, match="compute_reward"):
        venv.env_method("reset")
    model = SAC(
        "MultiInputPolicy",
        venv,
        replay_buffer_class=HerReplayBuffer,
        replay_buffer_kwargs={"n_sampled_goal": 4},
        learning_starts=100,
        batch_size=32,
        seed=0,
    )
    model.learn(160)
    assert len(model.ep_info_buffer) >= 4  # the episode statistics SB3 logs come with the adapter's infos
    batch = model.replay_buffer.sample(64, env=None)
    assert np.isfinite(batch.rewards.numpy()).all() and (batch.rewards.numpy() > 0.5).any()  # relabelled successes
    assert model.replay_buffer.infos.shape[1] == 4


def test_a_goal_env_that_cannot_be_made_closes_its_vector_env_first() -> None:
    import multiprocessing

    before = len(multiprocessing.active_children())
    with pytest.raises(TypeError, match="native vector env"):
        SB3VecEnv.make("RedSim/MiniChain-v0", 2, goal=True, shards=2)
    assert len(multiprocessing.active_children()) == before  # the shards' workers are gone
    with pytest.raises(TypeError, match="needs a reach env"):
        SB3VecEnv.make("RedSim/Klann-v0", 2, goal=True)


def test_goal_other_than_a_flag_or_the_wrappers_arguments_is_refused_and_an_empty_mapping_means_goal() -> None:
    """``goal="yes"`` was taken as True and ``goal={}`` (a mapping, but falsy) built a vector-observation env."""
    for goal in ("yes", 1, [1]):
        with pytest.raises(TypeError, match="goal must be True, False or a mapping of GoalVectorObservation"):
            SB3VecEnv.make("RedSim/MiniChain-v0", 2, goal=goal)
    venv = SB3VecEnv.make("RedSim/MiniChain-v0", 2, goal={})
    assert isinstance(venv.observation_space, gym.spaces.Dict)
    venv.close()


def test_sb3_reads_the_goal_env_through_outer_vector_wrappers() -> None:
    """HER's env_method and get_attr find the goal env's methods under Gymnasium vector wrappers; a vector
    RecordEpisodeStatistics outside gives SB3 each copy's episode at its end only."""
    from gymnasium.wrappers.vector import RecordEpisodeStatistics, RescaleAction

    inner = SB3VecEnv.make("RedSim/MiniChain-v0", 2, goal={"control_cost": True}, max_episode_steps=3).venv
    assert inner.control_cost
    venv = SB3VecEnv(RecordEpisodeStatistics(RescaleAction(inner, np.float32(-2.0), np.float32(2.0))))
    obs = venv.reset()
    assert venv.get_attr("observation_space")[0] == inner.single_observation_space
    assert venv.get_attr("compute_reward")[1] == inner.compute_reward
    goals = (obs["achieved_goal"], obs["desired_goal"], [{"reward_control": 0.0}] * 2)
    np.testing.assert_array_equal(venv.env_method("compute_reward", *goals)[0], inner.compute_reward(*goals))
    ended = []
    for _ in range(3):
        venv.step_async(np.zeros((2, 3), dtype=np.float32))
        *_, done, infos = venv.step_wait()
        ended.append(["episode" in info for info in infos])
        assert all(("terminal_observation" in info) == d for info, d in zip(infos, done, strict=True))
    assert ended == [[False, False], [False, False], [True, True]]
    assert infos[0]["episode"]["l"] == 3
    # the ended step's own info (from final_info): SB3's Monitor and EvalCallback read is_success there
    assert all({"is_success", "distance", "iterations"} <= set(info) for info in infos)


def test_an_info_layout_change_inside_the_vector_goal_env_is_refused() -> None:
    from gymnasium.wrappers.vector import DictInfoToList

    venv = gym.make_vec(
        "RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point", autoreset_mode="SameStep"
    )
    with pytest.raises(TypeError, match="outside GoalVectorObservation"):  # final_obs would stay flat
        GoalVectorObservation(DictInfoToList(venv))
