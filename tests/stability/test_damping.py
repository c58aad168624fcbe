"""`redsim bench stability --regimes damping`: released unforced runs keep a finite, falling share of their free
energy, and the full-space reference keeps more at a smaller time step (implicit Euler's damping is O(h))."""

from __future__ import annotations

import json
import math
from collections.abc import Callable

import pytest
import torch

from redsim import pretrained, scenes
from redsim.benches import damping, stability
from redsim.benches.accuracy import run_full
from redsim.benches.stability import DT, FULL_SLACK

Cli = Callable[..., tuple[int, str, str]]


@pytest.fixture(scope="module")
def mini_chain() -> tuple:
    scene = scenes.build("mini_chain")
    f = pretrained.load("mini_chain", scene)
    return scene, f, damping.release_start(scene, f)


def test_released_runs_keep_a_finite_falling_share_of_their_free_energy(mini_chain: tuple) -> None:
    scene, f, start = mini_chain
    assert start.converged
    rows = damping.scene_rows(scene, f, seconds=0.3, divisions=(1,), full_divisions=(1,), start=start)
    assert [r["space"] for r in rows] == [*damping.RUNTIME_DTYPES, "full f64"]
    for row in rows:
        assert row["nan"] == 0 and row["unconverged"] == 0 and row["steps"] == 15, row
        assert row["free_energy_J"] > 0.0, row
        end = row["retained"]["0.3"]
        assert math.isfinite(end) and end < row["largest"] <= 1.0 + 1e-3, row


def test_the_reference_loses_free_energy_every_step_and_less_at_half_the_step(mini_chain: tuple) -> None:
    """Backward Euler on the mini chain: F_t never rises (float64 round-off aside), and dt / 2 keeps more of it."""
    scene, _f, start = mini_chain
    s64 = scene.to(dtype=torch.float64)
    kept = []
    for dt in (DT, DT / 2):
        steps = round(0.3 / dt)
        loads = torch.zeros(steps, 1, 3, dtype=torch.float64)
        run = run_full(scene, start.q0, loads, dt=dt, tol=scenes.full_space_tol("mini_chain"), max_iter=100)
        fractions = damping.retained(s64, run.q, run.q[0], dt, start.full_rest_J)
        assert float(fractions[0]) == 1.0 and bool(torch.isfinite(fractions).all())
        assert float(torch.diff(fractions).max()) <= FULL_SLACK
        kept.append(float(fractions[-1]))
    assert 0.0 < kept[0] < kept[1] < 1.0, kept


def test_mujoco_chain_rows_are_finite_fractions() -> None:
    pytest.importorskip("mujoco")
    rows = damping.mujoco_rows(0.5, seconds=0.1, divisions=(1,))
    assert rows is not None and [r["space"] for r in rows] == [f"MuJoCo {i}" for i in damping.MUJOCO_INTEGRATORS]
    for row in rows:
        assert row["nan"] == 0 and row["free_energy_J"] > 0.0 and math.isfinite(row["retained"]["0.1"]), row


def test_cli_damping_regime(cli: Cli) -> None:
    argv = ("bench", "stability", "--regimes", "damping", "--damping-scenes", "mini_chain", "--damping-seconds", "0.1")
    code, out, err = cli(*argv, "--damping-divisions", "1", "--damping-full", "1", "--json")
    assert code == 0, err
    doc = json.loads(out)
    assert doc["rows"] == [] and "machine" in doc
    assert [(r["scene"], r["space"], r["steps"]) for r in doc["damping"]["rows"]] == [
        ("mini_chain", "latent f32", 5),
        ("mini_chain", "latent f64", 5),
        ("mini_chain", "full f64", 5),
    ]
    code, out, err = cli(*argv, "--damping-divisions", "1", "--damping-full", "none")
    assert code == 0, err
    assert out.startswith("machine: ") and "| mini_chain | latent f64 | 0.02 | 5 |" in out and "full f64" not in out
    code, _out, err = cli(*argv, "--damping-scenes", "klann")
    assert code == 2 and "--damping-scenes: unknown scene(s) ['klann']" in err


