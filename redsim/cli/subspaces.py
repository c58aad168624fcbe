"""``redsim fit``, ``inspect``, ``sample`` and ``animate``: fitting a subspace and using its checkpoint."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import math
import shlex
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from redsim.cli.common import (
    EXIT_INTERRUPTED,
    EXIT_NAN,
    EXIT_OK,
    CliError,
    SceneNotRebuilt,
    add_scene_args,
    check_writable,
    error,
    file_name,
    finish_command,
    json_out,
    load_checkpoint,
    non_negative_seed,
    out,
    parse_list,
    scene_from_args,
    warn,
    warn_earlier_frames,
)
from redsim.interrupts import ForcedInterrupt

if TYPE_CHECKING:
    import torch

    from redsim.scene import Scene

# (flag, FitConfig field, type, help); the flags of `redsim fit` are generated from this table.
FIT_FLAGS: tuple[tuple[str, str, Any, str], ...] = (
    ("--dim", "latent_dim", int, "latent dimension d"),
    ("--sigma", "sigma", float, "target Lipschitz scale σ [sqrt(kg) m per unit z]"),
    ("--lam", "lam", float, "weight λ of the pair term"),
    ("--steps", "steps", int, "Adam steps (with --resume: the fit's own unless given; a larger N extends it)"),
    ("--batch", "batch_size", int, "latent samples per step"),
    ("--lr", "learning_rate", float, "initial learning rate (halved after each quarter)"),
    ("--width", "hidden_width", int, "MLP hidden width"),
    ("--layers", "hidden_layers", int, "MLP hidden layers"),
    ("--explore", "exploration_fraction", float, "fraction of the steps over which ρ rises 0 -> 1"),
    (
        "--seed-bias",
        "seed_bias",
        bool,
        "start the output bias at the seed state (stiff meshes; no effect with --modal, which starts it at rest)",
    ),
    ("--drive", "drive", float, "start stiffness [N/m] of the scene's fitting drivers (cranks); 0: off"),
    ("--drive-fraction", "drive_fraction", float, "--drive holds for half this fraction of the steps, then falls to 0"),
    ("--soften-from", "soften_from", float, "initial weight of the --soften effects"),
    ("--soften-fraction", "soften_fraction", float, "fraction of the steps over which that weight rises to 1"),
    ("--anchor", "anchor", float, "start stiffness [1/s^2] of the pull through the scene's reference states; 0: off"),
    ("--anchor-fraction", "anchor_fraction", float, "--anchor holds for half this fraction of the steps, then ends"),
    ("--modal", "modal", float, "start weight of the pull of the map's rest and tangent to the lowest modes; 0: off"),
    ("--modal-fraction", "modal_fraction", float, "--modal holds for half this fraction of the steps, then ends"),
    (
        "--anchor-map",
        "anchor_map",
        str,
        "none, md or modes: a fixed modal-derivative (or linear-mode) map plus an MLP "
        "stripped of its Taylor polynomial at z = 0",
    ),
    (
        "--anchor-map-cond",
        "anchor_map_cond",
        str,
        "conditional --anchor-map: each or default (where the MLP's Taylor polynomial is taken)",
    ),
    ("--anchor-radius", "anchor_radius", float, "R > 0: the --anchor-map polynomial fades out beyond |z| ~ R"),
    ("--mirror", "mirror", float, "weight [1/s^2] of the map's equivariance under the scene's mirror; 0: off"),
    (
        "--checkpoint-every",
        "checkpoint_every",
        int,
        "steps between resumable checkpoints; 0: only at the end and on Ctrl-C",
    ),
    ("--dtype", "dtype", str, "float32 or float64"),
    ("--device", "device", str, "torch device"),
    ("--fused-adam", "fused_adam", bool, "fused Adam (--no-fused-adam: plain Adam)"),
    ("--compile", "compile", bool, "torch.compile the loss: faster steps after a compile of tens of seconds"),
)
FIELD_FLAGS = {field: flag for flag, field, _kind, _help in FIT_FLAGS} | {
    "periodic": "--periodic",
    "conditional": "--cond",
    "soften": "--soften",
}
"""The `redsim fit` flag of every FitConfig field (validation messages name the flag)."""


def _fit_config(args: argparse.Namespace, scene_name: str) -> Any:
    from redsim.trainers.fit import FitConfig, FitConfigError
    from redsim.trainers.presets import preset

    fields = preset(scene_name)
    for _flag, field, _kind, _help in FIT_FLAGS:
        value = getattr(args, field)
        if value is not None:
            fields[field] = value
    if args.periodic is not None:
        try:
            fields["periodic"] = tuple(int(i) for i in parse_list(args.periodic, "--periodic"))
        except ValueError as err:
            raise CliError(f"--periodic must be comma-separated integers, got {args.periodic!r}") from err
    if args.soften is not None:
        fields["soften"] = tuple(parse_list(args.soften, "--soften"))
    if args.cond:
        fields["conditional"] = True
    _drop_preset_anchor_map(args, fields, scene_name)
    if fields.get("anchor_map", "none") == "none":  # the preset's taper goes with its anchored map (--anchor-map none)
        for field in ("anchor_radius", "anchor_map_cond"):
            if getattr(args, field) is None:
                fields.pop(field, None)
    try:
        return FitConfig(**fields)
    except FitConfigError as err:
        raise CliError(err.describe(FIELD_FLAGS)) from err


def _drop_preset_anchor_map(args: argparse.Namespace, fields: dict[str, Any], scene_name: str) -> None:
    """A preset's anchored map gives way to the options it cannot go with (``--modal``, ``--seed-bias``,
    ``--periodic``) when the user asks for one of them and not for ``--anchor-map``; says so on stderr."""
    asked = [
        flag
        for flag, on in (
            ("--modal", bool(args.modal)),
            ("--seed-bias", bool(args.seed_bias)),
            ("--periodic", args.periodic is not None),
        )
        if on
    ]
    anchored = (args.anchor_map, args.anchor_radius, args.anchor_map_cond)  # any of them asks for the anchored map
    if not asked or args.anchor_map is not None or fields.get("anchor_map", "none") == "none":
        return
    if any(a is not None for a in anchored):
        options = (("--anchor-radius", anchored[1]), ("--anchor-map-cond", anchored[2]))
        kept = " and ".join(flag for flag, value in options if value is not None)
        raise CliError(
            f"{' and '.join(asked)} cannot go with the {scene_name} preset's anchored map (--anchor-map "
            f"{fields['anchor_map']}), which {kept} asks to keep: drop {kept} (the MLP alone), or drop "
            f"{' and '.join(asked)} (the anchored map)"
        )
    verb = "replaces" if len(asked) == 1 else "replace"
    warn(f"{' and '.join(asked)} {verb} the {scene_name} preset's --anchor-map {fields['anchor_map']} (the MLP alone)")
    fields["anchor_map"] = "none"


def _check_stem(stem: Path, args: argparse.Namespace, scene: Scene | None = None) -> None:
    """Refuse a stem that names no file, or one that holds a fit, unless ``--resume`` or ``--overwrite`` (with
    ``scene``: a fit of another scene unless ``--overwrite``, whose ``--resume`` could not continue it)."""
    if stem.name in ("", ".", ".."):
        raise CliError(f"--out must name a checkpoint stem (e.g. DIR/NAME), got {args.out!r}")
    from redsim.trainers.fit import check_fit_files, existing_fit, other_scene_fit, recorded_fit_command

    try:
        check_fit_files(stem)
    except ValueError as err:
        raise CliError(str(err).replace("choose another out", "choose another --out")) from err
    found = existing_fit(stem)
    if found is None or args.overwrite:
        return
    if scene is not None and (why := other_scene_fit(stem, scene)) is not None:
        default = "" if args.out is not None else " (the default name for this scene and --dim, in this folder)"
        command = recorded_fit_command(stem) if args.resume else None
        resume = f"; to continue that fit, give its scene as it records: {command} --resume" if command else ""
        raise CliError(
            f"a fit of another scene is at {found}{default}: {why}. Write this fit elsewhere with --out STEM, or "
            f"replace that one with --overwrite{resume}"
        )
    if not args.resume:  # minutes to hours of work: not replaced silently
        raise CliError(
            f"a fit exists at {found}: continue it with --resume (a larger --steps extends it), replace it with "
            "--overwrite, or write this fit elsewhere with --out STEM"
        )


def _not_an_interrupt(record: logging.LogRecord) -> bool:
    return not record.getMessage().startswith("interrupted")


@contextlib.contextmanager
def _interrupts_said_once() -> Iterator[None]:
    """Drop the fitter's own "interrupted after step N; rerun with --resume ..." log warnings inside: :func:`cmd_fit`
    says it in one line, with the whole command that continues the fit (a Ctrl-C printed both)."""
    from redsim.trainers import fit_subspace

    logger = logging.getLogger(fit_subspace.__module__)
    logger.addFilter(_not_an_interrupt)
    try:
        yield
    finally:
        logger.removeFilter(_not_an_interrupt)


def cmd_fit(args: argparse.Namespace) -> int:
    from redsim.subspace import checkpoint_path
    from redsim.trainers import fit_subspace
    from redsim.trainers.fit import (
        FitStopped,
        ResumeSettingsError,
        fit_command,
        high_stretch_warning,
        low_stretch_warning,
        planned_steps,
        quiet_low_stretch,
        recorded_fit_command,
    )

    if args.resume and args.overwrite:
        raise CliError("give --resume (continue the fit at the stem) or --overwrite (replace it), not both")
    if args.out is not None:  # refused before the scene is built (a mesh's voxelization can take minutes)
        _check_stem(Path(args.out), args)
    unnamed = all(getattr(args, what, None) is None for what in ("scene", "mesh", "spec"))
    if args.resume and args.out is not None and unnamed and (command := recorded_fit_command(args.out)) is not None:
        raise CliError(f"--resume needs the fit's scene and settings as it records them: {command} --resume")
    scene = scene_from_args(args)
    config = _fit_config(args, scene.name)
    stem = (
        Path(args.out) if args.out is not None else Path(file_name(f"{scene.name}_d{config.latent_dim}"))
    )  # in this folder
    _check_stem(stem, args, scene)
    if args.resume and args.steps is None and (steps := planned_steps(stem)) is not None:
        config = dataclasses.replace(config, steps=steps)  # the fit's own length, not the preset's
    if args.stop_at is not None and not 0 <= args.stop_at < config.steps:  # the steps done: fit_subspace's check
        raise CliError(f"--stop-at must be >= 0 and < the fit's --steps ({config.steps}), got {args.stop_at}")
    command = fit_command(scene, config, args.seed, stem)
    try:
        with quiet_low_stretch(), _interrupts_said_once():  # said below in one line, with the options' names
            result = fit_subspace(
                scene,
                config,
                seed=args.seed,
                out=stem,
                resume=args.resume,
                overwrite=args.overwrite,
                progress=not args.json,
                command=command,
                stop_at=args.stop_at,
            )
    except FitStopped as stop:
        if args.json:
            json_out({"stopped_at": stop.step, "steps": config.steps, "training_state": str(stop.state)})
        else:
            out(f"stopped after step {stop.step} of {config.steps}; continue with: {command} --resume")
        return EXIT_OK
    except KeyboardInterrupt as stop:
        state = checkpoint_path(stem, ".fit.pt")
        forced = isinstance(stop, ForcedInterrupt)  # a second Ctrl-C inside a step: that step is not saved
        if state.is_file():
            where = " inside a step, saved before it" if forced else ""
            warn(f"interrupted{where}; the state is in {state}; continue with: {command} --resume")
        else:
            when = "inside a step before any state was saved" if forced else "before the fit's first step"
            warn(f"interrupted {when}; nothing was saved, rerun: {command}")
        return EXIT_INTERRUPTED
    except FloatingPointError as err:  # the last state saved stays; rerunning it would meet the same NaN
        state = checkpoint_path(stem, ".fit.pt")
        kept = f"; the last state saved stays in {state} (a rerun with other settings replaces it with --overwrite)"
        error(f"{err}{kept if state.is_file() else ''}")
        return EXIT_NAN
    except ResumeSettingsError as err:  # named by the flags that set them
        raise CliError(f"{err.path}: {err.describe(FIELD_FLAGS)}") from err
    except ValueError as err:  # bad resume state, conditional fit without conditions, ...
        raise CliError(str(err)) from err
    except RuntimeError as err:  # --compile without a C++ compiler (check_compiler); other errors go on up
        if "compile needs a C++ compiler" not in str(err):
            raise
        raise CliError(str(err).replace("or step without compile", "or fit without --compile")) from err
    meta = result.subspace.metadata
    summary = {"checkpoint": str(checkpoint_path(stem, ".pt")), "metadata": str(checkpoint_path(stem, ".json")), **meta}
    if args.json:
        json_out(summary)
    else:
        final = meta["final"]
        out(f"fitted {scene.name} (n={scene.free_dof_count}, d={config.latent_dim}) in {result.fit_seconds:.1f} s")
        out(
            f"final energy {final['energy']:.4g} J, pair term {final['pair']:.4g}, "
            f"mean metric stretch {final['stretch']:.4f}"
        )
        out(f"wrote {summary['checkpoint']} and {summary['metadata']}")
        if scene.handles:  # a short fit can leave a map too stiff to follow the loads; nothing above shows it
            # a mesh scene's own handles come after its whole-body one, which the bench would push by default
            own = scene.handle_names[1:] if "builder" in scene.params else ()
            handle = f" --handle {own[0]}" if own else ""
            others = f" (or --handle {' / '.join(own[1:])})" if len(own) > 1 else ""
            out(
                f"before training on it, compare it with the full space: redsim bench accuracy "
                f"{shlex.quote(summary['checkpoint'])}"
                f"{handle} --scenarios push --full none --no-study{others}"
            )
    final = meta["final"]
    message = low_stretch_warning(final["stretch"], config.sigma, flags=True) or high_stretch_warning(
        final["stretch"], config.sigma, final["energy"], flags=True
    )
    if message is not None:
        warn(message)
    if config.latent_dim > scene.free_dof_count:  # it fits, but no latent can add a motion the DOFs lack
        warn(
            f"d = {config.latent_dim} latents for {scene.name}'s n = {scene.free_dof_count} free DOFs: more latents "
            f"than the scene has DOFs (benches with modal baselines refuse such a map); --dim {scene.free_dof_count} "
            "or less is the usual choice"
        )
    return EXIT_OK


def cmd_inspect(args: argparse.Namespace) -> int:
    from redsim.subspace import read_metadata

    try:
        scene, sub = load_checkpoint(args.checkpoint)
        meta = {"checkpoint": args.checkpoint, "n": scene.free_dof_count, "latent_dim": sub.latent_dim, **sub.metadata}
    except SceneNotRebuilt as err:  # what inspect prints is in the .json: print it, and say what was not checked
        doc = read_metadata(args.checkpoint)
        config = doc.get("config") or {}
        meta = {"checkpoint": args.checkpoint, "n": config.get("output_dim"), "latent_dim": config.get("latent_dim")}
        meta |= {**doc, "scene_not_rebuilt": str(err)}
        warn(f"{err}; the metadata below is the .json's, the weights were not loaded")
    if args.json:
        json_out(meta)
        return EXIT_OK
    out(f"{args.checkpoint}: scene {meta.get('scene')} (n={meta['n']}), d={meta['latent_dim']}")
    fit = meta.get("fit") if isinstance(meta.get("fit"), dict) else {}  # a hand-edited .json: null, a number
    seconds = meta.get("fit_seconds")
    took = f"{seconds:.1f} s" if isinstance(seconds, int | float) else f"{seconds!r} s"
    out(
        f"  fit: sigma={fit.get('sigma')} lam={fit.get('lam')} steps={fit.get('steps')} seed={meta.get('seed')} "
        f"width={fit.get('hidden_width')} layers={fit.get('hidden_layers')} in {took}"
    )
    conditions = meta.get("conditions") if isinstance(meta.get("conditions"), list) else []
    if conditions:  # a conditional map: what f(z, c) takes, in its input order
        shown = [f"{c.get('name')} in [{c.get('low')}, {c.get('high')}]" for c in conditions if isinstance(c, dict)]
        out(f"  conditions: {', '.join(shown)}")
    if fit.get("anchor_map", "none") != "none":
        out(f"  anchor map: --anchor-map {fit.get('anchor_map')} --anchor-map-cond {fit.get('anchor_map_cond')}")
    final = meta.get("final") if isinstance(meta.get("final"), dict) else {}
    for key, value in final.items():
        out(f"  final {key}: {value:.5g}" if isinstance(value, int | float) else f"  final {key}: {value!r}")
    for key, value in (meta.get("metrics") or {}).items():
        if isinstance(value, (int, float)):
            out(f"  metric {key}: {value:.5g}")
    if "scene_not_rebuilt" in meta:  # a scene built in Python, a mesh file changed since: the warning above says
        out(f"  fit settings: {meta.get('command')} (not runnable as it is: the scene cannot be rebuilt as recorded)")
    else:
        out(f"  reproduce: {meta.get('command')}")
    return EXIT_OK


def _latent_samples(sub: Any, scene: Scene, count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Seeded latents [count, d] (and conditions [count, m]) in the map's dtype (a float64 fit's too)."""
    import torch

    from redsim.integrators import map_condition_dim, map_tensor
    from redsim.subspace import periodic_latents, sample_latents

    generator = torch.Generator().manual_seed(seed)
    z = sample_latents(count, sub.latent_dim, periodic_latents(sub), generator=generator)
    cond = None
    if map_condition_dim(sub):
        assert scene.condition_space is not None  # a conditional map was fitted to a conditional scene
        cond = scene.condition_space.sample(count, generator).float()
    like = map_tensor(sub)
    if like is None:
        return z, cond
    return z.to(like), None if cond is None else cond.to(like)


