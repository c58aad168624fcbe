"""`redsim fit`, `inspect`, `sample` and `animate` on a toy scene, and their errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from redsim.cli import catmull_rom_loop, main


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
    assert code == 0 and "reproduce: redsim fit" in out


def test_sample_exports_states(capsys: pytest.CaptureFixture[str], fitted: str, tmp_path) -> None:
    out_path = tmp_path / "states.npz"
    code, out, _ = run(capsys, "sample", fitted, "-n", "50", "--out", str(out_path), "--json")
    assert code == 0 and json.loads(out)["finite"]
    data = np.load(out_path)
    assert data["q"].shape == (50, 36) and data["z"].shape == (50, 2)
    assert str(data["scene"]) == "toy_three_link_chain"


def test_animate_writes_gif(capsys: pytest.CaptureFixture[str], fitted: str, tmp_path) -> None:
    gif = tmp_path / "loop.gif"
    code, _, _ = run(capsys, "animate", fitted, "--keys", "3", "--frames", "6", "--out", str(gif))
    assert code == 0 and gif.read_bytes()[:6] in (b"GIF89a", b"GIF87a")


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
        (["fit", "toy_two_tets", "--resume", "--out", "/nonexistent/x"], "nothing to resume"),
        (["inspect", "/nonexistent/model.pt"], "no metadata"),
        (["sample", "/nonexistent/model.pt"], "no metadata"),
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
    assert (tmp_path / "toy_tiny_bar_2d_d8_s30.pt").is_file()
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
