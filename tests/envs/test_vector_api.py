"""Gymnasium's vector API on the native and the sharded vector env: get_attr / set_attr / call, reset masks,
the autoreset modes, the episode clock in get_state, and max_episode_steps as gym.make reads it."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import redsim  # registers the ids

ID = "RedSim/MiniChain-v0"
TIGHT = {"dtype": "float64", "stepper_options": {"tol": 1e-10, "max_iter": 60}}
"""Solved tightly, so that another batch split does not move a copy's solve."""
PUSH = np.full((2, 3), 0.5, np.float32)


def _vec(**kwargs):
    return gym.make_vec(ID, num_envs=2, vectorization_mode="vector_entry_point", **kwargs)


@pytest.mark.parametrize("shards", [1, 2])
def test_get_attr_call_and_set_attr_as_the_sync_vector_env(shards: int) -> None:
    venv, sync = _vec(shards=shards), gym.make_vec(ID, num_envs=2, vectorization_mode="sync")
    try:
        venv.reset(seed=0)
        sync.reset(seed=0)
        for name in ("dt", "observation_space", "action_space"):
            assert venv.get_attr(name) == sync.get_attr(name), name
        assert venv.call("dt") == sync.call("dt")
        states = venv.call("get_state")
        assert len(states) == 2 and set(states[1]) == set(sync.call("get_state")[1])
        single = gym.make(ID)
        single.reset(seed=1)
        np.testing.assert_allclose(states[1]["z"], single.unwrapped.get_state()["z"], atol=1e-6)
        venv.step(np.array([[1, 0, 0], [0, 1, 0]], np.float32))
        sync.step(np.array([[1, 0, 0], [0, 1, 0]], np.float32))
        q = venv.call("configuration")
        assert len(q) == 2 and not np.array_equal(q[0], q[1])
        np.testing.assert_allclose(np.stack(q), np.stack(sync.call("configuration")), atol=1e-4)
        with pytest.raises(AttributeError, match="share one simulation"):
            venv.set_attr("dt", [0.1, 0.1])
        with pytest.raises(AttributeError, match="copy by copy"):
            venv.get_attr("sim")
        with pytest.raises(AttributeError, match=r"'get_state' is a method: call\('get_state'\) answers it"):
            venv.get_attr("get_state")
        with pytest.raises(AttributeError, match="no methods of their own"):
            venv.call("get_wrapper_attr", "dt")
        with pytest.raises(TypeError, match="no arguments"):
            venv.call("configuration", 1)
    finally:
        venv.close()
        sync.close()


@pytest.mark.parametrize("shards", [1, pytest.param(2, marks=pytest.mark.slow)])  # sharded: 10 s
def test_each_copys_spec_is_a_single_envs_as_in_the_sync_vector_env(shards: int) -> None:
    """``get_attr("spec")`` answers what ``gym.make`` gives one copy: id, kwargs and episode length."""
    from redsim.envs.sb3 import SB3VecEnv

    for kwargs in ({}, {"max_episode_steps": 50, "dt": 0.01}):
        single = gym.make(ID, **kwargs).spec
        venv, sync = _vec(shards=shards, **kwargs), gym.make_vec(ID, 2, vectorization_mode="sync", **kwargs)
        try:
            assert venv.get_attr("spec") == sync.get_attr("spec") == (single, single), kwargs
            assert venv.spec.kwargs["num_envs"] == 2  # the vector env's own spec is unchanged
        finally:
            venv.close()
            sync.close()
    sb3 = SB3VecEnv.make(ID, num_envs=2, shards=shards, dt=0.01)
    try:
        assert sb3.get_attr("spec") == [gym.make(ID, dt=0.01).spec] * 2
    finally:
        sb3.close()


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_info_keys_and_dtypes_are_the_sync_vector_envs(mode: AutoresetMode) -> None:
    """Every info key (masks, ``q`` and ``final_info`` included) has the sync env's dtype: float64 floats."""
    options = {"include_q": True, "max_episode_steps": 2}
    native = _vec(autoreset_mode=mode, **options)
    sync = gym.make_vec(ID, 2, vectorization_mode="sync", vector_kwargs={"autoreset_mode": mode}, **options)
    infos = []
    for env in (native, sync):
        infos.append([env.reset(seed=0)[1], *(env.step(PUSH)[4] for _ in range(3))])  # an end, then a restart
    for ours, theirs in zip(*infos, strict=True):
        assert _dtypes(ours) == _dtypes(theirs)
    assert _dtypes(infos[0][1])["distance"] == np.float64


