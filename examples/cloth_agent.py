"""Train an agent to move a free corner of a pinned sheet with the trainers helper: curve, GIF, checkpoints, resume.

Run: python examples/cloth_agent.py [--steps 20000] [--episode-steps N] [--out DIR] [--resume | --overwrite]
[--no-progress]
It trains half the budget, then resumes the same run to the full budget, in DIR/hanging_cloth (default
runs/hanging_cloth): the same as `redsim train-agent RedSim/HangingCloth-v0 --algo sac --steps 20000 --out
runs/hanging_cloth`. Stopped by Ctrl-C, the run is saved; `--resume` goes on from it. A folder that holds a run
is refused unless `--resume` continues it or `--overwrite` replaces it. Gymnasium warns that HangingCloth-v0 is
out of date: v1 and v2 are its cubature versions, v0 steps every element (README "Gymnasium environments").
main()'s defaults are the tiny budget the test suite runs.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from redsim.trainers.agents import TrainingInterrupted, check_run_folder, evaluate, load_agent, train_agent

ENV_ID = "RedSim/HangingCloth-v0"


def main(
    out: Path | None = None,
    steps: int = 48,
    episode_steps: int | None = 8,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = False,
) -> dict[str, float]:
    limit = {} if episode_steps is None else {"max_episode_steps": episode_steps}
    tiny = steps < 1000
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(out or tmp) / "hanging_cloth"
        options = {"n_envs": 4, "eval_every": steps, "eval_episodes": 2, "final_episodes": 2} if tiny else {}
        half = None
        if not resume:  # half the budget first, as if the run had been stopped there ...
            half = train_agent(
                ENV_ID,
                folder,
                algo="sac",
                steps=steps // 2,
                env_kwargs=limit,
                video=False,
                progress_bar=progress,
                overwrite=overwrite,
                **options,
            )
        # ... then the same call with resume=True goes on to `steps` (from model.zip and its replay buffer)
        full = train_agent(
            ENV_ID, folder, algo="sac", steps=steps, env_kwargs=limit, resume=True, progress_bar=progress, **options
        )
        files = sorted(p.name for p in folder.iterdir())
        # wall_s counts every run into the folder: the first half's time is in it, also after --resume
        print(f"{ENV_ID}: {full.steps} env steps in {full.wall_s:.0f} s in all; files: {', '.join(files)}")
        model = load_agent(folder / "model.zip", ENV_ID)  # refuses a model trained on another env
        # the final evaluation's episodes again: as many copies in one batch, so the float32 solves round alike
        # (another batch size moves a return in the fourth digit: docs/agents.md, "From the README: eval-agent's
        # digits")
        episodes = full.evaluation.returns.size
        again = evaluate(ENV_ID, model, episodes=episodes, seed=full.evaluation.seed, env_kwargs=limit)
        final = full.evaluation
        print(
            f"final evaluation, {episodes} episodes: return {final.mean:.2f} ± {final.returns.std():.2f}, success "
            f"{100 * final.successes.mean():.0f}%; the reloaded model {again.mean:.2f}"
        )
        return {
            "half_steps": float("nan") if half is None else half.steps,
            "steps": full.steps,
            "budget": steps,
            "final_return": full.evaluation.mean,
            "reloaded_return": again.returns[:2].mean(),
            "final_first_two": full.evaluation.returns[:2].mean(),
            "curve": float((folder / "curve.csv").is_file() and (folder / "curve.png").is_file()),
            "gif": float((folder / "policy.gif").is_file()),
        }


def check(result: dict[str, float]) -> None:
    """What this example must show: the run resumed to its full budget, wrote its curve and GIF, and reloads."""
    assert result["steps"] >= result["budget"] and not result["half_steps"] >= result["steps"]
    assert result["curve"] == 1.0 and result["gif"] == 1.0
    assert abs(result["reloaded_return"] - result["final_first_two"]) < 1e-6  # same seeds, deterministic policy


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="Train SAC on RedSim/HangingCloth-v0 with redsim.trainers")
    parser.add_argument("--steps", type=int, default=20_000, help="env steps in all (default 20000)")
    parser.add_argument("--episode-steps", type=int, help="steps per episode (default: the env's limit)")
    parser.add_argument(
        "--out", type=Path, default=Path("runs"), help="the run goes to OUT/hanging_cloth (default runs)"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bars while training")
    what = parser.add_mutually_exclusive_group()
    what.add_argument("--resume", action="store_true", help="continue the run in OUT/hanging_cloth to --steps")
    what.add_argument("--overwrite", action="store_true", help="replace the run in OUT/hanging_cloth")
    args = parser.parse_args()
    if args.steps < 2:  # half of it runs first
        parser.error(f"--steps must be an integer >= 2, got {args.steps}")
    if args.episode_steps is not None and args.episode_steps < 1:
        parser.error(f"--episode-steps must be an integer >= 1, got {args.episode_steps}")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out} is a file, not a folder")
    try:  # a run already in the folder: --resume or --overwrite
        check_run_folder(args.out / "hanging_cloth", args.resume, args.overwrite)
    except ValueError as err:
        parser.error(str(err))
    try:
        check(main(args.out, args.steps, args.episode_steps, args.resume, args.overwrite, not args.no_progress))
    except TrainingInterrupted as stop:  # the model, buffer and curve are saved
        print(f"{stop}; continue with the same command and --resume", file=sys.stderr)
        sys.exit(130)
    except KeyboardInterrupt:
        print("interrupted before training started; nothing was saved", file=sys.stderr)
        sys.exit(130)
