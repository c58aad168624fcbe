"""``redsim cubature CHECKPOINT`` and ``redsim bench cubature``: argparse wiring (the work is in redsim.cubature)."""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path
from typing import Any

from redsim.cli.common import (
    EXIT_FAILED_STEP,
    EXIT_INTERRUPTED,
    EXIT_OK,
    CliError,
    check_scene_name,
    error,
    finish_command,
    json_out,
    load_checkpoint,
    machine_line,
    non_negative_seed,
    out,
    parse_ints,
    parse_list,
    shown_path,
    warn,
    write_error,
)
from redsim.cli.scene_runs import run_scenes

TOL_ELEMENTS = 1000
"""Most elements per effect with ``--tol``."""
BENCH_ELEMENTS = 200
"""Elements per effect of the cubature ``redsim bench cubature`` builds where none is beside the map."""
BENCH_SCENES = "cloth_ball,hanging_sheet"
"""The scenes ``redsim bench cubature`` benches where none is named."""
CONFIG_FLAGS = {
    "elements": "--elements",
    "samples": "--samples",
    "episodes": "--episodes",
    "steps": "--rollout-steps",
    "tol": "--tol",
}
"""CubatureConfig's fields as the command's flags (for its error messages)."""


def _command(args: argparse.Namespace) -> str:
    """The command line that rebuilds this cubature."""
    parts = ["redsim", "cubature", args.checkpoint]
    parts += ["--elements", str(args.elements)] if args.elements is not None else ["--tol", repr(args.tol)]
    parts += ["--samples", str(args.samples), "--episodes", str(args.episodes)]
    parts += ["--rollout-steps", str(args.rollout_steps), "--seed", str(args.seed)]
    parts += ["--full", args.full] if args.full is not None else []
    parts += ["--subsample", args.subsample] if args.subsample else []
    return " ".join(shlex.quote(p) for p in parts)


def _config(args: argparse.Namespace) -> Any:
    from redsim.cubature import CubatureConfig

    try:
        return CubatureConfig(
            elements=TOL_ELEMENTS if args.elements is None else args.elements,
            tol=args.tol,
            samples=args.samples,
            episodes=args.episodes,
            steps=args.rollout_steps,
            full=None if args.full is None else tuple(parse_list(args.full, "--full")),
            subsample=tuple(parse_list(args.subsample, "--subsample")) if args.subsample else (),
            seed=args.seed,
        )
    except ValueError as err:
        name, _, rest = str(err).partition(" ")
        raise CliError(f"{CONFIG_FLAGS.get(name, name)} {rest}") from err


def cmd_cubature(args: argparse.Namespace) -> int:
    from redsim.cubature import build_cubature
    from redsim.cubature.energy import cubature_path

    target = cubature_path(args.checkpoint)
    try:
        scene, subspace = load_checkpoint(args.checkpoint)
        _check_target(target, args.overwrite)
        command = _command(args)
        cub = build_cubature(scene, subspace, _config(args), progress=not args.json, command=command)
        path = cub.save(args.checkpoint)  # at once (write_atomically): a Ctrl-C leaves the file before, or this one
    except ValueError as err:
        raise CliError(str(err)) from err
    except KeyboardInterrupt:
        before = f"; the {target.name} there before is unchanged" if target.exists() else ""
        warn(f"interrupted before {target} was written{before}; nothing was saved, rerun: {args.command_line}")
        return EXIT_INTERRUPTED
    rows = [
        {
            "effect": r.name,
            "mode": r.mode,
            "kept": int(r.indices.numel()),
            "of": r.element_count,
            "held_out_error": r.held_out_error,
        }
        for r in cub.rules
    ]
    missed = args.tol is not None and cub.summary["train_error"] > args.tol
    if missed:  # the file is written and usable; the caller sees that it is coarser than asked
        warn(
            f"--tol {args.tol:g} not reached: training error {cub.summary['train_error']:.3g} (each subsampled "
            f"effect's search stops at its share of --tol, at {TOL_ELEMENTS} elements, or where no element lowers "
            "its error further)"
        )
    if args.json:
        json_out(
            {
                "path": str(path),
                "summary": cub.summary,
                "effects": rows,
                "tol_reached": None if args.tol is None else not missed,
            }
        )
        return EXIT_OK
    out(f"wrote {path}")
    for row in rows:
        out(
            f"  {row['effect']:<16} {row['mode']:<9} {row['kept']:>6} of {row['of']:<7} "
            f"held-out error {row['held_out_error']:.3g}"
        )
    s = cub.summary
    dropped = s.get("rollout_states_dropped") or {}
    dropped_note = (
        f"; {sum(dropped.values())} rollout states dropped: {dropped['diverged']} diverged, "
        f"{dropped['out_of_range']} out of the map's range"
        if sum(dropped.values())
        else ""
    )
    whole = s["held_out_rollouts"]
    out(
        f"  {s['states']} states ({s['sampled_states']} sampled, {s['rollout_states']} from rollouts{dropped_note}), "
        f"{s['held_out_states']} held out ({whole} whole rollout{'' if whole == 1 else 's'} among them): "
        f"force error {s['held_out_force_error']:.3g}, force+energy {s['held_out_error']:.3g}"
    )
    return EXIT_OK


