"""The whole CLI on a user's own mesh: fit, inspect, sample, animate, simulate, and a changed mesh file."""

from __future__ import annotations

import json
import shlex
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import trimesh

import redsim
from redsim.cli import main
from redsim.scenes.spec import SceneSpecError, scene_from_spec, scene_spec

Cli = Callable[..., tuple[int, str, str]]
MESH_ARGS = ["--kind", "fem", "--param", "voxel_pitch=0.05", "--param", "young=2e4"]


@pytest.fixture(scope="module")
def box(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 0.1 x 0.2 x 0.1 m box: 2 x 4 x 2 voxels at pitch 0.05."""
    path = tmp_path_factory.mktemp("mesh") / "box.obj"
    trimesh.creation.box(extents=(0.1, 0.2, 0.1)).export(path)
    return path


@pytest.fixture(scope="module")
def fitted(box: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    stem = tmp_path_factory.mktemp("fit") / "box"
    argv = ["fit", "--mesh", str(box), *MESH_ARGS, "--steps", "20", "--dim", "2", "--width", "8", "--layers", "1"]
    assert main([*argv, "--sigma", "0.01", "--out", str(stem), "--json"]) == 0
    return stem.with_name("box.pt")


def test_the_checkpoint_records_how_to_rebuild_the_mesh_scene(fitted: Path, box: Path) -> None:
    meta = json.loads(fitted.with_suffix(".json").read_text())
    params = meta["scene_params"]
    assert meta["scene"] == "mesh_fem" and params["builder"] == "fem"
    assert params["source"] == str(box.resolve()) and params["voxel_pitch"] == 0.05 and params["young"] == 2e4
    assert len(params["mesh_sha256"]) == 64
    assert meta["command"].startswith(f"redsim fit --mesh {box.resolve()} --kind fem ")
    scene = scene_from_spec(meta)
    assert scene.fingerprint() == meta["scene_fingerprint"]
    assert scene_spec(scene) == {"scene": "mesh_fem", "scene_params": params}


def test_inspect_sample_animate_work_on_a_mesh_checkpoint(cli: Cli, fitted: Path, tmp_path: Path) -> None:
    code, out, err = cli("inspect", str(fitted), "--json")
    assert code == 0, err
    doc = json.loads(out)
    n = doc["n"]
    assert doc["scene"] == "mesh_fem" and doc["latent_dim"] == 2
    code, out, err = cli("sample", str(fitted), "-n", "5", "--out", str(tmp_path / "s.npz"), "--json")
    assert code == 0, err
    assert np.load(tmp_path / "s.npz")["q"].shape == (5, n)
    gif = tmp_path / "a.gif"
    code, _, err = cli("animate", str(fitted), "--keys", "2", "--frames", "2", "--out", str(gif))
    assert code == 0, err
    assert gif.read_bytes()[:3] == b"GIF"


def test_refit_from_the_recorded_command(fitted: Path, tmp_path: Path) -> None:
    meta = json.loads(fitted.with_suffix(".json").read_text())
    argv = shlex.split(meta["command"])[1:]
    argv[argv.index("--out") + 1] = str(tmp_path / "again")
    assert main([*argv, "--json"]) == 0
    assert json.loads((tmp_path / "again.json").read_text())["scene_fingerprint"] == meta["scene_fingerprint"]


def test_a_mesh_fit_names_its_own_handle_in_the_accuracy_check_it_prints(cli: Cli, box: Path, tmp_path: Path) -> None:
    """The bench pushes a checkpoint scene's first handle, the whole body's centre of mass, by default; the handle a
    user added (the one an env of it pushes) is the one to check, so the printed command names it."""
    handles = ["--param", 'handles={"tip": "max_y", "side": "max_x"}']
    argv = ["fit", "--mesh", str(box), *MESH_ARGS, *handles, "--steps", "2", "--dim", "2", "--width", "8"]
    code, out, err = cli(*argv, "--layers", "1", "--out", str(tmp_path / "h"))
    assert code == 0, err
    assert f"redsim bench accuracy {tmp_path / 'h.pt'} --handle side --scenarios push --full none" in out
    assert "--no-study (or --handle tip)" in out


def test_simulate_a_mesh_and_a_cloth(cli: Cli, box: Path, tmp_path: Path) -> None:
    code, out, err = cli("simulate", "--mesh", str(box), *MESH_ARGS, "--steps", "1", "--json")
    assert code == 0, err
    assert json.loads(out)["scene"] == "mesh_fem"
    vertices, triangles = redsim.meshes.cloth_grid(0.2, 0.2, (3, 3), origin=(0.0, -0.2, 0.0))
    sheet = tmp_path / "sheet.obj"
    trimesh.Trimesh(vertices, triangles).export(sheet)
    argv = ["simulate", "--mesh", str(sheet), "--kind", "cloth", "--steps", "1", "--load", "cloth=0,0,0.1"]
    code, out, err = cli(*argv, "--out", str(tmp_path), "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["scene"] == "mesh_cloth" and summary["params"]["builder"] == "cloth"
    assert Path(summary["png"]).read_bytes()[:4] == b"\x89PNG"


def test_a_tet_mesh_file_is_simulated_fitted_and_inspected(cli: Cli, tmp_path: Path) -> None:
    vertices, tets = redsim.meshes.box_tet_grid((0.1, 0.2, 0.1), (2, 4, 2))
    path = tmp_path / "box.npz"
    np.savez(path, vertices=vertices, tets=tets)
    args = ["--mesh", str(path), "--kind", "tets", "--param", "young=2e4", "--param", "pin=[0, 1, 2]"]
    code, out, err = cli("simulate", *args, "--steps", "1", "--json")
    assert code == 0, err
    assert json.loads(out)["params"]["selections"] == {"pin": [0, 1, 2]}
    fit = ["--steps", "2", "--dim", "2", "--width", "8", "--layers", "1", "--sigma", "0.01"]
    code, _, err = cli("fit", *args, *fit, "--out", str(tmp_path / "t"))
    assert code == 0, err
    code, out, err = cli("inspect", str(tmp_path / "t.pt"), "--json")
    assert code == 0, err
    assert json.loads(out)["scene"] == "mesh_tets"


def test_a_checkpoint_json_is_a_scene_spec(cli: Cli, fitted: Path, box: Path, tmp_path: Path) -> None:
    meta = json.loads(fitted.with_suffix(".json").read_text())
    code, out, err = cli("simulate", "--spec", str(fitted.with_suffix(".json")), "--steps", "1", "--json")
    assert code == 0, err
    assert json.loads(out)["params"] == meta["scene_params"]
    spec = tmp_path / "chain.json"
    spec.write_text(json.dumps({"scene": "toy_three_link_chain", "scene_params": {"gravity": False}}))
    code, out, err = cli("simulate", "--spec", str(spec), "--steps", "1", "--json")
    assert code == 0, err
    assert json.loads(out)["params"]["gravity"] is False
    # in Python, the same files by path (a checkpoint's .pt reads its .json)
    rebuilt = scene_from_spec(fitted.with_suffix(".json"))
    assert (
        rebuilt.params == meta["scene_params"] and scene_from_spec(str(fitted)).fingerprint() == rebuilt.fingerprint()
    )
    assert scene_from_spec(spec).params["gravity"] is False
    with pytest.raises(SceneSpecError, match=r"cannot read the scene spec .*nothing\.json"):
        scene_from_spec(tmp_path / "nothing.json")
    (tmp_path / "list.json").write_text("[1]")
    code, _, err = cli("simulate", "--spec", str(tmp_path / "list.json"))
    assert code == 2 and f"the scene spec {tmp_path / 'list.json'} is not a JSON object" in err, err
    code, _, err = cli("simulate", "--spec", str(spec), "--param", "gravity=true")
    assert code == 2 and "--param does not apply to --spec" in err
    code, _, err = cli("simulate", "toy_two_tets", "--spec", str(spec))
    assert code == 2 and "not a scene name and --spec" in err


def test_a_cloth_pinned_by_vertex_index_on_the_command_line_is_rebuilt_from_its_checkpoint(
    cli: Cli, tmp_path: Path
) -> None:
    """`--param 'pin=[...]'` fitted, and then no command could use the fit: the .json held only the indices' hash."""
    vertices, triangles = redsim.meshes.cloth_grid(0.2, 0.2, (3, 3), origin=(0.0, -0.2, 0.0))
    sheet = tmp_path / "sheet.obj"
    trimesh.Trimesh(vertices, triangles).export(sheet)
    stem = tmp_path / "pinned"
    argv = ["fit", "--mesh", str(sheet), "--kind", "cloth", "--param", "pin=[6,7,8]", "--param", 'handles={"c": [0]}']
    code, _, err = cli(*argv, "--steps", "5", "--dim", "2", "--width", "8", "--layers", "1", "--out", str(stem))
    assert code == 0, err
    params = json.loads(stem.with_suffix(".json").read_text())["scene_params"]
    assert params["selections"] == {"pin": [6, 7, 8], "handles": {"c": [0]}}
    code, out, err = cli("inspect", str(stem.with_suffix(".pt")))
    assert code == 0 and "not runnable" not in out + err, err
    code, out, err = cli("simulate", "--spec", str(stem.with_suffix(".json")), "--steps", "1", "--json")
    assert code == 0 and json.loads(out)["params"] == params, err
    # the recorded command names the indices, not their hash label (`pin="ids:..."` could not be run again)
    command = json.loads(stem.with_suffix(".json").read_text())["command"]
    assert "ids:" not in command and "--param 'pin=[6, 7, 8]'" in command, command
    again = shlex.split(command)[1:]
    again[again.index("--out") + 1] = str(tmp_path / "again")
    code, _, err = cli(*again)
    assert code == 0, err
    assert json.loads((tmp_path / "again.json").read_text())["scene_params"] == params


def test_a_hand_written_spec_reads_a_relative_mesh_path_from_its_folder_and_needs_no_hash(
    cli: Cli, box: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "specs").mkdir()
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "box.obj").write_bytes(box.read_bytes())
    spec = tmp_path / "specs" / "box.json"
    params = {"builder": "fem", "source": "../meshes/box.obj", "voxel_pitch": 0.05}
    spec.write_text(json.dumps({"scene": "my_box", "scene_params": params}))
    monkeypatch.chdir(tmp_path / "meshes")  # not the spec's folder: the path is the spec's, as written
    code, out, err = cli("simulate", "--spec", str(spec), "--steps", "1", "--json")
    assert code == 0, err
    assert json.loads(out)["params"]["source"] == str(tmp_path / "meshes" / "box.obj")
    assert scene_from_spec(spec).name == "my_box"
    spec.write_text(json.dumps({"scene": "my_box", "scene_params": {"builder": "fem"}}))
    code, _, err = cli("simulate", "--spec", str(spec), "--steps", "1")
    assert code == 2 and "names no mesh file (a 'source' path in scene_params)" in err, err