def cmd_sample(args: argparse.Namespace) -> int:
    if args.n < 1:
        raise CliError(f"-n must be an integer >= 1, got {args.n}")
    if args.meshes:  # before anything is written
        check_writable(args.meshes, "--meshes", folder=True)
        warn_earlier_frames(args.meshes, "--meshes")
    path = None
    if args.out is not None or not args.meshes:  # --meshes alone does not replace a states.npz written before
        path = Path("states.npz" if args.out is None else args.out)
        if path.name in ("", ".", ".."):
            raise CliError(f"--out must name a .npz file, got {args.out!r}")
        if path.suffix != ".npz":  # numpy's savez would add it
            path = path.with_name(path.name + ".npz")
    done = {"npz": False, "meshed": 0}  # what a Ctrl-C leaves: the .npz written, the samples whose meshes are
    try:
        return _sample(args, path, done)
    except KeyboardInterrupt:
        kept = [str(path)] if done["npz"] else []
        kept += [f"the meshes of {done['meshed']} of {args.n} samples in {args.meshes}"] if done["meshed"] else []
        said = f"after writing {' and '.join(kept)}" if kept else "before anything was written"
        warn(f"interrupted {said}; rerun: {args.command_line}")
        return EXIT_INTERRUPTED


def _sample(args: argparse.Namespace, path: Path | None, done: dict[str, Any]) -> int:
    """:func:`cmd_sample` after its checks: the .npz at ``path`` (None: none) and the meshes, counted in ``done``
    (``npz``: written, ``meshed``: the samples whose meshes are) for a Ctrl-C's message."""
    import numpy as np
    import torch

    from redsim.subspace import write_atomically

    scene, sub = load_checkpoint(args.checkpoint)
    z, cond = _latent_samples(sub, scene, args.n, args.seed)
    with torch.no_grad():
        q = sub(z, cond).double()
        x = scene.full_positions(q)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {"z": z.numpy(), "q": q.numpy(), "x": x.numpy()}
        if cond is not None:
            arrays["cond"] = cond.numpy()
        fields = {"scene": scene.name, "scene_fingerprint": scene.fingerprint(), **arrays}

        def save(tmp: Path) -> None:  # a file object: savez would add .npz to the temporary's name
            with tmp.open("wb") as file:
                np.savez_compressed(file, **fields)

        write_atomically(path, save)  # Ctrl-C while writing leaves the states.npz there before, not a broken one
        done["npz"] = True
    finite_rows = torch.isfinite(q).all(dim=1)
    finite = bool(finite_rows.all())
    meshes = []
    if args.meshes:
        from redsim.render import export_meshes

        for i in range(args.n):
            if finite_rows[i]:  # a state that is not finite has no mesh (export_meshes raised, a traceback)
                meshes += export_meshes(scene, q[i], args.meshes, i)
            done["meshed"] = i + 1
    summary = {"out": None if path is None else str(path), "count": args.n, "n": scene.free_dof_count, "finite": finite}
    summary["meshes"] = [str(m) for m in meshes]
    if args.json:
        json_out(summary)
    else:
        if path is not None:
            out(f"wrote {args.n} states of {scene.name} (q: [{args.n}, {scene.free_dof_count}], full x too) to {path}")
        if meshes:
            out(f"wrote {len(meshes)} meshes (.ply, faces included) to {args.meshes}")
    if not finite:
        bad = (~finite_rows).nonzero().flatten().tolist()
        warn(
            f"{len(bad)} of {args.n} sampled states are NaN or inf (the map's output; first: sample {bad[0]})"
            + ("; the .npz holds them as they are" if path is not None else "")
            + ("; they have no meshes" if args.meshes else "")
        )
    return EXIT_OK if finite else EXIT_NAN


