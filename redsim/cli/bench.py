"""``redsim bench energy | subspace | fit | step | accuracy | scaling | stability``: benchmarks; each prints the machine
it ran on (``cubature``, ``envs``, ``mujoco-cloth`` and ``env-ab`` are added by their own modules)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import redsim
from redsim.cli import cubature
from redsim.cli.common import (
    EXIT_FAILED_STEP,
    EXIT_INTERRUPTED,
    EXIT_NAN,
    EXIT_OK,
    EXIT_SCENE_FAILED,
    CliError,
    add_bench_scene_args,
    add_out_folder,
    bench_scenes,
    build_scene,
    catalog_names,
    check_device_option,
    check_scene_name,
    error,
    finish_command,
    json_out,
    load_checkpoint,
    non_negative_seed,
    note,
    out,
    parse_env_id,
    parse_ints,
    parse_list,
    seconds,
    shown_path,
    warn,
)
from redsim.cli.common import (
    machine_line as _machine_line,
)
from redsim.cli.scene_runs import run_scenes


def cmd_bench_subspace(args: argparse.Namespace) -> int:
    from redsim import pretrained
    from redsim.bench import compare_subspaces, machine_info
    from redsim.trainers import FitConfig
    from redsim.trainers.cache import fitted_subspace
    from redsim.trainers.fit import low_stretch_warning, quiet_low_stretch
    from redsim.trainers.presets import preset

    scenes = bench_scenes(args, redsim.scenes.names("table1"))
    if not (math.isfinite(args.load_size) and args.load_size > 0.0):
        raise CliError(f"--load-size must be finite and > 0, got {args.load_size}")
    if args.samples < 1 or args.loads < 0:
        raise CliError(f"--samples must be >= 1 and --loads >= 0, got {args.samples} and {args.loads}")
    folder = _checkpoint_folder(args)
    planned = []
    for name, make in scenes:  # every scene's fit settings refused, if they are, before any fit runs
        scene = make()
        overrides = {} if args.steps is None else {"steps": args.steps}
        try:
            config = FitConfig(**{**preset(name), **overrides})
        except ValueError as err:  # FitConfigError names the field: --steps is the one this command sets
            raise CliError(f"--{err}" if str(err).startswith("steps ") else str(err)) from err
        if config.latent_dim > scene.free_dof_count:  # the modal baselines take d of the scene's n modes
            raise CliError(
                f"{name}: its fit has d = {config.latent_dim} latents (its preset's, or FitConfig's default) and the "
                f"scene n = {scene.free_dof_count} free DOFs; the modal baselines need d <= n: bench a larger scene"
            )
        planned.append((name, (scene, config)))
    rows: list[dict[str, Any]] = []
    if not args.json:
        out(_machine_line(machine_info(), "cpu"))  # the metrics are deterministic; the fits' times are not

    def run(name: str, item: tuple[Any, Any]) -> None:
        scene, config = item
        stem = folder / (name if args.steps is None else f"{name}_s{args.steps}")
        shipped = [pretrained.path(name)] if args.steps is None and name in pretrained.names() else []
        with quiet_low_stretch():  # said below in one line, as redsim fit says it
            neural, source = fitted_subspace(
                scene, config, stem, seed=args.seed, also=shipped, refit=args.refit, progress=not args.json, warn=warn
            )
        fit = neural.metadata["fit"]
        stretch = neural.metadata.get("final", {}).get("stretch", 1.0)  # a map saved without it: nothing to say
        if (message := low_stretch_warning(stretch, fit["sigma"])) is not None:
            warn(f"{source}: {message}")
        if not args.json:  # the full-space static responses can take minutes (a mechanism has none to find)
            note(f"{name}: energy, stretch and the static responses to {args.loads} load(s) of each subspace")
        metrics = compare_subspaces(
            scene,
            neural,
            sigma=fit["sigma"],
            loads_count=args.loads,
            response_fraction=args.load_size,
            samples=args.samples,
            seed=args.seed,
        )
        row = {
            "scene": name,
            "n": scene.free_dof_count,
            "d": int(neural.latent_dim),
            "steps": fit["steps"],
            "sigma": fit["sigma"],
            "lam": fit["lam"],
            "fit_seconds": neural.metadata.get("fit_seconds"),
            "checkpoint": str(source),
            "methods": metrics,
        }
        rows.append(row)
        if not args.json:
            out(_subspace_row(row))

    runs = run_scenes("bench subspace", planned, run, text=not args.json)
    if args.json:
        json_out({"machine": machine_info(), "rows": rows, **runs.fields()})
    return runs.status()


def _metric(result: dict[str, Any], *path: str) -> float | None:
    """The number at ``path`` in a method's result; None where it does not apply (absent, or undefined)."""
    value: Any = result
    for key in path:
        if not isinstance(value, dict) or key not in value:
            return None
        value = value[key]
    return float(value) if isinstance(value, (int, float)) else None


def _cell(value: float | None, width: int) -> str:
    """``value`` in ``width`` characters (3 significant digits); – where it does not apply."""
    return f"{'–':>{width}}" if value is None else f"{value:{width}.3g}"


def _subspace_row(row: dict[str, Any]) -> str:
    fit = row["fit_seconds"]
    took = "fit time not recorded" if fit is None else f"fit {fit:.{0 if fit >= 10 else 2}f} s"
    lines = [
        f"{row['scene']}  n={row['n']}  d={row['d']}  sigma={row['sigma']:g}  lam={row['lam']:g}  "
        f"steps={row['steps']}  {took}  ({shown_path(row['checkpoint'])})"
    ]
    for method, result in row["methods"].items():
        line = (
            f"  {method:18s} rel. energy {_cell(_metric(result, 'energy', 'relative_energy'), 8)}  "
            f"excess {_cell(_metric(result, 'energy', 'excess_energy'), 9)} J  "
            f"stretch {_cell(_metric(result, 'stretch', 'mean'), 8)}  "
            f"load error {_cell(_metric(result, 'load_response', 'mean_error'), 7)}  "
            f"response {_cell(_metric(result, 'load_response', 'mean_response_error'), 7)}  "
            f"strain {_cell(_metric(result, 'nonrigid_strain', 'mean'), 8)}"
        )
        if "reach" in result:
            line += "  reach " + "/".join(f"{e:.3g}" for e in result["reach"]["errors"])
        if "loop" in result:
            line += f"  crank turn {result['loop']['turn_degrees']:.0f} deg (winding {result['loop']['winding']})"
        lines.append(line)
    references = next((r["load_response"] for r in row["methods"].values() if "load_response" in r), None)
    if references is not None:  # the full-space equilibria every method's load error is measured against
        loaded = references["full_converged"]
        if not all(loaded):
            lines.append(
                f"  * {loaded.count(False)} of {len(loaded)} loaded full-space equilibria stopped unconverged "
                "(no static equilibrium found): the load errors leave them out"
            )
        if not references["rest_converged"]:
            lines.append(
                "  * the unloaded full-space equilibrium stopped unconverged: the load errors measure around it"
            )
    return "\n".join(lines)


