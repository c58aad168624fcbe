"""The headless rasterizer: back-face culling on closed surfaces, two-sided open ones, the numpy fill against
Pillow's, batches, degenerate input."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import torch

from redsim import raster, scenes
from redsim.raster import Arrow, Marker, SceneView


def _filled(view: SceneView, q, monkeypatch: pytest.MonkeyPatch) -> tuple[np.ndarray, int]:
    """The picture of q and the number of triangles filled for it."""
    calls = []
    original = raster.fill_triangles
    monkeypatch.setattr(raster, "fill_triangles", lambda tri, *a: calls.append(len(tri)) or original(tri, *a))
    picture = view.draw(q)
    monkeypatch.setattr(raster, "fill_triangles", original)
    return picture, sum(calls)


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


def _pillow_fill(corners: np.ndarray, colours: np.ndarray, height: int, width: int) -> np.ndarray:
    """Stop 35's fill: one Pillow polygon call per triangle [T, 3, 2] (x, y px), in order, on the background."""
    from PIL import Image, ImageDraw

    image = Image.new("RGB", (width, height), raster.BACKGROUND)
    pen = ImageDraw.Draw(image)
    for poly, colour in zip(corners.reshape(-1, 6).tolist(), colours.tolist(), strict=True):
        pen.polygon(poly, fill=tuple(colour))
    return np.asarray(image)


def _near_edges(corners: np.ndarray, height: int, width: int) -> np.ndarray:
    """Bool [H, W]: pixels within one pixel of a triangle's outline (Pillow's lines, grown by one pixel)."""
    from PIL import Image, ImageDraw

    image = Image.new("L", (width, height), 0)
    pen = ImageDraw.Draw(image)
    for poly in corners.reshape(-1, 6).tolist():
        pen.polygon(poly, outline=1)
    edge = np.pad(np.asarray(image) > 0, 1)
    grown = np.zeros_like(edge)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            grown |= np.roll(np.roll(edge, dy, 0), dx, 1)
    return grown[1:-1, 1:-1]


@pytest.mark.parametrize("size", [84, 240])
@pytest.mark.parametrize("name", ["mini_chain", "stewart", "cloth_ball", "bistable_bar", "conditional_bar"])
def test_the_numpy_fill_matches_pillows_on_real_scenes(name: str, size: int) -> None:
    """fill_triangles on a scene's triangles (3D links and plates, the two-sided cloth, the 2D bars) equals the
    per-triangle Pillow fill it replaced on >= 98% of the pixels (measured 98.99-99.98% here) and on most of the
    pixels either fill draws (measured 0.3-8.9% differ at 84 px, Stewart's thin plates the most; 0.3-3.2% at 240), and
    the pixels that differ all lie on a triangle's edge. Pillow 9.1-11.0 put a polygon's edge pixels otherwise (9.0 and
    11.1+ as measured here; 9.2's differ on 13-18% of the drawn pixels at 84 px): no reference for these shares."""
    import PIL

    if (9, 1) <= tuple(int(part) for part in PIL.__version__.split(".")[:2]) < (11, 1):
        pytest.skip(f"Pillow {PIL.__version__} fills polygon edges otherwise than the Pillow these were measured on")
    scene = scenes.build(name)
    generator = torch.Generator().manual_seed(0)
    q = scene.q_seed + 0.02 * scene.extent() * torch.randn(scene.q_seed.shape, generator=generator)
    view = SceneView(scene, scene.q_seed, width=size, height=size)
    corners, colours, frames = view._triangles(view._surface_points_batch(q.reshape(1, -1), view._drawn_groups))
    mine = raster.fill_triangles(corners, colours, frames, 1, size, size)[0]
    theirs = _pillow_fill(corners, colours, size, size)
    differ = (mine != theirs).any(-1)
    drawn = (mine != raster.BACKGROUND).any(-1) | (theirs != raster.BACKGROUND).any(-1)
    assert drawn.mean() > 0.01  # something was drawn
    assert differ.mean() < 0.02, differ.mean()
    assert differ[drawn].mean() < (0.10 if size < 100 else 0.04), differ[drawn].mean()  # a body, not the background
    assert not (differ & ~_near_edges(corners, size, size)).any()


