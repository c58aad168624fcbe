"""SB3 agents on the RedSim envs: train a few hundred steps, resume, evaluate; the CLI and its errors."""

from __future__ import annotations

import csv
import importlib.util
import json
import re
import tempfile
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import redsim
from redsim.trainers.agents import (
    ALGOS,
    HYPERPARAMS,
    Evaluation,
    evaluate,
    hyperparams,
    load_agent,
    model_record,
    normalizer_path,
    shipped_policies,
    shipped_policy,
    training_seed,
)

MINI = "RedSim/MiniChain-v0"
SHORT = {"max_episode_steps": 20}
"""Episodes of 20 steps keep the default suite fast."""
TINY = [
    "--episode-steps",
    "20",
    "--n-envs",
    "4",
    "--eval-every",
    "100",
    "--eval-episodes",
    "2",
    "--final-episodes",
    "2",
    "--no-progress",
]


def test_the_table_covers_every_id_and_algorithm() -> None:
    import redsim.envs

    assert set(redsim.envs.ids()) <= set(HYPERPARAMS)
    for env_id in redsim.envs.ids():
        for algo in ALGOS:
            settings = hyperparams(env_id, algo)
            assert settings["n_envs"] >= 1
    hyperparams(MINI, "sac")["policy_kwargs"]["net_arch"].append(1)  # a copy: the table is not changed
    assert HYPERPARAMS["default"]["sac"]["policy_kwargs"]["net_arch"] == [64, 64]
    with pytest.raises(ValueError, match="unknown algorithm 'a2c'"):
        hyperparams(MINI, "a2c")


def _evaluation(returns: list[float]) -> Evaluation:
    n = len(returns)
    zeros = np.zeros(n)
    return Evaluation("agent", np.array(returns), zeros.astype(bool), np.full(n, 10), 0, zeros, zeros)


@pytest.mark.filterwarnings("error")  # scipy's divide-by-zero and precision-loss warnings reached the user
def test_a_paired_test_of_one_episode_has_no_p_value_and_no_spread_gives_0_or_1() -> None:
    p_value, better = _evaluation([5.0]).above(_evaluation([1.0]))
    assert np.isnan(p_value) and better == 1
    assert _evaluation([2.0, 3.0]).above(_evaluation([1.0, 2.0])) == (0.0, 2)  # every episode 1 above
    assert _evaluation([1.0, 2.0]).above(_evaluation([2.0, 3.0])) == (1.0, 0)
    p_value, better = _evaluation([2.0, 3.5, 1.0]).above(_evaluation([1.0, 2.0, 1.5]))
    assert 0.0 < p_value < 1.0 and better == 2


@pytest.mark.filterwarnings("error")
def test_eval_agent_of_one_episode_prints_no_p_value(cli: Callable[..., tuple[int, str, str]]) -> None:
    code, stdout, err = cli("eval-agent", "shipped", MINI, "--episodes", "1", "--episode-steps", "5", "--baselines")
    assert code == 0, err
    assert stdout.count("paired one-sided t-test p = – (one episode), better in") == 2, stdout


def test_evaluation_is_seeded_and_the_scripted_controller_beats_random() -> None:
    first = evaluate(MINI, "random", episodes=3, seed=5, env_kwargs={"max_episode_steps": 40})
    again = evaluate(MINI, "random", episodes=3, seed=5, env_kwargs={"max_episode_steps": 40})
    np.testing.assert_array_equal(first.returns, again.returns)
    scripted = evaluate(MINI, "scripted", episodes=3, seed=5, env_kwargs={"max_episode_steps": 40})
    assert scripted.lengths.tolist() == [40, 40, 40]
    assert scripted.mean > first.mean + 20.0  # the PI controller reaches; random forces flail
    radius = gym.make(MINI).unwrapped.sim.task.success_radius
    np.testing.assert_array_equal(scripted.final_distance < radius, scripted.successes)  # [m], the last step's
    assert first.saturated_steps.shape == (3,) and np.all(first.saturated_steps < 0.05)  # uniform actions
    assert first.as_dict()["successes"] == first.successes.tolist()
    p_value, better = scripted.above(first)  # paired over the same three episodes
    assert p_value < 0.05 and better == 3
    assert first.above(scripted)[0] > 0.95 and first.above(first) == (1.0, 0)
    with pytest.raises(ValueError, match="the same episodes"):
        scripted.above(evaluate(MINI, "random", episodes=3, seed=6, env_kwargs={"max_episode_steps": 40}))
    with pytest.raises(ValueError, match="policy must be"):
        evaluate(MINI, "greedy", episodes=2)
    with pytest.raises(ValueError, match="unknown env"):
        evaluate("RedSim/Nope-v0", "random", episodes=2)


def test_train_resume_and_evaluate_through_the_cli(
    cli: Callable[..., tuple[int, str, str]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "run"
    (tmp_path / "tmp").mkdir()
    monkeypatch.delenv("SB3_LOGDIR", raising=False)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))  # where SB3 alone would make an SB3-* folder
    code, stdout, err = cli(
        "train-agent",
        MINI,
        "--algo",
        "sac",
        "--steps",
        "200",
        "--out",
        str(out),
        *TINY,
        "--env-arg",
        "max_force=3.0",
        "--json",
    )
    assert code == 0, err
    summary = json.loads(stdout)
    assert json.loads((out / "agent.json").read_text())["env_kwargs"] == {"max_force": 3.0, "max_episode_steps": 20}
    assert summary["steps"] == 200 and summary["final_evaluation"]["episodes"] == 2
    for name in ("model.zip", "best_model.zip", "curve.csv", "curve.png", "policy.gif", "agent.json"):
        assert (out / name).stat().st_size > 0, name
    with (out / "progress.csv").open() as handle:  # SB3's training log in the run, none in the temp folder
        rows = list(csv.DictReader(handle))
    assert rows and {"time/total_timesteps", "train/actor_loss", "eval/mean_reward"} <= set(rows[0])
    assert not list((tmp_path / "tmp").glob("SB3-*"))
    record = {"env_id": MINI, "algo": "sac", "normalized": True, "goal": None, "n_envs": 4}
    record["env_kwargs"] = {"max_force": 3.0, "max_episode_steps": 20}
    record["map"] = redsim.subspace.map_fingerprint(redsim.pretrained.load("mini_chain"))  # the shipped map's
    assert model_record(out / "model.zip") == record
    assert load_agent(out / "model.zip").model._n_updates > 0  # a 200-step run starts learning halfway, not never
    assert (out / "model.zip").stat().st_size < 1_000_000
    with np.load(out / "evaluations.npz") as first:
        first_steps = list(first["timesteps"])
        first_best = float(first["results"].mean(axis=1).max())
    best_bytes = (out / "best_model.zip").read_bytes()

    # the same --out again: refused, not mixed into the run; a resume in another env: refused
    again = ("train-agent", MINI, "--algo", "sac", "--steps", "300", "--out", str(out), *TINY)
    code, _, err = cli(*again, "--env-arg", "max_force=3.0")
    assert code == 2 and "holds a run" in err and "--overwrite" in err and (out / "best_model.zip").is_file()
    code, _, err = cli(*again, "--resume", "--no-video")
    assert code == 2 and "cannot resume with env_kwargs" in err and "'max_force': 3.0" in err
    code, _, err = cli(*again, "--resume", "--overwrite")
    assert code == 2 and "exclude each other" in err
    code, _, err = cli(*again, "--env-arg", "bogus=1", "--overwrite")  # refused before anything is removed
    assert code == 2 and (out / "best_model.zip").is_file() and (out / "agent.json").is_file()
    code, stdout, err = cli(*again, "--env-arg", "max_force=3.0", "--resume", "--no-video")
    assert code == 0, err
    assert "trained 100 env steps more (the run: 300 env steps in" in stdout  # this call's steps, then the run's
    assert load_agent(out / "model.zip", MINI).num_timesteps == 300
    with (out / "progress-from-200.csv").open() as handle:
        assert float(list(csv.DictReader(handle))[-1]["time/total_timesteps"]) > 200
    assert (out / "progress.csv").stat().st_size > 0 and not list((tmp_path / "tmp").glob("SB3-*"))
    with (out / "curve.csv").open() as handle:
        steps = [float(row["env_steps"]) for row in csv.DictReader(handle)]
    assert steps == sorted(steps) and steps[-1] == 300 and steps[0] <= 200  # the first run's rows are kept
    with np.load(out / "evaluations.npz") as both:  # SB3's evaluation log keeps the first run's too
        assert list(both["timesteps"][: len(first_steps)]) == first_steps and both["timesteps"][-1] == 300
        resumed_best = float(both["results"][len(first_steps) :].mean(axis=1).max())
    if resumed_best <= first_best:  # the best model is replaced only by a better mean return
        assert (out / "best_model.zip").read_bytes() == best_bytes
    code, stdout, err = cli(*again, "--env-arg", "max_force=3.0", "--resume", "--no-video")  # already at 300
    assert code == 0, err
    assert "is already at 300 env steps (--steps 300): nothing trained" in stdout and "trained 300" not in stdout
    assert load_agent(out / "model.zip", MINI).num_timesteps == 300

    # the run folder's model.zip, on the env it was trained on (its recorded env arguments, none given here)
    code, stdout, err = cli("eval-agent", str(out), MINI, "--episodes", "2", "--json", "--baselines")
    assert code == 0, err
    doc = json.loads(stdout)
    assert doc["normalization"] == str(out / "model_vecnormalize.pkl")
    assert doc["env_kwargs"] == {"max_force": 3.0, "max_episode_steps": 20}
    agent = doc["agent"]
    assert agent["episodes"] == 2 and np.isfinite(agent["mean_return"]) and 0.0 <= agent["success_rate"] <= 1.0
    assert agent["mean_length"] <= 20
    code, stdout, err = cli("eval-agent", str(out), MINI, "--episodes", "1", "--episode-steps", "5", "--json")
    assert code == 0 and json.loads(stdout)["env_kwargs"] == {"max_force": 3.0, "max_episode_steps": 5}, err
    assert json.loads(stdout)["agent"]["mean_length"] <= 5  # the arguments given here on top of the recorded ones
    for name in ("random", "scripted"):
        assert 0.0 <= doc[name]["agent_above_p"] <= 1.0 and 0 <= doc[name]["agent_better_episodes"] <= 2
    code, stdout, err = cli(
        "eval-agent", str(out / "model.zip"), MINI, "--episodes", "2", "--episode-steps", "20", "--baselines"
    )
    assert code == 0 and "agent above scripted: paired one-sided t-test p = " in stdout, err
    assert f"(observations normalized by {out / 'model_vecnormalize.pkl'}):" in stdout.splitlines()[0]
    assert stdout.startswith(f"{MINI} (max_force=3.0 max_episode_steps=20), ")
    (tmp_path / "no_run").mkdir()
    code, _, err = cli("eval-agent", str(tmp_path / "no_run"), MINI)
    assert code == 2 and "is a folder without a model.zip: give a model file (it holds none)" in err
    (tmp_path / "no_run" / "best_model.zip").write_bytes(b"")  # it suggested no_run/model.zip, which is not there
    code, _, err = cli("eval-agent", str(tmp_path / "no_run"), MINI)
    assert code == 2 and f"give a model file (e.g. {tmp_path / 'no_run' / 'best_model.zip'})" in err

    agent = load_agent(out / "model.zip", MINI)  # acts through the saved VecNormalize statistics
    obs = np.random.default_rng(0).normal(size=(3, 14)).astype(np.float32)
    np.testing.assert_array_equal(
        agent.predict(obs)[0], agent.model.predict(agent.normalizer.normalize_obs(obs), deterministic=True)[0]
    )
    assert not np.allclose(agent.normalizer.obs_rms.var, 1.0)  # statistics of the run, not the initial ones
    assert sorted(p.name for p in (out / "checkpoints").glob("*vecnormalize*")), "checkpoints keep their stats"
    (out / "model_vecnormalize.pkl").rename(out / "moved.pkl")
    code, _, err = cli("eval-agent", str(out / "model.zip"), MINI, "--episodes", "2")
    assert code == 2 and "no normalization statistics" in err
    (out / "moved.pkl").write_bytes(b"junk")
    (out / "moved.pkl").rename(out / "model_vecnormalize.pkl")
    code, _, err = cli("eval-agent", str(out / "model.zip"), MINI, "--episodes", "2")
    assert code == 2 and "is not a VecNormalize file" in err

    code, _, err = cli("eval-agent", str(out / "model.zip"), "RedSim/Chain-v0", "--episodes", "2")
    assert code == 2 and "was trained on RedSim/MiniChain-v0, not on RedSim/Chain-v0" in err
    code, _, err = cli("train-agent", "RedSim/Chain-v0", "--steps", "10", "--out", str(out), "--resume", *TINY)
    assert code == 2 and "cannot resume" in err
    other = [arg if arg != "4" else "2" for arg in TINY]  # --n-envs 2
    code, _, err = cli("train-agent", MINI, "--steps", "400", "--out", str(out), "--resume", *other)
    assert code == 2 and "cannot resume with 2 copies" in err and "--n-envs 4" in err