def cmd_bench_energy(args: argparse.Namespace) -> int:
    from redsim.bench import bench_energy, machine_info

    scenes = bench_scenes(args, [n for n in catalog_names() if n not in redsim.scenes.names("toy")])
    if args.repeats < 1:
        raise CliError(f"--repeats must be >= 1, got {args.repeats}")
    try:
        batches = parse_list(args.batches, "--batches", int)
    except ValueError as err:
        raise CliError(f"--batches must be comma-separated integers, got {args.batches!r}") from err
    if min(batches) < 1:
        raise CliError(f"--batches must be >= 1, got {args.batches!r}")
    if not (math.isfinite(args.perturbation) and args.perturbation > 0):
        raise CliError(f"--perturbation must be a finite number > 0, got {args.perturbation}")
    from redsim.devices import DTYPES

    dtypes = parse_list(args.dtypes, "--dtypes")
    unknown = [d for d in dtypes if d not in DTYPES]
    if unknown:
        raise CliError(f"unknown dtype(s) {unknown}; valid: {', '.join(DTYPES)}")
    check_device_option(args.device)

    machine = machine_info()
    columns = [(d, b) for d in dtypes for b in batches]
    if not args.json:
        out(
            f"energy + gradient wall time, median over up to {args.repeats} repeats (ms); "
            f"states: seed + {args.perturbation:g} x N(0, 1) x max(1, |seed|)"
        )
        out(_machine_line(machine, args.device))
        header = f"{'scene':<24} {'n':>8} " + " ".join(f"{f'f{d[5:]} B={b}':>12}" for d, b in columns)
        out(header + "  repeats")
        out("-" * (len(header) + 9))
    results: list[dict[str, Any]] = []

    def run(name: str, make: Any) -> None:
        base = make()
        row = [
            bench_energy(
                base.to(args.device, DTYPES[dtype]),
                batch,
                args.repeats,
                time_budget=args.budget,
                perturbation=args.perturbation,
            )
            for dtype, batch in columns
        ]
        results.extend(row)
        if not args.json:
            cells = " ".join(f"{1e3 * r['median_s']:>12.3g}" for r in row)
            out(f"{name:<24} {base.free_dof_count:>8} {cells}  {min(r['repeats'] for r in row)}")

    runs = run_scenes("bench energy", scenes, run, text=not args.json)
    if args.json:
        json_out(
            {
                "machine": machine,
                "device": args.device,
                "repeats": args.repeats,
                "perturbation": args.perturbation,
                "results": results,
                **runs.fields(),
            }
        )
    return runs.status()


def cmd_bench_step(args: argparse.Namespace) -> int:
    from redsim import pretrained
    from redsim.bench import machine_info
    from redsim.runtime.baseline import check_source
    from redsim.runtime.bench import STEP_SCENES, bench_step, mujoco_rows, step_table

    names = list(STEP_SCENES) if args.scenes is None else parse_list(args.scenes, "--scenes")
    for name in names:
        check_scene_name(name, takes_files=False)
        if name not in pretrained.names():
            raise CliError(f"no shipped subspace for {name!r}; shipped: {', '.join(pretrained.names())}")
    try:
        batches = tuple(parse_list(args.batches, "--batches", int))
    except ValueError as err:
        raise CliError(f"--batches must be comma-separated integers, got {args.batches!r}") from err
    if min(batches) < 1 or args.steps < 1 or args.reference_steps < 1 or args.rounds < 1:
        raise CliError("--batches, --steps, --reference-steps and --rounds must be >= 1")
    from redsim.integrators import MIN_TIME_STEP

    if not (math.isfinite(args.dt) and args.dt >= MIN_TIME_STEP):
        raise CliError(f"--dt must be a finite number >= {MIN_TIME_STEP:g} [s], got {args.dt}")
    check_device_option(args.device)
    baseline = None
    if args.baseline is not None:
        if args.hessians is not None:
            raise CliError("--baseline times the reference path; --hessians compares solver models: use one")
        try:
            baseline = check_source(Path(args.baseline))
        except ValueError as err:
            raise CliError(f"--baseline: {err}") from err
    if args.hessians is not None:
        ignored = [
            flag
            for flag, given in (
                ("--reference-steps", args.reference_steps != STEP_REFERENCE_STEPS),
                ("--rounds", args.rounds != 1),
                ("--no-compile", args.no_compile),
                ("--dense", args.dense),
            )
            if given
        ]
        if ignored:
            raise CliError(
                "--hessians runs each Hessian model once, eager and row-selected, without the reference: "
                f"drop {', '.join(ignored)}"
            )
    machine = machine_info()
    if args.hessians is not None:
        return _bench_step_hessians(args, names, batches, machine)
    rows: list[dict[str, Any]] = []

    def run(name: str, _: None) -> None:
        scene = build_scene(name)
        rows.append(
            bench_step(
                scene,
                pretrained.load(name, scene),
                dt=args.dt,
                batches=batches,
                steps=args.steps,
                reference_steps=min(args.reference_steps, args.steps),
                compiled=not args.no_compile,
                device=args.device,
                seed=args.seed,
                rounds=args.rounds,
                dense=args.dense,
                baseline=baseline,
            )
        )
        if not args.json:
            out(f"{name}: done")

    runs = run_scenes("bench step", [(name, None) for name in names], run, text=not args.json)
    mujoco = [] if runs.interrupted else mujoco_rows()  # measured after the scenes: not after a Ctrl-C
    nonfinite, undefined, diverged = _step_failures(rows)
    failures = [*nonfinite, *diverged, *undefined]
    if args.json:
        doc = {"machine": machine, "dt": args.dt, "rows": rows, "mujoco": mujoco}
        json_out({**doc, **runs.fields(), "nonfinite": nonfinite, "diverged": diverged, "undefined": undefined})
    else:
        out(_machine_line(machine, args.device))
        for line in step_table(rows, mujoco, args.dt):
            out(line)
        for line in failures:
            out(f"failed: {line}")
    if failures:  # the table is printed; the command fails, for scripts and CI
        error("; ".join(failures))
    status = EXIT_NAN if nonfinite else EXIT_FAILED_STEP if diverged else EXIT_SCENE_FAILED if undefined else EXIT_OK
    return runs.status(status)


