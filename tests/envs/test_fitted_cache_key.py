"""The user-cache key of an env's fitted map (:func:`redsim.envs.fitted.cache_stem`), from a hand mutation audit:
``device="cpu"`` (the default) and the speed-only options leave the key as it is, another device changes it (a GPU
fit is another map), and so does any option that changes the map."""

from __future__ import annotations

import pytest

from redsim import scenes
from redsim.envs.fitted import cache_stem


def test_the_cache_key_ignores_cpu_and_speed_only_options_but_not_a_gpu(
    tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    scene = scenes.build("toy_crank")
    base = cache_stem("toy_crank", scene, {"steps": 5, "latent_dim": 1})
    assert base is not None and base.parent == tmp_path / "subspaces" and base.name.startswith("toy_crank-")
    same = {"device": "cpu", "checkpoint_every": 2, "fused_adam": True, "compile": True}
    assert cache_stem("toy_crank", scene, {"steps": 5, "latent_dim": 1, **same}) == base
    assert cache_stem("toy_crank", scene, {"steps": 5, "latent_dim": 1, "device": "cuda"}) != base
    assert cache_stem("toy_crank", scene, {"steps": 6, "latent_dim": 1}) != base
    monkeypatch.setenv("REDSIM_CACHE", "off")
    assert cache_stem("toy_crank", scene, {"steps": 5}) is None
