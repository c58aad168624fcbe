"""`redsim demo ENV_ID --out DIR`: one episode with a trained policy or the task's scripted controller.

The scripted controller is :meth:`redsim.envs.base.Task.controller` (for the reach tasks a PI
controller on the goal handle); a policy is anything with SB3's ``predict(obs, deterministic=True)``
(the command line passes the policy shipped for the id, :func:`redsim.trainers.agents.shipped_policy`).
The speed reported is that of the env steps alone (the median step: the first, which warms the solver, is
reported apart), without the policy and the frames.

The frames are drawn after the episode, from the states kept on the way, with the env's fixed camera turned about
the vertical where it would see the overlay markers' motion (a reach env's goal handle) mostly end-on
(:func:`demo_camera`): Chain-v0's target at seed 0 lies along its camera's line of sight from the chain's rest end,
so the first and last frames looked alike.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

SEEN_FRACTION = 0.5
""":func:`demo_camera` turns the camera where it sees less than this fraction of the markers' motion on screen (the
length of its projection, against that of the best side view)."""
TURN_STEP_DEG = 15.0
"""The turns about the vertical [deg] that :func:`demo_camera` tries: multiples of this."""


def demo_name(env_id: str, scripted: bool = False, seed: int = 0) -> str:
    """The file stem of an id's demo: the task in lower case, with its version past v0 (``RedSim/Chain-v0`` ->
    ``chain``, ``RedSim/BistableBar-v1`` -> ``bistablebar_v1``), ``_scripted`` for the task's scripted controller
    and ``_seedS`` for a reset seed S other than 0, so demos of other versions, actors or seeds do not overwrite
    each other."""
    name, dash, version = env_id.split("/")[-1].rpartition("-")
    stem = version.lower() if not dash else name.lower() if version == "v0" else f"{name.lower()}_{version}"
    return stem + ("_scripted" if scripted else "") + (f"_seed{seed}" if seed else "")


def demo_camera(camera: dict[str, Any], motion: np.ndarray | None) -> dict[str, Any]:
    """``camera`` (the env's own, a user's keys over it) turned about the vertical to see ``motion`` side-on where
    it sees less than :data:`SEEN_FRACTION` of it: among turns by multiples of :data:`TURN_STEP_DEG` the one whose
    picture shows the motion longest (the smallest such turn). Unchanged for a 2D or no motion (None).

    Args:
        camera: The settings of :class:`redsim.raster.SceneView` (``azimuth``, ``elevation`` [deg], ...).
        motion: Displacements [P, 3] [m] of the overlay markers over the episode, or None.
    """
    from redsim.raster import DEFAULT_AZIMUTH, DEFAULT_ELEVATION, camera_rotation

    if motion is None or motion.shape[-1] != 3:
        return camera
    own, elevation = camera.get("azimuth", DEFAULT_AZIMUTH), camera.get("elevation", DEFAULT_ELEVATION)

    def seen(azimuth: float) -> float:  # the motion's length on screen [m]
        return float(np.linalg.norm((motion @ camera_rotation(azimuth, elevation).T)[:, :2]))

    turns = sorted(np.arange(-180.0, 180.0, TURN_STEP_DEG), key=abs)  # 0, -15, 15, -30, ...: the smallest first
    best = max((own + turn for turn in turns), key=seen)
    return camera if seen(own) >= SEEN_FRACTION * seen(best) else {**camera, "azimuth": float(best)}


def run_demo(
    env_id: str,
    out: str | Path,
    *,
    seed: int = 0,
    steps: int | None = None,
    frame_every: int = 2,
    width: int = 320,
    height: int = 320,
    policy: Any = None,
    **env_kwargs: Any,
) -> dict[str, Any]:
    """Run one episode of ``env_id`` (``policy``, or the task's scripted controller), writing ``OUT/<name>.gif`` and
    ``OUT/<name>.png`` (:func:`demo_name`: ``chain.gif`` for a policy at seed 0, ``chain_scripted.gif`` for the
    controller).

    Args:
        env_id: A registered id.
        out: Output folder (created).
        seed: Reset seed.
        steps: Episode length (default: the id's ``max_episode_steps``).
        frame_every: Keep every k-th frame in the GIF.
        width: Frame width [px].
        height: Frame height [px].
        policy: What acts: an object with ``predict(obs, deterministic=True) -> (action, state)``,
            or None for the task's scripted controller.
        **env_kwargs: Passed to ``gym.make``.

    Returns:
        ``return``, ``steps``, ``env_steps_per_s`` and ``sim_s_per_wall_s`` (of the median step), ``first_step_s``,
        ``final_distance`` [m], ``success_fraction`` (of steps with ``info["is_success"]``), ``gif``, ``png``,
        ``camera`` (the settings the frames were drawn with: :func:`demo_camera`).

    Raises:
        ValueError: bad counts.
    """
    if frame_every < 1:
        raise ValueError(f"frame_every must be >= 1, got {frame_every}")
    from PIL import Image

    from redsim.render import MAX_GIF_FPS, gif_frame_ms
    from redsim.subspace import write_atomically

    if steps is not None and int(steps) < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    if steps is not None:  # an episode of ``steps`` (longer than the id's own too: its time limit is replaced)
        env_kwargs = {**env_kwargs, "max_episode_steps": int(steps)}
    env = gym.make(env_id, render_mode="rgb_array", width=width, height=height, **env_kwargs)
    core = env.unwrapped
    sim = core.sim
    steps = int(env.spec.max_episode_steps or 200) if steps is None else int(steps)
    obs, _ = env.reset(seed=seed)
    kept = [sim.snapshot()]  # the states to draw, once the episode has shown the camera where to look
    total, stepped, success, step_times = 0.0, 0, 0, []
    info: dict[str, Any] = {}
    for i in range(steps):
        if policy is None:
            action = core.task.controller(core.sim)[0]
        else:
            action = policy.predict(obs, deterministic=True)[0]
        start = time.perf_counter()
        obs, reward, terminated, truncated, info = env.step(action)
        step_times.append(time.perf_counter() - start)
        total += reward
        stepped += 1
        success += int(bool(info.get("is_success", False)))
        if (i + 1) % frame_every == 0:
            kept.append(sim.snapshot())
        if terminated or truncated:
            break
    if stepped % frame_every:  # the last state, where the episode ended between kept frames
        kept.append(sim.snapshot())
    given = dict(env_kwargs.get("camera") or {})
    camera = {**core.camera, **given}
    if "azimuth" not in given:  # a user's own azimuth is kept
        camera = demo_camera(camera, _marker_motion(sim, kept[0], kept[-1]))
    frames = _draw(sim, kept, width, height, camera)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stem = demo_name(env_id, scripted=policy is None, seed=seed)
    gif, png = (out / f"{stem}{suffix}" for suffix in (".gif", ".png"))
    images = [Image.fromarray(f) for f in frames]
    duration = gif_frame_ms(min(MAX_GIF_FPS, 1.0 / (core.dt * frame_every)))
    # each to a temporary, then renamed: a Ctrl-C while writing leaves the previous demo's files whole
    write_atomically(
        gif,
        lambda tmp: images[0].save(
            tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0
        ),
    )
    picture = Image.fromarray(np.concatenate([frames[0], frames[-1]], axis=1))
    write_atomically(png, lambda tmp: picture.save(tmp, format="PNG"))
    env.close()
    return {
        "id": env_id,
        "return": total,
        "steps": stepped,
        "env_steps_per_s": 1.0 / statistics.median(step_times),
        "sim_s_per_wall_s": core.dt / statistics.median(step_times),
        "first_step_s": step_times[0],
        "final_distance": info.get("distance"),
        "success_fraction": success / stepped,
        "gif": str(gif),
        "png": str(png),
        "camera": camera,
    }


def _marker_motion(sim: Any, first: Any, last: Any) -> np.ndarray | None:
    """Displacements [P, D] [m] of the overlay markers from the state ``first`` to ``last``
    (:meth:`LatentSim.snapshot`), or None without markers (or not the same ones in both). The simulation is left at
    ``last``."""
    sim.restore(first)
    start = sim.marker_points((0,))
    sim.restore(last)
    end = sim.marker_points((0,))
    return None if start is None or end is None or start.shape != end.shape else end - start


def _draw(sim: Any, kept: list[Any], width: int, height: int, camera: dict[str, Any]) -> list[np.ndarray]:
    """The pictures [H, W, 3] of the kept states (:meth:`LatentSim.snapshot`), drawn as the env's ``render`` draws
    them with ``camera``. The simulation is left at the last state."""
    frames, view = [], None
    for saved in kept:
        sim.restore(saved)
        view = sim.framed_view(view, width, height, camera, (0,))
        frames.append(sim.draw(view, 0))
    return frames


__all__ = ["SEEN_FRACTION", "TURN_STEP_DEG", "demo_camera", "demo_name", "run_demo"]
