"""The ``redsim`` command line: ``scenes``, ``simulate``, ``fit``, ``inspect``, ``sample``, ``animate``, ``bench``.

Every subcommand has ``--help`` and ``--json`` (one JSON document on stdout; human-readable
text otherwise). Bad input is reported as a single ``redsim: error: ...`` line on stderr with
exit status 2, never as a traceback.

Exit status: 0 success; 1 a scene failed to build (``scenes``); 2 bad input; 3 a simulation
produced NaN or inf.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import re
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

import torch

import redsim
from redsim.scene import Scene
from redsim.subspace import checkpoint_path, periodic_latents, sample_latents

EXIT_OK = 0
EXIT_SCENE_FAILED = 1
EXIT_USAGE = 2
EXIT_NAN = 3
EXIT_INTERRUPTED = 130

_DTYPES = {"float64": torch.float64, "float32": torch.float32}


class CliError(Exception):
    """Bad command-line input: reported as one line on stderr with exit status ``code``."""

    def __init__(self, message: str, code: int = EXIT_USAGE) -> None:
        super().__init__(message)
        self.code = code


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors become :class:`CliError` (one line, exit status 2)."""

    def error(self, message: str) -> NoReturn:
        raise CliError(f"{message} (see `{self.prog} --help`)")


# -- output ---------------------------------------------------------------------------------
def _out(text: str = "") -> None:
    print(text, flush=True)


def _finite_or_none(obj: Any) -> Any:
    """``obj`` with NaN and inf floats replaced by None, so the output is strict JSON."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_or_none(v) for v in obj]
    return obj


def _json_out(obj: Any) -> None:
    print(json.dumps(_finite_or_none(obj), indent=2, default=str, allow_nan=False), flush=True)


def _warn(text: str) -> None:
    print(f"redsim: warning: {text}", file=sys.stderr, flush=True)


def _error(text: str) -> None:
    print(f"redsim: error: {text}", file=sys.stderr, flush=True)


# -- input ----------------------------------------------------------------------------------
def _catalog_names() -> list[str]:
    return list(redsim.scenes.names())


def _check_scene_name(name: str) -> None:
    names = _catalog_names()
    if name not in names:
        raise CliError(f"unknown scene {name!r}; valid scenes: {', '.join(names)}")


def _build_scene(name: str, params: dict[str, Any] | None = None) -> Scene:
    """Build catalog scene ``name``; unknown names and rejected parameters become CliErrors."""
    _check_scene_name(name)
    params = params or {}
    try:
        return redsim.scenes.build(name, **params)
    except (TypeError, ValueError, KeyError) as err:
        shown = ", ".join(f"{k}={json.dumps(v)}" for k, v in params.items()) or "no parameters"
        message = str(err.args[0]) if isinstance(err, KeyError) and err.args else str(err)
        raise CliError(f"cannot build scene {name!r} with {shown}: {message}") from err


def _parse_params(items: Sequence[str]) -> dict[str, Any]:
    """``KEY=VALUE`` pairs with VALUE a JSON literal (``3``, ``0.5``, ``false``, ``"text"``)."""
    params: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key.isidentifier():
            raise CliError(f"malformed --param {item!r}: expected KEY=VALUE, e.g. --param links=3")
        try:
            params[key] = json.loads(value)
        except json.JSONDecodeError as err:
            raise CliError(
                f"bad --param {item!r}: VALUE must be a JSON literal such as 3, 0.5, false, [1, 2] "
                f"or '\"text\"' (quotes included)"
            ) from err
    return params


def _parse_loads(items: Sequence[str], scene: Scene) -> dict[str, list[float]] | None:
    """``HANDLE=FX,FY[,FZ]`` forces [N] on the scene's handles; None when there are none."""
    if not items:
        return None
    example = "HANDLE=FX,FY" + (",FZ" if scene.dim == 3 else "")
    loads: dict[str, list[float]] = {}
    for item in items:
        handle, sep, value = item.partition("=")
        handle = handle.strip()
        try:
            force = [float(c) for c in value.split(",")] if sep and handle else None
        except ValueError:
            force = None
        if force is None or not all(math.isfinite(f) for f in force):
            raise CliError(f"malformed --load {item!r}: expected {example} with finite numbers")
        if handle not in scene.handle_names:
            valid = ", ".join(scene.handle_names) if scene.handles else "none (this scene has no handles)"
            raise CliError(f"unknown handle {handle!r} in --load for scene {scene.name!r}; valid handles: {valid}")
        if len(force) != scene.dim:
            raise CliError(
                f"--load {item!r} has {len(force)} component(s), but scene {scene.name!r} is {scene.dim}D: "
                f"expected {example}"
            )
        if handle in loads:
            raise CliError(f"--load gives handle {handle!r} twice")
        loads[handle] = force
    return loads


