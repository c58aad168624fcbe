"""The `redsim` command line: help, scene listing, simulate outputs, input errors, the energy bench.

Commands run in-process through :func:`redsim.cli.main` (one subprocess checks ``python -m
redsim``), on the two-tet toy scene, a few steps each.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import redsim
from redsim.cli import main

TOY = "toy_two_tets"


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def toy() -> redsim.Scene:
    return redsim.scenes.build(TOY)


@pytest.mark.parametrize(
    "argv",
    [
        [],
        ["scenes"],
        ["simulate"],
        ["fit"],
        ["inspect"],
        ["sample"],
        ["animate"],
        ["bench"],
        ["bench", "energy"],
        ["bench", "fit"],
    ],
    ids=lambda a: " ".join(a) or "top",
)
def test_help_exits_zero(capsys: pytest.CaptureFixture[str], argv: list[str]) -> None:
    code, out, _ = run(capsys, *argv, "--help")
    assert code == 0
    assert out.startswith("usage: redsim")


def test_fit_help_says_what_a_zero_checkpoint_every_does(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(capsys, "fit", "--help")
    assert code == 0 and "0: only at the end and on Ctrl-C" in " ".join(out.split())  # FitConfig allows 0


def test_python_m_redsim_help() -> None:
    done = subprocess.run([sys.executable, "-m", "redsim", "--help"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    for command in ("scenes", "simulate", "bench"):
        assert command in done.stdout


def test_scenes_json(capsys: pytest.CaptureFixture[str], toy: redsim.Scene) -> None:
    code, out, _ = run(capsys, "scenes", "--all", "--json")
    assert code == 0
    rows = {row["name"]: row for row in json.loads(out)}
    assert set(rows) == set(redsim.scenes.names())
    assert rows[TOY]["n"] == toy.free_dof_count
    assert {e["name"] for e in rows[TOY]["effects"]} == {e.name for e in toy.effects}
    assert all(isinstance(row["n"], int) and row["n"] > 0 for row in rows.values())


def test_scenes_exits_1_naming_a_scene_that_failed_to_build_and_says_so_in_its_help(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    build = redsim.scenes.build

    def broken(name: str, **params: object) -> redsim.Scene:
        if name == "mini_chain":
            raise ValueError("broken on purpose")
        return build(name, **params)

    monkeypatch.setattr(redsim.scenes, "names", lambda tag=None: [] if tag else ["mini_chain", TOY])
    monkeypatch.setattr(redsim.scenes, "build", broken)
    code, out, err = run(capsys, "scenes")
    assert code == 1 and "mini_chain  FAILED TO BUILD: ValueError: broken on purpose" in out and f"{TOY}  (3D" in out
    assert "1 scene(s) failed to build: mini_chain" in err
    assert "Exit status: 0 every scene built, 1 a scene failed to build" in " ".join(
        run(capsys, "scenes", "--help")[1].split()
    )


def test_scenes_hides_toys_without_all(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(redsim.scenes, "names", lambda tag=None: [TOY])
    code, out, _ = run(capsys, "scenes", "--json")
    assert code == 0
    assert json.loads(out) == []


def test_simulate_writes_picture_and_meshes(capsys: pytest.CaptureFixture[str], tmp_path, toy: redsim.Scene) -> None:
    code, out, err = run(
        capsys, "simulate", TOY, "--steps", "2", "--dt", "0.01", "--out", str(tmp_path), "--meshes", "--json"
    )
    assert code == 0, err
    summary = json.loads(out)
    assert summary["steps_run"] == 2
    assert summary["converged_steps"] == 2 and summary["not_converged_steps"] == []

    png = tmp_path / f"{TOY}_start_end.png"
    assert summary["png"] == str(png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    plys = sorted((tmp_path / "frames").glob("frame_*.ply"))
    assert len(plys) == 3 * len(toy.surfaces) > 0  # frames 0, 1, 2
    assert (tmp_path / "frames" / f"frame_0002_{toy.surfaces[0].name}.ply") in plys
    assert "earlier run" not in err, err
    code, _, err = run(capsys, "simulate", TOY, "--steps", "1", "--dt", "0.01", "--out", str(tmp_path), "--meshes")
    assert code == 0 and f"already holds {len(plys)} mesh files (frame_*.ply) from an earlier run" in err, err


def test_simulate_human_output_with_load(capsys: pytest.CaptureFixture[str], toy: redsim.Scene) -> None:
    if not toy.handles:
        pytest.skip(f"{TOY} has no handles")
    force = ",".join(["1.0"] * toy.dim)
    code, out, err = run(
        capsys, "simulate", TOY, "--steps", "1", "--dt", "0.01", "--load", f"{toy.handle_names[0]}={force}"
    )
    assert code == 0, err
    assert "step 1/1" in out and "1/1 steps converged" in out


def test_simulate_reports_steps_that_gained_energy(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The reference's energy-gain flag (StepInfo.energy_gain) was dropped: not in the per-step JSON, the summary or
    a warning. It is reported as the envs report it: never acted on (exit status 0)."""
    from redsim.integrators import ImplicitEuler

    step = ImplicitEuler.step

    def gaining_step(self, state, loads=None, cond=None):  # type: ignore[no-untyped-def]
        state, info = step(self, state, loads, cond)
        gained = round(float(state.time) / 0.01) == 2
        return state, dataclasses.replace(info, energy_gain=gained, mechanical_gain=0.5 if gained else 0.0)

    monkeypatch.setattr(ImplicitEuler, "step", gaining_step)
    code, out, err = run(capsys, "simulate", TOY, "--steps", "3", "--dt", "0.01", "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["energy_gain_steps"] == [2]
    assert [r["energy_gain"] for r in summary["per_step"]] == [False, True, False]
    assert summary["per_step"][1]["mechanical_gain"] == 0.5
    assert "1 of 3 step(s) raised K + E by more than the loads' work (first: step 2, 0.5 J)" in err


def test_simulate_reports_steps_that_tunneled(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A step whose path passed through a contact (StepInfo.tunneled) is listed and warned about, never acted on."""
    from redsim.integrators import ImplicitEuler

    step = ImplicitEuler.step

    def tunneling_step(self, state, loads=None, cond=None):  # type: ignore[no-untyped-def]
        state, info = step(self, state, loads, cond)
        index = round(float(state.time) / 0.01)
        return state, dataclasses.replace(info, tunneled=index == 3, tunnel_caught=index == 2)

    monkeypatch.setattr(ImplicitEuler, "step", tunneling_step)
    code, out, err = run(capsys, "simulate", TOY, "--steps", "3", "--dt", "0.01", "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["tunneled_steps"] == [3] and [r["tunneled"] for r in summary["per_step"]] == [False, False, True]
    assert summary["tunnels_caught_steps"] == [2]
    assert "1 of 3 step(s) moved through a contact that neither end touches (first: step 3)" in err
    code, out, err = run(capsys, "simulate", TOY, "--steps", "3", "--dt", "0.01")
    assert "1 step(s) moved through a contact in their first solve and were solved again" in out


def test_simulate_catches_a_tunnel_unless_told_not_to(capsys: pytest.CaptureFixture[str]) -> None:
    """The mini chain pulled down hard at a long step passes through its hook in its first solve: simulate solves it
    again and catches it there (tunnels_caught_steps); --no-retry-tunneled reports it (tunneled_steps) instead."""
    argv = ("simulate", "mini_chain", "--steps", "1", "--dt", "0.1", "--load", "bottom=0,-1000,0", "--json")
    code, out, err = run(capsys, *argv)
    caught = json.loads(out)
    code_off, out, err_off = run(capsys, *argv, "--no-retry-tunneled")
    through = json.loads(out)
    assert code == 0 and code_off != 0, err + err_off  # through the hook, the chain falls: a failed step too
    assert (caught["retry_tunneled"], through["retry_tunneled"]) == (True, False)
    assert caught["tunnels_caught_steps"] == [1] and caught["tunneled_steps"] == [], err
    assert through["tunneled_steps"] == [1] and through["tunnels_caught_steps"] == [] and through["failed_step"] == 1


def test_simulate_holds_the_conditions_given_and_reports_them(capsys: pytest.CaptureFixture[str]) -> None:
    """simulate ran a conditional scene at its default condition, with no way to set it and no word of which it was
    (a review's finding); `redsim scenes` names each condition's range and default."""
    code, out, err = run(capsys, "simulate", "conditional_bar", "--steps", "1", "--cond", "stiffness_ratio=4", "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["conditions"] == {"stiffness_ratio": 4.0, "pin_location": 0.65}
    scene = redsim.scenes.build("conditional_bar")
    from redsim.integrators import FullSpace, ImplicitEuler

    sim = ImplicitEuler(FullSpace(scene), 0.01)
    state, _ = sim.step(sim.initial_state(), None, torch.tensor([4.0, 0.65], dtype=torch.float64))
    energy = float(scene.energy(state.q, None, torch.tensor([4.0, 0.65], dtype=torch.float64)))
    assert summary["energy_end"] == pytest.approx(energy, rel=1e-9)
    assert summary["energy_end"] != pytest.approx(float(scene.energy(state.q)), rel=1e-6)  # not the default's
    assert run(capsys, "simulate", TOY, "--steps", "1", "--json")[1].count('"conditions": null') == 1
    code, out, _ = run(capsys, "scenes")
    assert code == 0 and "conditions (each with its range and default" in " ".join(
        run(capsys, "scenes", "--help")[1].split()
    )
    assert "  conditions: stiffness_ratio in [0.2, 5] (default 1), pin_location in [0.3, 1] (default 0.65)\n" in out
    row = next(r for r in json.loads(run(capsys, "scenes", "--json")[1]) if r["name"] == "conditional_bar")
    assert row["condition_space"][0] == {"name": "stiffness_ratio", "low": 0.2, "high": 5.0, "default": 1.0}


def test_simulate_escape_saddles_reaches_the_lower_step(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ("simulate", "mini_chain", "--steps", "3", "--dt", "0.02", "--load", "bottom=2,0,0", "--json")
    plain, escaped = (json.loads(run(capsys, *argv, *extra)[1]) for extra in ((), ("--escape-saddles",)))
    assert escaped["converged_steps"] == plain["converged_steps"] == 3
    assert (plain["escape_saddles"], escaped["escape_saddles"], plain["tol"], plain["max_iter"]) == (
        False,
        True,
        1e-8,
        100,
    )
    assert escaped["per_step"][2]["objective"] < plain["per_step"][2]["objective"] - 1e-3  # the saddle left
    help_text = " ".join(run(capsys, "simulate", "--help")[1].split())  # --tol's bound held only where convex
    assert "where the step's objective is convex (a converged step is stationary, and can be a saddle" in help_text


def test_simulate_nan_exits_3(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    from redsim.integrators import ImplicitEuler

    step = ImplicitEuler.step

    def nan_step(self, state, loads=None, cond=None):  # type: ignore[no-untyped-def]
        state, info = step(self, state, loads, cond)
        return dataclasses.replace(state, q=state.q * float("nan")), info

    monkeypatch.setattr(ImplicitEuler, "step", nan_step)
    code, out, err = run(capsys, "simulate", TOY, "--steps", "3", "--dt", "0.01", "--json")
    assert code == 3
    assert "step 1 produced NaN" in err
    summary = json.loads(out)  # strict JSON: NaN is written as null
    assert summary["nan_step"] == 1 and summary["steps_run"] == 1 and summary["energy_end"] is None


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["simulate", "no_such_scene"], TOY),  # the message lists the valid scenes
        (["simulate", TOY, "--load", "no_such_handle=1,2,3"], "valid handles"),
        (["simulate", TOY, "--load", "nonsense"], "malformed --load"),
        (["simulate", TOY, "--dt", "0"], "--dt must be"),
        (["simulate", TOY, "--dt", "-0.1"], "--dt must be"),
        (["simulate", TOY, "--steps", "0"], "--steps must be"),
        (["simulate", TOY, "--param", "young=soft"], "JSON literal"),
        (["simulate", TOY, "--param", "no_such_param=1"], "cannot build scene"),
        (["simulate", TOY, "--param", "young=1e4", "--param", "young=2e4"], "--param young given twice"),
        (["simulate", TOY, "--dt", "fast"], "invalid float value"),
        (["simulate", TOY, "--max-iter", "0"], "max_iter"),
        (["simulate", TOY, "--cond", "stiffness_ratio=2"], f"scene '{TOY}' has no conditions"),
        (["simulate", "conditional_bar", "--cond", "stiffness=2"], "valid conditions: stiffness_ratio in [0.2, 5]"),
        (["simulate", "conditional_bar", "--cond", "stiffness_ratio=-1"], "outside the range [0.2, 5]"),
        (["simulate", "conditional_bar", "--cond", "stiffness_ratio"], "malformed --cond"),
        (["bench", "energy", "--scenes", "no_such_scene"], TOY),
        (["bench", "subspace", "--scenes", "mini_chain", "--samples", "0"], "--samples must be >= 1"),  # traceback
        (["bench", "subspace", "--scenes", "mini_chain", "--loads", "-3"], "--loads >= 0, got 256 and -3"),
    ],
    ids=[
        "scene",
        "handle",
        "load",
        "dt0",
        "dt<0",
        "steps",
        "param",
        "param-key",
        "param-twice",
        "dt-text",
        "max-iter",
        "cond-none",
        "cond-name",
        "cond-range",
        "cond-value",
        "bench-scene",
        "subspace-samples",
        "subspace-loads",
    ],
)
def test_bad_input_is_one_line_exit_2(capsys: pytest.CaptureFixture[str], argv: list[str], expected: str) -> None:
    code, out, err = run(capsys, *argv)
    assert code == 2
    assert out == ""
    assert err.count("\n") == 1 and err.startswith("redsim: error: ")
    assert expected in err


def test_machine_line_names_the_cpu_generation_and_torchs_kernels() -> None:
    # hanging_sheet's cubature deviation read 12.7% on an AVX-512 "AMD EPYC" and 8.9% with the AVX2 kernels (stop 68):
    # a line saying only "AMD EPYC" could not tell such runs apart
    code = (
        "from redsim.bench import machine_info; from redsim.cli.common import machine_line; "
        "m = machine_info(); print(m['cpu_capability']); print(machine_line(m, 'cpu'))"
    )
    env = {**os.environ, "ATEN_CPU_CAPABILITY": "default"}
    capability, line = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout.splitlines()
    assert capability == "DEFAULT" and "torch " + torch.__version__ + " (DEFAULT kernels)," in line
    from redsim.bench import machine_info

    machine = machine_info()
    assert machine["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    if machine["cpu_family_model"] is not None:  # Linux on x86: the first CPU's "cpu family" and "model"
        assert machine["cpu_family_model"].startswith("family ") and machine["cpu_family_model"] + ")," in line


def test_bench_energy_json(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(
        capsys, "bench", "energy", "--scenes", TOY, "--repeats", "2", "--perturbation", "3e-3", "--json"
    )
    assert code == 0, err
    report = json.loads(out)
    assert report["machine"]["torch"] == torch.__version__
    results = report["results"]
    assert {(r["dtype"], r["batch"]) for r in results} == {(d, b) for d in ("float64", "float32") for b in (1, 32)}
    assert all(r["scene"] == TOY and r["median_s"] > 0 for r in results)
    assert report["perturbation"] == 3e-3
    from redsim.bench import bench_energy

    scene = redsim.scenes.build(TOY)
    assert bench_energy(scene, 1, 1, time_budget=1e-9)["repeats"] == 1  # a budget never times more (it timed 3)
    assert bench_energy(scene, 1, 9, time_budget=1e-9)["repeats"] == 3  # but at least 3 of the asked


def test_bench_energy_reports_a_scene_that_raises_and_keeps_rows_at_ctrl_c(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A scene whose energy raised ended the command in a traceback; Ctrl-C lost the JSON document's rows. Now the
    failed scene is a row and exit 1, and Ctrl-C prints the scenes finished before it and exits 130."""
    import redsim.bench

    real = redsim.bench.bench_energy

    def bench_energy(scene, batch, repeats, **kwargs):
        if scene.free_dof_count == broken[0]:
            raise broken[1]
        return real(scene, batch, repeats, **kwargs)

    monkeypatch.setattr(redsim.bench, "bench_energy", bench_energy)
    argv = (
        "bench",
        "energy",
        "--scenes",
        f"mini_chain,{TOY}",
        "--repeats",
        "1",
        "--batches",
        "1",
        "--dtypes",
        "float64",
    )
    broken = (redsim.scenes.build("mini_chain").free_dof_count, RuntimeError("no energy"))
    code, out, err = run(capsys, *argv)
    assert code == 1 and "failed: mini_chain: RuntimeError: no energy" in out and f"\n{TOY} " in out, err
    code, out, err = run(capsys, *argv, "--json")
    report = json.loads(out)
    assert code == 1 and report["failed"] == [{"scene": "mini_chain", "error": "RuntimeError: no energy"}]
    assert [r["scene"] for r in report["results"]] == [TOY]
    broken = (redsim.scenes.build(TOY).free_dof_count, KeyboardInterrupt())
    code, out, err = run(capsys, *argv, "--json")
    report = json.loads(out)
    assert code == 130 and report["interrupted"] and [r["scene"] for r in report["results"]] == ["mini_chain"]


def test_render_2d_scene(tmp_path) -> None:
    from redsim.effects import NeoHookean
    from redsim.render import draw_states, export_meshes

    vertices = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], dtype=torch.float64)
    tris = torch.tensor([[0, 1, 2], [1, 3, 2]])
    builder = redsim.SceneBuilder(dim=2)
    ids = builder.add_particles(vertices, torch.ones(4))
    builder.pin_particles(ids[:2])
    builder.add_effect(NeoHookean("elastic", builder.particle_dofs(tris), vertices[tris], young=1e3, poisson=0.3))
    builder.add_surface("sheet", builder.particle_points(ids), tris)
    scene = builder.finalize("two_tris")

    moved = scene.q_seed + 0.1
    png = draw_states(scene, [scene.q_seed, moved], ["seed", "moved"], tmp_path / "two.png")
    assert png.read_bytes()[:4] == b"\x89PNG"
    (ply,) = export_meshes(scene, moved, tmp_path, 7)
    assert ply.name == "frame_0007_sheet.ply"
    import numpy as np

    for frame in (np.int64(7), torch.tensor(7)):  # a loop over np.arange or a tensor's frame numbers
        assert export_meshes(scene, moved, tmp_path, frame) == [ply]
    import trimesh

    mesh = trimesh.load(ply, process=False)
    assert mesh.vertices.shape == (4, 3) and mesh.faces.shape == (2, 3)
    assert abs(mesh.vertices[:, 2]).max() == 0.0
    assert mesh.vertices[3].tolist()[:2] == pytest.approx([1.1, 1.1])
    with pytest.raises(ValueError, match="not finite"):  # not a .ply of NaNs
        export_meshes(scene, moved * torch.nan, tmp_path, 8)
    with pytest.raises(ValueError, match="needs finite states"):  # not matplotlib's axis-limits error
        draw_states(scene, [moved * torch.nan], path=tmp_path / "nan.png")
    with pytest.raises(ValueError, match="device must be 'cpu' or 'cuda"):
        scene.to(device="bogus")
    for frame in (-1, True, 7.0, torch.tensor(7.0)):
        with pytest.raises(ValueError, match="frame must be an integer >= 0"):
            export_meshes(scene, moved, tmp_path, frame)
    bare = redsim.SceneBuilder(dim=2)
    bare.add_particles(vertices, torch.ones(4))
    with pytest.raises(ValueError, match="no surfaces to export"):
        export_meshes(bare.finalize("points"), moved, tmp_path, 0)


def test_render_takes_a_batch_writes_where_it_says_and_never_overwrites_a_surface(tmp_path) -> None:
    """A review's findings: a batch [k, n] was an ambiguous-truth RuntimeError, a path without .png came back as a
    file that did not exist (matplotlib wrote NAME.png), two surfaces with one file name overwrote each other, a
    refused q left an empty folder, and a NaN frame of an animation failed inside matplotlib."""
    from redsim.render import animate_states, draw_states, export_meshes

    scene = redsim.scenes.build("mini_chain")
    batch = torch.stack([scene.q_seed, scene.q_seed + 0.01])
    written = draw_states(scene, batch, path=tmp_path / "no_suffix")
    assert written == tmp_path / "no_suffix" and written.read_bytes()[:4] == b"\x89PNG"
    assert animate_states(scene, batch, tmp_path / "two.gif").read_bytes()[:3] == b"GIF"
    with pytest.raises(ValueError, match=r"a sequence of \[n\] states or a batch \[k, n\], got shape \(24,\)"):
        draw_states(scene, scene.q_seed, path=tmp_path / "one.png")
    with pytest.raises(ValueError, match="animate_states needs finite states"):
        animate_states(scene, batch * torch.nan, tmp_path / "nan.gif")
    with pytest.raises(ValueError):
        export_meshes(scene, scene.q_seed[:5], tmp_path / "refused", 0)
    assert not (tmp_path / "refused").exists()
    surfaces = list(scene.surfaces)
    twins = dataclasses.replace(scene, surfaces=(surfaces[0], dataclasses.replace(surfaces[1], name=surfaces[0].name)))
    with pytest.raises(ValueError, match="share file names"):
        export_meshes(twins, scene.q_seed, tmp_path / "twins", 0)


def test_shown_path_is_machine_independent(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Reports print shipped checkpoints package-relative and local ones relative to the working folder."""
    from redsim import pretrained
    from redsim.cli.common import shown_path

    assert shown_path(pretrained.path("chain")) == "redsim/pretrained/chain.pt"
    monkeypatch.chdir(tmp_path)
    assert shown_path(tmp_path / "subspaces" / "chain.pt") == "subspaces/chain.pt"
    elsewhere = tmp_path.parent / "other.pt"
    assert shown_path(elsewhere) == str(elsewhere)


def test_every_path_argument_reads_a_leading_tilde() -> None:
    """Each option or argument that names a file or folder is in the list :func:`expand_home` reads, so a new one
    is not left out."""
    import argparse

    from redsim.cli import build_parser
    from redsim.cli.common import PATH_ARGS, Parser

    paths = []

    def walk(parser: argparse.ArgumentParser) -> None:
        if isinstance(parser, Parser):
            parser.complete()
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    walk(sub)
            elif action.metavar in ("DIR", "PATH", "FILE", "STEM") or action.dest in ("checkpoint", "model"):
                paths.append(action.dest)

    walk(build_parser())
    assert {"out", "checkpoint", "spec", "mesh", "meshes", "checkpoints"} <= set(paths)
    assert set(paths) <= set(PATH_ARGS), sorted(set(paths) - set(PATH_ARGS))


def test_an_env_arg_path_that_starts_with_a_tilde_is_in_the_home_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--env-arg subspace='"~/x.pt"'`` (JSON's quotes keep the shell from the ``~``) was looked for in a folder named
    ``~``: the env was not made ("the weights file is missing")."""
    from redsim import pretrained
    from redsim.cli.common import parse_env_args

    for suffix in (".pt", ".json"):
        (tmp_path / f"mine{suffix}").write_bytes(pretrained.path("mini_chain").with_suffix(suffix).read_bytes())
    monkeypatch.setenv("HOME", str(tmp_path))
    kwargs = parse_env_args(['subspace="~/mine.pt"', "cubature=false"], ["RedSim/MiniChain-v0"])
    assert kwargs == {"subspace": str(tmp_path / "mine.pt"), "cubature": False}
    kwargs = parse_env_args(['cubature="~/mine"'], [])  # not made: no env id
    assert kwargs == {"cubature": str(tmp_path / "mine")}
    assert parse_env_args(['cubature="lean"'], []) == {"cubature": "lean"}  # a shipped name stays one


def test_train_agent_draws_its_progress_bar_on_stderr(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    """SB3 draws its bar with tqdm.rich on rich's global console, which writes to stdout: the bar's last frame was
    in the command's result (``redsim train-agent ... > run.txt``)."""
    import rich

    argv = ["train-agent", "RedSim/MiniChain-v0", "--algo", "ppo", "--steps", "256", "--n-envs", "2"]
    argv += ["--eval-episodes", "1", "--final-episodes", "1", "--no-video", "--out", str(tmp_path / "run")]
    code, out, err = run(capsys, *argv, "--threads", "1")
    assert code == 0, err
    assert "256/256" in err  # the bar's last frame
    assert "256/256" not in out and "it/s" not in out, out
    assert out.startswith("RedSim/MiniChain-v0: PPO trained 256 env steps")
    assert rich.get_console().stderr is False  # the global console is set back for the caller


@pytest.mark.parametrize(
    ("argv", "picture"),
    [
        (["scaling", "--sizes", "1", "--fit-steps", "1", "--fit-warmup", "1", "--latent-steps", "1"], "scaling.png"),
        (["accuracy", "mini_chain", "--scenarios", "push", "--full", "none", "--no-study", "--steps", "10"], None),
    ],
    ids=["scaling", "accuracy"],
)
def test_a_bench_s_picture_is_written_whole_or_not_at_all(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path, argv: list[str], picture: str | None
) -> None:
    """bench scaling (after each size) and bench accuracy drew their PNG in place: a Ctrl-C while matplotlib wrote
    it left half a PNG over the one there before."""
    from matplotlib.figure import Figure

    def half_then_ctrl_c(self: Figure, path: object, **kwargs: object) -> None:
        with open(path, "wb") as file:  # type: ignore[call-overload]
            file.write(b"\x89PNG half")
        raise KeyboardInterrupt

    path = tmp_path / (picture or "accuracy_mini_chain.png")
    path.write_bytes(b"the picture before")
    monkeypatch.setattr(Figure, "savefig", half_then_ctrl_c)
    code, _, err = run(capsys, "bench", *argv, "--out", str(tmp_path), "--threads", "1")
    assert code == 130 and err.endswith("redsim: warning: interrupted\n"), err
    assert path.read_bytes() == b"the picture before"
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith("tmp")]  # no temporary left