def test_a_copy_restarted_by_the_next_step_is_not_stepped_and_holds_zeros_as_in_the_sync_env() -> None:
    """NEXT_STEP resets a copy that ended without stepping it, as the sync env: its slot's step values (a review read
    a diverged copy's flag and a 1e13 J energy there a second time, when the step solved it and discarded the result)
    are zeros as the sync env's; its reset info and the other copy's step are as before."""
    options = {"max_force": 1e15, "dtype": "float64"}  # copy 0's push diverges at once; copy 1 is left alone
    native = _vec(**options)
    sync = gym.make_vec(ID, 2, vectorization_mode="sync", **options)
    push = np.zeros((2, 3), np.float32)
    push[0] = 1.0
    infos = []
    solved = []  # the batch of each stepper step
    step = native.sim.stepper.step
    native.sim.stepper.step = lambda z, *args, **kwargs: solved.append(len(z)) or step(z, *args, **kwargs)
    for env in (native, sync):
        env.reset(seed=0)
        _, _, terminated, _, info = env.step(push)
        assert terminated.tolist() == [True, False] and info["diverged"].tolist() == [True, False]
        infos.append(env.step(np.zeros((2, 3), np.float32))[4])
    assert solved == [2, 1]  # copy 0 is not solved from the state that diverged
    with pytest.raises(ValueError, match=r"active must be a bool mask of shape \(2,\), got shape \(1,\)"):
        native.sim.step(np.zeros((2, 3), np.float32), active=[False])
    ours, theirs = infos
    assert set(ours) == set(theirs)
    for key in ("diverged", "converged", "energy", "iterations", "residual", "out_of_range", "distance"):
        np.testing.assert_array_equal(ours[f"_{key}"], theirs[f"_{key}"])
        np.testing.assert_allclose(ours[key], theirs[key], rtol=1e-6, atol=1e-9, err_msg=key)
    assert not ours["diverged"][0] and ours["energy"][0] == 0.0 and ours["_distance"][0]  # the new start's distance


def test_a_stepper_compiled_with_static_shapes_steps_every_copy_at_a_restart() -> None:
    """compile=True keeps one graph per batch size, so a restart does not solve a subset (a new size: a new graph,
    16 s in a review's run): every copy is solved, the restarted ones' results dropped as before. The flag alone is set
    here (its padded calls run eagerly), without the minutes a real compile takes."""
    venv = _vec(max_episode_steps=1)
    venv.sim.stepper.compiled = True
    solved = []
    step = venv.sim.stepper.step
    venv.sim.stepper.step = lambda z, *args, **kwargs: solved.append(len(z)) or step(z, *args, **kwargs)
    venv.reset(seed=0)
    venv.step(PUSH)
    info = venv.step(PUSH)[4]  # every copy restarts
    assert solved == [2, 2] and "energy" not in info and info["_distance"].all()


def _dtypes(info: dict) -> dict:
    """The dtype of each array in ``info``, nested dicts key by key."""
    return {k: _dtypes(v) if isinstance(v, dict) else np.asarray(v).dtype for k, v in info.items()}


def test_set_state_restores_the_episode_clock_after_an_episode_ended() -> None:
    """A state saved mid-episode and restored after the episode ended steps as it did (no pending autoreset)."""
    venv = _vec(max_episode_steps=3)
    venv.reset(seed=0)
    saved = venv.get_state()
    expected, reward, *_ = venv.step(PUSH)
    for _ in range(2):
        venv.step(PUSH)
    assert venv.autoresetting.all()
    venv.set_state(saved)
    obs, again, *_ = venv.step(PUSH)
    np.testing.assert_array_equal(obs, expected)
    np.testing.assert_array_equal(again, reward)
    _, _, _, truncated, _ = venv.step(PUSH)
    _, _, _, truncated, _ = venv.step(PUSH)
    assert truncated.all()  # the restored clock: step 3 of the episode truncates
    with pytest.raises(ValueError, match="elapsed_steps"):
        venv.set_state({**saved, "elapsed_steps": np.zeros(3)})


