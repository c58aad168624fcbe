"""The RLlib env creator and its config check (the one-iteration run on a local Ray cluster is
examples/rllib_agent.py's test, skipped without Ray)."""

from __future__ import annotations

import importlib.util

import pytest
from gymnasium.vector import VectorEnv

from redsim.trainers.rllib import check_env_config, env_creator, register

MINI = "RedSim/MiniChain-v0"


def test_env_creator_makes_the_id_with_its_kwargs_and_the_vector_env_where_rllib_asks() -> None:
    env = env_creator({"id": MINI, "kwargs": {"max_episode_steps": 7}})
    assert env.spec.max_episode_steps == 7 and env.action_space.shape == (3,)
    env.close()
    venv = env_creator({"id": MINI, "kwargs": {"max_episode_steps": 7}, "num_envs": 3})  # vector_entry_point mode
    assert isinstance(venv, VectorEnv) and venv.num_envs == 3 and venv.single_action_space.shape == (3,)
    venv.close()


def test_neighbouring_env_runners_share_no_episode() -> None:
    """RLlib resets runner w with config.seed + w: copy i gets b + i, b drawn from SeedSequence([s]), not s + i."""
    import numpy as np

    runners = [env_creator({"id": MINI, "num_envs": 4}) for _ in range(2)]
    first, second = (venv.reset(seed=42 + w)[0] for w, venv in enumerate(runners))
    targets = {tuple(np.round(row, 5)) for row in np.vstack([first, second])}
    assert len(targets) == 8  # with s + i, runner 1's copy i would be runner 0's copy i + 1
    np.testing.assert_array_equal(runners[0].reset(seed=42)[0], first)
    np.testing.assert_array_equal(runners[1].reset(seed=np.int64(43))[0], second)  # numpy integers alike
    assert runners[0].unwrapped.num_envs == 4 and runners[0].spec is not None
    for venv in runners:
        venv.close()


class _EnvContext(dict):
    """What RLlib's runners hand the creator: the env_config dict with the runner's index as an attribute."""

    def __init__(self, config: dict, worker_index: int) -> None:
        super().__init__(config)
        self.worker_index = worker_index
        self.vector_index = 0  # every copy of a runner's SyncVectorEnv gets the same context (Ray 2.60)


def _start_states(venvs: list, seeds: list[int]) -> set[tuple[float, ...]]:
    import numpy as np

    rows = np.vstack([venv.reset(seed=seed)[0] for venv, seed in zip(venvs, seeds, strict=True)])
    return {tuple(np.round(row, 5)) for row in rows}


def test_neighbouring_env_runners_share_no_episode_in_rllibs_own_vector_env() -> None:
    """RLlib's default (sync) vectorize mode: the creator makes each copy, SyncVectorEnv seeds copy i of the runner
    with worker_index w with seed + w + i, so copy i of runner w replayed copy i + 1 of runner w - 1."""
    from gymnasium.vector import SyncVectorEnv

    from redsim.trainers.rllib import RunnerCopySeed

    config = {"id": MINI, "kwargs": {"max_episode_steps": 20}}

    def runner(w: int) -> SyncVectorEnv:
        return SyncVectorEnv([lambda: env_creator(_EnvContext(config, worker_index=w))] * 3)

    runners = [runner(w) for w in (1, 2)]
    first = _start_states(runners, [42 + 1, 42 + 2])
    assert len(first) == 6  # without the runner's index: 4, two copies of runner 2 replaying runner 1's
    assert _start_states([runner(1), runner(2)], [43, 44]) == first  # a seeded run repeats
    assert isinstance(runners[0].envs[0], RunnerCopySeed) and runners[0].envs[0].spec.max_episode_steps == 20
    assert not isinstance(env_creator(config), RunnerCopySeed)  # a plain dict (not a runner's): the env as made
    for venv in runners:
        venv.close()


@pytest.mark.filterwarnings("ignore:.*Overriding environment rllib-single-agent-env-v0")  # two runners here
def test_rllibs_env_runners_share_no_episode_in_the_default_vectorize_mode() -> None:
    """The same on RLlib's own env runners (in this process, no cluster): their first episodes' start states."""
    pytest.importorskip("ray", reason='Ray RLlib is not installed (pip install "redsim[ray]")')
    import numpy as np
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.env.single_agent_env_runner import SingleAgentEnvRunner

    config = (
        PPOConfig()
        .environment(register(), env_config={"id": MINI, "kwargs": {"max_episode_steps": 20}})
        .env_runners(num_env_runners=2, num_envs_per_env_runner=3)  # gym_env_vectorize_mode: RLlib's default, sync
        .debugging(seed=0)
    )
    starts = []
    for w in (1, 2):
        runner = SingleAgentEnvRunner(config=config, worker_index=w)
        starts += [episode.get_observations(0) for episode in runner.sample(num_timesteps=3, random_actions=True)]
        runner.stop()
    assert len(starts) == 6 and len({tuple(np.round(row, 5)) for row in starts}) == 6


