"""`redsim fit`, `inspect`, `sample` and `animate` on a toy scene, and their errors."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from redsim import pretrained, scenes
from redsim.cli import main
from redsim.keyframes import catmull_rom_loop
from redsim.subspace import read_metadata


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> str:
    stem = tmp_path_factory.mktemp("fit") / "tl"
    code = main(
        [
            "fit",
            "toy_three_link_chain",
            "--steps",
            "40",
            "--dim",
            "2",
            "--sigma",
            "0.05",
            "--width",
            "16",
            "--layers",
            "2",
            "--out",
            str(stem),
            "--json",
        ]
    )
    assert code == 0
    return str(stem) + ".pt"


def test_fit_writes_checkpoint_with_reproducing_command(fitted: str) -> None:
    meta = json.loads(open(fitted.replace(".pt", ".json")).read())
    assert meta["scene"] == "toy_three_link_chain" and meta["fit"]["steps"] == 40
    assert meta["command"].startswith("redsim fit toy_three_link_chain ")
    assert "--dim 2" in meta["command"] and "--width 16" in meta["command"]


def test_refit_from_the_recorded_command_reproduces_the_weights(fitted: str, tmp_path) -> None:
    meta = json.loads(open(fitted.replace(".pt", ".json")).read())
    argv = meta["command"].split()[1:]
    argv[argv.index("--out") + 1] = str(tmp_path / "again")
    assert main([*argv, "--json"]) == 0
    a = torch.load(fitted, weights_only=True)
    b = torch.load(tmp_path / "again.pt", weights_only=True)
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_inspect_prints_metadata(capsys: pytest.CaptureFixture[str], fitted: str) -> None:
    code, out, _ = run(capsys, "inspect", fitted, "--json")
    assert code == 0
    doc = json.loads(out)
    assert doc["latent_dim"] == 2 and doc["n"] == 36 and "final" in doc
    code, out, _ = run(capsys, "inspect", fitted)
    assert code == 0 and "reproduce: redsim fit" in out and "conditions:" not in out and "anchor map" not in out
    stem = str(Path(fitted).parent / "anchored")
    fit = ("fit", "toy_two_tets", "--steps", "4", "--width", "8", "--layers", "1", "--dim", "2", "--anchor-map", "md")
    assert run(capsys, *fit, "--out", stem)[0] == 0
    code, out, _ = run(capsys, "inspect", stem + ".pt")
    assert code == 0 and "  anchor map: --anchor-map md --anchor-map-cond default\n" in out, out
    code, out, _ = run(capsys, "inspect", str(pretrained.path("conditional_bar")))  # what f(z, c) takes, in order
    assert code == 0 and "  conditions: stiffness_ratio in [0.2, 5.0], pin_location in [0.3, 1.0]\n" in out, out


def test_sample_exports_states(capsys: pytest.CaptureFixture[str], fitted: str, tmp_path) -> None:
    out_path = tmp_path / "states.npz"
    code, out, _ = run(capsys, "sample", fitted, "-n", "50", "--out", str(out_path), "--json")
    assert code == 0 and json.loads(out)["finite"]
    data = np.load(out_path)
    assert data["q"].shape == (50, 36) and data["z"].shape == (50, 2)
    assert str(data["scene"]) == "toy_three_link_chain"


def test_sample_writes_meshes_with_faces(capsys: pytest.CaptureFixture[str], fitted: str, tmp_path) -> None:
    import trimesh

    code, out, _ = run(
        capsys, "sample", fitted, "-n", "2", "--out", str(tmp_path / "s"), "--meshes", str(tmp_path / "m")
    )
    assert code == 0 and "meshes (.ply, faces included)" in out
    written = sorted((tmp_path / "m").glob("frame_*.ply"))
    surfaces = len(scenes.build("toy_three_link_chain").surfaces)
    assert len(written) == 2 * surfaces and written[0].name.startswith("frame_0000_")
    mesh = trimesh.load(written[0])
    assert len(mesh.faces) > 0 and np.isfinite(mesh.vertices).all()


def test_animate_writes_gif(capsys: pytest.CaptureFixture[str], fitted: str, tmp_path) -> None:
    gif = tmp_path / "loop.gif"
    code, _, _ = run(capsys, "animate", fitted, "--keys", "3", "--frames", "6", "--out", str(gif))
    assert code == 0 and gif.read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    from PIL import Image

    for fps, frame_ms in (("15", 70), ("45", 20), ("50", 20)):  # rounded to the 10 ms a GIF holds (Pillow: 60, 20)
        code, _, _ = run(capsys, "animate", fitted, "--keys", "2", "--frames", "2", "--fps", fps, "--out", str(gif))
        with Image.open(gif) as image:
            assert code == 0 and image.info["duration"] == frame_ms, fps


def _interrupted_write(*args: Any, **kwargs: Any) -> None:
    """A writer (a function or method whose first path or file argument is its output) that leaves half a file and
    is interrupted (Ctrl-C while the file is written)."""
    out = next(a for a in args if isinstance(a, str | Path) or hasattr(a, "write"))
    if hasattr(out, "write"):
        out.write(b"PK\x03\x04 half")
    else:
        Path(out).write_bytes(b"half")
    raise KeyboardInterrupt


@pytest.mark.parametrize(
    ("command", "name", "target"),
    [
        (("sample", "-n", "3"), "states.npz", "numpy.savez_compressed"),
        (("animate", "--keys", "2", "--frames", "2"), "loop.gif", "PIL.Image.Image.save"),
    ],
    ids=["sample", "animate"],
)
def test_ctrl_c_while_writing_leaves_the_file_there_before(
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    fitted: str,
    tmp_path: Path,
    command: tuple[str, ...],
    name: str,
    target: str,
) -> None:
    """sample's .npz and animate's .gif were written in place: Ctrl-C while writing left a broken file (a .npz
    whose arrays np.load could not read) over the good one; now a temporary file is renamed onto it."""
    path = tmp_path / name
    assert run(capsys, command[0], fitted, *command[1:], "--out", str(path))[0] == 0
    before = path.read_bytes()
    monkeypatch.setattr(target, _interrupted_write)
    code, _, err = run(capsys, command[0], fitted, *command[1:], "--seed", "1", "--out", str(path))
    assert code == 130 and "interrupted" in err
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]  # no temporary left


def test_simulate_picture_is_written_whole_or_not_at_all(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from matplotlib.figure import Figure

    monkeypatch.setattr(Figure, "savefig", _interrupted_write)
    code, _, _ = run(capsys, "simulate", "toy_three_link_chain", "--steps", "1", "--out", str(tmp_path))
    assert code == 130 and list(tmp_path.iterdir()) == []


def test_sample_and_animate_a_float64_fit(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    """The latents are drawn in the map's dtype: a float64 map was given float32 ones (a matmul dtype error)."""
    stem = str(tmp_path / "d64")
    fit = ("fit", "toy_two_tets", "--steps", "4", "--width", "8", "--layers", "1", "--dim", "2", "--dtype", "float64")
    assert run(capsys, *fit, "--out", stem)[0] == 0
    code, _, err = run(capsys, "sample", stem + ".pt", "-n", "3", "--out", str(tmp_path / "s.npz"))
    assert code == 0 and np.load(tmp_path / "s.npz")["q"].shape == (3, 6), err
    code, _, err = run(
        capsys, "animate", stem + ".pt", "--keys", "2", "--frames", "2", "--out", str(tmp_path / "a.gif")
    )
    assert code == 0 and (tmp_path / "a.gif").is_file(), err


