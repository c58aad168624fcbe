"""`redsim bench accuracy`: its scenarios, its error measures, its bad input, and (slow) a whole run."""

from __future__ import annotations

import csv

import pytest
import torch

from redsim import scenes
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
        accuracy.plan("cloth_ball")


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


def test_cli_refuses_bad_input(cli) -> None:
    code, _, err = cli("bench", "accuracy", "cloth_ball")
    assert code == 2 and "bench accuracy runs on" in err
    code, _, err = cli("bench", "accuracy", "mini_chain", "--steps", "5")
    assert code == 2 and "--steps >= 10" in err
    code, _, err = cli("bench", "accuracy", "mini_chain", "--full", "dt3")
    assert code == 2 and "dt3" in err


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
    assert labels[0] == "full reference" and "full 1 Newton iteration" in labels
    assert any(label.startswith("modal_derivatives:") for label in labels)
    assert all(int(r["nonfinite"]) == 0 for r in rows)
    assert (tmp_path / "accuracy_mini_chain.png").stat().st_size > 1000
