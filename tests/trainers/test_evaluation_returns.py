"""Training seeds move on with the steps a run resumes at (hand mutation audit, helper-281: a training seed of the
run's seed alone passed tests/trainers/test_agents.py -m 'not slow'). An evaluation's returns: tests/envs/
test_uneven_episodes.py."""

from __future__ import annotations

from redsim.trainers.agents import training_seed


def test_a_resumed_runs_training_seed_moves_on_with_its_steps() -> None:
    seeds = {training_seed(7, steps) for steps in (0, 1000, 2000, 5000)}
    assert len(seeds) == 4
    assert training_seed(7, 1000) == training_seed(7, 1000)