def cmd_animate(args: argparse.Namespace) -> int:
    import torch

    from redsim.keyframes import catmull_rom_loop
    from redsim.render import MAX_GIF_FPS, MIN_GIF_FPS, animate_states

    if args.keys < 2 or args.frames < args.keys:
        raise CliError(f"need --keys >= 2 and --frames >= --keys, got {args.keys} and {args.frames}")
    # a GIF's frame time is whole 10 ms, at most 65535 of them; browsers play 10 ms as 100 ms
    if not (math.isfinite(args.fps) and MIN_GIF_FPS <= args.fps <= MAX_GIF_FPS):
        raise CliError(
            f"--fps must be a number of frames per second in [{MIN_GIF_FPS:.3g}, {MAX_GIF_FPS:g}], got {args.fps}"
        )
    try:  # the frames are drawn first, then the GIF written at once (write_atomically)
        scene, sub = load_checkpoint(args.checkpoint)
        if Path(args.out).suffix.lower() != ".gif":  # before the frames are drawn
            raise CliError(f"--out must name a .gif file, got {args.out!r}")
        keys, cond = _latent_samples(sub, scene, args.keys, args.seed)
        z = catmull_rom_loop(keys, args.frames)
        with torch.no_grad():
            q = sub(z, None if cond is None else cond[:1].expand(args.frames, -1)).double()
        bad = (~torch.isfinite(q).all(dim=1)).nonzero().flatten().tolist()
        if bad:  # animate_states refuses them (a ValueError traceback)
            error(
                f"{len(bad)} of {args.frames} frames are NaN or inf (the map's output; first: frame {bad[0]}); no GIF"
            )
            return EXIT_NAN
        path = animate_states(scene, list(q), args.out, fps=args.fps)
    except KeyboardInterrupt:
        before = f"; the {Path(args.out).name} there before is unchanged" if Path(args.out).exists() else ""
        warn(f"interrupted before {args.out} was written{before}; rerun: {args.command_line}")
        return EXIT_INTERRUPTED
    if args.json:
        json_out({"out": str(path), "frames": args.frames, "keys": keys.tolist()})
    else:
        out(f"wrote {args.frames} frames through {args.keys} latent keyframes to {path}")
    return EXIT_OK


