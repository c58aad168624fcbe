"""A fast headless rasterizer for scene states: flat-shaded triangles, markers and arrows into RGB arrays.

Triangles are projected orthographically, sorted back to front and filled by Pillow's C polygon
fill (the painter's algorithm), with no display and no plotting library. On a closed, consistently
wound surface (rigid links, FEM solids) the triangles facing away from the camera are hidden by
the ones facing it, so they are not drawn (back-face culling); open surfaces (cloth) are drawn
two-sided. `redsim bench envs` prints each env's frames per second at 480x480. 3D scenes use the builders' y-up
convention: the camera turns about the y axis (``azimuth``) and then tilts down (``elevation``).

    >>> view = SceneView(scene, q_rest, width=480, height=480)
    >>> image = view.draw(q, markers=[Marker(target, radius=0.05)], arrows=[Arrow(p, force, 0.01)])  # [480, 480, 3]

Overlays scale with the picture: a marker with a scene radius [m] (a task's success radius) is drawn at that
radius, one without at :data:`MARKER_FRACTION` of the picture, never under :data:`MIN_MARKER_PX`; strokes and arrow
heads grow with the picture's size (:meth:`SceneView.stroke_px`). Markers are rings by default, so the body they
mark stays visible inside them.
"""

from __future__ import annotations

import gc
import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from redsim.scene import Scene

BACKGROUND = (250, 250, 247)
SURFACE_COLOURS = ((86, 126, 196), (214, 138, 64), (120, 170, 110), (170, 110, 170), (200, 190, 90))
"""Surface colours, cycled in ``scene.surfaces`` order."""
LIGHT = np.array([0.35, 0.8, 0.5]) / np.linalg.norm([0.35, 0.8, 0.5])
"""Light direction in camera space (two-sided Lambert)."""
TARGET_RGB = (255, 190, 190)
"""Colour of a task's target (its success disc): a light red whose grey level (Gymnasium's GrayscaleObservation
weights 0.2125 R + 0.7154 G + 0.0721 B: 204) lies 46 under the background's (250) and 81 over the brightest the cloth's
blue is shaded (123); a saturated red (220, 40, 40: 78) matched the shaded cloth in greyscale."""
HANDLE_RGB = (40, 40, 40)
"""Colour of the marker on the handle a task moves to its target (and of every marker's edge)."""
MIN_MARKER_PX = 2.0
"""Smallest marker radius [px]: a success radius under it (tiny at 84 px) is drawn this large."""
MARKER_FRACTION = 1.0 / 60.0
"""Radius of a marker without a scene radius, as a fraction of the picture's smaller side (8 px at 480 px)."""
ARROW_HEAD_FRACTION = 1.0 / 48.0
"""Length of an arrow's head, as a fraction of the picture's smaller side (at least 3 px, at most half the arrow;
10 px at 480 px)."""
STROKE_FRACTION = 1.0 / 160.0
"""Width of arrow shafts and marker rings, as a fraction of the picture's smaller side (at least 1 px; 3 px at
480 px)."""


@dataclass(frozen=True)
class Marker:
    """A ring (or a filled disc) around a scene point, edged in :data:`HANDLE_RGB`.

    Attributes:
        position: Point [m], shape [D].
        colour: RGB.
        radius: Radius [m] in scene units (e.g. a task's success radius), drawn at the view's pixels per metre
            (pixels before stop 35); None: :data:`MARKER_FRACTION` of the picture's smaller side. Never drawn under
            :data:`MIN_MARKER_PX`, nor over the picture's diagonal (a larger ring is off the picture anyway).
        filled: A filled disc instead of a ring (a ring leaves the body it marks visible).
    """

    position: np.ndarray
    colour: tuple[int, int, int] = TARGET_RGB
    radius: float | None = None
    filled: bool = False

    def __post_init__(self) -> None:
        if self.radius is not None and not (isinstance(self.radius, numbers.Real) and 0.0 <= self.radius < math.inf):
            raise ValueError(f"Marker.radius must be a finite number of metres >= 0 or None, got {self.radius!r}")


