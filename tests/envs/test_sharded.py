"""The sharded vector env (worker processes, each a native vector env of a block of copies) is the native one."""

from __future__ import annotations

import contextlib
import math
import multiprocessing
import os
import pickle
import signal
import subprocess
import sys
import time
import types
import warnings
from collections.abc import Iterator

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

from redsim.envs import sharded as sharded_module
from redsim.envs.sb3 import SB3VecEnv
from redsim.envs.sharded import (
    JOIN_TIMEOUT_S,
    KILL_AFTER_S,
    ShardedVectorEnv,
    ShardError,
    ShardTimeoutError,
    shard_sizes,
)

TIGHT = {"dtype": "float64", "stepper_options": {"tol": 1e-10, "max_iter": 60}}
"""Solved tightly, so that the batch composition does not move a copy's solve (see test_envs.py)."""


def _rollout(venv: gym.vector.VectorEnv, actions: np.ndarray, seed: int) -> tuple[list, list, list, list]:
    obs, _ = venv.reset(seed=seed)
    observations, rewards, dones, finals = [obs], [], [], []
    for a in actions:
        obs, reward, terminated, truncated, info = venv.step(a)
        observations.append(obs)
        rewards.append(reward)
        dones.append(terminated | truncated)
        finals.append(info.get("_final_obs", np.zeros(len(obs), dtype=bool)))
    return observations, rewards, dones, finals


