"""The checkpoint format shared by every kind of subspace map: ``STEM.pt`` + ``STEM.json``.

``STEM.pt`` is the module's state dict; ``STEM.json`` holds the format version, the map's
``config`` (what its kind needs to rebuild an empty module of the right shape) and its
``metadata`` (scene name and fingerprint, hyperparameters, metrics, the reproducing command).
Nothing is pickled. Which class a checkpoint rebuilds is decided by :mod:`redsim.subspace.kinds`.
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import json
import os
import re
import stat
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from redsim.scene import Scene, check_scene_type

try:
    import fcntl
except ImportError:  # Windows: no flock, so temporaries are neither locked nor removed as dead
    fcntl = None  # type: ignore[assignment]

FORMAT_VERSION = 1
PAIR_KEY = "map_fingerprint"
"""The key of a checkpoint's ``.json`` that records its ``.pt``'s :func:`map_fingerprint` (absent in older ones)."""


class CheckpointError(ValueError):
    """A checkpoint that is missing, corrupt, or made for another scene."""

    def __init__(self, message: str, path: str = "") -> None:
        super().__init__(f"{path}: {message}" if path else message)
        self.path = path


def map_fingerprint(subspace: nn.Module) -> str:
    """Hash of a map's weights (as float32, so a float64 copy of the same map matches)."""
    digest = hashlib.sha256()
    for key, value in sorted(subspace.state_dict().items()):
        digest.update(key.encode())
        if value.is_floating_point():
            value = value.to(torch.float32)
        digest.update(value.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]


def checkpoint_path(path: str | Path, suffix: str) -> Path:
    """``STEM + suffix`` for a checkpoint given as ``STEM``, ``STEM.pt`` or ``STEM.json``.

    Suffixes are appended, never swapped, so stems with dots ("bar_sigma0.3") stay whole.
    """
    path = Path(path)
    stem = path.with_suffix("") if path.suffix in (".pt", ".json") else path
    return stem.with_name(stem.name + suffix)


BESIDE = {".cubature.json": "a cubature", ".rest.json": "a shipped map's rest start"}
"""Files kept beside a checkpoint ``STEM.pt`` as ``STEM + suffix``, by suffix: what each is."""


def beside_checkpoint(path: str | Path) -> str | None:
    """Why ``path`` is not a checkpoint when it is a file of :data:`BESIDE` given in its place (naming the map it
    belongs to where that exists), else None."""
    name = Path(path).name
    for suffix, what in BESIDE.items():
        if name.endswith(suffix):
            mapped = Path(path).with_name(name[: -len(suffix)] + ".pt")
            where = f", {mapped}" if mapped.is_file() else " (a fit's STEM.pt)"
            return f"{path} is {what}, not a checkpoint: give the subspace it belongs to{where}"
    return None


def write_atomically(path: Path, write: Callable[[Path], Any]) -> None:
    """Call ``write(tmp)`` on a temporary file beside ``path``, then move it onto ``path``: an interrupted write
    leaves the previous file whole (and no partial one under its name). A killed writer's temporaries of ``path`` go
    first (:func:`remove_dead_temporaries`)."""
    remove_dead_temporaries(path)
    with _temporary(path) as tmp:
        write(tmp)
        os.replace(tmp, path)


@contextlib.contextmanager
def _temporary(path: Path) -> Iterator[Path]:
    """A new empty file ``NAME.XXXXXXXXtmp`` beside ``path`` (``NAME``), this writer's own, locked (``flock``) until
    the block ends and removed then if still there: two processes writing the same file (SubprocVecEnv workers
    fitting one cached map) each replace it whole (one shared ``NAME.tmp`` made the second one's replace fail, or
    moved a file the other was still writing), and a temporary no writer holds is a killed one's
    (:func:`remove_dead_temporaries`). ``NAME`` whole before the last dot: ``torch.save`` names its archive after the
    file without its last suffix, so a checkpoint's bytes stay those of the same weights written at any time;
    ``redsim cache clear`` knows a stale one (:data:`TEMPORARY`)."""
    while True:
        handle, name = tempfile.mkstemp(dir=path.parent, prefix=f"{path.name}.", suffix="tmp")
        _lock(handle)
        if os.fstat(handle).st_nlink:  # not removed as dead between its making and the lock
            break
        os.close(handle)
    try:
        umask = os.umask(0)  # mkstemp makes it 0600: the file it becomes gets the mode a plain write would give it
        os.umask(umask)
        os.chmod(name, 0o666 & ~umask)
        yield Path(name)
    finally:
        Path(name).unlink(missing_ok=True)  # before the lock goes: no one takes a live write's file for dead
        os.close(handle)