@pytest.mark.parametrize("shards", [1, 2])
def test_set_state_refuses_an_episode_clock_that_is_not_whole_counts(shards: int) -> None:
    """A NaN, inf, huge or fractional step count was cast to int64 (NaN: -2**63, a copy that never truncates) and a
    NaN flag to True; each is refused now, before anything changes (the sharded env stays open)."""
    venv = _vec(max_episode_steps=2, shards=shards)
    try:
        venv.reset(seed=0)
        saved = venv.get_state()
        for bad in (np.nan, np.inf, 1e30, 2.5, -1.0):
            with pytest.raises(ValueError, match=r"state\['elapsed_steps'\] must hold whole step counts >= 0"):
                venv.set_state({**saved, "elapsed_steps": np.array([bad, 0.0])})
        for bad in (np.nan, 2.0):
            with pytest.raises(ValueError, match=r"state\['autoresetting'\] must hold True/False"):
                venv.set_state({**saved, "autoresetting": np.array([bad, 0.0])})
        venv.set_state({**saved, "elapsed_steps": np.array([1.0, 0.0]), "autoresetting": np.array([0, 0])})
        _, _, _, truncated, _ = venv.step(PUSH)
        assert truncated.tolist() == [True, False]  # whole floats and 0/1 flags are taken as before
    finally:
        venv.close()


def test_a_restored_state_draws_the_same_next_episodes() -> None:
    """The copies' generators are part of the state: the autoresets after a restore draw the episodes they drew
    first; a single env's next unseeded reset alike; another env's or another dt's state is refused."""
    venv = _vec(max_episode_steps=2)
    venv.reset(seed=0)
    saved = venv.get_state()
    first = [venv.step(PUSH)[0] for _ in range(4)]  # through an autoreset
    venv.set_state(saved)
    np.testing.assert_array_equal(np.stack([venv.step(PUSH)[0] for _ in range(4)]), np.stack(first))
    env = gym.make("RedSim/MiniChain-v0").unwrapped
    env.reset(seed=3)
    state = env.get_state()
    after = env.reset()[0]
    env.set_state(state)
    np.testing.assert_array_equal(env.reset()[0], after)
    for other, message in (
        (gym.make("RedSim/Klann-v0").unwrapped, "scene 'mini_chain' \\(here 'klann'\\)"),
        (gym.make("RedSim/MiniChain-v0", frame_skip=2).unwrapped, "frame_skip 1 \\(here 2\\)"),
    ):
        with pytest.raises(ValueError, match=f"the state belongs to another env: .*{message}"):
            other.set_state(state)  # never reset: its params cannot tell


def test_reset_masks_are_checked_as_the_sync_vector_env_checks_them() -> None:
    venv = _vec()
    venv.reset(seed=0)
    with pytest.raises(TypeError, match="dtype np"):
        venv.reset(options={"reset_mask": np.array([0, 1])})
    with pytest.raises(ValueError, match="at least one"):
        venv.reset(options={"reset_mask": np.array([False, False])})
    with pytest.raises(ValueError, match="shape"):
        venv.reset(options={"reset_mask": np.array([True])})


@pytest.mark.parametrize("shards", [1, 2])
def test_disabled_autoreset_leaves_ended_copies_to_the_caller(shards: int) -> None:
    # float64: a batched solve and single ones agree far closer than float32's tolerance leaves them (in float32 one
    # observation entry differed by 6e-3 after two steps on stop 37's Intel Xeon, by under 5e-3 on stop 36's AMD EPYC)
    venv = _vec(max_episode_steps=2, autoreset_mode=AutoresetMode.DISABLED, shards=shards, dtype="float64")
    sync = gym.make_vec(
        ID, 2, "sync", max_episode_steps=2, dtype="float64", vector_kwargs={"autoreset_mode": AutoresetMode.DISABLED}
    )
    for env in (venv, sync):
        env.reset(seed=0)
    for _ in range(2):
        obs, reward, _, truncated, _ = venv.step(PUSH)
        sync_obs, sync_reward, _, sync_truncated, _ = sync.step(PUSH)
        np.testing.assert_allclose(obs, sync_obs, rtol=0.0, atol=1e-6)
        np.testing.assert_allclose(reward, sync_reward, rtol=0.0, atol=1e-6)
        np.testing.assert_array_equal(truncated, sync_truncated)
    assert truncated.all()
    venv.reset(options={"reset_mask": np.array([True, False])})
    with pytest.raises(RuntimeError, match=r"copies \[1\] ended"):  # sync asserts the same
        venv.step(PUSH)
    venv.reset(options={"reset_mask": np.array([False, True])})
    _, _, _, truncated, _ = venv.step(PUSH)
    assert not truncated.any()


def test_max_episode_steps_none_is_the_ids_and_minus_one_is_none() -> None:
    assert _vec(max_episode_steps=None).max_episode_steps == 200
    assert _vec(max_episode_steps=-1).max_episode_steps is None
    assert _vec().max_episode_steps == 200