def _step_failures(rows: list[dict[str, Any]]) -> tuple[list[str], list[str], list[str]]:
    """What fails `bench step` in its finished ``rows``, one line each: a non-finite one-step or rollout error (exit
    3), an undefined one (None: the reference did not move, so its accuracy was not measured; exit 1), and the paths
    and batch sizes whose solves diverged (rejected steps; exit 4)."""
    nonfinite, undefined, diverged = [], [], []
    for row in rows:
        keys = [key for key in ("step_error", "trajectory_error") if key in row]
        for key in keys:
            if row[key] is not None and not math.isfinite(row[key]):
                nonfinite.append(f"{row['scene']}: {key.replace('_', ' ')} is {row[key]} (a non-finite state)")
        if idle := [key.replace("_", " ") for key in keys if row[key] is None]:
            undefined.append(
                f"{row['scene']}: the reference did not move (its motion is 0; loads too small to be felt at this "
                f"--dt?): {' and '.join(idle)} undefined"
            )
        for label in ("eager", "cold", "compiled", "dense", "dense-cmp"):
            for b, result in row.get(label, {}).items():
                if result.get("diverged_fraction", 0.0) > 0.0:
                    share = 100 * result["diverged_fraction"]
                    diverged.append(f"{row['scene']}: {label} B={b}: {share:.3g}% of the steps diverged (rejected)")
    return nonfinite, undefined, diverged


def _bench_step_hessians(
    args: argparse.Namespace, names: list[str], batches: tuple[int, ...], machine: dict[str, Any]
) -> int:
    from redsim import pretrained
    from redsim.runtime.bench import compare_hessians
    from redsim.runtime.solver import HESSIANS

    hessians = tuple(parse_list(args.hessians, "--hessians"))
    unknown = [h for h in hessians if h not in HESSIANS]
    if unknown:
        raise CliError(f"unknown Hessian model(s) {unknown}; valid: {', '.join(HESSIANS)}")
    rows = []
    if not args.json:
        out(_machine_line(machine, args.device))
        out("its/step: solver iterations per step (mean over copies and steps); conv%: the copy-steps that converged")
        out(
            "median ms: the median step's wall time; env-steps/s: B x steps / the steps' total wall time "
            "(`bench envs`: B / its median step)"
        )
        out(
            f"{'scene':<14} {'hessian':<13} {'B':>4} {'its/step':>9} {'median ms':>10} {'env-steps/s':>12} {'conv%':>6}"
        )
    for name in names:
        scene = build_scene(name)
        for batch in batches:
            for row in compare_hessians(
                scene,
                pretrained.load(name, scene),
                dt=args.dt,
                batch=batch,
                steps=args.steps,
                hessians=hessians,
                seed=args.seed,
                device=args.device,
            ):
                rows.append(row)
                if not args.json:
                    out(
                        f"{name:<14} {row['hessian']:<13} {batch:>4} {row['iterations_per_step']:>9.2f} "
                        f"{1e3 * row['median_step_s']:>10.1f} {row['env_steps_per_s']:>12.3g} "
                        f"{100 * row['converged_fraction']:>6.1f}"
                    )
    if args.json:
        json_out({"machine": machine, "dt": args.dt, "rows": rows})
    return EXIT_OK


def cmd_bench_fit(args: argparse.Namespace) -> int:
    from redsim.bench import bench_fit_variants, machine_info
    from redsim.trainers import FitConfig
    from redsim.trainers.presets import preset

    scenes = bench_scenes(args, redsim.scenes.names("bench-fit"))
    for flag in ("steps", "warmup", "rounds"):
        if getattr(args, flag) < 1:
            raise CliError(f"--{flag} must be >= 1, got {getattr(args, flag)}")
    if args.batch < 2:
        raise CliError(f"--batch must be >= 2, got {args.batch}")
    check_device_option(args.device)
    built = [(name, make()) for name, make in scenes]
    if not args.scenes and args.mesh is None:  # smallest first: the first compiled scene also pays the start-up
        built.sort(key=lambda item: item[1].free_dof_count)
    machine = machine_info()
    if not args.json:
        out(
            f"fit step wall time (ms), median of {args.steps} steps in {min(args.rounds, args.steps)} interleaved "
            f"rounds, after {args.warmup} warm-up steps each; batch {args.batch}, {FitConfig().dtype}, scene presets"
        )
        out(_machine_line(machine, args.device))
        width = max(14, *(len(name) for name, _scene in built))
        header = f"{'scene':<{width}} {'n':>6} {'eager':>8} {'fused':>8} {'x':>5} {'compiled':>9} {'x':>5}"
        header += f" {'compile s':>10}"
        out(header)
        out("-" * len(header))
    rows: list[dict[str, Any]] = []

    def run(name: str, scene: Any) -> None:
        config = FitConfig(**{**preset(name), "batch_size": args.batch, "device": args.device})
        row = bench_fit_variants(scene, config, steps=args.steps, warmup=args.warmup, rounds=args.rounds)
        rows.append({"scene": name, "n": scene.free_dof_count, "variants": row})
        if not args.json:
            eager, fused, compiled = (1e3 * row[v]["median_s"] for v in ("eager", "fused", "compiled_fused"))
            out(
                f"{name:<{width}} {scene.free_dof_count:>6} {eager:>8.3g} {fused:>8.3g} {eager / fused:>5.2f} "
                f"{compiled:>9.3g} {eager / compiled:>5.2f} {row['compiled_fused']['startup_s']:>10.1f}"
            )
        recompiled = row["compiled_fused"]["graphs_compiled_timed"]
        if recompiled:
            warn(f"{name}: {recompiled} graph(s) were compiled during the timed steps (recompilation)")

    runs = run_scenes("bench fit", built, run, text=not args.json)
    if args.json:
        json_out({"machine": machine, "device": args.device, "rows": rows, **runs.fields()})
    else:
        out(
            "x: speed-up over eager (plain Adam); compile s: first compiled step minus a warm one "
            "(the first compiled scene also pays torch.compile's start-up)"
        )
    return runs.status()


