"""`redsim bench scaling`: growth exponents, the table, sizes left out, bad input, the smallest mesh measured."""

from __future__ import annotations

import json
import math

import pytest

from redsim import processes
from redsim.benches import scaling


def _rows(exponent: float) -> list[dict]:
    rows = []
    for n in (1000, 4000, 16000):
        row = {"cells": 1, "n": n, "batch": 64, "latent_iterations": 3.0, "cubature_iterations": 3.0}
        row.update({"full_iterations": 2.0, "cubature_kept": 200, "cubature_force_error": 0.01})
        row["unconverged"] = {"latent": [0, 5], "cubature_batch": [0, 320], "full": [0, 1]}
        row.update({key: 2.0 * n**exponent for key in scaling.CURVES})
        rows.append(row)
    return rows


def test_growth_exponents_recover_a_power_law() -> None:
    exponents = scaling.growth_exponents(_rows(1.5))
    assert all(e == pytest.approx(1.5) for e in exponents.values())
    one = _rows(1.0)[:1]
    assert all(math.isnan(e) for e in scaling.growth_exponents(one).values())


def test_table_has_a_row_per_size_and_the_exponents() -> None:
    rows = _rows(1.0)
    table = scaling.markdown_table({"rows": rows, "exponents": scaling.growth_exponents(rows)})
    lines = table.splitlines()
    assert len(lines) == 2 + 3 + 1
    assert lines[-1].startswith("| growth exponent | 1 |")
    one = scaling.markdown_table({"rows": rows[:1], "exponents": scaling.growth_exponents(rows[:1])})
    assert one.splitlines()[-1].startswith("| growth exponent | – | – |")  # one size: nothing to fit


def test_a_measured_value_that_is_not_finite_reads_nan_not_a_dash() -> None:
    """A NaN measurement (a cubature whose force error came out NaN) printed –, the mark of an exponent with nothing
    to fit: the failure read as "does not apply". It reads nan, and its exponent uses the finite sizes."""
    rows = _rows(1.0)
    rows[0]["cubature_force_error"] = math.nan
    rows[0]["full_step_ms"] = math.inf
    exponents = scaling.growth_exponents(rows)
    lines = scaling.markdown_table({"rows": rows, "exponents": exponents}).splitlines()
    cells = dict(zip(lines[0].split(" | "), lines[2].split(" | "), strict=True))
    assert cells["cubature force error"] == "nan" and cells["full step ms"] == "inf"
    assert "–" not in lines[2] and exponents["full_step_ms"] == pytest.approx(1.0)


def test_unconverged_steps_are_shown_beside_their_times() -> None:
    rows = _rows(1.0)
    rows[1]["unconverged"] = {"latent": [2, 5], "cubature_batch": [3, 320], "full": [1, 1]}
    lines = scaling.markdown_table({"rows": rows, "exponents": scaling.growth_exponents(rows)}).splitlines()
    assert lines[0].endswith("| peak MiB | unconverged steps |")
    assert lines[3].endswith("| latent 2/5, cubature B=64 3/320, full 1/1 |")
    assert lines[2].endswith("| 0 |") and lines[4].endswith("| 0 |")


def test_a_step_not_run_is_shown_as_such_and_left_out_of_its_exponent() -> None:
    rows = _rows(1.0)
    rows[-1]["full_step_ms"] = None  # above --full-max-n
    rows[-1]["full_iterations"] = None
    exponents = scaling.growth_exponents(rows)
    assert exponents["full_step_ms"] == pytest.approx(1.0)
    last = scaling.markdown_table({"rows": rows, "exponents": exponents}).splitlines()[-2]
    assert last.count("not run") == 2
    only_one = [dict(r, full_step_ms=None) for r in rows[1:]] + rows[:1]
    assert math.isnan(scaling.growth_exponents(only_one)["full_step_ms"])


def test_bad_sizes_are_refused(cli) -> None:
    code, _, err = cli("bench", "scaling", "--sizes", "4,x")
    assert code == 2 and "--sizes" in err
    code, _, err = cli("bench", "scaling", "--sizes", "0")
    assert code == 2 and ">= 1" in err
    code, _, err = cli("bench", "scaling", "--full-max-n", "-1")
    assert code == 2 and "--full-max-n" in err
    code, _, err = cli("bench", "scaling", "--cubature-elements", "0")
    assert code == 2 and "--cubature-elements" in err
    with pytest.raises(ValueError, match="sizes"):
        scaling.bench_scaling((0,))


