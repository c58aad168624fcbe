"""The headless rasterizer: back-face culling on closed surfaces, two-sided open ones, GC left as found."""

from __future__ import annotations

import dataclasses
import gc

import numpy as np
import pytest

from redsim import scenes
from redsim.raster import Arrow, Marker, SceneView


def _filled(view: SceneView, q, monkeypatch: pytest.MonkeyPatch) -> tuple[np.ndarray, int]:
    """The picture of q and the number of triangles Pillow filled for it."""
    from PIL import ImageDraw

    calls = []
    original = ImageDraw.ImageDraw.polygon
    monkeypatch.setattr(ImageDraw.ImageDraw, "polygon", lambda pen, *a, **k: calls.append(1) or original(pen, *a, **k))
    picture = view.draw(q)
    monkeypatch.setattr(ImageDraw.ImageDraw, "polygon", original)
    return picture, len(calls)


def _unculled(view: SceneView) -> SceneView:
    """The same camera drawing every triangle (no surface counted as closed)."""
    other = object.__new__(SceneView)
    other.__dict__.update(view.__dict__)
    other._outward = [0] * len(view._outward)
    return other


@pytest.mark.parametrize(("name", "closed"), [("mini_chain", True), ("stewart", True), ("hanging_sheet", False)])
def test_closed_surfaces_are_culled_and_look_the_same(name: str, closed: bool, monkeypatch) -> None:
    """Links and plates are closed and outward-wound (+1), the sheet open (0); culling moves silhouette pixels only."""
    scene = scenes.build(name)
    view = SceneView(scene, scene.q_seed, width=240, height=240)
    assert all(sign == (1 if closed else 0) for sign in view._outward)
    (culled, kept), (full, every) = (
        _filled(view, scene.q_seed, monkeypatch),
        _filled(_unculled(view), scene.q_seed, monkeypatch),
    )
    assert every == sum(len(f) for f in view._faces)
    if closed:  # about half of a closed surface faces away from the camera
        assert 0.3 * every < kept < 0.7 * every
    else:
        assert kept == every
    differ = np.abs(culled.astype(int) - full.astype(int)).sum(-1) > 0
    assert differ.mean() < 0.005  # one-pixel seams where a back face peeked past the silhouette
    assert (culled != culled[0, 0]).any(-1).mean() > 0.01  # something was drawn


def test_inward_wound_surfaces_cull_the_other_side(monkeypatch) -> None:
    """Flipping every triangle's winding flips the sign: the same faces are culled and the picture stays the same."""
    scene = scenes.build("mini_chain")
    flipped = dataclasses.replace(
        scene, surfaces=tuple(dataclasses.replace(s, faces=s.faces[:, [0, 2, 1]]) for s in scene.surfaces)
    )
    view, inward = SceneView(scene, scene.q_seed), SceneView(flipped, scene.q_seed)
    assert inward._outward == [-1] * len(scene.surfaces)
    (picture, kept), (inward_picture, inward_kept) = (_filled(v, scene.q_seed, monkeypatch) for v in (view, inward))
    assert kept == inward_kept < 0.7 * sum(len(f) for f in view._faces)
    assert np.array_equal(picture, inward_picture)


@pytest.mark.parametrize("enabled", [True, False])
def test_drawing_leaves_the_garbage_collector_as_it_found_it(enabled: bool) -> None:
    scene = scenes.build("mini_chain")
    view = SceneView(scene, scene.q_seed, width=64, height=64)
    was = gc.isenabled()
    try:
        gc.enable() if enabled else gc.disable()
        view.draw(scene.q_seed)
        assert gc.isenabled() == enabled
    finally:
        gc.enable() if was else gc.disable()


def test_arrows_and_markers_keep_their_share_of_the_picture_at_any_size() -> None:
    """An arrow of a given length [m] and a marker without a scene radius cover the same fraction of a 160 px and a
    480 px picture (within a factor 2: pixel rounding; smaller pictures reach the 1 px stroke and 2 px marker
    minimums), instead of fixed pixel widths that swamp a small picture."""
    scene = scenes.build("mini_chain")
    shares = []
    for size in (160, 480):
        view = SceneView(scene, scene.q_seed, width=size, height=size)
        view_blank = view.draw(scene.q_seed)
        arrow = Arrow(np.zeros(3), np.array([0.1, 0.0, 0.0]), 1.0)
        arrow_px = (view.draw(scene.q_seed, arrows=[arrow]) != view_blank).any(-1).sum()
        marker_px = (view.draw(scene.q_seed, markers=[Marker(np.zeros(3), filled=True)]) != view_blank).any(-1).sum()
        shares.append(np.array([arrow_px, marker_px]) / size**2)
    ratio = shares[0] / shares[1]
    assert ((0.5 < ratio) & (ratio < 2.0)).all(), ratio


def test_a_marker_radius_is_metres_checked_and_drawn_no_larger_than_the_picture() -> None:
    """A radius [m] far beyond the scene is drawn at most the picture's diagonal (Pillow would fill a 1000 m ring's
    whole ellipse: 88 s a frame), and a radius that is not a finite number >= 0 is refused."""
    scene = scenes.build("mini_chain")
    view = SceneView(scene, scene.q_seed, width=96, height=64)
    assert view.marker_radius_px(Marker(np.zeros(3), radius=1000.0)) == pytest.approx(np.hypot(96, 64))
    assert view.marker_radius_px(Marker(np.zeros(3), radius=np.float32(0.0))) == 2.0  # the minimum
    view.draw(scene.q_seed, markers=[Marker(np.zeros(3), radius=1000.0)])
    for bad in (float("nan"), -1.0, float("inf"), "7"):
        with pytest.raises(ValueError, match=r"Marker\.radius must be a finite number of metres"):
            Marker(np.zeros(3), radius=bad)