def _parse_list(text: str, what: str) -> list[str]:
    items = [s.strip() for s in text.split(",") if s.strip()]
    if not items:
        raise CliError(f"{what} must be a comma-separated list, got {text!r}")
    return items


def _file_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


# -- scenes ---------------------------------------------------------------------------------
def _cmd_scenes(args: argparse.Namespace) -> int:
    rows: list[dict[str, Any]] = []
    for name in _catalog_names():
        if name.startswith("toy_") and not args.all:
            continue
        try:
            scene = redsim.scenes.build(name)
        except Exception as err:  # one broken scene must not hide the others
            rows.append({"name": name, "error": f"{type(err).__name__}: {err}"})
            continue
        rows.append({**scene.describe(), "name": name})
    failed = [r["name"] for r in rows if "error" in r]
    if args.json:
        _json_out(rows)
    else:
        for row in rows:
            if "error" in row:
                _out(f"{row['name']}  FAILED TO BUILD: {row['error']}")
                continue
            _out(f"{row['name']}  ({row['dim']}D, n={row['n']})  {row['description']}")
            _out("  effects:    " + ", ".join(f"{e['name']}:{e['kind']}" for e in row["effects"]))
            _out("  handles:    " + (", ".join(row["handles"]) or "-"))
            _out("  conditions: " + (", ".join(row["conditions"]) or "-"))
    if failed:
        _warn(f"{len(failed)} scene(s) failed to build: {', '.join(failed)}")
        return EXIT_SCENE_FAILED
    return EXIT_OK


# -- simulate -------------------------------------------------------------------------------
def _step_line(rec: dict[str, Any], steps: int) -> str:
    status = "converged" if rec["converged"] else "NOT converged"
    return (
        f"step {rec['step']:>{len(str(steps))}}/{steps}  t={rec['time']:.4g} s  {status:<13}  "
        f"iters {rec['iterations']:>3}  |grad| {rec['grad_norm']:.2e}  E {rec['potential_energy']:.6g} J"
    )


def _cmd_simulate(args: argparse.Namespace) -> int:
    if args.steps < 1:
        raise CliError(f"--steps must be >= 1, got {args.steps}")
    if not (math.isfinite(args.dt) and args.dt > 0):
        raise CliError(f"--dt must be a finite number > 0, got {args.dt}")
    if args.meshes and args.out is None:
        raise CliError("--meshes needs --out DIR")
    params = _parse_params(args.param)
    scene = _build_scene(args.scene, params)
    loads = _parse_loads(args.load, scene)

    from redsim.integrators import FullSpace, ImplicitEuler

    try:
        integ = ImplicitEuler(
            FullSpace(scene),
            args.dt,
            minimizer=args.minimizer,
            tol=args.tol,
            max_iter=args.max_iter,
            strict=False,
        )
    except ValueError as err:  # bad --tol or --max-iter
        raise CliError(f"bad solver setting (--tol, --max-iter): {err}") from err
    out = Path(args.out) if args.out is not None else None
    frames = out / "frames" if out is not None else None
    mesh_paths: list[Path] = []

    def potential(q: torch.Tensor) -> float:
        with torch.no_grad():
            return float(scene.energy(q, loads))

    state = integ.initial_state()
    q_start = state.q.detach().clone()
    energy_start = potential(q_start)
    if args.meshes:
        from redsim.render import export_meshes

        mesh_paths += export_meshes(scene, q_start, frames, 0)
    if not args.json:
        _out(
            f"simulating {args.scene} (n={scene.free_dof_count}, {args.steps} steps of dt={args.dt:g} s, "
            f"{args.minimizer}); E {energy_start:.6g} J at t=0"
        )
    records: list[dict[str, Any]] = []
    q_last = q_start
    wall = 0.0
    nan_step = None
    for step in range(1, args.steps + 1):
        start = time.perf_counter()
        state, info = integ.step(state, loads=loads)
        wall += time.perf_counter() - start
        finite = bool(torch.isfinite(state.q).all())
        rec = {
            "step": step,
            "time": float(state.time),
            "converged": bool(info.converged),
            "iterations": int(info.iterations),
            "grad_norm": float(info.grad_norm),
            "objective": float(info.energy),
            "potential_energy": potential(state.q) if finite else math.nan,
            "message": info.message,
        }
        records.append(rec)
        if not args.json:
            _out(_step_line(rec, args.steps))
        if not finite or not math.isfinite(rec["grad_norm"]):
            nan_step = step
            break
        q_last = state.q.detach().clone()
        if args.meshes:
            mesh_paths += export_meshes(scene, q_last, frames, step)

    png = None
    if out is not None:
        if scene.surfaces:
            from redsim.render import draw_states

            last = records[-1] if nan_step is None else (records[-2] if len(records) > 1 else None)
            end_title = f"t={last['time']:.4g} s (step {last['step']})" if last is not None else "t=0"
            png = draw_states(
                scene,
                [q_start, q_last],
                [f"{args.scene}: t=0", end_title],
                out / f"{_file_name(args.scene)}_start_end.png",
            )
        else:
            _warn(f"scene {args.scene!r} has no surfaces; no picture written")

    not_converged = [r["step"] for r in records if not r["converged"]]
    summary = {
        "scene": args.scene,
        "params": params,
        "n": scene.free_dof_count,
        "dt": args.dt,
        "steps": args.steps,
        "steps_run": len(records),
        "minimizer": args.minimizer,
        "loads": loads or {},
        "converged_steps": len(records) - len(not_converged),
        "not_converged_steps": not_converged,
        "max_iterations": max(r["iterations"] for r in records),
        "final_grad_norm": records[-1]["grad_norm"],
        "energy_start": energy_start,
        "energy_end": records[-1]["potential_energy"],
        "wall_time_s": wall,
        "nan_step": nan_step,
        "png": str(png) if png is not None else None,
        "meshes": [str(p) for p in mesh_paths],
        "per_step": records,
    }
    if args.json:
        _json_out(summary)
    else:
        _out(
            f"{summary['converged_steps']}/{len(records)} steps converged, max {summary['max_iterations']} "
            f"iterations, final |grad| {summary['final_grad_norm']:.2e}, {wall:.3g} s"
        )
        _out(f"energy {energy_start:.6g} J -> {summary['energy_end']:.6g} J")
        if png is not None:
            _out(f"wrote {png}")
        if mesh_paths:
            _out(f"wrote {len(mesh_paths)} meshes to {frames}")
    if not_converged:
        first = records[not_converged[0] - 1]
        _warn(
            f"{len(not_converged)} of {len(records)} step(s) did not converge "
            f"(first: step {first['step']}: {first['message']})"
        )
    if nan_step is not None:
        _warn(f"step {nan_step} produced NaN or inf; stopped there")
        return EXIT_NAN
    return EXIT_OK


