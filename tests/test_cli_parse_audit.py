"""The command line's shared argument checks (redsim.cli.common) on the inputs the hand mutation audit (helper-283)
found no test giving: each check below was loosened by a one-line mutation that every CLI test passed.

- ``--load`` with fewer components than the scene's dimension (``!=`` loosened to ``>``), and a handle loaded twice
  (the second would silently win);
- a comma-separated count of 0 (``parse_ints``: ``--batches``, ``--sweep``, ``--damping-divisions``);
- a file a command cannot write (a full disk) exits with status 1 (redsim.cli's documented status), in one line: as
  status 2 (bad input) it passed every CLI test;
- ``redsim cache --older-than 0`` (every file) is taken: refused with the bound made strict, it passed;
- ``redsim animate --keys 1`` and ``redsim sample -n 0`` are refused before the checkpoint is read (a loop needs two
  keys, a sample one state; each bound loosened by one passed).
"""

from __future__ import annotations

import errno

import pytest
import torch

from redsim import SceneBuilder
from redsim.cli.common import CliError, parse_ints, parse_loads


def _scene_3d():
    builder = SceneBuilder(3)
    ids = builder.add_particles(torch.zeros(2, 3), torch.ones(2))
    builder.add_handle("tip", builder.particle_points(ids[1:]))
    return builder.finalize("two_points")


def test_a_load_with_too_few_or_too_many_components_is_refused() -> None:
    scene = _scene_3d()
    assert parse_loads(["tip=1,2,3"], scene) == {"tip": [1.0, 2.0, 3.0]}
    for given in ("tip=1,2", "tip=1", "tip=1,2,3,4"):
        with pytest.raises(CliError, match=r"component\(s\), but scene 'two_points' is 3D"):
            parse_loads([given], scene)


def test_a_handle_loaded_twice_is_refused() -> None:
    with pytest.raises(CliError, match="--load gives handle 'tip' twice"):
        parse_loads(["tip=1,2,3", "tip=0,0,1"], _scene_3d())


@pytest.mark.parametrize("text", ["0", "2,0", "-1,4"])
def test_a_count_below_one_is_refused(text: str) -> None:
    with pytest.raises(CliError, match="--batches must be >= 1"):
        parse_ints(text, "--batches")
    assert parse_ints("1,4", "--batches") == [1, 4]


def test_a_file_the_command_cannot_write_exits_with_status_1(monkeypatch, capsys) -> None:
    import redsim.cli.scenes
    from redsim.cli import main

    def full_disk(args):
        raise OSError(errno.ENOSPC, "No space left on device", "runs/out.json")

    monkeypatch.setattr(redsim.cli.scenes, "cmd_scenes", full_disk)
    assert main(["scenes"]) == 1
    captured = capsys.readouterr()
    assert captured.err == "redsim: error: No space left on device: runs/out.json\n" and captured.out == ""


def test_cache_older_than_zero_days_is_taken(tmp_path, monkeypatch, capsys) -> None:
    from redsim.cli import main

    monkeypatch.setenv("REDSIM_CACHE", str(tmp_path))
    assert main(["cache", "info", "--older-than", "0", "--json"]) == 0
    assert main(["cache", "clear", "--older-than", "0", "--dry-run", "--json"]) == 0
    assert capsys.readouterr().err == ""


def test_animate_needs_two_keys(tmp_path, capsys) -> None:
    from redsim.cli import main

    out = str(tmp_path / "loop.gif")
    assert main(["animate", str(tmp_path / "none.pt"), "--keys", "1", "--frames", "4", "--out", out]) == 2
    assert "need --keys >= 2 and --frames >= --keys, got 1 and 4" in capsys.readouterr().err


def test_sample_needs_one_state(tmp_path, capsys) -> None:
    from redsim.cli import main

    assert main(["sample", str(tmp_path / "none.pt"), "-n", "0", "--out", str(tmp_path / "s.npz")]) == 2
    assert "-n must be an integer >= 1, got 0" in capsys.readouterr().err
