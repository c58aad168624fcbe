"""Pictures and meshes of scene states: PNG panels with matplotlib, per-frame meshes with trimesh.

matplotlib is imported inside the functions (never when ``redsim`` is imported) and always
draws through its Agg canvas, so no display is needed. 3D scenes use the y-up convention of
the scene builders: scene ``(x, y, z)`` is drawn as matplotlib ``(x, -z, y)`` so that y points
up on screen.
"""

from __future__ import annotations

import logging
import math
import operator
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from redsim.scene import Scene
from redsim.subspace.checkpoint import write_atomically

logger = logging.getLogger(__name__)

MAX_DRAWN_FACES = 20_000
"""Faces drawn per panel; larger meshes are decimated (every k-th face) to keep drawing fast."""
FIXED_RGB = (0.45, 0.45, 0.45)
"""Colour of fixed bodies and pinned vertices (points no free DOF moves)."""
LOAD_RGB = (0.85, 0.1, 0.1)
"""Colour of the arrows of applied loads."""


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


def surface_meshes(scene: Scene, q: Tensor) -> list[Any]:
    """The surfaces of ``scene`` at free configuration ``q`` ([n]) as ``trimesh.Trimesh`` objects, in
    ``scene.surfaces`` order (2D surfaces at z = 0; a surface without faces has its vertices alone).

    Raises:
        DependencyNotInstalled: without trimesh.
    """
    trimesh = _require("trimesh")
    meshes = []
    for surface, v in zip(scene.surfaces, surface_vertices(scene, q), strict=True):
        if v.shape[1] == 2:
            v = np.concatenate([v, np.zeros((len(v), 1))], axis=1)
        meshes.append(trimesh.Trimesh(v, surface.faces.cpu().numpy(), process=False))
    return meshes


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
    qs: Sequence[Tensor] | Tensor,
    titles: Sequence[str] | None = None,
    path: str | Path = "states.png",
    *,
    loads: dict[str, Sequence[float]] | None = None,
    dpi: int = 100,
) -> Path:
    """Draw configurations of ``scene`` side by side, one panel per state, into a PNG.

    2D scenes are drawn as filled triangles with ``triplot`` edges per surface, 3D scenes with a
    ``Poly3DCollection`` per surface. Faces that do not move (fixed bodies) and pinned vertices
    are drawn in :data:`FIXED_RGB`; each load is an arrow at its handle in :data:`LOAD_RGB`,
    of a fixed length on screen and labelled with its size [N]. All panels share axis limits and
    an equal aspect, so motion between states is visible. Meshes with more than
    :data:`MAX_DRAWN_FACES` faces per panel are decimated.

    Args:
        scene: The scene (must have at least one surface).
        qs: Free configurations, each of shape [n] (or a batch [k, n]).
        titles: One title per state (default: ``state 0``, ``state 1``, ...).
        path: Output file; parent folders are created. Written whole or not at all (a temporary file, then a
            rename): an interrupted write leaves the file there before.
        loads: Forces [N] by handle name (as for :meth:`Scene.pack_loads`), drawn on every panel.
        dpi: Resolution of the PNG.

    Returns:
        The path written.

    Raises:
        ValueError: when the scene has no surfaces, ``qs`` is empty or not finite, the counts disagree, or ``loads``
            names a handle the scene lacks or holds a force that is not [D].
        DependencyNotInstalled: without matplotlib.
    """
    if not scene.surfaces:
        raise ValueError(f"scene {scene.name!r} has no surfaces to draw")
    qs = _states(qs, "draw_states")
    titles = [f"state {i}" for i in range(len(qs))] if titles is None else list(titles)
    if len(titles) != len(qs):
        raise ValueError(f"got {len(qs)} states but {len(titles)} titles")
    if loads:
        scene.pack_loads(loads, 1)  # an unknown handle or a wrong shape: the error scene.energy gives
    _require("matplotlib")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    verts, faces, center, half = _layout(scene, qs)
    import matplotlib as mpl

    fixed = fixed_points(scene)
    palette = mpl.colormaps["tab10"]
    fig = Figure(figsize=(4.0 * len(qs), 4.0), layout="constrained")
    FigureCanvasAgg(fig)
    for i, (q, state, title) in enumerate(zip(qs, verts, titles, strict=True)):
        ax = _draw_panel(fig, (1, len(qs), i + 1), scene.dim, state, faces, center, half, palette, title, fixed)
        _draw_loads(ax, scene, q, loads or {}, half)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, lambda tmp: fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight", pad_inches=0.1))
    return path


def _states(qs: Sequence[Tensor] | Tensor, caller: str) -> list[Tensor]:
    """``qs`` as a list of states [n]: a sequence of them, or a batch [k, n]; refused where empty or not finite."""
    if isinstance(qs, Tensor | np.ndarray):
        if qs.ndim != 2:
            raise ValueError(f"{caller} takes a sequence of [n] states or a batch [k, n], got shape {tuple(qs.shape)}")
        qs = list(qs)
    qs = list(qs)
    if not qs:
        raise ValueError(f"{caller} needs at least one state")
    if not all(bool(torch.isfinite(torch.as_tensor(q)).all()) for q in qs):
        raise ValueError(f"{caller} needs finite states: a state that is not finite has no picture")
    return qs


