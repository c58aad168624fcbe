"""`fitted_subspace`: fits what is missing once, reuses it after, skips checkpoints that do not qualify and never
overwrites them."""

from __future__ import annotations

import pytest

from redsim.scenes import build
from redsim.trainers import FitConfig, FitStopped, fit_subspace
from redsim.trainers.cache import fit_key, fitted_subspace

TINY = {"latent_dim": 2, "hidden_width": 8, "hidden_layers": 1, "steps": 4}


def test_fits_once_then_reuses_and_skips_another_d_or_scene(tmp_path) -> None:
    scene, skipped = build("toy_two_tets"), []
    stem = tmp_path / "two"
    first, source = fitted_subspace(scene, FitConfig(**TINY), stem, progress=False, warn=skipped.append)
    assert source == str(stem) + ".pt" and (tmp_path / "two.json").is_file() and not skipped
    stamp = (tmp_path / "two.pt").stat().st_mtime_ns
    again, _ = fitted_subspace(scene, FitConfig(**TINY), stem, progress=False, warn=skipped.append)
    assert (tmp_path / "two.pt").stat().st_mtime_ns == stamp and not skipped  # reused, not refitted
    assert all((a == b).all() for a, b in zip(first.state_dict().values(), again.state_dict().values(), strict=True))

    wider, source = fitted_subspace(
        scene, FitConfig(**{**TINY, "latent_dim": 3}), stem, progress=False, warn=skipped.append
    )
    assert int(wider.latent_dim) == 3 and "latent_dim = 2, not 3" in skipped[-2]
    assert source != str(stem) + ".pt" and (tmp_path / "two.pt").stat().st_mtime_ns == stamp  # fitted beside it
    anchored = FitConfig(**{**TINY, "lam": 3.0})  # any other option of the fit, e.g. after a preset changed
    fitted_subspace(scene, anchored, stem, progress=False, warn=skipped.append)
    assert "lam = 1.0, not 3.0" in skipped[-2]
    count = len(skipped)
    fitted_subspace(
        scene, FitConfig(**{**TINY, "lam": 3.0, "checkpoint_every": 7}), stem, progress=False, warn=skipped.append
    )
    assert len(skipped) == count + 1  # how a fit runs (checkpoints, device) is not what it fits: reused
    fitted_subspace(scene, anchored, stem, seed=1, progress=False, warn=skipped.append)
    assert "seed = 0, not 1" in skipped[-2]  # another seed is another fit

    other = build("toy_tiny_bar_2d")
    count, offered = len(skipped), str(stem) + ".pt"
    fitted_subspace(other, FitConfig(**TINY), tmp_path / "bar", also=[offered], progress=False, warn=skipped.append)
    assert len(skipped) == count + 1 and offered in skipped[-1]  # the two-tets map was offered for the bar, refused


def test_never_overwrites_a_checkpoint_it_cannot_use(tmp_path) -> None:
    scene, skipped = build("toy_two_tets"), []
    short = tmp_path / "short"
    fit_subspace(scene, FitConfig(**{**TINY, "steps": 2}), out=short, progress=False)
    fit_subspace(scene, FitConfig(**TINY), out=short, resume=True, progress=False)  # a user's fit, extended 2 -> 4
    mine = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    _, source = fitted_subspace(scene, FitConfig(**TINY), short, progress=False, warn=skipped.append)
    assert "extended from 2 steps" in skipped[0]  # its rho ramp ran over 2 steps: not a 4-step fit
    keyed = tmp_path / f"short_{fit_key(scene, FitConfig(**TINY), 0)}.pt"
    assert source == str(keyed) and str(keyed) in skipped[1]
    assert all((tmp_path / name).read_bytes() == data for name, data in mine.items())  # the user's fit is intact
    stamp = keyed.stat().st_mtime_ns
    _, again = fitted_subspace(scene, FitConfig(**TINY), short, progress=False, warn=skipped.append)
    assert again == source and keyed.stat().st_mtime_ns == stamp  # reused from the keyed stem

    stiffer = build("toy_two_tets", young=2e4)  # the same name, another scene (two meshes both named mesh_fem)
    _, source = fitted_subspace(stiffer, FitConfig(**TINY), short, progress=False, warn=skipped.append)
    assert source == str(tmp_path / f"short_{fit_key(stiffer, FitConfig(**TINY), 0)}.pt") != str(keyed)
    assert "fitted to scene" in skipped[-2] and keyed.stat().st_mtime_ns == stamp

    _, source = fitted_subspace(scene, FitConfig(**TINY), short, refit=True, progress=False)
    assert source == str(keyed) and keyed.stat().st_mtime_ns != stamp  # a refit replaces the cache's own fit only
    assert all((tmp_path / name).read_bytes() == data for name, data in mine.items())
    for suffix in (".pt", ".json"):  # the keyed stem taken by another fit too: refused, nothing written
        keyed.with_suffix(suffix).write_bytes(mine["short" + suffix])
    with pytest.raises(FileExistsError, match="another fit"):
        fitted_subspace(scene, FitConfig(**TINY), short, progress=False)


