"""`redsim bench envs --rounds N` merges its rounds (`redsim.envs.bench.median_rounds`): a round whose MuJoCo flex
cloth blew up is said, not hidden behind the first round's finite state."""

from __future__ import annotations

from typing import Any

from redsim.benches.mujoco_cloth import cloth_anchor_line, cloth_ratios
from redsim.envs.bench import median_rounds


def cloth_round(steps_per_s: float, finite: bool) -> dict[str, Any]:
    """One round's anchors as `bench envs` holds them, the flex cloth timed (1 vertex: the numbers are made up)."""
    cloth = {"vertices": 1, "pinned": 0, "nv": 3, "integrator": "implicitfast", "timestep": 0.01, "steps": 10}
    cloth |= {"steps_per_s": steps_per_s, "sim_s_per_wall_s": 0.01 * steps_per_s, "finite": finite}
    return {"available": True, "cloth": cloth}


def test_a_later_round_whose_cloth_ended_not_finite_is_reported() -> None:
    """The merged cloth kept the first round's ``finite``: a blow-up in round 2 or 3 printed a clean anchor line and
    took the cloth ratios against it."""
    rows = [{"id": "RedSim/HangingCloth-v0", "scene": "hanging_sheet", "vector": {"16": {"sim_s_per_wall_s": 1.0}}}]
    for bad in (1, 2):
        rounds = [cloth_round(100.0 + i, finite=i != bad) for i in range(3)]
        cloth = median_rounds(rounds)["cloth"]
        assert cloth["finite"] is False and cloth["steps_per_s"] == 101.0
        assert "NOT FINITE" in cloth_anchor_line(cloth) and cloth_ratios(rows, cloth) == {}
    cloth = median_rounds([cloth_round(100.0 + i, finite=True) for i in range(3)])["cloth"]
    assert cloth["finite"] is True and list(cloth_ratios(rows, cloth)) == ["RedSim/HangingCloth-v0"]