def cmd_bench_accuracy(args: argparse.Namespace) -> int:
    from redsim import pretrained
    from redsim.bench import machine_info
    from redsim.benches import accuracy
    from redsim.subspace import checkpoint_path

    checkpoint = args.scene not in accuracy.PLANS and (
        args.scene.endswith((".pt", ".json"))
        or Path(args.scene).is_file()
        or checkpoint_path(args.scene, ".pt").is_file()
    )
    if not checkpoint and args.scene not in accuracy.PLANS:
        raise CliError(
            f"bench accuracy runs on {', '.join(accuracy.PLANS)} or a checkpoint (STEM.pt); got {args.scene!r}"
        )
    if checkpoint and args.dims is not None:
        raise CliError("--dims fits maps of a catalog scene's preset: give a scene name, not a checkpoint")
    scenarios = tuple(parse_list(args.scenarios, "--scenarios"))
    full = tuple(parse_list(args.full, "--full")) if args.full != "none" else ()
    checks = (("--scenarios", scenarios, accuracy.SCENARIOS), ("--full", full, accuracy.FULL_VARIANTS))
    for flag, given, valid in checks:
        if unknown := [k for k in given if k not in valid]:
            extra = " (or none)" if flag == "--full" else ""
            raise CliError(f"{flag} must be from {', '.join(valid)}{extra}; got {', '.join(unknown)}")
    if args.steps < 10:
        raise CliError(f"--steps must be >= 10, got {args.steps}")
    _accuracy_unused(args, scenarios)
    if checkpoint:  # a user's map (a mesh scene's too): the scene its .json records, pushed as below
        scene, neural = load_checkpoint(args.scene)
        path = checkpoint_path(args.scene, ".pt")
    else:
        scene = redsim.scenes.build(args.scene)
        neural, path = pretrained.load(args.scene, scene), pretrained.path(args.scene)
    try:
        plan = accuracy.checkpoint_plan if checkpoint else accuracy.replanned
        load_plan = plan(scene, args.handle, args.max_force)
    except ValueError as err:
        raise CliError(str(err)) from err
    dims = _accuracy_dims(args, scene.free_dof_count)
    shipped_dim = int(neural.latent_dim)
    paths = {shipped_dim: path}
    maps = None if dims is None else _accuracy_maps(args, scene, neural, dims, paths)
    cubatures = _accuracy_cubatures(scene, {shipped_dim: neural, **(maps or {})}, paths)
    try:
        result = accuracy.bench_accuracy(
            scene,
            neural,
            steps=args.steps,
            scenarios=scenarios,
            seed=args.seed,
            full=full,
            study=not args.no_study,
            maps=maps,
            cubatures=cubatures,
            progress=None if args.json else note,
            load_plan=load_plan,
        )
    except accuracy.Interrupted as stop:  # Ctrl-C: the rows finished before it are printed, then exit 130
        result = stop.result
    for info in result["maps"]:
        shipped = info["d"] == shipped_dim and not checkpoint
        info["source"] = ("shipped " if shipped else "") + shown_path(paths[info["d"]])
    machine = machine_info()
    result["machine"] = machine
    line = _machine_line(machine, "cpu")
    paths = accuracy.write_outputs(result, Path(args.out), line) if args.out and result["rows"] else []
    if args.json:
        json_out(result)
    else:
        out(accuracy.report(result, line))
        if paths:
            out("wrote " + ", ".join(str(p) for p in paths))
    references, nonfinite = accuracy.failures(result)
    raised = accuracy.raised(result)
    status = EXIT_OK
    if references or nonfinite or raised:  # the rows are printed and written, and the command fails, for scripts/CI
        error("; ".join([*references, *nonfinite, *(f"{line} (raised)" for line in raised)]))
        status = EXIT_NAN if nonfinite else EXIT_FAILED_STEP if references else EXIT_SCENE_FAILED
    if result["interrupted"]:
        warn("interrupted: the tables have the rows finished before it")
        return EXIT_INTERRUPTED
    return status


def _accuracy_unused(args: argparse.Namespace, scenarios: tuple[str, ...]) -> None:
    """Refuse the options of ``bench accuracy`` that no chosen mode uses (they would be ignored); set the defaults of
    ``--seed`` (0) and ``--checkpoints`` (subspaces), which are None on the command line so that a given one is seen."""
    unused = [
        f"{flag} ({why})"
        for flag, given, why in (
            ("--seed", args.seed is not None and "actions" not in scenarios, "it seeds the actions scenario"),
            ("--no-study", args.no_study and "push" not in scenarios, "the start study runs on the push scenario"),
            ("--checkpoints", args.checkpoints is not None and args.dims is None, "it keeps the --dims fits"),
        )
        if given
    ]
    if unused:
        raise CliError(f"no chosen mode uses {', '.join(unused)}: drop it, or add what uses it")
    args.seed = 0 if args.seed is None else args.seed
    args.checkpoints = "subspaces" if args.checkpoints is None else args.checkpoints


def _accuracy_dims(args: argparse.Namespace, n: int) -> tuple[int, ...] | None:
    """The checked ``--dims`` (None without it); ``--fit-steps`` needs it."""
    if args.dims is None:
        if args.fit_steps is not None:
            raise CliError("--fit-steps needs --dims (it sets the steps of the maps --dims fits)")
        return None
    try:
        dims = tuple(sorted({int(d) for d in parse_list(args.dims, "--dims")}))
    except ValueError as err:
        raise CliError(f"--dims must be comma-separated integers, got {args.dims!r}") from err
    if dims[0] < 1 or dims[-1] > n:
        raise CliError(f"--dims must be between 1 and the scene's n = {n}, got {args.dims!r}")
    if args.fit_steps is not None and args.fit_steps < 1:
        raise CliError(f"--fit-steps must be >= 1, got {args.fit_steps}")
    _checkpoint_folder(args)
    return dims


def _checkpoint_folder(args: argparse.Namespace) -> Path:
    """``--checkpoints``, where fits are kept (made when missing); a file there, or above it, is refused before any
    work."""
    folder = Path(args.checkpoints)
    above = next((p for p in (folder, *folder.absolute().parents) if p.exists()), None)
    if above is not None and not above.is_dir():
        raise CliError(f"--checkpoints {folder}: {above} is a file, not a folder")
    return folder


def _accuracy_maps(
    args: argparse.Namespace, scene: Any, shipped: Any, dims: tuple[int, ...], paths: dict[int, Path]
) -> dict[int, Any]:
    """The neural map of each d: the shipped one at its d, else DIR/SCENE_dD[_sN] (a preset fit if missing).

    Adds the checkpoint of each map it loads or fits to ``paths``.
    """
    from redsim.trainers import FitConfig
    from redsim.trainers.cache import fitted_subspace
    from redsim.trainers.presets import preset

    overrides = {} if args.fit_steps is None else {"steps": args.fit_steps}
    suffix = "" if args.fit_steps is None else f"_s{args.fit_steps}"
    maps = {}
    for dim in dims:
        if dim == int(shipped.latent_dim):
            maps[dim] = shipped
            continue
        config = FitConfig(**{**preset(scene.name), **overrides, "latent_dim": dim})
        stem = _checkpoint_folder(args) / f"{scene.name}_d{dim}{suffix}"
        if not args.json:
            note(f"neural map d={dim}: {stem}.pt, or a fit of the {scene.name} preset ({config.steps} steps)")
        maps[dim], source = fitted_subspace(scene, config, stem, progress=not args.json, warn=warn)
        paths[dim] = Path(source)
    return maps


def _accuracy_cubatures(scene: Any, maps: dict[int, Any], paths: dict[int, Path]) -> dict[int, Any]:
    """The cubature stored beside each map's checkpoint (``STEM.cubature.json``); one for another map is skipped."""
    from redsim.cubature import cubature_path, load_cubature
    from redsim.subspace import CheckpointError

    cubatures = {}
    for dim, subspace in maps.items():
        if not cubature_path(paths[dim]).is_file():
            continue
        try:
            cubatures[dim] = load_cubature(paths[dim], scene, subspace)
        except CheckpointError as err:
            warn(f"not using the cubature of d={dim}: {err}")
    return cubatures