def _lock(handle: int) -> None:
    """Take an exclusive ``flock`` on the open file ``handle``, where the filesystem has one: where ``flock`` fails
    (Lustre mounted ``-o noflock``: ENOSYS) the temporary goes unlocked and the write goes on, as before locks
    were taken; :func:`remove_dead_temporaries` cannot lock it there either, so keeps it."""
    if fcntl is not None:
        with contextlib.suppress(OSError):
            fcntl.flock(handle, fcntl.LOCK_EX)


TEMPORARY_PART = re.compile(r"\.[a-z0-9_]{8}tmp")
"""What :func:`_temporary` appends to the name of the file it will replace: mkstemp's random part, ``tmp``."""


DEAD_AFTER_S = 60.0
"""Age [s] since its last write past which a temporary no writer holds counts as a killed writer's. A writer that
holds no lock writes in far less (the 10 MB training state of hanging_sheet's map: 9 ms, AMD EPYC) and is kept: a
redsim before locks, or one on another host where ``flock`` is each host's own (NFS mounted ``nolock``)."""


def remove_dead_temporaries(path: Path) -> list[Path]:
    """Remove the temporaries of ``path`` (:func:`_temporary`'s) that no writer holds and none wrote for
    :data:`DEAD_AFTER_S`: a killed writer's (SIGKILL, a crash), left beside ``path`` for good; a writer's in flight
    holds its lock, or writes, and is kept. Returns those removed (none where ``flock`` is missing: Windows)."""
    removed: list[Path] = []
    if fcntl is None or not path.parent.is_dir():
        return removed
    for tmp in path.parent.glob(f"{glob.escape(path.name)}.*tmp"):
        if not TEMPORARY_PART.fullmatch(tmp.name[len(path.name) :]):
            continue
        try:  # without waiting for a writer where it is a FIFO (a plain open waited forever)
            handle = os.open(tmp, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0))
        except OSError:  # removed meanwhile (its writer done), or a link
            continue
        try:
            opened = os.fstat(handle)
            if not stat.S_ISREG(opened.st_mode):  # not a file a writer made: a folder, a FIFO
                continue
            if time.time() - opened.st_mtime < DEAD_AFTER_S:  # maybe an unlocked writer's, in flight
                continue
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            if os.path.samestat(opened, tmp.stat()):  # still the file that was opened
                tmp.unlink()
                removed.append(tmp)
        except OSError:  # a live writer's (locked), or removed meanwhile
            pass
        finally:
            os.close(handle)
    return removed


def write_checkpoint(module: nn.Module, stem: str | Path, config: dict[str, Any]) -> tuple[Path, Path]:
    """Write ``stem.pt`` (the module's state dict) and ``stem.json`` (format version, ``config``, the module's
    ``metadata`` and ``map_fingerprint``, the weights' :func:`map_fingerprint`, by which a load refuses a pair that
    two saves wrote: one killed between its two replaces); returns both paths. Shared by every kind of subspace."""
    weights, meta = checkpoint_path(stem, ".pt"), checkpoint_path(stem, ".json")
    weights.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        **getattr(module, "metadata", {}),
        "format_version": FORMAT_VERSION,
        "config": config,
        PAIR_KEY: map_fingerprint(module),
    }
    text = json.dumps(doc, indent=2, sort_keys=True, default=_json_default)  # fails before any file is touched
    # both written in full before either replaces its file (an interruption while writing keeps the old pair); the
    # first temporary is removed too where the second cannot be made (a name too long for it)
    remove_dead_temporaries(weights)
    remove_dead_temporaries(meta)
    with _temporary(weights) as tmp_weights, _temporary(meta) as tmp_meta:
        torch.save(module.state_dict(), tmp_weights)
        tmp_meta.write_text(text)
        os.replace(tmp_weights, weights)
        os.replace(tmp_meta, meta)
    return weights, meta


def _json_default(value: Any) -> Any:
    if isinstance(value, Tensor):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON-serializable: {type(value).__name__}")


