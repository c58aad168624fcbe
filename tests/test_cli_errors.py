"""The CLI's answers to a new user's mistakes, and the options every computing command shares."""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

import redsim
from redsim.cli import build_parser
from redsim.subspace import CheckpointError, load_subspace, read_metadata
from redsim.trainers import FitConfig

Cli = Callable[..., tuple[int, str, str]]
SMALL = ["--dim", "2", "--width", "8", "--layers", "1"]


def test_version(cli: Cli) -> None:
    code, out, _ = cli("--version")
    assert code == 0 and out.strip() == f"redsim {redsim.__version__}"
    done = subprocess.run([sys.executable, "-m", "redsim", "--version"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == f"redsim {redsim.__version__}"


def test_a_stdout_that_is_not_utf8_gets_escapes_not_a_traceback() -> None:
    """fit's help (σ, ρ) ended in a UnicodeEncodeError traceback where stdout's encoding lacks them: Windows when
    stdout is a file or a pipe (cp1252), or PYTHONIOENCODING=ascii."""
    env = {**os.environ, "PYTHONIOENCODING": "ascii"}
    argv = [sys.executable, "-m", "redsim", "fit", "--help"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0 and done.stderr == "", done.stderr
    assert "\\u03c1" in done.stdout and "\\u03c3" in done.stdout  # ρ and σ, escaped


def test_weights_of_another_scene_are_one_line_naming_both_shapes(cli: Cli, tmp_path: Path) -> None:
    for scene in ("toy_two_tets", "toy_three_link_chain"):
        assert cli("fit", scene, "--steps", "2", *SMALL, "--out", str(tmp_path / scene), "--json")[0] == 0
    (tmp_path / "mixed.json").write_bytes((tmp_path / "toy_two_tets.json").read_bytes())
    (tmp_path / "mixed.pt").write_bytes((tmp_path / "toy_three_link_chain.pt").read_bytes())
    code, out, err = cli("inspect", str(tmp_path / "mixed.pt"))
    assert code == 2 and out == "" and err.count("\n") == 1
    assert "mlp.2.weight has shape [36, 8] in the .pt but [6, 8] by the .json" in err
    assert "size mismatch" not in err
    with pytest.raises(CheckpointError, match=r"\[36, 8\] in the \.pt but \[6, 8\]"):
        load_subspace(tmp_path / "mixed.pt", scene=redsim.scenes.build("toy_two_tets"))


@pytest.mark.parametrize(
    ("flags", "expected"),
    [
        (["--steps", "0"], "--steps must be an integer >= 1, got 0"),
        (["--dim", "0"], "--dim must be an integer >= 1, got 0"),
        (["--sigma", "0"], "--sigma must be a finite number > 0, got 0.0"),
        (["--sigma", "nan"], "--sigma must be a finite number > 0, got nan"),
        (["--lam", "-1"], "--lam must be a finite number >= 0, got -1.0"),
        (["--batch", "1"], "--batch must be an integer >= 2, got 1"),
        (["--lr", "0"], "--lr must be a finite number > 0, got 0.0"),
        (["--width", "0"], "--width must be an integer >= 1, got 0"),
        (["--layers", "0"], "--layers must be an integer >= 1, got 0"),
        (["--explore", "1.5"], "--explore must be a number in (0, 1], got 1.5"),
        (["--checkpoint-every", "-1"], "--checkpoint-every must be an integer >= 0, got -1"),
        (["--dtype", "float16"], "--dtype must be one of float32, float64, got 'float16'"),
        (["--device", "abacus"], "--device must be cpu or cuda[:N], a GPU this machine has, got 'abacus'"),
        (["--dim", "2", "--periodic", "5"], "--periodic must be distinct latent indices in [0, latent_dim), got 5"),
        (["--periodic", "x"], "--periodic must be comma-separated integers"),
    ],
)
def test_fit_config_errors_name_the_flag_and_the_rule(cli: Cli, flags: list[str], expected: str) -> None:
    code, out, err = cli("fit", "toy_two_tets", *flags)
    assert code == 2 and out == "" and err.count("\n") == 1
    assert expected in err and "FitConfig(" not in err


def test_fit_config_errors_in_python_name_the_field() -> None:
    with pytest.raises(ValueError) as caught:
        FitConfig(steps=0, lam=-1.0)
    assert str(caught.value) == "lam must be a finite number >= 0, got -1.0; steps must be an integer >= 1, got 0"
    with pytest.raises(ValueError, match=r"latent_dim must be an integer >= 1, got 2\.5"):
        FitConfig(latent_dim=2.5)  # type: ignore[arg-type]


def test_resume_with_more_steps_extends_the_fit(cli: Cli, tmp_path: Path) -> None:
    stem = str(tmp_path / "ext")
    argv = ["fit", "toy_two_tets", *SMALL, "--lr", "0.01", "--out", stem, "--json"]
    code, out, err = cli(*argv, "--steps", "8")
    assert code == 0, err
    first = json.loads(out)
    assert first["schedule"] == {"lr_halved_every": 2, "rho_ramp_steps": 8, "extensions": []}
    code, out, err = cli(*argv, "--steps", "20", "--resume")
    assert code == 0, err
    meta = json.loads(out)
    assert meta["fit"]["steps"] == 20
    assert meta["schedule"] == {
        "lr_halved_every": 5,
        "rho_ramp_steps": 8,
        "extensions": [{"at_step": 8, "from_steps": 8, "to_steps": 20}],
    }
    assert meta["command"] == f"{first['command']} && {first['command'].replace('--steps 8', '--steps 20')} --resume"
    state = torch.load(stem + ".fit.pt", weights_only=True)
    assert state["step"] == 20 and len(state["history"]) == 20
    assert [h["step"] for h in state["history"]] == list(range(1, 21))
    assert state["history"][-1]["rho"] == 1.0
    assert state["optimizer"]["param_groups"][0]["lr"] == pytest.approx(0.01 * 0.5**4)  # 20 steps, halved every 5
    code, out, err = cli(*argv, "--steps", "10", "--resume")
    assert code == 2 and "steps must be >= 20 to resume, got 10: 20 steps are done" in err


def test_resume_continues_to_the_fits_own_length_and_refuses_one_ending_before_rho_is_1(
    cli: Cli, tmp_path: Path
) -> None:
    from redsim.scenes import build
    from redsim.trainers import fit_subspace

    stem = tmp_path / "cut"

    def interrupt(step: int, _terms: dict) -> None:
        if step == 5:
            raise KeyboardInterrupt

    config = FitConfig(latent_dim=2, hidden_width=8, hidden_layers=1, steps=20)  # what SMALL asks for
    with pytest.raises(KeyboardInterrupt):
        fit_subspace(build("toy_two_tets"), config, out=stem, progress=False, callbacks=[interrupt])
    argv = ["fit", "toy_two_tets", *SMALL, "--out", str(stem), "--resume", "--json"]
    code, out, err = cli(*argv, "--steps", "19")  # would stop at rho = 19/20 and save the MLP alone
    assert code == 2 and out == "" and "steps must be >= 20 to resume, got 19: rho, ramped for 20 steps" in err
    assert not (tmp_path / "cut.pt").exists()
    code, out, err = cli(*argv, "--width", "16")  # named by its flag (it said hidden_width), with the saved command
    assert code == 2 and "settings (--width: saved 8, now 16); resume with the saved ones" in err, err
    assert "recorded command has them: redsim fit toy_two_tets " in err and " --width 8 " in err, err
    code, out, err = cli(*argv)  # no --steps: the interrupted fit's 20, not FitConfig's 10000
    assert code == 0, err
    meta = json.loads(out)
    assert meta["fit"]["steps"] == 20 and meta["schedule"]["extensions"] == []
    assert torch.load(f"{stem}.fit.pt", weights_only=True)["history"][-1]["rho"] == 1.0


def test_the_recorded_command_of_an_interrupted_then_extended_fit_reproduces_it(cli: Cli, tmp_path: Path) -> None:
    from redsim.scenes import build
    from redsim.trainers import fit_subspace

    def interrupt(step: int, _terms: dict) -> None:
        if step == 7:
            raise KeyboardInterrupt  # Ctrl-C after step 7 of 12

    config = FitConfig(latent_dim=2, hidden_width=8, hidden_layers=1, steps=12)  # what SMALL asks for
    with pytest.raises(KeyboardInterrupt):
        fit_subspace(build("toy_two_tets"), config, out=tmp_path / "a", progress=False, callbacks=[interrupt])
    code, out, err = cli("fit", "toy_two_tets", *SMALL, "--steps", "20", "--out", str(tmp_path / "a"), "--resume")
    assert code == 0, err
    command = read_metadata(tmp_path / "a.pt")["command"]
    assert " --steps 12 " in command and " --stop-at 7 && " in command and command.endswith(" --resume")
    outputs = []
    for part in command.split(" && "):  # run the record into an empty folder
        argv = shlex.split(part)[1:]
        argv[argv.index("--out") + 1] = str(tmp_path / "again" / "b")
        code, out, err = cli(*argv)
        assert code == 0, err
        outputs.append(out)
    a, b = (torch.load(tmp_path / name, weights_only=True) for name in ("a.pt", "again/b.pt"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert outputs[0].startswith("stopped after step 7 of 12; continue with: redsim fit toy_two_tets ")


def test_absurd_load_fails_the_step(cli: Cli) -> None:
    code, out, err = cli("simulate", "toy_two_tets", "--steps", "3", "--load", "top=1e30,0,0", "--json")
    assert code == 4
    summary = json.loads(out)
    assert summary["failed_step"] == 1 and summary["steps_run"] == 1 and summary["converged_steps"] == 0
    assert "far beyond what this scene can take" in summary["failure"]
    assert "step 1 failed" in err and "10x the scene's size" in err
    code, out, err = cli("simulate", "toy_two_tets", "--steps", "1", "--load", "top=1,0,0")
    assert code == 0 and "converged" in out
    code, out, _ = cli("simulate", "--help")
    assert "relative gradient tolerance" in " ".join(out.split())


@pytest.mark.parametrize(
    "argv",
    [
        ["simulate", "toy_two_tets"],
        ["fit", "toy_two_tets"],
        ["sample", "x.pt"],
        ["animate", "x.pt"],
        ["bench", "energy"],
        ["bench", "subspace"],
        ["bench", "fit"],
    ],
    ids=lambda a: " ".join(a[:2]),
)
def test_every_computing_command_takes_threads(argv: list[str]) -> None:
    assert build_parser().parse_args([*argv, "--threads", "3"]).threads == 3


def test_every_option_with_a_default_names_it_in_its_help() -> None:
    def options(parser: argparse.ArgumentParser, path: str) -> list[tuple[str, argparse.Action]]:
        found = []
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    found += options(sub.complete(), f"{path} {name}")  # fit's options are added on first use
            elif action.option_strings and isinstance(action.default, int | float | str) and action.help:
                found.append((f"{path} {action.option_strings[-1]}", action))
        return found

    found = options(build_parser(), "redsim")
    names = {name for name, _action in found}
    silent = [
        name
        for name, action in found
        if action.default not in (False, argparse.SUPPRESS)
        and "default" not in action.help
        and f"({action.default})" not in action.help
    ]
    assert silent == []
    assert "redsim fit --seed" in names and "redsim train-agent --algo" in names


@pytest.mark.parametrize(
    ("argv", "extras", "command"),
    [
        (["scenes", "nope"], "nope", "redsim scenes"),
        (["cache", "info", "extra"], "extra", "redsim cache info"),
        (["bench", "energy", "--scenes", "mini_chain", "--bogus"], "--bogus", "redsim bench energy"),
        (["simulate", "mini_chain", "a", "b"], "a b", "redsim simulate"),
    ],
    ids=lambda a: " ".join(a) if isinstance(a, list) else "",
)
def test_arguments_left_over_point_to_the_subcommands_help(
    cli: Cli, argv: list[str], extras: str, command: str
) -> None:
    code, out, err = cli(*argv)  # argparse named the top-level `redsim --help` for these
    assert code == 2 and out == ""
    assert err == f"redsim: error: unrecognized arguments: {extras} (see `{command} --help`)\n"


def test_threads_are_applied_and_restored(cli: Cli, monkeypatch: pytest.MonkeyPatch) -> None:
    from redsim.cli import scenes

    seen = []
    simulate = scenes.cmd_simulate
    monkeypatch.setattr(scenes, "cmd_simulate", lambda args: seen.append(torch.get_num_threads()) or simulate(args))
    before = torch.get_num_threads()
    code, _, err = cli("simulate", "toy_two_tets", "--steps", "1", "--threads", "2")
    assert code == 0, err
    assert seen == [2] and torch.get_num_threads() == before
    for threads in ("0", "99999999999", "40000"):  # an OverflowError traceback, a segfault
        code, _, err = cli("simulate", "toy_two_tets", "--threads", threads)
        assert code == 2 and f"--threads must be an integer in [1, 32768], got {threads}" in err


def test_simulate_picture_shows_loads_and_fixed_parts(tmp_path: Path) -> None:
    from redsim.render import draw_states, fixed_points

    scene = redsim.scenes.build("toy_two_tets")
    (mask,) = fixed_points(scene)
    pinned = scene.full_dof_count - scene.free_dof_count
    assert mask.sum() == pinned // 3 and 0 < mask.sum() < len(mask)
    plain = draw_states(scene, [scene.q_seed], path=tmp_path / "plain.png")
    loaded = draw_states(scene, [scene.q_seed], path=tmp_path / "load.png", loads={"top": [0.0, 5.0, 0.0]})
    import matplotlib.image

    red = [
        ((img[..., 0] > 0.7) & (img[..., 1] < 0.3) & (img[..., 2] < 0.3)).sum()
        for img in map(matplotlib.image.imread, (plain, loaded))
    ]
    assert red[0] == 0 and red[1] > 50  # the arrow (and its label) in the load colour


def test_a_picture_with_a_load_on_an_unknown_handle_is_refused(tmp_path: Path) -> None:
    from redsim.render import draw_states

    scene = redsim.scenes.build("toy_two_tets")
    with pytest.raises(ValueError, match=r"no handle\(s\) \['nope'\]; valid handles: \['top'\]"):
        draw_states(scene, [scene.q_seed], path=tmp_path / "x.png", loads={"nope": [5.0, 0.0, 0.0]})
    assert not (tmp_path / "x.png").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_fit_on_cuda_without_cuda_is_one_line(cli: Cli) -> None:
    code, _, err = cli("fit", "toy_two_tets", "--device", "cuda", "--steps", "2")
    assert code == 2 and err.count("\n") == 1 and "--device must be cpu or cuda[:N], a GPU this machine has" in err


def test_an_out_that_cannot_be_written_is_refused_before_any_work(cli: Cli, tmp_path: Path) -> None:
    (tmp_path / "file").write_text("")
    for argv in (
        ["fit", "toy_two_tets", *SMALL, "--steps", "2"],
        ["bench", "accuracy", "mini_chain", "--steps", "2", "--scenarios", "push", "--full", "none", "--no-study"],
    ):
        code, out, err = cli(*argv, "--out", str(tmp_path / "file" / "x"))
        assert code == 2 and out == "" and err.count("\n") == 1 and "cannot write --out" in err, (argv, err)
    # nothing is created on the way: a command that fails for another reason leaves no folders behind
    code, _, err = cli("fit", "toy_two_tets", "--resume", "--out", str(tmp_path / "new" / "deeper" / "x"))
    assert code == 2 and "nothing to resume" in err and not (tmp_path / "new").exists()
    from redsim import pretrained

    for argv in (["fit", "toy_two_tets", *SMALL, "--steps", "2"], ["sample", str(pretrained.path("mini_chain"))]):
        for folder in (".", str(tmp_path) + "/", str(tmp_path / "new") + "/", str(tmp_path) + "/."):  # folders
            code, _, err = cli(*argv, "--out", folder)
            assert code == 2 and err.count("\n") == 1 and "is a folder; name a file in it" in err, err
    assert not (tmp_path / "new").exists() and not (tmp_path.parent / f"{tmp_path.name}.npz").exists()
    # an empty path read as the default stem (fit, sample) or as no output (bench accuracy, sample --meshes)
    for argv in (
        *[[*a, "--out", ""] for a in (["fit", "toy_two_tets"], ["demo", "RedSim/MiniChain-v0"])],
        ["sample", str(pretrained.path("mini_chain")), "--meshes", ""],
    ):
        code, _, err = cli(*argv)
        assert code == 2 and err.count("\n") == 1 and "is empty: name a path, or leave the option out" in err, err
    # a GIF holds frame times up to 655.35 s (0.0015 fps was Pillow's struct.error); browsers play 10 ms as 100 ms
    for fps in ("0", "0.0015", "51"):
        gif = str(tmp_path / "a.gif")
        code, _, err = cli("animate", str(pretrained.path("mini_chain")), "--fps", fps, "--out", gif)
        assert code == 2 and "--fps must be a number of frames per second in [0.00153, 50]" in err
        assert not (tmp_path / "a.gif").exists()


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_an_out_in_a_folder_that_takes_no_files_is_refused_before_any_work(cli: Cli) -> None:
    """``os.access`` calls /proc writable (and every folder, for root), but nothing can be made in it: the bench
    ran to its end and lost its results."""
    from redsim import pretrained

    for argv in (
        ["bench", "accuracy", "mini_chain", "--steps", "10", "--scenarios", "push", "--full", "none", "--no-study"],
        ["bench", "scaling"],
    ):
        code, out, err = cli(*argv, "--out", "/proc/redsim_out")
        assert code == 2 and out == "" and err.count("\n") == 1, (argv, err)
        assert "cannot write --out /proc/redsim_out: no file can be made in /proc (" in err, err
    code, out, err = cli("sample", str(pretrained.path("mini_chain")), "-n", "1", "--meshes", "/proc/redsim_meshes")
    assert code == 2 and out == "" and err.count("\n") == 1, err  # was exit 1, "No such file or directory"
    assert "cannot write --meshes /proc/redsim_meshes: no file can be made in /proc (" in err, err


def test_a_cubature_beside_a_map_in_a_folder_that_takes_no_files_is_refused_before_any_work(
    cli: Cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The cubature is written beside the map: a folder where no file can be made (tried, as --out is) is refused
    before the fit of the cubature, not after it."""
    import shutil
    import tempfile

    from redsim import pretrained

    for suffix in (".pt", ".json"):
        shutil.copy(pretrained.path("mini_chain").with_suffix(suffix), tmp_path / f"m{suffix}")

    def refused(*args: object, **kwargs: object) -> object:
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "TemporaryFile", refused)
    code, out, err = cli("cubature", str(tmp_path / "m.pt"), "--elements", "5")
    assert code == 2 and out == "" and "its folder is not writable (Permission denied" in err, err


def test_an_out_folder_that_is_a_file_is_refused_before_any_work(cli: Cli, tmp_path: Path) -> None:
    existing = tmp_path / "file"
    existing.write_text("kept")
    for argv in (
        ["demo", "RedSim/MiniChain-v0", "--steps", "2"],
        ["train-agent", "RedSim/MiniChain-v0", "--steps", "10"],
        ["simulate", "mini_chain", "--steps", "1"],
        ["bench", "scaling"],
    ):
        code, out, err = cli(*argv, "--out", str(existing))
        assert code == 2 and out == "" and err.count("\n") == 1 and "it is a file, not a folder" in err, (argv, err)
    assert existing.read_text() == "kept"
    from redsim import pretrained

    states = tmp_path / "new.npz"  # sample wrote its states before it refused --meshes
    code, out, err = cli("sample", str(pretrained.path("mini_chain")), "--out", str(states), "--meshes", str(existing))
    assert code == 2 and "it is a file, not a folder" in err and not states.exists()


def test_sample_names_the_file_it_writes_and_animate_refuses_a_non_gif(cli: Cli, tmp_path: Path) -> None:
    from redsim import pretrained

    checkpoint = str(pretrained.path("mini_chain"))
    code, out, err = cli("sample", checkpoint, "-n", "2", "--out", str(tmp_path / "s.txt"))
    assert code == 0 and (tmp_path / "s.txt.npz").is_file() and str(tmp_path / "s.txt.npz") in out, err
    code, _, err = cli("animate", checkpoint, "--out", str(tmp_path / "a.mp4"))
    assert code == 2 and "--out must name a .gif file" in err and not (tmp_path / "a.mp4").exists()


def test_a_file_or_folder_that_is_no_checkpoint_is_named_as_given(cli: Cli, tmp_path: Path) -> None:
    mesh = tmp_path / "part.stl"
    mesh.write_text("solid part\nendsolid part\n")
    for given, kind in ((mesh, "a file"), (tmp_path, "a folder")):
        for command in ("inspect", "sample", "animate"):
            code, out, err = cli(command, str(given))  # was: "part.stl.pt: the weights file is missing"
            assert code == 2 and out == "" and f"{given} is {kind}, not a checkpoint: give a fit's STEM.pt" in err


def test_a_cubature_or_rest_start_given_as_a_checkpoint_names_the_map_it_belongs_to(cli: Cli, tmp_path: Path) -> None:
    from redsim import pretrained

    shipped = pretrained.path("hanging_sheet")
    stray = tmp_path / "part.rest.json"
    stray.write_text("{}")
    cases = (
        (shipped.with_name("hanging_sheet.cubature.json"), "a cubature", f"belongs to, {shipped}"),
        (stray, "a shipped map's rest start", "belongs to (a fit's STEM.pt)"),
    )
    for given, what, names in cases:
        for command in ("inspect", "sample", "animate", "cubature"):
            flags = ["--elements", "5"] if command == "cubature" else []
            code, out, err = cli(command, str(given), *flags)  # was: "...cubature.pt: the weights file is missing"
            assert (
                code == 2 and out == "" and f"{given} is {what}, not a checkpoint: give the subspace it {names}" in err
            )


def test_a_fits_training_state_given_as_a_checkpoint_says_what_it_is(cli: Cli, tmp_path: Path) -> None:
    stem = str(tmp_path / "part")
    code, _, err = cli("fit", "toy_two_tets", *SMALL, "--steps", "8", "--stop-at", "4", "--out", stem)
    assert code == 0 and Path(stem + ".fit.pt").is_file() and not Path(stem + ".pt").exists(), err
    for command in ("inspect", "sample", "animate", "cubature"):
        flags = ["--elements", "5"] if command == "cubature" else []
        code, out, err = cli(command, stem + ".fit.pt", *flags)  # the only file --stop-at leaves
        assert code == 2 and out == "" and err.count("\n") == 1, (command, err)
        assert f"{stem}.fit.pt is a fit's training state, not a checkpoint: the fit is unfinished" in err
        code, _, err = cli(command, stem + ".pt", *flags)
        assert code == 2 and f"the weights file is missing ({stem}.fit.pt holds an unfinished fit" in err
    assert cli("fit", "toy_two_tets", *SMALL, "--steps", "8", "--out", stem, "--resume")[0] == 0
    code, _, err = cli("inspect", stem + ".fit.pt")
    assert code == 2 and f"the fitted map is {stem}.pt" in err
    assert cli("inspect", stem + ".pt")[0] == 0


def test_sample_with_only_meshes_leaves_the_states_written_before(
    cli: Cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from redsim import pretrained

    monkeypatch.chdir(tmp_path)
    checkpoint = str(pretrained.path("mini_chain"))
    assert cli("sample", checkpoint, "-n", "3")[0] == 0
    before = (tmp_path / "states.npz").read_bytes()
    code, out, err = cli("sample", checkpoint, "-n", "1", "--meshes", "samples", "--json")
    assert code == 0 and json.loads(out)["out"] is None and json.loads(out)["meshes"], err
    assert (tmp_path / "states.npz").read_bytes() == before
    assert "earlier run" not in err, err
    code, _, err = cli("sample", checkpoint, "-n", "1", "--meshes", "samples")  # the folder holds the frames above
    assert (
        code == 0 and "--meshes samples already holds 3 mesh files (frame_*.ply) from an earlier run; they stay" in err
    ), err


def test_bench_step_refuses_a_bad_dt(cli: Cli) -> None:
    code, _, err = cli("bench", "step", "--scenes", "mini_chain", "--dt", "0")
    assert code == 2 and "--dt must be a finite number >= 1e-06 [s]" in err
    code, _, err = cli("simulate", "mini_chain", "--dt", "1e-300")
    assert code == 2 and "--dt must be a finite number >= 1e-06 [s]" in err and "Traceback" not in err


def _interrupted(*args: object, **kwargs: object) -> None:
    raise KeyboardInterrupt  # what Ctrl-C (or SIGTERM, under `redsim`) raises


def test_a_fit_interrupted_before_its_first_step_says_nothing_was_saved(
    cli: Cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import redsim.trainers

    monkeypatch.setattr(redsim.trainers, "fit_subspace", _interrupted)
    code, _, err = cli("fit", "toy_two_tets", *SMALL, "--steps", "2", "--out", str(tmp_path / "x"))
    assert code == 130 and "nothing was saved, rerun: redsim fit toy_two_tets" in err and "--resume" not in err


def test_any_interrupted_command_exits_130_with_one_line_and_no_traceback(
    cli: Cli, monkeypatch: pytest.MonkeyPatch
) -> None:
    from redsim.cli import subspaces

    monkeypatch.setattr(subspaces, "load_checkpoint", _interrupted)
    code, out, err = cli("inspect", "mini_chain.pt")
    assert (code, out, err) == (130, "", "redsim: warning: interrupted\n")


INTERRUPTED_IMPORT = """
import sys

class CtrlC:
    \"\"\"Ctrl-C as the module {name!r} is about to load.\"\"\"

    def find_spec(self, name, path=None, target=None):
        if name == {name!r}:
            raise KeyboardInterrupt
        return None

sys.meta_path.insert(0, CtrlC())
from redsim.cli import main
sys.exit(main(["scenes"]))
"""
"""A ``redsim scenes`` run whose Ctrl-C comes as the module ``name`` loads: its ``import redsim.cli.bench``, say."""


@pytest.mark.parametrize("module", ["redsim.cli.parser", "redsim.cli.common", "redsim.cli.bench"])
def test_a_ctrl_c_while_the_command_line_loads_is_one_line_and_exit_130(module: str) -> None:
    """The command line's modules loaded at ``from redsim.cli import main``, before main could catch anything: a Ctrl-C
    in that first tenth of a second printed a traceback of the imports (the process died of SIGINT)."""
    argv = [sys.executable, "-c", INTERRUPTED_IMPORT.format(name=module)]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert (done.returncode, done.stdout, done.stderr) == (130, "", "redsim: warning: interrupted\n")


@pytest.mark.parametrize(
    ("command", "presses"),
    [
        (["scenes"], ("torch",)),
        (["simulate", "toy_two_tets", "--steps", "1"], ("torch",)),
        (["fit", "toy_two_tets", "--steps", "1"], ("torch",)),
        (["scenes"], ("torch", "torch.nn")),  # a second Ctrl-C while it loads
        (["fit", "toy_two_tets", "--steps", "1"], ("torch", "torch.nn")),
    ],
)
def test_a_ctrl_c_while_torch_loads_waits_for_it_to_load(command: list[str], presses: tuple[str, ...]) -> None:
    """A KeyboardInterrupt raised inside torch's C++ start-up aborted the process ("terminate called after throwing an
    instance of 'pybind11::error_already_set'", exit 134): the command line loads torch with Ctrl-C held, a second
    Ctrl-C too (it raised at once, as a fit step's does: two presses 50 ms apart aborted 2 runs in 8), and says the
    one line once torch has loaded."""
    code = (
        "import os, signal, sys\n"
        "class CtrlC:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        f"        if name in {presses!r}:  # as torch (and a module of it) starts to load\n"
        "            os.kill(os.getpid(), signal.SIGINT)\n"
        "        return None\n"
        "sys.meta_path.insert(0, CtrlC())\n"
        "from redsim.cli import main\n"
        f"status = main({command!r})\n"
        "print('torch loaded' if hasattr(sys.modules.get('torch'), 'nn') else 'torch not loaded')\n"
        "sys.exit(status)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert (done.returncode, done.stdout, done.stderr) == (130, "torch loaded\n", "redsim: warning: interrupted\n")


def test_a_ctrl_c_while_the_parser_is_built_is_one_line_and_exit_130(cli: Cli, monkeypatch: pytest.MonkeyPatch) -> None:
    from redsim.cli import parser

    monkeypatch.setattr(parser, "build_parser", _interrupted)
    assert cli("scenes") == (130, "", "redsim: warning: interrupted\n")


def _mini_chain_copy(folder: Path) -> Path:
    """The shipped mini_chain map's .pt and .json copied into ``folder``; returns its .pt."""
    from redsim import pretrained

    for suffix in (".pt", ".json"):
        (folder / f"mini_chain{suffix}").write_bytes(pretrained.path("mini_chain").with_suffix(suffix).read_bytes())
    return folder / "mini_chain.pt"


def test_an_interrupted_cubature_says_nothing_was_saved_and_what_to_rerun(
    cli: Cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """It said only "interrupted": whether the cubature there before was replaced, and the command, were left to guess
    (`redsim fit` says both)."""
    import redsim.cubature

    monkeypatch.setattr(redsim.cubature, "build_cubature", _interrupted)
    checkpoint, target = _mini_chain_copy(tmp_path), tmp_path / "mini_chain.cubature.json"
    code, out, err = cli("cubature", str(checkpoint), "--elements", "2")
    rerun = f"redsim cubature {shlex.quote(str(checkpoint))} --elements 2"
    assert (code, out) == (130, "") and not target.exists()
    assert err == f"redsim: warning: interrupted before {target} was written; nothing was saved, rerun: {rerun}\n"
    target.write_text("the cubature before")
    code, out, err = cli("cubature", str(checkpoint), "--elements", "2", "--overwrite")
    assert code == 130 and target.read_text() == "the cubature before"
    assert err == (
        f"redsim: warning: interrupted before {target} was written; the mini_chain.cubature.json there before is "
        f"unchanged; nothing was saved, rerun: {rerun} --overwrite\n"
    )


def test_an_interrupted_sample_says_what_it_wrote_and_what_to_rerun(
    cli: Cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import redsim.render

    export = redsim.render.export_meshes
    calls: list[int] = []

    def third_interrupted(*args: object, **kwargs: object) -> object:
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return export(*args, **kwargs)

    monkeypatch.setattr(redsim.render, "export_meshes", third_interrupted)
    checkpoint, npz, meshes = _mini_chain_copy(tmp_path), tmp_path / "s.npz", tmp_path / "meshes"
    argv = ["sample", str(checkpoint), "-n", "4", "--out", str(npz), "--meshes", str(meshes)]
    code, out, err = cli(*argv)
    assert (code, out) == (130, "") and npz.is_file()
    assert err == (
        f"redsim: warning: interrupted after writing {npz} and the meshes of 2 of 4 samples in {meshes}; rerun: "
        f"{shlex.join(['redsim', *argv])}\n"
    )
    monkeypatch.setattr(redsim.render, "export_meshes", _interrupted)
    code, out, err = cli("sample", str(checkpoint), "-n", "4", "--meshes", str(tmp_path / "other"))
    assert code == 130 and err.startswith("redsim: warning: interrupted before anything was written; rerun: "), err


def test_an_interrupted_animate_says_no_gif_was_written_and_what_to_rerun(
    cli: Cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import redsim.render

    monkeypatch.setattr(redsim.render, "animate_states", _interrupted)
    checkpoint, gif = _mini_chain_copy(tmp_path), tmp_path / "a.gif"
    gif.write_bytes(b"the GIF before")
    argv = ["animate", str(checkpoint), "--frames", "4", "--out", str(gif)]
    code, out, err = cli(*argv)
    assert (code, out) == (130, "") and gif.read_bytes() == b"the GIF before"
    assert err == (
        f"redsim: warning: interrupted before {gif} was written; the a.gif there before is unchanged; rerun: "
        f"{shlex.join(['redsim', *argv])}\n"
    )


def test_a_resume_that_keeps_the_map_keeps_its_cubature(cli: Cli, tmp_path: Path) -> None:
    stem = str(tmp_path / "k")
    argv = ["fit", "toy_two_tets", *SMALL, "--out", stem, "--json"]
    assert cli(*argv, "--steps", "4")[0] == 0
    assert cli("cubature", stem + ".pt", "--elements", "1", "--samples", "16", "--episodes", "0", "--json")[0] == 0
    weights, cubature = (tmp_path / "k.pt").read_bytes(), (tmp_path / "k.cubature.json").read_text()
    code, _, err = cli(*argv, "--steps", "4", "--resume")  # already at 4 steps: none run, the same map
    assert code == 0, err
    assert (tmp_path / "k.pt").read_bytes() == weights and (tmp_path / "k.cubature.json").read_text() == cubature
    code, _, err = cli(*argv, "--steps", "6", "--resume")  # extended: another map
    assert code == 0 and not (tmp_path / "k.cubature.json").exists(), err
    assert f"redsim: warning: removed {tmp_path / 'k.cubature.json'}: it was built for the map this fit replaced" in err


def test_a_fit_whose_sigma_is_far_too_large_for_its_scene_is_warned_about(cli: Cli, tmp_path: Path) -> None:
    argv = ["fit", "toy_two_tets", *SMALL, "--steps", "40", "--json"]
    code, out, err = cli(*argv, "--sigma", "1000", "--out", str(tmp_path / "far"))
    stretch = json.loads(out)["final"]["stretch"]
    assert code == 0 and stretch < 1e-3 and err.count("\n") == 1, err
    assert "mean metric stretch" in err and f"try --sigma near {1000 * stretch:.2g}, " in err and "--seed-bias" in err
    code, out, err = cli(*argv, "--sigma", "0.05", "--out", str(tmp_path / "near"))
    assert code == 0 and json.loads(out)["final"]["stretch"] > 0.5 and err == ""
    # the Python fit warns too (a review's fit_subspace ended at stretch 0.035 silently), naming FitConfig's fields
    config = FitConfig(latent_dim=2, hidden_width=8, hidden_layers=1, steps=40, sigma=1000.0)
    with pytest.warns(UserWarning, match=r"try sigma near .* seed_bias=True, raise lam, or exploration_fraction=0.5"):
        redsim.trainers.fit_subspace(redsim.scenes.build("toy_two_tets"), config, progress=False)


def test_a_fit_whose_loss_becomes_nan_exits_3_with_one_line(
    cli: Cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import warnings

    from redsim.trainers import fit as fit_module

    loss = fit_module.subspace_loss

    def nan_loss(*args: object, **kwargs: object) -> tuple[torch.Tensor, dict]:
        value, terms = loss(*args, **kwargs)
        return value * float("nan"), terms

    monkeypatch.setattr(fit_module, "subspace_loss", nan_loss)
    with warnings.catch_warnings():
        warnings.simplefilter("always")  # the CLI shows every warning on stderr (show_warning), not to a recorder
        code, out, err = cli("fit", "toy_two_tets", *SMALL, "--steps", "3", "--out", str(tmp_path / "n"), "--json")
    assert code == 3 and out == "" and err.count("\n") == 1
    assert err.startswith("redsim: error: loss became nan at step 0")
    assert "requires_grad" not in err  # no torch warning before the error
    assert "last state saved" not in err  # none was: nothing to name

    def nan_from_step_3(*args: object, **kwargs: object) -> tuple[torch.Tensor, dict]:
        value, terms = loss(*args, **kwargs)
        return (value * float("nan") if args[6] >= 3 else value), terms  # args[6]: the step

    monkeypatch.setattr(fit_module, "subspace_loss", nan_from_step_3)
    stem = str(tmp_path / "m")
    argv = ["fit", "toy_two_tets", *SMALL, "--steps", "6", "--checkpoint-every", "2", "--out", stem, "--json"]
    code, _, err = cli(*argv)
    assert code == 3 and err.count("\n") == 1 and "loss became nan at step 3" in err, err
    assert f"the last state saved stays in {tmp_path / 'm.fit.pt'} (a rerun with other settings" in err, err
    assert torch.load(tmp_path / "m.fit.pt", weights_only=True)["step"] == 2 and not (tmp_path / "m.pt").exists()


def test_a_closed_pipe_gives_no_traceback() -> None:
    done = subprocess.run(
        f"{sys.executable} -m redsim scenes | head -c 1", shell=True, capture_output=True, text=True, timeout=120
    )
    assert "Traceback" not in done.stderr and "BrokenPipeError" not in done.stderr, done.stderr


def test_a_fit_of_another_scene_at_the_stem_says_so_and_names_out(
    cli: Cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two meshes fitted without --out share the default stem: the second fit said "continue it with --resume",
    which then failed on the other scene's training state."""
    monkeypatch.chdir(tmp_path)
    assert cli("fit", "toy_two_tets", *SMALL, "--steps", "2", "--json")[0] == 0  # default stem: toy_two_tets_d2
    other = ["fit", "toy_two_tets", "--param", "young=2e5", *SMALL, "--steps", "2", "--json"]
    for flags in ((), ("--resume",)):
        code, _, err = cli(*other, *flags)
        assert code == 2 and "a fit of another scene is at toy_two_tets_d2.pt (the default name" in err, err
        assert "young 10000.0 (this scene: 200000.0)" in err and "--out STEM" in err and "--overwrite" in err, err
    assert cli("fit", "toy_two_tets", *SMALL, "--steps", "4", "--stop-at", "2", "--out", "cut")[0] == 0
    code, _, err = cli(*other, "--out", "cut", "--resume")  # only its training state there: it names what differs
    assert code == 2 and "a fit of another scene is at cut.fit.pt: fitted to scene 'toy_two_tets'" in err, err
    assert "young 10000.0 (this scene: 200000.0)" in err and err.count("\n") == 1, err  # said only fingerprints
    code, _, err = cli(*other, "--out", "cut")  # refused before the scene is built: it names all three ways out
    assert code == 2 and "a fit exists at cut.fit.pt: continue it with --resume" in err and "--out STEM" in err, err
    assert cli(*other, "--overwrite", "--steps", "4", "--stop-at", "2")[0] == 0  # replaced, interrupted
    resume = ("fit", "toy_two_tets", "--param", "young=2e5", *SMALL, "--json", "--resume")
    code, _, err = cli(*resume)  # the training state decides, not the replaced fit's .json beside it
    assert code == 0, err
    assert json.loads((tmp_path / "toy_two_tets_d2.json").read_text())["scene_params"]["young"] == 2e5


def test_a_fit_at_an_existing_stem_is_refused_without_resume_or_overwrite(cli: Cli, tmp_path: Path) -> None:
    stem = str(tmp_path / "f")
    argv = ["fit", "toy_two_tets", *SMALL, "--steps", "2", "--out", stem, "--json"]
    assert cli(*argv)[0] == 0
    before = (tmp_path / "f.pt").read_bytes()
    code, _, err = cli(*argv, "--seed", "1")
    assert code == 2 and "a fit exists at" in err and "--overwrite" in err
    assert (tmp_path / "f.pt").read_bytes() == before  # untouched
    mesh = ["fit", "--mesh", str(tmp_path / "not_made_yet.stl"), "--kind", "fem", "--out", stem]
    code, _, err = cli(*mesh)  # refused before the scene is built (a mesh's voxelization can take minutes)
    assert code == 2 and "a fit exists at" in err, err
    assert cli(*argv, "--resume", "--overwrite")[0] == 2
    stale = tmp_path / "f.fit.pt"
    assert stale.is_file()
    (tmp_path / "f.cubature.json").write_text("{}")  # a cubature of the map being replaced
    code, _, err = cli(*argv, "--seed", "1", "--overwrite")
    assert code == 0 and (tmp_path / "f.pt").read_bytes() != before, err
    assert f"redsim: warning: removed {tmp_path / 'f.cubature.json'}: it was built for the map this fit replaced" in err
    assert not (tmp_path / "f.cubature.json").exists()
    (tmp_path / "g.fit.pt").mkdir()  # a folder where the training state goes: refused before the fit, not after it
    code, _, err = cli("fit", "toy_two_tets", *SMALL, "--steps", "2", "--out", str(tmp_path / "g"))
    assert code == 2 and "g.fit.pt is a folder, not a file" in err and "choose another --out" in err, err


def test_cubature_flags_are_named_in_their_errors(cli: Cli, tmp_path: Path) -> None:
    from redsim import pretrained

    checkpoint = str(pretrained.path("mini_chain"))
    for argv, expected in (
        (["cubature", checkpoint, "--elements", "0"], "--elements must be an integer >= 1, got 0"),
        (["cubature", checkpoint, "--elements", "3", "--rollout-steps", "0"], "--rollout-steps must be an integer"),
        (["cubature", checkpoint, "--elements", "3", "--full", "contact", "--subsample", "contact"], "both in full"),
        (["cubature", checkpoint, "--elements", "3", "--subsample", "gravity"], "cannot be subsampled"),
        (["bench", "cubature", "mini_chain", "--elements", "0"], "--elements must be an integer >= 1, got 0"),
    ):
        code, out, err = cli(*argv)
        assert code == 2 and out == "" and err.count("\n") == 1 and expected in err, (argv, err)


@pytest.mark.parametrize(
    "argv",
    [["bench", "energy", "--budget", "-1"], ["bench", "envs", "--budget", "inf"], ["bench", "energy", "--scenes", ""]],
)
def test_bench_budgets_and_empty_scene_lists_are_refused(cli: Cli, argv: list[str]) -> None:
    code, out, err = cli(*argv)
    assert code == 2 and out == "" and err.count("\n") == 1 and ("--budget" in err or "--scenes" in err), err


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["bench", "step", "--scenes", "mini_chain,chain,mini_chain"], "--scenes gives 'mini_chain' twice"),
        (["bench", "envs", "--envs", "RedSim/MiniChain-v0, RedSim/MiniChain-v0"], "--envs gives 'RedSim/MiniChain-v0'"),
        (["bench", "energy", "--scenes", "mini_chain", "--batches", "1,32,1"], "--batches gives '1' twice"),
        (["bench", "stability", "--regimes", "stiff,stiff"], "--regimes gives 'stiff' twice"),
        (["bench", "accuracy", "mini_chain", "--scenarios", "push,push"], "--scenarios gives 'push' twice"),
        (  # two spellings of one id (Gymnasium's module prefix) or one number are one item too
            ["bench", "envs", "--envs", "RedSim/MiniChain-v0,redsim:RedSim/MiniChain-v0"],
            "--envs gives 'RedSim/MiniChain-v0' and 'redsim:RedSim/MiniChain-v0', which read the same",
        ),
        (
            ["bench", "stability", "--envs", "redsim:RedSim/MiniChain-v0,RedSim/MiniChain-v0"],
            "--envs gives 'redsim:RedSim/MiniChain-v0' and 'RedSim/MiniChain-v0', which read the same",
        ),
        (["bench", "cubature", "mini_chain", "--batches", "1,01"], "--batches gives '1' and '01', which read the same"),
        (
            ["bench", "energy", "--scenes", "mini_chain", "--batches", "1,32,01"],
            "--batches gives '1' and '01', which read the same",
        ),
        (["bench", "envs", "--batches", "2,2.0"], None),  # not an integer: the option's own message
        (["bench", "envs", "--batches", "2,02"], "--batches gives '2' and '02', which read the same"),
    ],
)
def test_a_name_given_twice_in_a_bench_list_is_refused_before_any_work(
    cli: Cli, argv: list[str], expected: str | None
) -> None:
    code, out, err = cli(*argv)
    assert code == 2 and out == "" and err.count("\n") == 1 and (expected or "comma-separated integers") in err, err


def test_inspect_prints_the_json_of_a_checkpoint_whose_scene_cannot_be_rebuilt(cli: Cli, tmp_path: Path) -> None:
    """A fit of an in-memory mesh (Python API) records no file to rebuild its scene from; inspect still reads it."""
    import json
    import shutil

    from redsim import pretrained

    shutil.copy(pretrained.path("mini_chain"), tmp_path / "mine.pt")
    doc = json.loads(pretrained.path("mini_chain").with_suffix(".json").read_text())
    doc["scene_params"] = {"builder": "cloth", "source": "<trimesh>"}
    (tmp_path / "mine.json").write_text(json.dumps(doc))
    code, out, err = cli("inspect", str(tmp_path / "mine.pt"))
    assert code == 0 and "n=24), d=4" in out and "cannot rebuild the checkpoint's scene" in err, err
    assert "reproduce:" not in out and "fit settings: redsim fit " in out and "not runnable as it is" in out
    code, _, err = cli("sample", str(tmp_path / "mine.pt"), "--out", str(tmp_path / "s.npz"))
    assert code == 2 and "cannot rebuild the checkpoint's scene" in err


@pytest.mark.parametrize(
    "argv",
    [
        ["demo", "RedSim/Klann-v0"],
        ["eval-agent", "shipped", "RedSim/Klann-v0"],
        ["train-agent", "RedSim/Klann-v0"],
        ["fit", "mini_chain"],
        ["bench", "stability"],
        ["cubature", "x.pt"],
    ],
)
def test_a_negative_seed_is_refused_by_the_parser(cli: Cli, argv: list[str]) -> None:
    bits = 32 if argv[0] == "train-agent" else 64  # stable-baselines3 seeds NumPy's legacy generator
    for seed in ("-1", str(2**bits)):  # 2**64: torch's generators overflowed (a traceback in sample and animate)
        code, out, err = cli(*argv, "--seed", seed)
        expected = f"--seed: must be an integer in [0, 2**{bits} - 1], got '{seed}'"
        assert code == 2 and out == "" and err.count("\n") == 1 and expected in err, err


def test_train_agent_refuses_a_seed_stable_baselines3_refuses() -> None:
    """SB3 refuses seeds from 2**32 when it builds the model; train_agent says so first, naming the seed (a
    review's finding: the CLI let 2**32 .. 2**64 - 1 through to SB3's own message)."""
    from redsim.trainers.agents import train_agent

    with pytest.raises(ValueError, match=r"seed must be an integer in \[0, 2\*\*32 - 1\]"):
        train_agent("RedSim/MiniChain-v0", "unused", algo="ppo", steps=16, seed=2**32)


def test_metadata_that_is_no_object_and_weights_that_are_no_zip_are_one_line_errors(cli: Cli, tmp_path: Path) -> None:
    """A .json of valid JSON but no object was an AttributeError traceback; a .pt that is no zip printed torch's
    six lines (with its advice to load it with weights_only=False)."""
    import shutil

    from redsim import pretrained

    shipped = pretrained.path("mini_chain")
    for text in ("[]", "null", '"text"'):
        shutil.copy(shipped, tmp_path / "h.pt")
        (tmp_path / "h.json").write_text(text)
        code, out, err = cli("inspect", str(tmp_path / "h.pt"))
        assert code == 2 and out == "" and err.count("\n") == 1 and "metadata is not a JSON object" in err, err
    doc = json.loads(shipped.with_suffix(".json").read_text()) | {"fit": None, "fit_seconds": None}
    doc["final"] = {"energy": None}  # hand-edited: inspect's text formatted them (TypeError, AttributeError)
    shutil.copy(shipped, tmp_path / "h.pt")
    (tmp_path / "h.json").write_text(json.dumps(doc))
    code, out, err = cli("inspect", str(tmp_path / "h.pt"))
    assert code == 0 and "in None s" in out and "final energy: None" in out, err
    shutil.copy(shipped.with_suffix(".json"), tmp_path / "t.json")
    (tmp_path / "t.pt").write_text("garbage text")
    code, out, err = cli("sample", str(tmp_path / "t.pt"), "-n", "2", "--out", str(tmp_path / "s.npz"))
    assert (
        code == 2 and err.count("\n") == 1 and "weights are corrupt or truncated" in err and "weights_only" not in err
    )


def test_a_checkpoint_of_another_format_version_says_what_wrote_it_and_what_to_do(cli: Cli, tmp_path: Path) -> None:
    """Only "unsupported format_version 2 (this redsim reads 1)" was said: now which redsim wrote it and the way on."""
    import shutil

    from redsim import pretrained
    from redsim.subspace.checkpoint import FORMAT_VERSION

    shipped = pretrained.path("mini_chain")
    doc = json.loads(shipped.with_suffix(".json").read_text())
    for version, expected in (
        (FORMAT_VERSION + 1, "written by a newer redsim; upgrade redsim"),
        (
            FORMAT_VERSION - 1,
            f"written by an older redsim; fit it again with the command it records ({doc['command']})",
        ),
        (None, "not a redsim checkpoint's metadata"),
    ):
        shutil.copy(shipped, tmp_path / "v.pt")
        (tmp_path / "v.json").write_text(json.dumps(doc | {"format_version": version}))
        for command, out_file in (("inspect", None), ("sample", "s.npz"), ("animate", "a.gif")):
            argv = [command, str(tmp_path / "v.pt")] + ([] if out_file is None else ["--out", str(tmp_path / out_file)])
            code, out, err = cli(*argv)
            assert code == 2 and out == "" and err.count("\n") == 1 and expected in err, (command, err)


def test_sample_and_animate_report_states_that_are_not_finite(
    cli: Cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A map whose output is NaN: sample exited 3 without a word (and --meshes ended in a ValueError traceback),
    animate ended in animate_states' ValueError traceback. Now a stderr line each, exit 3, and no GIF."""
    import redsim.cli.subspaces as commands
    from redsim import pretrained

    real = commands.load_checkpoint

    def poisoned(path: str) -> tuple:
        scene, sub = real(path)
        with torch.no_grad():
            for weights in sub.parameters():
                weights.fill_(float("nan"))
        return scene, sub

    monkeypatch.setattr(commands, "load_checkpoint", poisoned)
    shipped = str(pretrained.path("mini_chain"))
    states, meshes = tmp_path / "s.npz", tmp_path / "m"
    code, _, err = cli("sample", shipped, "-n", "2", "--out", str(states), "--meshes", str(meshes))
    assert code == 3 and "2 of 2 sampled states are NaN or inf" in err and "Traceback" not in err, err
    assert states.is_file() and not list(meshes.glob("*.ply"))
    gif = tmp_path / "a.gif"
    code, _, err = cli("animate", shipped, "--frames", "4", "--out", str(gif))
    assert code == 3 and err.count("\n") == 1 and "4 of 4 frames are NaN or inf" in err and not gif.exists(), err


def test_simulate_says_a_step_that_did_not_converge_once_not_also_in_the_log(
    cli: Cli, caplog: pytest.LogCaptureFixture
) -> None:
    """Each such step was also a logged warning (one more stderr line per step, dated by the step's start time
    where simulate numbers it by its end); -v keeps the log's lines."""
    argv = ("simulate", "mini_chain", "--steps", "5", "--max-iter", "1", "--tol", "1e-14")
    code, out, err = cli(*argv)
    logged = [r for r in caplog.records if "did not converge" in r.getMessage()]
    assert code == 0 and "NOT converged" in out and err.count("did not converge") == 1 and not logged, err
    code, _, _ = cli("-v", *argv)
    logged = [r for r in caplog.records if "did not converge" in r.getMessage()]
    assert code == 0 and logged and all(r.name == "redsim.integrators.implicit_euler" for r in logged)


def test_simulate_interrupted_sums_up_the_steps_done(cli: Cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C (or SIGTERM) in a long simulate lost every step's statistics and the picture; now the steps done are
    summed up (--json: interrupted), drawn with --out, and the exit status is 130."""
    from redsim.integrators import ImplicitEuler

    real, calls = ImplicitEuler.step, []

    def step(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(self, *args, **kwargs)

    monkeypatch.setattr(ImplicitEuler, "step", step)
    code, out, err = cli("simulate", "mini_chain", "--steps", "10", "--out", str(tmp_path), "--json")
    summary = json.loads(out)
    assert code == 130 and summary["interrupted"] and summary["steps_run"] == 2 and len(summary["per_step"]) == 2
    assert "interrupted after step 2 of 10" in err and (tmp_path / "mini_chain_start_end.png").is_file()
    calls[:] = [1, 1]  # the first step interrupted: nothing to sum up
    code, out, err = cli("simulate", "mini_chain", "--steps", "10")
    assert code == 130 and err.strip() == "redsim: warning: interrupted", err


def test_simulate_refuses_a_time_step_whose_square_overflows(cli: Cli) -> None:
    code, out, err = cli("simulate", "mini_chain", "--steps", "1", "--dt", "1e200")  # an OverflowError traceback
    assert code == 2 and out == "" and "--dt must be a finite number" in err


@pytest.mark.parametrize(
    "raised",
    [
        RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 800000000000 bytes."),
        MemoryError(),
    ],
)
def test_running_out_of_memory_is_one_line_and_exit_1(
    cli: Cli, monkeypatch: pytest.MonkeyPatch, raised: BaseException
) -> None:
    """A batch too large for the machine (`bench step --batches 100000000`) ended in torch's allocator traceback."""

    def fail(args: argparse.Namespace) -> int:
        raise raised

    monkeypatch.setattr("redsim.cli.scenes.cmd_scenes", fail)
    code, out, err = cli("scenes")
    assert code == 1 and out == "" and err.count("\n") == 1, err
    assert err.startswith("redsim: error: out of memory: ") and "ask for less" in err
    monkeypatch.setattr("redsim.cli.scenes.cmd_scenes", lambda args: (_ for _ in ()).throw(RuntimeError("a bug")))
    with pytest.raises(RuntimeError, match="a bug"):  # any other error is not hidden
        cli("scenes")


def test_a_file_given_for_a_checkpoints_folder_is_called_a_file(cli: Cli, tmp_path: Path) -> None:
    """bench cubature said 'no such folder' of a file that is there (bench subspace and accuracy say it is a file)."""
    (tmp_path / "fits").write_text("")
    for argv in (["cubature"], ["subspace", "--scenes", "mini_chain"], ["accuracy", "mini_chain", "--dims", "2"]):
        code, out, err = cli("bench", *argv, "--checkpoints", str(tmp_path / "fits"))
        assert (code, out) == (2, "") and err.count("\n") == 1, (argv, err)
        assert "a file, not a folder" in err and "no such folder" not in err, (argv, err)