def _fit_defaults() -> dict[str, Any]:
    from redsim.trainers import FitConfig

    return dataclasses.asdict(FitConfig())


def _add_fit_arguments(p: Any) -> None:
    """The options of ``redsim fit`` (added on first use: :meth:`redsim.cli.common.Parser.add_later`)."""
    add_scene_args(p)
    fit_defaults = _fit_defaults()
    for flag, field, kind, text in FIT_FLAGS:
        if kind is bool:
            default = "on" if fit_defaults[field] else "off"
            p.add_argument(
                flag,
                dest=field,
                action=argparse.BooleanOptionalAction,
                help=f"{text} (default: preset, else {default})",
            )
        else:
            default = fit_defaults[field]
            p.add_argument(flag, dest=field, type=kind, default=None, help=f"{text} (default: preset, else {default})")
    p.add_argument("--periodic", default=None, metavar="I,J", help="latent indices that are angles")
    p.add_argument(
        "--soften", default=None, metavar="A,B", help="scene effects whose energy rises from --soften-from to full"
    )
    p.add_argument("--cond", action="store_true", help="fit a conditional subspace over the scene's conditions")
    p.add_argument(
        "--seed", type=non_negative_seed, default=0, help="seed of the initialisation and sampling (default 0)"
    )
    p.add_argument("--out", default=None, metavar="STEM", help="checkpoint stem (default SCENE_dD)")
    p.add_argument("--resume", action="store_true", help="continue from STEM.fit.pt")
    p.add_argument(
        "--stop-at",
        type=int,
        default=None,
        metavar="N",
        help="stop when N steps are done, saving STEM.fit.pt as Ctrl-C does (exit 0; --resume continues)",
    )
    p.add_argument(
        "--overwrite", action="store_true", help="replace an existing fit at STEM (without it, one is refused)"
    )
    finish_command(p, cmd_fit, "print the metadata as JSON (no progress bar)")


