"""The kind registry of subspace checkpoints: every kind loads back as itself; an unknown kind is a clear error."""

from __future__ import annotations

import json
import os

import pytest
import torch

from redsim import scenes, subspace
from redsim.subspace import KINDS, AnchoredSubspace, LinearSubspace, QuadraticSubspace, SubspaceMap


def _maps(n: int) -> list[torch.nn.Module]:
    g = torch.Generator().manual_seed(0)
    basis = torch.randn(n, 2, generator=g, dtype=torch.float64)
    offset = torch.randn(n, generator=g, dtype=torch.float64)
    quadratic = QuadraticSubspace(basis, offset, torch.randn(n, 3, generator=g, dtype=torch.float64))
    return [
        SubspaceMap(subspace.SubspaceConfig(2, n, hidden_width=4, hidden_layers=1, periodic=(1,))),
        LinearSubspace(basis, offset),
        quadratic,
        AnchoredSubspace(subspace.SubspaceConfig(2, n, hidden_width=4, hidden_layers=2), quadratic, radius=1.0),
    ]


def test_every_kind_round_trips_through_the_registry(tmp_path) -> None:
    scene = scenes.build("toy_two_tets")
    z = torch.randn(4, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    for sub in _maps(scene.free_dof_count):
        sub.metadata.update({"scene": scene.name, "scene_fingerprint": scene.fingerprint()})
        weights, _ = sub.save(tmp_path / sub.kind)
        loaded = subspace.load_subspace(weights, scene=scene)
        assert type(loaded) is KINDS[sub.kind] is type(sub)
        zz = z.to(next(iter(sub.state_dict().values())).dtype)
        with torch.no_grad():
            torch.testing.assert_close(loaded(zz), sub(zz), rtol=0, atol=0)
    assert set(KINDS) == {"neural", "linear", "quadratic", "autoencoder", "anchored"}


def test_an_unknown_kind_names_the_valid_ones(tmp_path) -> None:
    _, meta = LinearSubspace(torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)).save(
        tmp_path / "map"
    )
    doc = json.loads(meta.read_text())
    meta.write_text(json.dumps({**doc, "kind": "spline"}))
    valid = "neural, anchored, autoencoder, linear, quadratic"
    with pytest.raises(subspace.CheckpointError, match=f"unknown kind 'spline'; valid: {valid}"):
        subspace.load_subspace(tmp_path / "map.pt")


