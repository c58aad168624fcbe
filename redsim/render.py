"""Pictures and meshes of scene states: PNG panels with matplotlib, per-frame meshes with trimesh.

matplotlib is imported inside the functions (never when ``redsim`` is imported) and always
draws through its Agg canvas, so no display is needed. 3D scenes use the y-up convention of
the scene builders: scene ``(x, y, z)`` is drawn as matplotlib ``(x, -z, y)`` so that y points
up on screen.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from redsim.scene import Scene

logger = logging.getLogger(__name__)

MAX_DRAWN_FACES = 20_000
"""Faces drawn per panel; larger meshes are decimated (every k-th face) to keep drawing fast."""


class DependencyNotInstalled(ImportError):
    """An optional drawing or export dependency is missing."""


def _require(module: str) -> Any:
    """Import ``module`` or raise :class:`DependencyNotInstalled` naming the install command."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as err:
        top = module.split(".")[0]
        raise DependencyNotInstalled(
            f"{top} is not installed; it is a dependency of redsim: run `pip install redsim` (or `pip install {top}`)"
        ) from err


def surface_vertices(scene: Scene, q: Tensor) -> list[np.ndarray]:
    """Vertex positions [m] of every surface of ``scene`` at free configuration ``q`` ([n]).

    Returns:
        One float64 array of shape [P, D] per surface, in ``scene.surfaces`` order.
    """
    q = torch.as_tensor(q).detach()
    if q.shape != (scene.free_dof_count,):
        raise ValueError(f"scene {scene.name!r} expects q of shape [{scene.free_dof_count}], got {tuple(q.shape)}")
    x = scene.full_positions(q.to(device=scene.device, dtype=scene.dtype).unsqueeze(0))
    return [s.points.positions(x)[0].cpu().to(torch.float64).numpy() for s in scene.surfaces]


def _to_plot_frame(v: np.ndarray) -> np.ndarray:
    """Scene (x, y, z) with y up -> matplotlib (x, -z, y) with z up (a proper rotation)."""
    return np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1)


