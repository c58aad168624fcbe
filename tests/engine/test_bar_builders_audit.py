"""Where the 2D bar builders put their pins, handles and condition ranges, and the effects' positive-only lengths:
each test fails under a one-line mutation that every engine test passed (hand mutation audit, helper-283).

- bistable_bar pins its two end columns (pinning the column next to the right end kept the DOF count, the mirror and
  the compressed seed); its "middle" handle is the column at cells_x // 2 (one column right passed);
- conditional_bar's "tip" handle is its right end column (the column before it passed), and its "pin_location"
  condition is in metres, ``pin_location_range`` times ``length`` (the fractions themselves passed: length is 1 m by
  default);
- a sheet or 2D solid of thickness 0 is refused (the effects' "positive" check loosened to >= 0 took it, and the
  term's energy was 0 at every state).
"""

from __future__ import annotations

import pytest
import torch

from redsim import scenes
from redsim.effects import NeoHookean, StVKMembrane


def _seed_points(scene, handle: str) -> torch.Tensor:
    return scene.handle(handle).points.positions(scene.full_positions(scene.q_seed[None]))[0]


def test_the_bistable_bar_pins_its_end_columns_and_pulls_its_middle_column() -> None:
    cells_x, cells_y, length, compression = 6, 2, 1.0, 0.8
    scene = scenes.build("bistable_bar", cells_x=cells_x, cells_y=cells_y, length=length, compression=compression)
    pinned = scene.dof_map.full_values[scene.dof_map.pinned_index].reshape(-1, 2)  # (x, y) per pinned vertex
    ends = {0.0, compression * length}
    assert pinned.shape[0] == 2 * (cells_y + 1)
    assert {round(float(x), 12) for x in pinned[:, 0]} == ends
    middle = _seed_points(scene, "middle")
    assert middle.shape[0] == cells_y + 1
    assert torch.allclose(middle[:, 0], torch.full_like(middle[:, 0], compression * length * (cells_x // 2) / cells_x))


def test_the_conditional_bar_pulls_its_tip_and_places_its_support_in_metres() -> None:
    cells_x, cells_y, length = 6, 2, 2.0
    scene = scenes.build("conditional_bar", cells_x=cells_x, cells_y=cells_y, length=length)
    tip = _seed_points(scene, "tip")
    assert tip.shape[0] == cells_y + 1 and torch.allclose(tip[:, 0], torch.full_like(tip[:, 0], length))
    space = scene.condition_space
    index = space.names.index("pin_location")
    assert float(space.low[index]) == pytest.approx(0.3 * length) and float(space.high[index]) == pytest.approx(length)


def test_a_zero_thickness_is_refused() -> None:
    triangle = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]], dtype=torch.float64)
    with pytest.raises(ValueError, match="thickness of 'sheet' must be finite and > 0"):
        StVKMembrane("sheet", torch.arange(9).reshape(1, 3, 3), triangle, 1e4, 0.3, thickness=0.0)
    flat = triangle[:, :, :2]
    with pytest.raises(ValueError, match="thickness of 'plate' must be finite and > 0"):
        NeoHookean("plate", torch.arange(6).reshape(1, 3, 2), flat, 1e4, 0.3, thickness=0.0)
