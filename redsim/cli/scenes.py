"""``redsim scenes`` (the catalog) and ``redsim simulate`` (full-space implicit Euler on a scene)."""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import redsim
from redsim.cli.common import (
    EXIT_FAILED_STEP,
    EXIT_INTERRUPTED,
    EXIT_NAN,
    EXIT_OK,
    EXIT_SCENE_FAILED,
    CliError,
    add_out_folder,
    add_scene_args,
    catalog_names,
    file_name,
    finish_command,
    json_out,
    out,
    parse_loads,
    scene_from_args,
    warn,
    warn_earlier_frames,
)


def cmd_scenes(args: argparse.Namespace) -> int:
    rows: list[dict[str, Any]] = []
    toys = redsim.scenes.names("toy")
    for name in catalog_names():
        if name in toys and not args.all:
            continue
        try:
            scene = redsim.scenes.build(name)
        except Exception as err:  # one broken scene must not hide the others
            rows.append({"name": name, "error": f"{type(err).__name__}: {err}"})
            continue
        rows.append({**scene.describe(), "name": name})
    failed = [r["name"] for r in rows if "error" in r]
    if args.json:
        json_out(rows)
    else:
        for row in rows:
            if "error" in row:
                out(f"{row['name']}  FAILED TO BUILD: {row['error']}")
                continue
            out(f"{row['name']}  ({row['dim']}D, n={row['n']})  {row['description']}")
            out("  effects:    " + ", ".join(f"{e['name']}:{e['kind']}" for e in row["effects"]))
            out("  handles:    " + (", ".join(row["handles"]) or "-"))
            out("  conditions: " + (", ".join(_condition_text(c) for c in row["condition_space"] or []) or "-"))
    if failed:
        warn(f"{len(failed)} scene(s) failed to build: {', '.join(failed)}")
        return EXIT_SCENE_FAILED
    return EXIT_OK


def _condition_text(condition: dict[str, Any]) -> str:
    """``name in [low, high] (default d)`` of one row of :meth:`redsim.scene.ConditionSpace.describe`."""
    return f"{condition['name']} in [{condition['low']:g}, {condition['high']:g}] (default {condition['default']:g})"


def _parse_conditions(items: list[str], scene: redsim.Scene) -> dict[str, float] | None:
    """``NAME=VALUE`` conditions of a conditional scene, the others at their defaults (None: no condition space).

    Raises:
        CliError: ``--cond`` on a scene without conditions, a malformed or non-finite item, an unknown or repeated
            name, or a value outside the range the scene declares.
    """
    space = scene.condition_space
    if space is None:
        if items:
            raise CliError(f"scene {scene.name!r} has no conditions; --cond does not apply to it")
        return None
    rows = {c["name"]: c for c in space.describe()}
    values = {name: row["default"] for name, row in rows.items()}
    given: set[str] = set()
    for item in items:
        name, sep, text = (part.strip() for part in item.partition("="))
        try:
            value = float(text) if sep and name else math.nan
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise CliError(f"malformed --cond {item!r}: expected NAME=VALUE with a finite number")
        if name not in rows:
            raise CliError(
                f"unknown condition {name!r} in --cond for scene {scene.name!r}; valid conditions: "
                + ", ".join(_condition_text(row) for row in rows.values())
            )
        if name in given:
            raise CliError(f"--cond gives condition {name!r} twice")
        row = rows[name]
        if not row["low"] <= value <= row["high"]:
            raise CliError(
                f"--cond {name}={value:g} lies outside the range [{row['low']:g}, {row['high']:g}] scene "
                f"{scene.name!r} declares (a build parameter, --param, sets the range)"
            )
        given.add(name)
        values[name] = value
    return values


def _step_line(rec: dict[str, Any], steps: int) -> str:
    status = "FAILED" if rec.get("failure") else ("converged" if rec["converged"] else "NOT converged")
    return (
        f"step {rec['step']:>{len(str(steps))}}/{steps}  t={rec['time']:.4g} s  {status:<13}  "
        f"iters {rec['iterations']:>3}  |grad| {rec['grad_norm']:.2e}  E {rec['potential_energy']:.6g} J"
    )