def test_a_checkpoint_json_edited_to_a_relative_mesh_path_reads_it_from_its_folder(
    cli: Cli, fitted: Path, box: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """As a hand-written spec's: a checkpoint loaded by the commands resolved it against the working folder."""
    meta = json.loads(fitted.with_suffix(".json").read_text())
    meta["scene_params"]["source"] = "box.obj"
    (tmp_path / "box.obj").write_bytes(box.read_bytes())
    (tmp_path / "m.json").write_text(json.dumps(meta))
    (tmp_path / "m.pt").write_bytes(fitted.read_bytes())
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    code, _, err = cli("sample", str(tmp_path / "m.pt"), "-n", "2", "--out", str(tmp_path / "s.npz"))
    assert code == 0, err


def test_bench_energy_on_a_mesh(cli: Cli, box: Path) -> None:
    code, out, err = cli(
        "bench", "energy", "--mesh", str(box), *MESH_ARGS, "--repeats", "1", "--batches", "1", "--json"
    )
    assert code == 0, err
    results = json.loads(out)["results"]
    assert {r["scene"] for r in results} == {"mesh_fem"} and len(results) == 2
    code, _, err = cli("bench", "energy", "--scenes", "toy_two_tets", "--mesh", str(box), *MESH_ARGS)
    assert code == 2 and "either --scenes or --mesh" in err
    code, _, err = cli("bench", "fit", "--param", "young=1")
    assert code == 2 and "go with --mesh" in err


def test_a_changed_mesh_file_is_a_clear_error(cli: Cli, fitted: Path, box: Path, tmp_path: Path) -> None:
    meta = json.loads(fitted.with_suffix(".json").read_text())
    moved = tmp_path / "box.obj"
    moved.write_bytes(box.read_bytes())
    meta["scene_params"]["source"] = str(moved)
    (tmp_path / "m.json").write_text(json.dumps(meta))
    (tmp_path / "m.pt").write_bytes(fitted.read_bytes())
    trimesh.creation.box(extents=(0.1, 0.25, 0.1)).export(moved)
    code, _, err = cli("inspect", str(tmp_path / "m.pt"))  # shows the .json, and says why nothing was loaded
    assert code == 0 and "changed since" in err and meta["scene_params"]["mesh_sha256"] in err
    code, _, err = cli("sample", str(tmp_path / "m.pt"), "--out", str(tmp_path / "s.npz"))
    assert code == 2 and err.count("\n") == 1
    assert "changed since" in err and meta["scene_params"]["mesh_sha256"] in err
    moved.unlink()
    code, _, err = cli("sample", str(tmp_path / "m.pt"))
    assert code == 2 and "is missing" in err and "box.obj" in err


def test_specs_that_cannot_be_rebuilt() -> None:
    with pytest.raises(SceneSpecError, match="names no scene"):
        scene_from_spec({})
    with pytest.raises(SceneSpecError, match="unknown scene 'mine'"):
        scene_from_spec({"scene": "mine", "scene_params": {}})
    in_memory = redsim.scenes.cloth_scene_from_mesh(trimesh.creation.icosphere(subdivisions=1))
    with pytest.raises(SceneSpecError, match="in-memory mesh"):
        scene_from_spec(scene_spec(in_memory))
    assert scene_from_spec(scene_spec(redsim.scenes.build("toy_two_tets"))).name == "toy_two_tets"
    for params in ([1, 2], [["young", 5]]):  # dict()'s own message, or a list of pairs taken as an object
        with pytest.raises(SceneSpecError, match="scene_params must be a JSON object, got list"):
            scene_from_spec({"scene": "toy_crank", "scene_params": params})


def test_a_spec_with_a_misspelt_key_is_refused_naming_it(cli: Cli, box: Path, tmp_path: Path) -> None:
    """A misspelt 'scene_params' was dropped (the scene built with its defaults), and a builder argument the mesh
    builder does not take was a TypeError from the builder that named no valid one."""
    with pytest.raises(SceneSpecError, match="has no 'scene_params' but has 'scene_param': a typo"):
        scene_from_spec({"scene": "toy_crank", "scene_param": {"gravity": False}})
    params = {"builder": "fem", "source": str(box), "voxel_pitch": 0.05}
    assert scene_from_spec({"scene": "my_box", "scene_params": params}).name == "my_box"
    for key in ("youngg", "name"):  # the spec's "scene" is the name
        unknown = rf"unknown parameter\(s\) \['{key}'\] of a fem mesh scene; valid: voxel_pitch,.* young,"
        with pytest.raises(ValueError, match=unknown):
            scene_from_spec({"scene": "my_box", "scene_params": {**params, key: 1e5}})
    with pytest.raises(ValueError, match=r"handles must be a dict of name -> vertex selection .* got 'max_x'"):
        scene_from_spec({"scene": "my_box", "scene_params": {**params, "handles": "max_x"}})  # was dict()'s message
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"scene": "my_box", "scene_params": {**params, "youngg": 1e5}}))
    code, _, err = cli("simulate", "--spec", str(spec), "--steps", "1")
    named = "unknown parameter(s) ['youngg'] of a fem mesh scene; valid: voxel_pitch, target_dofs, young,"
    assert code == 2 and named in err, err