def test_normalizer_files_sit_beside_their_models() -> None:
    assert normalizer_path(Path("run/model.zip")) == Path("run/model_vecnormalize.pkl")
    assert normalizer_path(Path("run/best_model.zip")) == Path("run/best_model_vecnormalize.pkl")
    checkpoint = Path("run/checkpoints/rl_model_1200_steps.zip")
    assert normalizer_path(checkpoint) == Path("run/checkpoints/rl_model_vecnormalize_1200_steps.pkl")


def test_the_shipped_policies_load_and_the_mini_chain_one_beats_random() -> None:
    shipped = shipped_policies()
    assert MINI in shipped
    for env_id, path in shipped.items():
        assert path.stat().st_size + normalizer_path(path).stat().st_size < 500_000, "small enough to ship"
        agent = load_agent(path, env_id)
        assert agent.normalizer is not None and agent.num_timesteps > 0
        record = json.loads(path.with_suffix(".json").read_text())
        assert record["command"].startswith(f"redsim train-agent {env_id} ")
    agent = load_agent(shipped_policy(MINI), MINI)
    mine = evaluate(MINI, agent, episodes=1, seed=0)  # one whole 200-step episode each (~3 s)
    random = evaluate(MINI, "random", episodes=1, seed=0)
    assert mine.mean > random.mean + 300.0 and mine.success_rate == 1.0
    with pytest.raises(KeyError, match=r"no shipped policy for 'RedSim/Nope-v0'; shipped: .*MiniChain"):
        shipped_policy("RedSim/Nope-v0")


def test_evaluating_a_model_on_another_env_than_it_was_trained_on_is_warned_about() -> None:
    """Spaces of the same shapes let a model of one env act on another (a review evaluated a user's scene's model on
    MiniChain-v0 and got a return, silently): evaluate warns, naming both; a user's env of the same scene does not."""
    import dataclasses
    import warnings

    from redsim.envs import make

    agent = load_agent(shipped_policy(MINI), MINI)
    assert agent.env_id == MINI
    short = {"max_episode_steps": 2}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        evaluate(MINI, agent, episodes=1, env_kwargs=short)
        evaluate(make("mini_chain", task="reach", task_options={"goal_handle": "bottom"}, **short), agent, episodes=1)
    other = dataclasses.replace(agent, env_id="custom:my_rod")
    with pytest.warns(UserWarning, match=r"trained on custom:my_rod, and is evaluated on RedSim/MiniChain-v0"):
        evaluate(MINI, other, episodes=1, env_kwargs=short)
    user_env = make("mini_chain", task="reach", task_options={"goal_handle": "bottom"}, **short)
    with pytest.warns(UserWarning, match=r"trained on RedSim/Gone-v9, and is evaluated on custom:mini_chain"):
        evaluate(user_env, dataclasses.replace(agent, env_id="RedSim/Gone-v9"), episodes=1)  # an id not known here


def test_a_shipped_policy_scores_in_sb3_s_evaluate_policy_as_in_redsim_s_evaluation() -> None:
    """SB3's way (``SAC.load`` of the zip, ``VecNormalize.load`` of the statistics beside it, ``evaluate_policy`` on
    ``make_vec_env``) and ``load_agent``'s agent in ``evaluate_policy`` score redsim's returns of the same episodes.
    The agent's ``predict`` lacked SB3's ``state`` and ``episode_start``: ``evaluate_policy(agent, ...)`` was a
    TypeError."""
    from stable_baselines3 import SAC
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.vec_env import VecNormalize

    path = shipped_policy(MINI)
    exact = {**SHORT, "dtype": "float64"}  # in float64 a single env and a copy of the vector env agree
    ours = evaluate(MINI, load_agent(path, MINI), episodes=2, seed=0, env_kwargs=exact).returns

    def sb3_envs() -> Any:  # copy i's first episode has seed i, as redsim's episode i
        return make_vec_env(MINI, n_envs=2, seed=0, env_kwargs=exact)

    agent, _ = evaluate_policy(load_agent(path, MINI), sb3_envs(), n_eval_episodes=2, return_episode_rewards=True)
    normalized = VecNormalize.load(str(normalizer_path(path)), sb3_envs())
    normalized.training = False
    sb3, _ = evaluate_policy(SAC.load(path, device="cpu"), normalized, n_eval_episodes=2, return_episode_rewards=True)
    for returns in (agent, sb3):  # SB3's Monitor rounds a return to 6 decimals
        np.testing.assert_allclose(returns, ours, rtol=1e-5)


@pytest.mark.parametrize("shards", [1, 2])
def test_ppo_trains_a_few_hundred_steps(tmp_path: Path, shards: int) -> None:
    from redsim.trainers.agents import train_agent

    result = train_agent(
        MINI,
        tmp_path,
        algo="ppo",
        steps=256,
        n_envs=4,
        eval_every=128,
        eval_episodes=2,
        final_episodes=2,
        video=False,
        env_kwargs=SHORT,
        overrides={"n_steps": 64, "batch_size": 64, "n_epochs": 2},
        shards=shards,
    )
    assert result.steps == 256 and np.isfinite(result.evaluation.mean)
    assert model_record(result.model_path)["algo"] == "ppo"


def test_ppo_evaluations_score_the_policy_learnt_from_the_steps_they_are_labelled_with(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SB3's EvalCallback evaluates at a rollout's last step, before PPO's update: the point labelled 256 scored the
    untrained policy, and the trained one never reached the curve. Now each evaluation follows an update, the last
    at the end of training."""
    from stable_baselines3.common import callbacks

    from redsim.trainers.agents import train_agent

    seen = []
    evaluate_policy = callbacks.evaluate_policy

    def spy(model, *args, **kwargs):  # type: ignore[no-untyped-def]
        seen.append((int(model.num_timesteps), int(model._n_updates)))
        return evaluate_policy(model, *args, **kwargs)

    monkeypatch.setattr(callbacks, "evaluate_policy", spy)
    train_agent(
        MINI, tmp_path, algo="ppo", steps=256, n_envs=2, eval_every=128, eval_episodes=2, final_episodes=2,
        video=False, env_kwargs=SHORT, overrides={"n_steps": 64, "batch_size": 64, "n_epochs": 2},
    )  # fmt: skip
    assert seen == [(128, 2), (256, 4)]  # after one and two updates of 2 epochs (was (128, 0), (256, 2))
    with np.load(tmp_path / "evaluations.npz") as log:
        assert log["timesteps"].tolist() == [128, 256]


def test_every_evaluation_plays_the_same_episodes(tmp_path: Path) -> None:
    """The eval env is reseeded before each evaluation: a policy that does not change (learning never starts, no
    normalizer statistics following the training copies) scores
    the same at every point, so the points compare policies, and a resumed run's evaluations are the same as an
    uninterrupted one's (the env's stream went on, and restarted at a resume)."""
    from redsim.trainers.agents import train_agent

    options = {"algo": "sac", "eval_every": 20, "eval_episodes": 2, "final_episodes": 1, "video": False}
    options |= {"env_kwargs": {"max_episode_steps": 10}, "n_envs": 1}
    options |= {"overrides": {"learning_starts": 10**6, "normalize": None}}
    train_agent(MINI, tmp_path / "a", steps=80, **options)
    train_agent(MINI, tmp_path / "b", steps=40, **options)
    train_agent(MINI, tmp_path / "b", steps=80, resume=True, **options)
    with np.load(tmp_path / "a" / "evaluations.npz") as whole, np.load(tmp_path / "b" / "evaluations.npz") as resumed:
        assert whole["timesteps"].tolist() == resumed["timesteps"].tolist() == [20, 40, 60, 80]
        assert np.array_equal(whole["results"], resumed["results"])
        assert (whole["results"] == whole["results"][0]).all()


def test_bad_input_is_a_clear_cli_error(cli: Callable[..., tuple[int, str, str]], tmp_path: Path) -> None:
    code, _, err = cli("train-agent", "RedSim/Nope-v0", "--out", str(tmp_path))
    assert code == 2 and "unknown env 'RedSim/Nope-v0'; valid: RedSim/Chain-v0" in err
    code, _, err = cli("train-agent", MINI, "--steps", "0", "--out", str(tmp_path))
    assert code == 2 and "--steps must be >= 1" in err
    for flag in ("--final-episodes", "--eval-every"):  # refused before training, not after it
        code, _, err = cli("train-agent", MINI, flag, "0", "--out", str(tmp_path / "never"))
        assert code == 2 and f"{flag} must be >= 1, got 0" in err and not (tmp_path / "never").exists()
    from redsim.trainers.agents import train_agent

    with pytest.raises(ValueError, match="final_episodes must be an integer >= 1, got 0"):
        train_agent(MINI, tmp_path / "never", steps=8, final_episodes=0)
    with pytest.raises(ValueError, match=r"eval_every must be an integer >= 1 \(env steps\), got -5"):
        train_agent(MINI, tmp_path / "never", steps=8, eval_every=-5)
    code, _, err = cli("eval-agent", str(tmp_path / "missing.zip"), MINI)
    assert code == 2 and "no model file" in err
    junk = tmp_path / "junk.zip"
    junk.write_text("not a zip")
    code, _, err = cli("eval-agent", str(junk), MINI)
    assert code == 2 and "is not a stable-baselines3 model file" in err
    other_zip = tmp_path / "other.zip"  # a zip archive, but no SB3 "data" member: SB3 returns None for it
    with zipfile.ZipFile(other_zip, "w") as archive:
        archive.writestr("notes.txt", "hello")
    code, _, err = cli("eval-agent", str(other_zip), MINI, "--algo", "sac")
    assert code == 2 and "has no 'data' member" in err
    code, _, err = cli("eval-agent", str(_foreign_model(tmp_path)), MINI)
    assert code == 2 and "not one trained by redsim" in err
    code, _, err = cli("eval-agent", str(junk), MINI, "--episodes", "0")
    assert code == 2 and "--episodes must be >= 1" in err
    code, _, err = cli("train-agent", MINI, "--env-arg", "max_force", "--out", str(tmp_path))
    assert code == 2 and "malformed --env-arg 'max_force': expected KEY=VALUE" in err
    code, _, err = cli("train-agent", MINI, "--env-arg", "bogus=1", "--out", str(tmp_path))
    assert code == 2 and "cannot make RedSim/MiniChain-v0 with --env-arg bogus=1" in err and "'bogus'" in err
    code, _, err = cli(
        "train-agent", MINI, "--env-arg", "max_episode_steps=5", "--episode-steps", "5", "--out", str(tmp_path)
    )
    assert code == 2 and "give the episode length once" in err
    code, _, err = cli("train-agent", MINI, "--n-envs", "2", "--shards", "3", "--out", str(tmp_path))
    assert code == 2 and "shards must be an integer in [1, num_envs = 2], got 3" in err
    # gym.make's own keys passed its check, then the vector env (or the GIF's gym.make) crashed with a traceback
    code, _, err = cli("eval-agent", "shipped", MINI, "--episodes", "1", "--env-arg", "disable_env_checker=true")
    assert code == 2 and "--env-arg disable_env_checker: gym.make's own option" in err and "Traceback" not in err
    code, _, err = cli("train-agent", MINI, "--env-arg", 'render_mode="rgb_array"', "--out", str(tmp_path))
    assert code == 2 and "--env-arg render_mode: the command sets the render mode itself; drop it" in err


def test_the_gif_takes_the_env_args_width_and_height(tmp_path: Path) -> None:
    """``--env-arg width=64`` trained the whole run, then the GIF's gym.make got width twice and crashed."""
    from PIL import Image

    from redsim.trainers.agents import record_gif

    class Still:
        def predict(self, obs: Any, deterministic: bool = True) -> tuple[np.ndarray, None]:
            return np.zeros(3, np.float32), None

    kwargs = {"width": 48, "height": 32, "max_episode_steps": 4}
    assert record_gif(MINI, Still(), tmp_path / "a.gif", size=64, env_kwargs=kwargs) == 3
    assert Image.open(tmp_path / "a.gif").size == (48, 32)
    record_gif(MINI, Still(), tmp_path / "b.gif", size=40, env_kwargs={"max_episode_steps": 2})
    assert Image.open(tmp_path / "b.gif").size == (40, 40)

    # a Ctrl-C in PIL's save cut the GIF short in place (a resumed run's previous policy.gif too); now it is whole
    def cut_short(self: Image.Image, fp: Any, *args: Any, **kwargs: Any) -> None:
        Path(fp).write_bytes(b"GIF89a")
        raise KeyboardInterrupt

    before = (tmp_path / "b.gif").read_bytes()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Image.Image, "save", cut_short)
        with pytest.raises(KeyboardInterrupt):
            record_gif(MINI, Still(), tmp_path / "b.gif", size=40, env_kwargs={"max_episode_steps": 2})
    assert (tmp_path / "b.gif").read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [
        "a.gif",
        "b.gif",
    ]