MIN_GIF_FPS = 100.0 / 65535
"""The lowest frame rate a GIF holds [1/s]: its frame time is a 16-bit count of 10 ms (655.35 s at most)."""
MAX_GIF_FPS = 50.0
"""The highest frame rate a GIF plays at as written [1/s]: browsers show a frame time of 10 ms (or 0) as 100 ms."""


def gif_frame_ms(fps: float) -> int:
    """A GIF's frame time [ms] for ``fps`` in [:data:`MIN_GIF_FPS`, :data:`MAX_GIF_FPS`]: rounded to the 10 ms
    the format stores (Pillow truncates to them: 15 fps played at 16.7, 45 at 50)."""
    if not (math.isfinite(fps) and MIN_GIF_FPS <= fps <= MAX_GIF_FPS):
        raise ValueError(f"a GIF's fps must be in [{MIN_GIF_FPS:.3g}, {MAX_GIF_FPS:g}], got {fps!r}")
    return 10 * min(65535, max(2, round(100.0 / fps)))


def animate_states(
    scene: Scene, qs: Sequence[Tensor] | Tensor, path: str | Path = "anim.gif", *, fps: float = 20.0, dpi: int = 80
) -> Path:
    """Write configurations of ``scene`` as the frames of a looping GIF (shared axis limits).

    Args:
        scene: The scene (must have surfaces).
        qs: Free configurations, each of shape [n], one per frame (or a batch [k, n]).
        path: Output .gif file; parent folders are created. Written whole or not at all, as in :func:`draw_states`.
        fps: Frames per second, in [:data:`MIN_GIF_FPS`, :data:`MAX_GIF_FPS`] (:func:`gif_frame_ms`).
        dpi: Resolution.

    Returns:
        The path written.

    Raises:
        ValueError: a scene without surfaces, no state or one that is not finite, a path that is not a .gif, or an
            fps out of range.
    """
    if not scene.surfaces:
        raise ValueError(f"scene {scene.name!r} has no surfaces to draw")
    qs = _states(qs, "animate_states")
    if Path(path).suffix.lower() != ".gif":
        raise ValueError(f"animate_states writes a .gif, got {str(path)!r}")
    frame_ms = gif_frame_ms(fps)
    _require("matplotlib")
    import matplotlib as mpl
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from PIL import Image

    verts, faces, center, half = _layout(scene, qs)
    fixed = fixed_points(scene)
    palette = mpl.colormaps["tab10"]
    images = []
    for i, state in enumerate(verts):
        fig = Figure(figsize=(4.0, 4.0), dpi=dpi, layout="constrained")
        canvas = FigureCanvasAgg(fig)
        title = f"{scene.name}  frame {i}"
        _draw_panel(fig, (1, 1, 1), scene.dim, state, faces, center, half, palette, title, fixed)
        canvas.draw()
        images.append(Image.fromarray(np.asarray(canvas.buffer_rgba())).convert("P", palette=Image.ADAPTIVE))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(
        path,
        lambda tmp: images[0].save(
            tmp, format="GIF", save_all=True, append_images=images[1:], duration=frame_ms, loop=0
        ),
    )
    return path


def fixed_points(scene: Scene) -> list[np.ndarray]:
    """Per surface, a boolean mask [P] of the points no free DOF moves (pinned vertices, fixed bodies).

    Surface points are linear in the configuration, so a point is fixed exactly when a random
    change of every free DOF leaves it where it is.
    """
    q = scene.q_seed.detach().cpu().to(torch.float64)
    generator = torch.Generator().manual_seed(0)
    moved = q + torch.randn(q.shape, generator=generator, dtype=q.dtype)
    before, after = surface_vertices(scene, q), surface_vertices(scene, moved)
    return [np.all(np.abs(a - b) <= 1e-9 * (1.0 + np.abs(b)), axis=1) for a, b in zip(before, after, strict=True)]


