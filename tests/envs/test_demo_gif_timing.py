"""``redsim demo``'s GIF plays in simulated time: each frame is shown for the simulated time between kept frames,
``frame_every`` env steps of ``dt`` (capped at the fastest rate a GIF plays). With ``frame_every`` left out of the
frame time (hand mutation audit, helper-283) a demo keeping every 4th state played 4 times too fast and every demo test
passed; none read the GIF's frame time."""

from __future__ import annotations

import gymnasium as gym
from PIL import Image

from redsim.envs.demo import demo_name, run_demo
from redsim.render import MAX_GIF_FPS, gif_frame_ms


def test_the_gif_shows_each_frame_for_the_simulated_time_between_kept_states(tmp_path) -> None:
    env_id, frame_every = "RedSim/MiniChain-v0", 4
    dt = gym.make(env_id).unwrapped.dt
    assert 1.0 / (dt * frame_every) < MAX_GIF_FPS <= 1.0 / dt  # the cap does not hide the factor
    run_demo(env_id, tmp_path, steps=8, frame_every=frame_every, width=48, height=48)
    with Image.open(tmp_path / f"{demo_name(env_id, scripted=True)}.gif") as gif:
        assert gif.info["duration"] == gif_frame_ms(1.0 / (dt * frame_every))
