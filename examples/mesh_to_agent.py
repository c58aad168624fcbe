"""From a mesh file to a trained agent: build a cloth scene, fit its subspace, wrap it in an env, train SAC.

Run: python examples/mesh_to_agent.py [--fit-steps 3000] [--steps 20000] [--episode-steps 200] [--out DIR]
[--resume | --overwrite] [--no-progress]
The mesh here is a small square sheet written to DIR/my_sheet/sheet.obj, standing in for your file; its top
edge is pinned, and the agent pulls the sheet (handle "cloth") to targets the subspace can reach.
Everything goes to DIR/my_sheet (default runs/my_sheet): the mesh, the fitted map (subspace.pt, .json; `redsim inspect
DIR/my_sheet/subspace.pt` rebuilds its scene) and the agent's run.
Stopped by Ctrl-C while training, the run is saved and `--resume` goes on from it in the same map; a folder that
holds a run is refused unless `--resume` continues it or `--overwrite` fits and trains anew.
main()'s defaults are the tiny budget the test suite runs (a subspace that small is not a good one).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import trimesh

import redsim
from redsim.trainers import fit_subspace
from redsim.trainers.agents import TrainingInterrupted, check_run_folder, evaluate, train_agent


def sheet(size: float = 0.4, cells: int = 5) -> trimesh.Trimesh:
    """A square sheet [m] in the x-y plane, ``cells`` x ``cells`` squares of two triangles."""
    u = np.linspace(0.0, size, cells + 1)
    vertices = np.array([[x, y, 0.0] for y in u for x in u])
    faces = []
    for j in range(cells):
        for i in range(cells):
            a = j * (cells + 1) + i
            faces += [[a, a + 1, a + cells + 2], [a, a + cells + 2, a + cells + 1]]
    return trimesh.Trimesh(vertices, np.array(faces), process=False)


def check_folder(folder: Path, resume: bool, overwrite: bool) -> None:
    """Refuse a folder that holds a run or its map, unless ``resume`` continues it or ``overwrite`` replaces it."""
    check_run_folder(folder, resume, overwrite)
    fitted = folder / "subspace.pt"
    if fitted.is_file() and not (resume or overwrite):
        raise ValueError(f"{folder} holds a fitted map: continue its run with --resume or replace it with --overwrite")
    if resume and (folder / "model.zip").is_file() and not fitted.is_file():
        raise ValueError(f"{folder} holds an agent but not the map it was trained in (subspace.pt): use --overwrite")


def main(
    out: Path | None = None,
    fit_steps: int = 60,
    steps: int = 100,
    resume: bool = False,
    overwrite: bool = False,
    episode_steps: int = 20,
    progress: bool = False,
) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(out or tmp) / "my_sheet"
        fitted = folder / "subspace.pt"
        check_folder(folder, resume, overwrite)  # before a fit could replace the run's map
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / "sheet.obj"  # beside the map, whose .json names it: `redsim inspect` rebuilds the scene
        sheet().export(path)
        scene = redsim.scenes.cloth_scene_from_mesh(path, pin="max_y", name="my_sheet")
        losses = [0.0]
        if resume and fitted.is_file():
            subspace = redsim.load_subspace(fitted, scene=scene)  # the map the agent has been trained in
        else:
            fit = fit_subspace(scene, dim=3, sigma=0.05, lam=1.0, steps=fit_steps, progress=progress)
            print(f"{scene.name}: n = {scene.free_dof_count}, fitted d = 3 in {fit.fit_seconds:.1f} s")
            subspace, losses = fit.subspace, [h["loss"] for h in fit.history]
            subspace.save(folder / "subspace")

        env = redsim.envs.make(scene, subspace, task="reach", max_episode_steps=episode_steps)  # --resume: the same
        tiny = {"n_envs": 2, "eval_every": steps, "eval_episodes": 2, "final_episodes": 2} if steps < 1000 else {}
        settings = {"overrides": {"learning_starts": 50}, "resume": resume, "overwrite": overwrite, **tiny}
        result = train_agent(env, folder, algo="sac", steps=steps, progress_bar=progress, **settings)
        episodes = result.evaluation.returns.size  # the random policy on the agent's own evaluation episodes
        random = evaluate(env, "random", episodes=episodes, seed=result.evaluation.seed)
        print(
            f"{episodes} episodes: agent return {result.evaluation.mean:.2f}, success "
            f"{100 * result.evaluation.successes.mean():.0f}%; random {random.mean:.2f}, "
            f"{100 * random.successes.mean():.0f}% ({result.steps} steps)"
        )
        with torch.no_grad():  # the map must span shapes, or the env could not move
            spread = subspace(torch.randn(16, 3, generator=torch.Generator().manual_seed(0))).std(dim=0).max()
        return {
            "losses_finite": float(np.isfinite(losses).all()),
            "spread": float(spread),
            "steps": result.steps,
            "budget": steps,
            "agent": result.evaluation.mean,
            "random": random.mean,
            "model": float(result.model_path.is_file()),
        }


def check(result: dict[str, float]) -> None:
    """What this example must show: the fit spans shapes, and the agent trained on the user's env and saved."""
    assert result["losses_finite"] == 1.0 and result["spread"] > 1e-4  # [m]: different z, different sheets
    assert result["steps"] >= result["budget"] and result["model"] == 1.0
    assert np.isfinite([result["agent"], result["random"]]).all()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="Mesh -> subspace -> env -> SAC agent")
    parser.add_argument("--fit-steps", type=int, default=3000, help="steps of the subspace fit (default 3000)")
    parser.add_argument("--steps", type=int, default=20_000, help="SAC's env steps (default 20000)")
    parser.add_argument("--out", type=Path, default=Path("runs"), help="everything goes to OUT/my_sheet (default runs)")
    parser.add_argument("--episode-steps", type=int, default=200, help="steps per episode (default 200)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars while fitting and training")
    what = parser.add_mutually_exclusive_group()
    what.add_argument("--resume", action="store_true", help="continue the run in OUT/my_sheet, in its map")
    what.add_argument("--overwrite", action="store_true", help="fit and train anew in OUT/my_sheet")
    args = parser.parse_args()
    for flag, value in (
        ("--fit-steps", args.fit_steps),
        ("--steps", args.steps),
        ("--episode-steps", args.episode_steps),
    ):
        if value < 1:  # before the fit (it was saved, and the run refused after it)
            parser.error(f"{flag} must be an integer >= 1, got {value}")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out} is a file, not a folder")
    try:  # a run already in the folder: --resume or --overwrite
        check_folder(args.out / "my_sheet", args.resume, args.overwrite)
    except ValueError as err:
        parser.error(str(err))
    try:
        check(
            main(
                args.out,
                args.fit_steps,
                args.steps,
                args.resume,
                args.overwrite,
                args.episode_steps,
                not args.no_progress,
            )
        )
    except TrainingInterrupted as stop:  # the model, buffer and curve are saved beside the map
        print(f"{stop}; continue with the same command and --resume", file=sys.stderr)
        sys.exit(130)
    except KeyboardInterrupt:
        print("interrupted before training started; nothing was saved", file=sys.stderr)
        sys.exit(130)
    except ValueError as err:  # e.g. a run already in the folder: --resume or --overwrite
        parser.error(str(err))