# -- bench ----------------------------------------------------------------------------------
TABLE1_SCENES = (
    "cloth_ball",
    "klann",
    "stewart",
    "bistable_bar",
    "hanging_sheet",
    "conditional_bar",
    "chain",
    "mini_chain",
    "stiff_body",
    "cantilever",
    "elephant",
)


def _cmd_bench_subspace(args: argparse.Namespace) -> int:
    from redsim import pretrained
    from redsim.bench import compare_subspaces, machine_info
    from redsim.subspace import CheckpointError, load_subspace
    from redsim.trainers import FitConfig, fit_subspace
    from redsim.trainers.fit import fit_command
    from redsim.trainers.presets import preset

    names = _parse_list(args.scenes, "--scenes") if args.scenes else list(TABLE1_SCENES)
    for name in names:
        _check_scene_name(name)
    if not (math.isfinite(args.load_size) and args.load_size > 0.0):
        raise CliError(f"--load-size must be finite and > 0, got {args.load_size}")
    folder = Path(args.checkpoints)
    rows = []
    for name in names:
        scene = _build_scene(name)
        overrides = {} if args.steps is None else {"steps": args.steps}
        config = FitConfig(**{**preset(name), **overrides})
        stem = folder / (name if args.steps is None else f"{name}_s{args.steps}")
        candidates = [checkpoint_path(stem, ".pt")]
        if args.steps is None and name in pretrained.names():
            candidates.append(pretrained.path(name))
        neural, source = None, str(candidates[0])
        for path in candidates if not args.refit else []:
            if path.is_file():
                try:
                    neural, source = load_subspace(path, scene=scene), str(path)
                    break
                except CheckpointError as err:
                    _warn(f"not using {path}: {err}")
        if neural is None:
            result = fit_subspace(
                scene,
                config,
                seed=args.seed,
                out=stem,
                progress=not args.json,
                command=fit_command(scene, config, args.seed, stem),
            )
            neural = result.subspace
        fit = neural.metadata["fit"]
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
            "checkpoint": source,
            "methods": metrics,
        }
        rows.append(row)
        if not args.json:
            _out(_subspace_row(row))
    if args.json:
        _json_out({"machine": machine_info(), "rows": rows})
    return EXIT_OK


def _metric(result: dict[str, Any], *path: str) -> float:
    value: Any = result
    for key in path:
        if not isinstance(value, dict) or key not in value:
            return float("nan")
        value = value[key]
    return float(value) if isinstance(value, (int, float)) else float("nan")