@pytest.mark.parametrize(
    ("error", "said"),
    [
        (ChildProcessError("its process ended without a result (exit code -9)"), "its process ended without a result"),
        (FloatingPointError("loss became nan at step 1"), "FloatingPointError: loss became nan at step 1"),
    ],
)
def test_cli_prints_the_sizes_before_a_dead_or_raising_one_and_fails(
    cli, monkeypatch: pytest.MonkeyPatch, error: Exception, said: str
) -> None:
    """A size's process killed, or raising (a fit that went non-finite, say: it was raised as it was, and the sizes
    measured before it were lost), ends the run with the table of the sizes before it, the error named, exit 1."""

    def alone(_function, args):  # k = 1 measured, k = 2's process killed or raising
        if args[0] == 2:
            raise error
        return _rows(1.0)[0]

    monkeypatch.setattr(processes, "alone", alone)
    code, out, err = cli("bench", "scaling", "--sizes", "1,2,3")
    assert code == 1 and "| 1000 | 2e+03 |" in out and out.count("| 1000 |") == 1, (out, err)
    assert f"size k = 2: {said}" in err
    code, out, _ = cli("bench", "scaling", "--sizes", "1,2", "--json")
    doc = json.loads(out)
    assert code == 1 and len(doc["rows"]) == 1 and "k = 2" in doc["failed"]


def test_the_smallest_mesh_has_a_finite_cubature_step_and_no_full_step_above_its_limit() -> None:
    row = scaling.measure(1, fit_steps=1, warmup=1, latent_steps=1, cubature_elements=8, batch=2, full_max_n=10)
    assert row["n"] > 10 and row["cubature_kept"] == 8  # of the beam's 30 tets
    for key in ("cubature_eval_ms", "cubature_step_ms", "cubature_batch_ms", "latent_batch_ms", "cubature_build_s"):
        assert math.isfinite(row[key]) and row[key] > 0, key
    assert 0.0 <= row["cubature_force_error"] < 1.0
    assert row["full_step_ms"] is None and row["full_iterations"] is None
    timed = {key: of for key, (_, of) in row["unconverged"].items()}
    assert timed == {"latent": 1, "cubature": 1, "cubature_batch": 2, "latent_batch": 2}  # no full step: not run
    assert all(0 <= count <= of for count, of in row["unconverged"].values())


@pytest.mark.slow
def test_one_small_size_is_measured() -> None:
    row = scaling.measure(1, fit_steps=1, warmup=1, latent_steps=1)
    assert row["n"] > 0 and row["d"] == 2
    for key in scaling.CURVES:
        assert math.isfinite(row[key]) and row[key] > 0, key


def test_the_steps_feel_the_loads_at_every_size_and_converge() -> None:
    """The bench stepped the briefly fitted MLP as fitted: its f(0) far from rest, the stepper's force scale F_b was
    that strained state's elastic force, which grows with the mesh, and float32's tolerance with it (3.8 m/s^2 at
    n = 1500 up to 2.7e4 at n = 82620): no timed step felt the tip load, 'its' read 0 at every size. The map is now
    stepped with f(0) at the seed (rest_at_origin), in float64 by default: the resolution is the inertia term's, the
    same at every size and far below the load, and the timed steps converge."""
    rows = [
        scaling.measure(k, fit_steps=1, warmup=1, latent_steps=2, cubature_elements=8, batch=2, full_max_n=0)
        for k in (1, 2)
    ]
    assert [row["dtype"] for row in rows] == ["float64", "float64"]
    small, large = (row["acceleration_resolution"] for row in rows)
    assert small < 1e-4 and large == pytest.approx(small, rel=0.01)  # as fitted: 8.8e-6 and 5.8e-5 m/s^2
    for row in rows:
        assert all(count == 0 for count, _ in row["unconverged"].values()), row["unconverged"]
        assert row["latent_calls"] >= 1 and row["cubature_calls"] >= 1  # each step evaluates its start, at least


def test_rest_at_origin_puts_f0_at_the_seed() -> None:
    import torch

    from redsim import scenes
    from redsim.subspace import SubspaceConfig, SubspaceMap

    scene = scenes.build("cantilever", cells_x=5, cells_yz=1)
    torch.manual_seed(0)
    f = SubspaceMap(SubspaceConfig(latent_dim=2, output_dim=scene.free_dof_count))
    assert (f(torch.zeros(1, 2))[0] - scene.q_seed.float()).abs().max() > 1e-2
    g = scaling.rest_at_origin(f, scene)
    assert g is f and torch.allclose(f(torch.zeros(1, 2))[0], scene.q_seed.float(), atol=1e-6)


def test_an_unknown_dtype_is_refused(cli) -> None:
    code, _, err = cli("bench", "scaling", "--dtype", "float16")
    assert code == 2 and "--dtype" in err
    with pytest.raises(ValueError, match="dtype"):
        scaling.measure(1, dtype="float16")