def test_kind_with_a_spec_is_refused(cli: Cli, tmp_path: Path) -> None:
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(scene_spec(redsim.scenes.build("toy_crank"))))
    code, out, err = cli("simulate", "--spec", str(spec), "--kind", "cloth", "--steps", "1")  # ran, --kind ignored
    assert code == 2 and out == "" and "--kind goes with --mesh, not --spec" in err


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["simulate"], "give a scene name, a mesh with --mesh PATH"),
        (["simulate", "--mesh", "x.obj"], "--mesh needs --kind"),
        (["simulate", "toy_two_tets", "--kind", "fem"], "--kind needs --mesh"),
        (["fit", "toy_two_tets", "--mesh", "x.obj", "--kind", "fem"], "not a scene name and --mesh"),
        (["fit", "--mesh", "/nonexistent/x.obj", "--kind", "fem"], "x.obj"),
        (["simulate", "--mesh", "/nonexistent/x.obj", "--kind", "plate"], "invalid choice"),
        (
            ["fit", "--mesh", "x.obj", "--kind", "fem", "--param", "youngs=3"],
            "unknown parameter(s) ['youngs'] of a fem",
        ),
        (
            ["simulate", "--mesh", "x.npz", "--kind", "tets", "--param", "voxel_pitch=0.01"],
            "unknown parameter(s) ['voxel_pitch'] of a tets mesh scene",
        ),
        (["fit", "redsim:RedSim/Chain-v0"], "(an env id: demo, train-agent, eval-agent and bench envs take ids;"),
        (["simulate", "cloth.obj"], "(a file path: a mesh goes with --mesh PATH --kind fem|tets|cloth, a spec or"),
        (["bench", "cubature", "subspaces/cloth.pt"], "(a file path: this command runs on catalog scenes only)"),
    ],
)
def test_mesh_argument_errors(cli: Cli, argv: list[str], expected: str) -> None:
    code, out, err = cli(*argv)
    assert code == 2 and out == "" and err.count("\n") == 1
    assert expected in err