def _shade(tris: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """Lambert-like face colours [F, 4] for triangles [F, 3, 3] (two-sided)."""
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = normal / np.where(length > 0, length, 1.0)
    light = np.array([0.4, -0.5, 0.77])
    light = light / np.linalg.norm(light)
    intensity = 0.35 + 0.65 * np.abs(normal @ light)
    colors = np.ones((len(tris), 4))
    colors[:, :3] = rgb[None, :3] * intensity[:, None]
    return colors


def draw_states(
    scene: Scene,
    qs: Sequence[Tensor],
    titles: Sequence[str] | None = None,
    path: str | Path = "states.png",
    *,
    dpi: int = 100,
) -> Path:
    """Draw configurations of ``scene`` side by side, one panel per state, into a PNG.

    2D scenes are drawn as filled triangles with ``triplot`` edges per surface, 3D scenes with a
    ``Poly3DCollection`` per surface. All panels share axis limits and an equal aspect, so
    motion between states is visible. Meshes with more than :data:`MAX_DRAWN_FACES` faces per
    panel are decimated.

    Args:
        scene: The scene (must have at least one surface).
        qs: Free configurations, each of shape [n].
        titles: One title per state (default: ``state 0``, ``state 1``, ...).
        path: Output file; parent folders are created.
        dpi: Resolution of the PNG.

    Returns:
        The path written.

    Raises:
        ValueError: when the scene has no surfaces, ``qs`` is empty, or the counts disagree.
        DependencyNotInstalled: without matplotlib.
    """
    if not scene.surfaces:
        raise ValueError(f"scene {scene.name!r} has no surfaces to draw")
    if not qs:
        raise ValueError("draw_states needs at least one state")
    titles = [f"state {i}" for i in range(len(qs))] if titles is None else list(titles)
    if len(titles) != len(qs):
        raise ValueError(f"got {len(qs)} states but {len(titles)} titles")
    _require("matplotlib")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    verts, faces, center, half = _layout(scene, qs)
    import matplotlib as mpl

    palette = mpl.colormaps["tab10"]
    fig = Figure(figsize=(4.0 * len(qs), 4.0), layout="constrained")
    FigureCanvasAgg(fig)
    for i, (state, title) in enumerate(zip(verts, titles, strict=True)):
        _draw_panel(fig, (1, len(qs), i + 1), scene.dim, state, faces, center, half, palette, title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, bbox_inches="tight", pad_inches=0.1)
    return path


def animate_states(
    scene: Scene, qs: Sequence[Tensor], path: str | Path = "anim.gif", *, fps: float = 20.0, dpi: int = 80
) -> Path:
    """Write configurations of ``scene`` as the frames of a looping GIF (shared axis limits).

    Args:
        scene: The scene (must have surfaces).
        qs: Free configurations, each of shape [n], one per frame.
        path: Output .gif file; parent folders are created.
        fps: Frames per second.
        dpi: Resolution.

    Returns:
        The path written.
    """
    if not scene.surfaces:
        raise ValueError(f"scene {scene.name!r} has no surfaces to draw")
    if not qs:
        raise ValueError("animate_states needs at least one state")
    _require("matplotlib")
    import matplotlib as mpl
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from PIL import Image

    verts, faces, center, half = _layout(scene, qs)
    palette = mpl.colormaps["tab10"]
    images = []
    for i, state in enumerate(verts):
        fig = Figure(figsize=(4.0, 4.0), dpi=dpi, layout="constrained")
        canvas = FigureCanvasAgg(fig)
        _draw_panel(fig, (1, 1, 1), scene.dim, state, faces, center, half, palette, f"{scene.name}  frame {i}")
        canvas.draw()
        images.append(Image.fromarray(np.asarray(canvas.buffer_rgba())).convert("P", palette=Image.ADAPTIVE))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    return path


def _layout(scene: Scene, qs: Sequence[Tensor]) -> tuple[list[list[np.ndarray]], list[np.ndarray], np.ndarray, float]:
    """Plot-frame vertices per state and surface, (decimated) faces, and shared limits (centre, half-width)."""
    verts = [surface_vertices(scene, q) for q in qs]
    if scene.dim == 3:
        verts = [[_to_plot_frame(v) for v in state] for state in verts]
    faces = [s.faces.cpu().numpy() for s in scene.surfaces]
    total = sum(len(f) for f in faces)
    stride = max(1, math.ceil(total / MAX_DRAWN_FACES))
    if stride > 1:
        logger.info("drawing every %d-th of %d faces", stride, total)
        faces = [f[::stride] for f in faces]
    stacked = np.concatenate([v for state in verts for v in state])
    low, high = stacked.min(axis=0), stacked.max(axis=0)
    center, half = 0.5 * (low + high), 0.5 * float((high - low).max()) * 1.05
    return verts, faces, center, (half if half > 0 else 1.0)


def _draw_panel(
    fig: Any,
    grid: tuple[int, int, int],
    dim: int,
    state: list[np.ndarray],
    faces: list[np.ndarray],
    center: np.ndarray,
    half: float,
    palette: Any,
    title: str,
) -> None:
    """Draw one state's surfaces into a new subplot of ``fig`` at ``grid`` (rows, cols, index)."""
    if dim == 2:
        from matplotlib.collections import PolyCollection

        ax = fig.add_subplot(*grid)
        for k, (v, f) in enumerate(zip(state, faces, strict=True)):
            color = palette(k % 10)
            if len(f):
                ax.add_collection(PolyCollection(v[f], facecolors=[(*color[:3], 0.35)], edgecolors="none"))
                ax.triplot(v[:, 0], v[:, 1], f, color=color, linewidth=0.5)
            else:
                ax.plot(v[:, 0], v[:, 1], "o", color=color, markersize=2)
        ax.set_xlim(center[0] - half, center[0] + half)
        ax.set_ylim(center[1] - half, center[1] + half)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    else:
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection

        ax = fig.add_subplot(*grid, projection="3d")
        # One collection for all surfaces: mplot3d depth-sorts faces within a collection only.
        tris, colors = [], []
        for k, (v, f) in enumerate(zip(state, faces, strict=True)):
            rgb = np.asarray(palette(k % 10))
            if len(f):
                tris.append(v[f])
                colors.append(_shade(v[f], rgb))
            else:
                ax.scatter(v[:, 0], v[:, 1], v[:, 2], color=rgb, s=2)
        if tris:
            ax.add_collection3d(
                Poly3DCollection(np.concatenate(tris), facecolors=np.concatenate(colors), edgecolors="none")
            )
        ax.set_xlim(center[0] - half, center[0] + half)
        ax.set_ylim(center[1] - half, center[1] + half)
        ax.set_zlim(center[2] - half, center[2] + half)
        ax.set_box_aspect((1.0, 1.0, 1.0))
        ax.set_xlabel("x [m]")
        ax.set_ylabel("-z [m]")
        ax.set_zlabel("y [m]")
    ax.set_title(title)


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name) or "surface"


def export_meshes(scene: Scene, q: Tensor, directory: str | Path, frame: int) -> list[Path]:
    """Write every surface of ``scene`` at configuration ``q`` as ``frame_XXXX_<surface>.ply``.

    2D surfaces get z = 0. A surface without faces is written as a point cloud.

    Args:
        scene: The scene.
        q: Free configuration, shape [n].
        directory: Output folder (created if needed).
        frame: Frame number, zero-padded to four digits in the file names.

    Returns:
        The paths written, in ``scene.surfaces`` order.

    Raises:
        DependencyNotInstalled: without trimesh.
    """
    trimesh = _require("trimesh")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for surface, v in zip(scene.surfaces, surface_vertices(scene, q), strict=True):
        if v.shape[1] == 2:
            v = np.concatenate([v, np.zeros((len(v), 1))], axis=1)
        faces = surface.faces.cpu().numpy()
        geometry = trimesh.Trimesh(v, faces, process=False) if len(faces) else trimesh.PointCloud(v)
        path = directory / f"frame_{frame:04d}_{_safe_name(surface.name)}.ply"
        geometry.export(path)
        paths.append(path)
    return paths
