"""`redsim bench step`: the JSON report, bad input, the seeded load sequences and the MuJoCo chain model."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

import redsim
from redsim import pretrained, scenes
from redsim.cli import main
from redsim.runtime import LatentStepper
from redsim.runtime.baseline import check_source, run_baseline, weights_digest
from redsim.runtime.bench import load_magnitudes, load_sequence, mujoco_chain_xml, run_reference

SOURCE = Path(redsim.__file__).resolve().parent.parent
"""The source tree this redsim runs from: a baseline that must step exactly like this checkout's reference."""


def test_bench_step_json(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["bench", "step", "--scenes", "mini_chain", "--batches", "1,2", "--steps", "2", "--reference-steps", "2"]
    code = main([*argv, "--no-compile", "--rounds", "2", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    report = json.loads(out)
    (row,) = report["rows"]
    assert row["scene"] == "mini_chain" and row["d"] == 4
    assert set(row["eager"]) == {"1", "2"} and row["compiled"] == {}
    assert all(r["env_steps_per_s"] > 0 and 0.0 <= r["converged_fraction"] <= 1.0 for r in row["eager"].values())
    assert row["reference"]["converged_fraction"] == 1.0
    # two interleaved rounds: a rate is the median of its rounds, a speedup the median of per-round ratios
    assert row["rounds"] == 2 and len(row["reference"]["rounds_env_steps_per_s"]) == 2
    for b, r in row["eager"].items():
        mine, ref = r["rounds_env_steps_per_s"], row["reference"]["rounds_env_steps_per_s"]
        assert r["env_steps_per_s"] == pytest.approx(sum(mine) / 2)
        assert row["speedup"]["eager"][b] == pytest.approx((mine[0] / ref[0] + mine[1] / ref[1]) / 2)
    # one step from the reference's states; not small here: from rest the quasi-Newton solve of the mini
    # chain's first step lands in another (lower) local minimum than the reference's Newton
    assert math.isfinite(row["step_error"])
    assert report["mujoco"] is None or report["mujoco"][0]["nv"] == 72


def test_bench_step_dense_runs_both_iterations(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["bench", "step", "--scenes", "mini_chain", "--batches", "2", "--steps", "2", "--reference-steps", "2"]
    code = main([*argv, "--no-compile", "--dense", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    (row,) = json.loads(out)["rows"]
    assert row["dense-cmp"] == {} and set(row["speedup"]) == {"eager", "cold", "dense"}
    rows, dense = row["eager"]["2"], row["dense"]["2"]
    assert dense["rows_per_step"] >= 2 * dense["calls_per_step"] > 0  # every dense call evaluates the whole batch
    assert dense["converged_fraction"] == rows["converged_fraction"] == 1.0


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--scenes", "no_such_scene"], "no_such_scene"),
        (["--scenes", "toy_two_tets"], "no shipped subspace"),
        (["--batches", "0"], ">= 1"),
        (["--batches", "x"], "comma-separated integers"),
        (["--rounds", "0"], ">= 1"),
        (["--hessians", "magic"], "unknown Hessian"),
        (["--hessians", "exact", "--rounds", "3", "--dense"], "drop --rounds, --dense"),
        (["--hessians", "exact", "--reference-steps", "4", "--no-compile"], "drop --reference-steps, --no-compile"),
        (["--baseline", "/"], "holds no redsim package"),
    ],
)
def test_bench_step_bad_input_exits_2(capsys: pytest.CaptureFixture[str], argv: list[str], expected: str) -> None:
    code = main(["bench", "step", *argv])
    _, err = capsys.readouterr()
    assert code == 2
    assert expected in err


def test_load_sequences_are_seeded_and_change_every_few_steps() -> None:
    scene = scenes.build("mini_chain")
    stepper = LatentStepper(scene, pretrained.load("mini_chain"))
    magnitudes = load_magnitudes(stepper)
    assert magnitudes.shape == (1,) and float(magnitudes[0]) > 0
    a = load_sequence(scene, magnitudes, 12, 3, every=5, seed=4)
    assert a.shape == (12, 3, 1, 3)
    assert torch.equal(a, load_sequence(scene, magnitudes, 12, 3, every=5, seed=4))
    assert torch.equal(a[0], a[4]) and not torch.equal(a[4], a[5])
    assert float(torch.linalg.vector_norm(a, dim=-1).max()) <= float(magnitudes[0]) + 1e-12


def test_mujoco_chain_has_24_ball_joints() -> None:
    mujoco = pytest.importorskip("mujoco")
    model = mujoco.MjModel.from_xml_string(mujoco_chain_xml())
    assert model.nv == 72 and model.nbody == 26  # world, hook, 24 links


def test_baseline_runs_another_trees_reference_on_the_same_loads() -> None:
    """The baseline subprocess imports redsim from the tree it is given and steps the same computation: given
    this checkout, its reference takes the in-process reference's iterations on the same map, loads and start."""
    scene = scenes.build("mini_chain")
    subspace = pretrained.load("mini_chain", scene)
    stepper = LatentStepper(scene, subspace, 0.02)
    loads = load_sequence(scene, load_magnitudes(stepper), 3, 1, seed=0)[:, 0]
    z0 = stepper.rest_latent()[0]
    base = run_baseline(SOURCE, "mini_chain", subspace, 0.02, z0, loads)
    mine = run_reference(scene, subspace, 0.02, z0, loads)
    assert Path(base["redsim_file"]).resolve() == Path(redsim.__file__).resolve()
    assert base["same_weights"] and base["env_steps_per_s"] > 0
    assert base["iterations_per_step"] == mine["iterations_per_step"]
    other = pretrained.load("klann")
    assert weights_digest(other) != weights_digest(subspace)
    assert not run_baseline(SOURCE, "mini_chain", other, 0.02, z0, loads)["same_weights"]


def test_baseline_needs_a_redsim_source_tree(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="holds no redsim package"):
        check_source(tmp_path)


def test_the_full_space_row_times_from_where_its_settling_steps_end() -> None:
    """run_reference(settle=S): the first S loads run untimed from f(z0), the timing and the trajectory go on from
    there; a settle as long as the loads still times the last step."""
    scene = scenes.build("mini_chain")
    f = pretrained.load("mini_chain", scene)
    z0 = LatentStepper(scene, f, 0.02).rest_latent()[0]
    loads = load_sequence(scene, torch.tensor([5.0]), 4, 1, seed=0)[:, 0]
    full = run_reference(scene, f, 0.02, z0, loads, space="full", warmup=0)
    settled = run_reference(scene, f, 0.02, z0, loads, space="full", warmup=0, settle=2)
    assert len(full["trajectory"]) == 5 and len(settled["trajectory"]) == 3
    assert torch.allclose(settled["trajectory"][0], full["trajectory"][2], atol=1e-10)
    assert torch.allclose(settled["trajectory"][-1], full["trajectory"][-1], atol=1e-10)
    assert len(run_reference(scene, f, 0.02, z0, loads, space="full", warmup=0, settle=9)["trajectory"]) == 2


def _failing_on(name: str, error: BaseException, monkeypatch: pytest.MonkeyPatch) -> None:
    """Make bench_step raise ``error`` on scene ``name`` (the others run as they do)."""
    import redsim.runtime.bench as bench

    real = bench.bench_step

    def bench_step(scene, subspace, **kwargs):
        if scene.name == name:
            raise error
        return real(scene, subspace, **kwargs)

    monkeypatch.setattr(bench, "bench_step", bench_step)


STEP_ARGV = [
    "bench",
    "step",
    "--scenes",
    "mini_chain,klann",
    "--batches",
    "1",
    "--steps",
    "2",
    "--reference-steps",
    "2",
]


def test_a_scene_that_raises_is_reported_and_the_others_are_printed(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A scene whose bench raised ended the command in a traceback and lost the scenes measured before it."""
    _failing_on("mini_chain", RuntimeError("singular Hessian"), monkeypatch)
    code = main([*STEP_ARGV, "--no-compile"])
    out, err = capsys.readouterr()
    assert code == 1, err
    assert "klann " in out and "failed: mini_chain: RuntimeError: singular Hessian" in out
    assert "bench step: 1 scene(s) failed (mini_chain); the others ran" in err
    code = main([*STEP_ARGV, "--no-compile", "--json"])
    report = json.loads(capsys.readouterr().out)
    assert code == 1 and [r["scene"] for r in report["rows"]] == ["klann"]
    assert report["failed"] == [{"scene": "mini_chain", "error": "RuntimeError: singular Hessian"}]


def test_ctrl_c_prints_the_scenes_finished_before_it_and_exits_130(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C lost every finished scene (the table is printed at the end); they are printed now, without MuJoCo's."""
    _failing_on("klann", KeyboardInterrupt(), monkeypatch)
    code = main([*STEP_ARGV, "--no-compile"])
    out, err = capsys.readouterr()
    assert code == 130, err
    assert "mini_chain " in out and "klann" not in out and "MuJoCo" not in out and "mujoco" not in out
    assert out.rstrip().endswith("interrupted: the scenes finished before it")
    code = main([*STEP_ARGV, "--no-compile", "--json"])
    report = json.loads(capsys.readouterr().out)
    assert code == 130 and report["interrupted"] and [r["scene"] for r in report["rows"]] == ["mini_chain"]


def test_a_non_finite_error_or_a_diverged_solve_fails_the_command(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A rollout whose error read nan, or whose solves diverged, exited 0 with the table: now 3 and 4 (as bench
    stability and bench accuracy: non-finite 3, failed steps 4), each named under the table and in the JSON."""
    import redsim.runtime.bench as bench

    real = bench.bench_step

    def broken(change):
        def bench_step(scene, subspace, **kwargs):
            row = real(scene, subspace, **kwargs)
            if scene.name == "klann":
                change(row)
            return row

        return bench_step

    def nan_rollout(row):
        row["trajectory_error"] = float("nan")

    def diverged(row):
        row["cold"]["1"]["diverged_fraction"] = 0.5

    argv = [*STEP_ARGV, "--no-compile"]
    monkeypatch.setattr(bench, "bench_step", broken(nan_rollout))
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == 3, err
    assert "mini_chain " in out and "failed: klann: trajectory error is nan (a non-finite state)" in out
    monkeypatch.setattr(bench, "bench_step", broken(diverged))
    code = main([*argv, "--json"])
    report = json.loads(capsys.readouterr().out)
    assert code == 4 and [r["scene"] for r in report["rows"]] == ["mini_chain", "klann"]
    assert report["nonfinite"] == [] and report["diverged"] == ["klann: cold B=1: 50% of the steps diverged (rejected)"]


def test_a_reference_that_does_not_move_is_reported_as_undefined_not_non_finite(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """At dt 1e-4 the mini chain's loads are too small to be felt (float32 and the float64 reference alike), so the
    reference stays at rest: the rollout error was 0/0 = nan, reported as 'a non-finite state' with exit 3 (and the
    one-step error read 0). Both are undefined now: None, named under the table and in the JSON, exit 1."""
    argv = ["bench", "step", "--scenes", "mini_chain", "--batches", "1", "--steps", "3", "--reference-steps", "3"]
    code = main([*argv, "--dt", "1e-4", "--no-compile"])
    out, err = capsys.readouterr()
    assert code == 1, err
    assert "redsim: warning: torch.float32 at dt=0.0001 s resolves accelerations only to" in err  # the stepper's
    assert "smaller forces are not felt" in err and "UserWarning" not in err  # one line, no source (show_warning)
    assert (
        "one step undefined, rollout undefined of the motion (M-norm of f(z)); undefined: the reference did not" in out
    )
    line = "mini_chain: the reference did not move (its motion is 0; loads too small to be felt at this --dt?)"
    assert f"failed: {line}: step error and trajectory error undefined" in out and "non-finite" not in out + err
    code = main([*argv, "--dt", "1e-4", "--no-compile", "--json"])
    out, err = capsys.readouterr()
    report = json.loads(out)
    assert "smaller forces are not felt" in err
    assert code == 1 and report["nonfinite"] == [] and report["diverged"] == []
    assert report["undefined"] == [f"{line}: step error and trajectory error undefined"]
    assert report["rows"][0]["step_error"] is None and report["rows"][0]["trajectory_error"] is None


def test_a_relative_error_is_undefined_only_where_a_finite_error_meets_no_motion() -> None:
    """A still reference gave 0/0 = nan (rollout) or error / 1e-300 (one step: 0, or ~1e293 where the stepper moved);
    it is None now, while a non-finite state or reference stays nan (the command's exit 3)."""
    from redsim.runtime.bench import _relative_error

    def norms(*values: float) -> torch.Tensor:
        return torch.tensor(values, dtype=torch.float64)

    assert _relative_error(norms(0.0, 2e-3), norms(0.0, 1e-2)) == pytest.approx(0.2)
    assert _relative_error(norms(0.0, 1e-7), norms(0.0, 0.0)) is None
    assert math.isnan(_relative_error(norms(0.0, math.nan), norms(0.0, 0.0)))
    assert math.isnan(_relative_error(norms(0.0, 1e-3), norms(0.0, math.nan)))


def test_the_table_says_its_rates_are_medians_over_the_rounds(capsys: pytest.CaptureFixture[str]) -> None:
    """With --rounds 2 every cell but its, conv% and the full row is a median over the rounds (a speedup the median
    of per-round ratios, not the ratio of the printed rates): the table said nothing of it, as if one run's."""
    argv = ["bench", "step", "--scenes", "mini_chain", "--batches", "1", "--steps", "2", "--reference-steps", "2"]
    said = "each rate the median over 2 rounds (the reference and every path in turn, reversed every other round)"
    assert main([*argv, "--no-compile", "--rounds", "2"]) == 0
    text = capsys.readouterr().out
    assert said in text and "speedup: the median of the per-round ratios to that round's reference" in text
    assert main([*argv, "--no-compile"]) == 0
    assert "median over" not in capsys.readouterr().out  # one round: one run's rates
