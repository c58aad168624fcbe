"""``redsim train-agent ENV_ID`` and ``redsim eval-agent MODEL ENV_ID`` (logic in redsim.trainers.agents)."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from redsim.cli.common import (
    EXIT_INTERRUPTED,
    EXIT_OK,
    CliError,
    add_out_folder,
    finish_command,
    json_out,
    non_negative_seed,
    out,
    parse_env_args,
    parse_env_id,
    sb3_seed,
    warn,
    warn_if_out_of_date,
)


def _positive(value: int | None, flag: str) -> None:
    if value is not None and value < 1:
        raise CliError(f"{flag} must be >= 1, got {value}")


def _env_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """The env's keyword arguments: ``--env-arg KEY=VALUE`` pairs and ``--episode-steps``."""
    _positive(args.episode_steps, "--episode-steps")
    kwargs = parse_env_args(args.env_arg, [args.env_id])
    if args.episode_steps is not None:
        if "max_episode_steps" in kwargs:
            raise CliError("give the episode length once: --episode-steps or --env-arg max_episode_steps=N")
        kwargs["max_episode_steps"] = args.episode_steps
    return kwargs


def _add_env_args(parser: argparse.ArgumentParser, default: str = "the id's") -> None:
    parser.add_argument(
        "--episode-steps", type=int, metavar="N", help=f"truncate episodes at N steps (default: {default})"
    )
    parser.add_argument(
        "--env-arg",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="keyword argument of the env, VALUE a JSON literal (e.g. cubature=true, max_force=4.0); repeatable",
    )


def _model_file(given: str) -> Path:
    """MODEL of eval-agent: a model file, or a train-agent run folder (its ``model.zip``)."""
    path = Path(given)
    if path.is_dir():
        if not (path / "model.zip").is_file():
            # a run stopped hard before its first whole save keeps its best model and checkpoints
            found = sorted(str(p) for p in [*path.glob("*.zip"), *path.glob("checkpoints/*.zip")])
            hint = f"e.g. {', '.join(found[:3])}" if found else "it holds none"
            raise CliError(f"{path} is a folder without a model.zip: give a model file ({hint})")
        return path / "model.zip"
    return path


def _p_value(p: float | None) -> str:
    """A paired test's p-value, or – where it has none (one episode: ``--json`` gives null)."""
    return "– (one episode)" if p is None or math.isnan(p) else f"{p:.2g}"


def _line(name: str, result: dict[str, Any]) -> str:
    diverged = result.get("diverged_episodes", 0)
    return (
        f"{name:<9} return {result['mean_return']:9.2f} ± {result['std_return']:7.2f}   "
        f"success {100 * result['success_rate']:5.1f}% (of steps {100 * result['success_steps']:5.1f}%)   "
        f"({result['episodes']} episode{'s' * (result['episodes'] != 1)} from seed {result['seed']}"
        + (f"; {diverged} diverged" if diverged else "")
        + ")"
    )


def _warn_diverged(name: str, result: dict[str, Any]) -> None:
    """Warn (stderr, in --json runs too) where episodes of ``result`` (an ``Evaluation.as_dict()``) ended diverged."""
    diverged = result.get("diverged_episodes", 0)
    if diverged:
        warn(
            f"{name}: {diverged} of {result['episodes']} episodes ended diverged (info['diverged']: a step the stepper "
            "could not trust ended each; their returns and successes count only the steps up to it)"
        )


MAP_ARGS = ("subspace", "scene_params", "fit_options")
"""Env arguments that choose the subspace map, whose latent coordinates the observations are."""


def _warn_if_map_args_differ(trained_on: dict[str, Any], given: dict[str, Any]) -> None:
    """Warn (stderr) where eval-agent's ``--env-arg``s choose another map than the training env of a model that
    does not record its map (the shipped policies): the observations keep their shape, but are another map's latent
    coordinates, which the policy never saw."""
    changed = [key for key in MAP_ARGS if key in given and given[key] != trained_on.get(key)]
    if changed:
        warn(
            f"--env-arg {', '.join(changed)} differs from the model's training env ({trained_on or 'the defaults'}): "
            "the env may run another subspace map, whose latent coordinates (the observations) mean other states "
            "than those the policy learnt on"
        )


