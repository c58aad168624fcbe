"""What each column of a bench table is, said in its header: a rate of B x steps over their total time and a median
step are different numbers (the same name meant both, in `bench step` and `bench envs`)."""

from __future__ import annotations

from collections.abc import Callable

Cli = Callable[..., tuple[int, str, str]]


def test_bench_step_hessians_says_which_time_is_a_median_and_which_rate_a_total(cli: Cli) -> None:
    """It printed `ms/step` (the median step) beside `env-steps/s` (B x steps / total time) with no word of either:
    1000 B / ms/step did not give the rate beside it."""
    code, out, err = cli(
        "bench", "step", "--hessians", "exact", "--scenes", "mini_chain", "--batches", "2", "--steps", "2"
    )
    assert code == 0, err
    lines = out.splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("scene"))
    assert lines[header].split()[3:] == ["its/step", "median", "ms", "env-steps/s", "conv%"]
    legend = " ".join(lines[:header])
    assert "median ms: the median step's wall time" in legend
    assert "env-steps/s: B x steps / the steps' total wall time" in legend
    assert lines[header + 1].split()[:3] == ["mini_chain", "exact", "2"]


def test_bench_step_says_its_rates_are_totals_not_medians(cli: Cli) -> None:
    """One round of `bench step` printed env-steps/s with no word of what it is: B x steps over their total wall time,
    where `bench envs`' column of the same name is B over its median step."""
    argv = "bench step --scenes mini_chain --batches 1 --steps 2 --reference-steps 2 --no-compile".split()
    code, out, err = cli(*argv)
    assert code == 0, err
    lines = out.splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("scene"))
    legend = " ".join(lines[:header])
    assert "env-steps/s: B x steps / the steps' total wall time (`bench envs`: B / its median step)" in legend
