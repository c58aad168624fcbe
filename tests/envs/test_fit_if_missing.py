"""Scene parameters no shipped subspace covers: a clear error, or a fit into the user cache (fit_if_missing)."""

from __future__ import annotations

import copy
import pickle

import gymnasium as gym
import numpy as np
import pytest
import torch

import redsim
from redsim.envs import fitted
from redsim.subspace import CheckpointError

PARAMS = {"density": 8000.0}
"""mini_chain with heavier links (the shipped map is fitted to 7800 kg/m^3)."""
TINY = {"steps": 20, "hidden_width": 16}
"""A fit that takes a second: the test checks the plumbing, not the map's quality."""


@pytest.mark.parametrize(
    ("env_id", "params"), [("RedSim/MiniChain-v0", PARAMS), ("RedSim/BistableBar-v0", {"young": 2e5})]
)
def test_uncovered_scene_parameters_are_a_clear_error(env_id: str, params: dict) -> None:
    with pytest.raises(CheckpointError, match=r"no shipped subspace covers.*fit_if_missing=True"):
        gym.make(env_id, scene_params=params)


def test_default_parameters_use_the_shipped_map_without_fitting(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(fitted, "cached_subspace", lambda *a, **k: pytest.fail("fitted a covered scene"))
    env = gym.make("RedSim/MiniChain-v0", scene_params={"density": 7800.0}, fit_if_missing=True)
    assert env.unwrapped.sim.subspace.metadata["scene_fingerprint"] == env.unwrapped.scene.fingerprint()


def test_fit_options_without_fit_if_missing_are_refused() -> None:
    with pytest.raises(ValueError, match="fit_if_missing=True"):
        gym.make("RedSim/MiniChain-v0", fit_options=TINY)
    # beside a given map nothing is fitted: the options were dropped without a word (a review, helper-206)
    from redsim import pretrained

    with pytest.raises(ValueError, match="with subspace given that map is used as it is and nothing is fitted"):
        gym.make("RedSim/MiniChain-v0", subspace=pretrained.load("mini_chain"), fit_if_missing=True, fit_options=TINY)


def test_a_fit_on_another_device_is_another_cache_entry(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A CUDA fit draws another map, and its training state cannot resume on the CPU: they never share a stem."""
    from redsim import scenes

    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    scene = scenes.build("mini_chain", **PARAMS)
    assert fitted.cache_stem("mini_chain", scene, {**TINY, "device": "cuda"}) != fitted.cache_stem(
        "mini_chain", scene, TINY
    )


def test_bad_fit_options_are_a_clear_error(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    with pytest.raises(ValueError, match="unknown fit option"):
        gym.make("RedSim/MiniChain-v0", scene_params=PARAMS, fit_if_missing=True, fit_options={"stepz": 3})
    # the fitter's own arguments, which the cache sets: a TypeError "got multiple values for keyword argument"
    for option in ({"progress": False}, {"out": str(tmp_path / "x")}, {"resume": True}):
        with pytest.raises(ValueError, match=r"fit_options cannot set \['(progress|out|resume)'\]"):
            gym.make("RedSim/MiniChain-v0", scene_params=PARAMS, fit_if_missing=True, fit_options=option)


def test_fit_if_missing_fits_into_the_user_cache_with_a_progress_bar_then_reuses_it(
    tmp_path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    env = gym.make("RedSim/MiniChain-v0", scene_params=PARAMS, fit_if_missing=True, fit_options=TINY)
    assert "fit mini_chain" in capsys.readouterr().err  # tqdm's bar
    scene = env.unwrapped.scene
    saved = sorted(p.name for p in (tmp_path / fitted.FOLDER).iterdir())
    assert len(saved) == 2 and saved[0].endswith(".json") and saved[1].endswith(".pt")  # no training state left
    assert scene.fingerprint() in saved[0]
    assert env.unwrapped.sim.subspace.metadata["scene_fingerprint"] == scene.fingerprint()
    env.reset(seed=0)
    obs, _, _, _, info = env.step(np.ones(3, np.float32))
    assert np.all(np.isfinite(obs)) and np.isfinite(info["energy"])

    monkeypatch.setattr("redsim.trainers.fit.fit_subspace", lambda *a, **k: pytest.fail("fitted again"))
    again = gym.make("RedSim/MiniChain-v0", scene_params=PARAMS, fit_if_missing=True, fit_options=TINY)
    assert again.unwrapped.sim.subspace.metadata["scene_fingerprint"] == scene.fingerprint()


def test_with_the_cache_off_the_fit_stays_in_memory(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("REDSIM_CACHE", "0")
    monkeypatch.chdir(tmp_path)
    env = gym.make("RedSim/MiniChain-v0", scene_params=PARAMS, fit_if_missing=True, fit_options=TINY)
    env.reset(seed=0)
    assert not list(tmp_path.iterdir())


def test_an_env_fitted_in_memory_copies_with_its_map_instead_of_fitting_again(monkeypatch: pytest.MonkeyPatch) -> None:
    """With the cache off no file backs the map: pickle and deepcopy carry it, and the copy steps bit for bit alike;
    a shipped map's env still pickles without its weights (the copy loads the file)."""
    monkeypatch.setenv("REDSIM_CACHE", "0")
    env = gym.make("RedSim/MiniChain-v0", scene_params=PARAMS, fit_if_missing=True, fit_options=TINY)
    env.reset(seed=0)
    env.step(np.full(3, 0.3, np.float32))
    monkeypatch.setattr("redsim.trainers.fit.fit_subspace", lambda *a, **k: pytest.fail("fitted again"))
    clones = [pickle.loads(pickle.dumps(env)), copy.deepcopy(env)]
    clones.append(pickle.loads(pickle.dumps(clones[0])))  # a copy's copy carries the map too
    push = np.full(3, 0.7, np.float32)
    obs, reward, *_ = env.step(push)
    for clone in clones:
        clone_obs, clone_reward, *_ = clone.step(push)
        assert np.array_equal(clone_obs, obs) and clone_reward == reward
    assert len(pickle.dumps(env)) > _weights(env)
    shipped = gym.make("RedSim/MiniChain-v0")
    assert len(pickle.dumps(shipped)) < _weights(shipped)


def _weights(env: gym.Env) -> int:
    """Bytes of the env's map's pickled weights."""
    return len(pickle.dumps(env.unwrapped.sim.subspace.state_dict()))


def test_a_sharded_env_fitted_in_memory_sends_its_map_to_the_workers(monkeypatch: pytest.MonkeyPatch) -> None:
    """With the cache off, ``shards=2`` fits once (here) and each worker builds its copies from that map: the build a
    worker unpickles makes its env without fitting."""
    from redsim.envs import vector

    monkeypatch.setenv("REDSIM_CACHE", "0")
    made = {}

    class Recorded(Exception):
        """Raised in place of starting the workers, once what they would be sent is recorded."""

    def record(build, template, *args, **kwargs):
        made.update(build=build, template=template)
        raise Recorded

    monkeypatch.setattr(vector, "ShardedVectorEnv", record)
    with pytest.raises(Recorded):
        gym.make_vec(
            "RedSim/MiniChain-v0",
            num_envs=2,
            vectorization_mode="vector_entry_point",
            shards=2,
            scene_params=PARAMS,
            fit_if_missing=True,
            fit_options=TINY,
        )
    monkeypatch.setattr("redsim.trainers.fit.fit_subspace", lambda *a, **k: pytest.fail("a worker fitted again"))
    shard = pickle.loads(pickle.dumps(made["build"]))(1)  # what a worker runs
    template = made["template"].sim.subspace
    for mine, theirs in zip(template.state_dict().values(), shard.sim.subspace.state_dict().values(), strict=True):
        assert torch.equal(mine, theirs)


def test_dim_in_fit_options_replaces_the_recorded_latent_dim(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``dim`` (fit_subspace's alias of latent_dim) was merged beside the preset's (now the shipped record's)
    latent_dim and refused as two values that differ; it is the same cache entry as latent_dim."""
    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    scene = redsim.scenes.build("mini_chain", **PARAMS)
    by_alias = fitted.cached_subspace("mini_chain", scene, {**TINY, "dim": 2}, progress=False)
    assert by_alias.latent_dim == 2
    monkeypatch.setattr("redsim.trainers.fit.fit_subspace", lambda *a, **k: pytest.fail("fitted again"))
    by_field = fitted.cached_subspace("mini_chain", scene, {**TINY, "latent_dim": 2}, progress=False)
    assert by_field.latent_dim == 2  # loaded from the cache entry the alias made


def test_a_cache_that_cannot_hold_the_fit_fits_in_memory_with_a_warning(tmp_path, monkeypatch) -> None:
    """$REDSIM_CACHE naming a file: the fit's save failed with a raw NotADirectoryError after the whole fit; the other
    caches only warn, and so does this one now, fitting in memory."""
    blocker = tmp_path / "afile"
    blocker.write_text("not a folder")
    monkeypatch.setenv("REDSIM_CACHE", str(blocker))
    scene = redsim.scenes.build("mini_chain", **PARAMS)
    with pytest.warns(UserWarning, match="cannot hold this fit .* fitting in memory"):
        subspace = fitted.cached_subspace("mini_chain", scene, TINY, progress=False)
    assert getattr(subspace, fitted.IN_MEMORY_ATTRIBUTE) and blocker.read_text() == "not a folder"


@pytest.mark.parametrize("scene_name", ["chain", "bistable_bar"])
def test_the_cache_fits_as_the_shipped_map_was_fitted_not_the_moved_on_preset(
    scene_name: str, tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Stop 46 lengthened these presets (1.6*10^5 and 8*10^4 steps, maps the envs step 2-3x slower on); an env's
    uncovered parameters took that preset, a ~12-minute fit. The cache fits the shipped map's recorded options."""
    from redsim import pretrained, scenes
    from redsim.trainers.presets import preset

    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    seen = {}

    class Recorded(Exception):
        """Raised in place of fitting, once the options are recorded."""

    def record(scene, **options):
        seen.update(options)
        raise Recorded

    monkeypatch.setattr("redsim.trainers.fit.fit_subspace", record)
    scene = scenes.build(scene_name, density=scenes.build(scene_name).params["density"] * 1.1)
    with pytest.raises(Recorded):
        fitted.cached_subspace(scene_name, scene, {"hidden_layers": 4}, progress=False)
    shipped = pretrained.fit_record(scene_name)
    assert seen["steps"] == shipped["steps"] == 10000 != preset(scene_name)["steps"]
    assert seen["hidden_layers"] == 4  # fit_options still override
    assert seen.get("anchor", 0.0) == shipped.get("anchor", 0.0) and seen["seed"] == shipped["seed"]
    assert "checkpoint_every" not in seen and "device" not in seen  # speed and device are the fitter's defaults


def test_a_scene_whose_preset_fits_its_shipped_map_keeps_its_cache_entries(tmp_path, monkeypatch) -> None:
    """Where the preset still fits the shipped map (the mini chain), the cache entry keeps the name it had when the
    envs fitted presets: a user's cached fit is found, not fitted again."""
    from redsim import scenes
    from redsim.trainers.presets import preset

    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    scene = scenes.build("mini_chain", **PARAMS)
    before = fitted.cache_stem("mini_chain", scene, {**preset("mini_chain"), **TINY})
    made = fitted.cached_subspace("mini_chain", scene, TINY, progress=False)
    assert before.with_suffix(".pt").is_file() and made.latent_dim == preset("mini_chain")["latent_dim"]


@pytest.mark.parametrize("damaged", [".pt", ".json", ".fit.pt"])
def test_a_damaged_cache_entry_is_an_error_naming_the_files_to_delete(tmp_path, monkeypatch, damaged: str) -> None:
    """A truncated cached map (or an interrupted fit's training state) was a CheckpointError naming the file but not
    that it is the user cache's, nor what to do; it says which files to delete, and deleting them fits again."""
    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    scene = redsim.scenes.build("mini_chain", **PARAMS)
    fitted.cached_subspace("mini_chain", scene, TINY, progress=False)
    stem = fitted.cache_stem("mini_chain", scene, {**fitted._shipped_recipe("mini_chain"), **TINY})
    if damaged == ".fit.pt":  # a fit killed mid-way: its state, no map yet
        stem.with_name(stem.name + ".pt").rename(stem.with_name(stem.name + ".fit.pt"))
    path = stem.with_name(stem.name + damaged)
    path.write_bytes(path.read_bytes()[:300])
    with pytest.raises(CheckpointError, match=r"user cache.*: delete .*(\.pt and .*\.json to fit it again|\.fit\.pt)"):
        gym.make("RedSim/MiniChain-v0", scene_params=PARAMS, fit_if_missing=True, fit_options=TINY)
    for suffix in (".pt", ".json", ".fit.pt"):  # as the message says
        stem.with_name(stem.name + suffix).unlink(missing_ok=True)
    assert fitted.cached_subspace("mini_chain", scene, TINY, progress=False).latent_dim > 0


def test_an_interrupted_cache_fit_resumes_to_the_map_an_uninterrupted_one_makes(tmp_path, monkeypatch) -> None:
    """A fit stopped mid-way (Ctrl-C saves STEM.fit.pt so) leaves no map that loads as if whole: the next env
    resumes it from its training state, to the same weights as a fit never stopped, and removes the state."""
    from redsim.trainers import fit

    scene = redsim.scenes.build("mini_chain", **PARAMS)
    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path / "whole"))
    whole = fitted.cached_subspace("mini_chain", scene, TINY, progress=False)
    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path / "stopped"))
    options = {**fitted._shipped_recipe("mini_chain"), **TINY}
    stem = fitted.cache_stem("mini_chain", scene, options)
    with pytest.raises(fit.FitStopped):
        fit.fit_subspace(scene, out=stem, stop_at=7, progress=False, **options)
    assert sorted(p.name for p in stem.parent.iterdir()) == [stem.name + ".fit.pt"]
    calls = []
    real = fit.fit_subspace
    monkeypatch.setattr(fit, "fit_subspace", lambda *a, **k: calls.append(k["resume"]) or real(*a, **k))
    env = gym.make("RedSim/MiniChain-v0", scene_params=PARAMS, fit_if_missing=True, fit_options=TINY)
    assert calls == [True] and not stem.with_name(stem.name + ".fit.pt").exists()
    resumed = env.unwrapped.sim.subspace.state_dict()
    assert all(torch.equal(value, resumed[key]) for key, value in whole.state_dict().items())


def test_a_training_state_another_worker_removes_before_the_resume_loads_it_is_no_error(tmp_path, monkeypatch) -> None:
    """SubprocVecEnv workers fit one map: a worker that saw STEM.fit.pt resumes it, but another one that finished
    the fit (or started it over) may remove it first; that was a ValueError "nothing to resume" for the env."""
    from redsim.trainers import fit

    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    scene = redsim.scenes.build("mini_chain", **PARAMS)
    options = {**fitted._shipped_recipe("mini_chain"), **TINY}
    stem = fitted.cache_stem("mini_chain", scene, options)
    with pytest.raises(fit.FitStopped):
        fit.fit_subspace(scene, out=stem, stop_at=7, progress=False, **options)
    calls, real = [], fit.fit_subspace

    def other_worker_first(*args, **kwargs):
        calls.append(kwargs["resume"])
        if kwargs["resume"]:
            stem.with_name(stem.name + ".fit.pt").unlink()  # the other worker's overwrite=True start
        return real(*args, **kwargs)

    monkeypatch.setattr(fit, "fit_subspace", other_worker_first)
    subspace = fitted.cached_subspace("mini_chain", scene, TINY, progress=False)
    assert calls == [True, False] and subspace.metadata["scene_fingerprint"] == scene.fingerprint()