@contextlib.contextmanager
def _bar_on_stderr(shown: bool) -> Iterator[None]:
    """Draw SB3's progress bar on stderr while the block runs (where ``shown``). SB3 draws it with ``tqdm.rich``, on
    rich's global console, which writes to stdout, the command's result: ``redsim train-agent ... > run.txt`` held
    the bar's last frame, and a terminal saw it among the result lines. The console is set back afterwards (an
    in-process caller keeps its own); a new console also picks its colours for stderr (none in a file, none under
    ``NO_COLOR``)."""
    if not shown:
        yield
        return
    import rich

    console = rich.get_console()
    kept = dict(console.__dict__)
    rich.reconfigure(stderr=True)  # rich's way to replace its global console: the object stays, its settings change
    try:
        yield
    finally:
        console.__dict__ = kept


def cmd_train_agent(args: argparse.Namespace) -> int:
    from redsim.envs.sharded import ShardError
    from redsim.trainers.agents import TrainingInterrupted, train_agent

    args.env_id = parse_env_id(args.env_id)
    warn_if_out_of_date(args.env_id)
    for value, flag in (
        (args.steps, "--steps"),
        (args.n_envs, "--n-envs"),
        (args.eval_episodes, "--eval-episodes"),
        (args.final_episodes, "--final-episodes"),
        (args.eval_every, "--eval-every"),
    ):
        _positive(value, flag)
    bar = not args.json and not args.no_progress
    try:
        with _bar_on_stderr(bar):
            result = train_agent(
                args.env_id,
                args.out,
                algo=args.algo,
                steps=args.steps,
                seed=args.seed,
                n_envs=args.n_envs,
                eval_every=args.eval_every,
                eval_episodes=args.eval_episodes,
                final_episodes=args.final_episodes,
                resume=args.resume,
                overwrite=args.overwrite,
                progress_bar=bar,
                video=not args.no_video,
                env_kwargs=_env_kwargs(args),
                shards=args.shards,
                her=args.her,
            )
    except (ValueError, FileNotFoundError, ShardError) as err:
        raise CliError(str(err)) from err
    except TrainingInterrupted as stop:
        warn(f"{stop}; continue with the same command and --resume")
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:
        warn("interrupted before training started; nothing was saved")
        return EXIT_INTERRUPTED
    final = result.evaluation.as_dict()
    _warn_diverged("agent", final)
    files = sorted(str(p) for p in Path(args.out).iterdir() if p.is_file())
    if args.json:
        json_out(
            {
                "env_id": args.env_id,
                "algo": args.algo,
                "her": args.her,
                "steps": result.steps,
                "trained_now": result.trained,
                "wall_s": result.wall_s,
                "model": str(result.model_path),
                "final_evaluation": final,
                "files": files,
            }
        )
        return EXIT_OK
    replay = " with HER" if args.her else ""
    if result.trained == 0:  # --resume of a run already at --steps: only its final evaluation and files again
        out(
            f"{args.env_id}: the {args.algo.upper()}{replay} run in {args.out} is already at {result.steps} env steps "
            f"(--steps {args.steps}): nothing trained, its final evaluation and files made again"
        )
    elif result.trained < result.steps:  # a resumed run: this call's steps, then the run's
        out(
            f"{args.env_id}: {args.algo.upper()}{replay} trained {result.trained} env steps more "
            f"(the run: {result.steps} env steps in {result.wall_s:.0f} s)"
        )
    else:
        out(f"{args.env_id}: {args.algo.upper()}{replay} trained {result.steps} env steps in {result.wall_s:.0f} s")
    out(_line("agent", final))
    out(f"wrote {', '.join(Path(f).name for f in files)} in {args.out}")
    return EXIT_OK


