"""The keyframe loop is Catmull-Rom between its keys, its tangent at each key the chord of the two around it (hand
mutation audit, helper-281: taking the key itself for the one before it still passed through every key)."""

from __future__ import annotations

import torch

from redsim.keyframes import catmull_rom_loop

KEYS = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 2.0], [-1.0, 1.0]], dtype=torch.float64)


def test_the_midpoint_between_two_keys_is_catmull_roms() -> None:
    path = catmull_rom_loop(KEYS, 8)  # two frames per key: frame 2 k + 1 halfway from key k to key k + 1
    for k in range(4):
        p0, p1, p2, p3 = (KEYS[(k + j) % 4] for j in (-1, 0, 1, 2))
        torch.testing.assert_close(path[2 * k + 1], (-p0 + 9.0 * p1 + 9.0 * p2 - p3) / 16.0)


def test_the_tangent_at_a_key_is_half_the_chord_around_it_on_both_sides() -> None:
    frames = 4000  # 1000 per key: one-sided slopes at each key, per unit of the spline parameter
    path = catmull_rom_loop(KEYS, frames)
    step = 4 / frames
    for k in range(4):
        at = k * frames // 4
        after = (path[(at + 1) % frames] - path[at]) / step
        before = (path[at] - path[at - 1]) / step
        chord = 0.5 * (KEYS[(k + 1) % 4] - KEYS[k - 1])
        torch.testing.assert_close(after, chord, atol=5e-3, rtol=0)
        torch.testing.assert_close(before, chord, atol=5e-3, rtol=0)
