"""redsim's user cache: which folders it has, what they hold, and deleting them (the API and ``redsim cache``)."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest
import torch

import redsim
from redsim.cli import main
from redsim.envs.base import cached
from redsim.envs.fitted import cache_stem
from redsim.integrators import cache as equilibria
from redsim.usercache import FOLDERS, ClearError, cache_root, clear_user_cache, user_cache_usage

WEEK = 7 * 86400.0
STEM = "mini_chain-" + "a" * 16 + "-" + "b" * 12
"""A fitted map's cache stem (redsim.envs.fitted.cache_stem: SCENE-FINGERPRINT-OPTIONS)."""
NAMES = {
    "equilibria": ("0" * 64 + ".npz", "1" * 64 + ".npz"),
    "subspaces": (STEM + ".pt", STEM.replace("a", "c") + ".json"),
    "envs": ("rest-latent-" + "2" * 64 + ".npz", "3" * 64 + ".npz"),
}
"""Two files of each folder, named as redsim names them (the first is written now, the second a week ago)."""


@pytest.fixture
def root(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A user cache with two of redsim's files in each folder (one a week old), plus files the cache does not own
    (at the root, in a subfolder, of another kind, and a fresh temporary file: another process's write in flight)."""
    root = tmp_path / "cache"
    monkeypatch.setenv("REDSIM_CACHE", str(root))
    week = time.time() - WEEK
    for name, (new, old) in NAMES.items():
        (root / name).mkdir(parents=True)
        (root / name / new).write_bytes(b"x" * 10)
        (root / name / old).write_bytes(b"x" * 100)
        os.utime(root / name / old, (week, week))
    (root / "mine.txt").write_text("not the cache's")  # $REDSIM_CACHE may point at a user's folder
    (root / "envs" / "nested").mkdir()
    (root / "envs" / "nested" / "keep.npz").write_bytes(b"x")
    (root / "envs" / "notes.txt").write_text("a user's")
    (root / "envs" / ".abc.npz.tmp").write_bytes(b"in flight")
    return root


def _counts(usage: list) -> dict[str, tuple[int, int]]:
    return {u.name: (u.files, u.bytes) for u in usage}


def test_the_folders_are_those_the_caches_write_to(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    assert equilibria.cache_directory() == tmp_path / "equilibria"
    scene = redsim.scenes.build("toy_two_tets")
    assert cache_stem("toy_two_tets", scene, {}).parent == tmp_path / "subspaces"
    cached({}, ("test_usercache", 1), lambda: torch.zeros(2), disk="probe")
    assert [p.parent for p in tmp_path.rglob("*.npz")] == [tmp_path / "envs"]
    assert set(FOLDERS) == {"equilibria", "subspaces", "envs"}


def test_usage_counts_the_files_of_each_folder(root: Path) -> None:
    assert _counts(user_cache_usage()) == {name: (2, 110) for name in FOLDERS}
    assert _counts(user_cache_usage(["envs"], older_than_days=1)) == {"envs": (1, 100)}
    assert user_cache_usage()[0].path == root / "equilibria"


def test_clear_deletes_only_the_named_folders_files(root: Path) -> None:
    deleted = clear_user_cache(["envs", "equilibria"], older_than_days=1.5)
    assert _counts(deleted) == {"envs": (1, 100), "equilibria": (1, 100)}
    kept = [".abc.npz.tmp", "nested", "notes.txt", NAMES["envs"][0]]
    assert sorted(p.name for p in (root / "envs").iterdir()) == kept
    assert _counts(clear_user_cache()) == {"equilibria": (1, 10), "subspaces": (2, 110), "envs": (1, 10)}
    assert _counts(user_cache_usage()) == {name: (0, 0) for name in FOLDERS}
    assert (root / "mine.txt").is_file() and (root / "envs" / "nested" / "keep.npz").is_file()
    assert (root / "envs" / "notes.txt").is_file() and (root / "envs" / ".abc.npz.tmp").is_file()


def test_clear_leaves_linked_folders_and_files_alone_and_takes_stale_temporaries(root: Path, tmp_path: Path) -> None:
    """A linked cache folder could lead to a user's files: neither it nor a linked file is counted or deleted; a
    temporary file left by an interrupted writer more than a day ago is the cache's."""
    user = tmp_path / "documents"
    user.mkdir()
    (user / "thesis.npz").write_bytes(b"precious")
    for path in (root / "envs").iterdir():
        if path.is_file():
            path.unlink()
    (root / "envs" / "nested" / "keep.npz").unlink()
    (root / "envs" / "nested").rmdir()
    (root / "envs").rmdir()
    (root / "envs").symlink_to(user, target_is_directory=True)
    (root / "equilibria" / "linked.npz").symlink_to(user / "thesis.npz")
    for stale in (root / "subspaces" / f"{STEM}.fit.pt.tmp", root / "equilibria" / ".k2x_9abc.npz.tmp"):
        stale.write_bytes(b"x")  # write_atomically's before stop 44; write_arrays's (a random name)
        os.utime(stale, (time.time() - 2 * 86400.0,) * 2)
    assert _counts(user_cache_usage())["envs"] == (0, 0)
    assert _counts(clear_user_cache()) == {"equilibria": (3, 111), "subspaces": (3, 111), "envs": (0, 0)}
    assert (user / "thesis.npz").read_bytes() == b"precious" and (root / "equilibria" / "linked.npz").is_symlink()


def test_a_users_own_files_in_a_folder_named_like_the_caches_are_not_the_caches(root: Path) -> None:
    """$REDSIM_CACHE may name a user's folder, whose subspaces/ holds the user's fits (README: `redsim fit chain --out
    subspaces/chain`): any *.pt and *.json there were counted and deleted as cache; only redsim's names are now."""
    mine = [
        root / "subspaces" / name for name in ("chain.pt", "chain.json", "chain.fit.pt", "part-v2.pt", "chain.pt.tmp")
    ]
    mine += [root / "envs" / "states.npz", root / "equilibria" / "reference.npz"]
    week = time.time() - WEEK
    for path in mine:
        path.write_bytes(b"a fit of the user's")
        os.utime(path, (week, week))
    assert _counts(user_cache_usage()) == {name: (2, 110) for name in FOLDERS}
    assert _counts(clear_user_cache()) == {name: (2, 110) for name in FOLDERS}
    assert all(path.read_bytes() == b"a fit of the user's" for path in mine)


def test_equilibria_clear_cache_on_disk_uses_the_same_deletion(root: Path) -> None:
    equilibria.clear_cache(disk=True)
    assert _counts(user_cache_usage()) == {"equilibria": (0, 0), "subspaces": (2, 110), "envs": (2, 110)}


@pytest.mark.parametrize("bad", [{"folders": ["cache"]}, {"older_than_days": -1.0}, {"older_than_days": float("nan")}])
def test_bad_arguments_are_refused_before_anything_is_deleted(root: Path, bad: dict) -> None:
    with pytest.raises(ValueError, match=r"cache folder|older_than_days"):
        clear_user_cache(**bad)
    assert _counts(user_cache_usage()) == {name: (2, 110) for name in FOLDERS}


def test_with_the_cache_off_there_is_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("REDSIM_CACHE", "0")
    assert cache_root() is None and user_cache_usage() == [] and clear_user_cache() == []


def test_cli_info_and_clear(root: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["cache", "info", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["root"] == str(root) and [f["files"] for f in info["folders"]] == [2, 2, 2]
    assert main(["cache", "info"]) == 0
    text = capsys.readouterr().out
    assert str(root) in text and "6 files      330 B" in text  # not 0.00033 MB
    assert main(["cache", "clear", "envs", "--dry-run", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["deleted"][0]["files"] == 2
    assert _counts(user_cache_usage(["envs"])) == {"envs": (2, 110)}
    assert main(["cache", "clear", "subspaces", "--older-than", "3"]) == 0
    assert "deleted 1 file (100 B)" in capsys.readouterr().out
    assert _counts(user_cache_usage(["subspaces"])) == {"subspaces": (1, 10)}


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["cache", "clear", "models"], "unknown cache folder(s) models"),
        (["cache", "clear", "--older-than", "-2"], "--older-than must be a finite number"),
        (["cache", "info", "--older-than", "inf"], "--older-than must be a finite number"),
        (["cache"], "ACTION"),
    ],
)
def test_cli_refuses_bad_input(root: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str) -> None:
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert _counts(user_cache_usage()) == {name: (2, 110) for name in FOLDERS}


def test_cli_with_the_cache_off(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("REDSIM_CACHE", "off")
    assert main(["cache", "clear"]) == 0
    assert "the user cache is off" in capsys.readouterr().out


def test_cli_info_says_where_the_cache_is_not_made_yet_or_cannot_be(tmp_path, monkeypatch, capsys) -> None:
    """A missing root or $REDSIM_CACHE naming a file printed the same zero counts as an empty cache folder."""
    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path / "none"))
    assert main(["cache", "info"]) == 0
    assert "(not made yet: nothing is cached)" in capsys.readouterr().out
    (tmp_path / "afile").write_text("x")
    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path / "afile"))
    assert main(["cache", "info"]) == 0
    assert "which is not a folder: nothing can be cached there" in capsys.readouterr().err
    assert main(["cache", "info", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["state"] == "not a folder"


def test_files_that_cannot_be_deleted_are_reported_after_the_others_are(
    root: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A read-only entry (another user's file in a shared cache) stopped clear at the first such file, leaving the
    rest, and `redsim cache clear` printed only the OS error: what it had deleted went unsaid."""
    locked = root / "equilibria" / NAMES["equilibria"][0]
    unlink = Path.unlink

    def refuse(path: Path, missing_ok: bool = False) -> None:
        if path == locked:
            raise PermissionError(13, "Permission denied", str(path))
        unlink(path, missing_ok=missing_ok)

    monkeypatch.setattr(Path, "unlink", refuse)
    with pytest.raises(ClearError, match=rf"could not delete {locked} of redsim's user cache \(Permission denied\)"):
        clear_user_cache()
    assert _counts(user_cache_usage()) == {"equilibria": (1, 10), "subspaces": (0, 0), "envs": (0, 0)}
    assert main(["cache", "clear"]) == 1
    out, err = capsys.readouterr()
    assert out.count("deleted 0 files") == 3 and f"could not delete {locked}" in err
    assert main(["cache", "clear", "--json"]) == 1
    assert json.loads(capsys.readouterr().out)["failed"] == [str(locked)]