@pytest.mark.parametrize(
    ("env_config", "message"),
    [
        ({"id": "CartPole-v1"}, r"env_config\['id'\] must be one of RedSim/Chain-v0"),
        ({"id": MINI, "max_episode_steps": 5}, r"unknown key\(s\) \['max_episode_steps'\].*go in 'kwargs'"),
        ({"id": MINI, "kwargs": 3}, r"env_config\['kwargs'\] must be a dict"),
        ({"id": MINI, "kwargs": {"bogus": 1}}, r"env_config\['kwargs'\] \{'bogus': 1\}: .*unexpected keyword"),
    ],
)
def test_a_bad_env_config_is_a_clear_error_in_the_driver(env_config: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        check_env_config(env_config)


@pytest.mark.parametrize("env_config", [MINI, None, ["id", MINI]])
def test_an_env_config_that_is_not_a_dict_is_named(env_config: object) -> None:
    with pytest.raises(ValueError, match=r"env_config must be a dict \{'id': ENV_ID, 'kwargs': \{...\}\}, got "):
        check_env_config(env_config)


def test_checkpoint_config_refuses_a_folder_that_is_no_checkpoint(tmp_path) -> None:
    from redsim.trainers.rllib import checkpoint_config

    with pytest.raises(ValueError, match=r"is not an RLlib checkpoint \(no rllib_checkpoint\.json\)"):
        checkpoint_config(tmp_path)


def test_the_config_is_checked_as_the_runners_build_it() -> None:
    """gym.make takes disable_env_checker itself; the vector entry point passes it on to the env, which refuses it."""
    config = {"id": MINI, "kwargs": {"disable_env_checker": True}}
    check_env_config(config)
    with pytest.raises(ValueError, match="unexpected keyword argument 'disable_env_checker'"):
        check_env_config(config, num_envs=2)
    with pytest.raises(ValueError, match="max_episode_steps"):
        check_env_config({"id": MINI, "kwargs": {"max_episode_steps": 0}})


@pytest.mark.skipif(importlib.util.find_spec("ray") is not None, reason="Ray is installed here")
def test_register_and_restore_without_ray_name_the_extra(tmp_path) -> None:
    """restore() said only "No module named 'ray'" (it imported Ray first, without the extra's name)."""
    from redsim.trainers.rllib import restore

    with pytest.raises(ImportError, match='pip install "redsim\\[ray\\]"'):
        register()
    with pytest.raises(ImportError, match='pip install "redsim\\[ray\\]"'):
        restore(tmp_path)


def test_a_restored_algorithm_samples_with_the_checkpoints_weights_on_every_runner(tmp_path) -> None:
    """RLlib's from_checkpoint sent the weights to the runners without waiting: a runner busy with its build's own
    kept those, and the first restored iteration sampled with the untrained policy (which runners: run to run)."""
    ray = pytest.importorskip("ray", reason='Ray RLlib is not installed (pip install "redsim[ray]")')
    import torch
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.rl_module import RLModule

    from redsim.trainers.rllib import checkpoint_config, restore

    ray.init(address="local", num_cpus=3, include_dashboard=False, object_store_memory=200 * 2**20)
    try:
        config = (
            PPOConfig()
            .environment(register(), env_config={"id": MINI, "kwargs": {"max_episode_steps": 20}})
            .env_runners(num_env_runners=2, num_envs_per_env_runner=2, gym_env_vectorize_mode="vector_entry_point")
            .training(train_batch_size_per_learner=80, minibatch_size=80, num_epochs=1)
            .debugging(seed=0)
        )
        algo = config.build_algo()
        algo.train()
        algo.save_to_path(str(tmp_path / "ppo"))
        algo.stop()
        saved_config = checkpoint_config(tmp_path / "ppo")  # read without the cluster: what a restore needs first
        assert saved_config["num_env_runners"] == 2 and saved_config["env_config"]["id"] == MINI
        saved = RLModule.from_checkpoint(str(tmp_path / "ppo/learner_group/learner/rl_module/default_policy"))
        expected = saved.state_dict()
        restored = restore(tmp_path / "ppo")
        states = restored.env_runner_group.foreach_env_runner(
            lambda runner: {k: torch.as_tensor(v).detach().cpu() for k, v in runner.module.state_dict().items()},
            local_env_runner=False,
        )
        restored.stop()
        assert len(states) == 2
        for state in states:
            assert all(torch.equal(state[k], torch.as_tensor(expected[k])) for k in expected if k in state)
            assert set(expected) & set(state)
    finally:
        ray.shutdown()
