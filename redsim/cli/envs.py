"""The env commands: ``redsim demo ENV_ID``, ``redsim bench envs`` and its cloth anchor, ``bench mujoco-cloth``,
and ``redsim bench env-ab ENV_ID`` (an interleaved A/B of env settings)."""

from __future__ import annotations

import argparse
import dataclasses
import json
from typing import Any

from redsim.cli.bench import _machine_line
from redsim.cli.common import (
    EXIT_OK,
    CliError,
    add_out_folder,
    check_device_option,
    finish_command,
    json_out,
    non_negative_seed,
    note,
    out,
    parse_env_args,
    parse_env_id,
    parse_list,
    seconds,
    warn,
    warn_if_out_of_date,
)
from redsim.cli.scene_runs import SceneRuns

SCRIPTED = "scripted controller"


def cmd_demo(args: argparse.Namespace) -> int:
    from redsim.envs.demo import run_demo

    args.env_id = parse_env_id(args.env_id)
    warn_if_out_of_date(args.env_id)
    if args.steps is not None and args.steps < 1:
        raise CliError(f"--steps must be >= 1, got {args.steps}")
    policy, name = None, SCRIPTED
    if not args.scripted:
        from redsim.trainers.agents import load_agent, shipped_policies

        path = shipped_policies().get(args.env_id)
        if path is not None:
            policy, name = load_agent(path, env_id=args.env_id), f"shipped policy {path.name}"
        else:
            warn(f"no policy is shipped for {args.env_id}: the task's scripted controller runs it")
    result = run_demo(args.env_id, args.out, seed=args.seed, steps=args.steps, policy=policy, threads=args.threads)
    result["policy"], result["seed"] = name, args.seed
    if args.json:
        json_out(result)
        return EXIT_OK
    distance = result["final_distance"]  # None for a task without a target point (Klann's crank speed)
    out(
        f"{args.env_id} ({name}, seed {args.seed}): return {result['return']:.1f} over {result['steps']} steps, "
        + ("" if distance is None else f"final distance {distance:.3g} m, ")
        + f"{100 * result['success_fraction']:.1f}% of steps with info['is_success']"
    )
    out(
        f"speed: {result['env_steps_per_s']:.0f} env steps/s, {result['sim_s_per_wall_s']:.2f} simulated s per wall s "
        f"(the median env step on {args.threads} thread(s), without the policy and the frames; the first step took "
        f"{1e3 * result['first_step_s']:.0f} ms)"
    )
    out(f"wrote {result['gif']} and {result['png']}")
    return EXIT_OK


def _gap(value: float | None) -> str:
    """An env-ab observation gap as printed: "-" where the observations' shapes differ."""
    return "-" if value is None else f"{value:.2g}"


def _failed_solves(row: dict[str, Any], batches: list[int]) -> list[str]:
    """The single env and batches of a :func:`bench_env` row whose timed steps had a solve that did not converge,
    diverged or left the map's range, each as printed: "N=16: 92.5% converged, 3 diverged, 0 out of range"."""
    parts = [("single", row["single"]), *((f"N={b}", row["vector"][b]) for b in batches)]
    return [
        f"{name}: {100 * part['converged_fraction']:.1f}% converged, {part['diverged']} diverged, "
        f"{part['out_of_range']} out of range"
        for name, part in parts
        if "failed" not in part and (part["converged_fraction"] < 1 or part["diverged"] or part["out_of_range"])
    ]


def _cell(part: dict[str, Any], key: str, spec: str) -> str:
    """A part's value as a table cell, ``failed`` where the part raised (:func:`redsim.envs.bench.attempt`)."""
    return "failed" if "failed" in part else format(part[key], spec)


def _row_line(row: dict[str, Any], batches: list[int]) -> str:
    if "failed" in row:  # the id as a whole: no env, no sizes
        return f"{row['id']:<26} failed (the env itself, named below)"
    single = row["single"]
    cells = " ".join(f"{_cell(row['vector'][b], 'env_steps_per_s', '.0f'):>9}" for b in batches)
    timed = [row["vector"][b]["sim_s_per_wall_s"] for b in batches if "failed" not in row["vector"][b]]
    full = row["full_space"]
    flag = "!" if _failed_solves(row, batches) else ""
    if full and "failed" not in full:
        full_cell = f"{full['sim_s_per_wall_s']:.3g}{'' if full['converged'] else '*':1}"
    else:
        full_cell = "failed" if full else "-"
    return (
        f"{row['id'] + flag:<26} {row['n']:>6} {row['d']:>3} {row['action_size']:>4} {row['observation_size']:>4} "
        f"{_cell(single, 'env_steps_per_s', '.0f'):>8} {cells} "
        f"{'-' if 'failed' in single else format(single['sim_s_per_wall_s'], '.2f'):>9} "
        + (f"{max(timed):>10.1f} " if timed else f"{'-':>10} ")
        + full_cell.rjust(10)
        + f" {_cell(row['render'], 'frames_per_s', '.0f'):>8}"
    )