def test_render_fps_is_the_frame_rate_of_simulated_time() -> None:
    assert gym.make(ID).metadata["render_fps"] == 50
    assert gym.make(ID, frame_skip=3).metadata["render_fps"] == pytest.approx(50 / 3)
    # SB3's VecVideoRecorder reads the VecEnv's metadata (DummyVecEnv forwards the env's; else it writes 30 fps)
    from redsim.envs.sb3 import SB3VecEnv

    assert SB3VecEnv.make(ID, num_envs=2, frame_skip=3).metadata["render_fps"] == pytest.approx(50 / 3)


def test_the_sb3_adapter_reports_monitor_episode_statistics() -> None:
    """SB3 logs ep_rew_mean from info["episode"]: the adapter gives it as VecMonitor would, return and length."""
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import VecMonitor

    from redsim.envs.sb3 import SB3VecEnv

    own = SB3VecEnv.make(ID, 2, max_episode_steps=3)
    with pytest.warns(UserWarning, match="already wrapped with a `Monitor`"):  # SB3's note: VecMonitor's stats win
        monitored = VecMonitor(SB3VecEnv.make(ID, 2, max_episode_steps=3))
    assert own.env_is_wrapped(Monitor) == [True, True] and own.env_is_wrapped(gym.Wrapper) == [False, False]
    for venv in (own, monitored):
        venv.seed(0)
        venv.reset()
    total = np.zeros(2)
    for step in range(3):
        _, reward, done, infos = own.step(PUSH)
        _, _, _, monitor_infos = monitored.step(PUSH)
        total += reward
        assert done.all() == (step == 2) and ("episode" in infos[0]) == (step == 2)
    for info, monitor_info, expected in zip(infos, monitor_infos, total, strict=True):
        assert info["episode"]["l"] == monitor_info["episode"]["l"] == 3
        assert info["episode"]["r"] == pytest.approx(expected, rel=1e-5)
        assert info["episode"]["r"] == pytest.approx(monitor_info["episode"]["r"], rel=1e-4, abs=1e-4)


def test_the_sb3_adapters_infos_hold_the_keys_of_dummy_vec_envs_on_every_step() -> None:
    """SB3's DummyVecEnv puts ``TimeLimit.truncated`` in every step's info, not only an ended copy's: a callback
    reading it on any step got a KeyError from the adapter."""
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    from redsim.envs.sb3 import SB3VecEnv

    own = SB3VecEnv.make(ID, 2, max_episode_steps=3)
    dummy = DummyVecEnv([lambda: Monitor(gym.make(ID, max_episode_steps=3)) for _ in range(2)])
    for venv in (own, dummy):
        venv.seed(0)
        venv.reset()
    for step in range(4):
        _, _, done, infos = own.step(PUSH)
        _, _, dummy_done, dummy_infos = dummy.step(PUSH)
        assert done.tolist() == dummy_done.tolist() == [step == 2] * 2
        for info, dummy_info in zip(infos, dummy_infos, strict=True):
            assert set(info) == set(dummy_info), step
            assert info["TimeLimit.truncated"] == dummy_info["TimeLimit.truncated"] == (step == 2)
    own.close()
    dummy.close()


def test_the_sb3_adapters_time_limit_flag_is_false_where_a_copy_terminates_at_its_limit_as_dummy_vec_envs() -> None:
    """On the limit's step a copy that also terminates (diverged) reads ``TimeLimit.truncated`` False, one that
    only runs out of time True, as SB3's DummyVecEnv gives them (``truncated and not terminated``)."""
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    from redsim.envs.sb3 import SB3VecEnv

    options = {"max_force": 1e15, "dtype": "float64", "max_episode_steps": 1}  # copy 0's push diverges at once
    own = SB3VecEnv.make(ID, 2, **options)
    dummy = DummyVecEnv([lambda: Monitor(gym.make(ID, **options)) for _ in range(2)])
    push = np.zeros((2, 3), np.float32)
    push[0] = 1.0
    flags = []
    for venv in (own, dummy):
        venv.seed(0)
        venv.reset()
        _, _, done, infos = venv.step(push)
        assert done.tolist() == [True, True] and [info["diverged"] for info in infos] == [True, False]
        flags.append([info["TimeLimit.truncated"] for info in infos])
        venv.close()
    assert flags[0] == flags[1] == [False, True]


