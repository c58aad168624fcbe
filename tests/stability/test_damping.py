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
    """cloth_ball's full-space loaded start (the ball pushed off the cloth, falling: no equilibrium) ended 203 J below
    its converged rest: F_t / F_0 read 1. The note names the static solve that did not converge."""
    fractions = torch.tensor([1.0, 0.999, 0.998], dtype=torch.float64)
    rows = [
        damping._row("cloth_ball", "full f64", 0.02, fractions, -203.0, 0.04, unconverged=0, idle=0, nan=0),
        damping._row("cloth_ball", "latent f64", 0.02, fractions, 0.5, 0.04, unconverged=0, idle=0, nan=0),
    ]
    assert math.isnan(rows[0]["retained"]["0.04"]) and math.isnan(rows[0]["largest"])
    assert rows[1]["retained"]["0.04"] == pytest.approx(0.998) and rows[1]["largest"] == pytest.approx(0.999)
    result = {
        "seconds": 0.04,
        "rows": rows,
        "mujoco": None,
        "starts_converged": {"cloth_ball": False},
        "starts_unconverged": {"cloth_ball": ["full loaded"]},
    }
    lines = damping.damping_table(result)
    assert "| cloth_ball | full f64 | 0.02 | 2 | -203 | nan | nan |" in lines[2]
    assert lines[-2] == "a static solve of the start did not converge: cloth_ball (full loaded)"
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


@pytest.mark.parametrize(("gain", "code"), [(0.0, 0), (1e-7, 0), (5e-4, 0), (0.01, 4)])
def test_cli_fails_where_a_released_run_gained_free_energy(
    cli: Cli, monkeypatch: pytest.MonkeyPatch, gain: float, code: int
) -> None:
    """An unforced implicit-Euler run only loses free energy: a redsim row whose ``largest`` exceeds 1 + GAIN_TOL
    exits 4 and is named; round-off at rest (1e-7) and an idle run (exactly 1) pass."""
    real = damping.retained
    monkeypatch.setattr(damping, "retained", lambda *a: real(*a) * 0.0 + torch.tensor([1.0, 1.0 + gain]))
    argv = ("--damping-scenes", "mini_chain", "--damping-seconds", "0.02", "--damping-divisions", "1")
    status, out, err = cli("bench", "stability", "--regimes", "damping", *argv, "--damping-full", "none")
    assert status == code, err
    if code:
        assert (
            "released unforced runs gained free energy (damping: largest > 1.001): mini_chain latent f32 dt 0.02, "
            "mini_chain latent f64 dt 0.02"
        ) in err
        assert out.rstrip().endswith("mini_chain latent f32 dt 0.02, mini_chain latent f64 dt 0.02")
    else:
        assert err.count("redsim: error") == 0 and "gained" not in out


def test_mujoco_rows_that_gain_do_not_fail() -> None:
    """MuJoCo's implicit chain at 0.02 s gains 3x (docs/stability.md): a fact about MuJoCo, not a redsim defect."""
    row = damping._row(
        "mini_chain", "latent f64", 0.02, torch.tensor([1.0, 0.9]), 1.0, 0.02, unconverged=0, idle=0, nan=0
    )
    gain = damping._row("mujoco_chain", "MuJoCo implicit", 0.02, torch.tensor([1.0, 3.0]), 1.0, 0.02, nan=0)
    assert damping.gains({"rows": [row], "mujoco": [gain]}) == []
    assert damping.gains({"rows": [{**row, "largest": 1.0 + 2 * damping.GAIN_TOL}], "mujoco": None}) == [
        "mini_chain latent f64 dt 0.02"
    ]


def _interrupt_full_space(*_args: object, **_kwargs: object) -> None:
    raise KeyboardInterrupt


def test_an_interrupted_damping_run_keeps_the_rows_finished_before_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(damping, "run_full", _interrupt_full_space)
    with pytest.raises(damping.Interrupted) as stop:
        damping.bench_damping(["mini_chain"], seconds=0.02, divisions=(1,), full_divisions=(1,))
    assert isinstance(stop.value, KeyboardInterrupt)
    result = stop.value.result
    assert result["interrupted"] and result["starts_unconverged"] == {"mini_chain": []}
    assert [r["space"] for r in result["rows"]] == list(damping.RUNTIME_DTYPES)
    assert damping.damping_table(result)[-1] == "interrupted: the rows finished before it"