def _draw_loads(ax: Any, scene: Scene, q: Tensor, loads: dict[str, Sequence[float]], half: float) -> None:
    """Arrows for the forces [N] in ``loads`` at their handles' positions in configuration ``q``."""
    if not loads:
        return
    x = scene.full_positions(torch.as_tensor(q).detach().to(scene.device, scene.dtype).unsqueeze(0))
    by_name = {h.name: h for h in scene.handles}
    for name, force in loads.items():
        f = np.asarray(force, dtype=np.float64)
        size = float(np.linalg.norm(f))
        if size == 0.0 or not math.isfinite(size):
            continue
        at = by_name[name].position(x)[0].cpu().to(torch.float64).numpy()
        direction = 0.35 * half * f / size
        label = f"{name}: {size:.3g} N"
        if scene.dim == 2:
            ax.annotate(
                "",
                xy=tuple(at + direction),
                xytext=tuple(at),
                arrowprops={"arrowstyle": "-|>", "color": LOAD_RGB, "linewidth": 2.0, "mutation_scale": 15},
            )
            ax.text(*(at + 1.1 * direction), label, color=LOAD_RGB, fontsize=8)
        else:
            at, tip = _to_plot_frame(at[None])[0], _to_plot_frame((at + direction)[None])[0]
            d = tip - at
            ax.quiver(*at, *d, color=LOAD_RGB, linewidth=2.0, arrow_length_ratio=0.25)
            ax.text(*(at + 1.1 * d), label, color=LOAD_RGB, fontsize=8)


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
    fixed: list[np.ndarray] | None = None,
) -> Any:
    """Draw one state's surfaces into a new subplot of ``fig`` at ``grid`` (rows, cols, index); returns its axes.

    ``fixed`` (per surface, a mask of fixed points, see :func:`fixed_points`) draws fixed faces and
    pinned vertices in :data:`FIXED_RGB`.
    """
    fixed = fixed if fixed is not None else [np.zeros(len(v), dtype=bool) for v in state]
    if dim == 2:
        from matplotlib.collections import PolyCollection

        ax = fig.add_subplot(*grid)
        for k, (v, f, still) in enumerate(zip(state, faces, fixed, strict=True)):
            color = FIXED_RGB if still.all() else palette(k % 10)
            if len(f):
                face_rgb = np.where(still[f].all(axis=1)[:, None], FIXED_RGB, np.asarray(color[:3])[None])
                ax.add_collection(
                    PolyCollection(v[f], facecolors=np.c_[face_rgb, np.full(len(f), 0.35)], edgecolors="none")
                )
                ax.triplot(v[:, 0], v[:, 1], f, color=color, linewidth=0.5)
            else:
                ax.plot(v[:, 0], v[:, 1], "o", color=color, markersize=2)
            if still.any() and not still.all():
                ax.plot(v[still, 0], v[still, 1], "s", color=FIXED_RGB, markersize=3)
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
        for k, (v, f, still) in enumerate(zip(state, faces, fixed, strict=True)):
            rgb = np.asarray(palette(k % 10))
            if len(f):
                tris.append(v[f])
                shaded = _shade(v[f], rgb)
                still_faces = still[f].all(axis=1)
                shaded[still_faces] = _shade(v[f][still_faces], np.asarray(FIXED_RGB))
                colors.append(shaded)
            else:
                ax.scatter(v[:, 0], v[:, 1], v[:, 2], color=FIXED_RGB if still.all() else rgb, s=2)
            if still.any() and not still.all():
                ax.scatter(v[still, 0], v[still, 1], v[still, 2], color=FIXED_RGB, marker="s", s=6)
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
    return ax


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name) or "surface"


def frames_in(directory: str | Path) -> list[Path]:
    """The ``frame_XXXX_<surface>.ply`` files :func:`export_meshes` wrote into ``directory`` before, sorted (none
    where the folder does not exist)."""
    directory = Path(directory)
    return sorted(directory.glob("frame_[0-9][0-9][0-9][0-9]_*.ply")) if directory.is_dir() else []


def export_meshes(scene: Scene, q: Tensor, directory: str | Path, frame: int) -> list[Path]:
    """Write every surface of ``scene`` at configuration ``q`` as ``frame_XXXX_<surface>.ply``.

    2D surfaces get z = 0. A surface without faces is written as a point cloud.

    Args:
        scene: The scene.
        q: Free configuration, shape [n].
        directory: Output folder (created if needed).
        frame: Frame number (>= 0), zero-padded to four digits in the file names.

    Returns:
        The paths written, in ``scene.surfaces`` order.

    Raises:
        DependencyNotInstalled: without trimesh.
        ValueError: a scene without surfaces, a configuration that is not finite, a negative frame, or two surfaces
            whose file names coincide (one would overwrite the other).
    """
    if not scene.surfaces:
        raise ValueError(f"scene {scene.name!r} has no surfaces to export")
    if not bool(torch.isfinite(torch.as_tensor(q)).all()):
        raise ValueError("the configuration q is not finite: no mesh to export")
    try:
        index = -1 if isinstance(frame, bool) else operator.index(frame)  # an int, a NumPy or one-number torch integer
    except TypeError:
        index = -1
    if index < 0:
        raise ValueError(f"frame must be an integer >= 0, got {frame!r}")
    frame = index
    trimesh = _require("trimesh")
    names = [_safe_name(surface.name) for surface in scene.surfaces]
    same = sorted({name for name in names if names.count(name) > 1})
    if same:  # one file would overwrite the other
        raise ValueError(f"surfaces of scene {scene.name!r} share file names {same}: give them distinct names")
    meshes = surface_meshes(scene, q)  # a q of the wrong shape is refused before the folder is made
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, mesh in zip(names, meshes, strict=True):
        geometry = mesh if len(mesh.faces) else trimesh.PointCloud(mesh.vertices)
        path = directory / f"frame_{frame:04d}_{name}.ply"
        geometry.export(path)
        paths.append(path)
    return paths