def test_the_sb3_adapter_passes_set_options_to_the_reset() -> None:
    from redsim.envs.sb3 import SB3VecEnv

    venv = SB3VecEnv.make(ID, 2)
    venv.seed(0)
    venv.reset()
    moved = venv.step(PUSH)[0]
    venv.set_options({"reset_mask": np.array([True, False])})  # reset copy 0 only: copy 1 keeps its state
    again = venv.reset()
    np.testing.assert_array_equal(again[1], moved[1])
    assert not np.array_equal(again[0], moved[0])
    venv.set_options([{}, {"reset_mask": np.array([True, False])}])
    with pytest.raises(ValueError, match="same options"):
        venv.reset()


@pytest.mark.parametrize("shards", [1, 2])
def test_a_masked_first_reset_leaves_the_other_copies_unstarted(shards: int) -> None:
    """As Gymnasium's sync env: stepping before every copy was reset is refused (the env stays usable)."""
    venv = _vec(shards=shards)
    try:
        obs, _ = venv.reset(seed=0, options={"reset_mask": np.array([True, False])})
        assert obs.shape == (2, 14)
        with pytest.raises(gym.error.ResetNeeded, match=r"copies \[1\] were never reset") as refused:
            venv.step(PUSH)
        assert isinstance(refused.value, RuntimeError)  # what a step raised before stop 50
        venv.reset(options={"reset_mask": np.array([False, True])})
        venv.step(PUSH)
    finally:
        venv.close()


def test_a_state_moves_between_sharded_and_native_envs_of_the_same_copies() -> None:
    sharded, native = _vec(shards=2, **TIGHT), _vec(**TIGHT)
    try:
        sharded.reset(seed=0)
        native.reset(seed=5)
        sharded.step(PUSH)
        state = sharded.get_state()
        assert state["z"].shape[0] == 2 and state["elapsed_steps"].tolist() == [1, 1]
        native.set_state(state)
        np.testing.assert_allclose(native.step(PUSH)[0], sharded.step(PUSH)[0], atol=1e-9)
        sharded.set_state(native.get_state())
        np.testing.assert_allclose(sharded.step(PUSH)[0], native.step(PUSH)[0], atol=1e-9)
    finally:
        sharded.close()


def test_the_sb3_adapter_answers_get_attr_as_the_vector_env() -> None:
    from redsim.envs.sb3 import SB3VecEnv

    venv = SB3VecEnv.make(ID, num_envs=2)
    assert venv.get_attr("dt") == [venv.venv.unwrapped.template.dt] * 2
    for name in ("np_random", "sim"):
        with pytest.raises(AttributeError, match="not one value per copy"):
            venv.get_attr(name)
    venv.close()


def test_the_sb3_adapters_env_method_answers_the_per_copy_calls_copy_by_copy() -> None:
    from redsim.envs.sb3 import SB3VecEnv

    venv = SB3VecEnv.make(ID, num_envs=2, render_mode="rgb_array", width=32, height=32)
    try:
        venv.reset()
        venv.step(np.array([[1, 0, 0], [0, 1, 0]], np.float32))
        native = venv.venv.unwrapped
        states = venv.env_method("get_state")
        assert len(states) == 2 and not np.array_equal(states[0]["z"], states[1]["z"])
        for mine, theirs in zip(states, native.call("get_state"), strict=True):
            assert np.array_equal(mine["z"], theirs["z"]) and mine["rng"] == theirs["rng"]
        q = venv.env_method("configuration", indices=[1])
        assert len(q) == 1 and np.array_equal(q[0], native.call("configuration")[1])
        frames = venv.env_method("render", indices=0)
        assert len(frames) == 1 and frames[0].shape == (32, 32, 3)
        with pytest.raises(TypeError, match="no arguments"):
            venv.env_method("configuration", 1)
        with pytest.raises(AttributeError, match=r"configuration, render, trimeshes copy by copy.*not 'step'"):
            venv.env_method("step")
    finally:
        venv.close()


def test_the_sb3_adapters_env_method_answers_through_vector_wrappers_without_call() -> None:
    """Gymnasium's ``VectorWrapper`` does not pass ``call`` on: ``env_method("get_state")`` through a user's own
    wrapper, or the goal wrapper, raised "'...' object has no attribute 'call'". The goal's ``compute_reward``
    under the user's wrapper is still the one HER gets."""
    from redsim.envs.sb3 import SB3VecEnv

    class UserWrapper(gym.vector.VectorWrapper):
        pass

    for goal in (False, True):
        inner = SB3VecEnv.make(ID, num_envs=2, goal=goal).venv
        venv = SB3VecEnv(UserWrapper(inner))
        try:
            venv.reset()
            states = venv.env_method("get_state", indices=[1])
            assert len(states) == 1 and np.array_equal(states[0]["z"], inner.unwrapped.call("get_state")[1]["z"])
            if goal:
                assert venv.get_attr("compute_reward")[0] == inner.compute_reward
        finally:
            venv.close()