def _check_target(target: Path, overwrite: bool) -> None:
    """Refuse, before the build, a cubature file ``target`` that could not be written or, without ``overwrite``,
    exists."""
    if target.exists() and not target.is_file():  # found before the fit, not when it saves
        raise CliError(f"{target} is a folder, not a file: remove it, or copy STEM.pt and STEM.json elsewhere")
    if target.exists() and not overwrite:
        raise CliError(
            f"{target} exists (this map's cubature, which an env made with cubature=True uses); --overwrite replaces it"
        )
    if (why := write_error(target.absolute().parent)) is not None:
        raise CliError(
            f"cannot write {target}: its folder is not writable ({why}; copy STEM.pt and STEM.json elsewhere)"
        )


def _checkpoint_of(name: str, folder: Path | None) -> Path:
    """``folder/NAME.pt`` where it exists (refused if fitted to another scene), else the shipped map of ``name``."""
    from redsim import pretrained

    mine = folder / f"{name}.pt" if folder is not None else None
    if mine is not None and mine.is_file():
        _check_scene_of(mine, name)
        return mine
    try:
        return pretrained.path(name)
    except KeyError as err:
        where = f"no {mine}" if mine is not None else "no --checkpoints DIR given"
        raise CliError(
            f"{err.args[0]}; {where} (fit one with `redsim fit {name} --out DIR/{name}`, then pass --checkpoints DIR)"
        ) from err