def test_the_default_stem_stays_in_the_working_folder_whatever_the_scene_name(
    box: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    argv = ["fit", "--mesh", str(box), *MESH_ARGS, "--param", 'name="../escape"', "--steps", "2", "--dim", "2"]
    assert main([*argv, "--width", "8", "--layers", "1", "--sigma", "0.01", "--json"]) == 0
    assert (tmp_path / ".._escape_d2.pt").is_file() and not (tmp_path.parent / "escape_d2.pt").exists()


def test_a_resume_without_the_meshs_params_names_the_command_that_continues_it(
    cli: Cli, box: Path, tmp_path: Path
) -> None:
    """An interrupted mesh fit resumed with --mesh but not its --param (the likely slip) was refused with only
    "--out STEM or --overwrite", and --overwrite throws the interrupted fit away; it now gives the recorded command."""
    stem = str(tmp_path / "cut")
    small = ["--steps", "4", "--dim", "2", "--width", "8", "--layers", "1", "--sigma", "0.01", "--out", stem]
    assert cli("fit", "--mesh", str(box), *MESH_ARGS, *small, "--stop-at", "2")[0] == 0
    code, _, err = cli(
        "fit", "--mesh", str(box), "--kind", "fem", "--param", "voxel_pitch=0.05", "--out", stem, "--resume"
    )
    *said, refused = err.splitlines()  # the error in one line, after the voxel solid's warning (show_warning)
    assert code == 2 and "young 20000.0 (this scene: 100000.0)" in refused, err
    assert all(line.startswith("redsim: warning: the voxel solid of mesh") for line in said), err
    command = err.split("to continue that fit, give its scene as it records: ", 1)[1].strip()
    assert command.startswith("redsim fit --mesh") and command.endswith(f"--out {stem} --resume"), err
    code, _, err = cli("fit", "--out", stem, "--resume")  # no scene at all: the same command
    assert (
        code == 2
        and err == f"redsim: error: --resume needs the fit's scene and settings as it records them: {command}\n"
    )
    assert cli(*shlex.split(command)[1:])[0] == 0  # the command it names continues the fit
    assert (tmp_path / "cut.pt").is_file()