def cmd_eval_agent(args: argparse.Namespace) -> int:
    from redsim.trainers.agents import (
        SpaceMismatchError,
        evaluate,
        load_agent,
        model_record,
        normalizer_path,
        shipped_policy,
    )

    args.env_id = parse_env_id(args.env_id)
    warn_if_out_of_date(args.env_id)
    _positive(args.episodes, "--episodes")
    given = _env_kwargs(args)
    try:
        path = shipped_policy(args.env_id) if args.model == "shipped" else _model_file(args.model)
        model = load_agent(path, env_id=args.env_id, algo=args.algo)
        trained_on = model_record(path, plain_algo=args.algo)["env_kwargs"] or {}
    except KeyError as err:
        raise CliError(err.args[0]) from err
    except (ValueError, FileNotFoundError) as err:
        raise CliError(str(err)) from err
    policies = {"agent": model, **({"random": "random", "scripted": "scripted"} if args.baselines else {})}
    env_kwargs = {**trained_on, **given}  # the env the model was trained on, with the arguments given on top
    if model.map is None:  # a model that records its map is checked against the env's own (evaluate)
        _warn_if_map_args_differ(trained_on, given)
    try:
        runs = {
            name: evaluate(
                args.env_id,
                policy,
                episodes=args.episodes,
                seed=args.seed,
                deterministic=not args.stochastic,
                env_kwargs=env_kwargs,
            )
            for name, policy in policies.items()
        }
    except SpaceMismatchError as err:
        raise CliError(f"{path}: {err}") from err
    except ValueError as err:  # the env's arguments (--env-arg), e.g. no episode limit to end an evaluation
        raise CliError(str(err)) from err
    rows = {name: run.as_dict() for name, run in runs.items()}
    # which observation statistics the policy acted through: a plain model's file beside it is optional
    normalization = None if model.normalizer is None else str(normalizer_path(path))
    for name in rows.keys() - {"agent"}:
        rows[name]["agent_above_p"], rows[name]["agent_better_episodes"] = runs["agent"].above(runs[name])
    for name, row in rows.items():
        _warn_diverged(name, row)
    if args.json:
        doc = {"env_id": args.env_id, "env_kwargs": env_kwargs, "model": args.model, "normalization": normalization}
        json_out({**doc, **rows})
        return EXIT_OK
    acting = "raw observations" if normalization is None else f"observations normalized by {normalization}"
    sampling = f"; actions sampled, seed {args.seed}" if args.stochastic else ""
    settings = "".join(f" {k}={json.dumps(v)}" for k, v in env_kwargs.items())
    env = f"{args.env_id} ({settings.strip()})" if settings else args.env_id
    out(f"{env}, {args.model} ({acting}{sampling}):")
    for name, row in rows.items():
        out(_line(name, row))
        if name != "agent":
            out(
                f"{'':<9} agent above {name}: paired one-sided t-test p = {_p_value(row['agent_above_p'])}, "
                f"better in {row['agent_better_episodes']} of {row['episodes']} episodes"
            )
    return EXIT_OK


def _add_train_arguments(p: Any) -> None:
    """The options of ``redsim train-agent`` (added on first use: :meth:`redsim.cli.common.Parser.add_later`)."""
    from redsim.trainers.agents import ALGOS

    p.add_argument("env_id", metavar="ENV_ID", help="a RedSim env id, e.g. RedSim/MiniChain-v0 (prefix redsim: fine)")
    p.add_argument("--algo", choices=ALGOS, default="sac", help="algorithm (default sac)")
    p.add_argument("--steps", type=int, default=20_000, help="total env steps (default 20000)")
    add_out_folder(p, "output folder (default agent)", default="agent")
    p.add_argument(
        "--seed", type=sb3_seed, default=0, help="seed of the algorithm and the envs, below 2**32 (default 0)"
    )
    p.add_argument("--n-envs", type=int, help="vector env copies (default: the table's)")
    p.add_argument(
        "--shards",
        type=int,
        default=1,
        help="worker processes stepping the training copies (default 1; redsim.envs.sharded: the same env on P cores)",
    )
    p.add_argument("--eval-every", type=int, metavar="STEPS", help="env steps between evaluations (default steps/10)")
    p.add_argument("--eval-episodes", type=int, default=10, help="episodes per evaluation (default 10)")
    p.add_argument(
        "--final-episodes", type=int, default=20, help="seeded episodes of the final evaluation (default 20)"
    )
    p.add_argument("--resume", action="store_true", help="continue the run in DIR up to --steps in all")
    p.add_argument(
        "--overwrite", action="store_true", help="replace a run already in DIR (refused without it or --resume)"
    )
    p.add_argument(
        "--her",
        action="store_true",
        help="hindsight experience replay (sac/td3, reach envs): train on the goal-conditioned env "
        "(redsim.envs.goal); evaluations score the env's own reward",
    )
    _add_env_args(p)
    p.add_argument("--no-video", action="store_true", help="skip policy.gif")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    finish_command(p, cmd_train_agent, "print one JSON summary", default_threads=1)


