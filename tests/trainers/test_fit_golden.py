"""Golden fit: a short float64 fit of a toy scene gives the stored losses and map outputs.

Every checkpoint records the ``redsim fit`` command that rebuilds its weights (bit for bit on the same kind of CPU:
``tests/pretrained``), yet the fast tests of the fitter check its pieces by hand and that two fits in one process
agree, not that a fit computes what it did: a change of the order of the random draws, of the initialisation or of a
schedule passed them all. ``tests/data/golden/fit_toy_two_tets.json`` holds the per-step losses of :data:`CONFIG`
(toy_two_tets, seed 5, one periodic latent, 8 steps) and the fitted map at :func:`probe_latents`.

Tolerances, float64: runs on one machine agree bit for bit (one thread or two, fused or plain Adam); another CPU's
or BLAS's round-off is ~1e-16 relative per operation, far below :data:`LOSS_RTOL` and :data:`MAP_ATOL`, which sit
orders of magnitude below what a learning rate 1e-6 larger moves
(:func:`test_the_tolerance_catches_a_learning_rate_one_millionth_larger`). One exception, measured in stop 68: the
map's initial weights are drawn in float32 (torch's ``uniform_``), whose scalar kernels
(``ATEN_CPU_CAPABILITY=default``, a CPU without AVX2) round some draws one float32 ulp (6e-8) away from the AVX2 and
AVX-512 kernels', and the losses then differ by up to 6.6e-8 relative: this test fails there (AVX2 and AVX-512 pass).

A deliberate change of what a fit computes also means the recorded commands of the maps fitted before it no longer
rebuild them bit for bit: say so in the change, and regenerate the file with::

    python tests/trainers/test_fit_golden.py --update
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from redsim import scenes
from redsim.trainers import FitConfig, fit_subspace

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden" / "fit_toy_two_tets.json"
SCENE = "toy_two_tets"
SEED = 5
CONFIG = {
    "latent_dim": 2,
    "sigma": 0.05,
    "steps": 8,
    "batch_size": 8,
    "hidden_width": 8,
    "hidden_layers": 2,
    "periodic": (1,),
    "dtype": "float64",
}
LOSS_RTOL = 1e-10
"""Largest relative difference of a step's loss from the stored one (a learning rate 1e-6 larger: 2.8e-8)."""
MAP_ATOL = 1e-11
"""Largest |q - q_golden| [m] of the map at the probe latents (|q| <= 0.65; a learning rate 1e-6 larger: 8.6e-9)."""


def probe_latents() -> torch.Tensor:
    """Three fixed latents [3, 2], float64."""
    return torch.linspace(-1.0, 1.0, 6, dtype=torch.float64).reshape(3, 2)


def golden_fit(**changes: Any) -> dict[str, np.ndarray]:
    """The per-step ``losses`` [steps] and the map's ``q`` [3, n] at :func:`probe_latents` of :data:`CONFIG`'s fit."""
    with warnings.catch_warnings():  # 8 steps leave a map that spreads its samples little: said, and not the point
        warnings.simplefilter("ignore", UserWarning)
        result = fit_subspace(scenes.build(SCENE), FitConfig(**{**CONFIG, **changes}), seed=SEED, progress=False)
    with torch.no_grad():
        q = result.subspace(probe_latents())
    return {"losses": np.array([h["loss"] for h in result.history]), "q": q.numpy()}


def _load() -> dict[str, np.ndarray]:
    doc = json.loads(GOLDEN.read_text())
    return {"losses": np.array(doc["losses"]), "q": np.array(doc["q"])}


def test_a_short_fit_matches_its_golden_losses_and_map() -> None:
    gold, run = _load(), golden_fit()
    assert run["losses"].shape == gold["losses"].shape and run["q"].shape == gold["q"].shape
    assert abs(gold["losses"][-1] - gold["losses"][0]) > 1e6 * LOSS_RTOL * abs(gold["losses"][0])  # the fit moves
    np.testing.assert_allclose(run["losses"], gold["losses"], rtol=LOSS_RTOL, atol=0.0)
    np.testing.assert_allclose(run["q"], gold["q"], rtol=0.0, atol=MAP_ATOL)


def test_the_tolerance_catches_a_learning_rate_one_millionth_larger() -> None:
    gold, run = _load(), golden_fit(learning_rate=FitConfig().learning_rate * (1.0 + 1e-6))
    assert np.max(np.abs(run["losses"] - gold["losses"]) / np.abs(gold["losses"])) > 100 * LOSS_RTOL  # measured 2.8e-8
    assert np.abs(run["q"] - gold["q"]).max() > 100 * MAP_ATOL  # measured 8.6e-9


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=f"Regenerate {GOLDEN}.")
    parser.add_argument("--update", action="store_true", help="write the file (required: nothing is written without)")
    if not parser.parse_args(argv).update:
        parser.error("pass --update to rewrite the golden fit")
    torch.set_num_threads(1)  # the tests' setting (tests/conftest.py)
    run = golden_fit()
    doc = {"scene": SCENE, "seed": SEED, "config": CONFIG, "losses": run["losses"].tolist(), "q": run["q"].tolist()}
    GOLDEN.write_text(json.dumps(doc, indent=1) + "\n")
    losses = run["losses"]
    print(f"wrote {GOLDEN.name}: losses {losses[0]:.6g} -> {losses[-1]:.6g} over {len(losses)} steps")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