def cmd_bench_cubature(args: argparse.Namespace) -> int:
    import torch

    from redsim.bench import machine_info
    from redsim.cubature import AffineOutput, CubatureConfig, build_cubature, load_cubature
    from redsim.cubature.bench import WARMUP_STEPS, bench_cubature
    from redsim.cubature.energy import cubature_path
    from redsim.subspace import CheckpointError

    if args.cubature is not None and args.elements is not None:
        raise CliError("--elements sizes a cubature the bench builds; --cubature PATH benches one built already")
    args.elements = BENCH_ELEMENTS if args.elements is None else args.elements
    if args.elements < 1:
        raise CliError(f"--elements must be an integer >= 1, got {args.elements}")
    if args.steps < 1 or args.timed_steps < 2:  # the sweep's too
        raise CliError("--steps must be >= 1 and --timed-steps >= 2")
    if args.states < 1:
        raise CliError(f"--states must be an integer >= 1, got {args.states}")
    if args.sweep:
        if args.compile:
            raise CliError("--compile times the benched scenes' cubature step; the --sweep has no compiled column")
        if args.cubature:
            raise CliError("--cubature benches one scene's cubature; the --sweep fits none (unfitted maps)")
        if args.held_out or args.held_out_seed is not None:
            raise CliError("--held-out recomputes a fitted cubature's errors; the --sweep's maps are unfitted")
        unused = [
            flag
            for flag, given in (
                ("SCENES", args.scenes is not None),
                ("--checkpoints", args.checkpoints is not None),
                ("--steps", args.steps != 100),
                ("--states", args.states != 8),
                ("--warmup-steps", args.warmup_steps is not None),
                ("--dtype", args.dtype != "float32"),
            )
            if given
        ]
        if unused:  # the sweep times steps of unfitted hanging_sheet maps only: these would be ignored
            raise CliError(f"--sweep times the step only (hanging_sheet, unfitted maps): drop {', '.join(unused)}")
        return _sweep(args)
    if args.batch_max_n is not None:
        raise CliError("--batch-max-n limits the --sweep's all-element step: add --sweep C1,C2 or drop it")
    if args.compile:
        from redsim.runtime.stepper import check_compiler

        try:
            check_compiler(torch.device("cpu"))
        except RuntimeError as err:
            raise CliError(str(err)) from err
    names = parse_list(BENCH_SCENES if args.scenes is None else args.scenes, "SCENES")
    for name in names:
        check_scene_name(name, takes_files=False)
    batches = tuple(parse_ints(args.batches, "--batches"))
    warmup = WARMUP_STEPS if args.warmup_steps is None else args.warmup_steps
    if warmup < 0:
        raise CliError(f"--warmup-steps must be >= 0, got {warmup}")
    folder = Path(args.checkpoints) if args.checkpoints else None
    if folder is not None and not folder.is_dir():
        raise CliError(f"--checkpoints {folder}: " + ("a file, not a folder" if folder.exists() else "no such folder"))
    source = _cubature_source(args.cubature, names, named=args.scenes is not None)
    checkpoints = {name: _checkpoint_of(name, folder) for name in names}
    loaded = {}
    for name in names:  # every checkpoint and its cubature refused, if they are, before any bench runs
        weights = checkpoints[name]
        scene, subspace = load_checkpoint(str(weights))
        path = source or cubature_path(weights)
        try:
            cub = load_cubature(path, scene, subspace) if path.is_file() else None
        except CheckpointError as err:
            raise CliError(str(err)) from err
        if cub is None:  # the bench builds one: refuse a map it cannot build one for (an autoencoder's) now
            try:
                AffineOutput(subspace)
            except ValueError as err:
                raise CliError(f"{weights}: {err}") from err
        loaded[name] = (weights, scene, subspace, cub, path if cub is not None else None)
    machine = machine_info()
    results = []
    if not args.json:
        out(
            f"cubature vs all-element latent step ({args.dtype}, CPU); deviation over {args.steps} steps (median of "
            f"{args.states} rollouts); step time "
            f"median (ms) and value-and-gradient calls per step (a timed rollout's cold first step included), "
            + (f"after {warmup} all-element steps under the loads" if warmup else "from rest")
        )
        out(machine_line(machine, "cpu"))

    def run(name: str, item: tuple[Any, ...]) -> None:
        weights, scene, subspace, cub, path = item
        if cub is None:
            try:
                cub = build_cubature(scene, subspace, CubatureConfig(elements=args.elements))
            except ValueError as err:  # an NNLS out of iterations: fewer --elements (this scene's row fails)
                raise ValueError(f"{shown_path(weights)}: {err}") from err
        result = {"checkpoint": str(weights), "cubature": None if path is None else str(path)} | bench_cubature(
            scene,
            subspace,
            cub,
            steps=args.steps,
            batches=batches,
            timed_steps=args.timed_steps,
            warmup=warmup,
            dtype=getattr(torch, args.dtype),
            compiled=args.compile,
            states=args.states,
            held_out=args.held_out,
            held_out_seed=args.held_out_seed,
        )
        results.append(result)
        if not args.json:
            kept = ", ".join(f"{k} {v}/{result['element_counts'][k]}" for k, v in result["elements"].items())
            times = "  ".join(
                f"B={b}: {1e3 * t['all_s']:.3g} -> {1e3 * t['cubature_s']:.3g} ({t['all_s'] / t['cubature_s']:.1f}x; "
                f"calls {t['all_calls_per_step']:.1f} -> {t['cubature_calls_per_step']:.1f})"
                + (
                    f", compiled {1e3 * t['cubature_compiled_s']:.3g} ({t['all_s'] / t['cubature_compiled_s']:.1f}x)"
                    if args.compile
                    else ""
                )
                for b, t in result["timing"].items()
            )
            made = shown_path(path) if path is not None else f"built here, --elements {args.elements}"
            force = result["held_out_force_error"]  # a cubature made in Python may carry no summary
            plain = result["held_out_plain_force_error"]  # a build before 2026-12-07 recorded none
            errors = result["held_out_errors"]
            recomputed = (
                ""
                if errors is None
                else f" (recomputed on the {errors['states']} states "
                + (
                    "its config holds out: "
                    if args.held_out_seed is None
                    else f"its config draws under seed {errors['seed']}, which no build saw: "
                )
                + f"{errors['force_error']:.3g}, "
                f"plain {errors['plain_force_error']:.3g}, per state median {errors['median_state_force_error']:.3g} "
                f"and 90th percentile {errors['p90_state_force_error']:.3g}, energy {errors['energy_error']:.3g}, "
                f"plain against the subsampled effects' force {errors['subsampled_force_error']:.3g})"
            )
            flags = result["flags"]
            flagged = "".join(
                f"; {key.replace('_', ' ')} steps {flags['all'][key]} -> {flags['cubature'][key]}"
                for key in flags["all"]
                if flags["all"][key] or flags["cubature"][key]
            )
            out(
                f"{name} ({shown_path(weights)}; {made}): n={result['n']}, kept {kept}; "
                f"held-out force error {'unknown' if force is None else format(force, '.3g')}"
                + ("" if plain is None else f" (plain {plain:.3g})")
                + f"{recomputed}; "
                f"trajectory deviation {result['trajectory_deviation']:.3g}"
                + (f" (of {args.states * args.steps} state-steps{flagged})" if flagged else "")
                + f"; penetration {result['penetration_all_m']:.2g} -> {result['penetration_cubature_m']:.2g} m; "
                f"{times}"
            )

    runs = run_scenes("bench cubature", loaded.items(), run, text=not args.json)
    if args.json:
        json_out({"machine": machine, "results": results, **runs.fields()})
    diverged = [
        f"{r['scene']}: {r['flags']['all']['diverged']} (all elements) and {r['flags']['cubature']['diverged']} "
        f"(cubature) of {args.states * args.steps} state-steps"
        for r in results
        if r["flags"]["all"]["diverged"] or r["flags"]["cubature"]["diverged"]
    ]
    if diverged:  # the rows are printed; the command fails, for scripts and CI
        error(
            "diverged accuracy steps (rejected: the state stays, so the deviation measures a stalled rollout) in "
            + "; ".join(diverged)
        )
    return runs.status(EXIT_FAILED_STEP if diverged else EXIT_OK)