def cmd_bench_scaling(args: argparse.Namespace) -> int:
    from redsim.bench import machine_info
    from redsim.benches import scaling
    from redsim.subspace import write_atomically

    try:
        sizes = tuple(parse_list(args.sizes, "--sizes", int))
    except ValueError as err:
        raise CliError(f"--sizes must be comma-separated integers, got {args.sizes!r}") from err
    counts = (min(sizes), args.fit_steps, args.fit_warmup, args.latent_steps, args.cubature_elements)
    if min(counts) < 1:
        raise CliError("--sizes, --fit-steps, --fit-warmup, --latent-steps and --cubature-elements must be >= 1")
    if args.batch < 0 or min(v for v in (args.full_max_n, args.batch_max_n, 0) if v is not None) < 0:
        raise CliError("--batch, --full-max-n and --batch-max-n must be >= 0")
    threads = args.threads or 1
    folder = Path(args.out) if args.out else None

    def write(partial: dict) -> None:
        if folder is None:
            return
        folder.mkdir(parents=True, exist_ok=True)
        line = _machine_line({**machine_info(), "torch_threads": threads}, "cpu")
        table = f"{line}\n\n{scaling.markdown_table(partial)}\n"  # rewritten after each size: whole, or as it was
        write_atomically(folder / "scaling.md", lambda tmp: tmp.write_text(table))
        scaling.scaling_png(partial, folder / "scaling.png", line)
        if not args.json:
            n = partial["rows"][-1]["n"]
            note(f"bench scaling: n = {n} done, wrote {folder}/scaling.md and {folder}/scaling.png")

    failed = None
    try:
        result = scaling.bench_scaling(
            sizes,
            threads=threads,
            on_row=write,
            fit_steps=args.fit_steps,
            warmup=args.fit_warmup,
            latent_steps=args.latent_steps,
            full_max_n=0 if args.no_full else args.full_max_n,
            cubature_elements=args.cubature_elements,
            batch=args.batch,
            batch_max_n=args.batch_max_n,
            dtype=args.dtype,
        )
    except scaling.SizeFailed as err:  # the sizes measured before it are printed, then the error
        result, failed = err.result, str(err)
    machine = machine_info()
    result["machine"] = machine
    line = _machine_line({**machine, "torch_threads": threads}, "cpu")
    if args.json:
        json_out({**result, "failed": failed})
    elif result["rows"]:
        out(
            "bench scaling: cantilever beam (cells_x = 5k, cells_yz = k), 5 x 128 MLP (f(0) at rest), each size in its "
            f"own process; latent E+grad and steps in {args.dtype}"
        )
        out(line)
        out(scaling.markdown_table(result))
    if failed is not None:
        error(f"bench scaling: {failed}; the table has the sizes before it")
        return EXIT_SCENE_FAILED
    return EXIT_OK


def cmd_bench_stability(args: argparse.Namespace) -> int:
    from redsim.bench import machine_info
    from redsim.benches import damping as damping_bench
    from redsim.benches import stability

    extra = ("fuzz", "mujoco", "damping")
    regimes = list(stability.REGIMES) if args.regimes is None else parse_list(args.regimes, "--regimes")
    unknown = [r for r in regimes if r not in stability.REGIMES and r not in extra]
    if unknown:
        raise CliError(f"unknown regime(s) {unknown}; valid: {', '.join([*stability.REGIMES, *extra])}")
    if args.regimes is None:
        regimes += ["fuzz", "mujoco"]
    _regime_options(args, regimes)
    env_ids = list(redsim.envs.ids()) if args.envs is None else parse_list(args.envs, "--envs", parse_env_id)
    for flag in ("steps", "long_steps", "chain_steps", "chain_full_steps"):  # None: no chosen regime uses it
        if getattr(args, flag) is not None and getattr(args, flag) < 1:
            raise CliError(f"--{flag.replace('_', '-')} must be >= 1, got {getattr(args, flag)}")
    if args.copies is not None and args.copies < 1:
        raise CliError(f"--copies must be >= 1, got {args.copies}")
    damping_options = _damping_options(args, regimes)
    progress = None if args.json else note
    machine = machine_info()
    rows: list[dict[str, Any]] = []
    chain = None
    damping = None

    def run(name: str, _: None) -> None:  # one regime; its rows are kept as they finish (a Ctrl-C keeps those)
        nonlocal chain, damping
        if name in stability.REGIMES:
            if progress:
                progress(f"regime {name}")
            stability.REGIMES[name](args.long_steps, args.budget, rows)  # appends each row as it finishes
        elif name == "fuzz":
            for row in stability.fuzz_envs(
                env_ids, args.steps, seed=args.seed, copies=args.copies, seconds=args.budget, progress=progress
            ):
                rows.append(row)
        elif name == "mujoco":
            if progress:
                progress("chain scenarios: MuJoCo and redsim")
            mujoco = stability.mujoco_chain_cases(args.chain_steps)
            broken = None if mujoco is None else sorted({r["scenario"] for r in mujoco if r["blew_up"]})
            redsim_rows = stability.redsim_chain_cases(
                args.chain_steps, full_steps=args.chain_full_steps, scenarios=broken
            )
            chain = {
                "dt": 0.01,
                "steps": args.chain_steps,
                "full_steps": args.chain_full_steps,
                "mujoco": mujoco,
                "redsim": redsim_rows,
            }
        else:
            try:
                damping = damping_bench.bench_damping(**damping_options, progress=progress)
            except damping_bench.Interrupted as stop:  # its rows finished before the Ctrl-C are printed
                damping = stop.result
                raise

    order = [r for r in regimes if r in stability.REGIMES] + ["fuzz"] * bool("fuzz" in regimes and env_ids)
    order += [r for r in ("mujoco", "damping") if r in regimes]
    runs = run_scenes("bench stability", [(r, None) for r in order], run, text=not args.json, unit="regime")
    result = {
        "machine": machine,
        "long_steps": args.long_steps,
        "fuzz_steps": args.steps,
        "budget_s": args.budget,
        "rows": rows,
        "chain": chain,
        "damping": damping,
        **runs.fields(),
    }
    if args.json:
        json_out(result)
    else:
        out(_machine_line(machine, "cpu"))
        lines = stability.report(result)  # none for the damping regime alone
        if damping is not None:
            lines += ([""] if lines else []) + damping_bench.report(damping)
        for line in lines:
            out(line)
    totals = stability.row_totals([*rows, *(chain["redsim"] if chain else [])])  # redsim's chains, not MuJoCo's
    totals["nan"] += sum(r["nan"] for r in damping["rows"]) if damping else 0  # redsim's released runs, not MuJoCo's
    blown = [f"{r['scenario']} ({r['space']})" for r in (chain["redsim"] if chain else []) if r["blew_up"]]
    gained = damping_bench.gains(damping) if damping else []  # redsim's released runs that gained, not MuJoCo's
    limit = 1.0 + damping_bench.GAIN_TOL
    status = EXIT_OK
    if totals["nan"] or totals["unreported"] or blown or gained:  # the checks that must be 0 fail the command, for CI
        error(
            f"{totals['nan']} non-finite and {totals['unreported']} unreported energy gains (both must be 0)"
            + (f"; redsim's chain blew up in {', '.join(blown)}" if blown else "")
            + (
                f"; released unforced runs gained free energy (damping: largest > {limit:g}): {', '.join(gained)}"
                if gained
                else ""
            )
        )
        status = EXIT_NAN if totals["nan"] else EXIT_FAILED_STEP
    return runs.status(status)  # interrupted: 130 even after a failure above (its error is printed)