def _subspace_row(row: dict[str, Any]) -> str:
    lines = [
        f"{row['scene']}  n={row['n']}  d={row['d']}  sigma={row['sigma']:g}  lam={row['lam']:g}  "
        f"steps={row['steps']}  fit {row['fit_seconds']:.0f} s  ({row['checkpoint']})"
    ]
    for method, result in row["methods"].items():
        line = (
            f"  {method:18s} rel. energy {_metric(result, 'energy', 'relative_energy'):8.3g}  "
            f"excess {_metric(result, 'energy', 'excess_energy'):9.3g} J  "
            f"stretch {_metric(result, 'stretch', 'mean'):8.3g}  "
            f"load error {_metric(result, 'load_response', 'mean_error'):7.3g}  "
            f"response {_metric(result, 'load_response', 'mean_response_error'):7.3g}  "
            f"strain {_metric(result, 'nonrigid_strain', 'mean'):8.3g}"
        )
        if "reach" in result:
            line += "  reach " + "/".join(f"{e:.3g}" for e in result["reach"]["errors"])
        if "loop" in result:
            line += f"  crank turn {result['loop']['turn_degrees']:.0f} deg (winding {result['loop']['winding']})"
        lines.append(line)
    return "\n".join(lines)


def _machine_line(machine: dict[str, Any], device: str) -> str:
    load = machine["load_average_1min"]
    cpu = machine["processor"]
    cpu = cpu if cpu == machine["machine"] else f"{cpu} ({machine['machine']})"
    return (
        f"machine: {cpu}, {machine['cpu_count']} CPUs"
        + (f" (load {load:.2f})" if load is not None else "")
        + f", torch {machine['torch']}, {machine['torch_threads']} threads, device {device}"
        + (f" ({machine['cuda_device']})" if device.startswith("cuda") else "")
    )


def _cmd_bench_energy(args: argparse.Namespace) -> int:
    from redsim.bench import bench_energy, machine_info

    if args.scenes is None:
        names = [n for n in _catalog_names() if not n.startswith("toy_")]
    else:
        names = _parse_list(args.scenes, "--scenes")
        for name in names:
            _check_scene_name(name)
    if args.repeats < 1:
        raise CliError(f"--repeats must be >= 1, got {args.repeats}")
    try:
        batches = [int(b) for b in _parse_list(args.batches, "--batches")]
    except ValueError as err:
        raise CliError(f"--batches must be comma-separated integers, got {args.batches!r}") from err
    if min(batches) < 1:
        raise CliError(f"--batches must be >= 1, got {args.batches!r}")
    dtypes = _parse_list(args.dtypes, "--dtypes")
    unknown = [d for d in dtypes if d not in _DTYPES]
    if unknown:
        raise CliError(f"unknown dtype(s) {unknown}; valid: {', '.join(_DTYPES)}")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise CliError("--device cuda requested but torch sees no CUDA device")

    machine = machine_info()
    columns = [(d, b) for d in dtypes for b in batches]
    if not args.json:
        _out(f"energy + gradient wall time, median over up to {args.repeats} repeats (ms)")
        _out(_machine_line(machine, args.device))
        header = f"{'scene':<24} {'n':>8} " + " ".join(f"{f'f{d[5:]} B={b}':>12}" for d, b in columns)
        _out(header + "  repeats")
        _out("-" * (len(header) + 9))
    results = []
    for name in names:
        base = _build_scene(name)
        row = []
        for dtype, batch in columns:
            scene = base.to(args.device, _DTYPES[dtype])
            row.append(bench_energy(scene, batch, args.repeats, time_budget=args.budget))
        results += row
        if not args.json:
            cells = " ".join(f"{1e3 * r['median_s']:>12.3g}" for r in row)
            _out(f"{name:<24} {base.free_dof_count:>8} {cells}  {min(r['repeats'] for r in row)}")
    if args.json:
        _json_out({"machine": machine, "device": args.device, "repeats": args.repeats, "results": results})
    return EXIT_OK


BENCH_FIT_SCENES = ("mini_chain", "chain", "bistable_bar", "cloth_ball", "stiff_body")


