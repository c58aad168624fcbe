"""The env commands: ``redsim demo ENV_ID`` and ``redsim bench envs`` (their logic lives in redsim.envs)."""

from __future__ import annotations

import argparse
from typing import Any

from redsim.cli.bench import _machine_line
from redsim.cli.common import EXIT_OK, CliError, finish_command, json_out, out, parse_env_args, parse_list

SCRIPTED = "scripted controller"


def _check_id(env_id: str) -> None:
    import redsim

    if env_id not in redsim.envs.ids():
        raise CliError(f"unknown env {env_id!r}; valid: {', '.join(redsim.envs.ids())}")


def cmd_demo(args: argparse.Namespace) -> int:
    from redsim.envs.demo import run_demo

    _check_id(args.env_id)
    if args.steps is not None and args.steps < 1:
        raise CliError(f"--steps must be >= 1, got {args.steps}")
    policy, name = None, SCRIPTED
    if not args.scripted:
        from redsim.trainers.agents import load_agent, shipped_policies

        path = shipped_policies().get(args.env_id)
        if path is not None:
            policy, name = load_agent(path, env_id=args.env_id), f"shipped policy {path.name}"
    result = run_demo(args.env_id, args.out, seed=args.seed, steps=args.steps, policy=policy)
    result["policy"] = name
    if args.json:
        json_out(result)
        return EXIT_OK
    distance = result["final_distance"]  # None for a task without a target point (Klann's crank speed)
    out(
        f"{args.env_id} ({name}, seed {args.seed}): return {result['return']:.1f} over {result['steps']} steps, "
        + ("" if distance is None else f"final distance {distance:.3g} m, ")
        + f"{100 * result['success_fraction']:.0f}% of steps within the task's success tolerance"
    )
    out(f"speed: {result['env_steps_per_s']:.0f} env steps/s, {result['sim_s_per_wall_s']:.2f} simulated s per wall s")
    out(f"wrote {result['gif']} and {result['png']}")
    return EXIT_OK


def _row_line(row: dict[str, Any], batches: list[int]) -> str:
    cells = " ".join(f"{row['vector'][b]['env_steps_per_s']:>9.0f}" for b in batches)
    best = max((row["vector"][b]["sim_s_per_wall_s"] for b in batches), default=None)
    full = row["full_space"]
    return (
        f"{row['id']:<26} {row['n']:>6} {row['d']:>3} {row['action_size']:>4} {row['observation_size']:>4} "
        f"{row['single']['env_steps_per_s']:>8.0f} {cells} {row['single']['sim_s_per_wall_s']:>9.2f} "
        + (f"{best:>10.1f} " if best is not None else f"{'-':>10} ")
        + (f"{full['sim_s_per_wall_s']:>10.3g}" if full else f"{'-':>10}")
        + f" {row['render']['frames_per_s']:>8.0f}"
    )