def test_a_refit_keeps_an_extension_under_way(tmp_path) -> None:
    """A refit replaces its own finished fit, but not one whose ``--resume --steps N`` extension was interrupted: that
    STEM.fit.pt is the user's work in progress (the refit goes to STEM_KEY)."""
    scene = build("toy_two_tets")
    stem = tmp_path / "mine"
    fit_subspace(scene, FitConfig(**TINY), out=stem, progress=False)
    with pytest.raises(FitStopped):  # extended towards 8 steps, stopped at 6 as a Ctrl-C would
        fit_subspace(scene, FitConfig(**{**TINY, "steps": 8}), out=stem, resume=True, stop_at=6, progress=False)
    mine = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    _, source = fitted_subspace(scene, FitConfig(**TINY), stem, refit=True, progress=False)
    assert source == str(tmp_path / f"mine_{fit_key(scene, FitConfig(**TINY), 0)}.pt")
    assert all((tmp_path / name).read_bytes() == data for name, data in mine.items())  # still resumable to 8
    fit_subspace(scene, FitConfig(**TINY), out=tmp_path / "done", progress=False)
    stamp = (tmp_path / "done.pt").stat().st_mtime_ns
    _, source = fitted_subspace(scene, FitConfig(**TINY), tmp_path / "done", refit=True, progress=False)
    assert source == str(tmp_path / "done.pt") and (tmp_path / "done.pt").stat().st_mtime_ns != stamp  # its own: redone


def test_an_interrupted_fit_is_resumed_not_redone(tmp_path) -> None:
    """A bench's fit stopped by Ctrl-C (here stop_at, which saves as it does) left STEM.fit.pt; the next run fitted
    afresh into STEM_KEY (the work lost, "keeping the other fit at STEM"), and after a second interruption there
    refused both stems as "files of another fit". Now it continues the stopped fit: the map of an uninterrupted one."""
    import torch

    scene, said = build("toy_two_tets"), []
    config = FitConfig(**{**TINY, "steps": 6})
    straight = fit_subspace(scene, config, out=tmp_path / "straight", progress=False).subspace
    stem, keyed = tmp_path / "two", tmp_path / f"two_{fit_key(scene, config, 0)}"
    for at in (stem, keyed):  # two runs stopped, one in each stem
        with pytest.raises(FitStopped):
            fit_subspace(scene, config, out=at, stop_at=4, progress=False)
    subspace, source = fitted_subspace(scene, config, stem, progress=False, warn=said.append)
    assert source == str(stem) + ".pt" and said == [f"resuming the interrupted fit at {stem}.fit.pt (4 of 6 steps)"]
    z = torch.randn(5, 2)
    assert torch.equal(subspace(z), straight(z))
    other = FitConfig(**{**TINY, "steps": 6, "lam": 2.0})  # another fit's stopped state is not continued
    with pytest.raises(FitStopped):
        fit_subspace(scene, other, out=tmp_path / "lam", stop_at=4, progress=False)
    _, source = fitted_subspace(scene, config, tmp_path / "lam", progress=False, warn=said.append)
    assert source == str(tmp_path / f"lam_{fit_key(scene, config, 0)}.pt") and "resuming" not in said[-1]


def test_the_key_names_only_what_differs_from_the_defaults() -> None:
    import dataclasses

    from redsim.trainers import cache

    scene = build("toy_two_tets")
    key = fit_key(scene, FitConfig(**TINY, sigma=1), 0)
    assert key == fit_key(scene, FitConfig(**TINY, sigma=1.0), 0)  # 1 and 1.0 are the same fit
    assert key != fit_key(scene, FitConfig(**TINY, sigma=2.0), 0) != fit_key(scene, FitConfig(**TINY), 1)
    # a field at its default does not enter the key, so one added to FitConfig later leaves old keys as they were
    assert "new_option" not in cache.RUNTIME_FIELDS

    @dataclasses.dataclass(frozen=True)
    class Later(FitConfig):
        new_option: float = 0.5

    assert fit_key(scene, Later(**TINY), 0) == fit_key(scene, FitConfig(**TINY), 0)
    assert fit_key(scene, Later(**TINY, new_option=2.0), 0) != fit_key(scene, FitConfig(**TINY), 0)