def _add_eval_arguments(p: Any) -> None:
    """The options of ``redsim eval-agent`` (added on first use)."""
    from redsim.trainers.agents import ALGOS

    p.add_argument(
        "model",
        metavar="MODEL",
        help="a model .zip written by redsim train-agent (or its run folder: its model.zip), or 'shipped' (redsim's "
        "own); evaluated on the env it was trained on (its recorded --env-arg and --episode-steps, with those given "
        "here on top)",
    )
    p.add_argument("env_id", metavar="ENV_ID", help="the env id the model was trained on (the prefix redsim: is fine)")
    p.add_argument(
        "--algo",
        choices=ALGOS,
        help="the algorithm of a plain SB3 model that redsim did not write (e.g. an example's), acting through the "
        "NAME_vecnormalize.pkl beside NAME.zip where it exists",
    )
    p.add_argument("--episodes", type=int, default=20, help="episodes (default 20)")
    p.add_argument("--seed", type=non_negative_seed, default=0, help="first episode seed (default 0)")
    p.add_argument("--baselines", action="store_true", help="also a random policy and the scripted controller")
    p.add_argument(
        "--stochastic",
        action="store_true",
        help="sample the policy's actions (SB3's predict(deterministic=False), seeded by --seed; TD3 acts alike "
        "either way) instead of its deterministic action",
    )
    _add_env_args(p, default="the model's training env's, else the id's")
    finish_command(p, cmd_eval_agent, "print one JSON document", default_threads=1)


def add_commands(sub: Any) -> None:
    """Add ``train-agent`` and ``eval-agent`` to the subcommands ``sub``."""
    p = sub.add_parser(
        "train-agent",
        help="train a stable-baselines3 agent on a RedSim env",
        description=(
            "Train an SB3 algorithm on ENV_ID through the native vector env, with the settings of "
            "redsim.trainers.agents.HYPERPARAMS. Writes OUT/model.zip (+ model_vecnormalize.pkl where the "
            "observations are normalized), best_model.zip, replay_buffer.pkl (SAC, TD3: tens of MB), checkpoints/, "
            "curve.csv, curve.png (evaluation return vs env steps and wall time), evaluations.npz, progress.csv "
            "(SB3's log; a resumed run adds progress-from-STEPS.csv), policy.gif and agent.json. --resume of a run "
            "already at --steps trains nothing and makes its final evaluation and files again."
        ),
    )
    p.add_later(_add_train_arguments)  # --algo's choices come from redsim.trainers.agents, which imports torch

    p = sub.add_parser(
        "eval-agent",
        help="mean return ± std and success rate of a trained agent",
        description=(
            "Run seeded episodes (seeds SEED .. SEED+EPISODES-1) of a model written by train-agent on ENV_ID "
            "(MODEL 'shipped': the policy shipped with redsim for ENV_ID; --algo: any SB3 model of that algorithm); "
            "with --baselines, the same episodes with a random policy and with the task's scripted controller. "
            "Episodes that ended diverged (info['diverged']) are counted on each line and in --json "
            "('diverged_episodes') and warned about on stderr."
        ),
    )
    p.add_later(_add_eval_arguments)  # --algo's choices come from redsim.trainers.agents, which imports torch


__all__ = ["add_commands"]
