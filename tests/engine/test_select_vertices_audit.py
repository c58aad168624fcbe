"""``redsim.scenes.toolkit.select_vertices`` (the pins and handles of a user's mesh) on inputs the hand mutation audit
(helper-283) found no test giving: the catalog's meshes have exact coordinates and no repeated indices.

- "min_x" / "max_y" take every vertex within ``tolerance`` of the extreme coordinate: a face written with round-off
  (a CAD export, 1e-9 m of jitter) is still the whole face. With the tolerance dropped on the min side, one vertex of
  the face was pinned and every test passed.
- Indices given twice select the vertex once (a handle would otherwise weigh it twice); returning them as given passed.
"""

from __future__ import annotations

import numpy as np

from redsim.scenes.toolkit import select_vertices


def _jittered_square() -> np.ndarray:
    """A 3 x 3 grid of vertices on [0, 1]^2 [m], each coordinate moved by up to 1e-9 m."""
    x, y = np.meshgrid(np.linspace(0.0, 1.0, 3), np.linspace(0.0, 1.0, 3), indexing="ij")
    grid = np.stack([x.ravel(), y.ravel()], 1)
    return grid + np.random.default_rng(0).uniform(-1e-9, 1e-9, grid.shape)


def test_an_extreme_face_with_round_off_is_selected_whole() -> None:
    vertices = _jittered_square()
    assert select_vertices(vertices, "min_x", tolerance=1e-6).tolist() == [0, 1, 2]
    assert select_vertices(vertices, "max_x", tolerance=1e-6).tolist() == [6, 7, 8]
    assert select_vertices(vertices, "min_y", tolerance=1e-6).tolist() == [0, 3, 6]
    assert select_vertices(vertices, "max_y", tolerance=1e-6).tolist() == [2, 5, 8]


def test_indices_given_twice_select_the_vertex_once() -> None:
    assert select_vertices(_jittered_square(), [4, 1, 4, 1], tolerance=1e-6).tolist() == [1, 4]