def _cmd_bench_fit(args: argparse.Namespace) -> int:
    from redsim.bench import bench_fit_variants, machine_info
    from redsim.trainers import FitConfig
    from redsim.trainers.presets import preset

    names = _parse_list(args.scenes, "--scenes") if args.scenes else list(BENCH_FIT_SCENES)
    for name in names:
        _check_scene_name(name)
    for flag in ("steps", "warmup", "rounds", "threads"):
        if getattr(args, flag) < 1:
            raise CliError(f"--{flag} must be >= 1, got {getattr(args, flag)}")
    if args.batch < 2:
        raise CliError(f"--batch must be >= 2, got {args.batch}")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise CliError("--device cuda requested but torch sees no CUDA device")
    torch.set_num_threads(args.threads)
    machine = machine_info()
    if not args.json:
        _out(
            f"fit step wall time (ms), median of {args.steps} steps in {args.rounds} interleaved rounds, after "
            f"{args.warmup} warm-up steps each; batch {args.batch}, {FitConfig().dtype}, scene presets"
        )
        _out(_machine_line(machine, args.device))
        width = max(14, *(len(name) for name in names))
        header = f"{'scene':<{width}} {'n':>6} {'eager':>8} {'fused':>8} {'x':>5} {'compiled':>9} {'x':>5}"
        header += f" {'compile s':>10}"
        _out(header)
        _out("-" * len(header))
    rows = []
    for name in names:
        scene = _build_scene(name)
        config = FitConfig(**{**preset(name), "batch_size": args.batch, "device": args.device})
        row = bench_fit_variants(scene, config, steps=args.steps, warmup=args.warmup, rounds=args.rounds)
        rows.append({"scene": name, "n": scene.free_dof_count, "variants": row})
        if not args.json:
            eager, fused, compiled = (1e3 * row[v]["median_s"] for v in ("eager", "fused", "compiled_fused"))
            _out(
                f"{name:<{width}} {scene.free_dof_count:>6} {eager:>8.3g} {fused:>8.3g} {eager / fused:>5.2f} "
                f"{compiled:>9.3g} {eager / compiled:>5.2f} {row['compiled_fused']['startup_s']:>10.1f}"
            )
        recompiled = row["compiled_fused"]["graphs_compiled_timed"]
        if recompiled:
            _warn(f"{name}: {recompiled} graph(s) were compiled during the timed steps (recompilation)")
    if args.json:
        _json_out({"machine": machine, "device": args.device, "rows": rows})
    else:
        _out(
            "x: speed-up over eager (plain Adam); compile s: first compiled step minus a warm one "
            "(the first compiled scene also pays torch.compile's start-up)"
        )
    return EXIT_OK


# -- fitting and checkpoints -----------------------------------------------------------------
# (flag, FitConfig field, type, help); the flags of `redsim fit` are generated from this table.
_FIT_FLAGS: tuple[tuple[str, str, Any, str], ...] = (
    ("--dim", "latent_dim", int, "latent dimension d"),
    ("--sigma", "sigma", float, "target Lipschitz scale σ [sqrt(kg) m per unit z]"),
    ("--lam", "lam", float, "weight λ of the pair term"),
    ("--steps", "steps", int, "Adam steps"),
    ("--batch", "batch_size", int, "latent samples per step"),
    ("--lr", "learning_rate", float, "initial learning rate (halved after each quarter)"),
    ("--width", "hidden_width", int, "MLP hidden width"),
    ("--layers", "hidden_layers", int, "MLP hidden layers"),
    ("--explore", "exploration_fraction", float, "fraction of the steps over which ρ rises 0 -> 1"),
    ("--seed-bias", "seed_bias", bool, "start the output bias at the seed state (stiff meshes)"),
    ("--drive", "drive", float, "start stiffness [N/m] of the scene's fitting drivers (cranks); 0: off"),
    ("--drive-fraction", "drive_fraction", float, "--drive holds for half this fraction of the steps, then falls to 0"),
    ("--soften-from", "soften_from", float, "initial weight of the --soften effects"),
    ("--soften-fraction", "soften_fraction", float, "fraction of the steps over which that weight rises to 1"),
    ("--checkpoint-every", "checkpoint_every", int, "steps between resumable checkpoints"),
    ("--dtype", "dtype", str, "float32 or float64"),
    ("--device", "device", str, "torch device"),
    ("--fused-adam", "fused_adam", bool, "fused Adam (--no-fused-adam: plain Adam)"),
    ("--compile", "compile", bool, "torch.compile the loss: faster steps after a compile of tens of seconds"),
)


def _fit_defaults() -> dict[str, Any]:
    from redsim.trainers import FitConfig

    return dataclasses.asdict(FitConfig())


def _fit_config(args: argparse.Namespace, scene_name: str) -> Any:
    from redsim.trainers import FitConfig
    from redsim.trainers.presets import preset

    fields = preset(scene_name)
    for _flag, field, _kind, _help in _FIT_FLAGS:
        value = getattr(args, field)
        if value is not None:
            fields[field] = value
    if args.periodic is not None:
        fields["periodic"] = tuple(int(i) for i in _parse_list(args.periodic, "--periodic"))
    if args.soften is not None:
        fields["soften"] = tuple(_parse_list(args.soften, "--soften"))
    if args.cond:
        fields["conditional"] = True
    try:
        return FitConfig(**fields)
    except (TypeError, ValueError) as err:
        raise CliError(str(err)) from err


