"""The scene registry: one entry per named scene, and every other list of scenes derived from it."""

from __future__ import annotations

import pytest

import redsim
from redsim import metrics, pretrained
from redsim.scenes import ENTRIES, TAGS, SceneEntry
from redsim.scenes.registry import resolve
from redsim.scenes.testing import two_tets


def test_entries_are_the_scene_list() -> None:
    assert list(redsim.scenes.SCENES) == list(ENTRIES) == redsim.scenes.names()
    assert all(set(e.tags) <= set(TAGS) for e in ENTRIES.values())
    assert all(name.startswith("toy_") == ("toy" in e.tags) for name, e in ENTRIES.items())


def test_names_by_tag() -> None:
    assert redsim.scenes.names("env") == list(pretrained.ENV_SCENES)
    assert "stiff_body" in redsim.scenes.names("bench-fit") and "hetero_beam" not in redsim.scenes.names("table1")
    with pytest.raises(ValueError, match=r"unknown scene tag 'nope'; valid tags: \['table1', 'env'"):
        redsim.scenes.names("nope")
    with pytest.raises(ValueError, match=r"unknown scene 'nope'; valid scenes: \['cloth_ball'"):
        redsim.scenes.entry("nope")
    for path in ("sheet.obj", "subspaces/part.json", "out/fit.pt"):  # a file given where a scene name goes
        with pytest.raises(
            ValueError, match=r"\(a path: build a mesh file's scene with fem_scene_from_mesh, tet_scene_from_mesh or "
        ):
            redsim.envs.make(path)
    assert not redsim.scenes.looks_like_a_path("chain")
    for env_id in ("RedSim/MiniChain-v0", "redsim:RedSim/Chain-v0"):  # not a path (helper-194's finding)
        with pytest.raises(ValueError, match=r"\(an env id: gymnasium.make makes it; here a scene goes\)"):
            redsim.envs.make(env_id)


def test_bad_entries_are_refused() -> None:
    with pytest.raises(ValueError, match=r"scene 'x': unknown tag\(s\) \['big'\]"):
        SceneEntry("x", two_tets, tags=("big",))
    with pytest.raises(ValueError, match="module:function"):
        SceneEntry("x", two_tets, reference_states="redsim.metrics.buckled_states")
    with pytest.raises(ValueError, match=r"cannot resolve 'redsim.metrics:no_such'"):
        resolve("redsim.metrics:no_such")
    with pytest.raises(ValueError, match="is not callable"):
        resolve("redsim.scenes:TAGS")


def test_declared_reference_states_resolve() -> None:
    declared = {name: e.reference_states for name, e in ENTRIES.items() if e.reference_states}
    assert declared == {"bistable_bar": "redsim.metrics:buckled_states"}
    assert resolve(declared["bistable_bar"]) is metrics.buckled_states
    assert SceneEntry("x", two_tets).compute_reference_states(two_tets()) is None


def test_a_subspace_ships_exactly_for_the_environment_scenes() -> None:
    assert set(pretrained.names()) == set(redsim.scenes.names("env"))


def _tiny_fit(scene: redsim.Scene, **config: object) -> object:
    from redsim.trainers import FitConfig, fit_subspace

    return fit_subspace(scene, FitConfig(steps=5, hidden_width=16, hidden_layers=1, **config), progress=False).subspace


@pytest.mark.slow
def test_the_bench_loop_check_uses_the_declared_crank() -> None:
    from redsim.bench import compare_subspaces

    scene = redsim.scenes.build("klann")
    out = compare_subspaces(scene, _tiny_fit(scene, latent_dim=1, periodic=(0,)), sigma=0.05, loads_count=1, samples=8)
    assert out["neural"]["loop"]["samples"] == 360 and "loop" not in out["modes"]  # modes have no periodic latent
    assert all("reach" not in result for result in out.values())


def test_the_bench_reach_check_uses_the_declared_reference_states() -> None:
    from redsim.bench import compare_subspaces

    scene = redsim.scenes.build("bistable_bar", cells_x=12, cells_y=2)
    out = compare_subspaces(scene, _tiny_fit(scene, latent_dim=2), sigma=0.05, loads_count=1, samples=8)
    assert all(len(result["reach"]["errors"]) == 2 and "loop" not in result for result in out.values())