def _spread_line(row: dict[str, Any], batches: list[int]) -> str:
    """The lowest and highest env steps/s over the rounds (``rounds_env_steps_per_s`` of :func:`median_rounds`) of the
    single env and each batch: how far the rounds of one cell moved (the table's value is their median)."""
    parts = [row["single"], *(row["vector"][b] for b in batches)]
    cells = (
        "failed" if "failed" in p else f"{min(p['rounds_env_steps_per_s']):.0f}-{max(p['rounds_env_steps_per_s']):.0f}"
        for p in parts
    )
    return f"{row['id']:<26} " + " ".join(f"{c:>11}" for c in cells)


def _work_cell(part: dict[str, Any]) -> str:
    """A vector part's solver work as the second table's cell."""
    if "failed" in part:
        return "failed"
    return f"{part['iterations_per_step']:.1f} ({part['slowest_iterations_per_step']:.1f}) / " + (
        "- / -"  # a sharded env's workers keep their own counts
        if part["calls_per_step"] is None
        else f"{part['calls_per_step']:.1f} / {part['rows_per_copy_step']:.1f}"
    )


def cmd_bench_envs(args: argparse.Namespace) -> int:
    import redsim
    from redsim.bench import machine_info
    from redsim.benches.mujoco_cloth import cloth_anchor, cloth_anchor_line, cloth_ratio_lines, cloth_ratios
    from redsim.envs.bench import (
        anchor_lines,
        attempt,
        bench_env,
        failed_parts,
        median_rounds,
        mujoco_anchors,
        old_versions_quiet,
    )

    ids = redsim.envs.ids() if args.envs is None else parse_list(args.envs, "--envs", parse_env_id)
    try:
        batches = parse_list(args.batches, "--batches", int)
    except ValueError as err:
        raise CliError(f"--batches must be comma-separated integers, got {args.batches!r}") from err
    if min(batches) < 1 or args.steps < 1 or args.anchor_steps < 1 or args.rounds < 1:
        raise CliError("--batches, --steps, --anchor-steps and --rounds must be >= 1")
    if args.shards < 1 or args.shards > min(batches):
        raise CliError(f"--shards must be in [1, the smallest batch {min(batches)}], got {args.shards}")
    if args.shard_timeout is not None and args.shards == 1:
        raise CliError("--shard-timeout bounds the wait for a sharded env's workers: give it with --shards P > 1")
    with old_versions_quiet():  # the env args are checked on every id, the older versions too
        env_kwargs = parse_env_args(args.env_arg, ids)
    if "device" in env_kwargs:
        raise CliError("give the device with --device, not --env-arg device=...")
    if "threads" in env_kwargs:  # the full-space step and the frames run on --threads too: one setting for all
        raise CliError("give the threads with --threads, not --env-arg threads=...")
    check_device_option(args.device)
    machine = machine_info()
    if not args.json:
        if args.rounds == 1:
            out("env steps/s by wall time (median over timed steps, each configuration timed once in turn: compare ids")
        else:
            out(
                f"env steps/s by wall time (median over timed steps, then over {args.rounds} rounds of every id in "
                "turn, reversed every other round; the full-space step in the first: compare ids"
            )
        out("within a run, and settings with `redsim bench env-ab`); simulated s per wall s of the single env, of the")
        out("best batch, and of the scene's float64 full-space implicit-Euler step (Newton to the scene's tolerance,")
        out("1e-8, the cloths 1e-4; from the env's reset state after untimed steps, a fresh random action each step);")
        out("render/s: frames per second of the single env's rgb_array picture at 480 x 480")
        out(_machine_line(machine, args.device))
        if args.shards > 1:
            out(f"vector envs: {args.shards} shards (worker processes of redsim.envs.sharded), own torch threads")
        vec = " ".join(f"{f'N={b}':>9}" for b in batches)
        out(
            f"{'env':<26} {'n':>6} {'d':>3} {'act':>4} {'obs':>4} {'single':>8} {vec} {'sim/wall':>9} "
            f"{'best N':>10} {'full space':>10} {'render/s':>8}"
        )
    measured: dict[str, list[dict[str, Any]]] = {env_id: [] for env_id in ids}
    anchor_rounds = []
    failed: list[dict[str, Any]] = []  # each part that raised: the run goes on, and fails at its end
    for index in range(args.rounds):
        for env_id in ids if index % 2 == 0 else ids[::-1]:
            if args.json:  # the text prints each row as it is measured; a JSON run says where it is on stderr
                note(f"timing {env_id}" + (f" (round {index + 1} of {args.rounds})" if args.rounds > 1 else ""))
            row = {"id": env_id} | attempt(
                lambda env_id=env_id, index=index: bench_env(
                    env_id,
                    batches=batches,
                    steps=args.steps,
                    budget=args.budget,
                    device=args.device,
                    full_space=not args.no_full_space and index == 0,
                    shards=args.shards,
                    shard_timeout=args.shard_timeout,
                    threads=args.threads,
                    **env_kwargs,
                )
            )
            failed += [
                {"id": env_id, "part": part, "round": index + 1, "error": text}
                for part, text in failed_parts(row).items()
            ]
            measured[env_id].append(row)
            if not args.json and args.rounds == 1:  # one round: each id's line as soon as it is measured
                out(_row_line(row, batches))
        anchors = mujoco_anchors(args.anchor_steps)
        if anchors["available"]:
            anchors["cloth"] = attempt(lambda: cloth_anchor(args.anchor_steps, args.budget))
        failed += [
            {"id": "MuJoCo", "part": name, "round": index + 1, "error": anchors[name]["failed"]}
            for name in ("chain", "HalfCheetah-v5", "cloth")
            if "failed" in anchors.get(name, {})
        ]
        anchor_rounds.append(anchors)
    rows = [median_rounds(measured[env_id]) for env_id in ids]
    if not args.json and args.rounds > 1:
        for row in rows:
            out(_row_line(row, batches))
    timed = [row for row in rows if "failed" not in row]  # the ids made: their parts' tables
    if not args.json:
        fulls = [row["full_space"] for row in timed if row["full_space"] and "failed" not in row["full_space"]]
        if any(not full["converged"] for full in fulls):
            out("* a timed full-space step ended unconverged at Newton's iteration cap: a faster rate than converging")
        unsolved = {row["id"]: _failed_solves(row, batches) for row in timed}
        if any(unsolved.values()):
            out("! timed env steps with a solve that did not converge, diverged (the copy then restarts) or left the")
            out("map's range (info's converged, diverged, out_of_range of the copies solved): not a working env's rate")
            for env_id, parts in unsolved.items():
                if parts:
                    out(f"  {env_id}: " + "; ".join(parts))
        if failed:
            out("failed: parts that raised (their cells read failed; the other parts ran):")
            for item in failed:
                shown = f" (round {item['round']})" if args.rounds > 1 else ""
                out(f"  {item['id']} {item['part']}{shown}: {item['error']}")
        out(
            "solver work per vector step: iterations per copy (of the slowest copy) / value-and-gradient calls "
            "/ rows per copy"
        )
        out(f"{'env':<26} " + " ".join(f"{f'N={b}':>27}" for b in batches))
        for row in timed:
            out(f"{row['id']:<26} " + " ".join(f"{_work_cell(row['vector'][b]):>27}" for b in batches))
        if args.rounds > 1:
            out(f"env steps/s, the lowest and highest of the {args.rounds} rounds (each value above is their median)")
            out(f"{'env':<26} {'single':>11} " + " ".join(f"{f'N={b}':>11}" for b in batches))
            for row in timed:
                out(_spread_line(row, batches))
    anchors = median_rounds(anchor_rounds)
    lines = anchor_lines(anchors)
    ratios: dict[str, float] = {}
    if anchors["available"]:
        ratios = cloth_ratios(rows, anchors["cloth"])
        lines += [cloth_anchor_line(anchors["cloth"]), *cloth_ratio_lines(ratios)]
    machine["load_average_1min_at_end"] = machine_info()["load_average_1min"]
    if args.json:
        json_out(
            {
                "machine": machine,
                "env_args": env_kwargs,
                "rounds": args.rounds,
                "results": rows,
                "mujoco": anchors,
                "cloth_ratios": ratios,
                "failed": failed,
            }
        )
    else:
        for line in lines:
            out(line)
        if machine["load_average_1min_at_end"] is not None:
            out(f"load at the end: {machine['load_average_1min_at_end']:.2f} (1-minute average)")
    # the rows are printed; a part that raised fails the command (exit 1, for scripts and CI), on the stderr line
    # of every bench that loops over scenes
    errors: dict[str, str] = {}  # each part once, with its first round's error (every round's is listed above)
    for item in failed:
        errors.setdefault(f"{item['id']} {item['part']}", item["error"])
    runs = SceneRuns("bench envs", not args.json, "part", [{"scene": n, "error": e} for n, e in errors.items()])
    return runs.status()