def _cmd_fit(args: argparse.Namespace) -> int:
    from redsim.trainers import fit_subspace
    from redsim.trainers.fit import fit_command

    params = _parse_params(args.param)
    scene = _build_scene(args.scene, params)
    config = _fit_config(args, scene.name)
    out = Path(args.out) if args.out else Path(f"{scene.name}_d{config.latent_dim}")
    command = fit_command(scene, config, args.seed, out)
    try:
        result = fit_subspace(
            scene, config, seed=args.seed, out=out, resume=args.resume, progress=not args.json, command=command
        )
    except KeyboardInterrupt:
        _warn(f"interrupted; the state is in {checkpoint_path(out, '.fit.pt')}; continue with: {command} --resume")
        return EXIT_INTERRUPTED
    except FloatingPointError as err:
        _error(str(err))
        return EXIT_NAN
    except ValueError as err:  # bad resume state, conditional fit without conditions, ...
        raise CliError(str(err)) from err
    meta = result.subspace.metadata
    summary = {"checkpoint": str(checkpoint_path(out, ".pt")), "metadata": str(checkpoint_path(out, ".json")), **meta}
    if args.json:
        _json_out(summary)
    else:
        final = meta["final"]
        _out(f"fitted {scene.name} (n={scene.free_dof_count}, d={config.latent_dim}) in {result.fit_seconds:.1f} s")
        _out(
            f"final energy {final['energy']:.4g} J, pair term {final['pair']:.4g}, "
            f"mean metric stretch {final['stretch']:.4f}"
        )
        _out(f"wrote {summary['checkpoint']} and {summary['metadata']}")
    return EXIT_OK


def _load_checkpoint(path: str) -> tuple[Scene, Any]:
    """The scene a checkpoint was fitted to (rebuilt from its JSON) and the subspace."""
    from redsim.subspace import CheckpointError, load_subspace, read_metadata

    try:
        doc = read_metadata(path)
        scene_name = doc.get("scene")
        if not isinstance(scene_name, str):
            raise CheckpointError("metadata names no scene", path)
        scene = _build_scene(scene_name, doc.get("scene_params") or {})
        return scene, load_subspace(path, scene=scene)
    except CheckpointError as err:
        raise CliError(str(err)) from err


def _cmd_inspect(args: argparse.Namespace) -> int:
    scene, sub = _load_checkpoint(args.checkpoint)
    meta = {"checkpoint": args.checkpoint, "n": scene.free_dof_count, "latent_dim": sub.latent_dim, **sub.metadata}
    if args.json:
        _json_out(meta)
        return EXIT_OK
    _out(f"{args.checkpoint}: scene {scene.name} (n={scene.free_dof_count}), d={sub.latent_dim}")
    fit = meta.get("fit", {})
    _out(
        f"  fit: sigma={fit.get('sigma')} lam={fit.get('lam')} steps={fit.get('steps')} seed={meta.get('seed')} "
        f"width={fit.get('hidden_width')} layers={fit.get('hidden_layers')} in {meta.get('fit_seconds', 0):.1f} s"
    )
    for key, value in (meta.get("final") or {}).items():
        _out(f"  final {key}: {value:.5g}")
    for key, value in (meta.get("metrics") or {}).items():
        if isinstance(value, (int, float)):
            _out(f"  metric {key}: {value:.5g}")
    _out(f"  reproduce: {meta.get('command')}")
    return EXIT_OK


def _latent_samples(sub: Any, scene: Scene, count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor | None]:
    generator = torch.Generator().manual_seed(seed)
    z = sample_latents(count, sub.latent_dim, periodic_latents(sub), generator=generator)
    cond = None
    if getattr(getattr(sub, "config", None), "condition_dim", 0):
        assert scene.condition_space is not None  # a conditional map was fitted to a conditional scene
        cond = scene.condition_space.sample(count, generator).float()
    return z, cond


def _cmd_sample(args: argparse.Namespace) -> int:
    import numpy as np

    if args.n < 1:
        raise CliError(f"-n must be >= 1, got {args.n}")
    scene, sub = _load_checkpoint(args.checkpoint)
    z, cond = _latent_samples(sub, scene, args.n, args.seed)
    with torch.no_grad():
        q = sub(z, cond).double()
        x = scene.full_positions(q)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    arrays = {"z": z.numpy(), "q": q.numpy(), "x": x.numpy()}
    if cond is not None:
        arrays["cond"] = cond.numpy()
    np.savez_compressed(out, scene=scene.name, scene_fingerprint=scene.fingerprint(), **arrays)
    finite = bool(torch.isfinite(q).all())
    summary = {"out": str(out), "count": args.n, "n": scene.free_dof_count, "finite": finite}
    if args.json:
        _json_out(summary)
    else:
        _out(f"wrote {args.n} states of {scene.name} (q: [{args.n}, {scene.free_dof_count}], full x too) to {out}")
    return EXIT_OK if finite else EXIT_NAN


def catmull_rom_loop(keys: torch.Tensor, frames: int) -> torch.Tensor:
    """A closed uniform Catmull-Rom spline through ``keys`` [K, d], sampled at ``frames`` points [frames, d]."""
    K = keys.shape[0]
    t = torch.arange(frames, dtype=keys.dtype) * K / frames
    i = t.floor().long()
    u = (t - i).unsqueeze(-1)
    p0, p1, p2, p3 = (keys[(i + k) % K] for k in (-1, 0, 1, 2))
    return 0.5 * (2 * p1 + (p2 - p0) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u**2 + (3 * p1 - p0 - 3 * p2 + p3) * u**3)


