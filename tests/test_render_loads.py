"""``redsim draw``'s load arrows point along their forces (hand mutation audit, helper-281: reversing them in
redsim/render.py _draw_loads passed tests/test_cli.py, tests/test_cli_fit.py and tests/test_cli_errors.py, which
check only that a picture is written)."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.figure import Figure

from redsim import render, scenes


@pytest.mark.parametrize("force", [[30.0, 0.0], [0.0, -30.0], [-20.0, 20.0]])
def test_a_load_arrow_leaves_its_handle_along_the_force(force: list[float]) -> None:
    scene = scenes.build("toy_tiny_bar_2d")
    handle = scene.handles[0]
    at = handle.position(scene.full_positions(scene.q_seed[None]))[0].numpy()
    ax = Figure().add_subplot()  # as draw_states draws (no pyplot)
    render._draw_loads(ax, scene, scene.q_seed, {handle.name: force}, half=1.0)
    (arrow,) = [t for t in ax.texts if hasattr(t, "xyann")]
    (label,) = [t for t in ax.texts if not hasattr(t, "xyann")]
    tail, head = np.asarray(arrow.xyann), np.asarray(arrow.xy)
    np.testing.assert_allclose(tail, at)
    direction = np.asarray(force) / np.linalg.norm(force)
    np.testing.assert_allclose((head - tail) / np.linalg.norm(head - tail), direction, atol=1e-12)
    assert np.dot(np.asarray(label.get_position()) - at, direction) > 0.0
    assert label.get_text() == f"{handle.name}: {np.linalg.norm(force):.3g} N"