def _parse_settings(items: list[str], env_id: str) -> dict[str, dict[str, Any]]:
    """``--setting NAME[:KEY=VALUE]`` items -> name -> env keyword arguments, in the order the names first appear
    (a repeated NAME adds its KEY=VALUE to that setting; a bare NAME is the env's defaults)."""
    groups: dict[str, list[str]] = {}
    for item in items:
        name, _, pair = item.partition(":")
        name = name.strip()
        if not name or "=" in name:
            raise CliError(
                f"malformed --setting {item!r}: expected NAME or NAME:KEY=VALUE, e.g. --setting default "
                "--setting tight:stepper_options='{\"tol\": 1e-7}'"
            )
        groups.setdefault(name, [])
        if pair:
            groups[name].append(pair)
    if len(groups) < 2:
        raise CliError(f"give at least two settings (--setting NAME[:KEY=VALUE], repeated), got {list(groups)}")
    settings = {}
    for name, pairs in groups.items():
        try:
            settings[name] = parse_env_args(pairs, [env_id], "--setting", f"{name}:cubature=true")
        except CliError as err:
            raise CliError(f"setting {name!r}: {err}") from err
        if "device" in settings[name]:
            raise CliError(f"setting {name!r}: env-ab measures CPU time on the CPU; drop device=...")
    return settings