STEP_REFERENCE_STEPS = 10  # bench step's default --reference-steps
STABILITY_OPTIONS = {
    "steps": (("fuzz",), 10_000),
    "envs": (("fuzz",), None),
    "copies": (("fuzz",), None),
    "seed": (("fuzz",), 0),
    "budget": (("fuzz", "action_bounds"), None),
    "long_steps": (("long runs",), 2000),
    "chain_steps": (("mujoco",), 300),
    "chain_full_steps": (("mujoco",), 50),
}
"""bench stability's options that only some regimes use ("long runs": any of ``stability.REGIMES``; ``--budget`` caps
only action_bounds' runs among them) and their defaults; each is None unless given, so that one given without a regime
that uses it is refused, and stays None (null in the JSON) where no chosen regime uses it."""


def _regime_options(args: argparse.Namespace, regimes: list[str]) -> None:
    """Refuse the options (:data:`STABILITY_OPTIONS`) that no chosen regime uses, then fill in the defaults of those
    that one does."""
    from redsim.benches import stability

    chosen = {*regimes, *(["long runs"] if any(r in stability.REGIMES for r in regimes) else [])}
    unused = [
        f"--{o.replace('_', '-')}"
        for o, (users, _) in STABILITY_OPTIONS.items()
        if getattr(args, o) is not None and not chosen.intersection(users)
    ]
    if unused:
        raise CliError(
            f"{', '.join(unused)} not used by --regimes {','.join(regimes)}: --steps, --envs, --copies and --seed are "
            "the fuzz's, --long-steps the scene regimes' (stiff, ...), --budget the fuzz's and action_bounds', "
            "--chain-steps and --chain-full-steps mujoco's"
        )
    for option, (users, default) in STABILITY_OPTIONS.items():
        if getattr(args, option) is None and chosen.intersection(users):
            setattr(args, option, default)


DAMPING_OPTIONS = ("damping_scenes", "damping_seconds", "damping_divisions", "damping_full")
"""The ``--damping-*`` options (argparse names): None unless given, so that one given without the regime is refused."""


def _damping_options(args: argparse.Namespace, regimes: list[str]) -> dict[str, Any] | None:
    """The checked ``--damping-*`` options as keyword arguments of :func:`redsim.benches.damping.bench_damping`;
    None without the damping regime (a ``--damping-*`` option given then is a CLI error)."""
    from redsim import pretrained
    from redsim.benches import damping, stability

    if "damping" not in regimes:
        given = [f"--{o.replace('_', '-')}" for o in DAMPING_OPTIONS if getattr(args, o) is not None]
        if given:
            raise CliError(f"{', '.join(given)} can only be given with --regimes damping (add damping to --regimes)")
        return None
    names = list(damping.SCENES) if args.damping_scenes is None else parse_list(args.damping_scenes, "--damping-scenes")
    valid = [n for n in stability.LOADS if n in pretrained.names()]
    bad = [n for n in names if n not in valid]
    if bad:
        raise CliError(f"--damping-scenes: unknown scene(s) {bad}; valid: {', '.join(valid)}")
    divisions = list(damping.DIVISIONS)
    if args.damping_divisions is not None:
        divisions = parse_ints(args.damping_divisions, "--damping-divisions")
    full = list(damping.DIVISIONS)
    if args.damping_full is not None:
        full = [] if args.damping_full == "none" else parse_ints(args.damping_full, "--damping-full")
    seconds = damping.SECONDS if args.damping_seconds is None else args.damping_seconds
    try:
        damping.check_seconds(seconds, [*divisions, *full], "--damping-seconds")
    except ValueError as err:
        raise CliError(str(err)) from None
    return {"names": names, "seconds": seconds, "divisions": divisions, "full_divisions": full}


