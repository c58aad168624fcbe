"""Pixel observations of the vector envs (redsim.envs.pixels): the frames, the autoreset modes, SB3."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode
from gymnasium.wrappers import AddRenderObservation, GrayscaleObservation

import redsim  # noqa: F401  (registers the ids)
from redsim.envs.pixels import PixelVectorObservation, grey
from redsim.envs.sb3 import PIXEL_SIDE, SB3VecEnv

ENV_ID = "RedSim/MiniChain-v0"
SIZE = 32


def _vec(mode: AutoresetMode, steps: int = 3, **kwargs) -> gym.vector.VectorEnv:
    return gym.make_vec(
        ENV_ID,
        2,
        "vector_entry_point",
        render_mode="rgb_array",
        width=SIZE,
        height=SIZE,
        max_episode_steps=steps,
        autoreset_mode=mode,
        **kwargs,
    )


def test_a_copys_frame_is_the_single_envs_pixel_observation() -> None:
    venv = PixelVectorObservation(_vec(AutoresetMode.NEXT_STEP), grayscale=True)
    obs, _ = venv.reset(seed=0)
    assert obs.shape == (2, SIZE, SIZE, 1) and obs.dtype == np.uint8 and venv.observation_space.contains(obs)
    for i in range(2):
        single = gym.make(ENV_ID, render_mode="rgb_array", width=SIZE, height=SIZE)
        single = GrayscaleObservation(AddRenderObservation(single, render_only=True), keep_dim=True)
        assert single.observation_space == venv.single_observation_space
        np.testing.assert_array_equal(obs[i], single.reset(seed=i)[0])


def test_same_step_draws_the_last_picture_before_the_reset_and_steps_as_the_native_env() -> None:
    """Over a DISABLED env the wrapper autoresets in the ending step: its frames and info are the native SAME_STEP
    env's, and final_obs holds the picture a NEXT_STEP env shows at that step (the ended episode's last state)."""
    same = PixelVectorObservation(_vec(AutoresetMode.DISABLED), autoreset_mode="SameStep")
    assert same.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    native = _vec(AutoresetMode.SAME_STEP)
    nxt = PixelVectorObservation(_vec(AutoresetMode.NEXT_STEP))
    for env in (same, native, nxt):
        env.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1, 1, (3, 2, 3)).astype(np.float32)
    for action in actions:
        obs, reward, _, truncated, info = same.step(action)
        _, native_reward, *_, native_info = native.step(action)
        last, *_ = nxt.step(action)
        np.testing.assert_array_equal(obs, np.stack(native.render()))
        np.testing.assert_array_equal(reward, native_reward)
    assert truncated.all() and sorted(info) == sorted(native_info)
    for key in ("distance", "is_success"):  # the new episodes' reset info
        np.testing.assert_array_equal(info[key], native_info[key])
    assert sorted(info["final_info"]) == sorted(native_info["final_info"])
    for key in ("distance", "reward_distance", "converged"):  # the ended step's
        np.testing.assert_array_equal(info["final_info"][key], native_info["final_info"][key])
    assert not np.array_equal(obs, last)  # the new episodes start elsewhere
    np.testing.assert_array_equal(np.stack(info["final_obs"]), last)


def test_sb3_trains_a_cnn_policy_on_the_vector_envs_frames() -> None:
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecFrameStack

    size = 40  # SB3's NatureCNN needs 36 px
    venv = SB3VecEnv.make(ENV_ID, 2, pixels={"grayscale": True}, width=size, height=size, max_episode_steps=4)
    stacked = VecFrameStack(venv, 4)
    assert stacked.observation_space.shape == (size, size, 4)
    stacked.seed(0)
    stacked.reset()
    for _ in range(4):
        obs, _, done, infos = stacked.step(np.zeros((2, 3), np.float32))
    assert done.all() and obs.shape == (2, size, size, 4)
    assert infos[0]["terminal_observation"].shape == (size, size, 4) and infos[0]["TimeLimit.truncated"]
    PPO("CnnPolicy", stacked, n_steps=8, batch_size=16, n_epochs=1, seed=0).learn(16)  # the policy reads the frames
    stacked.close()


@pytest.mark.parametrize(
    ("make", "expected"),
    [
        (lambda: PixelVectorObservation(_vec(AutoresetMode.SAME_STEP)), "autoreset_mode='Disabled'"),
        (lambda: PixelVectorObservation(_vec(AutoresetMode.NEXT_STEP), autoreset_mode="SameStep"), "NextStep into"),
        (
            lambda: PixelVectorObservation(gym.make_vec(ENV_ID, 2, "vector_entry_point")),
            "render_mode='rgb_array'",
        ),
        (lambda: SB3VecEnv.make(ENV_ID, 2, pixels=True, goal=True), "goal observations are vectors"),
        (lambda: SB3VecEnv.make(ENV_ID, 2, pixels=True, render_mode=None), "pixels=True draws"),
    ],
)
def test_a_pixel_env_that_cannot_draw_its_frames_is_refused(make, expected: str) -> None:
    with pytest.raises(ValueError, match=expected):
        make()


def test_a_gymnasium_vector_env_is_refused() -> None:
    sync = gym.make_vec(ENV_ID, 2, "sync", render_mode="rgb_array", width=SIZE, height=SIZE)
    with pytest.raises(TypeError, match="needs a redsim vector env"):
        PixelVectorObservation(sync)
    sync.close()


def test_a_final_frame_owns_its_pixels() -> None:
    """info["final_obs"][i] is copy i's last frame alone, as the native env's final_obs and render() frames: keeping
    it (a list of terminal frames) must not keep the step's whole [N, H, W, C] batch alive."""
    venv = PixelVectorObservation(_vec(AutoresetMode.DISABLED, steps=1), autoreset_mode="SameStep")
    venv.reset(seed=0)
    *_, info = venv.step(np.zeros((2, 3), np.float32))
    for frame in info["final_obs"]:
        assert frame.shape == (SIZE, SIZE, 3) and frame.base is None
    venv.close()


