"""redsim.threads: a block runs on its own torch thread count and the caller's setting comes back, also when
blocks nest, raise, or run in several Python threads; and the envs compute on their ``threads``."""

from __future__ import annotations

import threading

import gymnasium as gym
import numpy as np
import pytest
import torch

from redsim.envs.base import LatentSim
from redsim.threads import check_threads, torch_threads


@pytest.fixture
def two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def test_a_block_runs_on_its_count_and_restores_the_caller_s(two_threads) -> None:
    with torch_threads(1):
        assert torch.get_num_threads() == 1
        with torch_threads(3):
            assert torch.get_num_threads() == 3
        assert torch.get_num_threads() == 1  # the outer block's count again
    assert torch.get_num_threads() == 2
    with pytest.raises(RuntimeError), torch_threads(1):
        raise RuntimeError("inside")
    assert torch.get_num_threads() == 2
    with torch_threads(None):
        assert torch.get_num_threads() == 2


def test_blocks_in_several_python_threads_give_each_its_own_setting_back(two_threads) -> None:
    """Two Python threads with settings of their own run overlapping blocks: each gets its own setting back."""
    inside = threading.Barrier(2)
    after = {}

    def work(own: int) -> None:
        torch.set_num_threads(own)
        with torch_threads(1):
            inside.wait()  # both blocks run at once
            assert torch.get_num_threads() == 1
            inside.wait()
        after[own] = torch.get_num_threads()

    workers = [threading.Thread(target=work, args=(own,)) for own in (3, 4)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    assert after == {3: 3, 4: 4}


def test_a_count_torch_refuses_changes_nothing(two_threads) -> None:
    """A count past what torch takes is refused by check_threads; torch's own refusal leaves the setting as it was."""
    with pytest.raises(ValueError, match="threads must be None or an integer in"):
        check_threads(2**40)
    with pytest.raises((ValueError, RuntimeError, OverflowError)), torch_threads(2**40):
        pass
    assert torch.get_num_threads() == 2
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "1", 2**16])
def test_check_threads_refuses_what_is_not_a_count(bad) -> None:
    with pytest.raises(ValueError, match="threads must be None or an integer in"):
        check_threads(bad)
    assert check_threads(None) is None and check_threads(np.int64(2)) == 2


@pytest.mark.parametrize(("threads", "inside"), [(None, 2), (1, 1), (2, 2)])
def test_envs_step_render_and_reset_on_their_threads(
    two_threads, monkeypatch: pytest.MonkeyPatch, threads: int | None, inside: int
) -> None:
    """The single and the vector env compute on ``threads`` (default 1; None: the caller's), and the caller's
    setting is back after every call."""
    seen = []
    for name in ("step", "reset_rows", "draw_rows", "set_state", "positions", "clone"):
        original = getattr(LatentSim, name)
        monkeypatch.setattr(
            LatentSim, name, lambda *a, _f=original, **k: seen.append(torch.get_num_threads()) or _f(*a, **k)
        )
    kwargs = {} if threads == 1 else {"threads": threads}  # 1 is the default
    env = gym.make("RedSim/MiniChain-v0", render_mode="rgb_array", width=32, height=32, **kwargs)
    env.reset(seed=0)
    env.step(env.action_space.sample())
    env.render()
    venv = gym.make_vec(
        "RedSim/MiniChain-v0", 2, "vector_entry_point", render_mode="rgb_array", width=32, height=32, **kwargs
    )
    venv.reset(seed=0)
    venv.step(venv.action_space.sample())
    venv.render()
    venv.unwrapped.set_state(venv.unwrapped.get_state())
    env.unwrapped.set_state(env.unwrapped.get_state())
    env.unwrapped.configuration()
    env.unwrapped.trimeshes()
    assert len(seen) >= 10 and set(seen) == {inside}
    assert torch.get_num_threads() == 2


def test_a_bad_thread_count_is_refused_before_the_env_builds_anything(monkeypatch: pytest.MonkeyPatch) -> None:
    from redsim.envs import fitted

    monkeypatch.setattr(fitted, "cached_subspace", lambda *a, **k: pytest.fail("fitted before checking threads"))
    with pytest.raises(ValueError, match="threads must be None or an integer"):
        gym.make("RedSim/MiniChain-v0", threads=0, scene_params={"density": 8000.0}, fit_if_missing=True)
