"""Full-space reference equilibria (saddle escapes) and their memory and disk cache."""

from __future__ import annotations

import logging
import warnings
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from redsim import metrics, scenes
from redsim.integrators import cache, reference, static_equilibrium
from redsim.scene import Scene
from redsim.subspace import LinearSubspace

pytestmark = pytest.mark.usefixtures("equilibrium_cache")


def _identity(scene: Scene) -> LinearSubspace:
    """f(z) = q_seed + z over all free DOFs (float64)."""
    return LinearSubspace(torch.eye(scene.free_dof_count, dtype=torch.float64), scene.q_seed)


def test_full_equilibria_are_kept_on_disk(count_solves: Callable[[], list[int]], equilibrium_cache: Path) -> None:
    scene = scenes.build("toy_two_tets")
    calls = count_solves()
    first = metrics.load_response_error(scene, _identity(scene), count=2, restarts=0)
    assert len(calls) == 3 and len(list(equilibrium_cache.glob("*.npz"))) == 3  # the rest equilibrium and 2 loads
    cache.clear_cache()  # a new process: only the disk cache is left
    again = metrics.load_response_error(scene, _identity(scene), count=2, restarts=0)
    assert len(calls) == 3 and again == first
    rest = reference.full_equilibrium(scene)
    assert rest[1] and rest[0].dtype == torch.float64 and rest[0].shape == (scene.free_dof_count,)
    other = scenes.build("toy_two_tets", gravity=False)  # other content, other key
    metrics.load_response_error(other, _identity(other), count=1, restarts=0)
    assert len(calls) == 5
    cache.clear_cache(disk=True)
    assert not list(equilibrium_cache.glob("*.npz"))


def test_a_damagedequilibrium_cache_entry_is_solved_again(
    count_solves: Callable[[], list[int]], caplog: pytest.LogCaptureFixture, equilibrium_cache: Path
) -> None:
    scene = scenes.build("toy_two_tets")
    q, converged, energy = reference.full_equilibrium(scene)
    (path,) = equilibrium_cache.glob("*.npz")
    calls = count_solves()
    for damage in (b"not a zip file", path.read_bytes()[:100], b""):
        path.write_bytes(damage)
        cache.clear_cache()
        with caplog.at_level(logging.WARNING, logger="redsim"):
            again = reference.full_equilibrium(scene)
        assert "ignoring unreadable equilibrium cache file" in caplog.text
        caplog.clear()
        torch.testing.assert_close(again[0], q, rtol=0.0, atol=0.0)
        assert again[1:] == (converged, energy)
    assert len(calls) == 3
    cache.clear_cache()
    reference.full_equilibrium(scene)  # the rewritten entry is good again
    assert len(calls) == 3 and not caplog.records


def test_theequilibrium_cache_can_be_turned_off_and_never_breaks_a_run(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, tmp_path: Path
) -> None:
    scene = scenes.build("toy_two_tets")
    for off in ("0", "off", ""):
        monkeypatch.setenv(cache.CACHE_ENV, off)
        assert cache.cache_directory() is None
    monkeypatch.setenv(cache.CACHE_ENV, "0")
    reference.full_equilibrium(scene)
    assert not any(tmp_path.rglob("*.npz"))
    monkeypatch.delenv(cache.CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache.cache_directory() == tmp_path / "xdg" / "redsim" / "equilibria"
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache folder should be")
    monkeypatch.setenv(cache.CACHE_ENV, str(blocker))
    cache.clear_cache()
    with caplog.at_level(logging.WARNING, logger="redsim"):
        _, converged, _ = reference.full_equilibrium(scene)
    assert converged and "could not write the equilibrium cache file" in caplog.text


def test_full_equilibria_leave_saddles() -> None:
    scene = scenes.build("mini_chain").to(dtype=torch.float64)
    saddle, info = static_equilibrium(scene, tol=reference.FULL_TOL)  # Newton from the seed stops at a saddle
    assert info.converged and reference._negative_curvature(scene, saddle, None, None) is not None
    rest, converged, energy = reference.full_equilibrium(scene)
    assert converged and energy < info.energy - 1e-3
    assert reference._negative_curvature(scene, rest, None, None) is None


def test_a_float32_scene_and_a_float32_start_are_solved_in_float64() -> None:
    """full_equilibrium of a float32 scene was a RuntimeError ("expected scalar type Float but found Double"), a
    review's finding; rest_state cast it, full_equilibrium did not."""
    scene = scenes.build("toy_two_tets")
    single = scene.to(dtype=torch.float32)
    rest, converged, energy = reference.full_equilibrium(single, start=single.q_seed)
    expected, _, expected_energy = reference.full_equilibrium(scene)
    assert converged and rest.dtype == torch.float64
    torch.testing.assert_close(rest, expected, rtol=0.0, atol=1e-7)
    assert energy == pytest.approx(expected_energy, rel=1e-6)
    with pytest.raises(ValueError, match="start must be finite"):
        reference.full_equilibrium(scene, start=torch.full_like(scene.q_seed, float("nan")))


def test_rest_or_warn_names_what_is_built_on_an_unconverged_rest(monkeypatch: pytest.MonkeyPatch) -> None:
    """The modal baselines, an anchored map's polynomial and the chain scenarios take the full-space rest as an
    equilibrium; where its solve did not converge they used the last iterate silently (helper-222's lead)."""
    from redsim.trainers.anchored import anchor_polynomial

    scene = scenes.build("mini_chain")
    q, converged = reference.rest_state(scene)
    assert converged
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert torch.equal(reference.rest_or_warn(scene, "the modes"), q)  # converged: silent
    monkeypatch.setattr(reference, "full_equilibrium", lambda *args, **kwargs: (q, False, 0.0))
    with pytest.warns(RuntimeWarning, match="rest of scene 'mini_chain' did not converge.*the modes uses its last"):
        assert torch.equal(reference.rest_or_warn(scene, "the modes"), q)
    with pytest.warns(RuntimeWarning, match="the anchored map's 'modes' polynomial"):
        anchor_polynomial(scene, 2, 1.0, "modes")
