"""`fitted_subspace`: fits what is missing once, reuses it after, and skips checkpoints that do not qualify."""

from __future__ import annotations

from redsim.scenes import build
from redsim.trainers import FitConfig, fit_subspace
from redsim.trainers.cache import fitted_subspace

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

    wider, _ = fitted_subspace(scene, FitConfig(**{**TINY, "latent_dim": 3}), stem, progress=False, warn=skipped.append)
    assert int(wider.latent_dim) == 3 and "latent_dim = 2, not 3" in skipped[-1]
    anchored = FitConfig(**{**TINY, "lam": 3.0})  # any other option of the fit, e.g. after a preset changed
    fitted_subspace(scene, anchored, stem, progress=False, warn=skipped.append)
    assert "lam = 1.0, not 3.0" in skipped[-1]
    fitted_subspace(
        scene, FitConfig(**{**TINY, "lam": 3.0, "checkpoint_every": 7}), stem, progress=False, warn=skipped.append
    )
    assert len(skipped) == 2  # how a fit runs (checkpoints, device) is not what it fits: reused
    fitted_subspace(scene, anchored, stem, seed=1, progress=False, warn=skipped.append)
    assert "seed = 0, not 1" in skipped[-1]  # another seed is another fit

    short = tmp_path / "short"
    fit_subspace(scene, FitConfig(**{**TINY, "steps": 2}), out=short, progress=False)
    fit_subspace(scene, FitConfig(**TINY), out=short, resume=True, progress=False)  # extended 2 -> 4 steps
    fitted_subspace(scene, FitConfig(**TINY), short, progress=False, warn=skipped.append)
    assert "extended from 2 steps" in skipped[-1]  # its rho ramp ran over 2 steps: not a 4-step fit

    other = build("toy_tiny_bar_2d")
    count, offered = len(skipped), str(stem) + ".pt"
    fitted_subspace(other, FitConfig(**TINY), tmp_path / "bar", also=[offered], progress=False, warn=skipped.append)
    assert len(skipped) == count + 1 and offered in skipped[-1]  # the two-tets map was offered for the bar, refused
