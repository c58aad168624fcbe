"""Cubature: weights, exactness on identical elements, error vs elements, refusal of other maps, runtime use."""

from __future__ import annotations

import copy
import functools
import itertools
import json
import math
import pickle

import pytest
import torch

from redsim import pretrained, scenes
from redsim.cubature import (
    AffineOutput,
    Cubature,
    CubatureConfig,
    CubatureEnergy,
    build_cubature,
    cubature_energy,
    load_cubature,
)
from redsim.cubature.bench import held_out_errors
from redsim.cubature.fit import LINEAR_KINDS
from redsim.effects.elastic import StVKMembrane
from redsim.runtime import LatentStepper, MapEnergy, ReducedInertia
from redsim.scene import SceneBuilder
from redsim.subspace import CheckpointError, LinearSubspace, SubspaceConfig, SubspaceMap

QUICK = {"samples": 48, "episodes": 0}


def _identical_triangles(count: int = 12):
    """``count`` disjoint copies of one triangle (one StVK element each) and a linear map moving all alike."""
    rest = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]], dtype=torch.float64)
    b = SceneBuilder(dim=3)
    shift = torch.arange(count, dtype=torch.float64)[:, None, None] * torch.tensor([0.5, 0.0, 0.0])
    ids = b.add_particles((rest + shift).reshape(-1, 3), torch.full((3 * count,), 0.01))
    dofs = b.particle_dofs(ids).reshape(count, 3, 3)
    b.add_effect(StVKMembrane("membrane", dofs, (rest + shift), 1e4, 0.3))
    scene = b.finalize("identical_triangles", params={"count": count})
    pattern = 0.02 * torch.randn(9, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    f = LinearSubspace(pattern.repeat(count, 1), scene.q_seed.clone())
    return scene, f


def _toy_cloth_map(seed: int = 0):
    scene = scenes.build("toy_small_cloth")
    torch.manual_seed(seed)
    f = SubspaceMap(SubspaceConfig(latent_dim=3, output_dim=scene.free_dof_count, hidden_width=32, hidden_layers=2))
    with torch.no_grad():
        f.mlp[-1].weight.mul_(0.05)
        f.mlp[-1].bias.copy_(scene.q_seed.to(torch.float32))
    return scene, f


def test_weights_are_non_negative_and_the_file_round_trips(tmp_path) -> None:
    scene, f = _toy_cloth_map()
    cub = build_cubature(scene, f, CubatureConfig(elements=6, **QUICK))
    modes = {r.name: r.mode for r in cub.rules}
    assert modes == {"membrane": "cubature", "bending": "cubature", "gravity": "linear"}
    for rule in cub.rules:
        assert bool((rule.weights >= 0).all())
        assert rule.indices.numel() <= (6 if rule.mode == "cubature" else rule.element_count)
    path = cub.save(tmp_path / "cloth")
    assert path.name == "cloth.cubature.json"
    back = load_cubature(tmp_path / "cloth.pt", scene, f)
    assert [r.indices.tolist() for r in back.rules] == [r.indices.tolist() for r in cub.rules]
    assert [r.weights.tolist() for r in back.rules] == [r.weights.tolist() for r in cub.rules]


def test_exact_on_identical_elements_in_identical_states() -> None:
    scene, f = _identical_triangles(12)
    cub = build_cubature(scene, f, CubatureConfig(elements=4, **QUICK))
    (rule,) = cub.rules
    assert rule.mode == "cubature"
    # one element stands for all twelve (the fit is exact, so the selection stops there); weights all equal
    assert rule.indices.numel() == 1
    assert torch.allclose(rule.weights, torch.full_like(rule.weights, 12.0 / rule.weights.numel()), rtol=1e-9)
    assert cub.summary["held_out_error"] < 1e-9
    energy = CubatureEnergy(scene, f, cub, dtype=torch.float64)
    z = torch.randn(5, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    full, _ = MapEnergy(scene, f, dtype=torch.float64).energy(z, None)
    approx, _ = energy.energy(z, None)
    assert torch.allclose(approx, full, rtol=1e-10, atol=1e-12)


def test_error_falls_as_elements_are_added() -> None:
    scene, f = _toy_cloth_map()
    errors = []
    for k in (1, 4, 16):
        cub = build_cubature(scene, f, CubatureConfig(elements=k, full=(), **QUICK))
        errors.append(cub.summary["train_error"])
        history = [h[1] for r in cub.rules for h in r.history[-1:]]
        assert all(e >= 0 for e in history)
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.5 * errors[0]


def test_a_cubature_for_another_map_or_scene_is_refused(tmp_path) -> None:
    scene, f = _toy_cloth_map(0)
    cub = build_cubature(scene, f, CubatureConfig(elements=4, **QUICK))
    cub.save(tmp_path / "cloth")
    _, other = _toy_cloth_map(1)
    with pytest.raises(CheckpointError, match=r"another map.*make one for this map with `redsim cubature CHECKPOINT"):
        load_cubature(tmp_path / "cloth", scene, other)
    with pytest.raises(CheckpointError, match="another map"):
        CubatureEnergy(scene, other, cub)
    stiffer = scenes.build("toy_small_cloth", young=2e5)
    with pytest.raises(CheckpointError, match="scene"):
        load_cubature(tmp_path / "cloth", stiffer, f)
    # the same map in float64 is the same map
    CubatureEnergy(scene, f.to(torch.float64), cub)
    # a map of the user's own takes its cubature through the factory the README names
    stepper = LatentStepper(scene, f, 0.02, energy=functools.partial(cubature_energy, source=tmp_path / "cloth.pt"))
    assert isinstance(stepper.energy, CubatureEnergy)


def test_bad_input_is_a_clear_error(tmp_path) -> None:
    scene, f = _toy_cloth_map()
    with pytest.raises(ValueError, match="elements"):
        CubatureConfig(elements=0)
    for tol in (-1.0, 0.0, 1.0, 2.0):  # a relative force error of 1 is what keeping no element gives
        with pytest.raises(
            ValueError, match=r"tol must be a relative error of the reduced forces and energy in \(0, 1\)"
        ):
            CubatureConfig(tol=tol)
    with pytest.raises(ValueError, match="held_out"):
        CubatureConfig(held_out=1.0)
    with pytest.raises(ValueError, match="no effect"):
        build_cubature(scene, f, CubatureConfig(full=("nope",), **QUICK))
    with pytest.raises(ValueError, match="both in full"):
        CubatureConfig(full=("membrane",), subsample=("membrane",))
    linear = next(e.name for e in scene.effects if e.kind in LINEAR_KINDS)
    with pytest.raises(ValueError, match="linear"):
        build_cubature(scene, f, CubatureConfig(subsample=(linear,), **QUICK))
    with pytest.raises(ValueError, match="affine output"):
        AffineOutput(torch.nn.Linear(3, 3))
    with pytest.raises(CheckpointError, match="no cubature file"):
        Cubature.load(tmp_path / "missing")
    (tmp_path / "bad.cubature.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="corrupt"):
        Cubature.load(tmp_path / "bad")


def test_an_unconditional_map_of_a_conditional_scene_gets_a_cubature() -> None:
    """The runtime steps a map without condition inputs (modal analysis) on the conditional bar; the fit passed the
    sampled conditions into the map as well as into the effects, and the map refused them."""
    from redsim.baselines import modal_analysis

    scene = scenes.build("conditional_bar")
    f = modal_analysis(scene, 3, sigma=0.05, rest=scene.q_seed.clone())
    cub = build_cubature(scene, f, CubatureConfig(elements=20, samples=8, episodes=0))
    assert cub.kept > 0 and math.isfinite(cub.summary["held_out_error"])
    LatentStepper(scene, f, 0.02, energy=CubatureEnergy(scene, f, cub))


def test_an_effect_idle_on_every_state_reports_its_real_error_and_no_split_leaves_a_side_empty() -> None:
    """A contact that never touches (its sphere 100 m away) keeps no element; its error is 0, as keeping none
    is exact there (it was reported as 1.0). A held-out share that rounds to every state leaves one to train on
    (a ZeroDivisionError before)."""
    from redsim.effects.penalty import FrameSet, SDFContact
    from redsim.effects.sdf import Sphere

    count = 6
    rest = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]], dtype=torch.float64)
    shift = torch.arange(count, dtype=torch.float64)[:, None, None] * torch.tensor([0.5, 0.0, 0.0])
    b = SceneBuilder(dim=3)
    ids = b.add_particles((rest + shift).reshape(-1, 3), torch.full((3 * count,), 0.01))
    b.add_effect(StVKMembrane("membrane", b.particle_dofs(ids).reshape(count, 3, 3), rest + shift, 1e4, 0.3))
    far = torch.eye(3, 4, dtype=torch.float64)
    far[1, 3] = 100.0
    b.add_effect(SDFContact("contact", b.particle_points(ids), FrameSet.world(far, 3 * count), Sphere(0.1), 1e3))
    scene = b.finalize("far_contact", params={"count": count})
    pattern = 0.02 * torch.randn(9 * count, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    f = LinearSubspace(pattern, scene.q_seed.clone())
    cub = build_cubature(scene, f, CubatureConfig(elements=4, samples=16, episodes=0, subsample=("contact",)))
    contact = next(r for r in cub.rules if r.name == "contact")
    assert contact.indices.numel() == 0 and contact.train_error == contact.held_out_error == 0.0
    for samples, held_out in ((4, 0.9), (2, 0.75)):
        cub = build_cubature(scene, f, CubatureConfig(elements=2, samples=samples, episodes=0, held_out=held_out))
        assert cub.summary["held_out_states"] == samples - 1 and math.isfinite(cub.summary["train_error"])


@pytest.mark.parametrize(
    ("field", "value", "expected"),
    [
        ("weights", math.nan, r"weights must be finite \(in float32\) and >= 0, got nan at position 0"),
        ("weights", 1e300, r"weights must be finite \(in float32\) and >= 0, got 1e\+300 at position 0"),
        ("weights", -1.0, r"weights must be finite \(in float32\) and >= 0, got -1.0 at position 0"),
        ("indices", 999, r"indices must lie in \[0, \d+\) \(its element_count\), got 999 at position 0"),
        ("indices", -1, r"indices must lie in \[0, \d+\) \(its element_count\), got -1 at position 0"),
        ("indices", 0.5, r"indices must be integers, got 0.5 at position 0"),  # read as element 0 before
        ("indices", True, r"indices must be integers, got True at position 0"),  # read as element 1 before
    ],
)
def test_a_tampered_cubature_file_is_refused_at_load(tmp_path, field: str, value: float, expected: str) -> None:
    scene, f = _toy_cloth_map()
    path = build_cubature(scene, f, CubatureConfig(elements=4, **QUICK)).save(tmp_path / "cloth")
    doc = json.loads(path.read_text())
    rule = next(r for r in doc["rules"] if r["mode"] == "cubature")
    rule[field][0] = value
    path.write_text(json.dumps(doc))
    with pytest.raises(CheckpointError, match=rf"cloth.cubature.json: effect '{rule['name']}': .*{expected}"):
        Cubature.load(tmp_path / "cloth")


def test_a_cubature_file_that_reduces_a_nonlinear_effect_as_linear_is_refused(tmp_path) -> None:
    """A rule's mode "linear" makes the energy r . c + e0 from the effect's value and gradient at r = 0: a membrane
    marked so (a hand-edited file) loaded and stepped a wrong energy without a word."""
    scene, f = _toy_cloth_map()
    path = build_cubature(scene, f, CubatureConfig(elements=4, **QUICK)).save(tmp_path / "cloth")
    doc = json.loads(path.read_text())
    rule = next(r for r in doc["rules"] if r["name"] == "membrane")
    rule.update(mode="linear", indices=None, weights=None)
    path.write_text(json.dumps(doc))
    with pytest.raises(CheckpointError, match=r"cloth.cubature.json: effect 'membrane' is reduced as linear, but its"):
        load_cubature(tmp_path / "cloth", scene, f)


def test_a_cubature_file_with_two_rules_for_one_effect_is_refused(tmp_path) -> None:
    """A file with a second rule for the membrane (a hand-merged file) loaded, passed the check against the scene's
    effects (compared by name) and stepped with the last of the two, the other ignored without a word."""
    scene, f = _toy_cloth_map()
    path = build_cubature(scene, f, CubatureConfig(elements=4, **QUICK)).save(tmp_path / "cloth")
    doc = json.loads(path.read_text())
    rule = next(r for r in doc["rules"] if r["name"] == "membrane")
    doc["rules"].append({**rule, "weights": [2.0 * w for w in rule["weights"]]})
    path.write_text(json.dumps(doc))
    with pytest.raises(CheckpointError, match=r"cloth.cubature.json: effect 'membrane' has 2 rules, not one: the"):
        load_cubature(tmp_path / "cloth", scene, f)


def _shipped(name: str):
    """The catalog scene ``name`` and its shipped map."""
    scene = scenes.build(name)
    return scene, pretrained.load(name, scene)


@pytest.fixture(scope="module")
def mini_chain():
    return _shipped("mini_chain")


def test_all_element_cubature_steps_like_the_map_energy(mini_chain) -> None:
    """Every effect kept whole: the reduced inertia (W^T M W in r) must give the same steps as all of q."""
    scene, f = mini_chain
    cub = build_cubature(scene, f, CubatureConfig(elements=1000, **QUICK))
    assert {r.mode for r in cub.rules} <= {"full", "linear"}
    energy = CubatureEnergy(scene, f, cub, dtype=torch.float64)
    assert isinstance(energy, ReducedInertia) and not isinstance(MapEnergy(scene, f), ReducedInertia)
    reduced = LatentStepper(scene, f, 0.02, dtype=torch.float64, energy=energy)
    full = LatentStepper(scene, f, 0.02, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"hessian='gauss_newton' needs an energy with q_energy.*CubatureEnergy"):
        LatentStepper(scene, f, 0.02, dtype=torch.float64, energy=energy, hessian="gauss_newton")  # not at a step
    z = reduced.rest_latent().expand(3, -1).clone()
    loads = 0.5 * torch.randn(3, len(scene.handles), scene.dim, generator=torch.Generator().manual_seed(0))
    a = b = c = d = z
    for _ in range(8):
        (na, sa), (nc, sc) = full.step(a, b, loads.double()), reduced.step(c, d, loads.double())
        a, b, c, d = na, a, nc, c
        assert bool(sa.converged.all()) and bool(sc.converged.all())
        assert torch.allclose(sa.energy, sc.energy, rtol=1e-8, atol=1e-10)
    assert float((a - c).abs().max()) < 1e-5 * float((a - z).abs().max())


class _Repulsive:
    """A cubature energy with a huge outward push: any step from it blows up (the runtime's test, reused)."""

    def __init__(self, inner: CubatureEnergy, push: float) -> None:
        self.inner, self.push = inner, push
        self.latent_dim, self.condition_dim, self.periodic = inner.latent_dim, inner.condition_dim, inner.periodic
        self.output_weight, self.output_bias = inner.output_weight, inner.output_bias

    def features(self, z, cond):
        return self.inner.features(z, cond)

    def positions(self, z, cond):
        return self.inner.positions(z, cond)

    def energy_features(self, z, cond):
        e, r = self.inner.energy_features(z, cond)
        return e - self.push * (z * z).sum(-1), r

    def energy(self, z, cond):
        return self.energy_features(z, cond)[0], None


def test_a_stepper_of_a_cubature_pickles_and_copies_and_steps_alike(mini_chain) -> None:
    """A user's pickle of a stepper (multiprocessing, a saved object; the envs rebuild theirs from their arguments): one
    with a cubature energy (its reduced inertia) failed, "Can't pickle local object
    'LatentStepper._reduce_inertia.<locals>.<lambda>'"."""
    scene, f = mini_chain
    energy = CubatureEnergy(scene, f, build_cubature(scene, f, CubatureConfig(elements=8, **QUICK)))
    stepper = LatentStepper(scene, f, 0.02, energy=energy)
    g = torch.Generator().manual_seed(0)
    z = stepper.rest_latent() + 0.1 * torch.randn(3, f.latent_dim, generator=g)
    loads = torch.randn(3, len(scene.handles), scene.dim, generator=g)
    z_next, stats = stepper.step(z, z, loads)
    for copied in (pickle.loads(pickle.dumps(stepper)), copy.deepcopy(stepper)):
        again, again_stats = copied.step(z, z, loads)
        assert torch.equal(again, z_next) and bool(stats.converged.all())
        assert torch.equal(again_stats.carry, stats.carry)
        assert torch.equal(copied.energy.energy(z, None)[0], energy.energy(z, None)[0])


def test_cubature_in_the_runtime_stays_finite_and_flags_divergence(mini_chain) -> None:
    scene, f = mini_chain
    cub = build_cubature(scene, f, CubatureConfig(elements=1000, **QUICK))
    energy = CubatureEnergy(scene, f, cub)
    z = 0.1 * torch.ones(2, f.latent_dim)
    calm = LatentStepper(scene, f, 0.02, energy=energy)
    z_next, stats = calm.step(z, z)
    assert bool(torch.isfinite(z_next).all()) and not bool(stats.diverged.any())
    wild = LatentStepper(scene, f, 0.02, energy=_Repulsive(energy, 1e4))
    z_next, stats = wild.step(z, z)
    assert bool(stats.diverged.all())
    assert bool(torch.isfinite(z_next).all())


def test_cli_writes_the_cubature_beside_the_checkpoint(cli, tmp_path) -> None:
    import json
    import shutil

    for suffix in (".pt", ".json"):
        shutil.copy(pretrained.path("mini_chain").with_suffix(suffix), tmp_path / f"chain{suffix}")
    code, out, err = cli(
        "cubature",
        str(tmp_path / "chain.pt"),
        "--elements",
        "8",
        "--samples",
        "32",
        "--episodes",
        "1",
        "--rollout-steps",
        "5",
        "--json",
    )
    assert code == 0, err
    doc = json.loads(out)
    assert doc["path"].endswith("chain.cubature.json")
    modes = {e["effect"]: e["mode"] for e in doc["effects"]}
    assert modes == {"rigid": "full", "contact": "full", "gravity": "linear"}  # contact (96 > 8) whole by default
    scene = scenes.build("mini_chain")
    cub = load_cubature(tmp_path / "chain", scene, pretrained.load("mini_chain", scene))
    assert cub.command.startswith("redsim cubature ") and "--elements 8" in cub.command
    # a second run neither replaces the cubature silently nor loses it; --overwrite replaces it
    before = (tmp_path / "chain.cubature.json").read_text()
    again = ("cubature", str(tmp_path / "chain.pt"), "--elements", "4", "--samples", "32", "--episodes", "0")
    code, _, err = cli(*again)
    assert code == 2 and "--overwrite replaces it" in err and (tmp_path / "chain.cubature.json").read_text() == before
    code, _, err = cli(*again, "--overwrite")
    assert code == 0, err
    assert "--elements 4" in load_cubature(tmp_path / "chain", scene, pretrained.load("mini_chain", scene)).command


def test_cli_bad_input_exits_with_a_message(cli, tmp_path) -> None:
    code, _, err = cli("cubature", str(tmp_path / "nothing.pt"), "--elements", "8")
    assert code == 2 and "missing" in err
    code, _, err = cli("cubature", str(pretrained.path("mini_chain")), "--elements", "0")
    assert code == 2 and "elements" in err
    code, _, err = cli("cubature", str(pretrained.path("mini_chain")), "--elements", "4", "--tol", "0.1")
    assert code == 2 and "not allowed" in err
    code, out, err = cli("bench", "cubature", "no_such_scene")
    assert code == 2 and "unknown scene 'no_such_scene'" in err and "redsim fit" not in err and not out
    code, _, err = cli("bench", "cubature", "stiff_body")
    assert code == 2 and "no shipped subspace" in err and "--checkpoints DIR" in err
    code, _, err = cli("bench", "cubature", "stiff_body", "--checkpoints", str(tmp_path))
    assert code == 2 and str(tmp_path / "stiff_body.pt") in err and "redsim fit stiff_body" in err
    # the sweep checks --timed-steps too (0 was statistics.StatisticsError, -3 a negative tensor size)
    for timed in ("0", "-3"):
        code, _, err = cli("bench", "cubature", "--sweep", "2", "--timed-steps", timed, "--batches", "1")
        assert code == 2 and "--timed-steps >= 2" in err
    code, _, err = cli("bench", "energy", "--scenes", "mini_chain", "--perturbation", "inf")
    assert code == 2 and "--perturbation must be a finite number > 0, got inf" in err
    import shutil

    for suffix in (".pt", ".json"):
        shutil.copy(pretrained.path("mini_chain").with_suffix(suffix), tmp_path / f"m{suffix}")
    (tmp_path / "m.cubature.json").mkdir()  # a folder where the cubature goes: refused before the fit, not after it
    for extra in ((), ("--overwrite",)):
        code, _, err = cli("cubature", str(tmp_path / "m.pt"), "--elements", "4", "--samples", "8", *extra)
        assert code == 2 and "m.cubature.json is a folder, not a file" in err, err
    (tmp_path / "m.cubature.json").rmdir()
    (tmp_path / "m.cubature.json").write_text("[]")  # JSON, but not an object: AttributeError before
    with pytest.raises(CheckpointError, match=r"corrupt cubature file \(not a JSON object: list\)"):
        Cubature.load(tmp_path / "m")


def test_cli_interrupted_fit_leaves_the_file_whole_or_absent(cli, tmp_path, monkeypatch) -> None:
    """Ctrl-C during the fit (exit 130): no cubature where there was none, the previous one unchanged under
    --overwrite, and no temporary file beside them; with neither --elements nor --tol nothing runs."""
    import shutil

    from redsim.cubature import fit

    for suffix in (".pt", ".json"):
        shutil.copy(pretrained.path("mini_chain").with_suffix(suffix), tmp_path / f"m{suffix}")
    argv = ("cubature", str(tmp_path / "m.pt"), "--elements", "4", "--samples", "8", "--episodes", "0")
    code, _, err = cli(*argv[:2])
    assert code == 2 and "one of the arguments --elements --tol is required" in err

    def interrupted(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(fit, "greedy_nnls", interrupted)
        code, _, err = cli(*argv, "--subsample", "contact")
    assert code == 130 and "interrupted" in err and sorted(p.name for p in tmp_path.iterdir()) == ["m.json", "m.pt"]
    code, _, err = cli(*argv)
    assert code == 0, err
    before = (tmp_path / "m.cubature.json").read_text()
    with monkeypatch.context() as patch:
        patch.setattr(fit, "greedy_nnls", interrupted)
        code, _, err = cli(*argv, "--subsample", "contact", "--overwrite")
    assert code == 130 and (tmp_path / "m.cubature.json").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.cubature.json", "m.json", "m.pt"]


def test_cli_says_a_tol_not_reached_and_refuses_full_names_that_keep_nothing(cli, tmp_path, monkeypatch) -> None:
    """--tol stopped at its element cap without a word; --full gravity (linear, exact anyway) or external_load (the
    stepper's term) was taken, and, replacing the default, quietly subsampled the contact."""
    import json
    import shutil

    for suffix in (".pt", ".json"):
        shutil.copy(pretrained.path("mini_chain").with_suffix(suffix), tmp_path / f"m{suffix}")
    quick = ("--samples", "16", "--episodes", "0", "--subsample", "contact")
    for name, why in (("gravity", "are linear: they stay exact"), ("external_load", "are the load term")):
        code, _, err = cli("cubature", str(tmp_path / "m.pt"), "--tol", "0.1", "--full", name, *quick)
        assert code == 2 and f"effect(s) ['{name}'] {why}" in err, err
    code, _, err = cli(
        "cubature", str(tmp_path / "m.pt"), "--elements", "4", *quick[:4], "--subsample", "external_load"
    )
    assert code == 2 and "effect(s) ['external_load'] are the load term" in err, err
    monkeypatch.setattr("redsim.cli.cubature.TOL_ELEMENTS", 2)  # of the contact's 96: a tight tol is out of reach
    code, out, err = cli("cubature", str(tmp_path / "m.pt"), "--tol", "1e-6", *quick, "--json")
    assert code == 0 and "--tol 1e-06 not reached: training error" in err and "at 2 elements" in err, err
    assert json.loads(out)["tol_reached"] is False
    code, out, err = cli("cubature", str(tmp_path / "m.pt"), "--tol", "0.9", *quick, "--json", "--overwrite")
    assert code == 0 and "not reached" not in err and json.loads(out)["tol_reached"] is True


def test_an_nnls_that_runs_out_of_iterations_names_the_effect_and_what_to_do(cli, tmp_path, monkeypatch) -> None:
    """scipy.optimize.nnls raises RuntimeError("Maximum number of iterations reached.") (scipy 1.17, its info 3) on
    columns it cannot solve within maxiter: `redsim cubature` ended in that traceback, naming no effect."""
    import shutil

    import scipy.optimize

    real = scipy.optimize.nnls

    def stuck(a, b, maxiter=None):  # from the third kept element on
        if a.shape[1] < 3:
            return real(a, b, maxiter=maxiter)
        raise RuntimeError("Maximum number of iterations reached.")

    monkeypatch.setattr(scipy.optimize, "nnls", stuck)
    for suffix in (".pt", ".json"):
        shutil.copy(pretrained.path("mini_chain").with_suffix(suffix), tmp_path / f"m{suffix}")
    argv = ("cubature", str(tmp_path / "m.pt"), "--elements", "4", "--samples", "16", "--episodes", "0")
    code, _, err = cli(*argv, "--subsample", "contact")
    expected = (
        "effect 'contact': NNLS ran out of iterations refitting the weights of 3 kept elements (maxiter 150; scipy: "
        "Maximum number of iterations reached.): keep fewer elements (elements, --elements: below 3) or stop "
        "earlier (a larger tol, --tol)"
    )
    assert code == 2 and expected in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json", "m.pt"]


def test_a_tol_chooses_how_many_elements_of_a_small_effect_it_needs(mini_chain) -> None:
    """Under --tol the cap is 1000 elements, and an effect with at most that many was kept whole without a search:
    the tolerance did nothing on the bars (756-846 elements). Without a tol such an effect is still kept whole."""
    from redsim.cubature.fit import effect_modes

    scene, _ = mini_chain
    config = CubatureConfig(elements=1000, tol=0.3, subsample=("contact",))
    assert effect_modes(scene, config)["contact"] == "cubature"
    assert effect_modes(scene, CubatureConfig(elements=1000, subsample=("contact",)))["contact"] == "full"


def test_bench_names_its_checkpoint_and_refuses_one_of_another_scene(cli, tmp_path) -> None:
    """``--checkpoints DIR``: a folder that is not there, or a DIR/SCENE.pt of another scene (by name, or a user's
    mesh of that name), is refused (exit 2); each row names the checkpoint it used, in the text and in ``--json``."""
    import json
    import shutil

    quick = ("mini_chain", "--steps", "2", "--batches", "1", "--timed-steps", "2", "--elements", "4")
    code, _, err = cli("bench", "cubature", *quick, "--checkpoints", str(tmp_path / "nowhere"))
    assert code == 2 and f"--checkpoints {tmp_path / 'nowhere'}: no such folder" in err
    for suffix in (".pt", ".json"):
        shutil.copy(pretrained.path("chain").with_suffix(suffix), tmp_path / f"mini_chain{suffix}")
    code, _, err = cli("bench", "cubature", *quick, "--checkpoints", str(tmp_path))
    assert code == 2 and f"{tmp_path / 'mini_chain.pt'} is a fit of scene 'chain', not of 'mini_chain'" in err
    for suffix in (".pt", ".json"):
        shutil.copy(pretrained.path("mini_chain").with_suffix(suffix), tmp_path / f"mini_chain{suffix}")
    code, out, err = cli("bench", "cubature", *quick, "--checkpoints", str(tmp_path), "--json")
    assert code == 0, err
    assert json.loads(out)["results"][0]["checkpoint"] == str(tmp_path / "mini_chain.pt")
    meta = json.loads((tmp_path / "mini_chain.json").read_text())
    meta["scene_params"] = {**meta["scene_params"], "builder": "fem"}  # a mesh scene named mini_chain
    (tmp_path / "mini_chain.json").write_text(json.dumps(meta))
    code, _, err = cli("bench", "cubature", *quick, "--checkpoints", str(tmp_path))
    assert code == 2 and "the fem mesh scene 'mini_chain', not of 'mini_chain'" in err
    code, out, err = cli("bench", "cubature", *quick)
    assert code == 0 and "mini_chain (redsim/pretrained/mini_chain.pt; built here, --elements 4): n=24" in out, err
    later = tmp_path / "later"  # a wrong checkpoint for a later scene is refused before the first scene is benched
    later.mkdir()
    for suffix in (".pt", ".json"):
        shutil.copy(pretrained.path("mini_chain").with_suffix(suffix), later / f"chain{suffix}")
    code, out, err = cli("bench", "cubature", "mini_chain,chain", *quick[1:], "--checkpoints", str(later))
    assert code == 2 and out == "" and "is a fit of scene 'mini_chain', not of 'chain'" in err
    # so is a cubature beside a later checkpoint that belongs to another map (it was loaded in that scene's turn)
    wrong = tmp_path / "wrong"
    wrong.mkdir()
    for name in ("mini_chain", "klann"):
        for suffix in (".pt", ".json"):
            shutil.copy(pretrained.path(name).with_suffix(suffix), wrong / f"{name}{suffix}")
    chain = scenes.build("mini_chain")
    build_cubature(chain, pretrained.load("mini_chain", chain), CubatureConfig(elements=4, **QUICK)).save(
        wrong / "klann"
    )
    code, out, err = cli("bench", "cubature", "mini_chain,klann", *quick[1:], "--checkpoints", str(wrong))
    assert code == 2 and "mini_chain (" not in out and "klann.cubature.json" in err, (out, err)


def test_bench_held_out_recomputes_the_errors_beside_the_recorded_ones(cli) -> None:
    """``--held-out`` replays the build's held-out states from its recorded config: the force error it reports again
    is the build's, printed beside the plain one, per state and energy errors; the --sweep (unfitted maps) refuses
    it."""
    quick = ("mini_chain", "--steps", "2", "--batches", "1", "--timed-steps", "2", "--elements", "4")
    code, out, err = cli("bench", "cubature", *quick, "--held-out", "--json")
    assert code == 0, err
    row = json.loads(out)["results"][0]
    errors = row["held_out_errors"]
    assert errors["force_error"] == pytest.approx(row["held_out_force_error"], rel=1e-9)
    assert errors["plain_force_error"] == pytest.approx(row["held_out_plain_force_error"], rel=1e-9)
    code, out, err = cli("bench", "cubature", *quick, "--held-out")
    assert code == 0, err
    force, plain = row["held_out_force_error"], row["held_out_plain_force_error"]
    assert f"held-out force error {force:.3g} (plain {plain:.3g}) (recomputed on the {errors['states']} states" in out
    code, _, err = cli("bench", "cubature", "--sweep", "2", "--held-out")
    assert code == 2 and "--held-out recomputes a fitted cubature's errors" in err


def test_bench_held_out_seed_recomputes_the_errors_on_every_state_of_another_seed(cli) -> None:
    """``--held-out-seed S`` draws every state of the recorded config under seed S (states no build saw): their count
    is the whole training set's, not the held-out part's; the --sweep refuses it too."""
    quick = ("mini_chain", "--steps", "2", "--batches", "1", "--timed-steps", "2", "--elements", "4", "--json")
    code, out, err = cli("bench", "cubature", *quick, "--held-out")
    assert code == 0, err
    own = json.loads(out)["results"][0]["held_out_errors"]
    code, out, err = cli("bench", "cubature", *quick, "--held-out-seed", "7")
    assert code == 0, err
    other = json.loads(out)["results"][0]["held_out_errors"]
    assert other["seed"] == 7 and own["seed"] != 7
    assert other["states"] > own["states"]  # every state, not the held-out quarter
    code, out, err = cli("bench", "cubature", *quick[:-1], "--held-out-seed", "7")
    assert code == 0, err
    assert f"recomputed on the {other['states']} states its config draws under seed 7, which no build saw: " in out
    code, _, err = cli("bench", "cubature", "--sweep", "2", "--held-out-seed", "7")
    assert code == 2 and "--held-out recomputes a fitted cubature's errors" in err


@pytest.mark.parametrize("name", ["hanging_sheet", "cloth_ball"])
def test_shipped_cubatures_are_chosen_with_one_option(name: str) -> None:
    scene = scenes.build(name)
    f = pretrained.load(name, scene)
    stepper = LatentStepper(scene, f, 0.02, energy=cubature_energy)
    assert isinstance(stepper.energy, CubatureEnergy) and stepper.reduced
    kept = stepper.energy.describe()
    assert kept["kept_elements"]["membrane"] < scene.effect("membrane").element_count
    z = torch.zeros(2, f.latent_dim)
    z_next, stats = stepper.step(z, z)
    assert bool(torch.isfinite(z_next).all()) and not bool(stats.diverged.any())


def test_the_energy_option_refuses_what_it_cannot_use(mini_chain) -> None:
    scene, f = mini_chain
    with pytest.raises(CheckpointError, match=r"no cubature file .* for a map of your own give its checkpoint"):
        LatentStepper(scene, f, 0.02, energy=cubature_energy)  # none is shipped for the mini chain
    with pytest.raises(ValueError, match="factory"):
        LatentStepper(scene, f, 0.02, energy="fast")


def test_mesh_sweep_leaves_the_batched_all_element_step_out_above_its_limit(cli) -> None:
    from redsim.cubature.bench import mesh_sweep

    before = torch.random.get_rng_state()
    small, big = mesh_sweep((3, 5), elements=8, batches=(1, 2), timed_steps=1, batch_max_n=50)
    assert torch.equal(torch.random.get_rng_state(), before)  # its maps draw from their own seeded stream
    assert small["n"] <= 50 < big["n"]
    assert small["timing"][2]["all_s"] > 0 and big["timing"][2]["all_s"] is None
    assert all(row["timing"][1]["all_s"] > 0 and row["timing"][2]["cubature_s"] > 0 for row in (small, big))
    code, _, err = cli("bench", "cubature", "--sweep", "3", "--batch-max-n", "-1")
    assert code == 2 and "--batch-max-n" in err
    code, _, err = cli("bench", "cubature", "--sweep", "3", "--compile")
    assert code == 2 and "--compile" in err


def test_bench_takes_a_cubature_file_and_refuses_a_wrong_one(cli, tmp_path) -> None:
    """``--cubature PATH`` benches that file (one scene, fitted to its map); each row names its cubature (None where
    the bench built one). Another scene's cubature, two scenes or none named, a file of another kind, a missing one,
    the --sweep and --elements (which sizes a cubature the bench builds) are refused (exit 2) before any bench runs."""
    import shutil

    quick = ("--steps", "2", "--batches", "1", "--timed-steps", "2", "--states", "1")
    for suffix in (".pt", ".json"):
        shutil.copy(pretrained.path("mini_chain").with_suffix(suffix), tmp_path / f"m{suffix}")
    code, _, err = cli("cubature", str(tmp_path / "m.pt"), "--elements", "4", "--samples", "16", "--episodes", "0")
    assert code == 0, err
    made = tmp_path / "m.cubature.json"
    code, out, err = cli("bench", "cubature", "mini_chain", *quick, "--cubature", str(made), "--json")
    assert code == 0, err
    row = json.loads(out)["results"][0]
    assert row["cubature"] == str(made) and row["checkpoint"] == str(pretrained.path("mini_chain"))
    assert row["elements"] == {r.name: int(r.indices.numel()) for r in Cubature.load(made).rules}
    code, out, err = cli("bench", "cubature", "mini_chain", *quick, "--elements", "4", "--json")
    assert code == 0 and json.loads(out)["results"][0]["cubature"] is None, err  # none beside the map: built here
    lean = pretrained.FOLDER / "cloth_ball.lean.cubature.json"
    for args, message in [
        (("mini_chain", "--cubature", str(lean)), "cubature built for scene 'cloth_ball'"),
        (("mini_chain,chain", "--cubature", str(made)), "name one scene, got mini_chain, chain"),
        (("mini_chain", "--cubature", str(tmp_path / "m.json")), "not a .cubature.json file"),
        (("mini_chain", "--cubature", str(tmp_path / "no.cubature.json")), "no such file"),
        (("--sweep", "2", "--cubature", str(made)), "the --sweep fits none"),
        (("--cubature", str(made)), "name its scene, e.g. `redsim bench cubature cloth_ball --cubature"),
        (("mini_chain", "--cubature", str(made), "--elements", "4"), "--elements sizes a cubature the bench builds"),
    ]:
        code, out, err = cli("bench", "cubature", *args, *quick)
        assert code == 2 and message in err and not out, (args, err)


def test_bench_fails_on_diverged_steps_and_names_what_it_cannot_bench(cli, tmp_path, mini_chain) -> None:
    """A cubature whose steps diverge (each rejected: the state stays) was benched with exit 0 and a plain deviation
    (1.0, a stalled rollout) beside a fine speed-up; now the row counts the flagged steps and the command exits 4. A
    cubature made in Python without a summary (no held-out error) and a map without an affine output layer (an
    autoencoder's, where the bench builds the cubature) were tracebacks."""
    from redsim.baselines import train_autoencoder

    scene, f = mini_chain
    quick = ("--steps", "3", "--batches", "1", "--timed-steps", "2", "--states", "2", "--warmup-steps", "0")
    cub = build_cubature(scene, f, CubatureConfig(elements=4, samples=16, episodes=0, subsample=("contact",)))
    wild = next(r for r in cub.rules if r.name == "contact")
    wild.indices = torch.arange(wild.element_count)  # every contact point, at a weight whose energy overflows
    wild.weights = torch.full((wild.element_count,), 3e38, dtype=torch.float64)
    path = cub.save(tmp_path / "wild")
    code, out, err = cli("bench", "cubature", "mini_chain", "--cubature", str(path), *quick, "--json")
    assert code == 4 and "diverged accuracy steps" in err and "mini_chain: 0 (all elements) and 6 (cubature)" in err
    flags = json.loads(out)["results"][0]["flags"]
    assert flags["all"]["diverged"] == 0 and flags["cubature"]["diverged"] == 6, flags
    code, out, _ = cli("bench", "cubature", "mini_chain", "--cubature", str(path), *quick)
    assert code == 4 and "(of 6 state-steps; diverged steps 0 -> 6; unconverged steps 0 -> 6)" in out, out
    bare = build_cubature(scene, f, CubatureConfig(elements=4, **QUICK))
    path = Cubature(bare.scene, bare.scene_fingerprint, bare.map_fingerprint, bare.rules).save(tmp_path / "bare")
    code, out, err = cli("bench", "cubature", "mini_chain", "--cubature", str(path), *quick)
    assert code == 0 and "held-out force error unknown; trajectory deviation" in out and "state-steps" not in out, err
    states = scene.q_seed[None] + 0.01 * torch.randn(
        16, scene.free_dof_count, generator=torch.Generator().manual_seed(0)
    )
    train_autoencoder(scene, states, 2, steps=1, hidden_width=8, hidden_layers=1).save(tmp_path / "ae" / "mini_chain")
    code, out, err = cli("bench", "cubature", "mini_chain", *quick, "--checkpoints", str(tmp_path / "ae"))
    assert (
        code == 2 and not out and f"{tmp_path / 'ae' / 'mini_chain.pt'}: a cubature needs a map with an affine" in err
    )


def test_bench_deviation_does_not_depend_on_the_timing_batches(mini_chain) -> None:
    """The deviation is the median over ACCURACY_STATES seeded rollouts, whatever batch sizes are timed."""
    from redsim.cubature.bench import ACCURACY_STATES, bench_cubature

    scene, f = mini_chain
    cub = build_cubature(scene, f, CubatureConfig(elements=4, **QUICK))
    runs = [bench_cubature(scene, f, cub, steps=6, batches=b, timed_steps=2) for b in ((1,), (1, 16))]
    assert runs[0]["trajectory_deviation"] == runs[1]["trajectory_deviation"] > 0.0
    per_state, motion = runs[0]["deviation_per_state"], runs[0]["motion_per_state"]
    assert len(per_state) == len(motion) == ACCURACY_STATES and min(motion) > 0.0 and runs[0]["max_latent_norm"] > 0.0
    assert runs[0]["trajectory_deviation"] == torch.tensor(per_state).median().item()  # the median of these


def test_bench_states_are_nested_and_counted(cli, mini_chain) -> None:
    """``states`` sets how many rollouts the deviation is the median of; their loads are nested (fewer states take the
    default's first ones, more add others after them); a count below 1 is refused by the function and the CLI."""
    from redsim.cubature import bench

    scene, f = mini_chain
    default = bench._state_loads(scene, 6, bench.ACCURACY_STATES, 2, 1.0, 0)
    assert torch.equal(default, bench._loads(scene, 6, bench.ACCURACY_STATES, 2, 1.0, 0))  # the default's loads
    more, fewer = (bench._state_loads(scene, 6, n, 2, 1.0, 0) for n in (11, 3))
    assert more.shape[1] == 11 and torch.equal(more[:, :8], default) and torch.equal(fewer, default[:, :3])
    assert not torch.equal(more[:, 8:], default[:, :3])  # the added states are others
    cub = build_cubature(scene, f, CubatureConfig(elements=4, **QUICK))
    run = bench.bench_cubature(scene, f, cub, steps=4, batches=(1,), timed_steps=2, states=11)
    assert len(run["deviation_per_state"]) == len(run["motion_per_state"]) == 11
    assert run["trajectory_deviation"] == torch.tensor(run["deviation_per_state"]).median().item()
    for bad in (0, True, 2.0):
        with pytest.raises(ValueError, match="states must be an integer >= 1"):
            bench.bench_cubature(scene, f, cub, steps=2, batches=(1,), timed_steps=2, states=bad)
    code, _, err = cli("bench", "cubature", "mini_chain", "--states", "0")
    assert code == 2 and "--states must be an integer >= 1, got 0" in err


def test_bench_times_both_energies_from_the_same_moving_state(cli, mini_chain) -> None:
    """The timed steps of both energies start where ``warmup`` all-element steps under the loads end (0: from rest),
    under the same loads, those after the warm-up's; the calls per step are the timed rollouts' own; the deviation
    does not depend on it; a bad warm-up is refused."""
    from redsim.cubature import bench
    from redsim.cubature.fit import default_load_scale

    scene, f = mini_chain
    cub = build_cubature(scene, f, CubatureConfig(elements=4, **QUICK))
    calls = []
    rollout = bench._rollout

    def spy(stepper, z0, loads, steps, z_prev=None, flags=None):  # type: ignore[no-untyped-def]
        before = stepper.evaluations.calls
        path, times = rollout(stepper, z0, loads, steps, z_prev, flags)
        calls.append((stepper, z0.clone(), z_prev, loads, path, stepper.evaluations.calls - before))
        return path, times

    bench._rollout = spy
    try:
        runs = [bench.bench_cubature(scene, f, cub, steps=6, batches=(2,), timed_steps=2, warmup=w) for w in (0, 3)]
    finally:
        bench._rollout = rollout
    assert runs[0]["trajectory_deviation"] == runs[1]["trajectory_deviation"] and runs[1]["warmup_steps"] == 3
    from_rest, warm_up, timed = calls[2:6], calls[8], calls[9:]  # per run: 2 accuracy rollouts, (warm-up,) 4 timed
    assert len(from_rest) == 4 and all(c[2] is None for c in from_rest)  # warmup 0: from rest, not moving
    loads = bench._loads(scene, 3 + 2, 2, 10, default_load_scale(scene), 1)  # warm-up + timed steps, B = 2, seed + 1
    assert torch.equal(warm_up[3], loads[:3]) and warm_up[2] is None
    moving, previous = warm_up[4][-1], warm_up[4][-2]
    assert not torch.equal(moving, previous)
    for _, z0, z_prev, timed_loads, _, _ in timed:
        assert torch.equal(z0, moving) and torch.equal(z_prev, previous) and torch.equal(timed_loads, loads[3:])
    assert {id(c[0]) for c in timed} == {id(timed[0][0]), id(timed[1][0])} and timed[0][0] is not timed[1][0]
    for key, stepper in (("all_calls_per_step", timed[0][0]), ("cubature_calls_per_step", timed[1][0])):
        own = sum(c[5] for c in timed if c[0] is stepper)  # 2 halves of 2 steps each
        assert own >= 4 and runs[1]["timing"][2][key] == own / 4
    with pytest.raises(ValueError, match="warmup must be an integer >= 0"):
        bench.bench_cubature(scene, f, cub, steps=2, batches=(1,), timed_steps=2, warmup=-1)
    code, _, err = cli("bench", "cubature", "mini_chain", "--warmup-steps", "-1")
    assert code == 2 and "--warmup-steps must be >= 0, got -1" in err


def test_bench_cubature_times_exactly_the_timed_steps_asked(mini_chain) -> None:
    """An odd ``timed_steps`` is timed whole: the two interleaved halves time (n + 1) // 2 and n // 2 steps after
    each rollout's untimed first step (n - 1 were timed before); 0 is refused."""
    from redsim.cubature import bench

    scene, f = mini_chain
    cub = build_cubature(scene, f, CubatureConfig(elements=4, **QUICK))
    timed = []
    rollout = bench._rollout

    def spy(stepper, z0, loads, steps, z_prev=None, flags=None):  # type: ignore[no-untyped-def]
        path, times = rollout(stepper, z0, loads, steps, z_prev, flags)
        timed.append(len(times) - 1)
        return path, times

    bench._rollout = spy
    try:
        for n in (3, 4):
            timed.clear()
            bench.bench_cubature(scene, f, cub, steps=2, batches=(1,), timed_steps=n, warmup=0)
            halves = timed[2:]  # after the two accuracy rollouts: all, cubature, all, cubature
            assert halves == [(n + 1) // 2] * 2 + [n // 2] * 2
    finally:
        bench._rollout = rollout
    with pytest.raises(ValueError, match="timed_steps must be an integer >= 1"):
        bench.bench_cubature(scene, f, cub, steps=2, batches=(1,), timed_steps=0)


def test_bench_cubature_in_float64(cli, mini_chain) -> None:
    """``--dtype float64`` steps both energies in float64 (the deviation without float32's round-off)."""
    import json

    code, out, err = cli(
        "bench",
        "cubature",
        "mini_chain",
        "--dtype",
        "float64",
        "--steps",
        "4",
        "--batches",
        "1",
        "--timed-steps",
        "2",
        "--elements",
        "4",
        "--json",
    )
    assert code == 0, err
    (result,) = json.loads(out)["results"]
    assert result["dtype"] == "float64" and result["trajectory_deviation"] >= 0.0


def test_bench_cubature_reports_a_scene_that_raises_and_keeps_rows_at_ctrl_c(cli, monkeypatch) -> None:
    """A scene whose bench raised ended the command in a traceback (the other scenes lost), and Ctrl-C lost the JSON
    document: now the scene is a ``failed`` line (exit 1), and Ctrl-C prints the finished scenes (exit 130)."""
    import json

    from redsim.cubature import bench

    real = bench.bench_cubature
    errors: dict[str, BaseException] = {"mini_chain": RuntimeError("no step")}

    def bench_cubature(scene, *args, **kwargs):
        if scene.name in errors:
            raise errors[scene.name]
        return real(scene, *args, **kwargs)

    monkeypatch.setattr(bench, "bench_cubature", bench_cubature)
    argv = ("bench", "cubature", "mini_chain,klann", "--steps", "2", "--batches", "1", "--timed-steps", "2")
    code, out, err = cli(*argv, "--elements", "4")
    assert code == 1 and "failed: mini_chain: RuntimeError: no step" in out and "\nklann (" in out, err
    assert "bench cubature: 1 scene(s) failed (mini_chain); the others ran" in err
    errors.update(mini_chain=KeyboardInterrupt())
    code, out, err = cli(*argv, "--elements", "4", "--json")
    doc = json.loads(out)
    assert code == 130 and doc["interrupted"] and doc["results"] == [] and doc["failed"] == [], err


def test_bench_cubature_refuses_options_the_sweep_or_the_scenes_do_not_use(cli) -> None:
    """--sweep ignored the scenes, --checkpoints, --steps, --states, --warmup-steps and --dtype, and the scenes' bench
    ignored --batch-max-n; each exited 0 as if it had been used."""
    code, out, err = cli("bench", "cubature", "--sweep", "4", "--warmup-steps", "3", "--states", "2")
    assert code == 2 and out == "" and "--sweep times the step only" in err and "drop --states, --warmup-steps" in err
    code, out, err = cli("bench", "cubature", "mini_chain", "--sweep", "4")
    assert code == 2 and "drop SCENES" in err, err
    code, out, err = cli("bench", "cubature", "mini_chain", "--batch-max-n", "3")
    assert code == 2 and out == "" and "--batch-max-n limits the --sweep's all-element step" in err, err


@pytest.mark.slow
def test_bench_cubature_times_the_compiled_cubature_step_on_request(cli, mini_chain, monkeypatch) -> None:
    """``--compile`` adds the cubature step with compile="dynamic" (its compiling first steps untimed); the sweep
    refuses it. Dynamo alone (backend "eager", no kernels built): the test is about what is timed and printed."""
    import json

    from redsim.runtime import stepper

    compile_ = torch.compile
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: compile_(fn, **{**kw, "backend": "eager"}))
    monkeypatch.setattr(stepper, "check_compiler", lambda device: None)
    argv = ("bench", "cubature", "mini_chain", "--steps", "3", "--batches", "1,4", "--timed-steps", "2", "--elements")
    code, out, err = cli(*argv, "4", "--compile", "--json")
    assert code == 0, err
    (result,) = json.loads(out)["results"]
    for timing in result["timing"].values():
        assert timing["cubature_compiled_s"] > 0.0 and timing["cubature_compiled_calls_per_step"] >= 1.0
    code, out, err = cli(*argv, "4", "--compile")
    assert code == 0 and out.count("compiled ") == 2, out


@pytest.mark.parametrize("name", ["cloth_ball", "hanging_sheet"])
def test_near_contact_path_equals_the_slice_path(name: str) -> None:
    """The default path (a whole single-frame contact by its near points only, the cloth's elements on edges computed
    from the features, whole element sums on the slice) gives the energy, gradient and steps of the path before
    (``slice_all=True``) to float64 round-off."""
    scene = scenes.build(name)
    f = pretrained.load(name, scene)
    cub = load_cubature(pretrained.FOLDER / name, scene, f)
    new = CubatureEnergy(scene, f, cub, dtype=torch.float64)
    old = CubatureEnergy(scene, f, cub, dtype=torch.float64, slice_all=True)
    if name == "cloth_ball":  # the contact's points are screened, not sliced; the graph reads fewer DOFs
        assert new.describe()["kept_dofs"] < old.describe()["kept_dofs"] == scene.dof_map.full_values.numel()
        assert new.describe()["screened_dofs"] == scene.dof_map.full_values.numel()
    else:  # no contact: the same kept DOFs, all of them read through the edge layer
        assert new.describe()["kept_dofs"] == old.describe()["kept_dofs"] and new.describe()["screened_dofs"] == 0
    assert new.describe()["slice_dofs"] < old.describe()["slice_dofs"] == old.describe()["kept_dofs"]
    assert new.describe()["edge_entries"] > 0 == old.describe()["edge_entries"]
    assert new.offset == pytest.approx(old.offset, rel=1e-12, abs=1e-12)
    stepper = LatentStepper(scene, f, 0.02, energy=old, dtype=torch.float64)
    rest = stepper.rest_latent()
    z = torch.cat([rest, 2.0 * torch.randn(7, f.latent_dim, generator=torch.Generator().manual_seed(0))])
    if name == "cloth_ball":  # some states touch the ball (the near path has points to differentiate)
        contact = stepper.scene.effect("contact")
        assert bool((contact.energy(stepper.scene.full_positions(stepper.positions(z))) > 0).any())
    values, grads = [], []
    for energy in (old, new):
        zz = z.clone().requires_grad_(True)
        value, _ = energy.energy_features(zz, None)
        (grad,) = torch.autograd.grad(value.sum(), zz)
        values.append(value.detach())
        grads.append(grad)
    assert torch.allclose(values[1], values[0], rtol=1e-12, atol=1e-12 * float(values[0].abs().max()))
    assert torch.allclose(grads[1], grads[0], rtol=1e-10, atol=1e-10 * float(grads[0].abs().max()))
    # each step from the same states (the old path's): a round-off difference can turn a line-search decision, so
    # two converged solves agree to the tolerance, not bitwise (one of hanging_sheet's third steps ends 1.2e-6 apart
    # after 25 and 26 iterations); a solve that hits max_iter (a random start far from rest) stops wherever its path
    # is, so only states both solves converged are compared
    steppers = [LatentStepper(scene, f, 0.02, energy=energy, dtype=torch.float64) for energy in (old, new)]
    zt, zp = z, z
    for _ in range(3):
        (z_old, stats_old), (z_new, stats_new) = (stepper.step(zt, zp) for stepper in steppers)
        both = stats_old.converged & stats_new.converged
        assert int(both.sum()) >= 6
        assert torch.allclose(z_new[both], z_old[both], rtol=0.0, atol=1e-5)
        zt, zp = z_old, zt


def test_float32_edges_are_as_accurate_as_the_float32_slice() -> None:
    """The cloth's edges from the features (W_E's row differences taken in float64) are as close to the float64
    energy and gradient in float32 as the slice's positions subtracted in float32 are (within 1.5x; measured closer)."""
    scene = scenes.build("hanging_sheet")
    f = pretrained.load("hanging_sheet", scene)
    cub = load_cubature(pretrained.FOLDER / "hanging_sheet.lean", scene, f)
    z = 0.7 * torch.randn(32, f.latent_dim, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    results = []
    for dtype, slice_all in ((torch.float64, True), (torch.float32, False), (torch.float32, True)):
        zz = z.to(dtype).requires_grad_(True)
        value, _ = CubatureEnergy(scene, f, cub, dtype=dtype, slice_all=slice_all).energy_features(zz, None)
        (grad,) = torch.autograd.grad(value.sum(), zz)
        results.append((value.detach().double(), grad.double()))
    (v64, g64), (v_edges, g_edges), (v_slice, g_slice) = results
    assert float((v_edges - v64).abs().max()) <= 1.5 * float((v_slice - v64).abs().max())
    assert float((g_edges - g64).abs().max()) <= 1.5 * float((g_slice - g64).abs().max())


def test_an_edge_effect_that_keeps_no_element_adds_nothing() -> None:
    """A cubature rule may keep no element (an effect idle on every training state, :mod:`redsim.cubature.fit`): on
    edges it adds zero energy, as on the slice (float64)."""
    from redsim.cubature.fit import EffectRule

    scene = scenes.build("hanging_sheet")
    f = pretrained.load("hanging_sheet", scene)
    cub = load_cubature(pretrained.FOLDER / "hanging_sheet.lean", scene, f)
    count = scene.effect("bending").element_count
    none = EffectRule(
        "bending", "cubature", count, torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.float64)
    )
    cub.rules = [none if r.name == "bending" else r for r in cub.rules]
    z = 0.5 * torch.randn(4, f.latent_dim, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    values = []
    for slice_all in (False, True):
        energy = CubatureEnergy(scene, f, cub, dtype=torch.float64, slice_all=slice_all)
        zz = z.clone().requires_grad_(True)
        value, _ = energy.energy_features(zz, None)
        values.append((value.detach(), torch.autograd.grad(value.sum(), zz)[0]))
    assert energy.describe()["edge_entries"] == 0  # the slice path's
    torch.testing.assert_close(values[0][0], values[1][0], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(values[0][1], values[1][1], rtol=1e-10, atol=1e-12)


def test_near_contact_follows_a_moving_sheared_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    """A whole single-frame contact whose frame is free (moved, sheared and scaled by the map) and particles
    around it: the near-point path, and its dense form under ``torch.compile``, equal the slice path (value and
    gradient) in float64."""
    from redsim.cubature.energy import map_fingerprint
    from redsim.cubature.fit import EffectRule
    from redsim.effects.penalty import FrameSet, SDFContact
    from redsim.effects.sdf import Sphere

    g = torch.Generator().manual_seed(5)
    count = 300
    b = SceneBuilder(dim=3)
    body = b.add_body(torch.eye(4, dtype=torch.float64))
    ids = b.add_particles(1.2 * (2.0 * torch.rand(count, 3, generator=g, dtype=torch.float64) - 1.0), torch.ones(count))
    points = b.particle_points(ids)
    b.add_effect(SDFContact("c", points, FrameSet.body(b.body_dofs(body), count), Sphere(0.5), 50.0, margin=0.02))
    scene = b.finalize("moving_ball", params={"count": count})
    n = scene.free_dof_count
    f = LinearSubspace(0.1 * torch.randn(n, 4, generator=g, dtype=torch.float64), scene.q_seed.clone())
    rule = EffectRule("c", "full", count, torch.arange(count), torch.ones(count, dtype=torch.float64), 0.0, 0.0, [])
    cub = Cubature(scene.name, scene.fingerprint(), map_fingerprint(f), [rule])
    new = CubatureEnergy(scene, f, cub, dtype=torch.float64)
    old = CubatureEnergy(scene, f, cub, dtype=torch.float64, slice_all=True)
    assert [how for how, _, _ in new.terms] == ["near"] and [how for how, _, _ in old.terms] == ["whole"]
    z = (2.0 * torch.randn(16, 4, generator=g, dtype=torch.float64)).requires_grad_(True)
    x = scene.full_positions(f(z.detach()))
    touching = scene.effect("c").element_energy(x[:, scene.effect("c").element_dofs]) > 0
    assert 0 < int(touching.sum()) < touching.numel()
    (value_old, _), (value_new, _) = old.energy_features(z, None), new.energy_features(z, None)
    (grad_old,) = torch.autograd.grad(value_old.sum(), z)
    (grad_new,) = torch.autograd.grad(value_new.sum(), z)
    torch.testing.assert_close(value_new, value_old, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(grad_new, grad_old, rtol=1e-10, atol=1e-10)
    monkeypatch.setattr(torch.compiler, "is_compiling", lambda: True)  # the dense form a compiled step takes
    (value_dense, _) = new.energy_features(z, None)
    (grad_dense,) = torch.autograd.grad(value_dense.sum(), z)
    torch.testing.assert_close(value_dense, value_old, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(grad_dense, grad_old, rtol=1e-10, atol=1e-10)


def test_rollout_states_dropped_are_counted_with_their_reason(mini_chain) -> None:
    from redsim.cubature.fit import training_states

    scene, f = mini_chain
    config = CubatureConfig(elements=4, samples=8, episodes=4, steps=10, load_scale=1e5)  # loads far outside the map
    z, _, dropped, episode = training_states(scene, f, config)
    rollout = z.shape[0] - 8
    assert dropped["out_of_range"] > 0 and rollout + sum(dropped.values()) == 4 * 10, dropped
    assert int((episode >= 0).sum()) == rollout and bool((episode[:8] == -1).all())  # a dropped step has no rollout
    _, _, dropped, episode = training_states(scene, f, CubatureConfig(elements=4, samples=8, episodes=2, steps=3))
    assert dropped == {"diverged": 0, "out_of_range": 0}
    assert episode.tolist() == [-1] * 8 + [0, 1] * 3  # step by step, each step's rollouts in order


def test_held_out_rollouts_are_held_out_whole(mini_chain) -> None:
    """A rollout's states lie a step apart: split one by one, most held-out rollout states had their neighbours in
    training, and their error was the training error. The split keeps each rollout on one side (the sampled states
    are split one by one as before); a fixed seed gives the same cubature, the largest one included."""
    from redsim.cubature.fit import split_states

    episode = torch.tensor([-1] * 8 + [0, 1, 2, 3] * 5)
    test, train = split_states(episode, CubatureConfig(held_out=0.25, seed=3))
    assert sorted(test.tolist() + train.tolist()) == list(range(episode.numel()))
    sides = {int(e): {bool(i in test) for i in torch.nonzero(episode == e).reshape(-1).tolist()} for e in range(4)}
    assert sorted(sides.values(), key=str) == [{False}] * 3 + [{True}]  # one rollout of four, whole
    assert int((episode[test] < 0).sum()) == 2  # a quarter of the sampled states
    test, _ = split_states(torch.tensor([-1] * 8 + [0] * 5), CubatureConfig(held_out=0.25))
    assert bool((test < 8).all())  # a single rollout trains
    only = split_states(torch.full((6,), -1), CubatureConfig(held_out=0.5, seed=2))[0]  # no rollouts: one by one
    assert torch.equal(only, torch.randperm(6, generator=torch.Generator().manual_seed(3))[:3])
    scene, f = mini_chain
    config = CubatureConfig(elements=4, samples=12, episodes=4, steps=2, subsample=("contact",), seed=2**64 - 1)
    runs = [build_cubature(scene, f, config) for _ in range(2)]  # the largest --seed (its split's seed overflowed)
    assert runs[0].summary["held_out_rollouts"] == 1 and runs[0].summary["held_out_states"] == 3 + 2
    assert runs[0].summary == runs[1].summary
    assert [(r.indices.tolist(), r.weights.tolist()) for r in runs[0].rules] == [
        (r.indices.tolist(), r.weights.tolist()) for r in runs[1].rules
    ]


def test_progress_covers_the_rollouts_and_the_element_forces(mini_chain, capsys) -> None:
    """Only the greedy search had a bar: the rollouts and every effect's per-element forces before it (on the cloth,
    nearly as long as the search) ran without a word."""
    scene, f = mini_chain
    config = CubatureConfig(elements=2, samples=8, episodes=1, steps=2, subsample=("contact",))
    build_cubature(scene, f, config, progress=True)
    bars = capsys.readouterr().err
    states = 8 + 2  # per effect: rigid, contact, gravity
    assert "cubature rollouts" in bars and "2/2" in bars, bars
    assert "cubature element forces" in bars and f"{3 * states}/{3 * states}" in bars, bars
    assert "cubature contact" in bars


def test_a_float64_maps_training_rollouts_run_in_float64() -> None:
    """A float64 fit's rollouts ran in the stepper's float32, which could not feel the small cloth's loads (and
    said so, advising a dtype that ``redsim cubature`` cannot take); they run in the map's dtype now."""
    import copy
    import warnings

    from redsim.cubature.fit import training_states
    from redsim.trainers import FitConfig, fit_subspace

    scene = scenes.build("toy_small_cloth")
    config = FitConfig(latent_dim=3, steps=20, hidden_width=16, hidden_layers=2, dtype="float64")
    f = fit_subspace(scene, config, progress=False).subspace
    rollouts = CubatureConfig(samples=4, episodes=1, steps=3)
    with pytest.warns(UserWarning, match="float32 at dt=0.02 s resolves accelerations only to"):
        training_states(scene, copy.deepcopy(f).float(), rollouts)  # what a float32 stepper makes of this scene
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        z, _, dropped, _ = training_states(scene, f, rollouts)
    assert z.dtype == torch.float64 and z.shape == (4 + 3, 3) and dropped == {"diverged": 0, "out_of_range": 0}


def test_bench_cubature_sweep_prints_the_sizes_finished_before_ctrl_c(cli, monkeypatch) -> None:
    """Ctrl-C while the --sweep ran its second size exited 130 with no size printed; the first is now printed (text
    and JSON, ``interrupted``)."""
    from redsim.cubature import bench

    real = bench.mesh_sweep

    def mesh_sweep(cells, **kwargs):  # type: ignore[no-untyped-def]
        if 3 in cells:
            raise KeyboardInterrupt
        return real(cells, **kwargs)

    monkeypatch.setattr(bench, "mesh_sweep", mesh_sweep)
    argv = ("bench", "cubature", "--sweep", "2,3", "--elements", "4", "--timed-steps", "2", "--batches", "1")
    code, out, err = cli(*argv, "--json")
    doc = json.loads(out)
    assert code == 130 and doc["interrupted"] and [r["cells"] for r in doc["sweep"]] == [2], err
    code, out, err = cli(*argv)
    assert code == 130 and "cells    2" in out and "cells    3" not in out, err
    assert out.rstrip().endswith("interrupted: the sizes finished before it")


@pytest.mark.parametrize(
    ("where", "value", "expected"),
    [
        ("element_count", 18.7, r"element_count must be an integer >= 0, got 18.7"),  # read as 18 before
        ("element_count", "18", r"element_count must be an integer >= 0, got '18'"),  # read as 18 before
        ("weights", True, r"weights must be numbers, got True at position 0"),  # read as 1.0 before
        ("weights", [0.5], r"weights must be numbers, got \[0.5\] at position 0"),
        ("summary", [1], r"corrupt cubature file \(summary must be a JSON object, got list\)"),
        ("held_out_force_error", "2%", r"summary held_out_force_error must be a number >= 0, got '2%'"),
    ],
)
def test_a_cubature_file_with_mistyped_counts_weights_or_summary_is_refused(tmp_path, where, value, expected) -> None:
    """A hand-edited element_count of 18.7 or "18", or a weight true, loaded (int() and torch.tensor read them as 18
    and 1.0); a summary that is not an object, or an error given as text, loaded, and `redsim bench cubature` failed
    on it after its whole bench (AttributeError, ValueError) instead of refusing the file first."""
    scene, f = _toy_cloth_map()
    path = build_cubature(scene, f, CubatureConfig(elements=4, **QUICK)).save(tmp_path / "cloth")
    doc = json.loads(path.read_text())
    rule = next(r for r in doc["rules"] if r["name"] == "membrane")
    if where == "element_count":
        rule[where] = value
    elif where == "weights":
        rule[where][0] = value
    elif where == "summary":
        doc[where] = value
    else:
        doc["summary"][where] = value
    path.write_text(json.dumps(doc))
    with pytest.raises(CheckpointError, match=rf"cloth.cubature.json: .*{expected}"):
        load_cubature(tmp_path / "cloth", scene, f)


@pytest.fixture(scope="module")
def conditional_bar():
    return _shipped("conditional_bar")


def test_error_falls_as_elements_are_added_on_a_shipped_map(conditional_bar) -> None:
    """The shipped conditional bar map (a fitted map, not a random one): each greedy round's training error is at most
    the round's before (NNLS over a superset of the kept elements), and the held-out error falls with it."""
    scene, f = conditional_bar
    cub = build_cubature(scene, f, CubatureConfig(elements=40, samples=32, episodes=0))
    rules = [r for r in cub.rules if r.mode == "cubature"]
    assert {r.name for r in rules} == {"elastic", "pin"}
    for rule in rules:
        kept = [h[0] for h in rule.history]
        train = [h[1] for h in rule.history]
        held = [h[2] for h in rule.history]
        assert kept == sorted(kept) and 30 <= kept[-1] <= 40, rule.history
        assert all(b <= a * (1 + 1e-9) for a, b in itertools.pairwise(train)), rule.history
        assert train[-1] < 0.1 * train[0] and held[-1] < 0.25 * held[0], rule.history


def test_held_out_states_choose_no_element_and_no_weight(conditional_bar, monkeypatch) -> None:
    """The held-out states (sampled ones and whole rollouts) enter the reported errors only: made nonsense, they change
    those errors and leave every kept element and weight as it was."""
    from redsim.cubature import fit

    scene, f = conditional_bar
    config = CubatureConfig(elements=12, samples=48, episodes=2, steps=4)
    _, _, _, episode = fit.training_states(scene, f, config)
    test, _ = fit.split_states(episode, config)
    assert int((episode[test] >= 0).sum()) == 4  # one rollout of two, whole, among them
    real = fit.element_columns

    def scrambled(scene, output, effect, z, cond, *args, **kwargs):  # type: ignore[no-untyped-def]
        forces, energies = real(scene, output, effect, z, cond, *args, **kwargs)
        if z.shape[0] == episode.numel():  # the training and held-out states (not z = 0)
            g = torch.Generator().manual_seed(0)
            forces[test] = 1e3 * torch.randn(forces[test].shape, generator=g, dtype=forces.dtype)
            energies[test] = 1e3 * torch.randn(energies[test].shape, generator=g, dtype=energies.dtype)
        return forces, energies

    before = build_cubature(scene, f, config)
    monkeypatch.setattr(fit, "element_columns", scrambled)
    after = build_cubature(scene, f, config)
    for a, b in zip(before.rules, after.rules, strict=True):
        assert a.indices.tolist() == b.indices.tolist() and torch.equal(a.weights, b.weights)
        assert [h[:2] for h in a.history] == [h[:2] for h in b.history]
    assert before.summary["train_error"] == after.summary["train_error"]
    assert after.summary["held_out_force_error"] != before.summary["held_out_force_error"]
    assert [r.held_out_error for r in after.rules if r.mode == "cubature"] != [
        r.held_out_error for r in before.rules if r.mode == "cubature"
    ]


def test_a_state_with_a_million_times_the_forces_weighs_as_much_as_before(conditional_bar, monkeypatch) -> None:
    """Each state's rows (every effect's forces and energy) are divided by that state's own scale, so a state whose
    forces and energy are all 1e6 times larger does not drown the others: the same elements, weights and errors."""
    from redsim.cubature import fit

    scene, f = conditional_bar
    config = CubatureConfig(elements=12, samples=48, episodes=0)
    _, train = fit.split_states(torch.full((48,), -1), config)
    real = fit.element_columns

    def louder(scene, output, effect, z, cond, *args, **kwargs):  # type: ignore[no-untyped-def]
        forces, energies = real(scene, output, effect, z, cond, *args, **kwargs)
        if z.shape[0] == 48:  # the sampled states (not z = 0, the energies' reference)
            forces[train[0]] *= 1e6
            energies[train[0]] = 1e6 * (energies[train[0]] - ref[effect.name]) + ref[effect.name]
        return forces, energies

    z0 = torch.zeros(1, f.latent_dim, dtype=torch.float64)
    c0 = scene.condition_space.default.to(torch.float64)[None]
    scene64, output = scene.to(dtype=torch.float64), fit.AffineOutput(f).to(torch.float64)
    ref = {e.name: real(scene64, output, e, z0, c0)[1][0] for e in scene64.effects if not e.uses_loads}
    before = build_cubature(scene, f, config)
    monkeypatch.setattr(fit, "element_columns", louder)
    after = build_cubature(scene, f, config)
    for a, b in zip(before.rules, after.rules, strict=True):
        assert a.indices.tolist() == b.indices.tolist()
        torch.testing.assert_close(a.weights, b.weights, rtol=1e-6, atol=0.0)
    assert after.summary["train_error"] == pytest.approx(before.summary["train_error"], rel=1e-6)


def test_the_reported_force_error_is_that_of_the_held_out_states_scaled_per_state(conditional_bar) -> None:
    """``held_out_force_error``, recomputed from the two latent energies' gradients in z on the held-out states: each
    state's residual and reduced force over that state's scale sqrt(|J^T grad E|^2 + (E - E(z=0))^2) of the total
    energy (docs/cubature.md, "How a cubature weighs its states and reports its error"), so a large-force state does
    not drown the others; unscaled the same residuals read otherwise."""
    from redsim.cubature import fit
    from redsim.runtime import MapEnergy

    scene, f = conditional_bar
    config = CubatureConfig(elements=20, samples=32, episodes=2, steps=6)
    cub = build_cubature(scene, f, config)
    z, cond, _, episode = fit.training_states(scene, f, config)
    test, _ = fit.split_states(episode, config)
    forces = []
    for energy in (CubatureEnergy(scene, f, cub, dtype=torch.float64), MapEnergy(scene, f, dtype=torch.float64)):
        zs = z[test].clone().requires_grad_(True)
        value = energy.energy(zs, cond[test])[0]
        forces.append(torch.autograd.grad(value.sum(), zs)[0])
        if isinstance(energy, MapEnergy):
            z0 = torch.zeros(1, z.shape[1], dtype=torch.float64)
            e0 = energy.energy(z0, scene.condition_space.default.to(torch.float64)[None])[0]
            scale = torch.sqrt(forces[-1].square().sum(-1) + (value.detach() - e0).square())
    approx, exact = forces
    scaled = ((approx - exact) / scale[:, None]).norm() / (exact / scale[:, None]).norm()
    assert float(scaled) == pytest.approx(cub.summary["held_out_force_error"], rel=1e-9)
    unscaled = float((approx - exact).norm() / exact.norm())
    assert abs(unscaled - float(scaled)) > 0.1 * float(scaled)  # the scale matters on this map
    assert unscaled == pytest.approx(cub.summary["held_out_plain_force_error"], rel=1e-9)  # recorded beside it
    per_state = ((approx - exact).norm(dim=-1) / exact.norm(dim=-1)).sort().values
    assert cub.summary["held_out_median_state_force_error"] == pytest.approx(float(per_state.quantile(0.5)), rel=1e-9)
    # the bench's recomputation, from the recorded config alone, finds the same states and the same errors
    again = held_out_errors(scene, f, cub)
    assert again["states"] == test.numel()
    for key in (
        "force_error",
        "plain_force_error",
        "median_state_force_error",
        "p90_state_force_error",
        "energy_error",
    ):
        assert again[key] == pytest.approx(cub.summary[f"held_out_{key}"], rel=1e-9), key


def test_the_plain_force_error_and_the_others_by_hand() -> None:
    """:func:`redsim.cubature.fit.error_measures` on two states worked by hand. State 1: F = (3, 4), residual
    (0.3, 0.4), E - E(0) = 12 (scale 13), its energy off by 1.2; state 2: F = (0, 3), residual (0, 1.5), E - E(0) = 4
    (scale 5), off by -0.4. Plain: sqrt((0.25 + 2.25) / (25 + 9)); per state 0.1 and 0.5; energy
    sqrt((1.44 + 0.16) / (144 + 16)) = 0.1; the fit's own, each state over its scale:
    sqrt((0.25/169 + 2.25/25) / (25/169 + 9/25))."""
    from redsim.cubature.fit import error_measures

    force = torch.tensor([[3.0, 4.0], [0.0, 3.0]], dtype=torch.float64)
    residual = torch.tensor([[0.3, 0.4], [0.0, 1.5]], dtype=torch.float64)
    energy = torch.tensor([12.0, 4.0], dtype=torch.float64)
    measures = error_measures(residual, force, torch.tensor([1.2, -0.4], dtype=torch.float64), energy)
    assert measures["plain_force_error"] == pytest.approx(math.sqrt(2.5 / 34), rel=1e-12)
    assert measures["median_state_force_error"] == pytest.approx(0.3, rel=1e-12)  # halfway between 0.1 and 0.5
    assert measures["p90_state_force_error"] == pytest.approx(0.1 + 0.9 * 0.4, rel=1e-12)
    assert measures["energy_error"] == pytest.approx(0.1, rel=1e-12)
    by_hand = math.sqrt((0.25 / 169 + 2.25 / 25) / (25 / 169 + 9 / 25))
    assert measures["force_error"] == pytest.approx(by_hand, rel=1e-12)
    assert by_hand > 1.5 * measures["plain_force_error"]  # the scale reweighs: the two differ
    given = error_measures(residual, force, torch.zeros(2, dtype=torch.float64), energy, torch.ones(2))
    assert given["force_error"] == pytest.approx(measures["plain_force_error"], rel=1e-12)  # a scale of 1: plain
    with pytest.raises(ValueError, match=r"force residual and force must be \[S, d\] alike, got \[2, 2\] and \[2\]"):
        error_measures(residual, force[:, 0], energy, energy)
    with pytest.raises(ValueError, match=r"energy residual and energy must be \[S\] \(S = 2\), got \[3\]"):
        error_measures(residual, force, torch.zeros(3), energy)


@pytest.mark.parametrize("name", ["mini_chain", "conditional_bar"])
def test_the_cubature_energy_is_the_weighted_sum_of_its_kept_elements(name: str) -> None:
    """E_cub(z) - E_cub(0) and its gradient in z (float64) against the scene's own per-element energies of f(z), kept
    elements times their weights, whole effects' and linear effects' energies in full, and against central finite
    differences of E_cub."""
    from redsim.cubature.output import AffineOutput

    scene, f = _shipped(name)
    config = CubatureConfig(elements=8, samples=32, episodes=0, subsample=("contact",) if name == "mini_chain" else ())
    cub = build_cubature(scene, f, config)
    assert "cubature" in {r.mode for r in cub.rules} and "linear" in {r.mode for r in cub.rules}
    energy = CubatureEnergy(scene, f, cub, dtype=torch.float64)
    scene64, output = scene.to(dtype=torch.float64), AffineOutput(f).to(torch.float64)
    rules = {r.name: r for r in cub.rules}
    space = scene.condition_space
    cond = None if space is None else space.default.to(torch.float64).expand(5, -1)

    def weighted(z: torch.Tensor) -> torch.Tensor:
        c = None if cond is None else cond[: z.shape[0]]
        x = scene64.full_positions(output(z, c))
        total = torch.zeros(z.shape[0], dtype=torch.float64)
        for effect in scene64.effects:
            rule = rules.get(effect.name)
            if rule is not None and rule.mode == "cubature":
                total = total + effect.element_energies(x, c)[:, rule.indices] @ rule.weights
            elif rule is not None:
                total = total + effect.energy(x, c)
        return total

    z = torch.randn(5, f.latent_dim, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    z0 = torch.zeros(1, f.latent_dim, dtype=torch.float64)
    values, grads = [], []
    for fn in (lambda u: energy.energy(u, None if cond is None else cond[: u.shape[0]])[0], weighted):
        zs = z.clone().requires_grad_(True)
        value = fn(zs)
        grads.append(torch.autograd.grad(value.sum(), zs)[0])
        values.append(value.detach() - fn(z0).detach())
    torch.testing.assert_close(values[0], values[1], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-10, atol=1e-12)
    h = 1e-5
    with torch.no_grad():
        steps = h * torch.eye(f.latent_dim, dtype=torch.float64)
        c = None if cond is None else cond[:5]
        fd = torch.stack([(energy.energy(z + s, c)[0] - energy.energy(z - s, c)[0]) / (2 * h) for s in steps], -1)
    torch.testing.assert_close(fd, grads[0], rtol=1e-6, atol=1e-6 * float(grads[0].abs().max()))


@pytest.mark.parametrize("stage", ["training_states", "element_columns", "greedy_nnls"])
def test_an_interrupted_cli_ends_on_its_rerun_command_not_on_a_bar(cli, tmp_path, monkeypatch, stage: str) -> None:
    """Ctrl-C during the rollouts or the per-element forces left their progress bar open: it was closed (and drew its
    line) after `redsim cubature` had said "interrupted ... rerun: ...", so the terminal's last line was a stale bar."""
    import shutil

    from redsim.cubature import fit

    for suffix in (".pt", ".json"):
        shutil.copy(pretrained.path("conditional_bar").with_suffix(suffix), tmp_path / f"m{suffix}")
    real = getattr(fit, stage)
    calls = []

    def interrupted(*args, **kwargs):  # type: ignore[no-untyped-def]
        if stage == "training_states":  # in the rollouts, after their first step
            tick = kwargs["progress"]
            kwargs["progress"] = lambda: (tick(), _raise(KeyboardInterrupt))
            return real(*args, **kwargs)
        if stage == "element_columns" and kwargs.get("progress") is not None:
            calls.append(kwargs["progress"](1))
            if len(calls) == 2:  # in the second effect's states
                raise KeyboardInterrupt
        if stage == "greedy_nnls":
            kwargs["progress"](1, 0.5)
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(fit, stage, interrupted)
    argv = ("cubature", str(tmp_path / "m.pt"), "--elements", "4", "--samples", "16", "--episodes", "1")
    code, out, err = cli(*argv, "--rollout-steps", "2")
    last = err.rstrip("\n").replace("\r", "\n").split("\n")[-1]
    assert code == 130 and not out and last.startswith("redsim: warning: interrupted before"), err
    assert last.endswith("rerun: redsim cubature " + " ".join(argv[1:]) + " --rollout-steps 2"), err


def _raise(error: type[BaseException]) -> None:
    raise error