def _cubature_source(given: str | None, names: list[str], named: bool) -> Path | None:
    """``--cubature PATH``: a ``.cubature.json`` file, for a bench of one scene (None: the one beside each map);
    ``named``: the caller named the scenes (else ``names`` are the defaults)."""
    from redsim.cubature.energy import SUFFIX

    if given is None:
        return None
    path = Path(given)
    if not named:
        raise CliError(
            f"--cubature {path} is one map's cubature: name its scene, e.g. `redsim bench cubature "
            f"cloth_ball --cubature {path}`"
        )
    if len(names) != 1:
        raise CliError(f"--cubature {path} is one map's cubature: name one scene, got {', '.join(names)}")
    if not path.name.endswith(SUFFIX):
        raise CliError(f"--cubature {path}: not a {SUFFIX} file (made by `redsim cubature`)")
    if not path.is_file():
        raise CliError(f"--cubature {path}: no such file")
    return path


def _check_scene_of(weights: Path, name: str) -> None:
    """Refuse ``weights`` (a user's DIR/NAME.pt) unless it was fitted to the catalog scene ``name``."""
    from redsim.subspace import CheckpointError, read_metadata

    try:
        doc = read_metadata(weights)
    except CheckpointError as err:
        raise CliError(str(err)) from err
    builder = (doc.get("scene_params") or {}).get("builder")
    if doc.get("scene") != name or builder is not None:
        what = f"the {builder} mesh scene" if builder is not None else "scene"
        raise CliError(
            f"{weights} is a fit of {what} {doc.get('scene')!r}, not of {name!r}: bench cubature reads "
            "DIR/SCENE.pt as a fit of the catalog scene SCENE (move that file, or pass another --checkpoints DIR)"
        )


