"""Markers and arrows are placed by ``SceneView.project``; it must put a point where the surface is drawn (hand
mutation audit, helper-281: projecting y downside up passed tests/test_raster.py and tests/envs/test_render.py, whose
marker checks read the pixel at ``project``'s own answer)."""

from __future__ import annotations

import numpy as np
import pytest

from redsim import scenes
from redsim.raster import SceneView


@pytest.mark.parametrize(("name", "above"), [("toy_tiny_bar_2d", [0.0, 1.0]), ("mini_chain", [0.0, 0.3, 0.0])])
def test_a_point_of_the_body_projects_onto_its_drawn_pixels(name: str, above: list[float]) -> None:
    scene = scenes.build(name)
    x = scene.full_positions(scene.q_seed[None])
    surfaces = [(np.asarray(s.points.positions(x)[0], dtype=np.float64), s.faces.numpy()) for s in scene.surfaces]
    points = np.concatenate([p for p, _ in surfaces])
    centroids = np.concatenate([p[f].mean(1) for p, f in surfaces])  # inside the drawn triangles
    # a frame that also holds a point well above the body: the body lies in the picture's lower part
    top = points.max(0) + np.asarray(above)
    view = SceneView(scene, scene.q_seed, width=160, height=160, margin=0.05, extra_points=top[None])
    picture = view.draw(scene.q_seed)
    background = picture[0, 0]
    drawn = (picture != background).any(-1)
    xy = np.floor(view.project(centroids)[:, :2]).astype(int)
    inside = (xy >= 0).all(1) & (xy[:, 0] < 160) & (xy[:, 1] < 160)
    hits = drawn[xy[inside, 1], xy[inside, 0]]
    assert inside.all() and hits.mean() > 0.9, hits.mean()
    # and image rows grow downwards: the point above the body projects above it
    assert view.project(top[None])[0, 1] < view.project(points)[:, 1].min()
