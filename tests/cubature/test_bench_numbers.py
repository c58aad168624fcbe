"""`redsim bench cubature`'s accuracy numbers recomputed from the rollouts it stepped: each energy's penetration is
its own rollout's, a state's deviation is max_t |q_cub - q_all|_M / max_t |q_all(t) - q_all(0)|_M."""

from __future__ import annotations

from redsim import pretrained, scenes
from redsim.cubature import CubatureConfig, build_cubature
from redsim.cubature import bench as cubature_bench


def test_the_accuracy_numbers_are_those_of_the_rollouts(monkeypatch) -> None:
    scene = scenes.build("mini_chain")
    f = pretrained.load("mini_chain", scene)
    cub = build_cubature(scene, f, CubatureConfig(elements=4, samples=48, episodes=0))
    rollouts = []
    original = cubature_bench._rollout

    def record(*args, **kwargs):
        out = original(*args, **kwargs)
        rollouts.append((args[0], out[0]))
        return out

    monkeypatch.setattr(cubature_bench, "_rollout", record)
    steps = 8
    run = cubature_bench.bench_cubature(scene, f, cub, steps=steps, batches=(1,), timed_steps=2, warmup=0)
    (stepper, z_all), (_, z_cub) = rollouts[:2]  # the accuracy rollouts: all elements, then the cubature
    q_all, q_cub = (
        stepper.positions(z.reshape(-1, z.shape[-1])).reshape(steps + 1, z.shape[1], -1) for z in (z_all, z_cub)
    )
    scene32 = stepper.scene
    pen_all = cubature_bench.penetration(scene32, q_all.reshape(-1, q_all.shape[-1]))
    pen_cub = cubature_bench.penetration(scene32, q_cub.reshape(-1, q_cub.shape[-1]))
    assert run["penetration_all_m"] == pen_all and run["penetration_cubature_m"] == pen_cub
    assert pen_all != pen_cub  # the two energies' rollouts touch the torus differently here
    # the deepest over all states and steps: the largest of each configuration's own
    singles = [cubature_bench.penetration(scene32, q) for q in q_all.reshape(-1, 1, q_all.shape[-1])]
    assert pen_all == max(singles) > 0.0
    mass = scene32.mass_norm_sq
    for b in range(z_all.shape[1]):
        gap = max(float(mass(q_cub[t, b : b + 1] - q_all[t, b : b + 1]).sqrt()) for t in range(steps + 1))
        motion = max(float(mass(q_all[t, b : b + 1] - q_all[0, b : b + 1]).sqrt()) for t in range(steps + 1))
        assert abs(run["deviation_per_state"][b] - gap / motion) <= 1e-5 * gap / motion