@dataclass(frozen=True)
class Arrow:
    """An arrow from a scene point along a vector given in pixels per unit.

    Attributes:
        origin: Start point [m], shape [D].
        vector: Direction and length, shape [D], drawn ``scale`` metres per unit.
        scale: Metres of arrow per unit of ``vector`` (e.g. m/N for a force).
        colour: RGB.
    """

    origin: np.ndarray
    vector: np.ndarray
    scale: float
    colour: tuple[int, int, int] = (30, 160, 60)


def _require_pillow():
    try:
        from PIL import Image, ImageDraw
    except ImportError as err:  # pragma: no cover - Pillow comes with matplotlib, a dependency
        from redsim.render import DependencyNotInstalled

        raise DependencyNotInstalled("Pillow is not installed; run `pip install pillow`") from err
    return Image, ImageDraw


def _outward_sign(points: np.ndarray, faces: np.ndarray) -> int:
    """+1 (-1) if the triangles [F, 3] form closed surfaces wound with outward (inward) normals, else 0.

    Closed means every edge is shared by exactly two triangles with opposite directions (trimesh's
    watertight and winding-consistent tests); the side is the sign of the enclosed volume, which must
    be the same for every connected piece. Only 3D points [P, 3] can be closed.
    """
    if points.shape[-1] != 3 or len(faces) < 4:
        return 0
    import trimesh

    mesh = trimesh.Trimesh(vertices=points, faces=faces, process=False)
    if not (mesh.is_watertight and mesh.is_winding_consistent):
        return 0
    piece = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(faces))
    tri = points[faces]
    volume = np.bincount(piece, weights=np.einsum("fi,fi->f", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])))
    signs = set(np.sign(volume).astype(int).tolist())
    return signs.pop() if len(signs) == 1 else 0


