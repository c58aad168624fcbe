"""Fit presets: kept with the fitter, keyed by the scene registry's names."""

from __future__ import annotations

import redsim
from redsim.trainers import FitConfig
from redsim.trainers.presets import PRESETS, preset


def test_every_catalog_scene_has_a_valid_preset() -> None:
    assert set(PRESETS) == set(redsim.scenes.names()) - set(redsim.scenes.names("toy"))
    for name in PRESETS:
        FitConfig(**preset(name))  # every field exists and passes FitConfig's checks
    assert preset("toy_two_tets") == {}