def test_evaluation_reports_the_episodes_that_ended_diverged(cli: Callable[..., tuple[int, str, str]]) -> None:
    """An episode the stepper ends diverged (BistableBar-v1 at 2500x its force and 10x its dt) has a shorter, so
    often better, return: evaluate marks it, eval-agent counts it on its line, in --json and in a warning (it was
    not told apart from an episode that ran to its limit)."""
    hard = {"max_force": 1e5, "dt": 0.2, "max_episode_steps": 20}
    run = evaluate("RedSim/BistableBar-v1", "random", episodes=2, env_kwargs=hard)
    assert run.diverged is not None and run.diverged.tolist() == [True, True] and (run.lengths < 20).all()
    assert run.as_dict()["diverged_episodes"] == 2 and run.as_dict()["diverged"] == [True, True]
    calm = evaluate(MINI, "random", episodes=2, env_kwargs={"max_episode_steps": 5})
    assert calm.diverged is not None and not calm.diverged.any() and calm.as_dict()["diverged_episodes"] == 0
    args = ["eval-agent", "shipped", "RedSim/BistableBar-v1", "--episodes", "2", "--episode-steps", "20"]
    args += ["--env-arg", "max_force=1e5", "--env-arg", "dt=0.2"]
    code, out, err = cli(*args)
    assert code == 0 and "(2 episodes from seed 0; 2 diverged)" in out
    assert "agent: 2 of 2 episodes ended diverged (info['diverged']" in err
    code, out, err = cli(*args, "--json")
    assert code == 0 and json.loads(out)["agent"]["diverged_episodes"] == 2 and "ended diverged" in err


def test_eval_agent_takes_a_plain_sb3_model_with_its_algorithm(
    cli: Callable[..., tuple[int, str, str]], tmp_path: Path
) -> None:
    """An example's model (plain SB3, its VecNormalize statistics beside it) evaluates with --algo; another env's
    model is refused by its spaces, and another algorithm's by SB3's loader, each as a one-line error."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    from redsim.envs.sb3 import SB3VecEnv

    venv = VecNormalize(SB3VecEnv.make(MINI, num_envs=2))
    model = PPO("MlpPolicy", venv, n_steps=8, batch_size=16, seed=0).learn(16)
    model.save(tmp_path / "mine.zip")
    venv.save(str(tmp_path / "mine_vecnormalize.pkl"))
    agent = load_agent(tmp_path / "mine.zip", MINI, algo="ppo")
    assert agent.normalizer is not None and agent.num_timesteps == 16
    short = ("--episode-steps", "20")  # what is checked is how the model loads, not how long its episodes run
    code, out, _ = cli(
        "eval-agent", str(tmp_path / "mine.zip"), MINI, "--algo", "ppo", "--episodes", "2", *short, "--json"
    )
    assert code == 0 and json.loads(out)["agent"]["episodes"] == 2
    assert json.loads(out)["normalization"] == str(tmp_path / "mine_vecnormalize.pkl")
    # named as SB3 names it (its save("mine") writes mine.zip, its load("mine") reads it): was "no model file"
    assert load_agent(tmp_path / "mine", MINI, algo="ppo").normalizer is not None
    code, out, _ = cli("eval-agent", str(tmp_path / "mine"), MINI, "--algo", "ppo", "--episodes", "2", *short, "--json")
    assert code == 0 and json.loads(out)["normalization"] == str(tmp_path / "mine_vecnormalize.pkl")
    (tmp_path / "mine_vecnormalize.pkl").rename(tmp_path / "elsewhere.pkl")  # a plain model's file is optional
    code, out, _ = cli("eval-agent", str(tmp_path / "mine.zip"), MINI, "--algo", "ppo", "--episodes", "2", *short)
    assert code == 0 and "(raw observations):" in out.splitlines()[0]
    (tmp_path / "elsewhere.pkl").rename(tmp_path / "mine_vecnormalize.pkl")
    code, _, err = cli("eval-agent", str(_foreign_model(tmp_path)), MINI, "--algo", "sac", "--episodes", "2")
    assert code == 2 and "the model's observation space has shape (3,), the env's (14,)" in err
    code, _, err = cli("eval-agent", str(tmp_path / "mine.zip"), MINI, "--algo", "sac")
    assert code == 2 and "does not load as a SAC model" in err
    with pytest.raises(ValueError, match="algo must be one of ppo, sac, td3"):
        load_agent(tmp_path / "mine.zip", algo="dqn")
    from stable_baselines3 import SAC, HerReplayBuffer

    goal_env = SB3VecEnv.make(MINI, num_envs=2, goal=True)  # as examples/her_agent.py --out saves sac_her.zip
    SAC("MultiInputPolicy", goal_env, replay_buffer_class=HerReplayBuffer, learning_starts=10).save(tmp_path / "h.zip")
    code, _, err = cli("eval-agent", str(tmp_path / "h.zip"), MINI, "--algo", "sac")
    assert code == 2 and "trained with HER on dict observations redsim does not know" in err


def test_an_evaluation_leaves_the_callers_cuda_generators(tmp_path: Path) -> None:
    """evaluate seeds torch's generators, the CUDA ones too (torch.manual_seed): it forked only the CPU's, so the
    caller's CUDA generators were reset to the evaluation's seed."""
    import torch
    from stable_baselines3 import PPO

    from redsim.envs.sb3 import SB3VecEnv

    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA device")
    PPO("MlpPolicy", SB3VecEnv.make(MINI, num_envs=2), n_steps=8, batch_size=16, seed=0).save(tmp_path / "m.zip")
    agent = load_agent(tmp_path / "m.zip", MINI, algo="ppo")
    torch.cuda.manual_seed_all(123)
    torch.rand(3, device="cuda")
    before = torch.cuda.get_rng_state_all()
    evaluate(MINI, agent, episodes=2, seed=4, deterministic=False, env_kwargs=SHORT)
    assert all(torch.equal(a, b) for a, b in zip(torch.cuda.get_rng_state_all(), before, strict=True))


def test_a_sampled_evaluation_repeats_and_leaves_the_callers_generator(
    cli: Callable[..., tuple[int, str, str]], tmp_path: Path
) -> None:
    """evaluate(deterministic=False) / eval-agent --stochastic: the policy's sampled actions, seeded by the evaluation's
    seed (two runs alike, unlike the deterministic actions), drawn without moving the caller's torch generator."""
    import torch
    from stable_baselines3 import PPO

    from redsim.envs.sb3 import SB3VecEnv

    PPO("MlpPolicy", SB3VecEnv.make(MINI, num_envs=2), n_steps=8, batch_size=16, seed=0).save(tmp_path / "m.zip")
    agent = load_agent(tmp_path / "m.zip", MINI, algo="ppo")
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    sampled = [evaluate(MINI, agent, episodes=2, seed=s, deterministic=False, env_kwargs=SHORT) for s in (4, 4)]
    np.testing.assert_array_equal(torch.rand(3), expected)  # the caller's draws go on as if nothing had sampled
    np.testing.assert_array_equal(sampled[0].returns, sampled[1].returns)
    assert sampled[0].sampled and sampled[0].as_dict()["sampled"]
    plain = evaluate(MINI, agent, episodes=2, seed=4, env_kwargs=SHORT)
    assert not plain.sampled and not np.array_equal(plain.returns, sampled[0].returns)
    sampling = ["eval-agent", str(tmp_path / "m.zip"), MINI, "--algo", "ppo", "--episodes", "2", "--stochastic"]
    code, out, err = cli(*sampling, "--episode-steps", "20", "--seed", "4", "--json")
    assert code == 0, err
    assert json.loads(out)["agent"]["returns"] == sampled[0].as_dict()["returns"]
    code, out, _ = cli(*sampling, "--episode-steps", "20", "--baselines")
    assert code == 0 and "actions sampled, seed 0" in out.splitlines()[0]


def _ctrl_c_at_training_step(monkeypatch: pytest.MonkeyPatch, call: int) -> Callable[..., Any]:
    """Make the ``call``-th vector step of the training env (the one with 2 copies; an evaluation env has 1) raise
    KeyboardInterrupt; returns SB3VecEnv's own ``step_wait``, to put back."""
    from redsim.envs.sb3 import SB3VecEnv

    calls = {"n": 0}
    step_wait = SB3VecEnv.step_wait

    def interrupting(self: SB3VecEnv) -> Any:
        calls["n"] += self.num_envs == 2
        if calls["n"] == call:
            raise KeyboardInterrupt
        return step_wait(self)

    monkeypatch.setattr(SB3VecEnv, "step_wait", interrupting)
    return step_wait


def _ctrl_c_in_second_evaluation(monkeypatch: pytest.MonkeyPatch) -> Callable[..., Any]:
    """Make SB3's second ``evaluate_policy`` call (the EvalCallback's) raise KeyboardInterrupt; returns the original,
    to put back."""
    import stable_baselines3.common.callbacks as sb3_callbacks

    evaluate = sb3_callbacks.evaluate_policy
    calls = {"n": 0}

    def interrupted_second(*args: object, **kwargs: object) -> object:
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return evaluate(*args, **kwargs)

    monkeypatch.setattr(sb3_callbacks, "evaluate_policy", interrupted_second)
    return evaluate


