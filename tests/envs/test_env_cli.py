"""`redsim demo` and `redsim bench envs` on the mini chain, with tiny budgets."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from redsim.cli import main
from redsim.envs.bench import median_rounds
from redsim.envs.sharded import ShardedVectorEnv


def test_demo_prints_return_and_speed_and_writes_gif_and_picture(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["demo", "RedSim/MiniChain-v0", "--steps", "6", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "return" in text and "env steps/s" in text
    assert "(shipped policy MiniChain-v0.zip, seed 0)" in text  # a policy is shipped for the mini chain
    assert (tmp_path / "minichain.gif").stat().st_size > 0 and (tmp_path / "minichain.png").stat().st_size > 0
    policy_gif = (tmp_path / "minichain.gif").read_bytes()
    assert main(["demo", "RedSim/MiniChain-v0", "--steps", "6", "--out", str(tmp_path), "--scripted"]) == 0
    text = capsys.readouterr().out
    assert "(scripted controller, seed 0)" in text and "minichain_scripted.gif" in text
    assert (tmp_path / "minichain.gif").read_bytes() == policy_gif  # the policy's demo is not overwritten
    assert main(["demo", "RedSim/MiniChain-v0", "--steps", "6", "--out", str(tmp_path), "--seed", "3"]) == 0
    capsys.readouterr()
    names = sorted(p.name for p in tmp_path.glob("*.gif"))
    assert names == ["minichain.gif", "minichain_scripted.gif", "minichain_seed3.gif"]
    assert main(["demo", "RedSim/MiniChain-v0", "--steps", "2", "--out", str(tmp_path), "--seed", "3", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["seed"] == 3  # the text said it, the JSON did not
    # the speed is the median step's: the first, which warms the solver, is reported apart (it was in a mean)
    assert doc["first_step_s"] > 0 and doc["sim_s_per_wall_s"] == pytest.approx(0.02 * doc["env_steps_per_s"])


def test_bench_envs_rounds_report_each_rate_s_median_over_the_rounds(capsys: pytest.CaptureFixture[str]) -> None:
    """``--rounds 3``: every id (and anchor) timed three times in turn; each rate is the median of its three values,
    listed beside it; the solver's work and the full-space step come from the first round. The JSON document's
    sizes, env args, solver work and render rate are checked on the same run."""
    args = ["bench", "envs", "--envs", "RedSim/MiniChain-v0", "--batches", "2", "--steps", "2", "--budget", "0.1"]
    tight = ["--env-arg", 'stepper_options={"tol": 1e-5}']
    assert main([*args, *tight, "--anchor-steps", "20", "--rounds", "3", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["rounds"] == 3 and doc["env_args"] == {"stepper_options": {"tol": 1e-5}}
    (row,) = doc["results"]
    assert row["n"] == 24 and row["d"] == 4 and row["action_size"] == 3 and row["observation_size"] == 14
    work = row["vector"]["2"]  # each step evaluates at least the start of every copy (z_t's: the last step's carry)
    assert work["iterations_per_step"] > 0 and work["calls_per_step"] >= 1 and work["rows_per_copy_step"] >= 1
    # a vector step calls the objective at least once per iteration of its slowest copy, after the start call
    assert work["iterations_per_step"] <= work["slowest_iterations_per_step"] <= work["calls_per_step"] - 1
    assert "machine" in doc and "available" in doc["mujoco"]
    assert row["render"]["size"] == [480, 480] and row["render"]["frames_per_s"] > 0
    for part in (row["single"], row["vector"]["2"], row["render"]):
        for key in ("env_steps_per_s", "sim_s_per_wall_s", "frames_per_s"):
            if key in part:
                values = part[f"rounds_{key}"]
                assert len(values) == 3 and all(v > 0 for v in values) and part[key] == sorted(values)[1]
    assert row["full_space"]["step_s"] > 0 and "rounds_env_steps_per_s" not in row["full_space"]
    assert row["vector"]["2"]["calls_per_step"] >= 1
    if doc["mujoco"]["available"]:
        chain = doc["mujoco"]["chain"]
        assert len(chain["rounds_steps_per_s"]) == 3 and chain["steps_per_s"] == sorted(chain["rounds_steps_per_s"])[1]
    assert main([*args, "--anchor-steps", "20", "--rounds", "2", "--no-full-space"]) == 0
    text = capsys.readouterr().out
    assert "the lowest and highest of the 2 rounds" in text
    spread = next(line for line in text.splitlines()[::-1] if line.startswith("RedSim/MiniChain-v0"))
    for cell in spread.split()[1:]:  # the single env and N=2: "low-high", low <= high
        low, high = (float(v) for v in cell.split("-"))
        assert 0 < low <= high
    assert main([*args, "--rounds", "0"]) == 2
    assert "--rounds must be >= 1" in capsys.readouterr().err


def test_median_rounds_keeps_what_the_first_round_alone_measured() -> None:
    rounds = [
        {"id": "x", "single": {"env_steps_per_s": v, "repeats": 2}, "full_space": full}
        for v, full in ((3.0, {"step_s": 1.0}), (1.0, None), (2.0, None))
    ]
    merged = median_rounds(rounds)
    assert merged["single"] == {"env_steps_per_s": 2.0, "rounds_env_steps_per_s": [3.0, 1.0, 2.0], "repeats": 2}
    assert merged["full_space"] == {"step_s": 1.0} and merged["id"] == "x"
    assert median_rounds(rounds[:1]) is rounds[0]
    with pytest.raises(ValueError, match="at least one round"):
        median_rounds([])


def test_bench_envs_times_the_mujoco_anchors_in_the_same_run(capfd: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("mujoco")
    args = ["bench", "envs", "--envs", "RedSim/MiniChain-v0", "--batches", "2", "--steps", "2", "--anchor-steps", "20"]
    assert main([*args, "--no-full-space", "--budget", "2"]) == 0
    text, err = capfd.readouterr()
    assert "RedSim/MiniChain-v0" in text and "solver work per vector step" in text
    assert "MuJoCo chain (24 capsules, nv 72" in text and "MuJoCo HalfCheetah-v5 (single env, dt 0.05 s)" in text
    assert "MuJoCo flex cloth (2070 vertices, 46 pinned, nv 6072, discrete dt" in text
    assert "cloth envs' best batch" not in text  # no cloth env in this run
    assert "settotalmass" not in err  # Gymnasium's half_cheetah.xml warning is filtered at gym.make
    assert main([*args, "--no-full-space", "--budget", "2", "--json"]) == 0
    doc = json.loads(capfd.readouterr().out)
    anchors = doc["mujoco"]
    assert anchors["chain"]["sim_s_per_wall_s"] > 0 and anchors["chain"]["nv"] == 72
    assert anchors["HalfCheetah-v5"]["env_steps_per_s"] > 0 and anchors["HalfCheetah-v5"]["dt"] == 0.05
    cloth = anchors["cloth"]
    assert cloth["vertices"] == 2070 and cloth["pinned"] == 46 and cloth["nv"] == 6072
    assert cloth["sim_s_per_wall_s"] > 0 and 1 <= cloth["steps"] <= 20 and cloth["finite"]
    assert doc["cloth_ratios"] == {} and doc["results"][0]["scene"] == "mini_chain"


def test_bench_envs_without_mujoco_skips_the_anchors_with_the_reason(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from redsim.envs import bench

    real = bench.importlib.util.find_spec
    monkeypatch.setattr(bench.importlib.util, "find_spec", lambda name: None if name == "mujoco" else real(name))
    args = ["bench", "envs", "--envs", "RedSim/MiniChain-v0", "--batches", "2", "--steps", "2", "--no-full-space"]
    assert main(args) == 0
    assert "MuJoCo anchors skipped: mujoco is not installed (pip install 'redsim[bench]')" in capsys.readouterr().out
    assert main([*args, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["mujoco"] == {"available": False, "reason": bench.MUJOCO_MISSING}


def test_bench_envs_says_an_envs_warning_once_though_it_builds_the_env_again(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Each env bench envs builds (to check --env-arg, then the single env and each batch's vector env) warned of the
    float32 step at dt 1 ms, and Python's once-per-location memory, reset by the catch_warnings around each build
    (old_versions_quiet) and by subprocess, said it again: 4 and 3 times here. Now once each per run."""
    from redsim.envs import bench

    real = bench.importlib.util.find_spec  # no MuJoCo anchors: not what this test is about
    monkeypatch.setattr(bench.importlib.util, "find_spec", lambda name: None if name == "mujoco" else real(name))
    args = ["bench", "envs", "--envs", "RedSim/MiniChain-v0", "--batches", "2,3", "--steps", "1", "--no-full-space"]
    assert main([*args, "--budget", "0.1", "--env-arg", "dt=0.001", "--json"]) == 0
    err = capsys.readouterr().err
    assert err.count("redsim: warning: torch.float32 at dt=0.001 s resolves accelerations only to") == 1, err
    assert err.count("redsim: warning: torch.float32 at dt=0.001 s cannot feel any value of an action") == 1, err