def test_a_pixel_env_answers_the_per_copy_calls() -> None:
    """``env_method("get_state")`` (and "configuration", "render", "trimeshes") of ``SB3VecEnv.make(...,
    pixels=True)`` was an AttributeError: Gymnasium's VectorWrapper has no ``call`` to pass on."""
    venv = SB3VecEnv.make(ENV_ID, 2, pixels=True, width=SIZE, height=SIZE)
    venv.reset()
    venv.step(np.ones((2, 3), np.float32))
    native = venv.venv.unwrapped
    for name in ("get_state", "configuration"):
        mine, theirs = venv.env_method(name), native.call(name)
        assert len(mine) == 2 and repr(mine) == repr(list(theirs))
    assert [m[0].vertices.tolist() for m in venv.env_method("trimeshes", indices=[1])] == [
        native.call("trimeshes")[1][0].vertices.tolist()
    ]
    frames = venv.env_method("render")
    np.testing.assert_array_equal(np.stack(frames), np.stack(native.render()))
    venv.close()


@pytest.mark.parametrize("pixels", ["grayscale", [1], 1])
def test_pixels_other_than_a_flag_or_the_wrappers_arguments_are_refused(pixels) -> None:
    """`pixels="grayscale"` used to build colour frames without a word (any truthy value meant True)."""
    with pytest.raises(TypeError, match="pixels must be True, False or a mapping"):
        SB3VecEnv.make(ENV_ID, 2, pixels=pixels)


def test_pixel_observations_are_84_px_unless_sized_and_an_empty_mapping_means_pixels() -> None:
    """``pixels=True`` observed the env's 480 x 480 frames (a PPO buffer of 2048 steps x 8 copies: 42 GiB), and
    ``pixels={}`` (falsy) built a state-vector env without a word."""
    for pixels in (True, {}):
        venv = SB3VecEnv.make(ENV_ID, 2, pixels=pixels)
        assert venv.observation_space.shape == (PIXEL_SIDE, PIXEL_SIDE, 3) == venv.reset().shape[1:]
        venv.close()
    venv = SB3VecEnv.make(ENV_ID, 2, pixels={"grayscale": True}, width=40, height=48)
    assert venv.observation_space.shape == (48, 40, 1)
    venv.close()