def add_commands(sub: Any) -> None:
    """Add ``fit``, ``inspect``, ``sample`` and ``animate`` to the subcommands ``sub``."""
    p = sub.add_parser(
        "fit",
        help="fit a neural subspace to a scene (data-free)",
        description=(
            "Fit f(z) -> q by the paper's loss from the scene's energy alone. Defaults per scene come from "
            "Table 1 (redsim.trainers.presets); flags override them. Writes OUT.pt + OUT.json (and OUT.fit.pt, "
            "the resumable training state); an existing fit there is refused unless --resume or --overwrite. "
            "Ctrl-C (or --stop-at) saves the state; rerun with --resume to continue to the fit's own length, or with "
            "--resume and a larger --steps to extend a fit (the learning-rate schedule is recomputed for the new "
            "length and recorded in the .json, an interruption as --stop-at in its command; ρ keeps its first ramp, "
            "so a --steps that ends the fit before ρ reaches 1 is refused)."
        ),
        epilog=(
            "Exit status: 0 done (or stopped by --stop-at), 2 bad input, 3 the loss became NaN/inf, "
            "130 interrupted (resumable)."
        ),
    )
    p.add_later(_add_fit_arguments)  # its defaults' help needs FitConfig, whose module imports torch

    p = sub.add_parser(
        "inspect",
        help="print a checkpoint's metadata and metrics",
        description="Print a checkpoint's metadata; its scene (catalog or your mesh) is rebuilt from the .json.",
    )
    p.add_argument("checkpoint", help="path to X.pt (X.json beside it)")
    finish_command(p, cmd_inspect, "print one JSON document", threads=False)

    p = sub.add_parser(
        "sample",
        help="export states sampled from a subspace (z ~ N(0, I))",
        epilog="Exit status: 0 done, 2 bad input, 3 a sampled state is NaN or inf (warned; written to the .npz as it "
        "is, no mesh for it).",
    )
    p.add_argument("checkpoint", help="path to X.pt")
    p.add_argument("-n", type=int, default=1000, help="number of states (default 1000)")
    p.add_argument("--seed", type=non_negative_seed, default=0, help="sampling seed (default 0)")
    p.add_argument(
        "--out",
        help="output .npz with z, q, x (and cond: a conditional map's sampled conditions), scene and "
        "scene_fingerprint (default states.npz, or none when only --meshes is given)",
    )
    p.add_argument(
        "--meshes",
        metavar="DIR",
        help="write every sample's surfaces with their faces as DIR/frame_XXXX_<surface>.ply (trimesh)",
    )
    finish_command(p, cmd_sample, "print one JSON summary")

    p = sub.add_parser(
        "animate",
        help="GIF of a cyclic Catmull-Rom keyframe loop in latent space",
        epilog="Exit status: 0 done, 2 bad input, 3 a frame is NaN or inf (no GIF written).",
    )
    p.add_argument("checkpoint", help="path to X.pt")
    p.add_argument("--keys", type=int, default=4, help="number of random latent keyframes (default 4)")
    p.add_argument("--frames", type=int, default=48, help="frames in the loop (default 48)")
    p.add_argument(
        "--fps",
        type=float,
        default=20.0,
        help="frames per second, at most 50; a GIF stores frame times in 10 ms, so the rate played is 100 / "
        "round(100 / fps) (default 20)",
    )
    p.add_argument("--seed", type=non_negative_seed, default=0, help="keyframe seed (default 0)")
    p.add_argument("--out", default="anim.gif", help="output GIF (default anim.gif)")
    finish_command(p, cmd_animate, "print one JSON summary")