def test_an_interrupted_write_keeps_the_previous_file_whole(tmp_path) -> None:
    path = tmp_path / "map.pt"
    path.write_text("previous")

    def interrupted(tmp) -> None:
        tmp.write_text("half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        subspace.write_atomically(path, interrupted)
    assert path.read_text() == "previous" and sorted(p.name for p in tmp_path.iterdir()) == ["map.pt"]
    subspace.write_atomically(path, lambda tmp: tmp.write_text("next"))
    assert path.read_text() == "next" and sorted(p.name for p in tmp_path.iterdir()) == ["map.pt"]


def test_two_writers_of_one_file_each_write_their_own_temporary(tmp_path) -> None:
    """SubprocVecEnv workers fitting one cached map write the same files: one shared NAME.tmp made the second
    writer's replace fail (FileNotFoundError), or moved a file the other was still writing. Each temporary keeps
    the file's name before its last dot (torch.save names its archive so: the same weights, the same bytes), and
    `redsim cache clear` knows a stale one."""
    path = tmp_path / "map.fit.pt"
    seen = []

    def outer(tmp) -> None:
        seen.append(tmp.name)
        tmp.write_text("outer")
        subspace.write_atomically(path, lambda inner: (seen.append(inner.name), inner.write_text("inner")))

    subspace.write_atomically(path, outer)  # the inner writer finishes while the outer one is still writing
    assert path.read_text() == "outer" and sorted(p.name for p in tmp_path.iterdir()) == ["map.fit.pt"]
    assert seen[0] != seen[1] and all(n.startswith("map.fit.pt.") and n.endswith("tmp") for n in seen)
    from redsim.usercache import TEMPORARY

    assert all(TEMPORARY.fullmatch(n)["name"] == "map.fit.pt" for n in seen)  # cache clear takes a stale one
    import os
    import stat

    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~umask  # mkstemp's 0600 would make it the owner's alone


def test_old_format_weights_load_and_a_failed_pair_write_leaves_nothing(tmp_path) -> None:
    """A .pt in torch's older (non-zip) format loads as before (a zip check refused it); a checkpoint whose second
    temporary cannot be made (a name too long) leaves no first one behind."""
    import shutil

    import torch

    from redsim import pretrained
    from redsim.subspace.checkpoint import write_checkpoint

    shipped = pretrained.path("mini_chain")
    shutil.copy(shipped.with_suffix(".json"), tmp_path / "m.json")
    weights = torch.load(shipped, weights_only=True)
    torch.save(weights, tmp_path / "m.pt", _use_new_zipfile_serialization=False)
    assert subspace.load_subspace(tmp_path / "m").latent_dim == 4
    long = tmp_path / "long"
    long.mkdir()
    with pytest.raises(OSError):
        write_checkpoint(torch.nn.Linear(2, 2), long / ("a" * 240), {})
    assert list(long.iterdir()) == []


def test_a_pair_written_by_two_saves_is_refused(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A save killed between its two replaces left the new weights beside the old fit's .json: a map of the same
    shapes loaded silently with another fit's metadata (settings, metrics, command). The .json records the weights'
    hash, and a load of a pair that disagrees says so."""
    import os

    config = subspace.SubspaceConfig(2, 6, hidden_width=4, hidden_layers=1)
    old, new = SubspaceMap(config), SubspaceMap(config)
    with torch.no_grad():
        for p in new.parameters():
            p.add_(1.0)
    old.save(tmp_path / "map")
    real, calls = os.replace, []

    def killed_before_the_json(src, dst) -> None:
        calls.append(dst)
        if str(dst).endswith(".json"):
            raise KeyboardInterrupt  # as a SIGKILL there would: the .pt replaced, the .json not
        real(src, dst)

    monkeypatch.setattr(os, "replace", killed_before_the_json)
    with pytest.raises(KeyboardInterrupt):
        new.save(tmp_path / "map")
    monkeypatch.undo()
    assert [p.name for p in calls] == ["map.pt", "map.json"]
    with pytest.raises(subspace.CheckpointError, match=r"map\.pt: the weights are not those map\.json describes"):
        subspace.load_subspace(tmp_path / "map")
    new.save(tmp_path / "map")  # a whole pair loads
    assert subspace.map_fingerprint(subspace.load_subspace(tmp_path / "map")) == subspace.map_fingerprint(new)


def test_the_next_write_removes_a_killed_writer_s_temporary_and_keeps_a_live_one(tmp_path) -> None:
    """A fit killed (SIGKILL) while writing its training state left ``m.fit.pt.XXXXXXXXtmp`` beside ``m.fit.pt``
    (measured: 3 of 6 kills of ``redsim fit mini_chain --checkpoint-every 1``), there for good. A writer holds a lock
    on its temporary until it is done, which a kill releases: the next write of the file removes the unlocked ones
    and leaves a writer's in flight alone (SubprocVecEnv workers write one cached map at once)."""
    import time

    path = tmp_path / "m.fit.pt"
    killed = tmp_path / "m.fit.pt.ui0_30udtmp"  # the name and empty file a kill left (no writer holds it)
    killed.touch()
    other = tmp_path / "n.fit.pt.ui0_30udtmp"  # another file's: not this write's to judge
    other.touch()
    written = time.time() - 2 * subspace.checkpoint.DEAD_AFTER_S  # both left by a kill two minutes ago
    for old in (killed, other):
        os.utime(old, (written, written))

    def outer(tmp) -> None:
        tmp.write_text("outer")
        os.utime(tmp, (written, written))  # as old: only its lock keeps it
        subspace.write_atomically(path, lambda inner: inner.write_text("inner"))
        assert tmp.is_file() and not killed.exists()  # the outer writer's temporary, locked, is kept

    subspace.write_atomically(path, outer)
    assert path.read_text() == "outer" and sorted(p.name for p in tmp_path.iterdir()) == ["m.fit.pt", other.name]


def test_a_filesystem_without_flock_saves_unlocked_and_removes_nothing(tmp_path, monkeypatch) -> None:
    """Where ``flock`` fails (Lustre mounted ``-o noflock`` answers ENOSYS), a save failed and left its
    temporary (``m.pt.XXXXXXXXtmp``) behind: every save, where saves had worked before temporaries were locked. It
    writes unlocked there, and the next write keeps a temporary it cannot lock (it cannot tell a live one there)."""
    import errno
    import types

    from redsim.subspace import checkpoint

    def no_flock(handle: int, operation: int) -> None:
        raise OSError(errno.ENOSYS, "Function not implemented")

    monkeypatch.setattr(checkpoint, "fcntl", types.SimpleNamespace(flock=no_flock, LOCK_EX=2, LOCK_NB=4))
    unknown = tmp_path / "m.pt.ui0_30udtmp"  # a killed writer's, or a live one's: not to be told apart here
    unknown.touch()
    new = SubspaceMap(subspace.SubspaceConfig(2, 6, hidden_width=4, hidden_layers=1))
    new.save(tmp_path / "m")
    subspace.write_atomically(tmp_path / "m.fit.pt", lambda tmp: tmp.write_text("state"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.fit.pt", "m.json", "m.pt", unknown.name]
    assert subspace.map_fingerprint(subspace.load_subspace(tmp_path / "m")) == subspace.map_fingerprint(new)


def test_without_fcntl_checkpoints_save_and_load(tmp_path) -> None:
    """Windows has no ``fcntl``: the import is guarded, a save and a load work, and no temporary is removed."""
    import subprocess
    import sys

    code = (
        "import sys; sys.modules['fcntl'] = None\n"  # its import fails, as on Windows
        "from pathlib import Path\n"
        "from redsim import subspace\n"
        "from redsim.subspace import checkpoint\n"
        "assert checkpoint.fcntl is None\n"
        "folder = Path(sys.argv[1]); (folder / 'm.pt.ui0_30udtmp').touch()\n"
        "new = subspace.SubspaceMap(subspace.SubspaceConfig(2, 6, hidden_width=4, hidden_layers=1))\n"
        "new.save(folder / 'm')\n"
        "loaded = subspace.load_subspace(folder / 'm')\n"
        "assert subspace.map_fingerprint(loaded) == subspace.map_fingerprint(new)\n"
        "print(sorted(p.name for p in folder.iterdir()))\n"
    )
    done = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["['m.json',", "'m.pt',", "'m.pt.ui0_30udtmp']"]


def test_a_mismatched_pair_beside_a_training_state_says_resume_writes_it_again(tmp_path) -> None:
    """A fit killed between its two replaces keeps its training state (``STEM.fit.pt``): its command with
    ``--resume`` writes the pair again without a step to run, where "fit the map again" alone redid the whole fit."""
    import shutil

    config = subspace.SubspaceConfig(2, 6, hidden_width=4, hidden_layers=1)
    SubspaceMap(config).save(tmp_path / "map")
    other = SubspaceMap(config)
    with torch.no_grad():
        for p in other.parameters():
            p.add_(1.0)
    other.save(tmp_path / "other")
    shutil.copyfile(tmp_path / "other.pt", tmp_path / "map.pt")  # the new .pt beside the old .json
    with pytest.raises(subspace.CheckpointError, match=r"fit the map again$"):
        subspace.load_subspace(tmp_path / "map")
    (tmp_path / "map.fit.pt").touch()
    with pytest.raises(subspace.CheckpointError, match=r"command with --resume, which writes both again from map\.fit"):
        subspace.load_subspace(tmp_path / "map")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs (Windows)")
def test_a_fifo_named_as_a_temporary_neither_hangs_a_save_nor_goes(tmp_path) -> None:
    """The next write's look at a file named as a temporary opened it to lock it: a FIFO of that name (no writer's:
    mkstemp makes plain files) made the open wait for a writer, and the save with it, forever. It is kept, unopened
    for long."""
    import threading

    fifo = tmp_path / "m.pt.ui0_30udtmp"
    os.mkfifo(fifo)
    save = threading.Thread(
        target=subspace.write_atomically, args=(tmp_path / "m.pt", lambda tmp: tmp.write_text("saved")), daemon=True
    )
    save.start()
    save.join(3.0)
    hung = save.is_alive()
    if hung:  # let it go: a writer's open ends the reader's wait
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        save.join(3.0)
    assert not hung and fifo.exists() and (tmp_path / "m.pt").read_text() == "saved"


def test_a_temporary_written_within_a_minute_is_kept_though_no_writer_locks_it(tmp_path) -> None:
    """A writer that takes no lock (redsim before locks, or one on another host where flock is each host's own: NFS
    mounted nolock) had its temporary removed mid-write by the next write of the file, and its own replace failed
    (FileNotFoundError; reproduced with two processes). A temporary written within DEAD_AFTER_S is kept."""
    import time

    path = tmp_path / "m.fit.pt"
    in_flight = tmp_path / "m.fit.pt.ui0_30udtmp"  # an unlocked writer's, just written
    in_flight.write_text("half")
    subspace.write_atomically(path, lambda tmp: tmp.write_text("saved"))
    assert in_flight.read_text() == "half"
    written = time.time() - 2 * subspace.checkpoint.DEAD_AFTER_S  # its writer killed two minutes ago
    os.utime(in_flight, (written, written))
    assert subspace.checkpoint.remove_dead_temporaries(path) == [in_flight] and not in_flight.exists()