def cmd_bench_env_ab(args: argparse.Namespace) -> int:
    from redsim.bench import machine_info
    from redsim.envs.bench_ab import bench_env_ab, check_same_threads

    args.env_id = parse_env_id(args.env_id)
    for flag, value, least in (
        ("--num-envs", args.num_envs, 1),
        ("--rounds", args.rounds, 1),
        ("--steps-per-round", args.steps_per_round, 1),
        ("--warmup", args.warmup, 0),
        ("--render", 8 if args.render is None else args.render, 8),
    ):
        if value < least:
            raise CliError(f"{flag} must be an integer >= {least}, got {value}")
    from redsim.envs.base import MAX_IMAGE_SIDE

    if args.render is not None and args.render > MAX_IMAGE_SIDE:
        raise CliError(f"--render must be an integer in [8, {MAX_IMAGE_SIDE}] [px], got {args.render}")
    settings = _parse_settings(args.setting, args.env_id)
    try:
        check_same_threads(settings, args.threads)
    except ValueError as err:
        raise CliError(str(err)) from None
    machine = machine_info()
    result = bench_env_ab(
        args.env_id,
        settings,
        num_envs=args.num_envs,
        rounds=args.rounds,
        steps_per_round=args.steps_per_round,
        warmup=args.warmup,
        seed=args.seed,
        render=args.render,
        threads=args.threads,
    )
    result["machine"] = machine
    result["load_average_1min_end"] = machine_info()["load_average_1min"]
    if args.json:
        json_out(result)
        return EXIT_OK
    rows = result["settings"]
    first = rows[0]["name"]
    drawn = "" if args.render is None else f", each step then rendering every copy at {args.render} x {args.render} px"
    out(
        f"interleaved A/B of {args.env_id}: {args.num_envs} envs, {args.rounds} rounds of {args.steps_per_round} "
        f"vector steps per setting after {args.warmup} untimed (order reversed every other round){drawn}, the same "
        f"random actions (seed {args.seed}); CPU time of this process"
    )
    out(_machine_line(machine, "cpu"))
    for row in rows:
        shown = " ".join(f"{k}={json.dumps(v)}" for k, v in row["env_args"].items()) or "the env's defaults"
        out(f"  {row['name']}: {shown}")
    width = max(10, *(len(row["name"]) for row in rows))
    rendered = args.render is not None
    render_column = f"{'of it render':>12} " if rendered else ""
    spread = args.rounds > 1  # one round's ratio has no range to show
    out(
        f"{'setting':<{width}} {'CPU ms/step':>11} {render_column}"
        f"{'steps/CPU s':>11} {'its (slowest)':>14} {'calls':>6} "
        f"{'rows/copy':>9} {'converged':>9} {'out_of_range':>12} {'diverged':>8} {'obs gap':>8}  "
        + (f"vs {first}: median (range)" if spread else f"vs {first} (one round)")
    )
    for row in rows:
        ratio = row["ratio"]
        its = f"{row['iterations_per_step']:.2f} ({row['slowest_iterations_per_step']:.1f})"
        render = f"{row['render_cpu_ms']:>12.1f} " if rendered else ""
        out(
            f"{row['name']:<{width}} {row['cpu_ms_per_step']:>11.1f} {render}{row['env_steps_per_cpu_s']:>11.0f} "
            f"{its:>14} {row['calls_per_step']:>6.1f} {row['rows_per_copy_step']:>9.1f} "
            f"{row['converged_fraction']:>9.3f} {row['out_of_range']:>12} {row['diverged']:>8} "
            f"{_gap(row['observation_gap']):>8}{'*' if row['iterations_per_step'] == 0 else ' '} "
            f"{ratio['median']:.2f}x" + (f" ({ratio['min']:.2f}-{ratio['max']:.2f})" if spread else "")
        )
    out(
        f"obs gap: the largest difference of a setting's observations from {first}'s over the timed steps (the same "
        "resets and actions): what it changes in the results"
    )
    if any(row["iterations_per_step"] == 0 for row in rows):
        out(
            "* no solver iteration in any timed step: each step took the solver's start as it was (no solve; its "
            "speed is no speed-up)"
        )
    out(f"per-round CPU ratio vs {first} ({first}'s time over the setting's: > 1 is faster):")
    for row in rows[1:]:
        out(f"  {row['name']}: " + " ".join(f"{r:.2f}" for r in row["ratio"]["rounds"]))
    threads = rows[0]["env_args"].get("threads", args.threads)  # every setting's (check_same_threads)
    if threads != 1:
        count = threads or "the process's default number of"
        out(
            f"note: the settings ran on {count} torch threads: CPU time adds up every thread's, spin-waits too, so "
            "a ratio is the CPU a setting costs, not its wall-clock speed"
        )
    end = result["load_average_1min_end"]
    if end is not None:
        out(f"load at the end: {end:.2f}")
    return EXIT_OK