def read_metadata(path: str | Path) -> dict[str, Any]:
    """The JSON beside a checkpoint (``X.pt`` or ``X.json`` or the stem ``X``)."""
    meta = checkpoint_path(path, ".json")
    if not meta.is_file():
        raise CheckpointError("no metadata file (expected a .json beside the .pt)", str(meta))
    try:
        doc = json.loads(meta.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise CheckpointError(f"metadata is not valid JSON ({err})", str(meta)) from None
    if not isinstance(doc, dict):  # valid JSON, but no checkpoint's (a list, null, a string)
        raise CheckpointError(f"metadata is not a JSON object (got {type(doc).__name__})", str(meta))
    if doc.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(_format_version_error(doc), str(meta))
    return doc


def _format_version_error(doc: dict[str, Any]) -> str:
    """What a metadata document of another (or no) ``format_version`` is, and what to do about it."""
    version = doc.get("format_version")
    said = f"unsupported format_version {version!r} (this redsim reads {FORMAT_VERSION})"
    if isinstance(version, int) and not isinstance(version, bool) and version > FORMAT_VERSION:
        return f"{said}: written by a newer redsim; upgrade redsim to read it"
    if isinstance(version, int) and not isinstance(version, bool):
        command = doc.get("command")
        again = f" ({command})" if isinstance(command, str) else ""
        return f"{said}: written by an older redsim; fit it again with the command it records{again}"
    return f"{said}: not a redsim checkpoint's metadata; give a fit's STEM.pt (STEM.json beside it)"


def scene_record(scene: Scene) -> str:
    """The scene as a checkpoint's metadata records it (name, fingerprint, parameters, n), as JSON text: what
    :func:`scene_mismatch` reads back (``json.loads``), kept where a checkpoint's ``.json`` is not (a fit's training
    state), so a refusal names the parameters that differ, not only two fingerprints."""
    doc = {
        "scene": scene.name,
        "scene_fingerprint": scene.fingerprint(),
        "scene_params": scene.params,
        "config": {"output_dim": scene.free_dof_count},
    }
    return json.dumps(doc, sort_keys=True, default=_json_default)


def scene_mismatch(doc: dict[str, Any], scene: Scene) -> str | None:
    """How the scene a checkpoint's metadata ``doc`` records differs from ``scene`` (name, fingerprint or n, and the
    parameters that differ), or None where it is this scene."""
    mine = (doc.get("scene"), doc.get("scene_fingerprint"), (doc.get("config") or {}).get("output_dim"))
    theirs = (scene.name, scene.fingerprint(), scene.free_dof_count)
    if (mine[0], mine[2]) == (theirs[0], theirs[2]) and scene.accepts(mine[1]):
        return None
    recorded = doc.get("scene_params") or {}
    differs = [
        f"{key} {recorded.get(key)!r} (this scene: {scene.params.get(key)!r})"
        for key in sorted(set(recorded) | set(scene.params))
        if recorded.get(key) != scene.params.get(key)
    ]
    where = f"; it records {', '.join(differs)}" if mine[0] == theirs[0] and differs else ""
    return (
        f"fitted to scene {mine[0]!r} (fingerprint {mine[1]}, n={mine[2]}), not to scene {theirs[0]!r} "
        f"(fingerprint {theirs[1]}, n={theirs[2]}){where}"
    )


def check_pair(doc: dict[str, Any], module: nn.Module, path: str) -> None:
    """Refuse weights ``module`` (loaded from ``path``, ``STEM.pt``) other than those the metadata ``doc`` of its
    ``.json`` records (:data:`PAIR_KEY`; a ``.json`` without it is not checked)."""
    recorded = doc.get(PAIR_KEY)
    if recorded is not None and recorded != (found := map_fingerprint(module)):
        meta, state = checkpoint_path(path, ".json").name, checkpoint_path(path, ".fit.pt")
        resume = (
            f" (a fit's: rerun the interrupted fit's command with --resume, which writes both again from {state.name} "
            "without fitting anew)"
            if state.is_file()
            else ""
        )
        raise CheckpointError(
            f"the weights are not those {meta} describes (weights hash {found}, the .json records {recorded}): the "
            f"two files come from two saves (one interrupted between writing them?); save or fit the map again{resume}",
            path,
        )


def check_scene(doc: dict[str, Any], scene: Scene, path: str) -> None:
    """Refuse a checkpoint whose metadata ``doc`` names another scene (:func:`scene_mismatch`), and a scene that
    is not a :class:`Scene` (a TypeError)."""
    check_scene_type(scene)
    if (why := scene_mismatch(doc, scene)) is not None:
        raise CheckpointError(f"{why}; build the scene with the parameters in the .json", path)