def test_the_sb3_adapters_env_method_names_the_method_and_env_where_no_layer_has_call(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A user's own vector env inside (no ``call``, as Gymnasium's ``VectorEnv``): ``env_method("get_state")``
    raised a bare StopIteration."""
    from redsim.envs.sb3 import SB3VecEnv

    class UserVectorEnv(gym.vector.VectorEnv):
        pass

    venv = SB3VecEnv.make(ID, num_envs=2)
    try:
        own = UserVectorEnv()
        monkeypatch.setattr(venv, "_layers", lambda: iter([gym.vector.VectorWrapper(own), own]))
        with pytest.raises(AttributeError, match=r"env_method\('get_state'\).*VectorWrapper around UserVectorEnv"):
            venv.env_method("get_state")
    finally:
        venv.close()


@pytest.mark.parametrize("shards", [1, 2])
def test_a_step_where_every_copy_restarts_reports_the_reset_infos_as_sync(shards: int) -> None:
    """No step keys (no copy stepped), every copy's new start (the reset's info), as Gymnasium's sync vector env."""
    kwargs = {"max_episode_steps": 1}  # NEXT_STEP autoreset, both envs' default
    venv, sync = _vec(shards=shards, **kwargs), gym.make_vec(ID, num_envs=2, vectorization_mode="sync", **kwargs)
    try:
        for env in (venv, sync):
            env.reset(seed=0)
            assert "energy" in env.step(PUSH)[4]
        calls = venv.sim.stepper.evaluations.calls if shards == 1 else 0
        mine, theirs = venv.step(PUSH)[4], sync.step(PUSH)[4]
        assert sorted(mine) == sorted(theirs) and "energy" not in mine and mine["_distance"].all()
        if shards == 1:  # nothing was solved
            assert venv.sim.stepper.evaluations.calls == calls
        for key in mine:
            np.testing.assert_allclose(mine[key], theirs[key], rtol=1e-5, atol=1e-6, err_msg=key)
    finally:
        venv.close()


