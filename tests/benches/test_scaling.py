"""`redsim bench scaling`: growth exponents, the table, bad input, and (slow) one small size measured."""

from __future__ import annotations

import math

import pytest

from redsim.benches import scaling


def _rows(exponent: float) -> list[dict]:
    rows = []
    for n in (1000, 4000, 16000):
        row = {"cells": 1, "n": n, "latent_iterations": 3.0, "full_iterations": 2.0}
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
    rows[0]["full_step_ms"] = math.nan
    table = scaling.markdown_table({"rows": rows, "exponents": scaling.growth_exponents(rows)})
    lines = table.splitlines()
    assert len(lines) == 2 + 3 + 1
    assert lines[-1].startswith("| growth exponent | 1 |")
    assert "–" in lines[2]


def test_bad_sizes_are_refused(cli) -> None:
    code, _, err = cli("bench", "scaling", "--sizes", "4,x")
    assert code == 2 and "--sizes" in err
    code, _, err = cli("bench", "scaling", "--sizes", "0")
    assert code == 2 and ">= 1" in err
    with pytest.raises(ValueError, match="sizes"):
        scaling.bench_scaling((0,))


@pytest.mark.slow
def test_one_small_size_is_measured() -> None:
    row = scaling.measure(1, fit_steps=1, warmup=1, latent_steps=1)
    assert row["n"] > 0 and row["d"] == 2
    for key in scaling.CURVES:
        assert math.isfinite(row[key]) and row[key] > 0, key