def cmd_bench_mujoco_cloth(args: argparse.Namespace) -> int:
    import math

    import redsim
    from redsim.bench import machine_info
    from redsim.benches import mujoco_cloth

    reason = mujoco_cloth.flex_cloth_unavailable()
    if reason is not None:
        raise CliError(reason)
    if not (math.isfinite(args.seconds) and args.seconds > 0 and math.isfinite(args.settle) and args.settle > 0):
        raise CliError(f"--seconds and --settle must be finite and > 0, got {args.seconds} and {args.settle}")
    sweep = mujoco_cloth.SWEEP_TIMESTEPS
    if args.timesteps is not None:
        integrator, colon, values = args.timesteps.partition(":")
        if not colon or not values.strip(" ,"):  # parse_list would name only the (empty) part after the colon
            raise CliError(f"--timesteps must be INTEGRATOR:DT,DT,..., e.g. discrete:0.02,0.01, got {args.timesteps!r}")
        try:
            sweep = {integrator: tuple(parse_list(values, "--timesteps", float))}
        except ValueError as err:
            raise CliError(f"--timesteps must be INTEGRATOR:DT,DT,..., got {args.timesteps!r}") from err
        steps_ok = all(math.isfinite(dt) and dt > 0 for dt in sweep[integrator])
        if integrator not in mujoco_cloth.SWEEP_TIMESTEPS or not steps_ok:
            raise CliError(
                f"--timesteps: integrator {' or '.join(mujoco_cloth.SWEEP_TIMESTEPS)} (the two that integrate flex "
                f"elasticity) and finite time steps > 0, got {args.timesteps!r}"
            )
    timesteps = [] if args.no_sweep else [dt for steps in sweep.values() for dt in steps]
    timesteps += [] if args.no_swing else [mujoco_cloth.SWING_REDSIM_DT, *(dt for _, dt in mujoco_cloth.SWING_RUNS)]
    try:  # up front: each run lasts the time printed, and the runs compared last the same time
        for dt in timesteps:
            mujoco_cloth.whole_steps(args.seconds, dt, "--seconds")
        if not args.no_sag:
            mujoco_cloth.whole_steps(args.settle, mujoco_cloth.CLOTH_TIMESTEP, "--settle")
    except ValueError as err:
        raise CliError(str(err)) from None
    machine = machine_info()
    scene = redsim.scenes.build(mujoco_cloth.CLOTH_SCENE)
    mesh = mujoco_cloth.sheet_mesh(scene)
    match = mujoco_cloth.matched_shell(scene)
    rows = [] if args.no_sweep else mujoco_cloth.timestep_sweep(scene, sweep, seconds=args.seconds, match=match)
    sag = None if args.no_sag else mujoco_cloth.rest_sag(scene, settle_s=args.settle, match=match)
    swing = None if args.no_swing else mujoco_cloth.swing_check(scene, seconds=args.seconds, match=match)
    result = {
        "machine": machine,
        "scene": mujoco_cloth.CLOTH_SCENE,
        "vertices": int(mesh.vertices.shape[0]),
        "triangles": int(mesh.triangles.shape[0]),
        "pinned": int(mesh.pinned.size),
        "free_mass_kg": mesh.free_mass,
        "match": dataclasses.asdict(match),
        "sweep": rows,
        "largest_stable": mujoco_cloth.largest_stable(rows) if rows else {},
        "anchor": {"integrator": mujoco_cloth.CLOTH_INTEGRATOR, "timestep": mujoco_cloth.CLOTH_TIMESTEP},
        "rest": sag,
        "swing": swing,
    }
    if args.json:
        json_out(result)
        return EXIT_OK
    out(_machine_line(machine, "cpu"))
    out(
        f"MuJoCo flex cloth of {mujoco_cloth.CLOTH_SCENE}: {result['vertices']} vertices ({result['pinned']} pinned), "
        f"{result['triangles']} triangles, moving mass {mesh.free_mass:.4f} kg, the scene's lumped masses and gravity"
    )
    out(
        f"shell: E t {match.stretch_stiffness:.4g} N/m and poisson {match.poisson:.3g} as the scene's membrane; "
        f"MuJoCo young {match.young:.4g} Pa, thickness {1e3 * match.thickness:.3f} mm, "
        f"D {match.bending_rigidity:.4g} J; "
        f"bending energy on a cylinder of curvature {mujoco_cloth.BEND_CURVATURE:g} 1/m: scene "
        f"{match.scene_bending_j:.5g} J, MuJoCo {match.mujoco_bending_j:.5g} J"
    )
    if rows:
        out(
            f"time-step sweep: {args.seconds:g} s from rest per scenario (hang: from the seed; drop: turned level "
            f"about the pinned edge); blew up: NaN, MuJoCo warning, edge strain > {mujoco_cloth.MAX_EDGE_STRAIN:g}, "
            f"or energy gain > {mujoco_cloth.ENERGY_GROWTH:g} m g L"
        )
        out(f"{'integrator':<11} {'dt [s]':>8} {'hang':>24} {'drop':>24} {'CPU ms/step':>12} {'sim s/CPU s':>12}")
        for integrator, steps in sweep.items():
            for dt in steps:
                cells = []
                mine = [r for r in rows if r["integrator"] == integrator and r["timestep"] == dt]
                for r in mine:
                    cells.append(
                        f"{r['reason']} at {r['at_s']:.2f} s" if r["blew_up"] else f"ok (strain {r['max_strain']:.2%})"
                    )
                cpu = sum(r["cpu_s_per_step"] for r in mine) / len(mine)
                out(
                    f"{integrator:<11} {dt:>8g} "
                    + " ".join(f"{c:>24}" for c in cells)
                    + f" {1e3 * cpu:>12.2f} {dt / cpu:>12.3g}"
                )
        stable = ", ".join(f"{k} {'none' if v is None else f'{v:g} s'}" for k, v in result["largest_stable"].items())
        out(f"largest stable dt: {stable}")
    anchor = f"anchor of `redsim bench envs`: {mujoco_cloth.CLOTH_INTEGRATOR} at dt {mujoco_cloth.CLOTH_TIMESTEP:g} s"
    if mujoco_cloth.CLOTH_INTEGRATOR not in result["largest_stable"]:
        out(f"{anchor} (the default sweep's largest stable time step; not swept in this run)")
    elif result["largest_stable"][mujoco_cloth.CLOTH_INTEGRATOR] == mujoco_cloth.CLOTH_TIMESTEP:
        out(f"{anchor} (the largest time step of this sweep at which it stayed stable)")
    else:
        found = result["largest_stable"][mujoco_cloth.CLOTH_INTEGRATOR]
        out(f"{anchor}; this sweep's largest stable time step under it: {'none' if found is None else f'{found:g} s'}")
    if sag is not None:
        out(
            f"rest under gravity, displacement from the seed [mm] (MuJoCo: {args.settle:g} s of "
            f"{mujoco_cloth.CLOTH_INTEGRATOR} steps, largest speed left {1e3 * sag['mujoco_speed_m_s']:.2g} mm/s; "
            f"redsim: full-space Newton rest, converged {sag['redsim_converged']})"
        )
        for name, h in sag["handles"].items():
            mj = ", ".join(f"{1e3 * v:.3f}" for v in h["mujoco_m"])
            rs = ", ".join(f"{1e3 * v:.3f}" for v in h["redsim_m"])
            out(f"  {name:<14} MuJoCo ({mj})  redsim ({rs})")
        out(f"  largest vertex distance between the two rests: {1e3 * sag['max_vertex_gap_m']:.3f} mm")
    if swing is not None:
        out(
            f"swing: the sheet dropped from level, {swing['seconds']:g} s; path of {swing['handle']}: its passes "
            "through the vertical below the pinned edge, lowest point, swing out on the far side, RMS distance from "
            "redsim's path"
        )
        for run in swing["runs"]:
            passes = ", ".join(f"{t:.3f}" for t in run["passes_s"]) or "none"
            unconverged, warnings = run.get("unconverged_steps"), run.get("warnings")
            failed = [f"{unconverged} of {run['steps']} steps unconverged"] if unconverged else []
            failed += [f"{warnings} MuJoCo warnings"] if warnings else []
            out(
                f"  {run['name']:<44} passes [s] {passes:<20} lowest {1e3 * run['lowest_m']:6.1f} mm  far side "
                f"{1e3 * run['far_side_m']:6.1f} mm  RMS gap {1e3 * run['rms_gap_m']:5.1f} mm  CPU {run['cpu_s']:.1f} s"
                + "".join(f"  ({f})" for f in failed)
            )
    return EXIT_OK