def test_bench_mujoco_cloth_without_mujoco_is_one_error_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "mujoco" else real(name, *a))
    assert main(["bench", "mujoco-cloth", "--no-sweep", "--no-sag", "--no-swing"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == "redsim: error: mujoco is not installed (pip install 'redsim[bench]')\n"


@pytest.mark.parametrize("argv", [["demo", "RedSim/Nope-v0"], ["bench", "envs", "--envs", "Nope"]])
def test_unknown_env_id_is_a_usage_error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(argv) == 2
    assert "unknown env" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["MiniChain-v0", "minichain-v0", "redsim:MiniChain-v0"])
def test_an_id_without_its_namespace_is_refused_naming_the_id_meant(
    name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """A bare name (helper-261 typed `--envs MiniChain-v0`) was refused with the list alone; the error now names the
    id it matches, case aside."""
    assert main(["bench", "envs", "--envs", name]) == 2
    assert "did you mean RedSim/MiniChain-v0? ids start with RedSim/" in capsys.readouterr().err


def test_commands_take_an_id_with_the_redsim_prefix_as_gym_make_does(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``redsim:RedSim/...`` (README: gym.make's module prefix) names the bare id everywhere: its shipped policy, its
    file names; another module's prefix stays an unknown env in every command that takes an id."""
    assert main(["demo", "redsim:RedSim/MiniChain-v0", "--steps", "2", "--out", str(tmp_path)]) == 0
    assert "RedSim/MiniChain-v0 (shipped policy MiniChain-v0.zip, seed 0)" in capsys.readouterr().out
    assert (tmp_path / "minichain.gif").is_file()
    assert main(["eval-agent", "shipped", "redsim:RedSim/MiniChain-v0", "--episodes", "1"]) == 0
    assert capsys.readouterr().out.startswith("RedSim/MiniChain-v0, shipped")
    from redsim.cli.common import parse_env_id

    assert parse_env_id("redsim:RedSim/Klann-v0") == parse_env_id("redsim.envs:RedSim/Klann-v0") == "RedSim/Klann-v0"
    for argv in (
        ["demo", "gymnasium:RedSim/MiniChain-v0"],
        ["train-agent", "redsim:RedSim/Nope-v0"],
        ["eval-agent", "shipped", "redsimx:RedSim/MiniChain-v0"],
        ["bench", "envs", "--envs", "RedSim/MiniChain-v0,other:RedSim/Chain-v0"],
        ["bench", "env-ab", "RedSim:MiniChain-v0", "--setting", "a", "--setting", "b"],
        ["bench", "stability", "--envs", "redsim:Nope"],
    ):
        assert main(argv) == 2, argv
        assert "unknown env" in capsys.readouterr().err, argv


@pytest.mark.parametrize(
    ("env_arg", "expected"),
    [
        ("no_such_option=1", "cannot make RedSim/MiniChain-v0 with --env-arg"),
        ('device="cpu"', "--device"),
        ("threads=2", "give the threads with --threads"),
    ],
)
def test_bench_envs_bad_env_arg_is_a_usage_error(
    env_arg: str, expected: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", "envs", "--envs", "RedSim/MiniChain-v0", "--env-arg", env_arg]) == 2
    assert expected in capsys.readouterr().err
    twice = ["--env-arg", "max_force=1.0", "--env-arg", "max_force=2.0"]
    assert main(["bench", "envs", "--envs", "RedSim/MiniChain-v0", *twice]) == 2
    assert "--env-arg max_force given twice" in capsys.readouterr().err


def test_bench_envs_sharded(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    args = ["bench", "envs", "--envs", "RedSim/MiniChain-v0", "--batches", "2", "--steps", "2", "--no-full-space"]
    assert main([*args, "--anchor-steps", "20", "--shards", "2", "--shard-timeout", "120", "--json"]) == 0
    work = json.loads(capsys.readouterr().out)["results"][0]["vector"]["2"]
    assert work["shards"] == 2 and work["env_steps_per_s"] > 0 and work["iterations_per_step"] > 0
    assert work["calls_per_step"] is None and work["rows_per_copy_step"] is None  # the workers keep their counts
    assert main([*args, "--shards", "3"]) == 2
    assert "--shards must be in [1, the smallest batch 2]" in capsys.readouterr().err
    assert main([*args, "--shard-timeout", "5"]) == 2  # no worker to wait for
    assert "--shard-timeout bounds the wait for a sharded env's workers" in capsys.readouterr().err
    assert main([*args, "--shards", "2", "--shard-timeout", "0"]) == 2
    assert "must be a number of seconds > 0" in capsys.readouterr().err
    # a worker past --shard-timeout fails its batch's part; the run goes on and fails at its end. The worker hangs
    # for sure (stopped before the reset): a live worker under a 1 us timeout raced the caller, which, descheduled on a
    # busy machine for the few ms of a reset between sending it and polling, found it answered and timed out a step
    reset = ShardedVectorEnv.reset

    def reset_with_a_hung_worker(self: ShardedVectorEnv, **kwargs: Any) -> Any:
        os.kill(self._processes[1].pid, signal.SIGSTOP)  # it answers nothing until the timeout kills it
        return reset(self, **kwargs)

    monkeypatch.setattr(ShardedVectorEnv, "reset", reset_with_a_hung_worker)
    assert main([*args, "--anchor-steps", "20", "--shards", "2", "--shard-timeout", "1", "--json"]) == 1
    failed = json.loads(capsys.readouterr().out)["results"][0]["vector"]["2"]["failed"]
    assert failed.startswith("ShardTimeoutError: the sharded env's reset timed out after 1 s: shard") and (
        "shard 1 (copy 1, worker pid" in failed  # shard 0 too where it had not answered within the second
    )


def test_an_out_of_date_id_is_one_warning_line_in_demo_and_eval_agent(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """Gymnasium's own warning (a source line, colour codes and its call) is replaced by one line naming the latest
    version; the latest version gets none. A demo of an id without a shipped policy says that its scripted controller
    runs it (unless --scripted asked for it)."""
    assert main(["demo", "RedSim/BistableBar-v0", "--out", str(tmp_path), "--steps", "2", "--scripted"]) == 0
    err = capfd.readouterr().err
    line = "redsim: warning: RedSim/BistableBar-v0 is out of date: RedSim/BistableBar-v1 is its latest version"
    assert line in err and "DeprecationWarning" not in err and "\x1b[" not in err and err.count("out of date") == 1
    assert "no policy is shipped for RedSim/BistableBar-v0: the task's scripted controller runs it" not in err  # asked
    assert main(["demo", "RedSim/BistableBar-v0", "--out", str(tmp_path), "--steps", "2"]) == 0
    assert (
        "redsim: warning: no policy is shipped for RedSim/BistableBar-v0: the task's scripted" in capfd.readouterr().err
    )
    assert main(["eval-agent", "shipped", "RedSim/ClothBall-v0", "--episodes", "1", "--episode-steps", "2"]) == 0
    assert capfd.readouterr().err.count("out of date") == 1
    assert main(["demo", "RedSim/BistableBar-v1", "--out", str(tmp_path), "--steps", "2", "--scripted"]) == 0
    assert "out of date" not in capfd.readouterr().err


def test_demo_runs_the_steps_asked_for_past_the_ids_time_limit(tmp_path: Path) -> None:
    import gymnasium as gym

    from redsim.envs.demo import run_demo

    limit = gym.spec("RedSim/MiniChain-v0").max_episode_steps
    result = run_demo("RedSim/MiniChain-v0", tmp_path, steps=limit + 3, frame_every=10_000, width=64, height=64)
    assert result["steps"] == limit + 3
    small = {"frame_every": 10_000, "width": 64, "height": 64}
    short = run_demo("RedSim/MiniChain-v0", tmp_path, steps=4, max_episode_steps=2, **small)
    assert short["steps"] == 4  # steps sets the episode, over a max_episode_steps given with it


def test_run_demo_takes_an_id_of_a_users_own_registered_as_the_readme_says(tmp_path: Path) -> None:
    """README ("Your own task"): an id registered on redsim.envs:make (a user's scene and map) gets its demo from
    run_demo, which the `redsim demo` command, on the shipped ids only, cannot give."""
    import gymnasium as gym

    from redsim.envs.demo import run_demo

    gym.register("MyChainDemo-v0", entry_point="redsim.envs:make", kwargs={"scene": "mini_chain"}, max_episode_steps=9)
    try:
        result = run_demo("MyChainDemo-v0", tmp_path, steps=3, frame_every=10_000, width=64, height=64)
        assert main(["demo", "MyChainDemo-v0", "--out", str(tmp_path)]) == 2  # the command: shipped ids only
    finally:
        del gym.registry["MyChainDemo-v0"]
    assert result["steps"] == 3 and result["gif"] == str(tmp_path / "mychaindemo_scripted.gif")
    assert (tmp_path / "mychaindemo_scripted.gif").is_file() and (tmp_path / "mychaindemo_scripted.png").is_file()


def test_demo_draws_the_last_state_where_the_episode_ends_between_kept_frames(tmp_path: Path) -> None:
    """The picture's right half and the GIF's last frame were the last kept frame (every frame_every steps), not the
    state the episode ended in: with 5 steps and frames every 2, step 4's."""
    import gymnasium as gym
    from PIL import Image

    from redsim.envs.demo import demo_name, run_demo

    run_demo("RedSim/MiniChain-v0", tmp_path, steps=5, frame_every=2, width=64, height=64)
    env = gym.make("RedSim/MiniChain-v0", render_mode="rgb_array", width=64, height=64)
    env.reset(seed=0)
    for _ in range(5):
        env.step(env.unwrapped.task.controller(env.unwrapped.sim)[0])
    stem = tmp_path / demo_name("RedSim/MiniChain-v0", scripted=True, seed=0)
    with Image.open(stem.with_suffix(".gif")) as gif:
        assert gif.n_frames == 4  # the reset, steps 2 and 4, and step 5
    picture = np.asarray(Image.open(stem.with_suffix(".png")).convert("RGB"))
    np.testing.assert_array_equal(picture[:, 64:], env.render())


def test_the_chain_demo_at_the_readme_seed_sees_the_reach_side_on(tmp_path: Path) -> None:
    """At seed 0 (the README's demo) Chain-v0's target lies along its camera's line of sight from the chain's rest
    end, so chain.png's two frames looked alike: the demo turns the camera to see the goal handle's motion side-on,
    and keeps an azimuth a user gives."""
    import gymnasium as gym

    from redsim.envs.demo import run_demo
    from redsim.raster import camera_rotation

    env = gym.make("RedSim/Chain-v0")
    env.reset(seed=0)
    handle, target = env.unwrapped.sim.marker_points((0,))
    reach = target - handle  # where the goal handle goes

    def seen(camera: dict[str, Any]) -> float:  # the fraction of the reach's length on screen
        return float(np.linalg.norm((camera_rotation(camera["azimuth"], camera["elevation"]) @ reach)[:2]))

    own = env.unwrapped.camera
    assert seen(own) < 0.3 * np.linalg.norm(reach)
    small = {"steps": 30, "frame_every": 30, "width": 48, "height": 48}
    turned = run_demo("RedSim/Chain-v0", tmp_path, **small)["camera"]
    assert seen(turned) > 0.9 * np.linalg.norm(reach) and turned["elevation"] == own["elevation"]
    assert run_demo("RedSim/Chain-v0", tmp_path, camera={"azimuth": 30.0}, **small)["camera"]["azimuth"] == 30.0


def test_the_demo_keeps_the_camera_where_the_markers_at_the_ends_differ() -> None:
    """Markers that are not the same ones at the first and last state give no motion (it was a broadcast difference
    or a shape-mismatch error)."""
    from redsim.envs.demo import _marker_motion

    class Sim:  # restore() sets the marker points marker_points() gives
        def restore(self, points: np.ndarray | None) -> None:
            self.points = points

        def marker_points(self, rows: tuple[int, ...]) -> np.ndarray | None:
            return self.points

    two, one = np.zeros((2, 3)), np.ones((1, 3))
    assert _marker_motion(Sim(), two, one) is None and _marker_motion(Sim(), None, one) is None
    np.testing.assert_array_equal(_marker_motion(Sim(), two, two + 1.0), np.ones((2, 3)))


def test_demo_files_of_two_versions_do_not_overwrite_each_other() -> None:
    from redsim.envs.demo import demo_name

    assert demo_name("RedSim/Chain-v0") == "chain"
    assert demo_name("RedSim/BistableBar-v1") == "bistablebar_v1" != demo_name("RedSim/BistableBar-v0")
    assert demo_name("MyEnv") == "myenv"
    assert demo_name("RedSim/Chain-v0", scripted=True, seed=2) == "chain_scripted_seed2"


def test_bench_envs_steps_through_a_step_where_every_copy_restarts() -> None:
    """That step's info has no keys (as SyncVectorEnv's); the bench counts the solver work of the others."""
    from redsim.envs.bench import bench_env

    row = bench_env(
        "RedSim/MiniChain-v0", batches=(2,), steps=6, warmup=1, budget=100.0, full_space=False, max_episode_steps=2
    )
    assert row["vector"][2]["env_steps_per_s"] > 0


def test_bench_envs_table_marks_an_unconverged_full_space_step() -> None:
    """The text table stars a full-space rate whose timed steps hit Newton's cap (only --json said so before)."""
    from redsim.cli.envs import _row_line

    row = {"id": "RedSim/X-v0", "n": 1, "d": 1, "action_size": 1, "observation_size": 1, "render": {"frames_per_s": 1}}
    solved = {"converged_fraction": 1.0, "out_of_range": 0, "diverged": 0}
    row |= {"single": {"env_steps_per_s": 1.0, "sim_s_per_wall_s": 0.02, **solved}, "vector": {}}
    converged = _row_line({**row, "full_space": {"sim_s_per_wall_s": 0.0322, "converged": True}}, [])
    capped = _row_line({**row, "full_space": {"sim_s_per_wall_s": 0.0322, "converged": False}}, [])
    assert "0.0322*" in capped and "*" not in converged and len(capped) == len(converged)


def test_bench_envs_reports_timed_steps_whose_solves_failed(capsys: pytest.CaptureFixture[str]) -> None:
    """One Newton iteration per stepper step leaves every solve unconverged, and such steps are ~3x faster: the
    table gave their rate as any other's without a word (only `bench env-ab` counted the flags). Each part now
    counts converged, diverged and out_of_range of its timed steps, and the text marks the id and names them."""
    from redsim.envs.bench import bench_env

    capped = {"stepper_options": {"max_iter": 1}}
    row = bench_env("RedSim/MiniChain-v0", batches=(2,), steps=3, warmup=1, budget=100.0, full_space=False, **capped)
    for part in (row["single"], row["vector"][2]):
        assert part["converged_fraction"] == 0.0 and part["diverged"] == 0 and part["out_of_range"] == 0
    fine = bench_env("RedSim/MiniChain-v0", batches=(2,), steps=3, warmup=1, budget=100.0, full_space=False)
    assert fine["single"]["converged_fraction"] == fine["vector"][2]["converged_fraction"] == 1.0
    args = ["bench", "envs", "--envs", "RedSim/MiniChain-v0", "--batches", "2", "--steps", "2", "--budget", "0.1"]
    args += ["--no-full-space", "--anchor-steps", "20", "--env-arg", 'stepper_options={"max_iter": 1}']
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "RedSim/MiniChain-v0!" in text and "! timed env steps with a solve that did not converge" in text
    assert "  RedSim/MiniChain-v0: single: 0.0% converged, 0 diverged, 0 out of range; N=2: 0.0% converged" in text


def test_bench_envs_parts_do_not_depend_on_which_others_run() -> None:
    """Each batch size's actions and the full-space step's draw come from their own streams: the solver work of
    N = 2 and of the full-space step are the same whether N = 3 runs before them or not."""
    from redsim.envs.bench import bench_env

    kwargs = {"steps": 4, "warmup": 1, "budget": 1000.0}
    alone = bench_env("RedSim/MiniChain-v0", batches=(2,), **kwargs)
    after = bench_env("RedSim/MiniChain-v0", batches=(3, 2), **kwargs)
    for key in ("iterations_per_step", "slowest_iterations_per_step", "calls_per_step", "rows_per_copy_step"):
        assert alone["vector"][2][key] == after["vector"][2][key]
    assert alone["full_space"]["iterations_per_step"] == after["full_space"]["iterations_per_step"]
    assert alone["full_space"]["repeats"] == after["full_space"]["repeats"] == 3


def test_bench_envs_row_prints_no_warnings_between_the_table_lines(
    recwarn: pytest.WarningsRecorder, caplog: pytest.LogCaptureFixture
) -> None:
    """An older version of an id (Gymnasium's "out of date") and a full-space step at Newton's cap (the table stars
    it) printed warnings in the middle of the table; both are the bench's business, not the reader's."""
    from redsim.envs.bench import bench_env

    caplog.set_level("WARNING")
    row = bench_env("RedSim/ConditionalBar-v0", batches=(2,), steps=2, warmup=1, budget=100.0)
    assert row["full_space"]["converged"] is False  # this scene's full-space steps do hit the cap
    assert not [str(w.message) for w in recwarn] and not caplog.records


def test_bench_envs_checks_env_args_on_an_older_version_quietly(capfd: pytest.CaptureFixture[str]) -> None:
    """--env-arg is checked by making every id with it: Gymnasium's "out of date" of a v0 id printed above the table."""
    args = ["bench", "envs", "--envs", "RedSim/BistableBar-v0", "--batches", "2", "--steps", "1", "--budget", "1"]
    assert main([*args, "--no-full-space", "--anchor-steps", "20", "--env-arg", 'dtype="float32"']) == 0
    text, err = capfd.readouterr()
    assert "RedSim/BistableBar-v0" in text and "out of date" not in err + text


def test_bench_envs_runs_on_past_a_part_that_raises(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """One part that raised (MiniChain-v0's vector env at N=3, Klann-v0's full-space step, the MuJoCo chain) ended the
    run with a traceback, the rows measured before it lost. Now its cell reads failed and a line under the table
    names it, the other ids and parts run and print, `--json` lists them under `failed`, and the command exits 1."""
    import importlib.util

    import gymnasium as gym

    from redsim.benches import mujoco_cloth
    from redsim.envs import bench

    real_make_vec, real_full, real_find_spec = gym.make_vec, bench._full_space_step, importlib.util.find_spec

    def make_vec(env_id: str, num_envs: int, **kwargs: object) -> object:
        if env_id == "RedSim/MiniChain-v0" and num_envs == 3:
            raise RuntimeError("no N=3 here")
        return real_make_vec(env_id, num_envs, **kwargs)

    def full_space_step(env: object, *args: object) -> dict:
        if env.sim.scene.name == "klann":
            raise ValueError("no full space here")
        return real_full(env, *args)

    def chain_anchor(steps: int) -> dict:
        raise RuntimeError("no chain here")

    monkeypatch.setattr(bench.gym, "make_vec", make_vec)
    monkeypatch.setattr(bench, "_full_space_step", full_space_step)
    monkeypatch.setattr(bench.importlib.util, "find_spec", lambda name: real_find_spec(name) or name == "mujoco")
    monkeypatch.setattr(bench, "_chain_anchor", chain_anchor)
    monkeypatch.setattr(bench, "_cheetah_anchor", lambda steps: {"reason": "not timed in this test"})
    monkeypatch.setattr(mujoco_cloth, "cloth_anchor", lambda steps, budget: {"reason": "not timed in this test"})
    args = ["bench", "envs", "--envs", "RedSim/MiniChain-v0,RedSim/Klann-v0", "--batches", "2,3", "--steps", "2"]
    args += ["--budget", "0.1", "--threads", "1"]
    assert main(args) == 1
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    mini = next(line for line in lines if line.startswith("RedSim/MiniChain-v0 "))
    klann = next(line for line in lines if line.startswith("RedSim/Klann-v0 "))
    assert mini.split()[7] == "failed" and float(mini.split()[6]) > 0 and float(mini.split()[10]) > 0  # N=3; N=2
    assert klann.split()[10] == "failed" and all(float(cell) > 0 for cell in klann.split()[5:10])  # the full space
    assert "  RedSim/MiniChain-v0 N=3: RuntimeError: no N=3 here" in lines
    assert "  RedSim/Klann-v0 full space: ValueError: no full space here" in lines
    assert "MuJoCo chain failed: RuntimeError: no chain here" in lines
    assert captured.err.endswith(
        "redsim: error: bench envs: 3 part(s) failed (RedSim/MiniChain-v0 N=3, RedSim/Klann-v0 full space, MuJoCo "
        "chain); the others ran; RedSim/MiniChain-v0 N=3 raised RuntimeError: no N=3 here; RedSim/Klann-v0 full "
        "space raised ValueError: no full space here; MuJoCo chain raised RuntimeError: no chain here\n"
    )
    assert main([*args, "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert doc["failed"] == [
        {"id": "RedSim/MiniChain-v0", "part": "N=3", "round": 1, "error": "RuntimeError: no N=3 here"},
        {"id": "RedSim/Klann-v0", "part": "full space", "round": 1, "error": "ValueError: no full space here"},
        {"id": "MuJoCo", "part": "chain", "round": 1, "error": "RuntimeError: no chain here"},
    ]
    mini_row, klann_row = doc["results"]
    assert mini_row["vector"]["3"] == {"failed": "RuntimeError: no N=3 here"}
    assert mini_row["vector"]["2"]["env_steps_per_s"] > 0 and mini_row["full_space"]["step_s"] > 0
    assert klann_row["full_space"] == {"failed": "ValueError: no full space here"}
    assert klann_row["vector"]["3"]["env_steps_per_s"] > 0 and doc["mujoco"]["chain"]["failed"]


def test_bench_envs_stops_on_ctrl_c(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """A part's KeyboardInterrupt is not a failed part: the run stops (exit 130) and times no further id."""
    from redsim.envs import bench

    def make_vec(*args: object, **kwargs: object) -> object:
        raise KeyboardInterrupt

    monkeypatch.setattr(bench.gym, "make_vec", make_vec)
    args = ["bench", "envs", "--envs", "RedSim/MiniChain-v0,RedSim/Klann-v0", "--batches", "2", "--steps", "1"]
    assert main([*args, "--budget", "0.1", "--no-full-space", "--threads", "1"]) == 130
    captured = capsys.readouterr()
    assert "RedSim/Klann-v0" not in captured.out and "interrupted" in captured.err


def test_bench_envs_a_failure_in_any_round_or_of_the_whole_id_is_what_the_table_shows() -> None:
    """A part that failed in one round of several is that failure, not the median of the rounds it ran in; an id
    that could not be made is one line."""
    from redsim.cli.envs import _row_line
    from redsim.envs.bench import failed_parts

    rounds = [{"id": "x", "single": {"env_steps_per_s": v}} for v in (1.0, 2.0)]
    rounds.append({"id": "x", "single": {"failed": "RuntimeError: third round"}})
    assert median_rounds(rounds)["single"] == {"failed": "RuntimeError: third round"}
    whole = {"id": "RedSim/X-v0", "failed": "OSError: no map"}
    assert median_rounds([rounds[0], whole]) == whole and failed_parts(whole) == {"env": "OSError: no map"}
    assert _row_line(whole, [2]) == f"{'RedSim/X-v0':<26} failed (the env itself, named below)"


def test_ctrl_c_while_the_demo_gif_is_written_keeps_the_previous_one_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The GIF was written in place: a Ctrl-C in PIL's save left a cut-short ``minichain_scripted.gif`` (over the
    previous demo's); now it goes to a temporary beside it, moved onto the name once whole."""
    from PIL import Image

    argv = ["demo", "RedSim/MiniChain-v0", "--steps", "2", "--scripted", "--out", str(tmp_path)]
    assert main(argv) == 0
    capsys.readouterr()
    gif = tmp_path / "minichain_scripted.gif"
    before = gif.read_bytes()

    def cut_short(self: Image.Image, fp: Any, *args: Any, **kwargs: Any) -> None:
        Path(fp).write_bytes(b"GIF89a")  # the header, then the user's Ctrl-C
        raise KeyboardInterrupt

    monkeypatch.setattr(Image.Image, "save", cut_short)
    assert main(argv) == 130
    assert gif.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [
        "minichain_scripted.gif",
        "minichain_scripted.png",
    ]


def test_bench_envs_sharded_workers_say_their_warnings_in_the_command_line_s_form(
    monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """A spawned shard worker printed its env's warnings in Python's raw form (``/.../envs/base.py:601: UserWarning:
    ...`` and the source line) beside the command's one-line ``redsim: warning: ...``; the workers now take the
    command line's display, with the record of what the command had said when they started: a line said before is
    not said again by each worker."""
    from redsim.envs import bench, sharded

    real = bench.importlib.util.find_spec  # no MuJoCo anchors: not what this test is about
    monkeypatch.setattr(bench.importlib.util, "find_spec", lambda name: None if name == "mujoco" else real(name))
    # spawn: the forkserver's workers write to the fd 2 it had when an earlier test started it, which capfd does not
    # see, and this test passed in a run of the file with the workers' display removed
    monkeypatch.setattr(sharded.mp, "get_all_start_methods", lambda: ["spawn"])
    args = ["bench", "envs", "--envs", "RedSim/MiniChain-v0", "--batches", "2", "--steps", "1", "--no-full-space"]
    assert main([*args, "--shards", "2", "--budget", "0.1", "--env-arg", "dt=0.001", "--json"]) == 0
    err = capfd.readouterr().err
    assert "UserWarning" not in err and "envs/base.py" not in err, err
    assert err.count("redsim: warning: torch.float32 at dt=0.001 s resolves accelerations only to") == 1, err


def test_a_solve_tally_of_steps_that_solved_nothing_reads_nan_not_a_crash() -> None:
    """Every timed step restarted every copy (NEXT_STEP autoreset): no solve to average, so NaN (JSON null), where
    ``statistics.fmean([])`` raised (helper-260's audit); the counts are 0. A step that solved is averaged as before."""
    from redsim.envs.bench import SolveTally

    tally = SolveTally()
    tally.add({"reward": np.zeros(4)})  # a step with no solve: no "iterations"
    summary = tally.summary()
    means = ("iterations_per_step", "slowest_iterations_per_step", "converged_fraction")
    assert all(np.isnan(summary[key]) for key in means)
    assert summary["out_of_range"] == summary["diverged"] == 0
    info = {"iterations": np.array([2, 4]), "converged": np.array([True, False])}
    tally.add({**info, "out_of_range": np.array([False, True]), "diverged": np.array([False, False])})
    assert tally.summary()["iterations_per_step"] == 3.0 and tally.summary()["converged_fraction"] == 0.5