def test_the_fill_covers_a_subset_of_pillows_pixels_on_random_triangles() -> None:
    """Single random triangles (some thin, some off the picture): every pixel filled is one Pillow fills, and
    Pillow fills < 1% more (measured 0.2%: rounding where an edge crosses a pixel centre's row)."""
    rng = np.random.default_rng(1)
    extra = covered = 0
    mark = np.array([[1, 2, 3]])
    for k in range(300):
        corners = rng.uniform(-5.0, 45.0, (1, 3, 2))
        if k % 5 == 0:
            corners[0, 2] = corners[0, 0] + 0.7 * (corners[0, 1] - corners[0, 0])  # zero area: a line
        mine = (raster.fill_triangles(corners, mark, np.zeros(1, int), 1, 40, 40)[0] == mark).all(-1)
        theirs = (_pillow_fill(corners, mark, 40, 40) == mark).all(-1)
        assert not (mine & ~theirs).any()
        extra, covered = extra + (theirs & ~mine).sum(), covered + theirs.sum()
    assert extra < 0.01 * covered


def test_degenerate_and_far_triangles_neither_crash_nor_paint_garbage() -> None:
    """Zero area paints its segment (Pillow's line), a point one pixel; a non-finite vertex or one beyond
    COORDINATE_LIMIT paints nothing (Pillow painted such triangles as garbage); a valid huge triangle around the
    picture paints all of it, one far off it nothing; none disturbs a normal triangle drawn with it."""
    normal = np.array([[[5.0, 5.0], [30.0, 8.0], [12.0, 28.0]]])

    def fill(extra: list[list[list[float]]]) -> np.ndarray:
        corners = np.concatenate([normal, np.array(extra, dtype=np.float64).reshape(-1, 3, 2)])
        colours = np.array([[10, 20, 30]] + [[200, 0, 0]] * (len(corners) - 1))
        return raster.fill_triangles(corners, colours, np.zeros(len(corners), int), 1, 40, 40)[0]

    alone = fill([])
    painted = lambda picture: (picture == (200, 0, 0)).all(-1)  # noqa: E731
    line = painted(fill([[[0, 36], [30, 36], [15, 36]]]))
    assert line.sum() == 31 and line[36, :31].all()
    assert painted(fill([[[38.5, 2.2], [38.1, 2.9], [38.9, 2.0]]])).sum() == 1
    nan, inf, big = float("nan"), float("inf"), 2.0 * raster.COORDINATE_LIMIT
    for bad in ([[nan, 0], [10, 10], [0, 20]], [[inf, 0], [10, 10], [0, 20]], [[big, 0], [10, 10], [0, 20]]):
        assert np.array_equal(fill([bad]), alone)
    assert painted(fill([[[-1e6, -1e6], [1e6, -1e6], [0, 1e6]]])).all()
    assert np.array_equal(fill([[[1e5, 0], [2e5, 10], [1e5, 1e6]]]), alone)
    assert raster.fill_triangles(np.zeros((0, 3, 2)), np.zeros((0, 3)), np.zeros(0, int), 2, 8, 8).shape == (2, 8, 8, 3)
    scene = scenes.build("mini_chain")
    view = SceneView(scene, scene.q_seed, width=32, height=32)
    blank = np.broadcast_to(np.array(raster.BACKGROUND, dtype=np.uint8), (32, 32, 3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # and no RuntimeWarning per frame (a training loop would print thousands)
        for bad in (float("nan"), float("inf")):
            assert np.array_equal(view.draw(scene.q_seed * bad), blank)  # a diverged state: nothing drawn
    with pytest.raises(ValueError, match=r"colours must be RGB values in \[0, 255\]"):  # never wrapped round
        raster.fill_triangles(np.zeros((1, 3, 2)), np.array([[300, 0, 0]]), np.zeros(1, int), 1, 8, 8)


@pytest.mark.parametrize("name", ["mini_chain", "cloth_ball", "bistable_bar"])
def test_a_batch_draws_each_state_as_draw_does(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """draw_batch's frame i is draw(q[i]) with copy i's markers and arrows, pixel for pixel, however the
    triangles are split into fill calls (FILL_CHUNK, FILL_PIXELS); the surface points are the scene's PointSet
    positions."""
    scene = scenes.build(name)
    generator = torch.Generator().manual_seed(1)
    q = scene.q_seed + 0.05 * scene.extent() * torch.randn((5, scene.q_seed.numel()), generator=generator)
    view = SceneView(scene, scene.q_seed, width=64, height=48)
    origin = np.zeros(scene.dim)
    markers = [[Marker(origin + 0.01 * i, radius=0.02 * i)] if i % 2 else [] for i in range(5)]
    arrows = [[Arrow(origin, np.eye(scene.dim)[0], 0.05 * i)] if i % 3 else [] for i in range(5)]
    x = scene.full_positions(q[:1])
    for points, surface in zip(view.surface_points(q[0]), scene.surfaces, strict=True):  # the PointSet's positions
        expected = surface.points.positions(x)[0].double().numpy()
        np.testing.assert_allclose(points, expected, rtol=0.0, atol=1e-6 * scene.extent())
    single = [view.draw(q[i], markers=markers[i], arrows=arrows[i]) for i in range(5)]
    assert len({s.tobytes() for s in single}) == 5
    assert view.draw_batch(q[:0]).shape == (0, 48, 64, 3)  # no state: no frame
    original, calls = raster.fill_triangles, []
    monkeypatch.setattr(raster, "fill_triangles", lambda *a: calls.append(a[3]) or original(*a))
    for chunk, pixels, frames in (
        (raster.FILL_CHUNK, raster.FILL_PIXELS, [5]),
        (1, 10**9, [1] * 5),
        (10**9, 2 * 64 * 48, [2, 2, 1]),
    ):
        monkeypatch.setattr(raster, "FILL_CHUNK", chunk)
        monkeypatch.setattr(raster, "FILL_PIXELS", pixels)
        calls.clear()
        batch = view.draw_batch(q, markers=markers, arrows=arrows)
        assert calls == frames  # frames per fill call: at most FILL_CHUNK triangles and FILL_PIXELS pixels
        assert batch.shape == (5, 48, 64, 3) and batch.dtype == np.uint8
        assert all(np.array_equal(batch[i], single[i]) for i in range(5))
    with pytest.raises(ValueError, match="one list of markers per state"):
        view.draw_batch(q, markers=markers[:2])


def test_merging_close_vertices_coarsens_a_mesh_and_keeps_its_winding() -> None:
    """Vertex clustering on a fine sphere: no change at a spacing below the vertex spacing; at a coarse one fewer
    faces over the lowest-numbered vertex of each cell, none degenerate or repeated, still outward and near the
    sphere's volume; a mesh smaller than one cell keeps one face; a non-finite point merges with nothing."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    points, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    assert raster.merge_close_vertices(points, faces, 0.0) is faces
    assert np.array_equal(raster.merge_close_vertices(points, faces, 1e-3), faces)
    coarse = raster.merge_close_vertices(points, faces, 0.4)
    assert 50 < len(coarse) < 0.3 * len(faces)
    assert (coarse[:, 0] != coarse[:, 1]).all() and (coarse[:, 1] != coarse[:, 2]).all()
    assert (coarse[:, 0] != coarse[:, 2]).all()
    cells = np.floor(points / 0.4)
    for vertex in np.unique(coarse):  # each kept vertex is the lowest-numbered of its cell
        assert vertex == np.flatnonzero((cells == cells[vertex]).all(1)).min()
    rotated = np.array([np.roll(f, -int(np.argmin(f))) for f in coarse])
    assert len(np.unique(rotated, axis=0)) == len(coarse)
    volume = np.einsum("fi,fi->", points[coarse[:, 0]], np.cross(points[coarse[:, 1]], points[coarse[:, 2]])) / 6
    assert 0.6 * sphere.volume < volume <= sphere.volume
    assert np.array_equal(raster.merge_close_vertices(points + 5.0, faces, 10.0), faces[:1])  # all in one cell
    holed = points.copy()
    holed[faces[0]] = np.nan
    assert any(set(faces[0]) <= set(f) for f in raster.merge_close_vertices(holed, faces, 0.4).tolist())


@pytest.mark.parametrize(
    ("name", "faces_kept", "size"), [("chain", 0.2, 84), ("stewart", 0.25, 84), ("chain", 1.0, 480)]
)
def test_a_small_picture_draws_a_coarser_mesh_with_the_same_silhouette(name: str, faces_kept: float, size: int) -> None:
    """At 84 px the chain's links and Stewart's arms merge to a few triangles each (measured 15% and 15% of the
    mesh's, framed on the seed states); the picture keeps its silhouette (background or not: >= 99% of pixels
    equal), while the shading of sub-pixel faces changes; ``merge_px=0`` draws every triangle; at 480 px nearly
    nothing merges."""
    scene = scenes.build(name)
    generator = torch.Generator().manual_seed(0)
    q = scene.q_seed + 0.01 * scene.extent() * torch.randn((4, scene.q_seed.numel()), generator=generator)
    view = SceneView(scene, scene.q_seed, width=size, height=size)
    every = SceneView(scene, scene.q_seed, width=size, height=size, merge_px=0.0)
    total = sum(len(s.faces) for s in scene.surfaces)
    assert sum(len(f) for f in every._faces) == total
    assert sum(len(f) for f in view._faces) <= faces_kept * total
    if size > 100:
        assert sum(len(f) for f in view._faces) > 0.99 * total
    merged, full = view.draw_batch(q), every.draw_batch(q)
    background = np.array(raster.BACKGROUND)
    silhouette = (merged == background).all(-1) != (full == background).all(-1)
    assert silhouette.mean() < 0.01, silhouette.mean()
    assert (full != background).any(-1).mean() > 0.005  # something was drawn
    with pytest.raises(ValueError, match="merge_px"):
        SceneView(scene, scene.q_seed, merge_px=-1.0)
    # a margin that leaves the scene under a pixel was a ZeroDivisionError at the env's first render
    for margin, expected in ((1e308, "smaller than a pixel"), (-0.1, "margin must be"), (np.inf, "margin must be")):
        with pytest.raises(ValueError, match=expected):
            SceneView(scene, scene.q_seed, margin=margin)


def test_a_picture_evaluates_only_the_points_its_faces_use() -> None:
    """After merging, a small picture's faces use a fraction of the surface points: only those are evaluated (the
    drawn faces renumbered onto them), each equal to its full evaluation, so the picture is the same."""
    scene = scenes.build("chain")
    generator = torch.Generator().manual_seed(0)
    q = scene.q_seed + 0.01 * scene.extent() * torch.randn((2, scene.q_seed.numel()), generator=generator)
    view = SceneView(scene, scene.q_seed, width=84, height=84)
    full, drawn = view._surface_points_batch(q), view._surface_points_batch(q, view._drawn_groups)
    assert sum(d.shape[1] for d in drawn) < 0.25 * sum(f.shape[1] for f in full)
    for points, subset, faces, renumbered in zip(full, drawn, view._faces, view._drawn_faces, strict=True):
        assert np.array_equal(subset[:, renumbered], points[:, faces])
