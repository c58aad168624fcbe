"""`redsim bench accuracy`: its scenarios, its error measures, its bad input, and (slow) a whole run."""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import pytest
import torch

from redsim import pretrained, scenes
from redsim.benches import accuracy
from redsim.benches.accuracy import Run


@pytest.fixture(scope="module")
def mini_chain():
    return scenes.build("mini_chain")


def test_push_is_a_constant_unit_action_along_x(mini_chain) -> None:
    loads = accuracy.scenario_loads(mini_chain, "push", 12)
    assert loads.shape == (12, 1, 3)
    assert bool((loads[:, 0, 0] == accuracy.PLANS["mini_chain"].max_force).all())
    assert bool((loads[:, 0, 1:] == 0).all())


def test_actions_are_seeded_bounded_and_held(mini_chain) -> None:
    a = accuracy.scenario_loads(mini_chain, "actions", 30, seed=3)
    assert torch.equal(a, accuracy.scenario_loads(mini_chain, "actions", 30, seed=3))
    assert not torch.equal(a, accuracy.scenario_loads(mini_chain, "actions", 30, seed=4))
    assert float(a.abs().max()) <= accuracy.PLANS["mini_chain"].max_force
    held = accuracy.HOLD_STEPS
    assert torch.equal(a[:held], a[:1].expand(held, -1, -1))
    assert not torch.equal(a[0], a[held])


def test_bad_scenarios_and_scenes_raise(mini_chain) -> None:
    with pytest.raises(ValueError, match="unknown scenario"):
        accuracy.scenario_loads(mini_chain, "wiggle", 10)
    with pytest.raises(ValueError, match="steps"):
        accuracy.scenario_loads(mini_chain, "push", 0)
    with pytest.raises(ValueError, match="knows scenes"):
        accuracy.plan("stiff_body")