@pytest.mark.parametrize(
    "mode",
    # SAME_STEP's shards also meet in test_a_key_only_some_shards_report_is_merged_as_the_native_env_reports_it
    [AutoresetMode.NEXT_STEP, pytest.param(AutoresetMode.SAME_STEP, marks=pytest.mark.slow)],
)
def test_sharded_env_equals_the_native_vector_env(mode: AutoresetMode) -> None:
    """Same seeds (copy i: seed + i), same actions, same autoresets, over 3 uneven shards of 5 copies."""
    n, steps = 5, 9
    actions = np.random.default_rng(0).uniform(-1, 1, (steps, n, 3)).astype(np.float32)
    kwargs = {"max_episode_steps": 4, "autoreset_mode": mode, **TIGHT}
    native = gym.make_vec("RedSim/MiniChain-v0", num_envs=n, vectorization_mode="vector_entry_point", **kwargs)
    sharded = gym.make_vec(
        "RedSim/MiniChain-v0", num_envs=n, vectorization_mode="vector_entry_point", shards=3, **kwargs
    )
    try:
        assert isinstance(sharded, ShardedVectorEnv) and sharded.sizes == [2, 2, 1]
        assert sharded.observation_space == native.observation_space and sharded.action_space == native.action_space
        expected, got = _rollout(native, actions, 11), _rollout(sharded, actions, 11)
        for a, b in zip(expected[:2], got[:2], strict=True):
            np.testing.assert_allclose(np.array(b), np.array(a), rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(np.array(got[2]), np.array(expected[2]))
        np.testing.assert_array_equal(np.array(got[3]), np.array(expected[3]))
        assert np.array(got[2])[3].all()  # every copy truncated at max_episode_steps = 4
        _, _, _, _, info = sharded.step(actions[0])
        _, _, _, _, native_info = native.step(actions[0])
        assert set(info) == set(native_info) and all(len(v) == n for v in info.values())
        sharded._processes[1].kill()  # a worker that dies raises in the caller, and the env closes
        sharded._processes[1].join()
        with pytest.raises(ShardError, match="shard 1: the worker process exited"):
            sharded.step(actions[0])
        assert sharded.closed
    finally:
        native.close()
        sharded.close()


def test_reset_mask_state_round_trip_render_and_close() -> None:
    venv = gym.make_vec(
        "RedSim/MiniChain-v0", num_envs=3, vectorization_mode="vector_entry_point", shards=2, render_mode="rgb_array"
    )
    processes = list(venv._processes)
    venv.reset(seed=0)
    state = venv.get_state()
    assert isinstance(state["rngs"], list) and len(state["rngs"]) == 3  # as the native env's, not an object array
    state = pickle.loads(pickle.dumps(state))  # what pickles instead of the env
    with pytest.raises(TypeError, match=r"does not pickle: pickle its get_state\(\)"):
        pickle.dumps(venv)
    after, *_ = venv.step(np.ones((3, 3), np.float32))
    venv.set_state(state)
    again, *_ = venv.step(np.ones((3, 3), np.float32))
    np.testing.assert_array_equal(again, after)
    kept, _ = venv.reset(options={"reset_mask": np.array([True, False, False])})
    assert not np.array_equal(kept[0], again[0])  # copy 0 reset, copies 1 and 2 untouched
    np.testing.assert_array_equal(kept[1:], again[1:])
    frames = venv.render()
    assert len(frames) == 3 and frames[0].ndim == 3 and frames[0].dtype == np.uint8
    venv.close()
    assert all(not p.is_alive() for p in processes)
    with pytest.raises(gym.error.ClosedEnvironmentError, match="this ShardedVectorEnv is closed"):
        venv.step(np.zeros((3, 3), np.float32))


def test_a_tracking_camera_frames_the_sharded_copies_as_the_native_env_does() -> None:
    """Each shard framed its own copies (its first copy's shape, its markers); now every shard draws with the view of
    all copies, pixel for pixel the native env's, through steps (a marker leaving the view reframes), a masked
    reset and a restored state."""
    kwargs = {"num_envs": 4, "vectorization_mode": "vector_entry_point", "render_mode": "rgb_array"}
    kwargs |= {"width": 64, "height": 64, "camera": {"track": True}, "dtype": "float64"}
    native = gym.make_vec("RedSim/MiniChain-v0", **kwargs)
    sharded = gym.make_vec("RedSim/MiniChain-v0", shards=2, **kwargs)
    actions = np.random.default_rng(0).uniform(-1, 1, (12, 4, 3)).astype(np.float32)

    def same_frames() -> None:
        for a, b in zip(native.render(), sharded.render(), strict=True):
            np.testing.assert_array_equal(a, b)

    try:
        for venv in (native, sharded):
            venv.reset(seed=3)
        same_frames()
        state = native.get_state()
        for action in actions:
            native.step(action)
            sharded.step(action)
            same_frames()
        mask = {"reset_mask": np.array([False, False, True, False])}
        native.reset(options=mask)
        sharded.reset(options=mask)
        same_frames()
        native.set_state(state)
        sharded.set_state(state)
        same_frames()
    finally:
        native.close()
        sharded.close()


def test_bad_input_is_a_clear_error_and_a_worker_s_error_raises_in_the_caller() -> None:
    make = lambda **kw: gym.make_vec(  # noqa: E731
        "RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point", **kw
    )
    with pytest.raises(ValueError, match="shards must be an integer in"):
        shard_sizes(2, 3)
    with pytest.raises(ValueError, match="shards must be an integer in"):
        make(shards=0)
    with pytest.raises(ValueError, match="unknown hessian"):  # raised here, before any worker starts
        make(shards=2, stepper_options={"hessian": "unknown"})
    venv = make(shards=2)
    assert venv.max_episode_steps == 200  # the id's, as the native env's
    with pytest.raises(gym.error.ResetNeeded, match="call reset"):  # as the native env, and the env stays usable
        venv.step(np.zeros((2, 3), np.float32))
    venv.reset(seed=0)
    with pytest.raises(ValueError, match="finite"):
        venv.step(np.full((2, 3), np.nan, np.float32))
    with pytest.raises(ValueError, match="state is missing"):  # checked here, in the native env's order
        venv.set_state({"z": None})
    with pytest.raises(ValueError, match="one row per copy"):
        venv.set_state({**venv.get_state(), "z": None})
    with pytest.raises(ValueError, match=r"state\['loads'\] must have shape"):  # before a worker refuses it
        venv.set_state({**venv.get_state(), "loads": np.zeros((2, 1, 1))})
    for key in ("z", "z_prev", "loads"):  # non-finite: refused here too, as the native env refuses it
        with pytest.raises(ValueError, match=rf"state\['{key}'\] must be finite"):
            venv.set_state({**venv.get_state(), key: np.full_like(venv.get_state()[key], np.nan)})
    with pytest.raises(ValueError, match="must name a NumPy bit generator"):  # here too, before any worker
        venv.set_state({**venv.get_state(), "rngs": [None, None]})
    assert not venv.closed
    with pytest.raises(ValueError, match="state is missing") as raised:  # a worker's own error, as itself
        venv._call([("set_state", {})] * len(venv.sizes))  # (a request the checks above would have refused)
    assert "shard 0:" in "\n".join(raised.value.__notes__)  # with the worker's traceback
    assert venv.closed  # (a worker that dies: test_sharded_env_equals_the_native_vector_env)


class _Interrupting:
    """A pipe end whose recv is interrupted (as by Ctrl-C while a step is in flight)."""

    def __init__(self, pipe) -> None:
        self.pipe = pipe

    def send(self, message) -> None:
        self.pipe.send(message)

    def recv(self):
        raise KeyboardInterrupt

    def close(self) -> None:
        self.pipe.close()


def test_an_interrupted_request_closes_the_env_instead_of_leaving_answers_unread() -> None:
    venv = gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point", shards=2)
    processes = list(venv._processes)
    venv.reset(seed=0)
    venv._pipes[1] = _Interrupting(venv._pipes[1])
    with pytest.raises(KeyboardInterrupt):
        venv.step(np.zeros((2, 3), np.float32))
    assert venv.closed and all(not p.is_alive() for p in processes)
    with pytest.raises(RuntimeError, match="closed"):
        venv.reset(seed=0)


def test_a_key_only_some_shards_report_is_merged_as_the_native_env_reports_it() -> None:
    """SAME_STEP: copies 2 and 3 (shard 1) restart a step later, so at step 3 only shard 0 reports final_obs."""
    kwargs = {"max_episode_steps": 3, "autoreset_mode": AutoresetMode.SAME_STEP, **TIGHT}
    envs = [
        gym.make_vec("RedSim/MiniChain-v0", num_envs=4, vectorization_mode="vector_entry_point", **kwargs),
        gym.make_vec("RedSim/MiniChain-v0", num_envs=4, vectorization_mode="vector_entry_point", shards=2, **kwargs),
    ]
    actions = np.random.default_rng(1).uniform(-1, 1, (4, 4, 3)).astype(np.float32)
    infos = []
    try:
        for venv in envs:
            venv.reset(seed=[5, 6, 7, 8])
            venv.step(actions[0])
            venv.reset(options={"reset_mask": np.array([False, False, True, True])})
            steps = [venv.step(a) for a in actions[1:]]
            infos.append(steps[1][4])  # step 3: copies 0 and 1 truncate, 2 and 3 do not
    finally:
        for venv in envs:
            venv.close()
    native, sharded = infos
    assert set(sharded) == set(native)
    np.testing.assert_array_equal(sharded["_final_obs"], [True, True, False, False])
    np.testing.assert_array_equal(sharded["_final_obs"], native["_final_obs"])
    for i in (0, 1):
        np.testing.assert_allclose(sharded["final_obs"][i], native["final_obs"][i], rtol=1e-6, atol=1e-6)
    final_s, final_n = sharded["final_info"], native["final_info"]
    assert set(final_s) == set(final_n) and "is_success" in final_n
    for key in final_n:
        if key.startswith("_"):
            np.testing.assert_array_equal(final_s[key], [True, True, False, False])
            np.testing.assert_array_equal(final_s[key], final_n[key])
        else:  # every entry: the masked ones keep the step's value in both (zeros in shard 1 before stop 50)
            np.testing.assert_allclose(final_s[key], final_n[key], rtol=1e-4, atol=1e-4)
    assert sharded["final_obs"][2] is None and sharded["final_obs"][3] is None


def test_a_masked_first_reset_and_garbage_states_as_the_native_env() -> None:
    """A shard none of whose copies a masked first reset names shows them as the native env does (at rest, zero
    task parameters; it returned zeros), and a state whose setting is no dict, or whose task parameters are no
    numbers, is the native env's ValueError (a TypeError before): a review's findings."""
    envs = [
        gym.make_vec("RedSim/MiniChain-v0", num_envs=3, vectorization_mode="vector_entry_point", **TIGHT),
        gym.make_vec("RedSim/MiniChain-v0", num_envs=3, vectorization_mode="vector_entry_point", shards=2, **TIGHT),
    ]
    try:
        first = {"reset_mask": np.array([True, False, False])}
        native, sharded = (venv.reset(seed=4, options=first)[0] for venv in envs)
        np.testing.assert_allclose(sharded, native, atol=1e-12)
        for venv in envs:
            venv.reset(seed=0)
            good = venv.get_state()
            with pytest.raises(ValueError, match=r"state\['setting'\] must be the dict get_state\(\) wrote"):
                venv.set_state({**good, "setting": 5})
            key = next(iter(good["params"]))
            bad = {**good, "params": {**good["params"], key: np.full(np.shape(good["params"][key]), "x")}}
            with pytest.raises(ValueError, match=f"params.{key}"):
                venv.set_state(bad)
    finally:
        for venv in envs:
            venv.close()


def test_sb3_adapter_runs_on_shards() -> None:
    venv = SB3VecEnv.make("RedSim/MiniChain-v0", 4, shards=2)
    try:
        obs = venv.reset()
        assert obs.shape == (4, *venv.observation_space.shape)
        obs, reward, _, infos = venv.step(np.zeros((4, 3), np.float32))
        assert reward.shape == (4,) and len(infos) == 4 and np.isfinite(obs).all()
    finally:
        venv.close()


def test_a_condition_outside_its_space_is_refused_before_the_workers_and_the_env_stays_open() -> None:
    """As the native env: ``set_state`` refuses a ``cond`` beyond the scene's condition space in this process."""
    venv = gym.make_vec("RedSim/ConditionalBar-v0", num_envs=2, vectorization_mode="vector_entry_point", shards=2)
    try:
        venv.reset(seed=0)
        state = venv.get_state()
        high = venv.template.sim.scene.condition_space.high.numpy()
        with pytest.raises(ValueError, match=r"state\['cond'\] must lie in the condition space"):
            venv.set_state({**state, "cond": np.tile(2.0 * np.abs(high) + 1.0, (2, 1))})
        assert not venv.closed
        venv.set_state(state)  # still usable
        venv.step(np.zeros((2, *venv.single_action_space.shape), np.float32))
    finally:
        venv.close()


@contextlib.contextmanager
def _reaped(venv: ShardedVectorEnv) -> Iterator[list[multiprocessing.Process]]:
    """The env's worker processes; on the way out, whatever the test did, the env closed and every worker killed
    (SIGKILL ends a stopped one too), so a failing test leaves no process behind."""
    processes = list(venv._processes)
    try:
        yield processes
    finally:
        for process in processes:
            if process.is_alive():
                process.kill()
                process.join(5.0)
        venv.close()


def _make(**kwargs) -> ShardedVectorEnv:
    return gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point", shards=2, **kwargs)


def test_a_stopped_worker_times_out_the_step_closes_the_env_and_is_killed() -> None:
    """A worker that never answers (SIGSTOP: it also ignores SIGTERM until continued) blocked ``step`` for ever; with
    ``timeout`` the step raises after about that many seconds, as Gymnasium's ``step_wait(timeout)`` raises
    ``multiprocessing.TimeoutError``, the env is closed and no worker is left (the stopped one killed)."""
    venv = _make(timeout=1.0)
    with _reaped(venv) as processes:
        assert venv.timeout == 1.0 and venv.spec.kwargs["timeout"] == 1.0
        assert "timeout" not in venv.get_attr("spec")[0].kwargs  # the vector env's argument, not a copy's
        venv.reset(seed=0)
        venv.step(np.zeros((2, 3), np.float32))  # a step within the timeout is an ordinary step
        os.kill(processes[1].pid, signal.SIGSTOP)
        start = time.monotonic()
        with pytest.raises(ShardTimeoutError) as raised:
            venv.step(np.zeros((2, 3), np.float32))
        elapsed = time.monotonic() - start
        assert isinstance(raised.value, multiprocessing.TimeoutError) and isinstance(raised.value, ShardError)
        message = str(raised.value)
        assert f"step timed out after 1 s: shard 1 (copy 1, worker pid {processes[1].pid}) did not answer" in message
        assert "shard 0" not in message and "the env is closed" in message and "Make the env again" in message
        assert 0.9 < elapsed < 1.0 + KILL_AFTER_S + 3.0  # the timeout, then at most KILL_AFTER_S for the SIGKILL
        assert venv.closed and not any(process.is_alive() for process in processes)
        assert processes[1].exitcode == -signal.SIGKILL  # SIGTERM did not stop it: killed
        with pytest.raises(gym.error.ClosedEnvironmentError, match="closed"):
            venv.step(np.zeros((2, 3), np.float32))


def test_every_request_is_timed_the_start_is_not() -> None:
    """The start (each worker builds its env: far more than a microsecond) is not timed; a request is (here
    ``reset``, which the stopped worker 1 cannot answer). It was a live worker's reset, which a caller descheduled on a
    busy machine, between sending it and polling, for the few ms the reset takes, found answered: the reset passed."""
    venv = _make(timeout=1e-6)
    with _reaped(venv) as processes:
        os.kill(processes[1].pid, signal.SIGSTOP)
        # shard 0 is named too where it had not answered when the caller polled it
        hung = r"(shard 0 \(copy 0, worker pid \d+\), )?shard 1 \(copy 1, worker pid"
        with pytest.raises(ShardTimeoutError, match=r"reset timed out after 1e-06 s: " + hung):
            venv.reset(seed=0)
        assert venv.closed and not any(process.is_alive() for process in processes)


def test_close_kills_a_stopped_worker_instead_of_leaving_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """``close`` waited JOIN_TIMEOUT_S, terminated, waited again and left a stopped worker alive (which then held up
    the interpreter's exit for ever); now it kills it, KILL_AFTER_S after the SIGTERM."""
    monkeypatch.setattr(sharded_module, "JOIN_TIMEOUT_S", 0.5)
    venv = _make()
    with _reaped(venv) as processes:
        assert venv.timeout is None  # the default: requests wait for ever, as before
        venv.reset(seed=0)
        os.kill(processes[0].pid, signal.SIGSTOP)
        start = time.monotonic()
        venv.close()
        assert time.monotonic() - start < 0.5 + KILL_AFTER_S + 3.0
        assert not any(process.is_alive() for process in processes)
        assert processes[0].exitcode == -signal.SIGKILL
        # the healthy worker exits on close's request, or is terminated where a loaded machine keeps its exit past
        # the join window (0.5 s here): either way it is gone
        assert processes[1].exitcode in (0, -signal.SIGTERM)


def test_close_waits_no_longer_than_the_envs_timeout_for_a_stopped_worker() -> None:
    """With ``timeout`` set, ``close`` waited the full JOIN_TIMEOUT_S (10 s) for a hung worker before the SIGTERM; it
    now waits at most the timeout the user gave for every other request (review of 42e7b28)."""
    venv = _make(timeout=0.5)
    with _reaped(venv) as processes:
        venv.reset(seed=0)
        os.kill(processes[0].pid, signal.SIGSTOP)
        start = time.monotonic()
        venv.close()
        assert time.monotonic() - start < 0.5 + KILL_AFTER_S + 3.0 < JOIN_TIMEOUT_S
        assert not any(process.is_alive() for process in processes)
        assert processes[0].exitcode == -signal.SIGKILL
        # the healthy worker exits on close's request, or is terminated where a loaded machine keeps its exit past
        # the join window (0.5 s here): either way it is gone
        assert processes[1].exitcode in (0, -signal.SIGTERM)


@pytest.mark.parametrize("timeout", [0, -1.0, math.nan, math.inf, True, "5"])
def test_a_bad_timeout_is_refused_before_any_worker_starts(timeout: object) -> None:
    with pytest.raises(ValueError, match=r"timeout must be None \(wait for ever\) or a finite number of seconds > 0"):
        _make(timeout=timeout)


def test_a_timeout_without_shards_is_refused() -> None:
    with pytest.raises(ValueError, match="shards=1 makes the native vector env"):  # no worker to wait for
        gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point", timeout=5.0)


class _Pipe:
    """A worker's pipe as _gather sees it: ``polls`` answered in turn (the last one for ever), then ``answer``."""

    def __init__(self, polls: list[bool], answer: object = ("ok", None)) -> None:
        self.polls, self.answer = polls, answer

    def poll(self, _timeout: float = 0.0) -> bool:
        return self.polls.pop(0) if len(self.polls) > 1 else self.polls[0]

    def recv(self) -> object:
        return self.answer

    def close(self) -> None:
        pass


class _Process:
    pid, exitcode = 4321, None

    def join(self, _timeout: float | None = None) -> None:
        pass

    def is_alive(self) -> bool:
        return False


class _Template:
    def close(self) -> None:
        pass


def _gathering(pipes: list[_Pipe]) -> ShardedVectorEnv:
    """A sharded env of one copy per pipe, its workers faked (no process starts), with timeout 1 s."""
    venv = object.__new__(ShardedVectorEnv)
    venv.sizes, venv.starts, venv.timeout = [1] * len(pipes), list(range(len(pipes))), 1.0
    venv._pipes, venv._processes, venv.template, venv.closed = pipes, [_Process() for _ in pipes], _Template(), False
    return venv


def test_an_answer_just_past_the_deadline_still_names_its_shard() -> None:
    """The shard whose poll ran out is named even where its answer lands before the hung shards are listed (it was
    left out: "timed out after 1 s:  did not answer" named no shard)."""
    venv = _gathering([_Pipe([True]), _Pipe([False, True])])  # shard 1: late by a hair, then readable
    with pytest.raises(ShardTimeoutError, match=r"step timed out after 1 s: shard 1 \(copy 1, worker pid 4321\) did"):
        venv._gather(what="step")
    assert venv.closed


def test_a_worker_error_before_a_timeout_is_kept_in_its_message() -> None:
    """Shard 0 answered with its error, shard 1 never answered: the timeout's message kept shard 0's traceback (it
    was dropped, and with it why the run went wrong)."""
    failed = _Pipe([True], ("error", (None, "Traceback (most recent call last):\nValueError: boom")))
    venv = _gathering([failed, _Pipe([False])])
    with pytest.raises(ShardTimeoutError) as raised:
        venv._gather(what="step")
    message = str(raised.value)
    assert "shard 1 (copy 1, worker pid 4321) did not answer" in message and "shard 0 (" not in message
    assert message.endswith("A worker failed before it: shard 0:\nTraceback (most recent call last):\nValueError: boom")


def test_a_callers_warning_display_the_workers_cannot_import_leaves_them_pythons(
    monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """A ``warnings.showwarning`` that pickles by reference but that a worker cannot import (one defined in a notebook
    or a ``python -c`` script: its module is ``__main__``) went to each worker as a Process argument, and each died
    unpickling it before building its env (ShardError "the worker process exited"). Now the worker keeps Python's
    display, and its warnings still print."""
    module = types.ModuleType("display_only_in_the_caller")  # what a spawned worker cannot import

    def display(*args: object, **kwargs: object) -> None:
        said.append(str(args[0]))

    said: list[str] = []
    display.__module__, display.__qualname__ = module.__name__, "display"
    module.display = display  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, module.__name__, module)
    monkeypatch.setattr(warnings, "showwarning", display)
    pickle.dumps(display)  # it pickles here, as a notebook's function does
    # spawn, not the forkserver, whose workers write to the fd 2 it had when an earlier test started it, not capfd's
    monkeypatch.setattr(sharded_module.mp, "get_all_start_methods", lambda: ["spawn"])
    venv = gym.make_vec(
        "RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point", shards=2, dt=0.001, timeout=60.0
    )
    try:
        obs, _ = venv.reset(seed=0)
        assert obs.shape[0] == 2
    finally:
        venv.close()
    err = capfd.readouterr().err
    assert any("resolves accelerations only to" in line for line in said)  # the caller's display in the caller
    assert "UserWarning: torch.float32 at dt=0.001 s resolves accelerations only to" in err, err  # Python's in workers


def test_a_script_read_from_stdin_makes_a_sharded_env() -> None:
    """``python - <<EOF``: the main module's ``__file__`` is '<stdin>', which each worker tried to run again and died of
    FileNotFoundError before it started (a ShardError whose hint blamed a missing ``__main__`` guard)."""
    script = (
        "import gymnasium as gym, redsim.envs\n"
        "venv = gym.make_vec('RedSim/MiniChain-v0', num_envs=2, vectorization_mode='vector_entry_point', shards=2)\n"
        "observation, _ = venv.reset(seed=0)\n"
        "print('shape', observation.shape)\n"
        "venv.close()\n"
    )
    done = subprocess.run([sys.executable, "-"], input=script, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "shape (2, " in done.stdout