class SceneView:
    """A fixed orthographic camera on one scene, framed on a reference state.

    Args:
        scene: The scene; its ``surfaces`` are what is drawn.
        q_frame: Free configuration [n] whose surfaces (grown by ``margin``) fill the picture.
        width: Image width [px].
        height: Image height [px].
        azimuth: Camera turn about +y [deg] (3D only; 0 looks along -z).
        elevation: Camera tilt down [deg] (3D only).
        margin: Extra frame around ``q_frame``, as a fraction of its size.
        extra_points: More points [P, D] [m] the frame must contain (e.g. every target).

    Raises:
        ValueError: a scene without surfaces or a bad image size.
    """

    def __init__(
        self,
        scene: Scene,
        q_frame: Tensor,
        *,
        width: int = 480,
        height: int = 480,
        azimuth: float = 30.0,
        elevation: float = 20.0,
        margin: float = 0.25,
        extra_points: np.ndarray | None = None,
    ) -> None:
        if not scene.surfaces:
            raise ValueError(f"scene {scene.name!r} has no surfaces to draw")
        if int(width) < 8 or int(height) < 8:
            raise ValueError(f"image size must be at least 8 x 8 px, got {width} x {height}")
        self.scene = scene
        self.width, self.height = int(width), int(height)
        self.dim = scene.dim
        self._faces = [s.faces.cpu().numpy() for s in scene.surfaces]
        frame_points = self.surface_points(q_frame)
        self._outward = [_outward_sign(p, f) for p, f in zip(frame_points, self._faces, strict=True)]
        self._colours = [
            np.array(SURFACE_COLOURS[i % len(SURFACE_COLOURS)], dtype=np.float64) for i in range(len(scene.surfaces))
        ]
        if self.dim == 3:
            a, e = math.radians(azimuth), math.radians(elevation)
            turn = np.array([[math.cos(a), 0.0, -math.sin(a)], [0.0, 1.0, 0.0], [math.sin(a), 0.0, math.cos(a)]])
            tilt = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(e), -math.sin(e)], [0.0, math.sin(e), math.cos(e)]])
            self._rotation = tilt @ turn  # world -> camera (x right, y up, z towards the viewer)
        else:
            self._rotation = np.eye(2)
        points = np.concatenate(self.surface_points(q_frame))
        if extra_points is not None and len(extra_points):
            points = np.concatenate([points, np.asarray(extra_points, dtype=np.float64).reshape(-1, self.dim)])
        cam = points @ self._rotation.T
        low, high = cam[:, :2].min(0), cam[:, :2].max(0)
        size = float(max((high - low).max(), 1e-6)) * (1.0 + 2.0 * margin)
        self._centre = 0.5 * (low + high)
        self._pixels_per_metre = min(self.width, self.height) / size

    def surface_points(self, q: Tensor) -> list[np.ndarray]:
        """Vertex positions [m] of every surface at free configuration q ([n]), float64."""
        q = torch.as_tensor(q).detach()
        x = self.scene.full_positions(q.reshape(1, -1).to(device=self.scene.device, dtype=self.scene.dtype))
        return [s.points.positions(x)[0].cpu().to(torch.float64).numpy() for s in self.scene.surfaces]

    @property
    def pixels_per_metre(self) -> float:
        """The camera's scale [px/m] (orthographic: the same everywhere in the picture)."""
        return self._pixels_per_metre

    def stroke_px(self) -> int:
        """Width [px] of arrow shafts and marker rings: :data:`STROKE_FRACTION` of the smaller side, at least 1."""
        return max(1, round(STROKE_FRACTION * min(self.width, self.height)))

    def marker_radius_px(self, marker: Marker) -> float:
        """The radius [px] ``marker`` is drawn at (its scene radius, or the frame-relative default; >= 2 px)."""
        if marker.radius is None:
            radius = MARKER_FRACTION * min(self.width, self.height)
        else:
            radius = float(marker.radius) * self._pixels_per_metre
        return min(max(MIN_MARKER_PX, radius), math.hypot(self.width, self.height))

    def contains(self, points: np.ndarray) -> bool:
        """Whether every point [P, D] [m] projects inside the picture."""
        pix = self.project(points)
        return bool(
            ((pix[:, 0] >= 0) & (pix[:, 0] <= self.width) & (pix[:, 1] >= 0) & (pix[:, 1] <= self.height)).all()
        )

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates [P, 2] (x right, y down) and depth [P] (larger is nearer) as [P, 3]."""
        cam = np.asarray(points, dtype=np.float64).reshape(-1, self.dim) @ self._rotation.T
        px = (cam[:, 0] - self._centre[0]) * self._pixels_per_metre + 0.5 * self.width
        py = 0.5 * self.height - (cam[:, 1] - self._centre[1]) * self._pixels_per_metre
        depth = cam[:, 2] if self.dim == 3 else np.zeros(len(cam))
        return np.stack([px, py, depth], axis=1)

    def draw(self, q: Tensor, *, markers: Sequence[Marker] = (), arrows: Sequence[Arrow] = ()) -> np.ndarray:
        """The picture of state q ([n]) with markers and arrows on top, uint8 [height, width, 3]."""
        Image, ImageDraw = _require_pillow()
        image = Image.new("RGB", (self.width, self.height), BACKGROUND)
        pen = ImageDraw.Draw(image)
        polygons, colours, depths = [], [], []
        surfaces = zip(self.surface_points(q), self._faces, self._colours, self._outward, strict=True)
        for verts, faces, rgb, outward in surfaces:
            tri = verts[faces]  # [F, 3, D]
            cam = tri.reshape(-1, self.dim) @ self._rotation.T
            pix = self.project(tri.reshape(-1, self.dim))[:, :2].reshape(-1, 6)
            if self.dim == 3:
                cam = cam.reshape(-1, 3, 3)
                normal = np.cross(cam[:, 1] - cam[:, 0], cam[:, 2] - cam[:, 0])
                if outward:  # a closed surface: keep the faces whose outward normal points at the camera
                    front = outward * normal[:, 2] >= 0.0
                    cam, normal, pix = cam[front], normal[front], pix[front]
                length = np.linalg.norm(normal, axis=1, keepdims=True)
                normal = normal / np.where(length > 0.0, length, 1.0)
                shade = 0.35 + 0.65 * np.abs(normal @ LIGHT)
                depths.append(cam[:, :, 2].mean(1))
            else:
                shade = np.full(len(tri), 0.9)
                depths.append(np.zeros(len(tri)))
            colours.append(np.clip(rgb[None] * shade[:, None], 0, 255).astype(np.int64))
            polygons.append(pix)
        order = np.argsort(np.concatenate(depths), kind="stable")  # far (small depth) first
        collecting = gc.isenabled()
        gc.disable()  # the loop makes ~10 short-lived objects per triangle; cyclic GC passes over them cost 3x the fill
        try:
            pix_all = np.concatenate(polygons)[order].tolist()
            col_all = [tuple(c) for c in np.concatenate(colours)[order].tolist()]
            for poly, colour in zip(pix_all, col_all, strict=True):
                pen.polygon(poly, fill=colour)
        finally:
            if collecting:
                gc.enable()
        for arrow in arrows:
            self._arrow(pen, arrow)
        for marker in markers:
            self._marker(pen, marker)
        return np.asarray(image, dtype=np.uint8).copy()

    def _marker(self, pen: object, marker: Marker) -> None:
        """A disc, or a ring of :meth:`marker_radius_px` around the marker: a band of :meth:`stroke_px` between
        1 px edges in :data:`HANDLE_RGB` where that leaves a hole of 2 px radius, else one band of the colour."""
        x, y, _ = self.project(np.asarray(marker.position))[0]
        r = self.marker_radius_px(marker)
        if marker.filled:
            pen.ellipse((x - r, y - r, x + r, y + r), fill=marker.colour, outline=HANDLE_RGB)  # type: ignore[attr-defined]
            return
        band = self.stroke_px()
        if r < band + 4:  # too small for edges: they would fill the hole
            pen.ellipse((x - r, y - r, x + r, y + r), outline=marker.colour, width=band + 1)  # type: ignore[attr-defined]
            return
        pen.ellipse((x - r, y - r, x + r, y + r), outline=HANDLE_RGB, width=band + 2)  # type: ignore[attr-defined]
        inner = r - 1
        pen.ellipse((x - inner, y - inner, x + inner, y + inner), outline=marker.colour, width=band)  # type: ignore[attr-defined]

    def _arrow(self, pen: object, arrow: Arrow) -> None:
        start = np.asarray(arrow.origin, dtype=np.float64)
        end = start + arrow.scale * np.asarray(arrow.vector, dtype=np.float64)
        (x0, y0, _), (x1, y1, _) = self.project(np.stack([start, end]))
        x1, y1 = self._inside(x0, y0, x1, y1)  # a long arrow ends at the border, its head still drawn
        length = math.hypot(x1 - x0, y1 - y0)
        if length < 1.0:
            return
        stroke = self.stroke_px()
        pen.line((x0, y0, x1, y1), fill=arrow.colour, width=stroke)  # type: ignore[attr-defined]
        ux, uy = (x1 - x0) / length, (y1 - y0) / length
        head = min(max(3.0, ARROW_HEAD_FRACTION * min(self.width, self.height)), 0.5 * length)
        left = (x1 - head * (ux - 0.5 * uy), y1 - head * (uy + 0.5 * ux))
        right = (x1 - head * (ux + 0.5 * uy), y1 - head * (uy - 0.5 * ux))
        pen.polygon([(x1, y1), left, right], fill=arrow.colour)  # type: ignore[attr-defined]

    def _inside(self, x0: float, y0: float, x1: float, y1: float) -> tuple[float, float]:
        """The end (x1, y1) [px] pulled back along the segment from (x0, y0) to the picture's border, 2 px in
        (unchanged when inside, or when the start itself is outside)."""
        low, high = 2.0, np.array([self.width - 2.0, self.height - 2.0])
        start, end = np.array([x0, y0]), np.array([x1, y1])
        if ((start < low) | (start > high)).any():
            return x1, y1
        t = 1.0
        for axis in range(2):
            delta = end[axis] - start[axis]
            if delta > 0 and end[axis] > high[axis]:
                t = min(t, (high[axis] - start[axis]) / delta)
            elif delta < 0 and end[axis] < low:
                t = min(t, (low - start[axis]) / delta)
        x, y = start + t * (end - start)
        return float(x), float(y)


__all__ = ["HANDLE_RGB", "TARGET_RGB", "Arrow", "Marker", "SceneView"]