class _NotConvergedFilter(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return "did not converge" not in record.getMessage()


@contextlib.contextmanager
def _said_here(*, verbose: bool) -> Iterator[None]:
    """Drop the integrator's warning for a step that did not converge (unless ``-v``): simulate says it for every
    step (its step line, ``--json``'s ``per_step``) and counts them in one warning; the log's line as well was one
    more stderr line per step, dated by the step's start time where simulate numbers the step by its end."""
    log = logging.getLogger("redsim.integrators.implicit_euler")
    quiet = None if verbose else _NotConvergedFilter()
    if quiet is not None:
        log.addFilter(quiet)
    try:
        yield
    finally:
        if quiet is not None:
            log.removeFilter(quiet)


def cmd_simulate(args: argparse.Namespace) -> int:
    import torch

    from redsim.plausibility import step_failure

    if args.steps < 1:
        raise CliError(f"--steps must be an integer >= 1, got {args.steps}")
    from redsim.integrators import MIN_TIME_STEP

    if not (math.isfinite(args.dt * args.dt) and args.dt >= MIN_TIME_STEP):  # 1 / dt^2 in the step (1e200: overflow)
        raise CliError(f"--dt must be a finite number >= {MIN_TIME_STEP:g} [s], got {args.dt}")
    if args.meshes and args.out is None:
        raise CliError("--meshes needs --out DIR")
    scene = scene_from_args(args)
    loads = parse_loads(args.load, scene)
    conditions = _parse_conditions(args.cond, scene)
    cond = None if conditions is None else torch.tensor(list(conditions.values()), dtype=scene.dtype)

    from redsim.integrators import FullSpace, ImplicitEuler

    try:
        integ = ImplicitEuler(
            FullSpace(scene),
            args.dt,
            minimizer=args.minimizer,
            tol=args.tol,
            max_iter=args.max_iter,
            strict=False,
            escape_saddles=args.escape_saddles,
            retry_tunneled=args.retry_tunneled,
        )
    except ValueError as err:  # bad --tol or --max-iter
        raise CliError(f"bad solver setting (--tol, --max-iter): {err}") from err
    folder = Path(args.out) if args.out is not None else None
    frames = folder / "frames" if folder is not None else None
    mesh_paths: list[Path] = []

    def potential(q: torch.Tensor) -> float:
        with torch.no_grad():
            return float(scene.energy(q, loads, cond))

    state = integ.initial_state()
    q_start = state.q.detach().clone()
    energy_start = potential(q_start)
    if args.meshes:
        from redsim.render import export_meshes

        warn_earlier_frames(frames, "--out")
        mesh_paths += export_meshes(scene, q_start, frames, 0)
    if not args.json:
        out(
            f"simulating {scene.name} (n={scene.free_dof_count}, {args.steps} steps of dt={args.dt:g} s, "
            f"{args.minimizer}); E {energy_start:.6g} J at t=0"
            + ("" if conditions is None else "; conditions " + ", ".join(f"{k}={v:g}" for k, v in conditions.items()))
        )
    records: list[dict[str, Any]] = []
    q_last = q_start
    wall = 0.0
    nan_step = failed_step = None
    interrupted = False
    for step in range(1, args.steps + 1):
        q_inertial = 2.0 * state.q - state.q_prev
        try:
            with _said_here(verbose=args.verbose):
                start = time.perf_counter()
                state, info = integ.step(state, loads=loads, cond=cond)
                wall += time.perf_counter() - start
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the steps done are summed up, and drawn with --out
            if not records:
                raise
            interrupted = True
            break
        finite = bool(torch.isfinite(state.q).all())
        rec = {
            "step": step,
            "time": float(state.time),
            "converged": bool(info.converged),
            "iterations": int(info.iterations),
            "grad_norm": float(info.grad_norm),
            "objective": float(info.energy),
            "potential_energy": potential(state.q) if finite else math.nan,
            "energy_gain": bool(info.energy_gain),
            "mechanical_gain": float(info.mechanical_gain),
            "tunneled": bool(info.tunneled),
            "tunnel_caught": bool(info.tunnel_caught),
            "message": info.message,
        }
        if not finite or not math.isfinite(rec["grad_norm"]):
            nan_step = step
        else:
            rec["failure"] = step_failure(scene, q_inertial, state.q, rec["grad_norm"], rec["potential_energy"])
            failed_step = step if rec["failure"] else None
        if rec.get("failure"):
            rec["converged"] = False
        records.append(rec)
        if not args.json:
            out(_step_line(rec, args.steps))
        if nan_step is not None or failed_step is not None:
            break
        q_last = state.q.detach().clone()
        if args.meshes:
            mesh_paths += export_meshes(scene, q_last, frames, step)

    png = None
    if folder is not None:
        if scene.surfaces:
            from redsim.render import draw_states

            stopped = nan_step is not None or failed_step is not None
            last = records[-1] if not stopped else (records[-2] if len(records) > 1 else None)
            end_title = f"t={last['time']:.4g} s (step {last['step']})" if last is not None else "t=0"
            png = draw_states(
                scene,
                [q_start, q_last],
                [f"{scene.name}: t=0", end_title],
                folder / f"{file_name(scene.name)}_start_end.png",
                loads=loads,
            )
        else:
            warn(f"scene {scene.name!r} has no surfaces; no picture written")

    not_converged = [r["step"] for r in records if not r["converged"]]
    gained = [r["step"] for r in records if r["energy_gain"]]
    tunneled = [r["step"] for r in records if r["tunneled"]]
    caught = [r["step"] for r in records if r["tunnel_caught"]]
    summary = {
        "scene": scene.name,
        "params": scene.params,
        "n": scene.free_dof_count,
        "dt": args.dt,
        "steps": args.steps,
        "steps_run": len(records),
        "minimizer": args.minimizer,
        "tol": args.tol,
        "max_iter": args.max_iter,
        "escape_saddles": args.escape_saddles,
        "retry_tunneled": args.retry_tunneled,
        "loads": loads or {},
        "conditions": conditions,
        "converged_steps": len(records) - len(not_converged),
        "not_converged_steps": not_converged,
        "energy_gain_steps": gained,
        "tunneled_steps": tunneled,
        "tunnels_caught_steps": caught,
        "max_iterations": max(r["iterations"] for r in records),
        "final_grad_norm": records[-1]["grad_norm"],
        "energy_start": energy_start,
        "energy_end": records[-1]["potential_energy"],
        "wall_time_s": wall,
        "nan_step": nan_step,
        "failed_step": failed_step,
        "failure": records[-1].get("failure"),
        "interrupted": interrupted,
        "png": str(png) if png is not None else None,
        "meshes": [str(p) for p in mesh_paths],
        "per_step": records,
    }
    if args.json:
        json_out(summary)
    else:
        out(
            f"{summary['converged_steps']}/{len(records)} steps converged, max {summary['max_iterations']} "
            f"iterations, final |grad| {summary['final_grad_norm']:.2e}, {wall:.3g} s"
        )
        out(f"energy {energy_start:.6g} J -> {summary['energy_end']:.6g} J")
        if caught:
            out(
                f"{len(caught)} step(s) moved through a contact in their first solve and were solved again within a "
                f"trust radius, to the contact's near side (first: step {caught[0]})"
            )
        if png is not None:
            out(f"wrote {png}")
        if mesh_paths:
            out(f"wrote {len(mesh_paths)} meshes to {frames}")
    if not_converged and failed_step is None:
        first = records[not_converged[0] - 1]
        warn(
            f"{len(not_converged)} of {len(records)} step(s) did not converge "
            f"(first: step {first['step']}: {first['message']})"
        )
    if gained:
        first = records[gained[0] - 1]
        warn(
            f"{len(gained)} of {len(records)} step(s) raised K + E by more than the loads' work (first: step "
            f"{first['step']}, {first['mechanical_gain']:.3g} J): an artefact of the solve, reported, not acted on"
        )
    if tunneled:
        warn(
            f"{len(tunneled)} of {len(records)} step(s) moved through a contact that neither end touches (first: "
            f"step {tunneled[0]}): a move longer than the contact is thick, which the penalty never felt, and "
            "solving it again within a trust radius did not catch it; reported (a smaller --dt resolves it)"
        )
    if interrupted:
        warn(f"interrupted after step {len(records)} of {args.steps}; the summary is of those steps")
        return EXIT_INTERRUPTED
    if nan_step is not None:
        warn(f"step {nan_step} produced NaN or inf; stopped there")
        return EXIT_NAN
    if failed_step is not None:
        warn(f"step {failed_step} failed: {summary['failure']}; stopped there")
        return EXIT_FAILED_STEP
    return EXIT_OK


def add_commands(sub: Any) -> None:
    """Add ``scenes`` and ``simulate`` to the subcommands ``sub``."""
    p = sub.add_parser(
        "scenes",
        help="list the scene catalog",
        description=(
            "List every scene of the catalog with its size n, effects (name:kind), handles and conditions (each "
            "with its range and default, what `simulate --cond` takes). Test scenes (toy_*) are listed with --all."
        ),
        epilog="Exit status: 0 every scene built, 1 a scene failed to build (named, the others still listed).",
    )
    p.add_argument("--all", action="store_true", help="include the toy_* test scenes")
    finish_command(p, cmd_scenes, "print one JSON list on stdout", threads=False)

    p = sub.add_parser(
        "simulate",
        help="run full-space implicit Euler on a scene",
        description=(
            "Run implicit Euler in the full space from the scene's seed state and report solver statistics. "
            "With --out, write OUT/SCENE_start_end.png (first and last state; loads drawn as arrows, fixed "
            "bodies and pins in grey) and, with --meshes, OUT/frames/frame_XXXX_<surface>.ply for every frame."
        ),
        epilog=(
            "Exit status: 0 done (non-converged steps, and steps that gained energy, are warned about), 2 bad "
            "input, 3 NaN or inf, 4 a step failed (its forces moved a coordinate more than 10 scene sizes in one "
            "step: loads or dt far beyond the scene), 130 interrupted (Ctrl-C or SIGTERM after the first step: "
            "the steps done are summed up, and drawn with --out)."
        ),
    )
    add_scene_args(p)
    p.add_argument("--steps", type=int, default=20, help="number of time steps (default 20)")
    p.add_argument("--dt", type=float, default=0.01, help="time step [s] (default 0.01)")
    p.add_argument(
        "--load",
        action="append",
        default=[],
        metavar="HANDLE=FX,FY[,FZ]",
        help="constant force [N] on a handle, repeatable",
    )
    p.add_argument(
        "--cond",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a condition of a conditional scene, within its range (`redsim scenes` lists them, e.g. "
        "conditional_bar's stiffness_ratio=2), held for every step; repeatable; the others keep their defaults",
    )
    p.add_argument("--minimizer", choices=("newton", "lbfgs"), default="newton", help="default newton")
    p.add_argument(
        "--tol",
        type=float,
        default=1e-8,
        help="relative gradient tolerance (default 1e-8): a step has converged when |grad| <= tol times the "
        "forces acting (internal, inertial and applied loads), which bounds its position error by about tol "
        "times the scene size where the step's objective is convex (a converged step is stationary, and can be a "
        "saddle: see --escape-saddles); a huge load makes the bound huge too, so implausible steps are checked "
        "separately",
    )
    p.add_argument("--max-iter", type=int, default=100, help="solver iterations per step (default 100)")
    p.add_argument(
        "--escape-saddles",
        action="store_true",
        help="leave a converged step that ended at a saddle of the step's objective (negative curvature, which "
        "Newton does not see: from a symmetric state, e.g. a chain's links) and solve again; one more Hessian "
        "and factorization per step",
    )
    p.add_argument(
        "--no-retry-tunneled",
        dest="retry_tunneled",
        action="store_false",
        help="report a step that moved through a contact (tunneled) without solving it again within a trust radius "
        "(by default it is solved again and, where that converges on the contact's near side, caught)",
    )
    add_out_folder(p, "folder for the picture and meshes (nothing is written without it)")
    p.add_argument("--meshes", action="store_true", help="write per-frame .ply meshes to OUT/frames")
    finish_command(p, cmd_simulate, "print one JSON summary (with per-step stats) on stdout")