def _foreign_model(folder: Path) -> Path:
    """An SB3 model of another project's env (saved untrained)."""
    from stable_baselines3 import SAC

    path = folder / "pendulum.zip"
    SAC("MlpPolicy", gym.make("Pendulum-v1"), learning_starts=0, buffer_size=10).save(path)
    assert zipfile.is_zipfile(path)
    return path


@pytest.mark.slow
@pytest.mark.parametrize("env_id", sorted(shipped_policies()))
def test_each_shipped_policy_beats_random_and_scripted_over_20_episodes(env_id: str) -> None:
    """On the same 20 episodes (seeds 0-19) the agent's returns are above each baseline's by a paired one-sided
    t-test at 5%, and it succeeds more often. Paired, because both run the same episodes: an unpaired margin of
    half the baseline's spread asked Stewart-v0 for 197.3 of at most 200 per episode, the scripted controller's
    spread coming from 3 episodes it never settles in (docs/agents.md)."""
    agent = evaluate(env_id, load_agent(shipped_policy(env_id), env_id), episodes=20, seed=0)
    for baseline in ("random", "scripted"):
        other = evaluate(env_id, baseline, episodes=20, seed=0)
        p_value, _ = agent.above(other)
        assert p_value < 0.05, (baseline, p_value)
        # a baseline that succeeds in every episode can only be matched (HangingCloth-v1's and v2's PI controller)
        assert agent.success_rate > other.success_rate or agent.success_rate == other.success_rate == 1.0, baseline


@pytest.mark.slow
def test_sac_learns_mini_chain_clearly_above_random(tmp_path: Path) -> None:
    from redsim.trainers.agents import train_agent

    result = train_agent(MINI, tmp_path, algo="sac", steps=20_000, eval_every=5_000, video=False)
    random = evaluate(MINI, "random", episodes=20, seed=20_000)  # the final evaluation's seeds
    scripted = evaluate(MINI, "scripted", episodes=20, seed=20_000)
    assert result.evaluation.mean > random.mean + 3 * random.std
    assert result.evaluation.mean > scripted.mean  # the table's settings beat the PI controller in 20k steps