def test_grey_is_gymnasiums_grayscale_observation_for_every_colour() -> None:
    """grey() replaced Gymnasium's formula (a [..., 3] float64 product, 7x slower) by its terms in the same order."""
    wrapper = GrayscaleObservation(
        AddRenderObservation(gym.make(ENV_ID, render_mode="rgb_array", width=8, height=8), render_only=True),
        keep_dim=True,
    )
    colours = np.arange(2**24, dtype=np.uint32)
    for chunk in np.split(colours, 16):
        frames = np.stack([chunk >> 16, chunk >> 8, chunk], -1).astype(np.uint8)  # uint8 keeps the low byte
        assert np.array_equal(grey(frames), wrapper.observation(frames))
    wrapper.close()


def _masks(info: dict) -> dict:
    """An info's keys and ``_key`` masks (final_info's too): what Gymnasium's vector info says of which copy reports."""
    out = {key: value.tolist() for key, value in info.items() if key.startswith("_")}
    out["keys"] = sorted(info)
    if "final_info" in info:
        out["final_info"] = _masks(info["final_info"])
    return out


@pytest.mark.parametrize(
    ("inner", "outer"),
    [(AutoresetMode.NEXT_STEP, None), (AutoresetMode.DISABLED, None), (AutoresetMode.DISABLED, "SameStep")],
)
def test_every_autoreset_mode_reports_as_gymnasiums_sync_env_of_pixel_envs(inner, outer) -> None:
    """Against SyncVectorEnv over AddRenderObservation single envs, same seeds and actions, 7 steps of 3-step
    episodes (a masked reset in DISABLED): the same info keys and masks (final_info's too), episode ends, final_obs
    slots and reset frames. The stepped frames may differ in a few edge pixels, the batched solve's tolerance
    against the single env's (at most 0.4% of the pixels when measured): under 1% here."""
    mode = AutoresetMode.SAME_STEP if outer else inner

    def single() -> gym.Env:
        env = gym.make(ENV_ID, render_mode="rgb_array", width=SIZE, height=SIZE, max_episode_steps=3)
        return AddRenderObservation(env, render_only=True)

    sync = gym.vector.SyncVectorEnv([single] * 2, autoreset_mode=mode)
    pixels = PixelVectorObservation(_vec(inner), autoreset_mode=outer)
    assert pixels.observation_space == sync.observation_space and pixels.metadata["autoreset_mode"] == mode
    (ours, our_info), (theirs, their_info) = pixels.reset(seed=3), sync.reset(seed=3)
    np.testing.assert_array_equal(ours, theirs)
    assert _masks(our_info) == _masks(their_info)
    actions = np.random.default_rng(1).uniform(-1, 1, (7, 2, 3)).astype(np.float32)
    for t, action in enumerate(actions):
        if mode == AutoresetMode.DISABLED and t == 3:
            mask = np.array([True, True])
            (ours, our_info), (theirs, their_info) = (
                env.reset(options={"reset_mask": mask.copy()}) for env in (pixels, sync)
            )
            np.testing.assert_array_equal(ours, theirs)
            assert _masks(our_info) == _masks(their_info)
        if mode == AutoresetMode.DISABLED and t == 6:
            break
        ours, _, our_term, our_trunc, our_info = pixels.step(action)
        theirs, _, their_term, their_trunc, their_info = sync.step(action)
        assert (our_term == their_term).all() and (our_trunc == their_trunc).all()
        assert _masks(our_info) == _masks(their_info)
        assert (ours != theirs).mean() < 0.01
        if "final_obs" in their_info:
            for mine, gym_frame in zip(our_info["final_obs"], their_info["final_obs"], strict=True):
                assert (mine is None) == (gym_frame is None)
                assert mine is None or (mine != gym_frame).mean() < 0.01
    pixels.close()
    sync.close()