def _sweep(args: argparse.Namespace) -> int:
    from redsim.bench import machine_info
    from redsim.cubature.bench import mesh_sweep

    cells = tuple(parse_ints(args.sweep, "--sweep"))
    batches = tuple(parse_ints(args.batches, "--batches"))
    if args.batch_max_n is not None and args.batch_max_n < 0:
        raise CliError(f"--batch-max-n must be >= 0, got {args.batch_max_n}")
    machine = machine_info()
    if not args.json:
        out("hanging_sheet meshed c x c, unfitted d=8 map near the seed: median step (ms), all elements -> cubature")
        out(machine_line(machine, "cpu"))
    rows: list[dict[str, Any]] = []

    def run(name: str, c: int) -> None:
        (row,) = mesh_sweep(
            (c,), elements=args.elements, batches=batches, timed_steps=args.timed_steps, batch_max_n=args.batch_max_n
        )
        rows.append(row)
        if not args.json:  # each size as it finishes: a Ctrl-C keeps those before it
            times = "  ".join(
                f"B={b}: {'not run' if t['all_s'] is None else format(1e3 * t['all_s'], '.3g')} -> "
                f"{1e3 * t['cubature_s']:.3g}"
                for b, t in row["timing"].items()
            )
            out(f"cells {row['cells']:>4}  n {row['n']:>7}  kept {row['kept']:>5}  {times}")

    sizes = [(f"cells {c}", c) for c in cells]
    runs = run_scenes("bench cubature --sweep", sizes, run, text=not args.json, unit="size")
    if args.json:
        json_out({"machine": machine, "sweep": rows, **runs.fields()})
    return runs.status()


def add_commands(sub: Any) -> None:
    """``redsim cubature``."""
    p = sub.add_parser(
        "cubature",
        help="fit a cubature energy for a subspace checkpoint",
        description=(
            "Choose a few elements per effect with non-negative weights (greedy + NNLS) so that the reduced forces "
            "and energy match the full energy's on states sampled from the subspace (z ~ N(0, I)) and visited by "
            "latent rollouts under random loads; write CHECKPOINT.cubature.json beside the checkpoint."
        ),
    )
    p.add_argument("checkpoint", help="the subspace checkpoint (STEM, STEM.pt or STEM.json)")
    size = p.add_mutually_exclusive_group(required=True)
    size.add_argument("--elements", type=int, help="most elements kept per subsampled effect")
    size.add_argument(
        "--tol",
        type=float,
        help="target training error of the reduced forces and energy together, relative to their totals: each of "
        "the m subsampled effects stops at TOL/sqrt(m), at most 1000 elements each (a target not reached is said)",
    )
    p.add_argument("--samples", type=int, default=256, help="states z ~ N(0, I) (default 256)")
    p.add_argument("--episodes", type=int, default=4, help="latent rollouts under random loads (default 4)")
    p.add_argument("--rollout-steps", type=int, default=40, help="steps per rollout (default 40)")
    p.add_argument(
        "--full",
        metavar="E1,E2",
        help="effects kept whole, in place of the default (contact effects): name contact too to keep it whole",
    )
    p.add_argument("--subsample", metavar="E1,E2", help="effects subsampled even if they are contact")
    p.add_argument("--seed", type=non_negative_seed, default=0, help="seed of samples, loads and split (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing CHECKPOINT.cubature.json")
    finish_command(p, cmd_cubature, "print one JSON document on stdout (no progress bar)")