def test_her_with_shards_is_refused_before_any_worker_starts(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from redsim.envs import sharded
    from redsim.trainers.agents import train_agent

    def no_workers(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("a worker process was started")

    monkeypatch.setattr(sharded.ShardedVectorEnv, "__init__", no_workers)
    with pytest.raises(ValueError, match=r"native vector env in one process \(shards=1, no --shards\), got shards=2"):
        train_agent(MINI, tmp_path / "x", algo="sac", steps=4000, her=True, shards=2, video=False)
    assert not (tmp_path / "x").exists()


def test_an_env_without_an_episode_limit_is_refused_before_training_and_evaluation(
    cli: Callable[..., tuple[int, str, str]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """max_episode_steps=-1 (no limit, as gym.make reads it) passed every check: the EvalCallback's first evaluation
    of a reach env never ended (train-agent, with --her too), and eval-agent printed a traceback. None is the id's own
    limit, which HER refused as none."""
    from redsim.envs.sb3 import SB3VecEnv
    from redsim.trainers.agents import _her_settings, train_agent

    def no_env(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("an env was made")

    monkeypatch.setattr(SB3VecEnv, "__init__", no_env)
    for her in (False, True):
        with pytest.raises(ValueError, match=r"needs an episode limit \(max_episode_steps\)"):
            train_agent(MINI, tmp_path / "x", algo="sac", steps=100, her=her, env_kwargs={"max_episode_steps": -1})
    assert not (tmp_path / "x").exists()
    code, _, err = cli("train-agent", MINI, "--steps", "100", "--env-arg", "max_episode_steps=-1", "--out", "y")
    assert code == 2 and "needs an episode limit" in err, err
    settings: dict[str, Any] = {}
    from redsim.trainers.agents import _episode_steps

    assert _episode_steps(MINI, {"max_episode_steps": None}) == 200 and _episode_steps(MINI, {}) == 200
    _her_settings(settings, "sac", 2, _episode_steps(MINI, {"max_episode_steps": None}), 1000, 1)  # the id's 200
    code, _, err = cli("eval-agent", "shipped", MINI, "--episodes", "1", "--env-arg", "max_episode_steps=-1")
    assert code == 2 and "evaluation needs an env with an episode limit" in err and "Traceback" not in err, err


HER_RUN = {"eval_every": 100, "eval_episodes": 2, "final_episodes": 2, "env_kwargs": SHORT, "n_envs": 4}
"""A tiny HER run of the mini chain: 200 steps over 4 copies of 20-step episodes."""


def test_her_trains_on_the_goal_env_and_its_agent_acts_on_the_flat_one(tmp_path: Path) -> None:
    from redsim.envs.goal import GoalSplit
    from redsim.trainers.agents import train_agent

    out = tmp_path / "her"
    result = train_agent(
        MINI, out, steps=200, her=True, overrides={"learning_starts": 100, "batch_size": 32}, **HER_RUN
    )
    model = load_agent(result.model_path, MINI)
    from stable_baselines3.common.save_util import load_from_pkl

    buffer = load_from_pkl(out / "replay_buffer.pkl")
    assert type(buffer).__name__ == "HerReplayBuffer" and buffer.pos == 50  # 200 steps over 4 copies
    assert model.model._n_updates > 0  # it trained, sampling relabelled goals
    goal = {"z": 4, "z_dot": 4, "handle_position": 3, "target_offset": 3}
    assert model_record(result.model_path)["goal"] == goal == model.goal
    assert json.loads((out / "agent.json").read_text())["her"] and np.isfinite(result.evaluation.mean)
    obs = np.random.default_rng(0).normal(size=(3, 14)).astype(np.float32)  # the env's flat observations
    split = model.normalizer.normalize_obs(GoalSplit(goal)(obs))
    np.testing.assert_array_equal(model.predict(obs)[0], model.model.predict(split, deterministic=True)[0])
    with pytest.raises(ValueError, match="observations of size 14"):  # another env's: not silently cut
        model.predict(obs[:, :12])


@pytest.mark.slow
def test_her_resumes_after_an_interruption_and_through_the_cli(
    cli: Callable[..., tuple[int, str, str]], tmp_path: Path
) -> None:
    from redsim.trainers.agents import train_agent

    interrupted = tmp_path / "interrupted"  # killed after a checkpoint: no model.zip, no buffer
    train_agent(
        MINI, interrupted, steps=200, her=True, checkpoint_every=100, overrides={"learning_starts": 100}, **HER_RUN
    )
    (interrupted / "model.zip").unlink()
    resumed = train_agent(MINI, interrupted, steps=300, her=True, resume=True, video=False, **HER_RUN)
    assert resumed.steps == 300 and np.isfinite(resumed.evaluation.mean)

    out = tmp_path / "her"
    code, _, err = cli("train-agent", MINI, "--her", "--steps", "200", "--out", str(out), *TINY, "--no-video")
    assert code == 0, err
    code, _, err = cli(
        "train-agent", MINI, "--her", "--steps", "300", "--out", str(out), *TINY, "--resume", "--no-video"
    )
    assert code == 0, err
    assert load_agent(out / "model.zip").num_timesteps == 300
    code, _, err = cli("train-agent", MINI, "--steps", "400", "--out", str(out), *TINY, "--resume")
    assert code == 2 and "cannot resume" in err and "sac with HER on RedSim/MiniChain-v0, not sac on" in err
    code, stdout, err = cli("eval-agent", str(out / "model.zip"), MINI, "--episodes", "2", "--episode-steps", "20")
    assert code == 0 and "agent" in stdout, err


def test_her_settings_it_cannot_train_are_clear_cli_errors(
    cli: Callable[..., tuple[int, str, str]], tmp_path: Path
) -> None:
    """Refused before training (the slow test above trains with HER): an on-policy algorithm, shards, a budget
    that ends no episode, an env without a goal; refused runs leave no folders behind."""
    for extra, message in (
        (["--algo", "ppo"], "off-policy"),
        (["--shards", "2"], "native vector env in one process (shards=1, no --shards), got shards=2"),
        (["--steps", "50"], "50 steps are not enough: HER's relabelling needs an ended episode of every copy"),
    ):
        code, _, err = cli("train-agent", MINI, "--her", "--out", str(tmp_path / "x"), *TINY, *extra)
        assert code == 2 and message in err, (extra, err)
    code, _, err = cli("train-agent", "RedSim/Klann-v0", "--her", "--out", str(tmp_path / "k"), *TINY)
    assert code == 2 and "needs a reach env" in err
    # the task is refused first, whatever the budget; refused runs leave no folders behind
    code, _, err = cli("train-agent", "RedSim/Klann-v0", "--her", "--out", str(tmp_path / "k"), *TINY, "--steps", "50")
    assert code == 2 and "needs a reach env" in err and "RedSim/Klann-v0 has no goal" in err
    assert not (tmp_path / "x").exists() and not (tmp_path / "k").exists()


@pytest.mark.slow
def test_a_resumed_run_draws_new_episodes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from redsim.envs.sb3 import SB3VecEnv
    from redsim.trainers.agents import train_agent

    seeds: list[int | None] = []
    reset = SB3VecEnv.reset

    def recording(self: SB3VecEnv) -> np.ndarray:
        seeds.append(self._seeds[0])
        return reset(self)

    monkeypatch.setattr(SB3VecEnv, "reset", recording)
    tiny = {"n_envs": 2, "eval_episodes": 2, "final_episodes": 2, "env_kwargs": SHORT, "video": False, "eval_every": 40}
    train_agent(MINI, tmp_path, algo="sac", steps=40, seed=3, **tiny)
    first = seeds[0]
    seeds.clear()
    train_agent(MINI, tmp_path, algo="sac", steps=80, seed=3, resume=True, **tiny)
    assert first == training_seed(3, 0) and first >= 20_100  # no evaluation's seeds (3 + 10_000 + i, eval-agent's)
    assert seeds[0] not in (first, 3 + 10_000, 3 + 20_000)  # not the first run's, nor the evaluations'
    again = seeds[0]
    seeds.clear()
    train_agent(MINI, tmp_path, algo="sac", steps=120, seed=3, resume=True, **tiny)
    assert seeds[0] not in (first, again, 3 + 10_000, 3 + 20_000)


@pytest.mark.slow
def test_a_resume_that_gives_an_env_default_again_goes_on_and_another_value_is_refused(
    cli: Callable[..., tuple[int, str, str]], tmp_path: Path
) -> None:
    """``--env-arg max_episode_steps=200`` (the id's length), ``dt=0.02`` (the env's) and ``dtype="float32"`` (a
    default of LatentEnv, which the env's ``**kwargs`` reach) make the env the run was made with (no env args): the
    resume goes on."""
    run = ["train-agent", MINI, "--algo", "sac", "--n-envs", "2", "--eval-every", "20", "--eval-episodes", "1"]
    run += ["--final-episodes", "1", "--no-video", "--no-progress", "--out", str(tmp_path)]
    assert cli(*run, "--steps", "20")[0] == 0
    defaults = ["--env-arg", "max_episode_steps=200", "--env-arg", "dt=0.02", "--env-arg", 'dtype="float32"']
    code, _, err = cli(*run, "--steps", "40", "--resume", *defaults)
    assert code == 0, err
    assert load_agent(tmp_path / "model.zip", MINI).num_timesteps == 40
    code, _, err = cli(*run, "--steps", "60", "--resume", "--episode-steps", "100")
    assert code == 2 and "cannot resume with env_kwargs {'max_episode_steps': 100}" in err, err


def test_training_seeds_are_apart_and_env_defaults_are_the_env_s_own() -> None:
    """Neighbouring seeds' 16 copies share no episode; a base class's default that the env replaces by its own class
    attribute is not taken for the env's (``randomize_condition``: True in ConditionalBar-v0, False in LatentEnv)."""
    from redsim.trainers.agents import _env_defaults

    starts = [training_seed(s, 0) for s in range(100)]
    assert min(abs(a - b) for i, a in enumerate(starts) for b in starts[i + 1 :]) > 16
    assert training_seed(3, 0) >= 20_100  # above every evaluation's seeds (3 + 10_000 + i, eval-agent's 3 + 20_000)
    assert "randomize_condition" not in _env_defaults("RedSim/ConditionalBar-v0")
    assert _env_defaults(MINI)["dtype"] == "float32"


def test_td3_resumes_from_a_checkpoint_with_other_copies(tmp_path: Path) -> None:
    """No replay buffer comes with a checkpoint, so the copies may change; the exploration noise follows them."""
    from redsim.trainers.agents import train_agent

    tiny = {"eval_episodes": 2, "final_episodes": 2, "env_kwargs": SHORT, "video": False, "eval_every": 40}
    train_agent(MINI, tmp_path, algo="td3", steps=40, n_envs=2, checkpoint_every=20, **tiny)
    (tmp_path / "model.zip").unlink()  # interrupted after its checkpoints
    result = train_agent(MINI, tmp_path, algo="td3", steps=80, n_envs=4, resume=True, **tiny)
    assert result.steps == 80 and model_record(result.model_path)["n_envs"] == 4


def test_resume_takes_the_file_trained_the_most_steps_not_the_newest(tmp_path: Path) -> None:
    """A copy that resets file times (``cp`` without ``-a``, a sync tool) must not make an older checkpoint win."""
    import json
    import os
    import zipfile

    from redsim.trainers.agents import _resume_from

    (tmp_path / "checkpoints").mkdir()
    for name, steps in (("model.zip", 972), ("checkpoints/rl_model_300_steps.zip", 300)):
        with zipfile.ZipFile(tmp_path / name, "w") as saved:
            saved.writestr("data", json.dumps({"num_timesteps": steps}))
    os.utime(tmp_path / "model.zip", (1, 1))  # older on disk than the 300-step checkpoint
    assert _resume_from(tmp_path) == tmp_path / "model.zip"
    with zipfile.ZipFile(tmp_path / "checkpoints/rl_model_972_steps.zip", "w") as saved:
        saved.writestr("data", json.dumps({"num_timesteps": 972}))
    assert _resume_from(tmp_path) == tmp_path / "model.zip"  # a tie: model.zip keeps the replay buffer


def test_a_resume_from_a_checkpoint_keeps_a_later_best_model(tmp_path: Path) -> None:
    """Resumed at 200 steps from a checkpoint, the run's evaluations up to 200 are carried and the best mean to beat
    is the best of all of them (the t = 300 evaluation saved best_model.zip)."""
    from stable_baselines3.common.callbacks import EvalCallback

    from redsim.trainers.agents import _continue_evaluations

    path = tmp_path / "evaluations.npz"
    results = np.array([[1.0, 1.0], [2.0, 2.0], [5.0, 5.0], [3.0, 3.0]])
    np.savez(path, timesteps=[100, 200, 300, 400], results=results, ep_lengths=np.full((4, 2), 20))
    callback = EvalCallback(gym.make("RedSim/MiniChain-v0"), n_eval_episodes=2)
    _continue_evaluations(callback, path, until=200, episodes=2)
    assert callback.best_mean_reward == 5.0 and callback.evaluations_timesteps == [100, 200]
    other = EvalCallback(gym.make("RedSim/MiniChain-v0"), n_eval_episodes=5)
    _continue_evaluations(other, path, until=200, episodes=5)  # another episode count: only the best is carried
    assert other.best_mean_reward == 5.0 and other.evaluations_timesteps == []


def test_ctrl_c_saves_the_run_and_resume_goes_on_from_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A KeyboardInterrupt inside learn keeps the model, replay buffer, curve and agent.json (interrupted), and
    --resume continues from that model with its buffer, not from an older checkpoint."""
    from redsim.envs.sb3 import SB3VecEnv
    from redsim.trainers.agents import BUFFER, TrainingInterrupted, train_agent

    step_wait = _ctrl_c_at_training_step(monkeypatch, 31)
    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "env_kwargs": SHORT, "video": False}
    with pytest.raises(TrainingInterrupted, match="interrupted at 60 env steps") as stop:
        train_agent(MINI, tmp_path, algo="sac", steps=100, eval_every=20, **tiny)
    assert stop.value.steps == 60 and stop.value.model_path == tmp_path / "model.zip"
    record = json.loads((tmp_path / "agent.json").read_text())
    assert record["interrupted"] is True and record["steps"] == 60 and "final_evaluation" not in record
    assert (tmp_path / "model.zip").is_file() and (tmp_path / BUFFER).is_file()
    with (tmp_path / "curve.csv").open() as handle:
        assert [int(row["env_steps"]) for row in csv.DictReader(handle)] == [20, 40, 60]
    monkeypatch.setattr(SB3VecEnv, "step_wait", step_wait)
    with pytest.raises(ValueError, match=r"cannot resume with seed 5: the run in .* was started with seed 0"):
        train_agent(MINI, tmp_path, algo="sac", steps=100, eval_every=20, resume=True, seed=5, **tiny)
    (tmp_path / "model_vecnormalize.pkl").rename(tmp_path / "aside.pkl")
    with pytest.raises(FileNotFoundError, match=r"trained on normalized observations and its statistics .* missing"):
        train_agent(MINI, tmp_path, algo="sac", steps=100, eval_every=20, resume=True, **tiny)
    (tmp_path / "aside.pkl").rename(tmp_path / "model_vecnormalize.pkl")
    result = train_agent(MINI, tmp_path, algo="sac", steps=100, eval_every=20, resume=True, **tiny)
    assert result.steps == 100
    record = json.loads((tmp_path / "agent.json").read_text())
    assert "interrupted" not in record and record["wall_s"] >= 0.0
    with (tmp_path / "curve.csv").open() as handle:
        assert [int(row["env_steps"]) for row in csv.DictReader(handle)] == [20, 40, 60, 80, 100]


@pytest.mark.parametrize(
    "stopped_in",
    ["model.zip", pytest.param("model_vecnormalize.pkl", marks=pytest.mark.slow)],  # the same save, 10 s
)
def test_ctrl_c_while_the_run_is_saved_keeps_its_previous_files_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, stopped_in: str
) -> None:
    """A Ctrl-C inside the save after training (recorded as an interrupted run that --resume finishes) leaves the
    previous model.zip, replay buffer and statistics whole and together: not a cut-short zip, nor a new model beside
    the statistics of the older one (which a resume, or eval-agent, would act through)."""
    from stable_baselines3 import SAC
    from stable_baselines3.common.vec_env import VecNormalize

    from redsim.envs.sb3 import SB3VecEnv
    from redsim.trainers.agents import TrainingInterrupted, train_agent

    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "env_kwargs": SHORT, "video": False, "eval_every": 20}
    train_agent(MINI, tmp_path, algo="sac", steps=20, **tiny)
    names = ("model.zip", "replay_buffer.pkl", "model_vecnormalize.pkl")
    before = {name: (tmp_path / name).read_bytes() for name in names}
    owner = SAC if stopped_in == "model.zip" else VecNormalize
    save = owner.save

    def cut_short(self: Any, path: Any, *args: Any, **kwargs: Any) -> None:
        save(self, path, *args, **kwargs)
        if Path(path).name.startswith(stopped_in):  # the run's own file, not a checkpoint's
            with open(path, "r+b") as handle:
                handle.truncate(100)  # stopped mid-write
            raise KeyboardInterrupt

    monkeypatch.setattr(owner, "save", cut_short)
    made, closed = [], []
    init, close = SB3VecEnv.__init__, SB3VecEnv.close

    def counted_init(self: Any, *args: Any, **kwargs: Any) -> None:
        made.append(self)
        init(self, *args, **kwargs)

    def counted_close(self: Any) -> None:
        closed.append(self)
        close(self)

    monkeypatch.setattr(SB3VecEnv, "__init__", counted_init)
    monkeypatch.setattr(SB3VecEnv, "close", counted_close)
    with pytest.raises(TrainingInterrupted, match="and again while saving them") as stop:
        train_agent(MINI, tmp_path, algo="sac", steps=40, resume=True, **tiny)  # the save is retried once, also cut
    assert stop.value.saved is False and json.loads((tmp_path / "agent.json").read_text())["saved"] is False
    assert {name: (tmp_path / name).read_bytes() for name in names} == before
    assert made and all(any(env is c for c in closed) for env in made)  # the training and evaluation envs closed
    monkeypatch.setattr(owner, "save", save)
    assert train_agent(MINI, tmp_path, algo="sac", steps=40, resume=True, **tiny).steps == 40


def test_a_second_ctrl_c_while_an_interrupted_run_is_saved_is_reported_as_such(
    cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C in training, then again in the save it starts (a replay buffer of tens of MB takes a while): the
    CLI said 'interrupted before training started; nothing was saved' though the run had trained and its
    checkpoints were there; now the interrupt says the last whole save stands, and --resume goes on from it."""
    from stable_baselines3 import SAC

    save = SAC.save

    def interrupted_save(self: Any, path: Any, *args: Any, **kwargs: Any) -> None:
        if Path(path).name.startswith("model.zip"):  # the run's own file, not a checkpoint's
            raise KeyboardInterrupt
        save(self, path, *args, **kwargs)

    step_wait = _ctrl_c_at_training_step(monkeypatch, 31)
    monkeypatch.setattr(SAC, "save", interrupted_save)
    argv = ("train-agent", MINI, "--algo", "sac", "--steps", "100", "--eval-every", "20", "--n-envs", "2")
    tiny = ("--eval-episodes", "1", "--final-episodes", "1", "--episode-steps", "20", "--no-video", "--no-progress")
    code, _, err = cli(*argv, *tiny, "--out", str(tmp_path))
    assert code == 130 and "interrupted at 60 env steps and again while saving them" in err, err
    assert "nothing was saved" not in err and not (tmp_path / "model.zip").exists()
    assert any((tmp_path / "checkpoints").iterdir())
    monkeypatch.setattr(SAC, "save", save)
    from redsim.envs.sb3 import SB3VecEnv

    monkeypatch.setattr(SB3VecEnv, "step_wait", step_wait)
    code, _, err = cli(*argv, *tiny, "--out", str(tmp_path), "--resume")
    assert code == 0, err


@pytest.mark.slow
def test_ctrl_c_in_the_final_evaluation_or_mid_rollout_keeps_an_honest_record(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Stopped in the final evaluation, the saved model is the trained one and --resume only evaluates it; PPO
    stopped mid-rollout records the steps of its last whole rollout (it never learnt from the rest)."""
    from redsim.trainers import agents
    from redsim.trainers.agents import TrainingInterrupted, train_agent

    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "env_kwargs": SHORT, "video": False}
    evaluate_ = agents.evaluate

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(agents, "evaluate", stop)
    with pytest.raises(TrainingInterrupted, match="interrupted at 40 env steps"):
        train_agent(MINI, tmp_path / "sac", algo="sac", steps=40, **tiny)
    assert json.loads((tmp_path / "sac" / "agent.json").read_text())["interrupted"] is True
    monkeypatch.setattr(agents, "evaluate", evaluate_)
    result = train_agent(MINI, tmp_path / "sac", algo="sac", steps=40, resume=True, **tiny)
    assert result.steps == 40 and "final_evaluation" in json.loads((tmp_path / "sac" / "agent.json").read_text())
    plot = agents.plot_curve
    monkeypatch.setattr(agents, "plot_curve", stop)  # after the final evaluation, in the files: the same record
    with pytest.raises(TrainingInterrupted, match="interrupted at 40 env steps"):
        train_agent(MINI, tmp_path / "late", algo="sac", steps=40, **tiny)
    assert json.loads((tmp_path / "late" / "agent.json").read_text())["interrupted"] is True
    monkeypatch.setattr(agents, "plot_curve", plot)
    assert train_agent(MINI, tmp_path / "late", algo="sac", steps=40, resume=True, **tiny).trained == 0
    assert (tmp_path / "late" / "curve.png").is_file()

    # rollouts of n_steps 8 x 2 copies: one whole rollout (16 steps) and 4 more steps
    _ctrl_c_at_training_step(monkeypatch, 13)
    with pytest.raises(TrainingInterrupted, match="interrupted at 16 env steps"):
        train_agent(MINI, tmp_path / "ppo", algo="ppo", steps=64, overrides={"n_steps": 8, "batch_size": 8}, **tiny)
    assert json.loads((tmp_path / "ppo" / "agent.json").read_text())["steps"] == 16


def test_the_training_log_keeps_sb3_s_tensorboard_and_stdout_settings(tmp_path: Path) -> None:
    """progress.csv always; SB3's own outputs where tensorboard_log or verbose ask for them (as SB3 would set up)."""
    from types import SimpleNamespace

    from stable_baselines3.common.logger import CSVOutputFormat, HumanOutputFormat

    from redsim.trainers.agents import _training_log

    quiet = _training_log(SimpleNamespace(tensorboard_log=None, verbose=0), tmp_path, None)
    assert [type(f) for f in quiet.output_formats] == [CSVOutputFormat] and (tmp_path / "progress.csv").is_file()
    loud = _training_log(SimpleNamespace(tensorboard_log=None, verbose=1), tmp_path, 200)
    assert {type(f) for f in loud.output_formats} == {HumanOutputFormat, CSVOutputFormat}
    assert (tmp_path / "progress-from-200.csv").is_file()
    if importlib.util.find_spec("tensorboard") is None:  # asked for and missing: SB3's own error, as before
        with pytest.raises(ImportError, match="tensorboard is not installed"):
            _training_log(SimpleNamespace(tensorboard_log=str(tmp_path / "tb"), verbose=0), tmp_path, None)
    for logger in (quiet, loud):
        logger.close()


def test_an_interrupted_ppo_run_saves_the_normalizer_of_its_last_rollout(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """PPO's saved steps end at its last finished rollout (16 of the 24 stepped): so do its VecNormalize statistics."""
    import pickle

    from redsim.trainers.agents import TrainingInterrupted, train_agent

    _ctrl_c_at_training_step(monkeypatch, 13)  # 12 vector steps: the first rollout's 8, 4 of the next
    small = {"n_steps": 8, "batch_size": 16, "n_epochs": 1}
    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "env_kwargs": SHORT, "video": False}
    with pytest.raises(TrainingInterrupted, match="interrupted at 16 env steps"):
        train_agent(MINI, tmp_path, algo="ppo", steps=64, eval_every=64, overrides=small, **tiny)
    with (tmp_path / "model_vecnormalize.pkl").open("rb") as handle:
        saved = pickle.load(handle)  # a VecNormalize without its env
    assert saved.obs_rms.count == pytest.approx(2 + 16, abs=1e-3)  # the reset and the first rollout's 8 x 2 steps


def test_ppo_interrupted_in_its_update_or_at_a_rollouts_last_step_saves_its_last_learnt_rollout(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SB3 counts a rollout's 16 steps before it updates on them: stopped inside the second update (weights half
    changed in place), the run is saved as of the first update (16 steps, its weights, optimizer and statistics),
    not at 32 steps with weights that never learnt them. PPO's evaluations come after an update, as the next rollout
    starts: stopped in the second (at 32 steps, two updates learnt), the run is saved at 32 with those statistics."""
    import pickle

    import stable_baselines3.common.callbacks as sb3_callbacks
    import torch
    from stable_baselines3 import PPO

    from redsim.trainers.agents import TrainingInterrupted, train_agent

    learnt: list[dict[str, torch.Tensor]] = []
    train = PPO.train

    def interrupted_second(self: PPO) -> None:
        train(self)  # the second update changes the weights, then the interrupt comes
        learnt.append({k: v.clone() for k, v in self.policy.state_dict().items()})
        if len(learnt) == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(PPO, "train", interrupted_second)
    small = {"n_steps": 8, "batch_size": 16, "n_epochs": 1}
    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "env_kwargs": SHORT, "video": False}
    with pytest.raises(TrainingInterrupted, match="interrupted at 16 env steps"):
        train_agent(MINI, tmp_path / "train", algo="ppo", steps=64, eval_every=64, overrides=small, **tiny)
    saved = load_agent(tmp_path / "train" / "model.zip")
    assert saved.num_timesteps == 16 and saved.model._n_updates == 1
    assert saved.normalizer.obs_rms.count == pytest.approx(2 + 16, abs=1e-3)  # the reset and the first rollout
    for name, value in saved.model.policy.state_dict().items():
        torch.testing.assert_close(value, learnt[0][name], rtol=0, atol=0)  # the first update's, not the second's
    assert not all(torch.equal(value, learnt[1][name]) for name, value in saved.model.policy.state_dict().items())
    assert {int(s["step"]) for s in saved.model.policy.optimizer.state_dict()["state"].values()} == {1}  # Adam's
    monkeypatch.setattr(PPO, "train", train)

    evaluate = sb3_callbacks.evaluate_policy
    calls = {"n": 0}

    def interrupted_evaluation(*args: object, **kwargs: object) -> object:  # every 16 steps: each rollout's start
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return evaluate(*args, **kwargs)

    monkeypatch.setattr(sb3_callbacks, "evaluate_policy", interrupted_evaluation)
    with pytest.raises(TrainingInterrupted, match="interrupted at 32 env steps"):
        train_agent(MINI, tmp_path / "evaluation", algo="ppo", steps=64, eval_every=16, overrides=small, **tiny)
    assert load_agent(tmp_path / "evaluation" / "model.zip").model._n_updates == 2
    with (tmp_path / "evaluation" / "model_vecnormalize.pkl").open("rb") as handle:
        assert pickle.load(handle).obs_rms.count == pytest.approx(2 + 32, abs=1e-3)


def test_ppo_checkpoints_hold_learnt_rollouts_and_a_resume_after_ctrl_c_takes_model_zip(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """PPO's checkpoints are saved as a rollout starts (and as training ends), so each holds the weights, update
    count and statistics of the steps it counts, and a run stopped mid-rollout (16 steps learnt, 28 stepped) leaves
    none past 16: --resume goes on from model.zip to the 64 steps asked, not from a 24-step checkpoint to 72."""
    from redsim.envs.sb3 import SB3VecEnv
    from redsim.trainers.agents import TrainingInterrupted, train_agent

    small = {"n_steps": 8, "batch_size": 16, "n_epochs": 1}  # rollouts of 16 env steps, one update each
    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "env_kwargs": SHORT, "video": False}
    run = {"algo": "ppo", "steps": 64, "eval_every": 64, "overrides": small, **tiny}
    train_agent(MINI, tmp_path / "whole", checkpoint_every=16, **run)
    folder = tmp_path / "whole" / "checkpoints"
    assert sorted(p.name for p in folder.glob("rl_model_*_steps.zip")) == [
        f"rl_model_{n}_steps.zip" for n in (16, 32, 48, 64)
    ]
    for n in (16, 32, 48, 64):
        saved = load_agent(folder / f"rl_model_{n}_steps.zip")
        assert saved.num_timesteps == n and saved.model._n_updates == n // 16  # every rollout it counts was learnt
        assert saved.normalizer.obs_rms.count == pytest.approx(2 + n, abs=1e-3)  # the reset and n steps
    (tmp_path / "whole" / "model.zip").unlink()  # killed after its last checkpoint
    assert train_agent(MINI, tmp_path / "whole", resume=True, **{**run, "steps": 80}).steps == 80

    step_wait = _ctrl_c_at_training_step(monkeypatch, 15)  # 14 vector steps: the first rollout's 8, 6 of the next
    with pytest.raises(TrainingInterrupted, match="interrupted at 16 env steps"):
        train_agent(MINI, tmp_path / "stopped", checkpoint_every=24, **run)
    assert not list((tmp_path / "stopped" / "checkpoints").glob("rl_model_*"))  # 24 is saved as a rollout starts
    monkeypatch.setattr(SB3VecEnv, "step_wait", step_wait)
    assert train_agent(MINI, tmp_path / "stopped", checkpoint_every=24, resume=True, **run).steps == 64


def test_a_run_interrupted_in_an_evaluation_makes_it_on_resume(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Stopped inside the evaluation at 40 steps, the resumed run evaluates at 40 first: no grid point is lost."""
    import stable_baselines3.common.callbacks as sb3_callbacks

    from redsim.trainers.agents import TrainingInterrupted, train_agent

    evaluate = _ctrl_c_in_second_evaluation(monkeypatch)
    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "env_kwargs": SHORT, "video": False}
    with pytest.raises(TrainingInterrupted, match="interrupted at 40 env steps"):
        train_agent(MINI, tmp_path, algo="sac", steps=100, eval_every=20, **tiny)
    monkeypatch.setattr(sb3_callbacks, "evaluate_policy", evaluate)
    train_agent(MINI, tmp_path, algo="sac", steps=100, eval_every=20, resume=True, **tiny)
    with (tmp_path / "curve.csv").open() as handle:
        assert [int(row["env_steps"]) for row in csv.DictReader(handle)] == [20, 40, 60, 80, 100]
    with np.load(tmp_path / "evaluations.npz") as evaluations:
        assert list(evaluations["timesteps"]) == [20, 40, 60, 80, 100]


@pytest.mark.slow
def test_a_resume_with_other_eval_episodes_evaluates_only_the_missed_step(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """evaluations.npz drops the evaluations of another episode count, the curve keeps them: a finished run extended
    with another --eval-episodes does not evaluate its last step again (no second row at 40), and one stopped
    inside the evaluation at 40 still makes it first."""
    import stable_baselines3.common.callbacks as sb3_callbacks

    from redsim.trainers.agents import TrainingInterrupted, train_agent

    tiny = {"n_envs": 2, "final_episodes": 1, "env_kwargs": SHORT, "video": False, "eval_every": 20}

    def curve_steps(run: Path) -> list[int]:
        with (run / "curve.csv").open() as handle:
            return [int(row["env_steps"]) for row in csv.DictReader(handle)]

    train_agent(MINI, tmp_path / "done", algo="sac", steps=40, eval_episodes=1, **tiny)
    train_agent(MINI, tmp_path / "done", algo="sac", steps=60, eval_episodes=2, resume=True, **tiny)
    assert curve_steps(tmp_path / "done") == [20, 40, 60]

    evaluate = _ctrl_c_in_second_evaluation(monkeypatch)
    with pytest.raises(TrainingInterrupted, match="interrupted at 40 env steps"):
        train_agent(MINI, tmp_path / "stopped", algo="sac", steps=60, eval_episodes=1, **tiny)
    monkeypatch.setattr(sb3_callbacks, "evaluate_policy", evaluate)
    train_agent(MINI, tmp_path / "stopped", algo="sac", steps=60, eval_episodes=2, resume=True, **tiny)
    assert curve_steps(tmp_path / "stopped") == [20, 40, 60]


def test_sigterm_saves_the_run_as_ctrl_c_does_and_a_bufferless_resume_refills_first(
    cli: Callable[..., tuple[int, str, str]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog
) -> None:
    """A batch scheduler's SIGTERM takes the Ctrl-C path (exit 130, model and replay buffer saved); a resume from a
    checkpoint, which keeps no replay buffer, waits for new transitions before learning, and says so."""
    import os
    import signal
    import threading

    from redsim.trainers import agents

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals reach the main thread only")
    before = signal.getsignal(signal.SIGTERM)
    training_log = agents._training_log

    def terminated(*args: object) -> object:
        os.kill(os.getpid(), signal.SIGTERM)  # arrives as the run starts to learn
        return training_log(*args)

    monkeypatch.setattr(agents, "_training_log", terminated)
    code, _, err = cli("train-agent", MINI, "--steps", "200", "--out", str(tmp_path), *TINY)
    assert code == 130 and "interrupted at 0 env steps" in err, err
    assert (tmp_path / "model.zip").is_file() and (tmp_path / agents.BUFFER).is_file()
    assert signal.getsignal(signal.SIGTERM) == before  # put back: not left on the caller
    monkeypatch.setattr(agents, "_training_log", training_log)

    run = tmp_path / "checkpointed"
    tiny = {"n_envs": 2, "eval_episodes": 2, "final_episodes": 2, "env_kwargs": SHORT, "video": False, "eval_every": 20}
    agents.train_agent(MINI, run, algo="sac", steps=40, checkpoint_every=20, overrides={"learning_starts": 10}, **tiny)
    (run / "model.zip").unlink()  # killed after its checkpoints
    with caplog.at_level("WARNING", logger="redsim.trainers.agents"):
        result = agents.train_agent(MINI, run, algo="sac", steps=60, resume=True, **tiny)
    model = agents.load_agent(result.model_path).model
    assert "without a replay buffer" in caplog.text and model.learning_starts == 40 + 10  # half of the 20 left
    with caplog.at_level("WARNING", logger="redsim.trainers.agents"):
        agents.train_agent(MINI, tmp_path / "empty", algo="sac", steps=20, resume=True, **tiny)
    assert "nothing to resume in" in caplog.text


def test_a_resumed_run_keeps_the_evaluation_and_checkpoint_grid(tmp_path: Path) -> None:
    """Evaluations and checkpoints every 20 env steps land at 20, 40, 60 in all, whether or not the run stopped at 30
    (SB3's callbacks count their calls from 0 again on a resume)."""
    from redsim.trainers.agents import train_agent

    tiny = {"n_envs": 2, "eval_episodes": 2, "final_episodes": 2, "env_kwargs": SHORT, "video": False}
    grid = {"eval_every": 20, "checkpoint_every": 20, "overrides": {"learning_starts": 10}}
    train_agent(MINI, tmp_path, algo="sac", steps=30, **grid, **tiny)
    train_agent(MINI, tmp_path, algo="sac", steps=60, resume=True, **grid, **tiny)
    with np.load(tmp_path / "evaluations.npz") as evaluations:
        assert evaluations["timesteps"].tolist() == [20, 40, 60]
    assert sorted(p.name for p in (tmp_path / "checkpoints").glob("rl_model_*_steps.zip")) == [
        f"rl_model_{n}_steps.zip" for n in (20, 40, 60)
    ]


@pytest.mark.slow
def test_a_resume_without_intervals_keeps_the_runs_own_and_refuses_other_settings(tmp_path: Path) -> None:
    """A run resumed with more steps and no --eval-every evaluates and checkpoints on its first call's grid (it was
    steps / 10 and steps / 4 of the new budget), and overrides other than those its model was made with are refused
    (the loaded model ignored them while agent.json recorded them): a review's findings."""
    import json

    from redsim.trainers.agents import train_agent

    tiny = {"n_envs": 2, "eval_episodes": 2, "final_episodes": 2, "env_kwargs": SHORT, "video": False}
    made = {"overrides": {"learning_starts": 10, "learning_rate": 1e-3}}
    train_agent(MINI, tmp_path, algo="sac", steps=40, **made, **tiny)  # evaluations every 4, checkpoints every 10
    with pytest.raises(ValueError, match=r"cannot resume with overrides \{'learning_rate': 0.5\}.*0.001"):
        train_agent(MINI, tmp_path, algo="sac", steps=80, resume=True, overrides={"learning_rate": 0.5}, **tiny)
    train_agent(MINI, tmp_path, algo="sac", steps=80, resume=True, **tiny)  # no overrides: the model's settings
    with np.load(tmp_path / "evaluations.npz") as evaluations:
        assert evaluations["timesteps"].tolist() == list(range(4, 81, 4))
    assert sorted(int(p.name.split("_")[2]) for p in (tmp_path / "checkpoints").glob("rl_model_*_steps.zip")) == [
        10,
        20,
        30,
        40,
        50,
        60,
        70,
        80,
    ]
    record = json.loads((tmp_path / "agent.json").read_text())
    assert record["eval_every"] == 4 and record["checkpoint_every"] == 10
    assert record["hyperparams"]["learning_rate"] == 1e-3  # what the model trained with, not the table's


def test_the_curve_marks_each_runs_final_evaluation_apart_from_the_periodic_ones(tmp_path: Path) -> None:
    """A run that ends off the evaluation grid ends its curve with the final evaluation, on other episodes
    (``final_episodes`` from SEED + FINAL_EVAL_SEED) than the periodic ones: its row is marked ``final`` (1), also once
    a resume has gone past it, so the periodic rows alone compare policies. A user's curve.png jumped at that point
    (a 3,008-step MiniChain run: -80 at the last periodic evaluation, +33 at the final one, -20 for the same model on
    the periodic episodes): the episodes changed, not the policy."""
    from redsim.trainers.agents import _read_curve, train_agent

    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "env_kwargs": SHORT, "video": False}
    train_agent(MINI, tmp_path, algo="sac", steps=50, eval_every=20, **tiny)
    with (tmp_path / "curve.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [(int(r["env_steps"]), float(r["final"])) for r in rows] == [(20, 0.0), (40, 0.0), (50, 1.0)]
    train_agent(MINI, tmp_path, algo="sac", steps=80, eval_every=20, resume=True, **tiny)  # ends on the grid
    marked = [(r["env_steps"], r["final"]) for r in _read_curve(tmp_path / "curve.csv")]
    assert marked == [(20, 0.0), (40, 0.0), (50, 1.0), (60, 0.0), (80, 0.0)]


def test_plot_curve_draws_the_final_evaluations_apart_from_the_periodic_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The periodic evaluations are one line; a final evaluation (other episodes) is a point of its own, not the
    line's next point. A curve.csv written before the ``final`` column reads as periodic rows."""
    from matplotlib.axes import Axes

    from redsim.trainers.agents import _read_curve, plot_curve

    drawn: list[tuple[str, list[float]]] = []
    for name in ("plot", "errorbar"):
        original = getattr(Axes, name)

        def record(self: Axes, x: Any, *args: Any, _name: str = name, _original: Any = original, **kw: Any) -> Any:
            drawn.append((_name, [float(v) for v in x]))
            return _original(self, x, *args, **kw)

        monkeypatch.setattr(Axes, name, record)
    row = {"wall_s": 1.0, "mean_return": 2.0, "std_return": 0.5, "success_rate": 0.0}
    curve = [row | {"env_steps": 20}, row | {"env_steps": 40, "final": 0.0}, row | {"env_steps": 50, "final": 1.0}]
    plot_curve(curve, tmp_path / "curve.png", "t")
    assert ("plot", [20.0, 40.0]) in drawn and ("errorbar", [50.0]) in drawn
    assert not [x for name, x in drawn if 50.0 in x and name == "plot"]
    (tmp_path / "old.csv").write_text("env_steps,wall_s,mean_return,std_return,success_rate\n20,1.0,2.0,0.5,0.0\n")
    assert _read_curve(tmp_path / "old.csv") == [{"final": 0.0, "env_steps": 20} | row]


def test_run_files_are_replaced_whole(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """curve.csv and agent.json go through a temporary file: a write that stops half way leaves the previous file
    (they were written in place, and a cut curve.csv or empty agent.json stopped --resume: a review's finding)."""
    import csv

    from redsim.trainers.agents import _read_curve, _write_curve, _write_record

    row = {"env_steps": 4, "wall_s": 1.0, "mean_return": 2.0, "std_return": 0.5, "success_rate": 0.0, "final": 0.0}
    _write_curve(tmp_path / "curve.csv", [row])
    _write_record(tmp_path, {"seed": 3})

    def stopped(self: csv.DictWriter, rows: list) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(csv.DictWriter, "writerows", stopped)
    with pytest.raises(KeyboardInterrupt):
        _write_curve(tmp_path / "curve.csv", [row, row])
    monkeypatch.setattr(Path, "write_text", lambda self, text: (_ for _ in ()).throw(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        _write_record(tmp_path, {"seed": 4})
    monkeypatch.undo()
    assert _read_curve(tmp_path / "curve.csv") == [row]
    assert (tmp_path / "agent.json").read_text().count('"seed": 3') == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["agent.json", "curve.csv"]  # no temporary left


def test_a_resume_skips_a_checkpoint_whose_statistics_are_missing_or_damaged(tmp_path: Path) -> None:
    """A hard stop between a checkpoint's model and its VecNormalize file (written after it) leaves a model without
    statistics: the resume takes the newest whole save instead of refusing the run."""
    from redsim.trainers.agents import _resume_from, normalizer_path, train_agent

    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "env_kwargs": SHORT, "video": False, "eval_every": 20}
    overrides = {"learning_starts": 10, "normalize": {"clip_obs": 10.0}}
    train_agent(MINI, tmp_path, algo="sac", steps=40, checkpoint_every=20, overrides=overrides, **tiny)
    (tmp_path / "model.zip").unlink()
    newest = tmp_path / "checkpoints" / "rl_model_40_steps.zip"
    assert _resume_from(tmp_path) == newest
    normalizer_path(newest).write_bytes(b"cut sho")
    assert _resume_from(tmp_path) == tmp_path / "checkpoints" / "rl_model_20_steps.zip"
    normalizer_path(newest).unlink()
    assert _resume_from(tmp_path) == tmp_path / "checkpoints" / "rl_model_20_steps.zip"
    older = tmp_path / "checkpoints" / "rl_model_20_steps.zip"
    kept = normalizer_path(older).read_bytes()
    normalizer_path(older).unlink()  # none whole: refused, never a new run over the old one (a review's finding)
    with pytest.raises(FileNotFoundError, match="are missing"):
        train_agent(MINI, tmp_path, algo="sac", steps=60, resume=True, checkpoint_every=20, **tiny)
    for path in (newest, older):
        normalizer_path(path).write_bytes(b"cut")
    with pytest.raises(ValueError, match="its statistics are damaged"):
        train_agent(MINI, tmp_path, algo="sac", steps=60, resume=True, checkpoint_every=20, **tiny)
    normalizer_path(older).write_bytes(kept)
    result = train_agent(MINI, tmp_path, algo="sac", steps=60, resume=True, checkpoint_every=20, **tiny)
    assert result.steps == 60


def test_kept_settings_compare_what_a_record_can_hold(tmp_path: Path) -> None:
    """A dict override is compared key by key (HER adds goal_selection_strategy to replay_buffer_kwargs), and a
    function (a schedule) is not compared by its per-process name: a resume with the same overrides goes on."""
    from redsim.trainers.agents import _check_kept_settings

    recorded = {"replay_buffer_kwargs": {"n_sampled_goal": 2, "goal_selection_strategy": "future"}, "gamma": 0.98}
    _check_kept_settings({"replay_buffer_kwargs": {"n_sampled_goal": 2}, "gamma": 0.98}, recorded, tmp_path)
    _check_kept_settings({"learning_rate": lambda progress: 1e-3 * progress}, {"learning_rate": "<fn>"}, tmp_path)
    with pytest.raises(ValueError, match="cannot resume with overrides"):
        _check_kept_settings({"replay_buffer_kwargs": {"n_sampled_goal": 4}}, recorded, tmp_path)


def test_a_resume_from_an_older_checkpoint_counts_the_wall_time_up_to_it() -> None:
    """The wall time a resumed run starts from: the record's where it stopped at the resumed step, else read off the
    curve (linear between its evaluations), not the dropped later work's."""
    from redsim.trainers.agents import _wall_at

    curve = [{"env_steps": 20, "wall_s": 10.0}, {"env_steps": 40, "wall_s": 30.0}]
    record = {"steps": 60, "wall_s": 50.0}
    assert _wall_at(curve, record, 60) == 50.0 and _wall_at(curve, record, 40) == 30.0
    assert _wall_at(curve, record, 30) == 20.0 and _wall_at(curve, record, 10) == 5.0
    assert _wall_at(curve, record, 80) == 50.0  # a killed run's later checkpoint: at least the record's
    assert _wall_at([], {"wall_s": 7.0}, 20) == 7.0  # a record without its steps: as before


def test_a_user_env_in_a_wrapper_its_copies_would_not_have_is_refused(tmp_path: Path) -> None:
    """The copies are made from the bare env: gym.make's own wrappers stand for them (the TimeLimit's length is
    kept), another wrapper would be dropped silently, so it is refused."""
    from redsim.trainers.agents import train_agent

    made = gym.make(MINI, max_episode_steps=7)
    assert evaluate(made, "scripted", episodes=1).lengths.tolist() == [7]
    wrapped = gym.wrappers.NormalizeObservation(made)
    with pytest.raises(ValueError, match="wrapped in NormalizeObservation"):
        evaluate(wrapped, "scripted", episodes=1)
    with pytest.raises(ValueError, match="wrapped in NormalizeObservation"):
        train_agent(wrapped, tmp_path, algo="sac", steps=20, n_envs=1, video=False)
    assert not any(tmp_path.iterdir())  # refused before anything is written


def test_a_random_episode_is_the_same_whatever_the_episode_count() -> None:
    """Episode i's random actions come from its own generator, so --episodes 2 and 3 share their first two
    episodes (in float64, where the batch size does not move the solves)."""
    exact = {"dtype": "float64", "max_episode_steps": 6}
    two = evaluate(MINI, "random", episodes=2, seed=5, env_kwargs=exact)
    three = evaluate(MINI, "random", episodes=3, seed=5, env_kwargs=exact)
    np.testing.assert_allclose(three.returns[:2], two.returns, rtol=1e-6)


def test_a_dict_observation_model_is_named_as_such() -> None:
    """A plain SB3 model of the goal-conditioned env (dict observations) on the env's array: said plainly, not as a
    shape of None."""
    from stable_baselines3 import SAC

    from redsim.envs.goal import GoalObservation
    from redsim.trainers.agents import SpaceMismatchError, _check_spaces

    model = SAC("MultiInputPolicy", GoalObservation(gym.make(MINI)), buffer_size=100)
    venv = gym.make_vec(MINI, num_envs=1, vectorization_mode="vector_entry_point")
    with pytest.raises(SpaceMismatchError, match=r"dict observations \(achieved_goal, desired_goal, observation\)"):
        _check_spaces(model, venv)


def test_ppo_says_when_whole_rollouts_take_more_steps_than_asked(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """24 steps asked of 8-step rollouts over 2 copies: SB3 finishes the second rollout (32), and the run says so."""
    from redsim.trainers.agents import train_agent

    small = {"n_steps": 8, "batch_size": 16, "n_epochs": 1}
    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "env_kwargs": SHORT, "video": False, "eval_every": 32}
    with caplog.at_level("WARNING", logger="redsim.trainers.agents"):
        result = train_agent(MINI, tmp_path, algo="ppo", steps=24, overrides=small, **tiny)
    assert result.steps == 32 and "this run takes 32, not 24" in caplog.text


def test_a_user_envs_episode_limit_is_recorded_and_checked_on_resume(tmp_path: Path) -> None:
    """A user's env is made by no kwargs, so nothing was recorded: a resume with another TimeLimit went on with
    other episodes without a word (the mesh example's length followed --steps). Its limit is recorded now."""
    from redsim.trainers.agents import model_record, train_agent

    options = {"algo": "sac", "eval_every": 40, "eval_episodes": 1, "final_episodes": 1, "video": False, "n_envs": 1}
    result = train_agent(gym.make(MINI, max_episode_steps=5), tmp_path, steps=40, **options)
    assert model_record(result.model_path)["env_kwargs"] == {"max_episode_steps": 5}
    with pytest.raises(ValueError, match=r"max_episode_steps': 50}: .* trained with \{'max_episode_steps': 5\}"):
        train_agent(gym.make(MINI, max_episode_steps=50), tmp_path, steps=80, resume=True, **options)
    again = train_agent(gym.make(MINI, max_episode_steps=5), tmp_path, steps=80, resume=True, **options)
    assert again.steps == 80


def test_eval_agent_warns_where_an_env_arg_chooses_another_map(
    cli: Callable[..., tuple[int, str, str]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The shipped MiniChain policy on another map of the same latent dimension: the observations keep their shape
    (no SpaceMismatchError) but are another map's coordinates; eval-agent evaluated it without a word."""
    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    short = ("--episodes", "1", "--episode-steps", "2")
    code, _, err = cli("eval-agent", "shipped", MINI, *short, "--env-arg", "max_force=2.0")
    assert code == 0 and "another subspace map" not in err
    other = ("--env-arg", 'scene_params={"density": 8000.0}', "--env-arg", "fit_if_missing=true")
    other += ("--env-arg", 'fit_options={"steps": 20, "hidden_width": 16}')
    code, _, err = cli("eval-agent", "shipped", MINI, *short, *other)
    assert code == 0 and "--env-arg scene_params, fit_options differs from the model's training env" in err
    assert "another subspace map" in err


def test_a_resume_over_a_damaged_replay_buffer_says_what_to_do(
    cli: Callable[..., tuple[int, str, str]], tmp_path: Path
) -> None:
    """A truncated replay_buffer.pkl beside model.zip was a raw UnpicklingError traceback from SB3's loader; it is a
    one-line error naming the file, and deleting it, as the error says, resumes from model.zip without one."""
    from redsim.trainers.agents import train_agent

    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "env_kwargs": SHORT, "video": False}
    train_agent(MINI, tmp_path, algo="sac", steps=20, **tiny)
    buffer = tmp_path / "replay_buffer.pkl"
    buffer.write_bytes(buffer.read_bytes()[:5000])
    args = ("train-agent", MINI, "--steps", "40", "--n-envs", "2", "--out", str(tmp_path), "--resume")
    args += ("--eval-episodes", "1", "--final-episodes", "1", "--episode-steps", "20", "--no-video", "--no-progress")
    code, _, err = cli(*args)
    assert code == 2 and f"the replay buffer {buffer} is damaged" in err and "delete it to resume" in err
    buffer.unlink()
    assert cli(*args)[0] == 0 and model_record(tmp_path / "model.zip")["n_envs"] == 2


def test_a_resume_over_a_damaged_record_names_it(tmp_path: Path) -> None:
    """A truncated agent.json was "redsim: error: Expecting ',' delimiter: line 5 column 31", naming no file."""
    from redsim.trainers.agents import train_agent

    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "env_kwargs": SHORT, "video": False}
    train_agent(MINI, tmp_path, algo="sac", steps=20, **tiny)
    record = tmp_path / "agent.json"
    for damage in (record.read_text()[:100], "[]"):
        record.write_text(damage)
        with pytest.raises(ValueError, match=rf"the run's record {re.escape(str(record))} is damaged .* move it away"):
            train_agent(MINI, tmp_path, algo="sac", steps=40, resume=True, **tiny)


def test_a_resume_over_a_damaged_evaluation_log_warns_and_goes_on(tmp_path: Path, caplog) -> None:
    """SB3's EvalCallback writes evaluations.npz in place, so a hard stop mid-write truncates it; a resume then died
    in a raw BadZipFile traceback. It is taken as no earlier evaluations (as a missing file is), with a warning."""
    from redsim.trainers.agents import train_agent

    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "env_kwargs": SHORT, "video": False}
    train_agent(MINI, tmp_path, algo="sac", steps=20, eval_every=10, **tiny)
    log = tmp_path / "evaluations.npz"
    log.write_bytes(log.read_bytes()[:300])
    with caplog.at_level("WARNING", logger="redsim.trainers.agents"):
        result = train_agent(MINI, tmp_path, algo="sac", steps=40, eval_every=10, resume=True, **tiny)
    assert result.steps == 40 and f"ignoring {log} (BadZipFile" in caplog.text
    with np.load(log) as evaluations:
        assert evaluations["timesteps"].tolist() == [30, 40]


def test_a_model_records_its_map_and_an_evaluation_in_another_warns(tmp_path: Path) -> None:
    """A checkpoint refitted in place (the same --env-arg subspace=PATH) gives observations of the same shapes in
    another map's latent coordinates: the policy was evaluated on them without a word."""
    from redsim.subspace import map_fingerprint
    from redsim.trainers import fit_subspace
    from redsim.trainers.agents import train_agent

    scene = redsim.scenes.build("mini_chain")
    fit_subspace(scene, out=tmp_path / "map", steps=20, hidden_width=16, progress=False)
    mine = {**SHORT, "subspace": str(tmp_path / "map.pt")}
    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "video": False}
    result = train_agent(MINI, tmp_path / "run", algo="sac", steps=20, env_kwargs=mine, **tiny)
    agent = load_agent(result.model_path, MINI)
    assert agent.map == map_fingerprint(redsim.load_subspace(tmp_path / "map.pt", scene=scene))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the map it was trained in: no warning
        evaluate(MINI, agent, episodes=1, env_kwargs=mine)
    fit_subspace(scene, out=tmp_path / "map", steps=20, hidden_width=16, seed=1, overwrite=True, progress=False)
    with pytest.warns(UserWarning, match=rf"trained in the subspace map {agent.map}, and is evaluated in [0-9a-f]+"):
        evaluate(MINI, agent, episodes=1, env_kwargs=mine)


def test_a_resume_in_another_map_is_refused_and_closes_its_envs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run trained in one subspace map resumed in another (a checkpoint refitted in place): the observations keep
    their shapes, so SB3 loaded the model and trained on another map's coordinates; and a resume refused after its
    envs were built left them open."""
    from redsim.envs.sb3 import SB3VecEnv
    from redsim.trainers.agents import train_agent

    tiny = {"n_envs": 2, "eval_episodes": 1, "final_episodes": 1, "env_kwargs": SHORT, "video": False}
    train_agent(MINI, tmp_path, algo="sac", steps=20, **tiny)
    model = tmp_path / "model.zip"
    with zipfile.ZipFile(model) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(members["data"])
    data["redsim_map"] = "0" * len(data["redsim_map"])  # as if trained in another map
    members["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(model, "w") as archive:
        for name, content in members.items():
            archive.writestr(name, content)
    closed = []
    close = SB3VecEnv.close
    monkeypatch.setattr(SB3VecEnv, "close", lambda self: (closed.append(self), close(self))[1])
    with pytest.raises(ValueError, match=r"cannot resume: .*model.zip was trained in the subspace map 0000.* steps in"):
        train_agent(MINI, tmp_path, algo="sac", steps=40, resume=True, **tiny)
    assert len(closed) == 2  # the training copies and the evaluation env