def cmd_bench_envs(args: argparse.Namespace) -> int:
    import redsim
    from redsim.bench import machine_info
    from redsim.envs.bench import anchor_lines, bench_env, mujoco_anchors

    ids = redsim.envs.ids() if args.envs is None else parse_list(args.envs, "--envs")
    for env_id in ids:
        _check_id(env_id)
    try:
        batches = [int(b) for b in parse_list(args.batches, "--batches")]
    except ValueError as err:
        raise CliError(f"--batches must be comma-separated integers, got {args.batches!r}") from err
    if min(batches) < 1 or args.steps < 1 or args.anchor_steps < 1:
        raise CliError("--batches, --steps and --anchor-steps must be >= 1")
    env_kwargs = parse_env_args(args.env_arg, ids)
    if "device" in env_kwargs:
        raise CliError("give the device with --device, not --env-arg device=...")
    machine = machine_info()
    if not args.json:
        out("env steps/s (median over timed steps); simulated s per wall s of the single env, of the best batch,")
        out("and of the scene's float64 full-space implicit-Euler step (Newton) under the same kind of load;")
        out("render/s: frames per second of the single env's rgb_array picture at 480 x 480")
        out(_machine_line(machine, args.device))
        vec = " ".join(f"{f'N={b}':>9}" for b in batches)
        out(
            f"{'env':<26} {'n':>6} {'d':>3} {'act':>4} {'obs':>4} {'single':>8} {vec} {'sim/wall':>9} "
            f"{'best N':>10} {'full space':>10} {'render/s':>8}"
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
            **env_kwargs,
        )
        rows.append(row)
        if not args.json:
            out(_row_line(row, batches))
    if not args.json:
        out(
            "solver work per vector step: iterations per copy (of the slowest copy) / value-and-gradient calls "
            "/ rows per copy"
        )
        out(f"{'env':<26} " + " ".join(f"{f'N={b}':>27}" for b in batches))
        for row in rows:
            cells = (
                f"{r['iterations_per_step']:.1f} ({r['slowest_iterations_per_step']:.1f}) / "
                f"{r['calls_per_step']:.1f} / {r['rows_per_copy_step']:.1f}"
                for r in (row["vector"][b] for b in batches)
            )
            out(f"{row['id']:<26} " + " ".join(f"{c:>27}" for c in cells))
    anchors = mujoco_anchors(args.anchor_steps)
    if args.json:
        json_out({"machine": machine, "env_args": env_kwargs, "results": rows, "mujoco": anchors})
    else:
        for line in anchor_lines(anchors):
            out(line)
    return EXIT_OK


def add_commands(sub: Any, bench: Any) -> None:
    """Add ``demo`` to the top-level subcommands ``sub`` and ``envs`` to the ``bench`` subcommands."""
    p = sub.add_parser(
        "demo",
        help="run an env with its shipped policy or scripted controller; print return and speed, write a GIF",
        description=(
            "One episode of ENV_ID (e.g. RedSim/Chain-v0) driven by the trained policy shipped for it "
            "(redsim/pretrained/policies) or, where none is shipped or with --scripted, the task's scripted controller."
        ),
    )
    p.add_argument("env_id", metavar="ENV_ID", help="a RedSim env id")
    p.add_argument("--out", default="out", help="output folder (default out)")
    p.add_argument("--seed", type=int, default=0, help="reset seed (default 0)")
    p.add_argument("--steps", type=int, help="episode length (default: the env's max_episode_steps)")
    p.add_argument("--scripted", action="store_true", help="use the scripted controller even where a policy is shipped")
    finish_command(p, cmd_demo, "print one JSON summary", default_threads=1)

    p = bench.add_parser(
        "envs",
        help="env steps/s single and vectorized, against the full-space step",
        description=(
            "For each env id: n, d, action and observation sizes, env steps/s of the single env and of the native "
            "vector env per batch size, simulated seconds per wall second, and the same scene's float64 full-space "
            "implicit-Euler step; with mujoco installed, MuJoCo's 24-capsule chain and HalfCheetah-v5 in the same run."
        ),
    )
    p.add_argument("--envs", metavar="A,B,...", help="comma-separated ids (default: all)")
    p.add_argument("--batches", default="16,64,256", help="vector env sizes (default 16,64,256)")
    p.add_argument("--steps", type=int, default=20, help="timed steps per configuration (default 20)")
    p.add_argument("--budget", type=float, default=20.0, help="seconds of timing per configuration (default 20)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--no-full-space", action="store_true", help="skip the full-space step")
    p.add_argument("--anchor-steps", type=int, default=2000, help="timed steps of each MuJoCo anchor (default 2000)")
    p.add_argument(
        "--env-arg",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="keyword argument of every env, VALUE a JSON literal (e.g. cubature=true, "
        "stepper_options='{\"tol\": 1e-5}'); repeatable",
    )
    finish_command(p, cmd_bench_envs, "print one JSON document", default_threads=1)


__all__ = ["add_commands"]