def _same_state(a: dict, b: dict) -> bool:
    """Equal get_state()s, generators' states included."""
    return all(
        np.array_equal(a[k], b[k]) if isinstance(a[k], np.ndarray) else a[k] == b[k]
        for k in ("z", "z_prev", "model", "elapsed_steps", "autoresetting", "rngs")
    ) and all(np.array_equal(a["params"][k], b["params"][k]) for k in a["params"])


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_a_step_interrupted_in_its_autoreset_leaves_every_copy_as_it_was(mode: AutoresetMode) -> None:
    """Ctrl-C after the simulation step (here in the autoreset's draw) is undone: the clock, the generators, z."""
    venv, twin = (_vec(max_episode_steps=2, autoreset_mode=mode) for _ in range(2))
    for env in (venv, twin):
        env.reset(seed=0)
        env.step(PUSH)
        if mode == AutoresetMode.NEXT_STEP:
            env.step(PUSH)  # both copies end here; the next step resets them
    before = venv.get_state()
    draw = venv.sim.reset_rows

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    venv.sim.reset_rows = interrupted
    with pytest.raises(KeyboardInterrupt):
        venv.step(PUSH)
    venv.sim.reset_rows = draw
    assert _same_state(venv.get_state(), before)
    got, want = venv.step(PUSH), twin.step(PUSH)
    for a, b in zip(got[:4], want[:4], strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_single_env_step_interrupted_after_the_simulation_leaves_it_as_it_was() -> None:
    env, twin = gym.make(ID), gym.make(ID)
    for e in (env, twin):
        e.reset(seed=0)
        e.step(PUSH[0])
    before = env.unwrapped.get_state()
    sim = env.unwrapped.sim
    observe = sim.observe

    def interrupted():
        raise KeyboardInterrupt

    sim.observe = interrupted
    with pytest.raises(KeyboardInterrupt):
        env.step(PUSH[0])
    sim.observe = observe
    after = env.unwrapped.get_state()
    assert all(np.array_equal(after[k], before[k]) for k in ("z", "z_prev", "model"))
    np.testing.assert_array_equal(env.step(PUSH[0])[0], twin.step(PUSH[0])[0])


def test_the_native_vector_env_takes_the_env_itself_and_names_the_fix_for_a_wrapped_one() -> None:
    """A wrapper would act on no copy (the copies are rows of one simulation): refused, naming env.unwrapped and the
    TimeLimit's length for max_episode_steps."""
    from redsim.envs.vector import LatentVectorEnv

    for wrapped in (redsim.envs.make("mini_chain"), gym.make(ID)):
        with pytest.raises(TypeError, match=r"pass env\.unwrapped .*max_episode_steps=200\)"):
            LatentVectorEnv(wrapped, 2)
    with pytest.raises(TypeError, match="takes a redsim LatentEnv, got str"):
        LatentVectorEnv(ID, 2)
    venv = LatentVectorEnv(redsim.envs.make("mini_chain").unwrapped, 2, max_episode_steps=200)
    assert venv.reset(seed=0)[0].shape == (2, *venv.single_observation_space.shape)


@pytest.mark.parametrize("shards", [1, 2])
def test_a_users_own_id_gets_the_native_vector_env_through_make_vec(shards: int) -> None:
    """A user's scene registered with ``redsim.envs:make`` and ``redsim.envs:make_vec`` (a review found no vector
    entry point for it: ``make_vec`` fell back to N separate simulations): one batched solve, or P workers, whose
    copies step as the single envs of the id do and end at the length in kwargs; SB3's adapter takes the id."""
    from redsim.envs.sb3 import SB3VecEnv
    from redsim.envs.vector import LatentVectorEnv

    own = "RedSimTest/MyMini-v0"
    kwargs = {"scene": redsim.scenes.build("mini_chain"), "task_options": {"goal_handle": "bottom"}, **TIGHT}
    gym.register(own, entry_point="redsim.envs:make", vector_entry_point="redsim.envs:make_vec", kwargs=kwargs)
    try:
        gym.registry[own].kwargs["max_episode_steps"] = 3
        venv = gym.make_vec(own, num_envs=2, vectorization_mode="vector_entry_point", shards=shards)
        assert shards > 1 or isinstance(venv, LatentVectorEnv)
        singles = [gym.make(own) for _ in range(2)]
        obs, _ = venv.reset(seed=5)
        alone = [env.reset(seed=5 + i)[0] for i, env in enumerate(singles)]
        np.testing.assert_allclose(obs, np.stack(alone), atol=1e-6)
        for step in range(3):
            obs, _, _, truncated, _ = venv.step(PUSH)
            alone = [env.step(PUSH[i]) for i, env in enumerate(singles)]
            np.testing.assert_allclose(obs, np.stack([a[0] for a in alone]), atol=1e-6)
            assert truncated.tolist() == [a[3] for a in alone] == [step == 2] * 2
        venv.close()
        if shards == 1:
            adapter = SB3VecEnv.make(own, 2)
            assert adapter.num_envs == 2 and adapter.reset().shape == (2, *venv.single_observation_space.shape)
            with pytest.raises(ValueError, match="max_episode_steps must be None or -1"):
                redsim.envs.make_vec("mini_chain", num_envs=2, max_episode_steps=0)
            with pytest.raises(ValueError, match="render_mode must be None or 'rgb_array'"):
                redsim.envs.make_vec("mini_chain", num_envs=2, render_mode="ansi")
    finally:
        gym.registry.pop(own)


def _episode_end(env: gym.Env, most: int = 12) -> int | None:
    """The step (1-based) at which ``env`` first truncates within ``most`` steps, or None."""
    env.reset(seed=0)
    for step in range(1, most + 1):
        if env.step(PUSH[0])[3]:
            return step
    return None


def test_a_users_own_id_ends_its_episodes_where_gymnasium_says_single_and_vectorized() -> None:
    """Registered the Gymnasium way, the length in the spec (helper-193's finding): ``gym.make`` ended episodes at
    make's own 200 steps inside the spec's N, and ``gym.make_vec``, which passes N to make_vec, at N; a length given
    to ``gym.make``, -1 (no limit) and a copy made from the spec where the id is not registered (a spawned worker)
    hold too (helper-194's), and the vectorized copies of a single env take the length that ends its episodes."""
    from redsim.trainers.agents import _base_env

    own = "RedSimTest/MyMiniLength-v0"
    kwargs = {"scene": "mini_chain", "task_options": {"goal_handle": "bottom"}, **TIGHT}
    gym.register(own, entry_point="redsim.envs:make", vector_entry_point="redsim.envs:make_vec", kwargs=kwargs)
    try:
        gym.registry[own].max_episode_steps = 4
        venv = gym.make_vec(own, num_envs=2, vectorization_mode="vector_entry_point")
        venv.reset(seed=0)
        assert [bool(venv.step(PUSH)[3][0]) for _ in range(4)] == [False, False, False, True]
        venv.close()
        for made, end in (
            (gym.make(own), 4),
            (gym.make(own, max_episode_steps=8), 8),
            (gym.make(own, max_episode_steps=2), 2),
        ):
            assert _episode_end(made) == end and _base_env(made)[1] == end and made.spec.max_episode_steps == end
        assert _episode_end(gym.make(own, max_episode_steps=-1)) is None  # was 200: make's own inside no limit
        spec = gym.registry.pop(own)
        assert _episode_end(gym.make(spec)) == 4  # as a spawned worker makes it, the id unknown there
        gym.register(
            own, entry_point="redsim.envs:make", kwargs={**kwargs, "max_episode_steps": 3}, max_episode_steps=4
        )
        assert _episode_end(gym.make(own)) == 3  # a length in the kwargs holds, as gym.make_vec passes it
        assert redsim.envs.make("mini_chain")._max_episode_steps == 200  # no spec: make's own default
    finally:
        gym.registry.pop(own, None)


@pytest.mark.parametrize("shards", [1, 2])
def test_a_step_before_reset_raises_what_sync_raises(shards: int) -> None:
    """Gymnasium's sync env raises ``ResetNeeded`` for a step before its reset, so ``except ResetNeeded`` catches
    the native and sharded envs' refusal too (a review's finding: they raised a plain RuntimeError)."""
    sync = gym.vector.SyncVectorEnv([lambda: gym.make(ID)] * 2)
    with pytest.raises(gym.error.ResetNeeded):
        sync.step(PUSH)
    sync.close()
    venv = _vec(shards=shards)
    try:
        with pytest.raises(gym.error.ResetNeeded, match=r"call reset\(\) before step\(\)"):
            venv.step(PUSH)
        venv.reset(seed=0)
        venv.step(PUSH)  # usable after the refusal
    finally:
        venv.close()


@pytest.mark.parametrize("shards", [1, 2])
def test_render_before_every_copy_was_reset_is_refused_as_sync(shards: int) -> None:
    """Gymnasium's sync env's copies refuse a render before their reset (OrderEnforcing); a copy's picture is then
    of no episode."""
    sync = gym.vector.SyncVectorEnv([lambda: gym.make(ID, render_mode="rgb_array")] * 2)
    with pytest.raises(gym.error.ResetNeeded):
        sync.render()
    sync.close()
    venv = _vec(shards=shards, render_mode="rgb_array")
    try:
        with pytest.raises(gym.error.ResetNeeded, match="render"):
            venv.render()
        venv.reset(seed=0, options={"reset_mask": np.array([True, False])})
        with pytest.raises(gym.error.ResetNeeded, match=r"copies \[1\]"):
            venv.render()
        venv.reset(options={"reset_mask": np.array([False, True])})
        assert len(venv.render()) == 2
    finally:
        venv.close()


@pytest.mark.parametrize("shards", [1, 2])
def test_render_without_a_render_mode_warns_as_a_single_env_and_the_sync_env_do(shards: int) -> None:
    """Made without ``render_mode``, render() draws nothing: the single env, Gymnasium's sync env (through its copies)
    and SB3's VecEnv say so with a warning; the vector envs returned None silently."""
    venv = _vec(shards=shards)
    try:
        venv.reset(seed=0)
        with pytest.warns(UserWarning, match="render_mode='rgb_array'"):
            assert venv.render() is None
        with pytest.warns(UserWarning, match="render_mode='rgb_array'"):
            assert venv.call("render") == (None, None)
        venv.close()
        with pytest.raises(gym.error.ClosedEnvironmentError, match="closed"):  # the sharded env warned, gave None
            venv.render()
    finally:
        venv.close()


def test_a_closed_native_vector_env_refuses_to_step_or_reset_as_the_sharded_one_does() -> None:
    """Closed, it went on stepping as if open (the sharded env raises: test_sharded.py)."""
    venv = gym.make_vec(ID, num_envs=2, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    venv.close()
    with pytest.raises(gym.error.ClosedEnvironmentError, match="this LatentVectorEnv is closed"):  # AsyncVectorEnv's
        venv.step(np.zeros((2, 3), np.float32))
    with pytest.raises(RuntimeError, match="this LatentVectorEnv is closed"):
        venv.reset(seed=0)
    # its state and per-copy calls too (they answered from the closed env; helper-207)
    for call in (venv.unwrapped.get_state, lambda: venv.call("configuration"), lambda: venv.call("get_state")):
        with pytest.raises(gym.error.ClosedEnvironmentError, match="this LatentVectorEnv is closed"):
            call()
    venv.close()  # closing again stays harmless