def test_errors_compare_displacements_and_report_the_rest_offset(mini_chain) -> None:
    """A run that moves exactly like the reference from another start has zero error and a rest offset."""
    scene = mini_chain.to(dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    q = scene.q_seed + 0.01 * torch.randn(11, scene.free_dof_count, generator=g, dtype=torch.float64)
    reference = Run(q, torch.arange(11), [1.0] * 10)
    same = accuracy.trajectory_errors(scene, reference, reference, "bottom")
    assert same["rel_error_mean"] == 0.0 and same["handle_cm_mean"] == 0.0 and same["rest_offset"] == 0.0
    shift = torch.zeros(scene.free_dof_count, dtype=torch.float64)
    shift[3::12] = 0.05  # t_x of every body: the whole chain 5 cm to the side
    moved = accuracy.trajectory_errors(scene, Run(q + shift, torch.arange(11), [1.0] * 10), reference, "bottom")
    assert moved["rel_error_mean"] < 1e-12
    assert moved["rest_offset"] > 0.0
    assert moved["rest_offset_cm"] == pytest.approx(5.0)
    still = accuracy.trajectory_errors(
        scene, Run(q[:1].expand(11, -1), torch.arange(11), [1.0] * 10), reference, "bottom"
    )
    assert 0.0 < still["rel_error_mean"] <= 1.0  # not moving at all: at most the reference's own motion
    # the error at the projection floor's steps (every 10th: here step 10 alone), which the floor bounds
    assert still["rel_error_at_projection_steps"] == pytest.approx(still["rel_error_final"])
    assert math.isnan(
        accuracy.trajectory_errors(scene, Run(q[:6], torch.arange(6), [1.0] * 5), reference, "bottom")[
            "rel_error_at_projection_steps"
        ]
    )


def test_every_plan_is_an_envs_push_and_the_help_names_it(cli) -> None:
    """The reach envs' scenes push the env's handle with its max_force (bench and env cannot drift apart), and
    `--help` lists every scene the bench runs on."""
    from redsim.envs.cloth_ball import ClothBallEnv
    from redsim.envs.conditional_bar import ConditionalBarEnv

    for name, env in (("cloth_ball", ClothBallEnv), ("conditional_bar", ConditionalBarEnv)):
        plan = accuracy.plan(name)
        assert (plan.handle, plan.max_force) == (env.goal_handle, env.default_max_force)
        assert plan.reference_tol == scenes.full_space_tol(name)
        assert plan.handle in [h.name for h in scenes.build(name).handles]
    _, out, _ = cli("bench", "accuracy", "--help")
    assert all(name in " ".join(out.split()) for name in accuracy.PLANS)


def test_the_readme_names_every_plan_whose_reference_is_looser() -> None:
    """The README's reference sentence names each scene whose full-space reference stops above tol 1e-8, with its
    tolerance (cloth_ball's 1e-4 came with its plan and was left out)."""
    from pathlib import Path

    readme = " ".join((Path(__file__).parents[2] / "README.md").read_text().split())
    sentence = readme[readme.index("The **reference** is float64") :].split(" A latent run")[0]
    assert "tol 1e-8" in sentence
    for name in accuracy.PLANS:
        tol = accuracy.plan(name).reference_tol
        if tol != 1e-8:
            shown = f"{tol:.0e}".replace("e-0", "e-")  # 1e-4, as the README writes it
            assert name.replace("_", " ") in sentence and shown in sentence, (name, sentence)


def test_cli_refuses_bad_input(cli) -> None:
    code, _, err = cli("bench", "accuracy", "klann")
    assert code == 2 and "bench accuracy runs on" in err and "or a checkpoint (STEM.pt)" in err
    code, _, err = cli("bench", "accuracy", "mini_chain", "--steps", "5")
    assert code == 2 and "--steps must be >= 10, got 5" in err
    code, _, err = cli("bench", "accuracy", "mini_chain", "--full", "dt3")
    assert code == 2 and "--full must be from" in err and "(or none); got dt3" in err, err
    code, _, err = cli("bench", "accuracy", "mini_chain", "--scenarios", "push,pull")
    assert code == 2 and "--scenarios must be from push, actions; got pull" in err, err


def test_cli_refuses_options_no_chosen_mode_uses(cli, tmp_path) -> None:
    """--seed without the actions scenario, --no-study without push and --checkpoints without --dims were ignored."""
    argv = ("bench", "accuracy", "mini_chain", "--steps", "10", "--full", "none")
    for given, named in (
        (("--scenarios", "push", "--seed", "3"), "--seed (it seeds the actions scenario)"),
        (("--scenarios", "actions", "--no-study"), "--no-study (the start study runs on the push scenario)"),
        (("--scenarios", "push", "--checkpoints", str(tmp_path)), "--checkpoints (it keeps the --dims fits)"),
    ):
        code, out, err = cli(*argv, *given)
        assert code == 2 and out == "" and f"no chosen mode uses {named}: drop it" in err, (given, err)


@pytest.mark.filterwarnings("ignore:torch.float32 at dt")  # the toy cloth's loads are below float32's resolution
def test_a_checkpoint_of_any_scene_is_benched_as_the_reach_task_pushes_it(cli, tmp_path) -> None:
    """A user's map (a mesh scene's too) against the full space of the scene its .json records: how a short fit
    that barely follows the loads shows before an agent trains on it."""
    from redsim.envs.factory import default_force

    stem = str(tmp_path / "cloth")
    small = ("--dim", "2", "--width", "8", "--layers", "1", "--steps", "20", "--json")
    assert cli("fit", "toy_small_cloth", *small, "--out", stem)[0] == 0
    run = ("bench", "accuracy", stem + ".pt", "--steps", "10", "--scenarios", "push", "--full", "none", "--no-study")
    code, out, err = cli(*run, "--json")
    assert code == 0, err
    result = json.loads(out)
    scene = scenes.build("toy_small_cloth")
    assert result["scene"] == "toy_small_cloth" and result["plan"]["handle"] == scene.handle_names[0]
    assert result["plan"]["max_force"] == pytest.approx(default_force(scene))
    assert result["maps"][0]["source"].endswith("cloth.pt") and "shipped" not in result["maps"][0]["source"]
    labels = [row["config"] for row in result["rows"]]
    assert labels[:2] == ["full reference", accuracy.NO_MOTION] and any(x.startswith("neural:") for x in labels)
    bare = ("bench", "accuracy", stem, *run[3:], "--json")  # a bare STEM is a checkpoint too
    code, out, _ = cli(*bare, "--max-force", "0.5", "--handle", scene.handle_names[-1])
    assert code == 0 and json.loads(out)["plan"] | {"note": ""} == {
        "handle": scene.handle_names[-1], "max_force": 0.5, "reference_tol": 1e-8, "note": ""
    }  # fmt: skip
    for flags, message in (
        (("--handle", "nope"), "has no handle 'nope'; valid:"),
        (("--max-force", "0"), "max_force must be finite and > 0"),
        (("--dims", "1"), "--dims fits maps of a catalog scene's preset"),
    ):
        code, _, err = cli(*run, *flags)
        assert code == 2 and message in err, (flags, err)


def test_handle_and_max_force_on_a_catalog_scene_change_only_what_is_given(
    cli, mini_chain, tmp_path, monkeypatch
) -> None:
    shipped = accuracy.plan("mini_chain")
    stronger = accuracy.replanned(mini_chain, max_force=30.0)
    assert (stronger.handle, stronger.max_force, stronger.reference_tol) == (
        shipped.handle,
        30.0,
        shipped.reference_tol,
    )
    assert stronger.note.endswith("max_force 30.0 given") and accuracy.replanned(mini_chain) == shipped
    with pytest.raises(ValueError, match="has no handle 'tip'"):
        accuracy.replanned(mini_chain, handle="tip")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mini_chain").write_text("a file named like the scene")  # the catalog name wins
    code, _, err = cli("bench", "accuracy", "mini_chain", "--steps", "5")
    assert code == 2 and "--steps must be >= 10, got 5" in err, err
    code, _, err = cli("bench", "accuracy", "mini_chain", "--max-force", "-1")
    assert code == 2 and "max_force must be finite and > 0" in err, err


@pytest.mark.slow
def test_a_short_run_writes_table_csv_and_png(cli, tmp_path) -> None:
    code, out, _ = cli(
        "bench", "accuracy", "mini_chain", "--steps", "10", "--scenarios", "push", "--full", "newton1",
        "--no-study", "--out", str(tmp_path),
    )  # fmt: skip
    assert code == 0, out
    assert "| full reference |" in out and "machine:" in out
    rows = list(csv.DictReader((tmp_path / "accuracy_mini_chain.csv").open()))
    labels = [r["config"] for r in rows]
    assert labels[:2] == ["full reference", accuracy.NO_MOTION] and "full 1 Newton iteration" in labels
    still = rows[1]
    assert still["ms_per_step"] == "nan" and 0.0 < float(still["rel_error_mean"]) <= 1.0
    assert any(label.startswith("modal_derivatives:") for label in labels)
    assert all(int(r["nonfinite"]) == 0 for r in rows)
    assert (tmp_path / "accuracy_mini_chain.png").stat().st_size > 1000


def test_cli_refuses_bad_dims(cli) -> None:
    for dims, message in (("1,x", "comma-separated integers"), ("0,4", "between 1 and"), ("4,25", "n = 24")):
        code, _, err = cli("bench", "accuracy", "mini_chain", "--dims", dims)
        assert code == 2 and message in err, (dims, err)
    code, _, err = cli("bench", "accuracy", "mini_chain", "--fit-steps", "5")
    assert code == 2 and "--fit-steps needs --dims" in err
    code, _, err = cli("bench", "accuracy", "mini_chain", "--dims", "1", "--fit-steps", "0")
    assert code == 2 and "--fit-steps must be >= 1" in err


@pytest.fixture(scope="module")
def tiny_maps(mini_chain):
    """Neural maps of d = 1 and 2 of the mini chain (5 preset steps each) and a small cubature of the d = 2 one."""
    from redsim.cubature import CubatureConfig, build_cubature
    from redsim.trainers import FitConfig, fit_subspace
    from redsim.trainers.presets import preset

    maps = {
        d: fit_subspace(mini_chain, FitConfig(**{**preset("mini_chain"), "latent_dim": d, "steps": 5}), progress=False)
        for d in (1, 2)
    }
    maps = {d: result.subspace for d, result in maps.items()}
    cubature = build_cubature(mini_chain, maps[2], CubatureConfig(elements=4, samples=16, episodes=0))
    return maps, cubature


@pytest.mark.slow
def test_dims_build_three_subspaces_per_d_and_a_cubature_row(mini_chain, tiny_maps) -> None:
    maps, cubature = tiny_maps
    result = accuracy.bench_accuracy(
        mini_chain, maps[1], steps=10, scenarios=("push",), full=(), study=False, maps={2: maps[2]},
        cubatures={2: cubature},
    )  # fmt: skip
    assert result["dims"] == [1, 2] and [m["cubature_elements"] for m in result["maps"]] == [None, cubature.kept]
    labels = [row["config"] for row in result["rows"]]
    assert labels[:2] == ["full reference", accuracy.NO_MOTION]
    prefixes = [label.split(":")[0] for label in labels[2:]]
    assert list(dict.fromkeys(prefixes)) == [f"{k} d={d}" for k in accuracy.KINDS for d in (1, 2)]
    assert sum(label.startswith("neural d=1: runtime") for label in labels) == 6  # every option for `neural`
    assert sum(label.startswith("neural d=2: runtime") for label in labels) == 2  # default + cubature
    (row,) = [r for r in result["rows"] if r["config"].endswith(f"+ cubature ({cubature.kept} elements)")]
    assert row["d"] == 2 and row["nonfinite"] == 0 and row["steps_run"] == 10
    assert all(r["d"] == int(r["config"].split(" d=")[1][0]) for r in result["rows"][2:])
    assert "neural maps: d=1: 5 fit steps" in accuracy.report(result, "machine: test")


def test_maps_and_cubatures_that_do_not_belong_are_refused(mini_chain, tiny_maps) -> None:
    maps, cubature = tiny_maps
    with pytest.raises(ValueError, match="another map at d=1"):
        accuracy.bench_accuracy(mini_chain, maps[1], maps={1: maps[2]})
    with pytest.raises(ValueError, match="no neural map of that d"):
        accuracy.bench_accuracy(mini_chain, maps[1], cubatures={2: cubature})
    with pytest.raises(ValueError, match=r"maps\[2\] has d=1"):
        accuracy.bench_accuracy(mini_chain, maps[1], maps={2: maps[1]})
    with pytest.raises(ValueError, match="cubature built for another map"):
        accuracy.bench_accuracy(mini_chain, maps[1], cubatures={1: cubature})  # built for the d = 2 map


def test_a_checkpoints_file_is_refused_before_any_work(cli, tmp_path) -> None:
    """``--checkpoints`` of bench accuracy --dims and bench subspace is a folder (made when missing), never a file."""
    (tmp_path / "file").write_text("kept")
    for argv in (
        ["bench", "accuracy", "mini_chain", "--steps", "10", "--scenarios", "push", "--full", "none", "--dims", "1"],
        ["bench", "subspace", "--scenes", "toy_tiny_bar_2d", "--steps", "3"],
    ):
        for folder in (tmp_path / "file", tmp_path / "file" / "sub"):  # the file itself, or a folder below it
            code, out, err = cli(*argv, "--checkpoints", str(folder))
            assert code == 2 and out == "" and f"--checkpoints {folder}: {tmp_path / 'file'} is a file" in err, err
    assert (tmp_path / "file").read_text() == "kept" and not list(tmp_path.glob("*.pt"))  # no fit ran


@pytest.mark.slow
def test_cli_dims_fit_what_is_missing_once(cli, tmp_path) -> None:
    argv = ["bench", "accuracy", "mini_chain", "--steps", "10", "--scenarios", "push", "--full", "none", "--no-study"]
    argv += ["--dims", "1,4", "--fit-steps", "3", "--checkpoints", str(tmp_path), "--json"]
    code, out, err = cli(*argv)
    assert code == 0, err
    result = json.loads(out)
    fitted = tmp_path / "mini_chain_d1_s3.pt"
    assert [(m["d"], m["fit_steps"]) for m in result["maps"]] == [(1, 3), (4, 10_000)]
    assert result["maps"][0]["source"] == str(fitted) and result["maps"][1]["source"].startswith("shipped ")
    stamp = fitted.stat().st_mtime_ns
    code, out, err = cli(*argv[:-1])
    assert code == 0 and fitted.stat().st_mtime_ns == stamp  # reused
    assert "d=1: 3 fit steps" in out and "| neural d=1: runtime f32" in out


def test_a_loose_full_space_solve_that_never_moves_is_counted_idle() -> None:
    """At tol 1e-3 a small push stays within the tolerance of the rest state: no iteration, no motion; the
    bench counts those steps (its "idle" column) instead of scoring them as a faster solve."""
    from redsim.integrators import static_equilibrium

    scene = scenes.build("mini_chain")
    rest, _ = static_equilibrium(scene, {})
    loads = torch.zeros(3, len(scene.handles), 3, dtype=torch.float64)
    loads[:, -1, 0] = 0.01  # [N]
    loose = accuracy.run_full(scene, rest.double(), loads, tol=1e-3)
    tight = accuracy.run_full(scene, rest.double(), loads)
    assert loose.idle == 3 and torch.equal(loose.q[-1], rest.double())
    assert tight.idle == 0 and float((tight.q[-1] - rest.double()).abs().max()) > 1e-4


def test_the_table_tells_a_non_finite_error_from_a_column_that_does_not_apply() -> None:
    row = {key: 1.0 for key, _header, _fmt in accuracy.COLUMNS}
    row.update(scenario="push", config="diverged run", failed=0, flagged_diverged=3, out_of_range=0)
    row.update(nonfinite=2, idle=0)
    row.update(rel_error_mean=float("nan"), projection=float("nan"))
    table = accuracy.markdown_table({"rows": [row]}, "push")
    cells = table.splitlines()[-1].split(" | ")
    headers = [h for _k, h, _f in accuracy.COLUMNS]
    assert cells[headers.index("rel. M error")] == "nan" and cells[headers.index("projection")] == "–"


def test_the_pareto_plot_names_the_rows_it_cannot_place(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A diverged row (no finite error) has no place on the log-log plot: the panel names it; it was left out
    silently while the table showed it as nan."""
    from matplotlib.axes import Axes

    texts: list[str] = []
    draw_text = Axes.text

    def recording_text(self, x, y, s, *args, **kwargs):
        texts.append(s)
        return draw_text(self, x, y, s, *args, **kwargs)

    monkeypatch.setattr(Axes, "text", recording_text)
    good = {"scenario": "push", "config": "runtime d=2 (default)", "family": "neural", "d": 2}
    good.update(rel_error_mean=0.01, ms_per_step=2.0)
    lost = {**good, "config": "runtime tol 1e-2", "rel_error_mean": float("nan")}
    # no run, never a time (every study has it): not named, or every panel would say it was left out
    still = {**good, "config": accuracy.NO_MOTION, "family": "reference", "ms_per_step": float("nan")}
    result = {"rows": [good, lost, still], "scene": "mini_chain", "n": 24, "d": 2, "dims": [2]}
    accuracy.pareto_png(result, tmp_path / "p.png", "machine")
    assert (tmp_path / "p.png").stat().st_size > 0
    assert accuracy.undrawn_configs(result["rows"], "push") == ["runtime tol 1e-2"]
    assert any("runtime tol 1e-2" in t for t in texts) and not any(accuracy.NO_MOTION in t for t in texts)


def test_substeps_are_finer_steps_of_the_same_load_and_each_scene_has_its_full_space_tolerance(mini_chain) -> None:
    """dt4th: a row step of 2 substeps is 2 reference steps of dt / 2 under the same load, counted once."""
    from redsim.integrators import FullSpace, FullState, ImplicitEuler
    from redsim.integrators.reference import rest_state

    q0 = rest_state(mini_chain)[0]
    loads = accuracy.scenario_loads(mini_chain, "push", 3)
    fine = accuracy.run_full(mini_chain, q0, loads, substeps=2)
    integrator = ImplicitEuler(FullSpace(mini_chain.to(dtype=torch.float64)), accuracy.DT / 2, tol=1e-8)
    state = FullState(q0.clone(), q0.clone(), 0.0)
    for i in range(3):
        for _ in range(2):
            state, _ = integrator.step(state, loads[i])
        assert torch.allclose(fine.q[i + 1], state.q, atol=1e-12)
    assert len(fine.step_s) == 3 and fine.failed == 0
    assert scenes.full_space_tol("hanging_sheet") == accuracy.PLANS["hanging_sheet"].reference_tol == 1e-4
    assert scenes.full_space_tol("chain") == 1e-8 == scenes.full_space_tol("a mesh scene not in the registry")


def test_a_full_space_rest_that_did_not_converge_is_said_in_the_report(mini_chain, monkeypatch) -> None:
    """``rest_converged`` was in the JSON alone: the text report now says so where the rest solve stopped short."""
    rest_state = accuracy.rest_state
    monkeypatch.setattr(accuracy, "rest_state", lambda scene: (rest_state(scene)[0], False))
    result = accuracy.bench_accuracy(
        mini_chain, pretrained.load("mini_chain"), steps=10, scenarios=("push",), full=(), study=False
    )
    assert result["rest_converged"] is False
    assert "note: the full-space rest solve did not converge" in accuracy.report(result, "machine: test")


def test_a_latent_rest_that_did_not_converge_is_said_in_the_report(mini_chain, monkeypatch) -> None:
    """Each subspace's rest solve's convergence was thrown away (a review's finding): its rows start where the solve
    stopped, so the JSON names the subspaces and the report says so."""
    solve = accuracy.latent_equilibrium

    def stopped_short(space, cond):
        z, info = solve(space, cond)
        return z, dataclasses.replace(info, converged=False)

    monkeypatch.setattr(accuracy, "latent_equilibrium", stopped_short)
    result = accuracy.bench_accuracy(
        mini_chain, pretrained.load("mini_chain"), steps=10, scenarios=("push",), full=(), study=False
    )
    assert result["latent_rests_unconverged"] and "neural" in result["latent_rests_unconverged"][0]
    assert "note: the latent rest solve did not converge for" in accuracy.report(result, "machine: test")


def _only(monkeypatch, *configs: accuracy.Config) -> None:
    """The bench's rows: the reference, no motion and ``configs`` (none of the subspaces' runs, for speed)."""
    monkeypatch.setattr(accuracy, "configurations", lambda *args, **kwargs: list(configs))


def test_a_reference_the_scene_cannot_make_or_a_non_finite_row_fails_the_command(cli, monkeypatch) -> None:
    """Both were a note or a column under exit status 0 (a review's finding): a script or CI took the rows measured
    against an impossible reference, or a run that went non-finite, for a good run. The rows are still printed."""
    argv = ("bench", "accuracy", "mini_chain", "--steps", "10", "--scenarios", "push", "--full", "none", "--no-study")
    _only(monkeypatch)
    code, out, err = cli(*argv, "--max-force", "1e9")  # far beyond what the chain can take: every step implausible
    assert code == 4 and "note: the reference is not a trustworthy motion" in out, (out, err)
    assert "scenario push: the reference made 10 of its 10 steps that the scene cannot" in err
    code, out, err = cli(*argv)  # the env's load: a good reference, exit 0
    assert code == 0 and "error" not in err, err

    def blown(loads: torch.Tensor) -> accuracy.Steps:
        q0 = accuracy.rest_state(scenes.build("mini_chain"))[0]
        q = q0.expand(loads.shape[0] + 1, -1).clone()
        q[5:] = math.nan
        yield
        return Run(q, torch.arange(q.shape[0]), [1e-3] * loads.shape[0], nonfinite=6)

    _only(monkeypatch, accuracy.Config("full blown", "full space", blown))
    code, out, err = cli(*argv, "--json")
    assert code == 3 and json.loads(out)["rows"][-1]["nonfinite"] == 6
    assert "scenario push, full blown: 6 non-finite states" in err
    unconverged = {"rows": [{"scenario": "push", "config": "full reference", "family": "reference", "failed": 65}]}
    assert accuracy.failures(unconverged) == ([], [])  # a note only (the bistable bar's reference: docs/accuracy.md)


def _raising(error: BaseException, after: int = 1):
    """A configuration's run that steps ``after`` times, then raises ``error``."""

    def run(loads: torch.Tensor) -> accuracy.Steps:
        for _ in range(after):
            yield
        raise error

    return run


def test_a_configuration_that_raises_is_a_row_that_fails_the_command(cli, monkeypatch) -> None:
    """A solve that raised in one configuration ended the command in a traceback, and every finished row of the
    scenario was lost; now its row reads nan with the error, the others are printed, and the command exits 1."""
    argv = ("bench", "accuracy", "mini_chain", "--steps", "10", "--scenarios", "push,actions", "--full", "none")
    good = accuracy.Config("full loose", "full space", lambda loads: accuracy.full_steps(*_rest(), loads, tol=1e-3))
    bad = accuracy.Config("full raises", "full space", _raising(RuntimeError("singular Hessian"), after=3))
    _only(monkeypatch, bad, good)
    code, out, err = cli(*argv, "--no-study")
    assert code == 1, err
    assert out.count("| full raises | – | – | nan | nan | nan |") == 2 and out.count("| full loose | ") == 2
    assert "note: full raises raised RuntimeError: singular Hessian: its row reads nan" in out
    assert "scenario push, full raises: RuntimeError: singular Hessian (raised)" in err
    code, out, err = cli(*argv, "--no-study", "--json")
    rows = json.loads(out)["rows"]
    assert (
        code == 1
        and [r["error"] for r in rows if r["config"] == "full raises"] == ["RuntimeError: singular Hessian"] * 2
    )
    assert all(r["error"] is None and r["rel_error_mean"] is not None for r in rows if r["config"] == "full loose")
    monkeypatch.setattr(accuracy, "full_steps", lambda *args, **kwargs: _raising(ValueError("no rest"))(None))
    _only(monkeypatch)
    code, out, err = cli(*argv, "--no-study")  # the reference itself: nothing is measured against it
    assert code == 1 and out.count("the reference raised ValueError: no rest: no row is measured") == 2, (out, err)


def _rest() -> tuple:
    scene = scenes.build("mini_chain")
    return scene, accuracy.rest_state(scene)[0]


def test_ctrl_c_keeps_the_finished_scenarios_rows_and_exits_130(cli, monkeypatch) -> None:
    """Ctrl-C lost every row (the command printed only "interrupted"); the finished scenario's rows are now printed
    (text and JSON, ``interrupted`` true), and the command exits 130 as bench stability's damping regime does."""
    argv = ("bench", "accuracy", "mini_chain", "--steps", "10", "--scenarios", "push,actions", "--full", "none")
    full_steps = accuracy.full_steps

    def interrupted_in_actions(scene, q0, loads, **options):
        if bool((loads[:, :, 1:] != 0).any()):  # the actions scenario's reference (push is along x only)
            raise KeyboardInterrupt
        return full_steps(scene, q0, loads, **options)

    monkeypatch.setattr(accuracy, "full_steps", interrupted_in_actions)
    _only(monkeypatch)
    code, out, err = cli(*argv, "--no-study")
    assert code == 130, err
    assert "scenario push:" in out and "scenario actions" not in out and "| full reference | " in out
    assert out.rstrip().endswith("interrupted: the rows finished before it")
    assert "redsim: warning: interrupted: the tables have the rows finished before it" in err
    code, out, err = cli(*argv, "--no-study", "--json")
    doc = json.loads(out)
    assert code == 130 and doc["interrupted"] and {r["scenario"] for r in doc["rows"]} == {"push"}


def test_a_max_force_beyond_float32_is_refused_before_any_work(cli, mini_chain) -> None:
    """1e300 N passed the check, ran the reference, then crashed the float32 runtime with a traceback."""
    code, out, err = cli("bench", "accuracy", "mini_chain", "--max-force", "1e300", "--steps", "10")
    assert code == 2 and out == "" and "max_force must be finite and > 0 [N], at most 3.4e+38" in err, err
    with pytest.raises(ValueError, match="at most"):
        accuracy.reach_plan(mini_chain, max_force=1e39)
    assert accuracy.replanned(mini_chain, max_force=1e38).max_force == 1e38


def test_a_checkpoint_of_a_catalog_scene_is_pushed_with_the_tables_loads(cli, tmp_path, monkeypatch) -> None:
    """A user's refit of the mini chain was pushed as the reach task pushes any scene (6.7 N, half its weight), not
    with the 15 N of the bench's plan, so its rows could not be set beside the README's tables (a review's finding);
    the bistable bar's was pushed with 1 N (no gravity) against the tables' 200 N."""
    stem = str(tmp_path / "mc")
    small = ("--dim", "2", "--width", "8", "--layers", "1", "--steps", "3", "--json")
    assert cli("fit", "mini_chain", *small, "--out", stem)[0] == 0
    _only(monkeypatch)
    argv = ("bench", "accuracy", stem + ".pt", "--steps", "10", "--scenarios", "push", "--full", "none", "--no-study")
    code, out, err = cli(*argv, "--json")
    assert code == 0, err
    shipped = accuracy.plan("mini_chain")
    assert json.loads(out)["plan"] == dataclasses.asdict(shipped)
    code, out, err = cli(*argv, "--json", "--max-force", "7")
    assert code == 0 and json.loads(out)["plan"]["max_force"] == 7.0, err


def test_the_start_studys_full_space_run_is_solved_as_the_reference(mini_chain, monkeypatch) -> None:
    """The study's run from f(z*) took run_full's defaults (tol 1e-8, 50 iterations) whatever the reference's (1e-4
    on the cloths, 100 iterations), so its ``full_fall`` came from another solve (a review's finding)."""
    full_steps, calls = accuracy.full_steps, []

    def spy(*args, **kwargs):
        calls.append((kwargs.get("tol"), kwargs.get("max_iter")))
        return full_steps(*args, **kwargs)

    monkeypatch.setattr(accuracy, "full_steps", spy)
    _only(monkeypatch)
    loose = dataclasses.replace(accuracy.plan("mini_chain"), reference_tol=1e-6)
    neural = pretrained.load("mini_chain")
    accuracy.bench_accuracy(mini_chain, neural, steps=10, scenarios=("push",), study_steps=10, load_plan=loose)
    assert calls == [(1e-6, accuracy.REFERENCE_MAX_ITER)] * 2  # the reference, then the study's run


def test_an_unconverged_reference_is_said_without_blaming_the_load(mini_chain, monkeypatch) -> None:
    """Unconverged steps alone (the bistable bar's reference, 65 of 100 near tol 1e-8 under the bench's own 200 N)
    were reported as "not a trustworthy motion ... a smaller --max-force", a load the user never gave (a review's
    finding); steps the scene cannot make keep that note."""
    _only(monkeypatch)
    result = accuracy.bench_accuracy(
        mini_chain, pretrained.load("mini_chain"), steps=10, scenarios=("push",), full=(), study=False
    )
    result["rows"][0]["failed"] = 3
    text = accuracy.report(result, "machine: test")
    assert "note: 3 of the reference's 10 steps ended unconverged (Newton stopped short of tol 1e-08" in text
    assert "--max-force" not in text and "trustworthy" not in text
    result["rows"][0]["implausible"] = 2
    assert "note: the reference is not a trustworthy motion: 2 of its 10 steps moved" in accuracy.report(result, "m")


def test_a_full_space_row_through_a_contact_is_said_and_a_reference_through_one_fails(mini_chain, monkeypatch) -> None:
    """At 5x the time step the mini chain's links passed through the hook (docs/accuracy.md): the row's errors (those
    of another motion) stood without a word. Those steps are now solved again and caught at the hook, which the
    report says (their times hold two solves); a row or a reference still through a contact is said, and a reference
    through one fails the command, as one the scene cannot make does."""
    from redsim.integrators.reference import rest_state

    q_rest, _ = rest_state(mini_chain)
    dt5 = accuracy.Config(
        "full dt x5", "full space", lambda loads: accuracy.full_steps(mini_chain, q_rest, loads, stride=5)
    )
    _only(monkeypatch, dt5)
    result = accuracy.bench_accuracy(
        mini_chain, pretrained.load("mini_chain"), steps=40, scenarios=("push",), full=(), study=False
    )
    row = next(r for r in result["rows"] if r["config"] == "full dt x5")
    assert row["tunneled"] == 0 and row["tunnels_caught"] >= 1 and result["rows"][0]["tunnels_caught"] == 0
    assert row["rel_error_mean"] < 1.0  # the motion of the chain the hook holds (95.4 through it)
    assert f"note: full dt x5 moved through a contact in the first solve of {row['tunnels_caught']} of its 8" in (
        accuracy.report(result, "m")
    )
    row["tunneled"] = 1
    assert "note: full dt x5 passed through a contact in 1 of its 8 steps" in accuracy.report(result, "m")
    assert accuracy.failures(result) == ([], [])
    result["rows"][0]["tunneled"] = 2
    assert "note: the reference is not a trustworthy motion: 2 of its 40 steps passed through a contact" in (
        accuracy.report(result, "m")
    )
    assert accuracy.failures(result)[0] == [
        "scenario push: the reference made 2 of its 40 steps through a contact (its note)"
    ]


def test_the_configurations_of_a_scenario_are_timed_step_by_step_in_turn(mini_chain) -> None:
    """Each row was timed after the one before (the reference first), so a load that changed during the bench moved
    the rows' time ratios by up to ~2x (a review's rerun, docs/accuracy.md); lockstep steps them in turn, a dt x 2
    run once every 2 reference steps, and each run's result is the one it makes alone."""
    q0 = accuracy.rest_state(mini_chain)[0]
    loads = accuracy.scenario_loads(mini_chain, "push", 4)
    order = []

    def tagged(name: str, steps: accuracy.Steps) -> accuracy.Steps:
        while True:
            try:
                next(steps)
            except StopIteration as stop:
                return stop.value
            order.append(name)
            yield

    fine = accuracy.full_steps(mini_chain, q0, loads)
    coarse = accuracy.full_steps(mini_chain, q0, loads, stride=2)
    runs = accuracy.lockstep([tagged("fine", fine), tagged("coarse", coarse)])
    assert order == ["fine", "coarse"] * 4  # the coarse run yields twice per step of 2 dt
    assert torch.equal(runs[0].q, accuracy.run_full(mini_chain, q0, loads).q)
    assert torch.equal(runs[1].times, torch.tensor([0, 2, 4])) and len(runs[1].step_s) == 2
    said = []  # the rows come when every configuration has ended; a long bench says how far it got meanwhile
    accuracy.bench_accuracy(mini_chain, pretrained.load("mini_chain"), steps=10, scenarios=("push",), full=(),
                            study=False, progress=said.append)  # fmt: skip
    assert said[:3] == ["push: 12 configurations stepped in turn, 10 steps", "push: step 1 of 10", "push: step 2 of 10"]
    assert "push: step 9 of 10" in said and "push: step 10 of 10" not in said and len(said) == 1 + 9 + 12


def test_a_full_space_row_the_scene_cannot_make_is_said(mini_chain, monkeypatch) -> None:
    """A loosened full-space run whose steps moved a coordinate more than 10x the scene's size (``implausible``,
    counted in the row) was said of the reference alone: the row's errors stood in the table, the count in the CSV
    and JSON only. The report names it, as it names a row through a contact."""

    def wild(loads: torch.Tensor) -> accuracy.Steps:
        q0 = accuracy.rest_state(mini_chain)[0]
        for _ in range(loads.shape[0]):
            yield
        q = q0.expand(loads.shape[0] + 1, -1).clone()
        return Run(q, torch.arange(q.shape[0]), [1e-3] * loads.shape[0], implausible=3)

    _only(monkeypatch, accuracy.Config("full wild", "full space", wild))
    result = accuracy.bench_accuracy(
        mini_chain, pretrained.load("mini_chain"), steps=10, scenarios=("push",), full=(), study=False
    )
    assert "note: full wild made 3 of its 10 steps that moved a coordinate more than 10x the scene's size" in (
        accuracy.report(result, "m")
    )
    assert accuracy.failures(result) == ([], [])  # a loosened row: a note, not a failure of the command


def test_a_flag_a_run_does_not_have_reads_dash_not_zero(mini_chain, monkeypatch) -> None:
    """Full-space rows printed ``diverged`` and ``out of range`` 0, the converged latent reference those and ``idle``
    0, and the no-motion row every count 0: flags and counts those runs never make (diverged and out of range are the
    runtime's; no motion solves nothing). They read –; the runtime's and full space's own counts stay numbers."""
    q_rest, _ = accuracy.rest_state(mini_chain)
    f = pretrained.load("mini_chain")
    z = accuracy.latent_equilibrium(accuracy.LatentSpace(mini_chain.to(dtype=torch.float64), f), None)[0]
    configs = [
        accuracy.Config(
            "full tol", "full space", lambda loads: accuracy.full_steps(mini_chain, q_rest, loads, tol=1e-3)
        ),
        accuracy.Config("latent ref", "neural", lambda loads: accuracy.latent_reference_steps(mini_chain, f, z, loads)),
        accuracy.Config(
            "runtime",
            "neural",
            lambda loads: accuracy.runtime_steps(accuracy.LatentStepper(mini_chain, f, 0.02), z, loads),
        ),
    ]
    _only(monkeypatch, *configs)
    result = accuracy.bench_accuracy(mini_chain, f, steps=10, scenarios=("push",), full=(), study=False)
    headers = [h for _k, h, _f in accuracy.COLUMNS]
    table = {
        line.split(" | ")[0].strip("| "): dict(zip(headers, line.strip("| ").split(" | "), strict=True))
        for line in accuracy.markdown_table(result, "push").splitlines()[2:]
    }
    counts = ("unconverged", "diverged", "out of range", "idle")
    assert [table[accuracy.NO_MOTION][c] for c in counts] == ["–"] * 4
    assert [table["full tol"][c] for c in counts] == ["0", "–", "–", "0"]
    assert [table["full reference"][c] for c in counts] == ["0", "–", "–", "0"]
    assert [table["latent ref"][c] for c in counts] == ["0", "–", "–", "–"]
    assert all(table["runtime"][c].isdigit() for c in counts)
    assert all(table[row]["non-finite"] == "0" for row in table)