def add_bench_command(bench: Any) -> None:
    """``redsim bench cubature`` under the ``bench`` subcommands ``bench``."""
    p = bench.add_parser(
        "cubature",
        help="cubature energy vs the all-element latent step",
        description=(
            "For each scene's shipped subspace (or DIR/SCENE.pt) and the cubature beside it (or --cubature PATH; "
            "built with --elements if there is none): elements kept, held-out force error, trajectory deviation from "
            "the all-element step under the same seeded loads, contact penetration of both, and step time per batch "
            "size side by side. Steps of the accuracy rollouts the stepper flagged (unconverged, diverged, out of the "
            "map's range) are counted in the row; a diverged one makes the command exit 4."
        ),
    )
    p.add_argument("scenes", nargs="?", help=f"comma-separated scene names (default: {BENCH_SCENES})")
    p.add_argument("--steps", type=int, default=100, help="steps of the accuracy rollouts (default 100)")
    p.add_argument("--timed-steps", type=int, default=10, help="timed steps per batch size (default 10)")
    p.add_argument(
        "--states",
        type=int,
        default=8,
        help="accuracy rollouts whose median deviation is reported (default 8; more keep the first 8 and add others)",
    )
    p.add_argument(
        "--warmup-steps",
        type=int,
        help="all-element steps under the loads before the timed ones, which start from that moving state "
        "(default redsim.cubature.bench.WARMUP_STEPS, 30; 0: from rest; not the --sweep)",
    )
    p.add_argument("--batches", default="1,64", metavar="B1,B2", help="batch sizes timed (default 1,64)")
    p.add_argument(
        "--elements",
        type=int,
        help=f"elements per effect of the cubature the bench builds where none is beside the map "
        f"({BENCH_ELEMENTS}; not with --cubature)",
    )
    p.add_argument(
        "--dtype",
        choices=("float32", "float64"),
        default="float32",
        help="dtype of both steps (default float32; float64 shows what round-off adds to the deviation)",
    )
    p.add_argument(
        "--checkpoints",
        metavar="DIR",
        help="use DIR/SCENE.pt (a fit of SCENE) and the cubature beside it where they exist, the shipped ones "
        "elsewhere (default: the shipped ones; each row names its checkpoint)",
    )
    p.add_argument(
        "--cubature",
        metavar="PATH",
        help="bench this cubature file (one scene; it must belong to the scene's map, e.g. "
        "redsim/pretrained/cloth_ball.lean.cubature.json) instead of the one beside the map",
    )
    p.add_argument(
        "--compile",
        action="store_true",
        help='also time the cubature step with LatentStepper(compile="dynamic") (its first steps, which compile, '
        "untimed; needs a C++ compiler)",
    )
    p.add_argument(
        "--held-out",
        action="store_true",
        help="also recompute the cubature's errors on the states its recorded config holds out (it replays the "
        "build's rollouts): the force error as the build reports it (each state over its force and energy), the plain "
        "relative force error, its median and 90th percentile per state, and the energy error",
    )
    p.add_argument(
        "--held-out-seed",
        metavar="S",
        type=int,
        help="as --held-out, on every state the recorded config draws under seed S instead: states no build saw (a "
        "build before 2026-12-07 trained on some of the states its config holds out)",
    )
    p.add_argument(
        "--sweep",
        metavar="C1,C2",
        help="instead: the mesh sweep, hanging_sheet with C x C cells each (step time only, unfitted maps)",
    )
    p.add_argument(
        "--batch-max-n",
        type=int,
        help="sweep: time the all-element step at batches > 1 only up to this many free DOFs (default: always)",
    )
    finish_command(p, cmd_bench_cubature, "print one JSON document on stdout", default_threads=1)