def test_catmull_rom_loop_passes_through_keys_and_closes() -> None:
    keys = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=torch.float64)
    path = catmull_rom_loop(keys, 40)
    assert torch.allclose(path[::10], keys)
    assert torch.allclose(catmull_rom_loop(keys, 4), keys)


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["fit", "nope"], "unknown scene"),
        (["fit", "toy_two_tets", "--sigma", "-1"], "sigma"),
        (["fit", "toy_two_tets", "--cond"], "no condition space"),
        (["fit", "toy_two_tets", "--resume", "--out", "no_such_dir/x"], "nothing to resume"),
        (
            ["fit", "toy_two_tets", "--steps", "4", "--stop-at", "4", "--out", "no_such_dir/x"],
            "--stop-at must be >= 0 and < the fit's --steps (4), got 4",
        ),
        (["fit", "toy_two_tets", "--drive", "10", "--out", "no_such_dir/x"], "declares no driver"),
        (["fit", "toy_crank", "--drive", "10", "--out", "no_such_dir/x"], "not periodic (periodic []; --periodic)"),
        (["fit", "toy_crank", "--soften", "rigid,nope", "--out", "no_such_dir/x"], "no effect(s) ['nope']"),
        (["fit", "toy_crank", "--soften-from", "0"], "--soften-from must be a number in (0, 1]"),
        (["inspect", "/nonexistent/model.pt"], "model.pt: the weights file is missing"),
        (["sample", "/nonexistent/model.pt"], "model.pt: the weights file is missing"),
        (["animate", "/nonexistent/model.pt"], "model.pt: the weights file is missing"),
        (["bench", "fit", "--scenes", "nope"], "unknown scene"),
        (["bench", "fit", "--steps", "0"], "--steps must be >= 1"),
    ],
)
def test_fit_family_errors_are_one_line_exit_2(
    capsys: pytest.CaptureFixture[str], argv: list[str], expected: str
) -> None:
    code, _, err = run(capsys, *argv)
    assert code == 2, err
    assert expected in err and "Traceback" not in err and err.count("\n") == 1


