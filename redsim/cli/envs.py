"""``redsim demo ENV_ID`` and ``redsim bench envs`` (logic in redsim.envs)."""

from __future__ import annotations

import argparse
import json
from typing import Any

SCRIPTED = "scripted controller"


def _error(message: str) -> int:
    import sys

    print(f"redsim: error: {message}", file=sys.stderr, flush=True)
    return 2


def _check_id(env_id: str) -> str | None:
    import redsim

    return None if env_id in redsim.envs.ids() else f"unknown env {env_id!r}; valid: {', '.join(redsim.envs.ids())}"


def _cmd_demo(args: argparse.Namespace) -> int:
    from redsim.envs.demo import run_demo

    problem = _check_id(args.env_id)
    if problem:
        return _error(problem)
    if args.steps is not None and args.steps < 1:
        return _error(f"--steps must be >= 1, got {args.steps}")
    import torch

    torch.set_num_threads(args.threads)
    result = run_demo(args.env_id, args.out, seed=args.seed, steps=args.steps)
    if args.json:
        print(json.dumps(result), flush=True)
        return 0
    distance = result["final_distance"]
    print(
        f"{args.env_id} ({SCRIPTED}, seed {args.seed}): return {result['return']:.1f} over {result['steps']} steps, "
        f"final distance {distance:.3g} m, {100 * result['success_fraction']:.0f}% of steps within the success radius",
        flush=True,
    )
    print(
        f"speed: {result['env_steps_per_s']:.0f} env steps/s, {result['sim_s_per_wall_s']:.2f} simulated s per wall s",
        flush=True,
    )
    print(f"wrote {result['gif']} and {result['png']}", flush=True)
    return 0


def _row_line(row: dict[str, Any], batches: list[int]) -> str:
    cells = " ".join(f"{row['vector'][b]['env_steps_per_s']:>9.0f}" for b in batches)
    best = max(batches, key=lambda b: row["vector"][b]["sim_s_per_wall_s"]) if batches else None
    sim = f"{row['vector'][best]['sim_s_per_wall_s']:>9.1f}" if best is not None else f"{'-':>9}"
    full = row["full_space"]
    full_text = f"{full['sim_s_per_wall_s']:>9.3f}" if full else f"{'-':>9}"
    return (
        f"{row['id']:<26} {row['n']:>6} {row['d']:>3} {row['action_size']:>4} {row['observation_size']:>4} "
        f"{row['single']['env_steps_per_s']:>8.0f} {cells} {row['single']['sim_s_per_wall_s']:>9.2f} {sim} "
        f"{full_text}"
    )


def _cmd_bench_envs(args: argparse.Namespace) -> int:
    import redsim
    from redsim.bench import machine_info
    from redsim.envs.bench import bench_env, mujoco_anchors

    ids = redsim.envs.ids() if args.envs is None else [e.strip() for e in args.envs.split(",") if e.strip()]
    for env_id in ids:
        problem = _check_id(env_id)
        if problem:
            return _error(problem)
    try:
        batches = [int(b) for b in args.batches.split(",") if b.strip()]
    except ValueError:
        return _error(f"--batches must be comma-separated integers, got {args.batches!r}")
    if any(b < 1 for b in batches) or args.steps < 1:
        return _error("--batches and --steps must be >= 1")
    import torch

    torch.set_num_threads(args.threads)
    machine = machine_info()
    if not args.json:
        print("env steps/s (median over timed steps), simulated s per wall s; full space: float64 Newton step")
        load = machine["load_average_1min"]
        print(
            f"machine: {machine['processor']}, {machine['cpu_count']} CPUs (load {load:.2f}), torch {machine['torch']},"
            f" {machine['torch_threads']} threads, device {args.device}"
        )
        vec = " ".join(f"{f'N={b}':>9}" for b in batches)
        print(
            f"{'env':<26} {'n':>6} {'d':>3} {'act':>4} {'obs':>4} {'single':>8} {vec} {'sim/wall':>9} "
            f"{'sim/wall N':>9} {'full sim/wall':>9}"
        )
    rows = []
    for env_id in ids:
        row = bench_env(
            env_id,
            batches=batches,
            steps=args.steps,
            budget=args.budget,
            device=args.device,
            full_space=not args.no_full_space,
        )
        rows.append(row)
        if not args.json:
            print(_row_line(row, batches), flush=True)
    anchors = mujoco_anchors()
    if args.json:
        print(json.dumps({"machine": machine, "results": rows, "mujoco": anchors}, default=str), flush=True)
    elif anchors["available"]:
        cheetah = anchors["HalfCheetah-v5"]
        print(
            f"MuJoCo HalfCheetah-v5 (single): {cheetah['env_steps_per_s']:.0f} env steps/s, "
            f"{cheetah['sim_s_per_wall_s']:.1f} sim s per wall s"
        )
    else:
        print(f"MuJoCo anchors: {anchors['reason']}")
    return 0


def add_commands(sub: Any, bench: Any) -> None:
    """Add ``demo`` to the top-level subparsers ``sub`` and ``envs`` to the ``bench`` subparsers."""
    p = sub.add_parser(
        "demo",
        help="run an env with its scripted controller; print return and speed, write a GIF and a picture",
        description="One episode of ENV_ID (e.g. RedSim/Chain-v0) driven by the task's scripted controller.",
    )
    p.add_argument("env_id", metavar="ENV_ID", help="a RedSim env id")
    p.add_argument("--out", default="out", help="output folder (default out)")
    p.add_argument("--seed", type=int, default=0, help="reset seed (default 0)")
    p.add_argument("--steps", type=int, help="episode length (default: the env's max_episode_steps)")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    p.add_argument("--json", action="store_true", help="print one JSON summary")
    p.set_defaults(func=_cmd_demo)

    p = bench.add_parser(
        "envs",
        help="env steps/s single and vectorized, against the full-space step",
        description=(
            "For each env id: n, d, action and observation sizes, env steps/s of the single env and of the native "
            "vector env per batch size, simulated seconds per wall second, and the same scene's float64 full-space "
            "implicit-Euler step; MuJoCo anchors when mujoco is installed."
        ),
    )
    p.add_argument("--envs", metavar="A,B,...", help="comma-separated ids (default: all)")
    p.add_argument("--batches", default="16,64,256", help="vector env sizes (default 16,64,256)")
    p.add_argument("--steps", type=int, default=20, help="timed steps per configuration (default 20)")
    p.add_argument("--budget", type=float, default=20.0, help="seconds of timing per configuration (default 20)")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--no-full-space", action="store_true", help="skip the full-space step")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=_cmd_bench_envs)


__all__ = ["add_commands"]