def _cmd_animate(args: argparse.Namespace) -> int:
    from redsim.render import animate_states

    if args.keys < 2 or args.frames < args.keys:
        raise CliError(f"need --keys >= 2 and --frames >= --keys, got {args.keys} and {args.frames}")
    scene, sub = _load_checkpoint(args.checkpoint)
    keys, cond = _latent_samples(sub, scene, args.keys, args.seed)
    z = catmull_rom_loop(keys, args.frames)
    with torch.no_grad():
        q = sub(z, None if cond is None else cond[:1].expand(args.frames, -1)).double()
    path = animate_states(scene, list(q), args.out, fps=args.fps)
    if args.json:
        _json_out({"out": str(path), "frames": args.frames, "keys": keys.tolist()})
    else:
        _out(f"wrote {args.frames} frames through {args.keys} latent keyframes to {path}")
    return EXIT_OK


# -- parser ---------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    """The ``redsim`` argument parser with its subcommands."""
    parser = _Parser(
        prog="redsim",
        description="Data-free neural reduced-order simulation and control of physical systems.",
    )
    parser.add_argument("--version", action="version", version=f"redsim {redsim.__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress (INFO) to stderr")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser(
        "scenes",
        help="list the scene catalog",
        description=(
            "List every scene of the catalog with its size n, effects (name:kind), handles and condition "
            "names. Test scenes (toy_*) are listed with --all."
        ),
    )
    p.add_argument("--all", action="store_true", help="include the toy_* test scenes")
    p.add_argument("--json", action="store_true", help="print one JSON list on stdout")
    p.set_defaults(func=_cmd_scenes)

    p = sub.add_parser(
        "simulate",
        help="run full-space implicit Euler on a scene",
        description=(
            "Run implicit Euler in the full space from the scene's seed state and report solver statistics. "
            "With --out, write OUT/SCENE_start_end.png (first and last state) and, with --meshes, "
            "OUT/frames/frame_XXXX_<surface>.ply for every frame."
        ),
        epilog="Exit status: 0 done (non-converged steps are warned about), 2 bad input, 3 NaN or inf.",
    )
    p.add_argument("scene", help="catalog name (see `redsim scenes --all`)")
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
        "--param",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="scene build parameter, VALUE a JSON literal (e.g. links=3, gravity=false); repeatable",
    )
    p.add_argument("--minimizer", choices=("newton", "lbfgs"), default="newton", help="default newton")
    p.add_argument("--tol", type=float, default=1e-8, help="solver gradient tolerance (default 1e-8)")
    p.add_argument("--max-iter", type=int, default=100, help="solver iterations per step (default 100)")
    p.add_argument("--out", metavar="DIR", help="folder for the picture and meshes (nothing is written without it)")
    p.add_argument("--meshes", action="store_true", help="write per-frame .ply meshes to OUT/frames")
    p.add_argument("--json", action="store_true", help="print one JSON summary (with per-step stats) on stdout")
    p.set_defaults(func=_cmd_simulate)

    p = sub.add_parser(
        "fit",
        help="fit a neural subspace to a scene (data-free)",
        description=(
            "Fit f(z) -> q by the paper's loss from the scene's energy alone. Defaults per scene come from "
            "Table 1 (redsim.trainers.presets); flags override them. Writes OUT.pt + OUT.json (and OUT.fit.pt, "
            "the resumable training state). Ctrl-C saves the state; rerun with --resume to continue."
        ),
        epilog="Exit status: 0 done, 2 bad input, 3 the loss became NaN/inf, 130 interrupted (resumable).",
    )
    p.add_argument("scene", help="catalog name")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help="scene build parameter")
    fit_defaults = _fit_defaults()
    for flag, field, kind, text in _FIT_FLAGS:
        if kind is bool:
            default = "on" if fit_defaults[field] else "off"
            p.add_argument(
                flag,
                dest=field,
                action=argparse.BooleanOptionalAction,
                help=f"{text} (default: preset, else {default})",
            )
        else:
            p.add_argument(flag, dest=field, type=kind, default=None, help=f"{text} (default: scene preset)")
    p.add_argument("--periodic", default=None, metavar="I,J", help="latent indices that are angles")
    p.add_argument(
        "--soften", default=None, metavar="A,B", help="scene effects whose energy rises from --soften-from to full"
    )
    p.add_argument("--cond", action="store_true", help="fit a conditional subspace over the scene's conditions")
    p.add_argument("--seed", type=int, default=0, help="seed of the initialisation and sampling (default 0)")
    p.add_argument("--out", default=None, metavar="STEM", help="checkpoint stem (default SCENE_dD)")
    p.add_argument("--resume", action="store_true", help="continue from STEM.fit.pt")
    p.add_argument("--json", action="store_true", help="print the metadata as JSON (no progress bar)")
    p.set_defaults(func=_cmd_fit)

    p = sub.add_parser("inspect", help="print a checkpoint's metadata and metrics")
    p.add_argument("checkpoint", help="path to X.pt (X.json beside it)")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=_cmd_inspect)

    p = sub.add_parser("sample", help="export states sampled from a subspace (z ~ N(0, I))")
    p.add_argument("checkpoint", help="path to X.pt")
    p.add_argument("-n", type=int, default=1000, help="number of states (default 1000)")
    p.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    p.add_argument("--out", default="states.npz", help="output .npz with z, q, x (default states.npz)")
    p.add_argument("--json", action="store_true", help="print one JSON summary")
    p.set_defaults(func=_cmd_sample)

    p = sub.add_parser("animate", help="GIF of a cyclic Catmull-Rom keyframe loop in latent space")
    p.add_argument("checkpoint", help="path to X.pt")
    p.add_argument("--keys", type=int, default=4, help="number of random latent keyframes (default 4)")
    p.add_argument("--frames", type=int, default=48, help="frames in the loop (default 48)")
    p.add_argument("--fps", type=float, default=16.0, help="frames per second (default 16)")
    p.add_argument("--seed", type=int, default=0, help="keyframe seed (default 0)")
    p.add_argument("--out", default="anim.gif", help="output GIF (default anim.gif)")
    p.add_argument("--json", action="store_true", help="print one JSON summary")
    p.set_defaults(func=_cmd_animate)

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
    p.add_argument("--scenes", metavar="A,B,...", help="comma-separated scene names (default: all non-toy scenes)")
    p.add_argument("--repeats", type=int, default=20, help="timed calls per measurement (default 20)")
    p.add_argument("--batches", default="1,32", metavar="B1,B2", help="batch sizes (default 1,32)")
    p.add_argument("--dtypes", default="float64,float32", metavar="D1,D2", help="float64 and/or float32 (default both)")
    p.add_argument(
        "--budget",
        type=float,
        default=2.0,
        metavar="SECONDS",
        help="time per measurement; slow scenes get fewer repeats, at least 3 (default 2)",
    )
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    p.set_defaults(func=_cmd_bench_energy)

    p = bench.add_parser(
        "subspace",
        help="neural subspace vs linear modes vs modal derivatives",
        description=(
            "For each scene, take a neural subspace: DIR/SCENE.pt if it exists, else the one shipped with redsim "
            "(environment scenes), else fit one with the scene's preset into DIR/SCENE; with --steps N, "
            "DIR/SCENE_sN.pt or a fit of N steps. Build linear modes and modal derivatives of the same d and sigma, "
            "and print for each the energy of samples relative to the seed's (0: rest, 1: seed) and in J above the "
            "rest state, the metric stretch, the load-response error, (FEM) the non-rigid strain and (bistable_bar) "
            "how close the subspace comes to each buckled state."
        ),
    )
    p.add_argument("--scenes", metavar="A,B,...", help="comma-separated scenes (default: the eleven of Table 1)")
    p.add_argument("--steps", type=int, help="fit (or reuse) N-step subspaces instead (default: the presets')")
    p.add_argument("--checkpoints", default="subspaces", metavar="DIR", help="where fits are kept (default subspaces)")
    p.add_argument("--refit", action="store_true", help="fit even if a checkpoint exists (shipped ones included)")
    p.add_argument("--loads", type=int, default=8, help="loads of the load-response error (default 8)")
    p.add_argument(
        "--load-size",
        type=float,
        default=0.1,
        help="size of each load: its linear response along the handle's softest direction, as a fraction of the "
        "scene size (default 0.1; larger probes the nonlinear range)",
    )
    p.add_argument("--samples", type=int, default=256, help="latent samples per statistic (default 256)")
    p.add_argument("--seed", type=int, default=0, help="seed of fits, samples and loads (default 0)")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=_cmd_bench_subspace)

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
    p.add_argument("--scenes", metavar="A,B,...", help=f"comma-separated (default: {','.join(BENCH_FIT_SCENES)})")
    p.add_argument("--steps", type=int, default=20, help="timed steps per variant, over all rounds (default 20)")
    p.add_argument("--warmup", type=int, default=3, help="untimed steps per round, the compile included (default 3)")
    p.add_argument("--rounds", type=int, default=2, help="interleaved rounds of all variants (default 2)")
    p.add_argument("--batch", type=int, default=32, help="latent samples per step (default 32)")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    p.set_defaults(func=_cmd_bench_fit)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``redsim`` command line.

    Args:
        argv: Arguments without the program name (default: ``sys.argv[1:]``).

    Returns:
        The exit status (0 ok, 1 a scene failed to build, 2 bad input, 3 NaN in a simulation).
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as done:  # --help and --version
        return int(done.code or 0)
    except CliError as err:
        _error(str(err))
        return err.code
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="redsim: %(levelname)s: %(name)s: %(message)s",
    )
    try:
        return int(args.func(args))
    except CliError as err:
        _error(str(err))
        return err.code