def _add_bench_fit_arguments(p: Any) -> None:
    """The options of ``redsim bench fit`` (added on first use: :meth:`redsim.cli.common.Parser.add_later`)."""
    add_bench_scene_args(p, f"{','.join(redsim.scenes.names('bench-fit'))}, smallest first")
    p.add_argument("--steps", type=int, default=20, help="timed steps per variant, over all rounds (default 20)")
    p.add_argument("--warmup", type=int, default=3, help="untimed steps per round, the compile included (default 3)")
    p.add_argument("--rounds", type=int, default=2, help="interleaved rounds of all variants (default 2)")
    p.add_argument("--batch", type=int, default=32, help="latent samples per step (default 32)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    finish_command(p, cmd_bench_fit, "print one JSON document on stdout", default_threads=1)


def add_commands(sub: Any) -> Any:
    """Add ``bench`` and its subcommands to the subcommands ``sub``; returns the ``bench`` subcommands."""
    p = sub.add_parser("bench", help="benchmarks", description="Benchmarks; each prints the machine it ran on.")
    bench = p.add_subparsers(dest="bench_command", metavar="BENCH", required=True)
    p = bench.add_parser(
        "energy",
        help="time energy + gradient per scene",
        description=(
            "Median wall time of scene.energy plus its gradient (backward) on random perturbations of the "
            "seed, per scene, dtype and batch size, after warm-up."
        ),
    )
    add_bench_scene_args(p, "all non-toy scenes")
    p.add_argument("--repeats", type=int, default=20, help="timed calls per measurement (default 20)")
    p.add_argument("--batches", default="1,32", metavar="B1,B2", help="batch sizes (default 1,32)")
    p.add_argument("--dtypes", default="float64,float32", metavar="D1,D2", help="float64 and/or float32 (default both)")
    p.add_argument(
        "--budget",
        type=seconds,
        default=2.0,
        metavar="SECONDS",
        help="time per measurement; slow scenes get fewer repeats, at least 3 (default 2)",
    )
    p.add_argument(
        "--perturbation",
        type=float,
        default=1e-3,
        help="relative size of the states' random perturbation of the seed (default 1e-3; at 3e-3 the chain's "
        "contact points are near their neighbours as often as in Chain-v0's states, ~3%%, at 1e-3 0.1%%)",
    )
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    finish_command(p, cmd_bench_energy, "print one JSON document on stdout")

    p = bench.add_parser(
        "subspace",
        help="neural subspace vs linear modes vs modal derivatives",
        description=(
            "For each scene, take a neural subspace: DIR/SCENE.pt if it is the preset's fit, else the one shipped "
            "with redsim (environment scenes), else fit one with the scene's preset into DIR/SCENE; with --steps N, "
            "DIR/SCENE_sN.pt or a fit of N steps. A file there that is another fit (other options, extended by "
            "--resume, another scene of the same name) is kept: the fit goes to DIR/SCENE[_sN]_KEY.pt beside it "
            "(KEY: 8 hex digits of a hash of the scene and the fit) and is reused from there. Build linear modes and "
            "modal derivatives of the same d and sigma, and print for each the energy of samples relative to the "
            "seed's (0: rest, 1: seed) and in J above the rest state, the metric stretch, the load-response error, "
            "(FEM) the non-rigid strain and (bistable_bar) how close the subspace comes to each buckled state."
        ),
    )
    add_bench_scene_args(p, "the eleven of Table 1")
    p.add_argument("--steps", type=int, help="fit (or reuse) N-step subspaces instead (default: the presets')")
    p.add_argument("--checkpoints", default="subspaces", metavar="DIR", help="where fits are kept (default subspaces)")
    p.add_argument(
        "--refit",
        action="store_true",
        help="fit even if a checkpoint qualifies (shipped ones included; never over another fit)",
    )
    p.add_argument("--loads", type=int, default=8, help="loads of the load-response error (default 8)")
    p.add_argument(
        "--load-size",
        type=float,
        default=0.1,
        help="size of each load: its linear response along the handle's softest direction, as a fraction of the "
        "scene size (default 0.1; larger probes the nonlinear range)",
    )
    p.add_argument("--samples", type=int, default=256, help="latent samples per statistic (default 256)")
    p.add_argument("--seed", type=non_negative_seed, default=0, help="seed of fits, samples and loads (default 0)")
    finish_command(p, cmd_bench_subspace, "print one JSON document")

    p = bench.add_parser(
        "fit",
        help="time fitting steps: eager vs fused Adam vs torch.compile",
        description=(
            "For each scene, with its preset: the median wall time of a fitting step (latent sample, loss, "
            "backward, Adam step) of the real fit loop, for eager + plain Adam, eager + fused Adam and compiled "
            "+ fused Adam, side by side in one process (interleaved rounds, so that other load on the machine hits "
            "all three alike), and the one-off compile time."
        ),
    )
    p.add_later(_add_bench_fit_arguments)  # its help names the scenes, whose catalog imports torch

    p = bench.add_parser(
        "step",
        help="env-steps/s of the batched latent stepper vs today's reference path",
        description=(
            "For each scene with a shipped subspace: env-steps/s (B x steps / their total wall time; `bench envs` "
            "takes B / its median step) of ImplicitEuler(LatentSpace) (one state at a time), "
            "the batched LatentStepper eager and compiled at each batch size B, on the same seeded load sequences "
            "(changing every 5 steps, inside the subspace's range), iterations per step, converged fraction, the "
            "full-space step at B = 1, and with mujoco installed a MuJoCo chain of 24 capsules for scale."
        ),
    )
    p.add_argument(
        "--scenes",
        metavar="A,B,...",
        help="comma-separated (default: mini_chain,chain,klann,bistable_bar,hanging_sheet,cloth_ball)",
    )
    p.add_argument("--batches", default="1,16,64,256", metavar="B1,B2", help="batch sizes (default 1,16,64,256)")
    p.add_argument("--steps", type=int, default=20, help="timed steps per batch size (default 20)")
    p.add_argument(
        "--reference-steps",
        type=int,
        default=STEP_REFERENCE_STEPS,
        help=f"steps of the reference path (default {STEP_REFERENCE_STEPS})",
    )
    p.add_argument("--dt", type=float, default=0.02, help="time step [s] (default 0.02)")
    p.add_argument("--no-compile", action="store_true", help="skip the torch.compile variant")
    p.add_argument(
        "--dense",
        action="store_true",
        help="also run the solver's dense masked iteration (dense, and compiled: dense-cmp) next to the "
        "row-selected one (eager, cold, compiled)",
    )
    p.add_argument(
        "--hessians",
        metavar="H1,H2",
        help="instead: compare the solver's Hessian models (of exact,gauss_newton,bfgs,lagged,lagged_fd; lagged_fd "
        "is the default) on the same loads",
    )
    p.add_argument("--device", default="cpu", help="torch device of the stepper (default cpu)")
    p.add_argument("--seed", type=non_negative_seed, default=0, help="seed of the load sequences (default 0)")
    p.add_argument(
        "--rounds",
        type=int,
        default=1,
        help="run the reference and every path this many times, interleaved; rates are medians over the rounds, "
        "speedups medians of per-round ratios (default 1)",
    )
    p.add_argument(
        "--baseline",
        metavar="DIR",
        help="also time the reference path of the redsim in this source tree (another version, e.g. a "
        "`git worktree add --detach DIR COMMIT`) in each round, on the same loads, start and map, and print "
        "every path's speedup over it",
    )
    finish_command(p, cmd_bench_step, "print one JSON document on stdout", default_threads=1)

    p = bench.add_parser(
        "accuracy",
        help="trajectory error vs time per step against the float64 full-space implicit-Euler reference at the same "
        "dt (Newton-converged; --full dt4th shows its own time-step error)",
        description=(
            "Seeded load scenarios (env-style actions on the scene's handle) from the full-space rest; the "
            "float64 full-space trajectory is the reference. Per configuration (full space loosened; the shipped "
            "neural subspace, linear modes and modal derivatives of its d from their own rest; runtime options): "
            "median wall time per step (the configurations stepped in turn, step by step with the reference) and "
            "the relative M-norm and handle (cm) trajectory errors. Exits 4 where a reference made steps the scene "
            "cannot, 3 where a row went non-finite (the tables printed all the same). See "
            "redsim.benches.accuracy."
        ),
    )
    p.add_argument(
        "scene",
        help="one of mini_chain, chain, cloth_ball, hanging_sheet, conditional_bar, bistable_bar (its shipped map), or "
        "a checkpoint STEM.pt (any scene, a mesh's too: the map against the full space of the scene its .json records)",
    )
    p.add_argument(
        "--handle",
        help="the handle the loads push (default: the scene's env's, also for a checkpoint of one of these scenes; "
        "another checkpoint scene's first handle)",
    )
    p.add_argument(
        "--max-force",
        type=float,
        metavar="N",
        help="force [N] of a unit action, at most float32's largest (default: the scene's env's, or, for another "
        "checkpoint scene, the reach task's: half the scene's weight)",
    )
    p.add_argument("--steps", type=int, default=100, help="steps per scenario, >= 10 (default 100)")
    p.add_argument("--scenarios", default="push,actions", help="push and/or actions (default both)")
    p.add_argument("--seed", type=non_negative_seed, help="seed of the actions scenario (default 0)")
    p.add_argument(
        "--full",
        default="tol,newton1,newton3,dt2,dt5",
        help="loosened full-space runs: tol (1e-3), newton1, newton3 (iterations), dt2, dt5 (time step), or none; "
        "dt4th (dt / 4, not in the default) is the reference's own time-step error",
    )
    p.add_argument("--no-study", action="store_true", help="skip the start study (push scenario)")
    p.add_argument(
        "--dims",
        metavar="D1,D2",
        help="compare the three subspaces at each of these d (e.g. 1,2,4,8,16) and the shipped map's d: the shipped "
        "neural map at its d, else DIR/SCENE_dD.pt, fitted with the scene's preset into --checkpoints when missing "
        "(into DIR/SCENE_dD_KEY.pt where DIR/SCENE_dD.pt is another fit, as in bench subspace)",
    )
    p.add_argument("--checkpoints", metavar="DIR", help="where --dims fits are kept (default subspaces)")
    p.add_argument(
        "--fit-steps",
        type=int,
        metavar="N",
        help="fit (or reuse, DIR/SCENE_dD_sN.pt) the --dims maps with N steps instead of the preset's",
    )
    add_out_folder(p, "write DIR/accuracy_SCENE.md, .csv and .png")
    finish_command(p, cmd_bench_accuracy, "print one JSON document on stdout", default_threads=1)

    p = bench.add_parser(
        "scaling",
        help="fit, forward, latent (all elements and cubature) and full-space step time and memory against mesh size",
        description=(
            "The cantilever beam meshed at several resolutions, the same 5 x 128 MLP: fit time per 1000 steps "
            "(a few timed steps, scaled), forward-pass time, a cubature of the briefly fitted map (build time, "
            "error), latent energy evaluation and step time with all elements and with the cubature (B = 1 and "
            "batched; the map's f(0) shifted to rest so that the steps feel the loads; --dtype), full-space step "
            "time and peak memory per size (each size in its own process), and the growth exponent of each curve. "
            "See redsim.benches.scaling."
        ),
    )
    p.add_argument("--sizes", default="4,6,8,11", help="cross-section cells k per mesh (default 4,6,8,11)")
    p.add_argument("--fit-steps", type=int, default=5, help="timed fit steps per size (default 5)")
    p.add_argument("--fit-warmup", type=int, default=2, help="untimed fit steps before them (default 2)")
    p.add_argument("--latent-steps", type=int, default=5, help="timed latent steps per size (default 5)")
    p.add_argument(
        "--cubature-elements", type=int, default=200, help="most elastic elements of each size's cubature (default 200)"
    )
    p.add_argument("--batch", type=int, default=64, help="batch of the batched latent steps, 0 for none (default 64)")
    p.add_argument(
        "--batch-max-n",
        type=int,
        help="run the all-element batched step only up to this many free DOFs (default: every size)",
    )
    p.add_argument(
        "--full-max-n", type=int, help="run the full-space step only up to this many free DOFs (default: every size)"
    )
    p.add_argument("--no-full", action="store_true", help="skip the full-space step at every size")
    p.add_argument(
        "--dtype",
        choices=("float32", "float64"),
        default="float64",  # redsim.benches.scaling.DTYPE (the parser imports no torch)
        help=(
            "dtype of the latent E+grad and steps (default float64: at float32's tolerance the cubature step of the "
            "briefly fitted map stalls in round-off and runs max_iter; the full step is float64 always)"
        ),
    )
    add_out_folder(p, "write DIR/scaling.md and DIR/scaling.png (rewritten after each size)")
    finish_command(p, cmd_bench_scaling, "print one JSON document on stdout", default_threads=1)

    p = bench.add_parser(
        "stability",
        help="hard cases: stiff, big steps, far latents, actions at bounds, impacts, fuzzed env steps",
        description=(
            "Drive scenes and envs into the regimes that break simulators (stiffness x1000, dt 0.1 and 0.5 s, "
            "|z| = 10, bang-bang and alternating actions, high-speed impacts into contact, starts near element "
            "inversion, condition range edges, fuzzed env steps) and print per run: steps, failures detected and "
            "recovered, nan count (must be 0), unreported energy gains (must be 0), the largest energy above the "
            "start and the largest work of the loads. With mujoco installed: kicked and dropped 24-capsule chains "
            "under MuJoCo's integrators at dt 0.01, and redsim's chain under the scenarios that blew MuJoCo up "
            "(all of them without mujoco). See redsim.benches.stability."
        ),
    )
    p.add_argument("--steps", type=int, help="fuzzed env steps over all envs (default 10000)")
    p.add_argument("--envs", metavar="ID1,ID2", help="env ids to fuzz (default: all registered)")
    p.add_argument(
        "--regimes",
        metavar="R1,R2",
        help="only these, from stiff, big_dt, far_latent, action_bounds, impact, near_inversion, condition_edges, "
        "fuzz, mujoco, damping (default all but damping, which measures implicit Euler's numerical damping: released "
        "unforced runs, the free energy they keep; redsim.benches.damping)",
    )
    p.add_argument(
        "--long-steps",
        type=int,
        help="steps of the action_bounds regime's bang-bang runs (default 2000); the other scene regimes run a "
        "fraction of it (stiff and condition_edges 1/10, big_dt 1/20, far_latent 1/40, impact and near_inversion "
        "1/100, near_inversion at most 5), at least 2 steps",
    )
    p.add_argument("--chain-steps", type=int, help="steps of the chain scenarios (default 300)")
    p.add_argument("--chain-full-steps", type=int, help="steps of redsim's full-space chain runs (default 50)")
    p.add_argument(
        "--copies",
        type=int,
        help="vector env copies of the fuzzed envs other than the cloths (default 256; the cloths run 8)",
    )
    p.add_argument(
        "--budget",
        type=seconds,
        metavar="SECONDS",
        help="wall-time budget of each fuzzed env and of each scene's action_bounds runs (the other scene regimes "
        "run their fixed steps and refuse it): they stop there and report the steps they ran (default none)",
    )
    p.add_argument(
        "--damping-scenes",
        metavar="A,B",
        help="scenes of the damping regime (default mini_chain,chain,bistable_bar,conditional_bar; also "
        "hanging_sheet, cloth_ball)",
    )
    p.add_argument(
        "--damping-seconds",
        type=seconds,
        metavar="T",
        help="simulated seconds of each released run of the damping regime, a whole multiple of each of its time "
        "steps (default 1)",
    )
    p.add_argument(
        "--damping-divisions",
        metavar="K1,K2",
        help="the damping regime's latent runs (and MuJoCo's) step at 0.02 s / K for each K (default 1,4,16)",
    )
    p.add_argument(
        "--damping-full",
        metavar="K1,K2",
        help="its full-space runs step at 0.02 s / K for each K, or none (default 1,4,16)",
    )
    p.add_argument("--seed", type=non_negative_seed, help="seed of the fuzzed actions and resets (default 0)")
    finish_command(p, cmd_bench_stability, "print one JSON document on stdout", default_threads=1)
    cubature.add_bench_command(bench)
    return bench