def test_cli_prints_the_chain_table_beside_the_damping_table(cli: Cli, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--regimes mujoco,damping`` ran the chain scenarios (a blow-up there fails the command) but printed only the
    damping table."""
    monkeypatch.setattr(stability, "mujoco_chain_cases", lambda _steps: None)
    monkeypatch.setattr(stability, "redsim_chain_cases", lambda *_a, **_k: [])
    argv = ["--damping-scenes", "mini_chain", "--damping-seconds", "0.02", "--damping-divisions", "1"]
    code, out, err = cli("bench", "stability", "--regimes", "mujoco,damping", *argv, "--damping-full", "none")
    assert code == 0, err
    assert "| kick_1 |" in out and "the MuJoCo columns are skipped" in out and "| mini_chain | latent f64 |" in out


def test_a_start_not_above_its_rest_has_no_retained_fraction() -> None:
    """cloth_ball's full-space rest does not converge and lies 203 J above the loaded start: F_t / F_0 read 1."""
    fractions = torch.tensor([1.0, 0.999, 0.998], dtype=torch.float64)
    rows = [
        damping._row("cloth_ball", "full f64", 0.02, fractions, -203.0, 0.04, unconverged=0, idle=0, nan=0),
        damping._row("cloth_ball", "latent f64", 0.02, fractions, 0.5, 0.04, unconverged=0, idle=0, nan=0),
    ]
    assert math.isnan(rows[0]["retained"]["0.04"]) and math.isnan(rows[0]["largest"])
    assert rows[1]["retained"]["0.04"] == pytest.approx(0.998) and rows[1]["largest"] == pytest.approx(0.999)
    result = {"seconds": 0.04, "rows": rows, "mujoco": None, "starts_converged": {"cloth_ball": False}}
    lines = damping.damping_table(result)
    assert "| cloth_ball | full f64 | 0.02 | 2 | -203 | nan | nan |" in lines[2]
    assert lines[-1] == (
        "no retained fraction (nan) where the start is not above the rest: cloth_ball full f64 (its free energy at "
        "the start is <= 0)"
    )


def test_the_float32_runtime_idles_when_its_tolerance_outgrows_the_forces(mini_chain: tuple) -> None:
    """At dt / 16 the float32 runtime's tolerance (1e-6 of a force scale that grows as 1/h²) holds at the released
    start, so every step ends without an iteration and the chain never moves; float64 (1e-9) moves it."""
    scene, f, start = mini_chain
    loads = torch.zeros(10, 1, 3, dtype=torch.float64)
    for dtype, idle in ((torch.float32, 10), (torch.float64, 0)):
        run = stability.runtime_rollout(scene, f, loads, DT / 16, z0=start.z0, z_prev=start.z0, dtype=dtype)
        assert run.flags["idle"] == idle and run.flags["unconverged"] == 0, (dtype, run.flags)
        moved = float(torch.linalg.vector_norm(run.q[-1] - run.q[0]))
        assert (moved == 0.0) == (idle == 10), (dtype, moved)


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--damping-seconds", "0.001"], "--damping-seconds must be a whole multiple of 0.02 s"),
        (["--damping-seconds", "0.01"], "--damping-seconds must be a whole multiple of 0.02 s"),
        (["--damping-seconds", "0.003", "--damping-divisions", "16", "--damping-full", "4,16"], "of 0.005 s"),
        (["--damping-seconds", "0.03", "--damping-divisions", "1", "--damping-full", "none"], "of 0.02 s"),
        (["--damping-seconds", "0.01", "--damping-divisions", "1", "--damping-full", "4"], "of 0.02 s"),
    ],
)
def test_cli_refuses_damping_seconds_that_no_time_step_divides(cli: Cli, argv: list[str], expected: str) -> None:
    """Shorter than a step (no step to run) or not a whole number of steps (its columns would be mislabelled)."""
    code, out, err = cli("bench", "stability", "--regimes", "damping", "--damping-scenes", "mini_chain", *argv)
    assert code == 2 and out == "" and err.count("\n") == 1 and expected in err, err
    assert "Traceback" not in err


@pytest.mark.parametrize(
    "argv",
    [
        ["--damping-seconds", "2"],
        ["--damping-scenes", "chain"],
        ["--damping-divisions", "1"],
        ["--damping-full", "none"],
    ],
)
def test_cli_refuses_damping_options_without_the_damping_regime(cli: Cli, argv: list[str]) -> None:
    code, out, err = cli("bench", "stability", "--regimes", "stiff", *argv)
    assert code == 2 and out == "" and err.count("\n") == 1, err
    assert f"{argv[0]} can only be given with --regimes damping" in err


def test_check_seconds_takes_whole_multiples_of_every_step_up_to_round_off() -> None:
    for seconds in (0.02, 0.3, 1.0, 2.5):
        damping.check_seconds(seconds, damping.DIVISIONS)
    damping.check_seconds(0.005, (4, 16))
    for seconds, divisions in ((0.001, (1,)), (0.01, (1,)), (0.03, (1, 4)), (0.013, (16,)), (0.01, (3,))):
        with pytest.raises(ValueError, match="whole multiple"):
            damping.check_seconds(seconds, divisions)
    with pytest.raises(ValueError, match="whole multiple"):
        damping.bench_damping(["mini_chain"], seconds=0.001, divisions=(1,), full_divisions=())