def test_ctrl_c_in_the_mujoco_rows_does_not_read_as_mujoco_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    """Interrupted while MuJoCo's chain ran, the result held the lift angle without the rows, which the table reads as
    "mujoco is not installed"; the angle now comes with the rows."""
    monkeypatch.setattr(damping, "release_start", lambda *_: damping.Start(*[torch.zeros(1)] * 4, 0.0, 0.0))
    monkeypatch.setattr(damping, "_scene_rows", lambda *_: iter(()))
    monkeypatch.setattr(damping, "lift_angle", lambda *_: 0.1)
    monkeypatch.setattr(damping, "mujoco_rows", _interrupt_full_space)
    with pytest.raises(damping.Interrupted) as stop:
        damping.bench_damping(["chain"], seconds=0.02, divisions=(1,), full_divisions=())
    result = stop.value.result
    assert result["interrupted"] and result["mujoco"] is None and result["mujoco_lift_deg"] is None
    assert not any("mujoco" in line for line in damping.damping_table(result))


def test_cli_prints_the_rows_finished_before_ctrl_c_and_exits_130(cli: Cli, monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C in the full-space run, after the two latent rows: the table has them, and the command exits 130."""
    monkeypatch.setattr(damping, "run_full", _interrupt_full_space)
    argv = ("--damping-scenes", "mini_chain", "--damping-seconds", "0.02", "--damping-divisions", "1")
    code, out, err = cli("bench", "stability", "--regimes", "damping", *argv, "--damping-full", "1")
    assert code == 130, err
    assert "| mini_chain | latent f32 | 0.02 | 1 |" in out and "| mini_chain | latent f64 | 0.02 | 1 |" in out
    assert "full f64" not in out and "interrupted: the rows finished before it" in out
    assert "redsim: warning: interrupted: the table has the regimes finished before it" in err
    code, out, err = cli("bench", "stability", "--regimes", "damping", *argv, "--damping-full", "1", "--json")
    assert code == 130, err
    doc = json.loads(out)["damping"]
    assert doc["interrupted"] and [r["space"] for r in doc["rows"]] == ["latent f32", "latent f64"]


@pytest.mark.slow
def test_cloth_ball_rest_converges_and_the_push_has_no_equilibrium() -> None:
    """Why cloth_ball's damping row reads nan: its rest converges, but under the push (8 N along +x on the 1 kg ball)
    the ball leaves the cloth and falls (nothing is below it), so the loaded solve stops unconverged far below."""
    from redsim.integrators.reference import full_equilibrium, rest_state

    scene = scenes.build("cloth_ball").to(dtype=torch.float64)
    q_rest, rest_ok = rest_state(scene)
    assert rest_ok
    q0, loaded_ok, _ = full_equilibrium(scene, damping.release_load(scene), start=q_rest)
    positions = scene.handle_positions(torch.stack([q_rest, q0])).reshape(2, len(scene.handles), scene.dim)
    ball = positions[:, scene.handle_names.index("ball")]
    assert not loaded_ok and float(ball[0, 1]) > -0.2 and float(ball[1, 1]) < -1.0, ball
    energies = scene.energy(torch.stack([q_rest, q0]))
    assert float(energies[1]) < float(energies[0]) - 10.0, energies


def test_counts_a_row_does_not_make_print_dash(mini_chain: tuple) -> None:
    """The full-space rows printed ``idle`` 0 and MuJoCo's ``unconverged`` and ``idle`` 0: counts never taken (idle is
    the runtime's; MuJoCo has no solve of redsim's). They are None and read -."""
    scene, f, start = mini_chain
    rows = damping.scene_rows(scene, f, seconds=0.02, divisions=(1,), full_divisions=(1,), start=start)
    full = next(r for r in rows if r["space"] == "full f64")
    assert full["idle"] is None and full["unconverged"] == 0
    mujoco = damping.mujoco_rows(0.5, seconds=0.02, divisions=(1,)) or []
    assert all(r["unconverged"] is None and r["idle"] is None for r in mujoco)
    lines = damping.damping_table({"rows": rows, "mujoco": mujoco, "seconds": 0.02, "starts_unconverged": {}})
    assert next(line for line in lines if "| full f64 |" in line).endswith("| 0 | - | 0 |")
    assert all(line.endswith("| - | - | 0 |") for line in lines if "| MuJoCo " in line)