def test_inspect_refuses_a_checkpoint_of_changed_scene(
    capsys: pytest.CaptureFixture[str], fitted: str, tmp_path
) -> None:
    meta = json.loads(open(fitted.replace(".pt", ".json")).read())
    meta["scene_params"]["joint_stiffness"] = 123.0  # the JSON now describes another scene
    (tmp_path / "m.json").write_text(json.dumps(meta))
    (tmp_path / "m.pt").write_bytes(open(fitted, "rb").read())
    code, _, err = run(capsys, "inspect", str(tmp_path / "m.pt"))
    assert code == 2 and "not to scene" in err


def test_bench_subspace_compares_neural_modes_and_derivatives(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    code, out, _ = run(
        capsys,
        "bench",
        "subspace",
        "--scenes",
        "toy_tiny_bar_2d",
        "--steps",
        "30",
        "--loads",
        "2",
        "--samples",
        "16",
        "--checkpoints",
        str(tmp_path),
        "--json",
    )
    assert code == 0
    row = json.loads(out)["rows"][0]
    assert set(row["methods"]) == {"neural", "modes", "modal_derivatives"}
    for result in row["methods"].values():
        assert result["stretch"]["mean"] > 0 and len(result["load_response"]["errors"]) == 2
    assert (tmp_path / "toy_tiny_bar_2d_s30.pt").is_file() and row["steps"] == 30
    code, out, _ = run(
        capsys,
        "bench",
        "subspace",
        "--scenes",
        "toy_tiny_bar_2d",
        "--steps",
        "30",
        "--loads",
        "2",
        "--samples",
        "16",
        "--checkpoints",
        str(tmp_path),
    )
    assert code == 0 and "modal_derivatives" in out and "load error" in out
    assert "toy_tiny_bar_2d_s30.pt" in out  # reused, not refitted
    assert out.startswith("machine: ") and "strain" in out


def test_bench_subspace_uses_the_shipped_subspace(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    argv = ["bench", "subspace", "--scenes", "mini_chain", "--loads", "1", "--samples", "8"]
    code, out, err = run(capsys, *argv, "--checkpoints", str(tmp_path), "--json")
    assert code == 0, err
    row = json.loads(out)["rows"][0]
    assert row["checkpoint"] == str(pretrained.path("mini_chain")) and not list(tmp_path.iterdir())
    assert row["steps"] == read_metadata(pretrained.path("mini_chain"))["fit"]["steps"]
    response = row["methods"]["neural"]["load_response"]
    assert response["response_fraction"] == 0.1 and len(response["response_errors"]) == 1
    code, out, err = run(capsys, *argv, "--load-size", "0", "--checkpoints", str(tmp_path))
    assert code == 2 and "--load-size" in err


def test_speed_switches_are_recorded_and_do_not_block_resume(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    stem = str(tmp_path / "sw")
    argv = ["fit", "toy_two_tets", "--steps", "6", "--dim", "2", "--width", "8", "--layers", "1", "--out", stem]
    code, out, err = run(capsys, *argv, "--checkpoint-every", "3", "--no-fused-adam", "--json")
    assert code == 0, err
    meta = json.loads(out)
    assert meta["fit"]["fused_adam"] is False and meta["fit"]["compile"] is False
    assert meta["command"].endswith("--no-fused-adam --out " + stem)
    code, out, err = run(capsys, *argv, "--checkpoint-every", "3", "--fused-adam", "--resume", "--json")
    assert code == 0, err
    assert json.loads(out)["fit"]["fused_adam"] is False  # no step ran: the map is the saved fit's, so is its record
    extended = [*argv[:3], "8", *argv[4:]]  # --steps 8: two more steps, run fused
    code, out, err = run(capsys, *extended, "--checkpoint-every", "3", "--fused-adam", "--resume", "--json")
    assert code == 0, err
    assert json.loads(out)["fit"]["fused_adam"] is True


def test_a_stem_ending_in_fit_is_refused_and_a_map_saved_there_before_still_loads(
    capsys: pytest.CaptureFixture[str], tmp_path
) -> None:
    """STEM.fit.pt is a fit's training state: a map saved as X.fit.pt was refused by inspect as an unfinished fit, and
    a --resume of X took it for X's training state (a KeyError traceback)."""
    code, _, err = run(capsys, "fit", "toy_two_tets", "--steps", "2", "--out", str(tmp_path / "a.fit"))
    assert code == 2 and "a stem ending in .fit would save the map as" in err and "choose another --out" in err, err
    for suffix in (".pt", ".json"):  # a map saved there by an earlier version
        (tmp_path / f"a.fit{suffix}").write_bytes(pretrained.path("mini_chain").with_suffix(suffix).read_bytes())
    code, out, err = run(capsys, "inspect", str(tmp_path / "a.fit.pt"))
    assert code == 0 and "mini_chain" in out, err
    code, _, err = run(capsys, "fit", "mini_chain", "--steps", "4", "--out", str(tmp_path / "a"), "--resume")
    assert code == 2 and "not a fit's training state (it lacks" in err and err.count("\n") == 1, err


def test_more_latents_than_dofs_are_warned_about_and_bench_subspace_refuses_them(
    capsys: pytest.CaptureFixture[str], tmp_path
) -> None:
    """toy_two_tets (n = 6) has no preset, so FitConfig's d = 8: fit said nothing, and bench subspace fitted the map
    and then crashed in the modal baselines; its --steps 0 was a traceback."""
    argv = ["fit", "toy_two_tets", "--steps", "2", "--width", "8", "--layers", "1", "--out", str(tmp_path / "t")]
    code, _, err = run(capsys, *argv)
    assert code == 0 and "d = 8 latents for toy_two_tets's n = 6 free DOFs" in err, err
    bench = ["bench", "subspace", "--scenes", "toy_two_tets", "--checkpoints", str(tmp_path / "b")]
    code, _, err = run(capsys, *bench, "--steps", "2")
    assert code == 2 and "the modal baselines need d <= n" in err and err.count("\n") == 1, err
    assert not (tmp_path / "b").exists() or not list((tmp_path / "b").iterdir())  # refused before any fit
    code, _, err = run(capsys, *bench, "--steps", "0")
    assert code == 2 and "--steps must be an integer >= 1" in err and err.count("\n") == 1, err


def test_bench_fit_times_the_real_fit_loop_in_interleaved_rounds() -> None:
    from redsim.bench import bench_fit, bench_fit_variants
    from redsim.scenes import build
    from redsim.trainers import FitConfig

    scene, config = build("toy_two_tets"), FitConfig(latent_dim=2, hidden_width=8, steps=10_000)
    result = bench_fit(scene, config, steps=3, warmup=2)
    assert result["steps"] == 3 and result["warmup"] == 2 and result["fused_adam"] and not result["compile"]
    assert len(result["times_s"]) == 3 and 0 < result["min_s"] <= result["median_s"] <= result["max_s"]
    assert result["graphs_compiled_timed"] == 0 and result["n"] == 6
    variants = {"plain": {"fused_adam": False}, "fused": {"fused_adam": True}}
    rows = bench_fit_variants(scene, config, variants=variants, steps=3, warmup=1, rounds=2)
    assert list(rows) == ["plain", "fused"] and [r["fused_adam"] for r in rows.values()] == [False, True]
    assert all(r["steps"] == len(r["times_s"]) == 3 and r["rounds"] == 2 for r in rows.values())  # 2 + 1 (was 4)
    rows = bench_fit_variants(scene, config, variants=variants, steps=1, warmup=1, rounds=3)
    assert all(r["steps"] == len(r["times_s"]) == 1 and r["rounds"] == 1 for r in rows.values())  # was 3 in 3


@pytest.mark.slow
def test_bench_fit_compares_eager_fused_and_compiled(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["bench", "fit", "--scenes", "toy_two_tets", "--steps", "3", "--warmup", "1"]
    code, out, err = run(capsys, *argv, "--json")
    assert code == 0, err
    report = json.loads(out)
    assert report["machine"]["torch_threads"] == 1
    (row,) = report["rows"]
    variants = row["variants"]
    assert set(variants) == {"eager", "fused", "compiled_fused"}
    assert [(v["compile"], v["fused_adam"]) for v in variants.values()] == [(False, False), (False, True), (True, True)]
    assert all(v["median_s"] > 0 and v["graphs_compiled_timed"] == 0 for v in variants.values())
    losses = [v["final_loss"] for v in variants.values()]
    assert losses == pytest.approx([losses[0]] * 3, rel=1e-3)
    code, out, err = run(capsys, *argv)
    assert code == 0, err
    assert "toy_two_tets" in out and "machine:" in out and "compiled" in out


def test_an_option_a_preset_s_anchored_map_cannot_take_replaces_it(
    capsys: pytest.CaptureFixture[str], tmp_path
) -> None:
    """The cantilever preset fits the anchored map; --modal asks for the MLP (they cannot go together)."""
    small = ["--steps", "2", "--width", "8", "--layers", "1", "--checkpoint-every", "0", "--json"]
    assert main(["fit", "cantilever", "--modal", "10", *small, "--out", str(tmp_path / "m")]) == 0
    assert "--modal replaces the cantilever preset's --anchor-map md" in capsys.readouterr().err
    assert read_metadata(tmp_path / "m.pt")["fit"]["anchor_map"] == "none"
    assert main(["fit", "cantilever", "--modal", "10", "--anchor-map", "md", *small, "--out", str(tmp_path / "x")]) == 2
    assert "--anchor-map must be one of" in capsys.readouterr().err  # asked for both: refused, as before
    taper = ["--modal", "10", "--anchor-radius", "1.0", *small, "--out", str(tmp_path / "t")]
    assert main(["fit", "cantilever", *taper]) == 2  # a taper asks for the anchored map too
    assert "--modal cannot go with the cantilever preset's anchored map" in capsys.readouterr().err
    zero = ["--modal", "10", "--anchor-radius", "0", *small, "--out", str(tmp_path / "z")]
    assert main(["fit", "cantilever", *zero]) == 2  # a zero taper is still given: named, with a fix that works
    assert "which --anchor-radius asks to keep: drop --anchor-radius (the MLP alone)" in capsys.readouterr().err
    assert main(["fit", "cantilever", "--anchor-map", "none", *small, "--out", str(tmp_path / "n")]) == 0
    command = read_metadata(tmp_path / "n.pt")["command"]
    assert "--anchor-map none" in command  # reruns as the MLP, not as the preset's anchored map
    # a preset that also tapers its anchored map (the conditional bar's): --anchor-map none drops the taper with it
    # (it was refused: "--anchor-radius must be ... 0 without anchor_map", so the shipped map's command failed)
    tiny = ["--steps", "2", "--width", "8", "--layers", "1", "--checkpoint-every", "0", "--json"]
    assert main(["fit", "conditional_bar", "--cond", "--anchor-map", "none", *tiny, "--out", str(tmp_path / "c")]) == 0
    fit = read_metadata(tmp_path / "c.pt")["fit"]
    assert fit["anchor_map"] == "none" and fit["anchor_radius"] == 0.0
    taper = ["--anchor-map", "none", "--anchor-radius", "1.0", *tiny, "--out", str(tmp_path / "r")]
    assert main(["fit", "conditional_bar", *taper]) == 2  # a taper given with the MLP alone is still refused


def test_bench_subspace_marks_load_errors_measured_against_unconverged_references() -> None:
    """cloth_ball's row printed its load error with 5 of its 8 full-space references stopped unconverged and nothing
    said so (the warnings came only from the solve, not from a cached rerun); the row now says it."""
    from redsim.cli.bench import _subspace_row

    def row(full: list[bool], rest: bool = True) -> str:
        result = {
            "load_response": {
                "mean_error": 0.9,
                "mean_response_error": 0.9,
                "full_converged": full,
                "rest_converged": rest,
            }
        }
        header = {"scene": "s", "n": 3, "d": 1, "sigma": 0.1, "lam": 1.0, "steps": 2, "fit_seconds": 1.0}
        return _subspace_row({**header, "checkpoint": "x.pt", "methods": {"neural": result, "modes": result}})

    assert "unconverged" not in row([True] * 8)
    marked = row([True, False, False, True, False, True, False, False])
    assert marked.count("* 5 of 8 loaded full-space equilibria stopped unconverged") == 1
    assert "the load errors leave them out" in marked and "unloaded" not in marked
    rest = row([True] * 8, rest=False)
    assert "of 8 loaded" not in rest
    assert "* the unloaded full-space equilibrium stopped unconverged: the load errors measure around it" in rest


def test_a_fit_ends_with_the_accuracy_check_to_run_and_that_command_runs(
    capsys: pytest.CaptureFixture[str], tmp_path
) -> None:
    """Nothing in a fit's summary shows a map too stiff to follow its loads; it names the command that does, which
    runs on the fit (whose d = 8 > n = 6 leaves out the modal baselines: they crashed it)."""
    stem = str(tmp_path / "tt")
    code, out, err = run(capsys, "fit", "toy_two_tets", "--steps", "4", "--width", "8", "--layers", "1", "--out", stem)
    check = [line for line in out.splitlines() if "redsim bench accuracy" in line]
    assert code == 0 and len(check) == 1, (out, err)
    argv = check[0].split("redsim ", 1)[1].split()
    code, out, err = run(capsys, *argv, "--steps", "10")
    assert code == 0 and "no motion" in out and "neural maps: d=8: 4 fit steps" in out, (out, err)
    assert "no modes or modal derivatives for d > n = 6" in out
    assert "note: the reference is not a trustworthy motion" not in out
    code, out, err = run(capsys, *argv, "--steps", "10", "--max-force", "1000")  # ~60x the scene's weight on 0.2 m
    note = re.search(r"note: the reference is not a trustworthy motion: (\d+) of its 10 steps moved", out)
    assert code == 4 and note and int(note.group(1)) >= 1, (out, err)  # the command fails (bench accuracy)


def test_a_fit_that_runs_away_is_warned_about(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    """A learning rate far too large drove the map's samples to ~1e4 sigma at ~1e31 J, and fit said nothing."""
    argv = ["fit", "toy_tiny_bar_2d", "--sigma", "100", "--lr", "1", "--steps", "60", "--out", str(tmp_path / "r")]
    code, _, err = run(capsys, *argv)
    assert code == 0 and "as far as sigma (100) asks, at a final energy of" in err and "smaller --lr" in err, err


def test_bench_subspace_and_fit_report_a_scene_that_raises_and_keep_rows_at_ctrl_c(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path
) -> None:
    """A scene that raised ended bench subspace / bench fit in a traceback, losing the other scenes, and Ctrl-C lost
    the JSON document: now the scene is a ``failed`` line (exit 1), and Ctrl-C prints the finished ones (exit 130)."""
    import redsim.bench

    def failing(real, error_on):
        def bench(scene, *args, **kwargs):
            if scene.name in error_on:
                raise error_on[scene.name]
            return real(scene, *args, **kwargs)

        return bench

    real = redsim.bench.compare_subspaces
    argv = ["bench", "subspace", "--scenes", "mini_chain,klann", "--loads", "0", "--samples", "8"]
    argv += ["--checkpoints", str(tmp_path)]
    monkeypatch.setattr(redsim.bench, "compare_subspaces", failing(real, {"mini_chain": RuntimeError("boom")}))
    code, out, err = run(capsys, *argv)
    assert code == 1 and "failed: mini_chain: RuntimeError: boom" in out and "klann  n=60" in out, err
    assert "bench subspace: 1 scene(s) failed (mini_chain); the others ran" in err
    monkeypatch.setattr(redsim.bench, "compare_subspaces", failing(real, {"klann": KeyboardInterrupt()}))
    code, out, err = run(capsys, *argv, "--json")
    doc = json.loads(out)
    assert code == 130 and doc["interrupted"] and [r["scene"] for r in doc["rows"]] == ["mini_chain"], err

    timing = {"median_s": 1e-3, "startup_s": 0.5, "graphs_compiled_timed": 0}
    fake = {variant: timing for variant in ("eager", "fused", "compiled_fused")}
    argv = ["bench", "fit", "--scenes", "toy_two_tets,mini_chain", "--steps", "1", "--warmup", "1"]
    errors = {"toy_two_tets": RuntimeError("no fit")}
    monkeypatch.setattr(redsim.bench, "bench_fit_variants", failing(lambda *a, **k: fake, errors))
    code, out, err = run(capsys, *argv, "--json")
    doc = json.loads(out)
    assert code == 1 and doc["failed"] == [{"scene": "toy_two_tets", "error": "RuntimeError: no fit"}], err
    assert [r["scene"] for r in doc["rows"]] == ["mini_chain"] and not doc["interrupted"]
    errors["mini_chain"] = KeyboardInterrupt()
    code, out, err = run(capsys, *argv)
    assert code == 130 and "failed: toy_two_tets: RuntimeError: no fit" in out, err
    assert out.rstrip().endswith("interrupted: the scenes finished before it")


def test_compile_without_a_cpp_compiler_is_exit_2_and_writes_nothing(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """`redsim fit --compile` where no C++ compiler runs: one line naming the fix, exit 2, before any file is written
    or an --overwrite removes the old state (it was an Inductor traceback, exit 1, from the first step)."""
    from torch._inductor import cpp_builder, exc

    def missing() -> str:
        raise exc.InvalidCxxCompiler

    monkeypatch.setattr(cpp_builder, "get_cpp_compiler", missing)
    small = ["toy_two_tets", "--steps", "2", "--dim", "2", "--width", "8", "--layers", "1", "--batch", "4"]
    code, _, err = run(capsys, "fit", *small, "--compile", "--out", str(tmp_path / "new"))
    assert code == 2 and "compile needs a C++ compiler" in err and "fit without --compile" in err
    assert "Traceback" not in err and not list(tmp_path.iterdir())
    assert main(["fit", *small, "--out", str(tmp_path / "old"), "--json"]) == 0
    state = (tmp_path / "old.fit.pt").read_bytes()
    code, _, err = run(capsys, "fit", *small, "--compile", "--overwrite", "--out", str(tmp_path / "old"))
    assert code == 2 and (tmp_path / "old.fit.pt").read_bytes() == state


def test_a_path_that_starts_with_a_tilde_is_in_the_home_folder(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--out=~/runs/tt`` (the shell leaves it as typed) made a folder named ``~`` in the working folder, and a
    quoted ``'~/runs/tt.pt'`` was not found."""
    home, work = tmp_path / "home", tmp_path / "work"
    home.mkdir()
    work.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(work)
    small = ("--dim", "2", "--width", "8", "--layers", "1", "--steps", "5", "--threads", "1")
    code, _, err = run(capsys, "fit", "toy_two_tets", *small, "--out=~/runs/tt")
    assert code == 0, err
    assert (home / "runs" / "tt.pt").is_file() and not (work / "~").exists()
    code, out, err = run(capsys, "inspect", "~/runs/tt.pt", "--json")
    assert code == 0, err
    assert json.loads(out)["checkpoint"] == str(home / "runs" / "tt.pt")


def test_the_bench_command_fit_suggests_quotes_a_path_with_spaces(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """The suggested ``redsim bench accuracy PATH ...`` split a stem with a space into two arguments."""
    stem = tmp_path / "my runs" / "t t"
    small = ("--dim", "2", "--width", "8", "--layers", "1", "--steps", "5", "--threads", "1")
    code, out, err = run(capsys, "fit", "toy_two_tets", *small, "--out", str(stem))
    assert code == 0, err
    hint = next(line for line in out.splitlines() if "redsim bench accuracy" in line)
    argv = shlex.split(hint.partition("full space: ")[2])
    assert argv[:4] == ["redsim", "bench", "accuracy", f"{stem}.pt"], hint


def test_an_interrupted_fit_says_so_in_one_line(
    capsys: pytest.CaptureFixture[str],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The fitter's log warning ``redsim: WARNING: redsim.trainers.fit: interrupted after step N; rerun with --resume
    to continue (STEM.fit.pt)`` came before the command's own line, which says it with the command to continue."""
    import contextlib
    import logging
    from collections.abc import Callable, Iterator

    from redsim.trainers import fit as fitter

    @contextlib.contextmanager
    def ctrl_c_in_step_3() -> Iterator[Callable[[], None]]:
        steps = iter(range(1, 10**6))

        def interrupt_point() -> None:
            if next(steps) == 3:
                raise KeyboardInterrupt

        yield interrupt_point

    monkeypatch.setattr(fitter, "deferred_interrupts", ctrl_c_in_step_3)
    small = ("--dim", "2", "--width", "8", "--layers", "1", "--steps", "50", "--threads", "1", "--json")
    with caplog.at_level(logging.WARNING):
        code, out, err = run(capsys, "fit", "toy_two_tets", *small, "--out", str(tmp_path / "t"))
    assert code == 130 and out == "", err
    assert err.count("\n") == 1 and err.startswith(f"redsim: warning: interrupted; the state is in {tmp_path}"), err
    assert [r.getMessage() for r in caplog.records] == []
    assert not logging.getLogger(fitter.__name__).filters  # the command's filter is gone after it