def add_commands(sub: Any, bench: Any) -> None:
    """Add ``demo`` to the top-level subcommands ``sub`` and ``envs`` to the ``bench`` subcommands."""
    p = sub.add_parser(
        "demo",
        help="run an env with its shipped policy or scripted controller; print return and speed, write a GIF",
        description=(
            "One episode of ENV_ID (e.g. RedSim/Chain-v0) driven by the trained policy shipped for it "
            "(redsim/pretrained/policies) or, where none is shipped or with --scripted, the task's scripted "
            "controller. Writes OUT/NAME.gif (every other frame) and OUT/NAME.png (first and last frame), NAME "
            "the task in lower case with its version past v0, _scripted for the controller and _seedS for a seed "
            "S other than 0 (RedSim/Chain-v0: chain, chain_scripted, chain_seed3), so other demos are not "
            "overwritten (a --steps run replaces the full episode's demo of the same name)."
        ),
    )
    p.add_argument("env_id", metavar="ENV_ID", help="a RedSim env id (the prefix redsim: as in gym.make is fine)")
    add_out_folder(p, "output folder (default out)", default="out")
    p.add_argument("--seed", type=non_negative_seed, default=0, help="reset seed (default 0)")
    p.add_argument("--steps", type=int, help="episode length (default: the env's max_episode_steps)")
    p.add_argument("--scripted", action="store_true", help="use the scripted controller even where a policy is shipped")
    finish_command(p, cmd_demo, "print one JSON summary", default_threads=1)

    p = bench.add_parser(
        "envs",
        help="env steps/s single and vectorized, against the full-space step",
        description=(
            "For each env id: n, d, action and observation sizes, env steps/s of the single env and of the native "
            "vector env per batch size, simulated seconds per wall second, and the same scene's float64 full-space "
            "implicit-Euler step; with mujoco installed, MuJoCo's 24-capsule chain, HalfCheetah-v5 and a flex cloth "
            "of the hanging sheet in the same run, and the cloth envs' best batch against that cloth. A part that "
            "raises reads failed and is named under the table; the others still run, and the command exits 1."
        ),
    )
    p.add_argument("--envs", metavar="A,B,...", help="comma-separated ids (default: all)")
    p.add_argument("--batches", default="16,64,256", help="vector env sizes (default 16,64,256)")
    p.add_argument("--steps", type=int, default=20, help="timed steps per configuration (default 20)")
    p.add_argument(
        "--rounds",
        type=int,
        default=1,
        help="time every id and anchor this many times in turn (ids reversed every other round) and report each "
        "rate's median over the rounds (default 1), and the env steps/s' lowest and highest round in a table of their "
        "own; the full-space step is timed in the first round only",
    )
    p.add_argument(
        "--budget",
        type=seconds,
        default=20.0,
        help="seconds of timing per configuration and of the flex cloth (default 20)",
    )
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--no-full-space", action="store_true", help="skip the full-space step")
    p.add_argument(
        "--shards",
        type=int,
        default=1,
        help="worker processes per vector env (default 1: the native vector env; P > 1: redsim.envs.sharded, "
        "each worker a block of the copies, its env on --threads; its solver calls are not "
        "counted)",
    )
    p.add_argument(
        "--shard-timeout",
        type=seconds,
        default=None,
        metavar="SECONDS",
        help="with --shards P > 1: seconds each vector env call waits for its workers (default: for ever); a worker "
        "that hangs past it fails that batch's part (the workers stopped, the env closed) and the run goes on",
    )
    p.add_argument(
        "--anchor-steps",
        type=int,
        default=2000,
        help="timed steps of each MuJoCo anchor (default 2000; the flex cloth stops after --budget seconds)",
    )
    p.add_argument(
        "--env-arg",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="keyword argument of every env, VALUE a JSON literal (e.g. cubature=true, "
        "stepper_options='{\"tol\": 1e-5}'); repeatable",
    )
    finish_command(p, cmd_bench_envs, "print one JSON document", default_threads=1)

    p = bench.add_parser(
        "env-ab",
        help="interleaved A/B of env settings by CPU time: speed and solver work per setting",
        description=(
            "One native vector env of ENV_ID per --setting, in one process, reset with the same seed and fed the "
            "same uniform random actions; after --warmup untimed steps, --rounds rounds of --steps-per-round vector "
            "steps of every setting (order reversed every other round), each round timed by this process's CPU "
            "time. Prints per setting the median CPU ms per vector step, env steps per CPU second, the solver's "
            "iterations per copy (of the slowest copy), value-and-gradient calls per step and rows per copy, the "
            "converged fraction and the out_of_range / diverged copy-steps; then each setting's per-round CPU "
            "ratio against the first setting."
        ),
    )
    p.add_argument("env_id", metavar="ENV_ID", help="a RedSim env id (the prefix redsim: as in gym.make is fine)")
    p.add_argument(
        "--setting",
        action="append",
        default=[],
        metavar="NAME[:KEY=VALUE]",
        help="a setting to compare: a name and one keyword argument of the env, VALUE a JSON literal as in "
        "`bench envs --env-arg` (e.g. old:stepper_options='{\"warm_refresh\": true}'); a bare NAME is the env's "
        "defaults; repeat NAME to add arguments to it; at least two settings, the first the ratios' reference",
    )
    p.add_argument("--num-envs", type=int, default=64, help="copies per vector env (default 64)")
    p.add_argument("--rounds", type=int, default=4, help="timed rounds (default 4)")
    p.add_argument("--steps-per-round", type=int, default=10, help="vector steps per setting and round (default 10)")
    p.add_argument("--warmup", type=int, default=3, help="untimed vector steps of each setting first (default 3)")
    p.add_argument("--seed", type=non_negative_seed, default=0, help="seed of the resets and the actions (default 0)")
    p.add_argument(
        "--render",
        type=int,
        metavar="PX",
        help="also render every copy after each timed step, rgb_array frames of PX x PX (e.g. 84, a pixel agent's; "
        "the CPU times include the renders, and their share is printed)",
    )
    finish_command(p, cmd_bench_env_ab, "print one JSON document", default_threads=1)

    p = bench.add_parser(
        "mujoco-cloth",
        help="the flex cloth anchor of `bench envs`: its match to the hanging sheet, time-step sweep and rest",
        description=(
            "MuJoCo's flex cloth of the hanging_sheet scene (needs mujoco): the shell parameters matched to the "
            "scene's membrane and bending, a time-step sweep of 'discrete' and 'Euler' (which steps stay stable "
            "hanging and dropped), the rest under gravity against redsim's full-space rest and the dropped sheet's "
            "swing against redsim's full-space implicit Euler."
        ),
    )
    p.add_argument(
        "--seconds",
        type=float,
        default=2.0,
        help="simulated seconds per sweep and swing run, a whole multiple of each time step run (default 2)",
    )
    p.add_argument("--timesteps", metavar="INTEGRATOR:DT,...", help="sweep only these (e.g. discrete:0.02,0.01)")
    p.add_argument(
        "--settle",
        type=float,
        default=20.0,
        help="simulated seconds MuJoCo settles for, whole 0.05 s steps (default 20)",
    )
    p.add_argument("--no-sweep", action="store_true", help="skip the time-step sweep")
    p.add_argument("--no-sag", action="store_true", help="skip the rest comparison")
    p.add_argument("--no-swing", action="store_true", help="skip the swing comparison (redsim's full space: minutes)")
    finish_command(p, cmd_bench_mujoco_cloth, "print one JSON document", default_threads=1)


__all__ = ["add_commands"]
